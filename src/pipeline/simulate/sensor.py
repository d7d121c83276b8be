"""Photons to DN for one lens region of the raw mosaic.

DN = bias + offset FPN (ADU) + K * offset FPN (e-) + frame offset
     + response(K * (Poisson(photo-electrons + dark electrons)))
     + K * read noise (e-) * N(0, 1),

with the electrons clipped at the full well when the sensor has one,
rounded and clipped to the 14-bit range, with K = conversion gain at ISO 100
times ISO/100 times the effects' gain factor (Larouche et al. 2024, Eq. 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.effects.base import Effect
from pipeline.simulate.camera import SensorParams


@dataclass
class StaticPattern:
    """Per-pixel offsets that do not change between frames (one lens)."""

    offset_fpn_dn: np.ndarray   # ADU
    offset_fpn_e: np.ndarray    # electrons


def draw_static_pattern(rng: np.random.Generator, shape, sensor: SensorParams) -> StaticPattern:
    """Draw the per-pixel offsets of one lens that do not change between frames.

    Parameters
    ----------
    rng : numpy.random.Generator
        The camera's static generator.
    shape : tuple of (int, int)
        (rows, columns) of the lens region, raw pixels.
    sensor : SensorParams
        The sensor: standard deviations of the offset fixed-pattern noise in ADU (``offset_fpn_dn``) and in
        electrons (``offset_fpn_e``).

    Returns
    -------
    StaticPattern
        Zero-mean normal offsets per pixel (float32): ``offset_fpn_dn`` in DN, ``offset_fpn_e`` in electrons.
    """
    return StaticPattern(
        offset_fpn_dn=(sensor.offset_fpn_dn * rng.standard_normal(shape)).astype(np.float32),
        offset_fpn_e=(sensor.offset_fpn_e * rng.standard_normal(shape)).astype(np.float32),
    )


def true_exposure_and_gain(effects, exposure_s: float, iso: float) -> tuple[float, float]:
    """The time the shutter is really open and the factor on the nominal gain at ``iso``.

    The shutter offset and the per-ISO gain factor, as the camera with ``effects`` records a frame.

    Parameters
    ----------
    effects : iterable of Effect
        The true effects switched on.
    exposure_s : float
        The nominal exposure time, s.
    iso : float
        The ISO setting.

    Returns
    -------
    exposure_s : float
        The time the shutter is open, s.
    gain_factor : float
        The factor on the nominal conversion gain, dimensionless.
    """
    t_true, gain_factor = exposure_s, 1.0
    for effect in effects:
        t_true = effect.true_exposure_s(t_true)
        gain_factor *= effect.gain_factor(iso)
    return t_true, gain_factor


def expose(rng: np.random.Generator, *, lens: str, photo_rate_e_per_s, exposure_s: float,
           iso: float, sensor: SensorParams, pattern: StaticPattern, effects: list[Effect],
           frame_offset_dn: float, shape, temperature_c: float | None = None) -> np.ndarray:
    """One exposure of one lens: uint16 raw mosaic of ``shape``.

    The light reaches the sensor only while the shutter is open (the true exposure of
    :func:`true_exposure_and_gain`); dark current accumulates over the nominal integration.

    Parameters
    ----------
    rng : numpy.random.Generator
        The frame's generator (shot and read noise).
    lens : str
        The lens (the effects' per-lens maps).
    photo_rate_e_per_s : numpy.ndarray or float
        The photo-electron rate per raw pixel, e- s-1 (an array of ``shape``, or 0).
    exposure_s : float
        The nominal exposure time, s.
    iso : float
        The ISO setting (the conversion gain is K at ISO 100 times ISO / 100).
    sensor : SensorParams
        The sensor: bias, read noise, full well, ADC range, conversion gain.
    pattern : StaticPattern
        The lens's fixed offsets (:func:`draw_static_pattern`).
    effects : list of Effect
        The true effects switched on (shutter offset, gain factors, dark current, nonlinearity, bias drift, ...).
    frame_offset_dn : float
        The black-level shift of the whole frame (bias drift), DN, drawn once per frame by the caller so that
        both lenses share it.
    shape : tuple of (int, int)
        (rows, columns) of the lens region, raw pixels.
    temperature_c : float, optional
        The sensor's temperature, deg C, for the temperature-dependent effects; default None.

    Returns
    -------
    numpy.ndarray
        uint16, shape ``shape``: the raw values, DN, rounded and clipped to [0, ``adc_max_dn``].
    """
    t_true, gain_factor = true_exposure_and_gain(effects, exposure_s, iso)
    dark_rate = 0.0
    dark_factor = 1.0
    for effect in effects:
        dark_rate = dark_rate + effect.dark_rate_e_per_s(lens, shape)
        dark_factor *= effect.dark_rate_factor(temperature_c)
        frame_offset_dn += effect.bias_offset_dn(temperature_c)
    dark_rate = dark_rate * dark_factor
    k = sensor.conversion_gain(iso) * gain_factor
    # Light reaches the sensor only while the shutter is open (t_true); dark
    # current accumulates over the nominal integration.
    mean_e = np.asarray(photo_rate_e_per_s, dtype=np.float64) * t_true + np.asarray(dark_rate) * exposure_s
    if mean_e.ndim == 0 and mean_e == 0.0:
        # an unlit lens without dark current: Poisson(0) is 0 and numpy draws nothing from the stream for it,
        # so the zeros are the same frame and the same generator state as rng.poisson would leave
        electrons = np.zeros(shape)
    else:
        electrons = rng.poisson(np.broadcast_to(mean_e, shape)).astype(np.float64)
    if sensor.full_well_e is not None:
        electrons = np.minimum(electrons, sensor.full_well_e)
    signal_dn = k * electrons
    full_scale = sensor.adc_max_dn - sensor.bias_dn
    for effect in effects:
        signal_dn = effect.response_dn(signal_dn, full_scale)
    dn = (sensor.bias_dn + frame_offset_dn + pattern.offset_fpn_dn + k * pattern.offset_fpn_e
          + signal_dn + k * sensor.read_noise_e * rng.standard_normal(shape))
    return np.clip(np.rint(dn), 0, sensor.adc_max_dn).astype(np.uint16)

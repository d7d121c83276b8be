"""Absolute-radiance experiment (Larouche et al. 2024, Sections 2.6 and 3.5; Fig. 1c, Table 1).

Per lens: the 1-inch port of the integrating sphere (2796 K QTH lamp) on the
optical axis, filling the central field; 10 signal frames then 5 dark frames
at ISO 100 and 0.1 s (Table 1).

Sidecars written as a lab would:

* ``source_spectrum.csv``: the port's relative spectrum from a fibre
  spectrometer, 380-780 nm in 1 nm steps, arbitrary units, with noise;
  ``radiance_std`` is the standard uncertainty of each value.
* ``source_reference.csv``: the C-OPS reading at 589 nm, 6.8e-4
  W sr-1 m-2 nm-1 with its stated relative uncertainty, the "conservative
  2.5 %" of Section 3.5.

The lab's systematic errors (:mod:`pipeline.simulate.lab_errors`, drawn per
dataset when the simulation asks for them, zero otherwise): the spectrometer's
calibrated spectrum carries the calibration lamp's error (a scale part and a
colour-temperature shape, 9.1 % at 400 nm to 6.9 % at 800 nm in all), and the
C-OPS reading its scale error (2.5 %). The truth gives, besides the camera's
R^-1, ``inverse_responsivity_lab``: what an exact analysis of these sidecars
(noise-free spectrum, true response) gives, R^-1 (1 + r)
<1 + e>_LS / (1 + e(589 nm)), with <.>_LS the band average weighted by
source radiance times response.

The camera sees, in band b, the effective band radiance of the TRUE source
spectrum through the TRUE spectral response on a 0.1 nm grid (Eq. 3), so a
pipeline that uses its measured 10 nm response carries that approximation.
Each lens sees the source through its own true response. Truth: R^-1 = 1 / responsivity
per band (W sr-1 m-2 nm-1 per DN/s at ISO 100, the camera's, the same for both lenses) and,
per lens (``lenses``), the effective band radiances and what the lab's errors make of R^-1.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from pipeline.io.bands import BANDS
from pipeline.radiometry.source import (QTH_TEMPERATURE_K, REFERENCE_RADIANCE_W_SR_M2_NM, REFERENCE_WAVELENGTH_NM,
                                        planck_radiance)
from pipeline.radiometry.spectral import effective_band_radiance
from pipeline.simulate.lab_errors import REFERENCE_RELATIVE_SIGMA, lamp_factor
from pipeline.simulate.plan import ExperimentPlan, FrameSpec, SimContext, planner
from pipeline.simulate.spectral import camera_response, default_spectral_response

SIGNAL_FRAMES = 10
DARK_FRAMES = 5
ISO = 100.0
EXPOSURE_S = 0.1
#: half-angle of the field filled by the sphere port (deg)
PORT_HALF_ANGLE_DEG = 20.0
#: fibre spectrometer grid (nm) and relative noise of one value
SPECTROMETER_NM = np.arange(380.0, 780.0 + 1e-9, 1.0)
SPECTROMETER_RELATIVE_NOISE = 0.003
#: arbitrary spectrometer units: counts at the reference wavelength
SPECTROMETER_COUNTS_AT_REFERENCE = 20000.0

_FINE_NM = np.arange(380.0, 720.0 + 1e-9, 0.1)


def default_source_radiance(wavelength_nm, temperature_k=QTH_TEMPERATURE_K):
    """Simulator's calibration-source radiance, W sr-1 m-2 nm-1.

    A Planck spectrum at ``temperature_k`` scaled to 6.8e-4 W sr-1 m-2 nm-1
    at 589 nm (exact scaling, no interpolation).  Through the close lens's
    measured spectral response its effective band radiances are about 0.75,
    0.50, 0.29 mW sr-1 m-2 nm-1 (R, G, B; the far lens's 0.77, 0.52, 0.31),
    against 0.74, 0.48, 0.26 (+- 0.08, 0.05, 0.03) in Table 1 of Larouche et
    al. (2024).
    """
    b = planck_radiance(wavelength_nm, temperature_k)
    return b * (REFERENCE_RADIANCE_W_SR_M2_NM / planck_radiance(REFERENCE_WAVELENGTH_NM, temperature_k))


def true_effective_band_radiance(response=None) -> dict[str, float]:
    """Eq. (3) with the true source and a true response on a fine grid (W sr-1 m-2 nm-1).

    Parameters
    ----------
    response : callable, optional
        Function of the wavelengths giving band -> response (default: the close lens's
        :func:`pipeline.simulate.spectral.default_spectral_response`).

    Returns
    -------
    dict
        Band -> effective band radiance of the source.
    """
    s = (response or default_spectral_response)(_FINE_NM)
    radiance = default_source_radiance(_FINE_NM)
    return {b: float(effective_band_radiance(_FINE_NM, radiance, s[b])) for b in BANDS}


def lab_factors(errors: dict, response=None) -> dict[str, float]:
    """Per band, the factor the lab's errors put on R^-1: (1 + r) <1 + e>_LS / (1 + e(589 nm)).

    Parameters
    ----------
    errors : dict
        The lab's systematic errors (:mod:`pipeline.simulate.lab_errors`).
    response : callable, optional
        Function of the wavelengths giving band -> response (default: the close lens's).

    Returns
    -------
    dict
        Band -> factor.
    """
    s = (response or default_spectral_response)(_FINE_NM)
    radiance = default_source_radiance(_FINE_NM)
    f = lamp_factor(_FINE_NM, errors)
    f_ref = float(lamp_factor(REFERENCE_WAVELENGTH_NM, errors))
    return {b: float((1.0 + errors["reference_relative_error"]) * np.trapezoid(radiance * s[b] * f, _FINE_NM)
                     / np.trapezoid(radiance * s[b], _FINE_NM) / f_ref) for b in BANDS}


#: the lens whose true response the camera's ``sphere_band_radiance`` is stated for
SPHERE_REFERENCE_LENS = "close"


def lens_band_radiance(camera, lens: str, radiance: dict) -> dict:
    """The lab sphere's band radiance as one lens sees it.

    The sphere is lit by the same 2796 K lamp as the absolute experiment's port, so its band radiance
    through each lens's true response is in the ratio of the port's: ``radiance`` (the camera's
    ``sphere_band_radiance`` or a fraction of it, stated for the close lens's response) times
    L_b(lens) / L_b(close), Eq. (3) with :func:`default_source_radiance` (the far lens's bands lie 5 nm
    longer: 3 to 6 % more). A camera with its own response (the smartphone, one lens) sees ``radiance``.

    Parameters
    ----------
    camera : object
        The simulated camera.
    lens : str
        The lens name.
    radiance : dict
        Band -> band radiance as the close lens sees it (W sr-1 m-2 nm-1).

    Returns
    -------
    dict
        Band -> band radiance through ``lens``'s response.
    """
    if getattr(camera, "spectral_response", None) is not None or lens == SPHERE_REFERENCE_LENS:
        return dict(radiance)
    ratio = _lens_ratio(lens)
    return {b: float(radiance[b] * ratio[b]) for b in BANDS}


@lru_cache(maxsize=None)
def _lens_ratio(lens: str) -> dict:
    this = true_effective_band_radiance(lambda wl: default_spectral_response(wl, lens))
    ref = true_effective_band_radiance(lambda wl: default_spectral_response(wl, SPHERE_REFERENCE_LENS))
    return {b: this[b] / ref[b] for b in BANDS}


def _port(values):
    def port(lens, geometry, band_index):
        return values[lens][band_index] * (geometry.theta_deg <= PORT_HALF_ANGLE_DEG)

    return port


@planner("absolute")
def plan_absolute(ctx: SimContext) -> ExperimentPlan:
    camera = ctx.camera
    responses = {lens: (lambda wl, lens=lens: camera_response(camera, lens, wl)) for lens in camera.lens_names}
    lbar = {lens: true_effective_band_radiance(responses[lens]) for lens in camera.lens_names}
    port = _port({lens: np.array([lbar[lens][b] for b in BANDS]) for lens in camera.lens_names})

    frames = []
    for lens in camera.lens_names:
        frames += [FrameSpec(lens, "signal", ISO, EXPOSURE_S, {}, port) for _ in range(SIGNAL_FRAMES)]
        frames += [FrameSpec(lens, "dark", ISO, EXPOSURE_S, {}) for _ in range(DARK_FRAMES)]

    wl = SPECTROMETER_NM
    true = default_source_radiance(wl)
    counts = true * (SPECTROMETER_COUNTS_AT_REFERENCE / REFERENCE_RADIANCE_W_SR_M2_NM)
    errors = ctx.lab_errors
    measured = counts * lamp_factor(wl, errors) * (1.0 + SPECTROMETER_RELATIVE_NOISE * ctx.rng.standard_normal(wl.size))
    spectrum = ["wavelength_nm,radiance,radiance_std"]
    spectrum += [f"{w:.1f},{m:.8g},{SPECTROMETER_RELATIVE_NOISE * m:.6g}" for w, m in zip(wl, measured)]
    reading = REFERENCE_RADIANCE_W_SR_M2_NM * (1.0 + errors["reference_relative_error"])
    reference = ["wavelength_nm,radiance_W_sr_m2_nm,uncertainty_rel",
                 f"{REFERENCE_WAVELENGTH_NM:.1f},{reading:.8g},{REFERENCE_RELATIVE_SIGMA:.6g}"]
    lab = {lens: lab_factors(errors, responses[lens]) for lens in camera.lens_names}

    resp = camera.radiometry.responsivity_dn_s_per_radiance
    # the inverse responsivity is the camera's, the same for both lenses; what the lab's errors make of it
    # and the port's band radiance depend on each lens's spectral response
    truth = {
        "iso": ISO, "exposure_s": EXPOSURE_S, "port_half_angle_deg": PORT_HALF_ANGLE_DEG,
        "bands": {b: {"inverse_responsivity": 1.0 / resp[b]} for b in BANDS},
        "lenses": {lens: {"bands": {b: {"inverse_responsivity_lab": lab[lens][b] / resp[b],
                                        "effective_band_radiance_W_sr_m2_nm": lbar[lens][b],
                                        "dn_per_s_iso100": resp[b] * lbar[lens][b]} for b in BANDS}}
                   for lens in camera.lens_names},
        "lab_errors": {k: v for k, v in errors.items() if k != "photodiode_coefficients"},
        "units": {"inverse_responsivity": "W sr-1 m-2 nm-1 per DN s-1 at ISO 100"},
    }
    return ExperimentPlan(frames, sidecars={"source_spectrum.csv": "\n".join(spectrum) + "\n",
                                            "source_reference.csv": "\n".join(reference) + "\n"},
                          truth=truth)

"""The measurement model: Eq. (4) inverted, one named step each (Larouche et al. 2024, Section 2.1).

Eq. (4) with Eq. (2) says what a band pixel reads for a spectral radiance L,

    y_raw = dark(ISO, t, T) + N( (t + dt) * g * f_ISO * F(x, y) * g(theta, phi) / I * R * L ),

with ``dark`` the dark model (Section 2.8), ``dt`` the shutter offset, ``g =
ISO/100`` and ``f_ISO`` the fitted per-ISO gain factor, ``N`` the
nonlinearity ``s -> s (1 - beta s / full_scale)``, ``F`` the flat field,
``g(theta, phi)`` the roll-off (Eq. 13), ``I`` the immersion factor in water
(Eq. 11) and ``R`` the responsivity (``R^-1``: Eq. 9). The chain below undoes
it one step at a time, on a whole band image at once:

    raw band DN -> subtract_dark -> add_shot_noise -> flag_hot_pixels -> flag_saturation ->
    linearise -> normalise_exposure -> correct_flat_field -> correct_rolloff ->
    correct_immersion -> to_radiance   [W sr-1 m-2 nm-1]

Each step applies only the effects of ``model.effects`` that it owns
(``dark_current`` and ``temperature`` in the dark level, ``hot_pixels``,
``nonlinearity``, ``shutter_offset`` and ``iso_gain``, ``prnu``); roll-off,
immersion and responsivity are the base model. The nonlinearity bends the
dark-corrected signal in DN (the linearity stage fits it there), so its
inverse is taken before the division by exposure and gain; that is the
exposure-and-gain step of DESIGN.md's chain written in DN.

Uncertainty goes forward with the value, to first order, in two parts kept as
named variances (in the units of the current value):

* random, different from pixel to pixel (and, but for the fixed patterns,
  frame to frame): ``shot`` (signal electrons, from the photon-transfer
  conversion gain), ``read`` (the dark stage's temporal noise at that ISO),
  ``dark`` (dark-current electrons and the pixel-to-pixel offset pattern that
  the mean dark level leaves), ``prnu`` (sensitivity of pixels the flat field
  does not cover);
* systematic, common to every pixel of a band (calibration terms): the dark
  model's parameters, shutter offset, ISO gain factor, nonlinearity, roll-off
  (from its covariance, a function of theta), immersion factor and the R^-1
  budget. Terms of different names are taken as independent.

Every step is a pure function of a :class:`Measured` value and a small
parameter object, so each is tested on hand values without files.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from pipeline.errors import ImpossibleResult
from pipeline.radiometry.dark import dark_model_level_dn, temperature_model_shift_dn
from pipeline.radiometry.exposure import gain_from_iso
from pipeline.radiometry.rolloff import rolloff_on_image

__all__ = [
    "FLAG_SATURATED", "FLAG_HOT", "FLAG_OUTSIDE_IMAGE_CIRCLE", "FLAG_BEYOND_CALIBRATED_ANGLE", "FLAG_MEANINGS",
    "Measured", "FrameSettings", "DarkModel", "ResponseModel", "BandCalibration",
    "from_raw", "subtract_dark", "add_shot_noise", "flag_hot_pixels", "flag_saturation", "linearise", "normalise_exposure",
    "correct_flat_field", "correct_rolloff", "correct_immersion", "to_radiance", "measure_band",
    "check_inverse_responsivity",
]

#: quality flag bits of a pixel's radiance
FLAG_SATURATED = 1                  # a CFA site at the white level, or the signal above the saturation level
FLAG_HOT = 2                        # hot pixel of the dark stage's mask
FLAG_OUTSIDE_IMAGE_CIRCLE = 4       # no viewing direction: radiance NaN
FLAG_BEYOND_CALIBRATED_ANGLE = 8    # field angle beyond the largest angle the roll-off was measured at
FLAG_MEANINGS = {"saturated": FLAG_SATURATED, "hot_pixel": FLAG_HOT,
                 "outside_image_circle": FLAG_OUTSIDE_IMAGE_CIRCLE,
                 "beyond_calibrated_field_angle": FLAG_BEYOND_CALIBRATED_ANGLE}


@dataclass(frozen=True)
class Measured:
    """A band image on its way through the chain: value, named variances, quality flags.

    ``random_var`` and ``systematic_var`` map a term name to its variance in
    the units of ``value`` (arrays broadcastable to it).
    """

    value: np.ndarray
    units: str
    random_var: dict[str, np.ndarray] = field(default_factory=dict)
    systematic_var: dict[str, np.ndarray] = field(default_factory=dict)
    flags: np.ndarray | None = None

    @cached_property
    def random_sigma(self) -> np.ndarray:
        """sqrt of the sum of the random variances (computed once per value)."""
        return _root_sum(self.random_var.values(), self.value)

    @cached_property
    def systematic_sigma(self) -> np.ndarray:
        """sqrt of the sum of the systematic variances (computed once per value)."""
        return _root_sum(self.systematic_var.values(), self.value)

    def scaled(self, factor, units: str, **extra_systematic) -> "Measured":
        """value * factor, every variance times factor^2, plus new systematic terms (already in the new units)."""
        f2 = np.square(factor)
        sys_var = {k: v * f2 for k, v in self.systematic_var.items()}
        sys_var.update(extra_systematic)
        return dataclasses.replace(self, value=self.value * factor, units=units,
                                   random_var={k: v * f2 for k, v in self.random_var.items()},
                                   systematic_var=sys_var)

    def flagged(self, where, bit: int) -> "Measured":
        flags = np.zeros(np.shape(self.value), np.uint8) if self.flags is None else self.flags.copy()
        flags[np.broadcast_to(np.asarray(where, bool), flags.shape)] |= np.uint8(bit)
        return dataclasses.replace(self, flags=flags)


def _root_sum(variances, like) -> np.ndarray:
    """sqrt of the sum of variances (arrays broadcastable to ``like``), accumulated in one array."""
    variances = list(variances)
    # the dtype the sum would have had (float64 terms promote a float32 value), at least float32
    total = np.zeros(np.shape(like), dtype=np.result_type(np.float32, like, *(np.asarray(v).dtype for v in variances)))
    for v in variances:
        total += v
    return np.sqrt(total, out=total)


@dataclass(frozen=True)
class FrameSettings:
    """The exposure parameters of one frame, from its tags (and a logged temperature)."""

    exposure_s: float
    iso: float
    temperature_c: float | None = None


@dataclass(frozen=True)
class DarkModel:
    """The dark stage's model of one band (Section 2.8): level = b0 + b1 (g - 1) + D g t [+ temperature].

    ``read_noise_dn``: temporal noise of one raw site at the frame's ISO;
    ``offset_pattern_dn``: spatial spread of the pixel offsets about the mean
    level (the fixed pattern the dark model does not remove);
    ``sites_per_pixel``: raw sites averaged in a band pixel (2 for G).
    """

    bias_dn: float
    read_noise_dn: float
    bias_dn_sigma: float = 0.0
    bias_per_gain_dn: float = 0.0
    bias_per_gain_dn_sigma: float = 0.0
    dark_current_dn_per_s: float = 0.0
    dark_current_dn_per_s_sigma: float = 0.0
    temperature_bias_dn_per_c: float = 0.0
    temperature_dark_dn_per_s_per_c: float = 0.0
    temperature_reference_c: float = float("nan")
    offset_pattern_dn: float = 0.0
    sites_per_pixel: int = 1


@dataclass(frozen=True)
class ResponseModel:
    """What the linearity stage fitted for one band (Section 2.2), at the frame's ISO.

    ``conversion_gain_dn_per_e``: photon-transfer gain at ISO 100 (DN per
    electron); ``iso_gain_factor``: true gain over ISO/100 at this ISO (1 at
    ISO 100); ``nonlinearity_beta`` and ``full_scale_dn`` of
    ``s (1 - beta s / full_scale)``; ``saturation_dn`` the saturation level
    above dark (NaN when not reached).
    """

    conversion_gain_dn_per_e: float
    shutter_offset_s: float = 0.0
    shutter_offset_s_sigma: float = 0.0
    iso_gain_factor: float = 1.0
    iso_gain_factor_sigma: float = 0.0
    nonlinearity_beta: float = 0.0
    nonlinearity_beta_sigma: float = 0.0
    full_scale_dn: float = float("nan")
    saturation_dn: float = float("nan")


@dataclass(frozen=True)
class BandCalibration:
    """The calibration terms of one band, lens and medium: roll-off, immersion, R^-1.

    ``rolloff_coefficients`` (a0, a2, a4, a6, a8) for theta in degrees with
    ``rolloff_covariance``; ``calibrated_field_angle_deg`` the largest angle
    the roll-off was measured at; ``immersion_factor`` 1 in air;
    ``inverse_responsivity`` in W sr-1 m-2 nm-1 per DN s-1 (ISO 100); the
    ``rolloff_azimuth_*`` terms the azimuthal part of the roll-off (``rolloff_azimuth``).
    """

    rolloff_coefficients: np.ndarray
    inverse_responsivity: float
    inverse_responsivity_relative_sigma: float = 0.0
    rolloff_covariance: np.ndarray | None = None
    calibrated_field_angle_deg: float = float("inf")
    immersion_factor: float = 1.0
    immersion_factor_sigma: float = 0.0
    #: ``rolloff_azimuth``: g(theta, phi) = g(theta) (1 + A (theta / theta_ref) cos(phi - phi0)), the
    #: roll-off stage's odd term (its polynomial is the even part, fitted with that term removed)
    rolloff_azimuth_amplitude: float = 0.0
    rolloff_azimuth_amplitude_sigma: float = 0.0
    rolloff_azimuth_phi0_deg: float = 0.0
    rolloff_azimuth_phi0_deg_sigma: float = 0.0
    rolloff_azimuth_theta_ref_deg: float = 90.0


# --------------------------------------------------------------------------- the steps
def from_raw(image_dn, saturated=None) -> Measured:
    """A raw band image (DN) entering the chain; ``saturated`` marks band pixels with a site at the white level."""
    m = Measured(value=np.asarray(image_dn, dtype=float), units="DN")
    return m.flagged(np.zeros(m.value.shape, bool) if saturated is None else saturated, FLAG_SATURATED)


def subtract_dark(m: Measured, dark: DarkModel, frame: FrameSettings, effects) -> Measured:
    """Raw DN -> DN above the dark level of the dark model at the frame's ISO, exposure and temperature.

    Adds the random variances of the raw reading (per band pixel: read noise
    and, with the dark current, its electrons; the offset pattern) and the
    dark model's parameter uncertainty as the systematic ``dark_model`` term.
    The signal's shot noise needs the signal, so the next step adds it
    (:func:`add_shot_noise`).
    """
    gain = gain_from_iso(frame.iso)
    current = dark.dark_current_dn_per_s if "dark_current" in effects else 0.0
    level = dark_model_level_dn(dark.bias_dn, dark.bias_per_gain_dn, current, gain, frame.exposure_s)
    if "temperature" in effects and frame.temperature_c is not None and np.isfinite(frame.temperature_c) \
            and np.isfinite(dark.temperature_reference_c):
        level += temperature_model_shift_dn(dark.temperature_bias_dn_per_c, dark.temperature_dark_dn_per_s_per_c,
                                            dark.temperature_reference_c, gain, frame.exposure_s, frame.temperature_c)
    sites = dark.sites_per_pixel
    # the same for every pixel: 0-d arrays (broadcast), maps only once a per-pixel factor scales them
    rand = dict(m.random_var)
    rand["read"] = np.asarray(dark.read_noise_dn**2 / sites, dtype=float)
    rand["dark"] = np.asarray(dark.offset_pattern_dn**2, dtype=float)
    sys_var = dict(m.systematic_var)
    sys_var["dark_model"] = np.asarray(dark.bias_dn_sigma**2 + ((gain - 1.0) * dark.bias_per_gain_dn_sigma) ** 2
                                       + ((gain * frame.exposure_s * dark.dark_current_dn_per_s_sigma) ** 2
                                          if "dark_current" in effects else 0.0), dtype=float)
    return dataclasses.replace(m, value=m.value - level, random_var=rand, systematic_var=sys_var)


def add_shot_noise(m: Measured, dark: DarkModel, response: ResponseModel, frame: FrameSettings, effects) -> Measured:
    """Poisson noise of the electrons of a dark-corrected signal (DN): K_ISO * s per site, over the sites.

    K_ISO = K_100 * ISO/100 * f_ISO (photon-transfer gain, Janesick 2007);
    the dark current's electrons join the ``dark`` term.
    """
    k_iso = response.conversion_gain_dn_per_e * gain_from_iso(frame.iso) * (
        response.iso_gain_factor if "iso_gain" in effects else 1.0)
    sites = dark.sites_per_pixel
    rand = dict(m.random_var)
    rand["shot"] = k_iso * np.clip(m.value, 0.0, None) / sites
    if "dark_current" in effects:
        dark_dn = dark.dark_current_dn_per_s * gain_from_iso(frame.iso) * frame.exposure_s
        rand["dark"] = rand.get("dark", 0.0) + k_iso * max(dark_dn, 0.0) / sites
    return dataclasses.replace(m, random_var=rand)


def flag_hot_pixels(m: Measured, hot_mask, effects) -> Measured:
    """Flag the dark stage's hot pixels (``hot_pixels`` effect); their values are kept, flagged."""
    if "hot_pixels" not in effects or hot_mask is None:
        return m
    return m.flagged(np.asarray(hot_mask) > 0, FLAG_HOT)


def flag_saturation(m: Measured, response: ResponseModel) -> Measured:
    """Flag dark-corrected signals at or above the saturation level found by the linearity stage."""
    if not np.isfinite(response.saturation_dn):
        return m
    return m.flagged(m.value >= response.saturation_dn, FLAG_SATURATED)


def linearise(m: Measured, response: ResponseModel, effects) -> Measured:
    """Inverse of the nonlinearity m = s (1 - beta s / F) (``nonlinearity`` effect), in DN above dark.

    s = 2 m / (1 + sqrt(1 - 4 beta m / F)); ds/dm = 1 / sqrt(1 - 4 beta m / F).
    A reading beyond the curve's top (4 beta m > F) has no inverse: NaN, flagged saturated.
    """
    beta, full = response.nonlinearity_beta, response.full_scale_dn
    if "nonlinearity" not in effects or beta == 0.0:
        return m
    if not np.isfinite(full) or full <= 0:
        raise ImpossibleResult(None, f"nonlinearity full scale {full} DN is not positive: rerun the linearity stage")
    disc = 1.0 - 4.0 * beta * m.value / full
    beyond = disc <= 0
    root = np.sqrt(np.where(beyond, np.nan, disc))
    s = 2.0 * m.value / (1.0 + root)
    slope = 1.0 / root
    out = m.scaled(slope, m.units)
    if "shot" in m.random_var:
        # the electrons' Poisson noise is k s in the linear signal s (the sensor bends the noisy signal):
        # the shot term k m of the bent reading m becomes k s, not k m slope^2
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(m.value > 0, s / np.where(m.value > 0, m.value, 1.0), 1.0)
        out = dataclasses.replace(out, random_var={**out.random_var, "shot": m.random_var["shot"] * ratio})
    ds_dbeta = s**2 / full / root
    sys_var = dict(out.systematic_var)
    sys_var["nonlinearity"] = (ds_dbeta * response.nonlinearity_beta_sigma) ** 2
    out = dataclasses.replace(out, value=s, systematic_var=sys_var)
    return out.flagged(beyond, FLAG_SATURATED)


def normalise_exposure(m: Measured, response: ResponseModel, frame: FrameSettings, effects) -> Measured:
    """Eq. (2) with the true exposure and gain: DN -> DN s-1 at ISO 100.

    y = s / ((t + dt) * ISO/100 * f_ISO), with the shutter offset dt
    (``shutter_offset``) and the per-ISO gain factor f_ISO (``iso_gain``).
    """
    offset = response.shutter_offset_s if "shutter_offset" in effects else 0.0
    factor = response.iso_gain_factor if "iso_gain" in effects else 1.0
    exposure = frame.exposure_s + offset
    if exposure <= 0:
        raise ImpossibleResult(None, f"true exposure {exposure:g} s (nominal {frame.exposure_s:g} s + shutter offset "
                                     f"{offset:g} s) is not positive")
    out = m.scaled(1.0 / (exposure * gain_from_iso(frame.iso) * factor), "DN s-1")
    extra = {}
    if "shutter_offset" in effects:
        extra["shutter_offset"] = (out.value / exposure * response.shutter_offset_s_sigma) ** 2
    if "iso_gain" in effects:
        extra["iso_gain"] = (out.value / factor * response.iso_gain_factor_sigma) ** 2
    return dataclasses.replace(out, systematic_var={**out.systematic_var, **extra})


def correct_flat_field(m: Measured, flat_field, effects, prnu_sigma_rel: float = 0.0,
                       flat_field_sigma=None, sites: int = 1) -> Measured:
    """Divide by the relative pixel sensitivity (``prnu``: the linearity stage's flat field, mean 1).

    Where the flat field was not measured (NaN: outside the region the
    linearity stage saw), the pixel's sensitivity is unknown by the fitted
    PRNU spread: value kept, random term ``prnu`` = (value * prnu_sigma_rel)^2 / sites
    (``prnu_sigma_rel`` is the spread of one raw site, the linearity stage's
    S^2 / sites term; a band pixel of ``sites`` sites averages their patterns).
    Where it was measured, ``prnu`` is the noise of the measured flat field,
    (value * flat_field_sigma)^2: fixed from frame to frame, random from pixel
    to pixel.
    """
    if "prnu" not in effects or flat_field is None:
        return m
    flat = np.asarray(flat_field, dtype=float)
    measured = np.isfinite(flat) & (flat > 0)
    out = m.scaled(1.0 / np.where(measured, flat, 1.0), m.units)
    rand = dict(out.random_var)
    flat_rel = 0.0 if flat_field_sigma is None else np.nan_to_num(np.asarray(flat_field_sigma, float)) / np.where(
        measured, flat, 1.0)
    rand["prnu"] = np.where(measured, (out.value * flat_rel) ** 2, (out.value * prnu_sigma_rel) ** 2 / sites)
    return dataclasses.replace(out, random_var=rand)


def correct_rolloff(m: Measured, theta_deg, calibration: BandCalibration, phi_deg=None, effects=()) -> Measured:
    """Divide by the roll-off g(theta), Eq. (13) (Section 2.4); systematic term ``rolloff`` from its covariance.

    With ``rolloff_azimuth`` (and the pixel azimuths ``phi_deg``) also by its
    azimuthal factor 1 + A (theta / theta_ref) cos(phi - phi0); systematic
    term ``rolloff_azimuth`` from the uncertainties of A and phi0.

    Pixels without a viewing direction (theta NaN) are flagged outside the
    image circle; field angles beyond the calibrated one are flagged.
    """
    theta = np.asarray(theta_deg, dtype=float)
    if calibration.rolloff_covariance is None:
        g, g_sigma = rolloff_on_image(calibration.rolloff_coefficients, theta), np.zeros(theta.shape)
    else:
        g, g_sigma = rolloff_on_image(calibration.rolloff_coefficients, theta, calibration.rolloff_covariance)
    out = m.scaled(1.0 / g, m.units)
    out = dataclasses.replace(out, systematic_var={**out.systematic_var, "rolloff": (out.value * g_sigma / g) ** 2})
    if "rolloff_azimuth" in effects and phi_deg is not None and calibration.rolloff_azimuth_amplitude != 0.0:
        c = calibration
        u = np.minimum(theta, 100.0) / c.rolloff_azimuth_theta_ref_deg
        dphi = np.radians(np.asarray(phi_deg, dtype=float) - c.rolloff_azimuth_phi0_deg)
        a = 1.0 + c.rolloff_azimuth_amplitude * u * np.cos(dphi)
        out = out.scaled(1.0 / a, m.units)
        rel_var = ((u * np.cos(dphi) * c.rolloff_azimuth_amplitude_sigma) ** 2
                   + (c.rolloff_azimuth_amplitude * u * np.sin(dphi) * np.radians(c.rolloff_azimuth_phi0_deg_sigma)) ** 2
                   ) / a**2
        out = dataclasses.replace(out, systematic_var={**out.systematic_var,
                                                       "rolloff_azimuth": out.value**2 * rel_var})
    out = out.flagged(~np.isfinite(theta), FLAG_OUTSIDE_IMAGE_CIRCLE)
    return out.flagged(theta > calibration.calibrated_field_angle_deg, FLAG_BEYOND_CALIBRATED_ANGLE)  # NaN: False


def correct_immersion(m: Measured, calibration: BandCalibration, medium: str) -> Measured:
    """In water multiply by the immersion factor I, Eq. (4) and (11); term ``immersion_factor``. In air, nothing."""
    if medium != "water":
        return m
    i = calibration.immersion_factor
    if not np.isfinite(i) or i <= 0:
        raise ImpossibleResult(None, f"immersion factor {i} is not positive: rerun the immersion stage")
    out = m.scaled(i, m.units)
    rel = calibration.immersion_factor_sigma / i
    return dataclasses.replace(out, systematic_var={**out.systematic_var, "immersion_factor": (out.value * rel) ** 2})


def check_inverse_responsivity(value: float, where: str = "") -> None:
    """A non-positive (or non-finite) R^-1 is no calibration: stop with a clear message."""
    if not np.isfinite(value) or value <= 0:
        raise ImpossibleResult(None, f"inverse responsivity R^-1 {where}is {value}, not positive: "
                                     "rerun the absolute stage")


def to_radiance(m: Measured, calibration: BandCalibration) -> Measured:
    """Eq. (9) turned round: L = R^-1 y, in W sr-1 m-2 nm-1; term ``inverse_responsivity`` (its budget)."""
    check_inverse_responsivity(calibration.inverse_responsivity)
    out = m.scaled(calibration.inverse_responsivity, "W sr-1 m-2 nm-1")
    rel = calibration.inverse_responsivity_relative_sigma
    return dataclasses.replace(out, systematic_var={**out.systematic_var, "inverse_responsivity": (out.value * rel) ** 2})


# --------------------------------------------------------------------------- the chain
def measure_band(image_dn, frame: FrameSettings, dark: DarkModel, response: ResponseModel,
                 calibration: BandCalibration, theta_deg, medium: str, effects, *, saturated=None,
                 hot_mask=None, flat_field=None, prnu_sigma_rel: float = 0.0, phi_deg=None,
                 flat_field_sigma=None) -> Measured:
    """One band image of one lens from raw DN to spectral radiance: the whole inverse of Eq. (4)."""
    effects = tuple(effects)
    m = from_raw(image_dn, saturated)
    m = subtract_dark(m, dark, frame, effects)
    m = add_shot_noise(m, dark, response, frame, effects)
    m = flag_hot_pixels(m, hot_mask, effects)
    m = flag_saturation(m, response)
    m = linearise(m, response, effects)
    m = normalise_exposure(m, response, frame, effects)
    m = correct_flat_field(m, flat_field, effects, prnu_sigma_rel, flat_field_sigma, dark.sites_per_pixel)
    m = correct_rolloff(m, theta_deg, calibration, phi_deg, effects)
    m = correct_immersion(m, calibration, medium)
    return to_radiance(m, calibration)

"""The camera's response as the linearity stage fitted it, for the measurement chain (Larouche et al. 2024, Section 2.2).

Eq. (2) divides a dark-corrected signal by the nominal exposure time and
ISO/100. The linearity stage may have found that the true exposure is the
nominal one plus a shutter offset (``shutter_offset``), that the true gain is
ISO/100 times a factor per ISO (``iso_gain``, 1 at ISO 100) and that the
response bends towards saturation (``nonlinearity``). This module reads those
fitted terms from a linearity artefact into the chain's
:class:`~pipeline.radiometry.measurement.ResponseModel`, and takes a
dark-corrected signal through the chain's ``linearise`` and
``normalise_exposure`` steps (and, for pixel maps, ``correct_flat_field``
with the stage's flat field when it fitted ``prnu``), so that every stage
downstream of linearity normalises its frames as ``apply`` does.

Only the effects of the linearity artefact's own model (its ``model_effects``
attribute) are applied: an effect the linearity stage did not fit has no
parameter to apply.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from pipeline.io.artefact import model_effects
from pipeline.errors import ArtefactError, InputError
from pipeline.radiometry.dark import band_value
from pipeline.radiometry.exposure import UNIT_GAIN_ISO
from pipeline.radiometry.measurement import (FrameSettings, Measured, ResponseModel, correct_flat_field, linearise,
                                             normalise_exposure)

__all__ = ["RESPONSE_EFFECTS", "response_effects", "response_model", "flat_field_at", "response_corrected",
           "linear_signal", "PixelResponse"]

#: effects of the catalogue that the chain's linearise, normalise_exposure and correct_flat_field steps own
RESPONSE_EFFECTS = ("shutter_offset", "iso_gain", "nonlinearity", "prnu")
#: the linearity artefact's variable holding each effect's fitted parameter(s)
_FITTED_VARIABLE = {"shutter_offset": "effect_shutter_offset", "iso_gain": "effect_iso_gain",
                    "nonlinearity": "effect_nonlinearity", "prnu": "flat_field"}


def linear_signal(reading_dn, beta: float, full_scale_dn: float) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of the fitted nonlinearity m = s (1 - beta s / F) on arrays of readings (DN above dark).

    s = 2 m / (1 + sqrt(1 - 4 beta m / F)), ds/dm = 1 / sqrt(1 - 4 beta m / F), the
    same inverse as the chain's ``linearise`` step (a reading beyond the curve's top, 4 beta m >= F, is
    held at its top). With beta = 0 (or no finite full scale) the reading itself and a unit slope.
    E.g. beta = 0.05, F = 15600 DN: m = 10000 DN is s = 10343 DN, ds/dm = 1.071.

    Parameters
    ----------
    reading_dn : array_like
        Readings m above dark (DN).
    beta : float
        The fitted nonlinearity beta (dimensionless).
    full_scale_dn : float
        The full scale F of the nonlinearity (DN).

    Returns
    -------
    signal : numpy.ndarray
        Linear signal s (DN), shape of ``reading_dn``.
    slope : numpy.ndarray
        ds/dm (dimensionless), same shape.
    """
    m = np.asarray(reading_dn, dtype=float)
    if not beta or not np.isfinite(full_scale_dn) or full_scale_dn <= 0:
        return m, np.ones_like(m)
    root = np.sqrt(np.clip(1.0 - 4.0 * beta * m / full_scale_dn, 1e-6, None))
    return 2.0 * m / (1.0 + root), 1.0 / root


def response_effects(linearity: xr.Dataset | None) -> tuple[str, ...]:
    """The response corrections the linearity artefact fitted: its model's effects that the chain's response steps own.

    An effect in its model without its fitted parameter is a broken artefact: refused.

    Parameters
    ----------
    linearity : xarray.Dataset or None
        The linearity artefact of the lens; None: no correction.

    Returns
    -------
    tuple of str
        The effects of :data:`RESPONSE_EFFECTS` in the artefact's ``model_effects``, in that order.

    Raises
    ------
    pipeline.errors.ArtefactError
        When the artefact's model lists an effect whose fitted variable it does not hold.
    """
    if linearity is None:
        return ()
    fitted = model_effects(linearity)
    out = tuple(e for e in RESPONSE_EFFECTS if e in fitted)
    missing = [e for e in out if _FITTED_VARIABLE[e] not in linearity]
    if missing:
        raise ArtefactError(None, f"the linearity artefact's model lists {', '.join(missing)} but it holds no "
                                  f"fitted {', '.join(_FITTED_VARIABLE[e] for e in missing)}: rerun the linearity stage")
    return out


def _band_value(ds: xr.Dataset, name: str, band: str, default: float) -> float:
    """A scalar of the artefact, taken at ``band`` when it has a band dimension; ``default`` when absent."""
    if name not in ds:
        return default
    value = band_value(ds, name, band)
    return float(value.ravel()[0]) if value.ndim else float(value)


def _iso_gain_factor(linearity: xr.Dataset, iso: float) -> tuple[float, float]:
    """True gain over ISO/100 at ``iso`` and its standard uncertainty (1 exactly at ISO 100, the reference)."""
    if float(iso) == UNIT_GAIN_ISO:
        return 1.0, 0.0
    isos = linearity["effect_iso_gain_iso"].values.astype(float)
    hit = np.flatnonzero(isos == float(iso))
    if hit.size != 1:
        raise InputError(None, f"the linearity stage fitted no gain factor at ISO {iso:g} (it has ISO "
                               f"{', '.join(f'{i:g}' for i in isos)}): the frame's gain is unknown")
    i = int(hit[0])
    return 1.0 + float(linearity["effect_iso_gain"].values[i]), float(linearity["effect_iso_gain_sigma"].values[i])


def response_model(linearity: xr.Dataset, band: str, iso: float) -> ResponseModel:
    """The chain's ResponseModel of one band at one ISO from a linearity artefact (Section 2.2).

    Parameters of effects outside :func:`response_effects` keep their neutral
    values (no offset, factor 1, no bending), so the chain leaves them out even
    if it were asked to apply them.

    Parameters
    ----------
    linearity : xarray.Dataset
        The linearity artefact of the lens.
    band : str
        Band label.
    iso : float
        ISO setting of the frame.

    Returns
    -------
    pipeline.radiometry.measurement.ResponseModel
        Conversion gain (DN per electron at ISO 100), shutter offset (s), ISO gain factor, nonlinearity beta,
        full scale and saturation level (DN), with their standard uncertainties.

    Raises
    ------
    pipeline.errors.InputError
        With ``iso_gain`` fitted, when ``iso`` is neither ISO 100 nor an ISO the stage fitted a factor at.
    pipeline.errors.ArtefactError
        When the artefact is broken (:func:`response_effects`).
    """
    effects = response_effects(linearity)
    offset = offset_sigma = 0.0
    if "shutter_offset" in effects:
        offset = _band_value(linearity, "effect_shutter_offset", band, 0.0)
        offset_sigma = _band_value(linearity, "effect_shutter_offset_sigma", band, 0.0)
    factor, factor_sigma = _iso_gain_factor(linearity, iso) if "iso_gain" in effects else (1.0, 0.0)
    beta = beta_sigma = 0.0
    if "nonlinearity" in effects:
        beta = _band_value(linearity, "effect_nonlinearity", band, 0.0)
        beta_sigma = _band_value(linearity, "effect_nonlinearity_sigma", band, 0.0)
    return ResponseModel(
        conversion_gain_dn_per_e=_band_value(linearity, "conversion_gain_dn_per_e", band, float("nan")),
        shutter_offset_s=offset, shutter_offset_s_sigma=offset_sigma,
        iso_gain_factor=factor, iso_gain_factor_sigma=factor_sigma,
        nonlinearity_beta=beta, nonlinearity_beta_sigma=beta_sigma,
        full_scale_dn=_band_value(linearity, "nonlinearity_full_scale_dn", band, float("nan")),
        saturation_dn=_band_value(linearity, "saturation_dn", band, float("nan")))


def flat_field_at(linearity: xr.Dataset | None, band: str, mask: np.ndarray) -> np.ndarray | None:
    """The linearity artefact's flat field (relative pixel sensitivity) at the pixels of ``mask``.

    Parameters
    ----------
    linearity : xarray.Dataset or None
        The linearity artefact of the lens.
    band : str
        Band label.
    mask : numpy.ndarray of bool
        Band pixels to take, the band image's shape.

    Returns
    -------
    numpy.ndarray or None
        The flat field (dimensionless, mean 1; NaN where not measured) at the mask's pixels, 1-D; None when
        the artefact did not fit ``prnu`` or its map does not have the mask's shape.
    """
    if "prnu" not in response_effects(linearity):
        return None
    flat = linearity["flat_field"].sel(band=band).values
    return flat[mask] if flat.shape == np.shape(mask) else None


def response_corrected(signal_dn, linearity: xr.Dataset | None, band: str, frame: FrameSettings,
                       signal_sigma_dn=0.0, flat_field=None) -> tuple[Measured, Measured]:
    """A dark-corrected signal (DN) through the chain's linearise, normalise_exposure and correct_flat_field steps.

    The fitted parameters' uncertainties come out as the systematic terms of the chain. Without a linearity
    artefact both steps are the nominal Eq. (2): the signal itself, and the signal over t ISO/100.

    Parameters
    ----------
    signal_dn : array_like
        Dark-corrected signal (DN).
    linearity : xarray.Dataset or None
        The linearity artefact of the lens.
    band : str
        Band label.
    frame : pipeline.radiometry.measurement.FrameSettings
        Exposure time and ISO of the frame.
    signal_sigma_dn : float or array_like, default 0.0
        Standard uncertainty of the signal (DN), entering as the random term ``signal``.
    flat_field : array_like, optional
        The pixels' relative sensitivity (:func:`flat_field_at`); used when the artefact fitted ``prnu``.

    Returns
    -------
    linear : pipeline.radiometry.measurement.Measured
        The linearised signal (DN).
    rate : pipeline.radiometry.measurement.Measured
        The signal rate (DN s-1 at ISO 100; Eq. 2 with the true exposure t + dt and gain ISO/100 f_ISO),
        divided by the flat field when it applies.
    """
    effects = response_effects(linearity)
    response = response_model(linearity, band, frame.iso) if linearity is not None \
        else ResponseModel(conversion_gain_dn_per_e=float("nan"))
    value = np.asarray(signal_dn, dtype=float)
    m = Measured(value=value, units="DN",
                 random_var={"signal": np.broadcast_to(np.square(np.asarray(signal_sigma_dn, float)), value.shape)})
    linear = linearise(m, response, effects)
    return linear, correct_flat_field(normalise_exposure(linear, response, frame, effects), flat_field, effects)


class PixelResponse:
    """The chain's per-pixel response steps, ``linearise`` and ``correct_flat_field``, on pixels taken by
    flat index from the band images of a stage that measures ratios of signals at one exposure and ISO
    (the roll-off: each spot against the axis).

    From a linearity artefact (or None: the readings as they are), for one band: the fitted nonlinearity
    m = s (1 - beta s / F) inverted (:func:`linear_signal`) and the reading divided by the flat field at
    each pixel where it was measured, each when the artefact fitted it (:func:`response_effects`). ``beta_shift`` (in units of
    the fitted beta's standard uncertainty) evaluates the inverse at beta + beta_shift sigma_beta: the
    finite difference by which a stage carries that uncertainty into what it fits.
    """

    def __init__(self, linearity: xr.Dataset | None, band: str):
        effects = response_effects(linearity)
        self.effects = effects
        self.beta = self.beta_sigma = 0.0
        self.full_scale_dn = float("nan")
        if "nonlinearity" in effects:
            # the one reading of the fitted terms (at ISO 100, where the gain factor is 1 by definition)
            response = response_model(linearity, band, UNIT_GAIN_ISO)
            self.beta, self.beta_sigma = response.nonlinearity_beta, response.nonlinearity_beta_sigma
            self.full_scale_dn = response.full_scale_dn
        self.flat = None
        if "prnu" in effects:
            # where the linearity stage did not measure the flat field (NaN: outside its photon-transfer
            # region) the pixel's reading is kept, as the chain's correct_flat_field keeps it
            flat = linearity["flat_field"].sel(band=band).values.astype(float).ravel()
            self.flat = np.where(np.isfinite(flat) & (flat > 0), flat, 1.0)

    @property
    def corrections(self) -> tuple[str, ...]:
        """The response steps this object applies (the artefact's fitted nonlinearity and flat field)."""
        return tuple(e for e in ("nonlinearity", "prnu") if e in self.effects)

    def __call__(self, reading_dn, index, beta_shift: float = 0.0) -> np.ndarray:
        """Readings above dark (DN) of the band pixels at flat ``index``: linear signal over the flat field."""
        beta = self.beta + beta_shift * self.beta_sigma
        s = linear_signal(reading_dn, beta, self.full_scale_dn)[0] if beta else np.asarray(reading_dn, float)
        return s / self.flat[index] if self.flat is not None else s

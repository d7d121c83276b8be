"""The dark model and the correction of a frame by it (Larouche et al. 2024, Section 2.8).

The dark stage fits, per lens and band, a black level that grows with the
analogue gain and a dark current that grows with gain and exposure time:

    level = b0 + b1 (g - 1) + D g t,      g = ISO / 100

with, when the ``temperature`` effect is in the model, a linear change of the
black level and of the dark current with the logged temperature. These
functions read that model from a dark artefact; every later stage subtracts
the dark level through them.

Dark frames all at one ISO (a fixed-gain camera, or a lab that locks the ISO) do not
measure b1: the dark stage fixes it at 0 (attribute ``measured`` = 0 on
``bias_per_gain_dn``) and b0 is the black level at that ISO, so the model holds at
that ISO only; :func:`check_dark_iso` refuses any other.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from pipeline.errors import InputError
from pipeline.radiometry.exposure import gain_from_iso

__all__ = ["band_value", "dark_model_level_dn", "dark_level_dn", "temperature_model_shift_dn", "temperature_shift_dn",
           "check_dark_iso"]


def check_dark_iso(ds: xr.Dataset, iso: float, iso_coord: str = "iso") -> None:
    """Refuse, in one line, an ISO that a dark model without a gain term (b1 not measured: one ISO in
    the dark frames) was not calibrated at; a dark model with b1 measured passes every ISO.

    Parameters
    ----------
    ds : xarray.Dataset
        A dark artefact (or a dataset holding its variables), with ``bias_per_gain_dn`` and the ISO coordinate.
    iso : float
        ISO setting of the frame to correct.
    iso_coord : str, default "iso"
        Name of the variable that lists the ISO settings of the dark frames.

    Raises
    ------
    pipeline.errors.InputError
        When b1 was not measured and ``iso`` is none of the dark frames' ISO settings.
    """
    per_gain = ds.variables.get("bias_per_gain_dn")
    if per_gain is None or per_gain.attrs.get("measured", 1):
        return
    isos = np.asarray(ds.variables[iso_coord].values, dtype=float)
    if not np.any(np.isclose(isos, float(iso))):
        raise InputError(None, f"ISO {float(iso):g} is not calibrated: the dark model was measured at ISO "
                               f"{', '.join(f'{i:g}' for i in isos)} only (no gain sweep in the dark frames)")


def dark_model_level_dn(bias_dn, bias_per_gain_dn, dark_current_dn_per_s, gain, exposure_s):
    """The dark model b0 + b1 (g - 1) + D g t in DN, from its parameters (vectorised).

    E.g. b0 = 800, b1 = 0.7, D = 0.5 DN/s at g = 4 and t = 1 s -> 800 + 2.1 + 2 = 804.1 DN.

    Parameters
    ----------
    bias_dn : float or array_like
        Black level b0 at ISO 100 (DN; at the dark frames' one ISO when b1 was not measured).
    bias_per_gain_dn : float or array_like
        Change b1 of the black level per unit of gain above 1 (DN).
    dark_current_dn_per_s : float or array_like
        Dark current D at ISO 100 (DN s-1).
    gain : float or array_like
        Gain g = ISO / 100 (dimensionless).
    exposure_s : float or array_like
        Exposure time t (s).

    Returns
    -------
    float or numpy.ndarray
        Mean dark level (DN), broadcast over the inputs.
    """
    return bias_dn + bias_per_gain_dn * (gain - 1.0) + dark_current_dn_per_s * gain * exposure_s


def temperature_model_shift_dn(bias_dn_per_c, dark_dn_per_s_per_c, reference_c, gain, exposure_s, temperature_c):
    """The ``temperature`` effect's change of the dark level, from its parameters (vectorised):
    (dB/dT + dD/dT g t) (T - T_ref), in DN.

    Parameters
    ----------
    bias_dn_per_c : float or array_like
        Change of the black level with temperature dB/dT (DN per degree Celsius).
    dark_dn_per_s_per_c : float or array_like
        Change of the dark current at ISO 100 with temperature dD/dT (DN s-1 per degree Celsius).
    reference_c : float
        The dark model's reference temperature T_ref (degree Celsius).
    gain : float or array_like
        Gain g = ISO / 100 (dimensionless).
    exposure_s : float or array_like
        Exposure time t (s).
    temperature_c : float or array_like
        Logged sensor temperature T (degree Celsius).

    Returns
    -------
    numpy.ndarray
        Change of the dark level (DN), broadcast over the inputs.
    """
    dt = np.asarray(temperature_c, dtype=float) - reference_c
    return (bias_dn_per_c + dark_dn_per_s_per_c * gain * np.asarray(exposure_s, dtype=float)) * dt


def band_value(ds: xr.Dataset, name: str, band: str) -> np.ndarray:
    """``ds[name]`` at ``band`` (all of it when it has no band axis) as a numpy array.

    It is what ``ds.sel(band=band)[name]`` holds, read from the variable itself (selecting on a dark artefact's
    some seventy variables, or making a DataArray of one of them, costs far more than the arithmetic it feeds,
    once per frame and band in every stage that predicts a dark level).

    Parameters
    ----------
    ds : xarray.Dataset
        An artefact, e.g. the dark stage's.
    name : str
        Name of the variable.
    band : str
        Band label on the ``band`` axis (e.g. ``"R"``).

    Returns
    -------
    numpy.ndarray
        The variable's values at that band, in its units (a 0-d array for a per-band scalar).
    """
    var = ds.variables[name]
    if "band" in var.dims:
        var = var.isel(band=ds.indexes["band"].get_loc(band))
    return var.values


def dark_level_dn(ds: xr.Dataset, band: str, iso: float, exposure_s: float,
                  temperature_c: float | None = None) -> float:
    """Mean dark level predicted by the fitted dark model for one band and setting (DN).

    With the ``temperature`` effect in the dark model and a logged temperature,
    the level follows it.

    Parameters
    ----------
    ds : xarray.Dataset
        The dark artefact of the lens.
    band : str
        Band label.
    iso : float
        ISO setting of the frame.
    exposure_s : float
        Exposure time of the frame (s).
    temperature_c : float, optional
        Logged sensor temperature (degree Celsius); None or NaN: the model's level at its reference.

    Returns
    -------
    float
        Mean dark level (DN).

    Raises
    ------
    pipeline.errors.InputError
        When the dark model holds at one ISO only and ``iso`` is another (:func:`check_dark_iso`).
    """
    check_dark_iso(ds, iso)
    gain = gain_from_iso(iso)
    level = float(dark_model_level_dn(band_value(ds, "bias_dn", band), band_value(ds, "bias_per_gain_dn", band),
                                      band_value(ds, "dark_current_dn_per_s", band), gain, exposure_s))
    if temperature_c is not None and np.isfinite(temperature_c):
        level += float(temperature_shift_dn(ds, iso, exposure_s, temperature_c))
    return level


def temperature_shift_dn(ds: xr.Dataset, iso, exposure_s, temperature_c):
    """Change of the dark level with temperature (the ``temperature`` effect), 0 without it.

    Black level and dark current change linearly with the logged temperature
    about the dark model's reference: dB/dT dT + dD/dT g t dT. Vectorised.

    Parameters
    ----------
    ds : xarray.Dataset
        The dark artefact (its ``temperature_*`` variables, present with the effect).
    iso : float or array_like
        ISO setting.
    exposure_s : float or array_like
        Exposure time (s).
    temperature_c : float or array_like
        Logged sensor temperature (degree Celsius).

    Returns
    -------
    float or numpy.ndarray
        Change of the dark level (DN); zeros shaped like ``temperature_c`` when the artefact has no
        temperature term.
    """
    if "temperature_bias_dn_per_c" not in ds:
        return np.zeros(np.shape(temperature_c)) if np.ndim(temperature_c) else 0.0
    return temperature_model_shift_dn(float(ds["temperature_bias_dn_per_c"]), float(ds["temperature_dark_dn_per_s_per_c"]),
                                      float(ds["temperature_reference_c"]), gain_from_iso(iso), exposure_s, temperature_c)

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

__all__ = ["dark_model_level_dn", "dark_level_dn", "temperature_model_shift_dn", "temperature_shift_dn",
           "check_dark_iso"]


def check_dark_iso(ds: xr.Dataset, iso: float, iso_coord: str = "iso") -> None:
    """Refuse, in one line, an ISO that a dark model without a gain term (b1 not measured: one ISO in
    the dark frames) was not calibrated at; a dark model with b1 measured passes every ISO."""
    if "bias_per_gain_dn" not in ds or ds["bias_per_gain_dn"].attrs.get("measured", 1):
        return
    isos = np.asarray(ds[iso_coord].values, dtype=float)
    if not np.any(np.isclose(isos, float(iso))):
        raise InputError(None, f"ISO {float(iso):g} is not calibrated: the dark model was measured at ISO "
                               f"{', '.join(f'{i:g}' for i in isos)} only (no gain sweep in the dark frames)")


def dark_model_level_dn(bias_dn, bias_per_gain_dn, dark_current_dn_per_s, gain, exposure_s):
    """The dark model b0 + b1 (g - 1) + D g t in DN, from its parameters (vectorised).

    E.g. b0 = 800, b1 = 0.7, D = 0.5 DN/s at g = 4 and t = 1 s -> 800 + 2.1 + 2 = 804.1 DN.
    """
    return bias_dn + bias_per_gain_dn * (gain - 1.0) + dark_current_dn_per_s * gain * exposure_s


def temperature_model_shift_dn(bias_dn_per_c, dark_dn_per_s_per_c, reference_c, gain, exposure_s, temperature_c):
    """The ``temperature`` effect's change of the dark level, from its parameters (vectorised):
    (dB/dT + dD/dT g t) (T - T_ref), in DN."""
    dt = np.asarray(temperature_c, dtype=float) - reference_c
    return (bias_dn_per_c + dark_dn_per_s_per_c * gain * np.asarray(exposure_s, dtype=float)) * dt

def dark_level_dn(ds: xr.Dataset, band: str, iso: float, exposure_s: float,
                  temperature_c: float | None = None) -> float:
    """Mean dark level predicted by the fitted dark model for one band and setting (DN).

    With the ``temperature`` effect in the dark model and a logged temperature,
    the level follows it.
    """
    check_dark_iso(ds, iso)
    # the three parameters alone, as numbers (selecting the band of the whole artefact, maps and tables, costs
    # milliseconds a call, and every lit frame's corner record calls this)
    def param(name):
        var = ds[name]
        return (var.sel(band=band) if "band" in var.dims else var).values

    gain = gain_from_iso(iso)
    level = float(dark_model_level_dn(param("bias_dn"), param("bias_per_gain_dn"), param("dark_current_dn_per_s"),
                                      gain, exposure_s))
    if temperature_c is not None and np.isfinite(temperature_c):
        level += float(temperature_shift_dn(ds, iso, exposure_s, temperature_c))
    return level


def temperature_shift_dn(ds: xr.Dataset, iso, exposure_s, temperature_c):
    """Change of the dark level with temperature (the ``temperature`` effect), 0 without it.

    Black level and dark current change linearly with the logged temperature
    about the dark model's reference: dB/dT dT + dD/dT g t dT. Vectorised.
    """
    if "temperature_bias_dn_per_c" not in ds:
        return np.zeros(np.shape(temperature_c)) if np.ndim(temperature_c) else 0.0
    return temperature_model_shift_dn(float(ds["temperature_bias_dn_per_c"]), float(ds["temperature_dark_dn_per_s_per_c"]),
                                      float(ds["temperature_reference_c"]), gain_from_iso(iso), exposure_s, temperature_c)

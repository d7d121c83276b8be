"""The dark model and the correction of a frame by it (Larouche et al. 2024, Section 2.8).

The dark stage fits, per lens and band, a black level that grows with the
analogue gain and a dark current that grows with gain and exposure time:

    level = b0 + b1 (g - 1) + D g t,      g = ISO / 100

with, when the ``temperature`` effect is in the model, a linear change of the
black level and of the dark current with the logged temperature. These
functions read that model from a dark artefact; every later stage subtracts
the dark level through them.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

__all__ = ["analogue_gain", "dark_level_dn", "subtract_dark"]

#: ISO speed at which the analogue gain is 1 (the dark model's reference)
REFERENCE_ISO = 100.0


def analogue_gain(iso):
    """Analogue gain relative to the reference ISO: g = ISO / 100 (Eq. 2's ISO/100)."""
    return np.asarray(iso, dtype=float) / REFERENCE_ISO if np.ndim(iso) else float(iso) / REFERENCE_ISO


def dark_level_dn(ds: xr.Dataset, band: str, iso: float, exposure_s: float,
                  temperature_c: float | None = None) -> float:
    """Mean dark level predicted by the fitted dark model for one band and setting (DN).

    With the ``temperature`` effect in the dark model and a logged temperature,
    the level follows it.
    """
    b = ds.sel(band=band)
    gain = analogue_gain(iso)
    level = float(b["bias_dn"] + b["bias_per_gain_dn"] * (gain - 1.0)
                  + ds["dark_current_dn_per_s"] * gain * exposure_s)
    if temperature_c is not None and np.isfinite(temperature_c) and "temperature_bias_dn_per_c" in ds:
        dt = temperature_c - float(ds["temperature_reference_c"])
        level += float(ds["temperature_bias_dn_per_c"]) * dt
        level += float(ds["temperature_dark_dn_per_s_per_c"]) * gain * exposure_s * dt
    return level


def subtract_dark(image_dn: np.ndarray, ds: xr.Dataset, band: str, iso: float, exposure_s: float,
                  temperature_c: float | None = None) -> np.ndarray:
    """A band image with the dark model's level removed (DN above dark)."""
    return np.asarray(image_dn, dtype=float) - dark_level_dn(ds, band, iso, exposure_s, temperature_c)

"""Synthetic linearity setting tables: the observation table of the linearity stage's settings drawn
directly, without frames, for measuring the diagnostics' block test (its false alarms and power) on many
tables at once.

Shaped as the tiny camera's: 7 exposure settings at ISO 100 and 6 gain settings at 8.33 ms, 2 lenses x 3
bands each, so 13 blocks (settings) of 6 rows; row noise 0.1 sqrt(DN x ISO/100) + 1 DN; per setting a
relative change of the signal (``rel_sigma``, source flicker) and an offset (``offset_dn``, black-level
jitter) common to its rows; the analogue gain (ISO/100)^(1 - ``gain_deficit``), a gain ladder that
``iso_gain`` should find when ``gain_deficit`` is not 0.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

EXPOSURES_S = (0.00833, 0.01667, 0.03333, 0.06667, 0.1, 0.2, 0.5)
ISOS = (100.0, 200.0, 400.0, 800.0, 1600.0, 3200.0)
#: DN per second at ISO 100 in the linearity mask, per band (the tiny camera, seed 101)
RATES_DN_PER_S = {"R": 30500.0, "G": 32400.0, "B": 10900.0}
#: the tiny camera's saturation level above the bias, DN (the ``full_scale_dn`` column)
FULL_SCALE_DN = 15576.0


def synthetic_linearity_settings(rng: np.random.Generator, rel_sigma: float, offset_dn: float,
                                 gain_deficit: float = 0.0) -> pd.DataFrame:
    """One linearity setting table, drawn with ``rng``.

    The columns the linearity stage's ``obs_setting`` has and the block test reads: 13 settings (blocks) of
    2 lenses x 3 bands.

    Parameters
    ----------
    rng : numpy.random.Generator
        The generator of every draw.
    rel_sigma : float
        Standard deviation of the relative change of the signal common to a setting's rows (source flicker),
        dimensionless.
    offset_dn : float
        Standard deviation of the offset common to a setting's rows (black-level jitter), DN.
    gain_deficit : float, optional
        The analogue gain is (ISO/100)^(1 - ``gain_deficit``); default 0 (a gain exactly ISO/100).

    Returns
    -------
    pandas.DataFrame
        One row per setting, lens and band: ``lens``, ``band``, ``sweep``, ``setting``, ``iso``, ``exposure_s``
        (s), ``gain``, ``x_rate``, ``pred_linear_dn``, ``full_scale_dn``, ``sigma_dn``, ``value_dn`` (DN) and
        ``group`` (lens/band/sweep).
    """
    settings = [("exposure", t, 100.0) for t in EXPOSURES_S] + [("gain", EXPOSURES_S[0], iso) for iso in ISOS]
    rows = []
    for s, (sweep, t, iso) in enumerate(settings):
        rel, off = rel_sigma * rng.standard_normal(), offset_dn * rng.standard_normal()
        for lens in ("far", "close"):
            for band, rate in RATES_DN_PER_S.items():
                linear = rate * t * iso / 100.0
                true = linear * (iso / 100.0) ** (-gain_deficit)
                sigma = 0.1 * np.sqrt(true * iso / 100.0) + 1.0
                rows.append({"lens": lens, "band": band, "sweep": sweep, "setting": s, "iso": iso, "exposure_s": t,
                             "gain": iso / 100.0, "x_rate": t * iso / 100.0, "pred_linear_dn": linear,
                             "full_scale_dn": FULL_SCALE_DN, "sigma_dn": sigma,
                             "value_dn": true * (1 + rel) + off + sigma * rng.standard_normal()})
    table = pd.DataFrame(rows)
    table["group"] = table["lens"] + "/" + table["band"] + "/" + table["sweep"]
    return table

"""Photon transfer of the linearity stage on hand-made points: the conversion gain of a bent response."""

from __future__ import annotations

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.stages.linearity import photon_transfer


def _points(k, read_dn, beta, full):
    s = np.array([250.0, 500.0, 1000.0, 2000.0, 3000.0, 6000.0, 9000.0])
    bend = 1.0 - 2.0 * beta * s / full                   # N'(s) of m = s (1 - beta s / F)
    m = s * (1.0 - beta * s / full)
    return pd.DataFrame({"used": True, "band": "R", "sweep": "exposure", "iso": 100.0,
                         "ptc_mean_dn": 800.0 + m, "dark_mask_dn": 800.0,
                         "ptc_var_dn2": bend**2 * k * s + read_dn**2})


def test_conversion_gain_of_a_bent_response_is_taken_on_the_linear_signal():
    k, read_dn, beta, full = 0.8, 1.7, 0.05, 15576.0
    dark = xr.Dataset({"read_noise_dn": (("band", "iso"), np.full((1, 1), read_dn))},
                      coords={"band": ["R"], "iso": [100.0]})
    rows = _points(k, read_dn, beta, full)
    straight = photon_transfer(rows, dark)["conversion_gain_dn_per_e"][0]
    linear = photon_transfer(rows, dark, beta, full)["conversion_gain_dn_per_e"][0]
    assert straight < 0.98 * k                           # left bent, low by about 3 beta s / F
    np.testing.assert_allclose(linear, k, rtol=1e-9)

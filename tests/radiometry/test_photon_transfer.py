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


def _dark(read_dn_by_band, drift_dn=0.0):
    bands = list(read_dn_by_band)
    return xr.Dataset({"read_noise_dn": (("band", "iso"), np.array([[read_dn_by_band[b]] for b in bands])),
                       "bias_drift_dn": ((), drift_dn)}, coords={"band": bands, "iso": [100.0]})


def test_frame_offsets_and_band_read_noise_leave_the_gain_exact():
    """Per setting, the frames' common black-level offsets (bias drift) add their sample variance to every
    pixel's temporal variance; the corners measure it (offset_var_dn2) and the curve loses it. Each band has
    its own zero-signal variance (the G band pixel's two sites pool the drift twice). Noise-free points: exact."""
    k, sites = 0.8, {"R": 1, "G": 2, "B": 1}
    read = {"R": 1.7, "G": 2.4, "B": 1.6}                 # site read noise (DN) of each band, zero signal
    rng = np.random.default_rng(4)
    rows = []
    for band in ("R", "G", "B"):
        for s in (90.0, 180.0, 360.0, 720.0, 1100.0, 2100.0, 5200.0):
            offset_var = 9.0 * rng.chisquare(3) / 3       # sample variance of 4 frames' drift of 3 DN
            rows.append({"used": True, "band": band, "sweep": "exposure", "iso": 100.0, "ptc_mean_dn": 800.0 + s,
                         "dark_mask_dn": 800.0, "offset_var_dn2": offset_var,
                         "ptc_var_dn2": (k * s + read[band] ** 2) / sites[band] + offset_var})
    rows = pd.DataFrame(rows)
    got = photon_transfer(rows, _dark(read), offsets_removed=True)["conversion_gain_dn_per_e"][0]
    np.testing.assert_allclose(got, k, rtol=1e-9)
    kept = photon_transfer(rows, _dark(read), offsets_removed=False)["conversion_gain_dn_per_e"][0]
    assert abs(kept - k) > 1e-3                          # the offsets left in scatter the low points


def test_gain_is_unbiased_and_its_sigma_honest_with_noisy_variances():
    """Each variance point scatters by 5 % of itself (a sample variance of ~800 values); the slope is weighted
    by the model, so the points that came out low are not favoured. Over 250 curves of 21 points the mean
    gain has a standard error of about 0.011 / sqrt(250) = 7e-4 (the spread of one curve's gain): it must
    lie within 4 of them of the truth (weights from the noisy points themselves would put it 2 x 0.05^2 =
    0.5 % low, 6 standard errors); the stated sigma must match the spread of the gains within 15 % (the
    spread's own standard error is 1 / sqrt(500) = 4.5 %)."""
    k, read = 0.8, {"R": 1.7, "G": 2.4, "B": 1.6}
    signal = np.array([90.0, 180.0, 360.0, 720.0, 1100.0, 2100.0, 5200.0])
    base = pd.DataFrame([{"used": True, "band": b, "sweep": "exposure", "iso": 100.0, "ptc_mean_dn": 800.0 + s,
                          "dark_mask_dn": 800.0, "site_true": k * s + read[b] ** 2}
                         for b in ("R", "G", "B") for s in signal])
    rng = np.random.default_rng(7)
    dark = _dark(read)
    gains, sigmas = [], []
    sites = base["band"].map({"R": 1, "G": 2, "B": 1}).to_numpy()
    for _ in range(250):
        rows = base.assign(ptc_var_dn2=base["site_true"] * (1.0 + 0.05 * rng.standard_normal(len(base))) / sites)
        g, s = photon_transfer(rows, dark)["conversion_gain_dn_per_e"]
        gains.append(g)
        sigmas.append(s)
    gains = np.array(gains)
    assert abs(gains.mean() - k) < 4 * gains.std() / np.sqrt(len(gains)), gains.mean()
    assert abs(np.sqrt(np.mean(np.square(sigmas))) / gains.std() - 1.0) < 0.15

"""The camera in water against a co-located OCR-504-like reference over a profile of depths (issue 33, item 6).

Five depths (1 to 9 m) of the underwater scene (:mod:`pipeline.simulate.underwater`),
the camera level, one bracket per depth merged by ``light_field_from_brackets``
(medium water, 9 degree grid); beside the frames, the reference's CSV
(:mod:`pipeline.simulate.reference_profile`: E_d and L_u channels at the camera's
band wavelengths, 3 % calibration drawn per profile and channel, 1 % and 2 %
noise per reading, all stated in the file). Match-up statistics of the camera
against the reference (:func:`pipeline.stats.matchup.matchup_statistics`: MUPD,
median symmetric accuracy, SSPB with bootstrap intervals), and a z test of the
differences d / sqrt(sigma_camera^2 + sigma_reference^2).

- The reference's file states its sigmas, and its readings agree with the
  truth within them (the truth is known here).
- The match-up statistics are finite with their intervals, and the z of
  every difference within 3 (15 values per quantity).
- Detection of an injected 10 % E_d calibration error of the reference: the
  mean z of the 15 differences beyond 3 / sqrt(15) = 0.77. Measured: as
  drawn, E_d MUPD 2.1 % [1.2, 3.3], SSPB -1.1 % [-2.8, -0.3], L_u MUPD
  12.2 % [5.9, 21.3], largest |z| 1.76 and 0.37; with the 10 % error, E_d
  MUPD 11.3 % [10.3, 12.5], SSPB -11.3 % [-13.1, -10.4] and mean z -2.47
  (largest |z| 3.85): detected. The camera's stated E_d sigma is a median
  2.8 % of E_d (level camera), the fill model's share small since the band
  between the lenses is filled in ln L (pipeline.lightfield.fill; it was
  14 % with the bound-like sigma of the linear fill in L, and the error went
  undetected, mean z -0.74).

Run time: about 30 s of CPU with the session fixture ``calibrated`` (measured 30.3 s user).
"""

from __future__ import annotations

from datetime import datetime

import numpy as np
import pandas as pd
import pytest
from dataclasses import replace

from pipeline.io.bands import BANDS
from pipeline.lightfield.command import light_field_from_brackets
from pipeline.simulate.reference_profile import profile_times, profile_truth, write_reference_profile
from pipeline.simulate.underwater import UnderwaterScene, render_underwater_bracket
from pipeline.stats.matchup import matchup_statistics

DEPTHS_M = (1.0, 3.0, 5.0, 7.0, 9.0)
START = datetime(2021, 3, 18, 16, 0, 0)
SEED = 4


@pytest.fixture(scope="module")
def profile(calibrated, tmp_path_factory):
    """The camera's E_d and L_u (value, sigma; depth x band) and the reference's tables (as drawn, and with a
    10 % E_d miscalibration)."""
    folder = tmp_path_factory.mktemp("profile")
    times = profile_times(START, len(DEPTHS_M))
    camera = {q: np.zeros((len(DEPTHS_M), len(BANDS), 2)) for q in ("E_d", "L_u")}
    for i, (z, t) in enumerate(zip(DEPTHS_M, times)):
        info = render_underwater_bracket(folder / f"z{i}", replace(UnderwaterScene(), depth_m=z), seed=SEED + i,
                                         start=t, bracket=f"Z{i}")
        ds = light_field_from_brackets(calibrated[4], info["files"], info["frames_csv"], "water", grid_deg=9.0)
        for q in camera:
            camera[q][i, :, 0] = ds[q][0].values
            camera[q][i, :, 1] = ds[f"{q}_sigma"][0].values
    scene = UnderwaterScene()
    ref = write_reference_profile(folder / "reference.csv", scene, DEPTHS_M, times, seed=SEED)
    bad = write_reference_profile(folder / "reference_bad.csv", scene, DEPTHS_M, times, seed=SEED,
                                  calibration_error={"E_d": 0.10})
    return camera, ref, bad, profile_truth(scene, DEPTHS_M), folder


def _pairs(camera, table, q):
    rows = table[table["quantity"] == q]
    x = np.array([[rows[(rows["depth_m"] == z) & (rows["band"] == b)]["value"].item() for b in BANDS]
                  for z in DEPTHS_M])
    sx = np.array([[rows[(rows["depth_m"] == z) & (rows["band"] == b)]["sigma"].item() for b in BANDS]
                   for z in DEPTHS_M])
    return camera[q][..., 0], camera[q][..., 1], x, sx


def test_reference_file_states_its_sigmas_and_agrees_with_the_truth(profile):
    _, ref, _, truth, folder = profile
    table = pd.read_csv(folder / "reference.csv")
    assert {"time_utc", "depth_m", "channel", "value", "sigma", "calibration_relative_sigma",
            "noise_relative_sigma"} <= set(table.columns)
    assert len(table) == 2 * len(DEPTHS_M) * len(BANDS)
    for q in ("E_d", "L_u"):
        rows = ref[ref["quantity"] == q]
        t = np.array([truth[q][DEPTHS_M.index(z), BANDS.index(b)] for z, b in zip(rows["depth_m"], rows["band"])])
        assert np.all(np.abs(rows["value"].values - t) <= 4 * rows["sigma"].values), q


def test_matchup_statistics_and_z_test(profile):
    camera, ref, _, _, _ = profile
    for q in ("E_d", "L_u"):
        y, sy, x, sx = _pairs(camera, ref, q)
        stats = matchup_statistics(y.ravel(), x.ravel(), sy.ravel(), sx.ravel(), n_resamples=500)
        for name in ("mupd", "median_symmetric_accuracy", "signed_symmetric_bias"):
            assert np.isfinite([stats[name], stats[f"{name}_low"], stats[f"{name}_high"]]).all(), (q, name)
            assert stats[f"{name}_low"] <= stats[name] <= stats[f"{name}_high"], (q, name)
        z = (y - x) / np.hypot(sy, sx)
        assert np.all(np.abs(z) <= 3.0), (q, z)


def test_injected_reference_calibration_error_detected(profile):
    camera, _, bad, _, _ = profile
    y, sy, x, sx = _pairs(camera, bad, "E_d")
    z = (y - x) / np.hypot(sy, sx)
    # the mean z over 15 values: significant beyond 3 / sqrt(15) of a unit normal's mean
    assert abs(z.mean()) > 3.0 / np.sqrt(z.size)

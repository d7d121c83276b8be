"""Every lit stage records its frames' unlit corners against the dark model (pipeline.radiometry.unlit_corners).

On the session's calibrated tiny camera (tests/conftest.py ``calibrated``: seed 5, no effect, the pipeline's own
dark and geometry artefacts), each of the roll-off, spectral, absolute and immersion stages is run again for one
lens with the raw reader counted:

* each raw file is decoded once (the corner mean comes from the frame the stage's own reduction decodes);
* its artefact's ``obs_corner`` holds one row per signal frame of the lens and band, with the frame's ISO and
  exposure as its DNG states them, and the corner mean's noise as the dark stage's read noise at that ISO over
  the square root of the sites averaged (R and B one site per band pixel, G two, so that G's noise is R's over
  sqrt 2 to rounding);
* the corners' departures from the dark model's prediction, in their stated noise, average to zero within 5
  standard errors (5 / sqrt(rows); the clean camera has nothing but read noise in its corners, and with 60 rows
  or more that is under two thirds of one row's noise).
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pandas as pd
import pytest

from pipeline.io import frames as frames_mod
from pipeline.io.artefact import read_artefact
from pipeline.stages.observations import CORNER_PREFIX, dataset_to_table
from pipeline.io.rawio import read_raw
from pipeline.runner.workflow import STAGES, run_stage

LENS = "far"
#: the stage's own keys on each row of its corner record
STAGE_KEYS = {"rolloff": ("medium", "azimuth_deg", "angle_deg"), "spectral": ("wavelength_nm",),
              "absolute": (), "immersion": ("medium", "water_height_cm")}


@pytest.mark.parametrize("stage", sorted(STAGE_KEYS))
def test_lit_stage_records_its_frames_corners_from_one_decode(stage, calibrated, config, tmp_path, monkeypatch):
    root, _, _, artefacts, _, _ = calibrated
    reads = Counter()

    def counting_read_raw(path):
        reads[str(path)] += 1
        return read_raw(path)

    monkeypatch.setattr(frames_mod, "read_raw", counting_read_raw)
    spec = STAGES[stage]
    upstream = {name: artefacts[name] for name in spec.upstream + spec.optional_upstream if name in artefacts}
    assert "dark" in upstream
    art = run_stage(stage, root, config, {LENS: tmp_path / f"{LENS}.nc"}, upstream)[LENS]

    frames = pd.read_csv(root / spec.experiment / "frames.csv")
    mine = frames[frames["lens"].isin([LENS, "both"])]
    assert reads and set(reads.values()) == {1}, reads.most_common(3)
    assert len(reads) == len(mine)

    table = dataset_to_table(art, CORNER_PREFIX)
    signal = mine[mine["kind"] == "signal"]
    assert len(table) == 3 * len(signal)
    assert set(table["lens"]) == {LENS}
    assert sorted(table.groupby("file_index")["band"].apply(lambda b: "".join(sorted(b)))) == ["BGR"] * len(signal)
    for key in STAGE_KEYS[stage]:
        assert key in table, key
    # ISO and exposure as the frames' DNGs state them
    stated = {(float(r.iso), round(float(r.exposure_s), 9)) for r in (read_raw(root / spec.experiment / f)
                                                                        for f in signal["file"])}
    assert set(zip(table["iso"].astype(float), table["exposure_s"].astype(float))) == stated
    noise = table.groupby("band")["sigma_corner_dn"].median()
    assert noise["G"] == pytest.approx(noise["R"] / np.sqrt(2.0), rel=0.05)
    z = (table["corner_dn"] - table["dark_corner_dn"]) / table["sigma_corner_dn"]
    assert abs(float(z.mean())) < 5.0 / np.sqrt(len(z)), float(z.mean())


def test_corner_pattern_from_the_dark_artefacts_average_only_at_its_corner_fraction():
    """The dark stage stores the offset map averaged over the unlit corners with the corner fraction it used
    (``fpn_corner_mean_dn``); a lit stage takes that value only when its own corners come from the same
    fraction, and otherwise averages the map over its own corners. A synthetic dark model whose stored value
    (5 DN) differs from the map's corner mean (the map is 2 DN in the corners, 0 elsewhere) tells which was read."""
    import xarray as xr

    from pipeline.radiometry.unlit_corners import corner_pattern_dn, corner_pixels

    shape = (40, 40)
    corners = corner_pixels(shape, "fisheye", 1.0)
    fpn = np.where(corners, 2.0, 0.0).astype(np.float32)
    dark = xr.Dataset({"fpn_map_dn": (("band", "y", "x"), np.stack([fpn] * 3)),
                       "fpn_corner_mean_dn": ("band", [5.0, 5.0, np.nan], {"corner_min_radius_fraction": 1.0})},
                      coords={"band": ["R", "G", "B"]})
    assert corner_pattern_dn(dark, "G", corners, 1.0) == 5.0
    assert corner_pattern_dn(dark, "G", corners, 1.1) == 2.0     # another fraction: the map over these corners
    assert corner_pattern_dn(dark, "G", corners) == 2.0          # fraction not given: the map
    assert corner_pattern_dn(dark, "B", corners, 1.0) == 2.0     # nothing stored for the band: the map
    assert corner_pattern_dn(dark.drop_vars("fpn_corner_mean_dn"), "R", corners, 1.0) == 2.0


#: hot pixels of the test below: a fraction 40 times the default's, so that the tiny camera's corners hold some
HOT_FRACTION = 0.02


def _corner_slope(art) -> tuple[float, float]:
    """Slope (DN/s) of the corners' departure from the dark model against exposure over the ISO 100 exposure
    sweep of a linearity artefact's ``obs_corner``, with its standard error (weighted least squares)."""
    t = dataset_to_table(art, CORNER_PREFIX)
    t = t[t["iso"] == 100.0]
    d = (t["corner_dn"] - t["dark_corner_dn"]).to_numpy(float)
    w = 1.0 / t["sigma_corner_dn"].to_numpy(float) ** 2
    X = np.column_stack([np.ones(len(t)), t["exposure_s"].to_numpy(float)])
    cov = np.linalg.inv(X.T @ (X * w[:, None]))
    coef = cov @ (X.T @ (w * d))
    return float(coef[1]), float(np.sqrt(cov[1, 1]))


def test_corners_leave_out_the_hot_pixels_the_dark_model_leaves_out(make_dataset, config, tmp_path, monkeypatch):
    """With ``hot_pixels`` in the model the dark model is the level of the pixels that are not hot, so a lit
    frame's corner mean must leave out the dark stage's hot pixels too: a hot pixel in a corner adds its own rate
    times the exposure. Tiny camera, hot pixels at a fraction of 0.02 (about 4 per band in a lens's 200-odd
    corner pixels, each some 300 DN/s): the corners' departure from the dark model along the linearity's
    exposure sweep (ISO 100, 8 ms to 0.5 s) has no slope within 4 of its standard errors (the corners hold read
    noise only; measured -0.05 +- 0.032 DN/s, seed 61); taking every corner pixel instead, as before, the hot
    ones' mean rate shows as a slope (measured 8.14 +- 0.031 DN/s; asserted above 10 standard errors)."""
    import pipeline.stages.linearity as linearity_stage
    from pipeline.radiometry.unlit_corners import corner_pixels, corner_sites

    root, _ = make_dataset([("dark_current", {}), ("hot_pixels", {"fraction": HOT_FRACTION})], seed=61)
    run_stage("dark", root, config, {LENS: tmp_path / "dark.nc"})
    dark = read_artefact(tmp_path / "dark.nc", "dark")
    art = run_stage("linearity", root, config, {LENS: tmp_path / "lin.nc"}, {"dark": {LENS: tmp_path / "dark.nc"}})
    slope, se = _corner_slope(art[LENS])
    print(f"corners without the hot pixels: slope {slope:.3g} +- {se:.2g} DN/s")
    assert abs(slope) < 4 * se, (slope, se)
    # the hot pixels were left out: fewer sites than the corners hold
    t = dataset_to_table(art[LENS], CORNER_PREFIX)
    shape = dark["hot_pixel_mask"].sel(band="G").shape
    whole = corner_pixels(shape, "fisheye", config["bias"]["corner_min_radius_fraction"])
    kept = corner_sites(dark, whole)
    assert int(dark["hot_pixel_mask"].sel(band="G").values[whole].sum()) > 0
    assert set(t.loc[t["band"] == "G", "n_corner_sites"]) == {2 * int(kept["G"].sum())} != {2 * int(whole.sum())}

    # the same with every corner pixel, hot ones included: the slope the closure flagged
    monkeypatch.setattr(linearity_stage, "corner_sites", lambda d, corners: {b: corners for b in "RGB"})
    with_hot = run_stage("linearity", root, config, {LENS: tmp_path / "lin_hot.nc"},
                         {"dark": {LENS: tmp_path / "dark.nc"}})
    slope_hot, se_hot = _corner_slope(with_hot[LENS])
    print(f"every corner pixel: slope {slope_hot:.3g} +- {se_hot:.2g} DN/s")
    assert slope_hot > 10 * se_hot, (slope_hot, se_hot)

"""Roll-off stage on a simulated tiny dataset: curves within 1 % of truth, field angles, clean closure."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.artefact import read_artefact, write_artefact
from pipeline.diagnostics import error_figures, observations_from_artefacts, rank_missing_effects
from pipeline.radiometry.rolloff import evaluate_rolloff
from pipeline.simulate import simulate_dataset
from pipeline.observations import dataset_to_table
from pipeline.simulate.lens import default_rolloff
from pipeline.simulate.rolloff import ANGLES_DEG
from pipeline.workflow import run_stage

from helpers import true_geometry_dataset


def run_rolloff(tmp_path_factory, config, effects=(), seed=3, model=None):
    root = tmp_path_factory.mktemp("roll") / "dataset"
    simulate_dataset(root, scale="tiny", seed=seed, effects=list(effects), experiments=("rolloff",), progress=False)
    geo = {}
    for lens in ("far", "close"):
        geo[lens] = root.parent / f"geometry_{lens}.nc"
        write_artefact(true_geometry_dataset(lens, 64), geo[lens], stage="geometry", inputs={}, config_subset={},
                       effects=[])
    cfg = {**config, "model": {**config["model"], "effects": list(model or [])}}
    outputs = {lens: root.parent / f"rolloff_{lens}.nc" for lens in geo}
    run_stage("rolloff", root, cfg, outputs, {"geometry": geo})
    return {lens: read_artefact(p, "rolloff") for lens, p in outputs.items()}



@pytest.fixture(scope="module")
def config(config):
    """The session config with exact field angles: these tests use the simulator's true
    geometry maps, so the field angle carries no calibration error."""
    return {**config, "rolloff": {**config["rolloff"], "field_angle_sigma_px": 0.0}}

@pytest.fixture(scope="module")
def clean(tmp_path_factory, config):
    return run_rolloff(tmp_path_factory, config)


def test_rolloff_within_one_percent(clean):
    for lens, ds in clean.items():
        for medium in ("air", "water"):
            theta = np.abs(ANGLES_DEG[medium])
            for band in ("R", "G", "B"):
                c = ds["rolloff_coefficients"].sel(medium=medium, band=band).values
                rel = evaluate_rolloff(c, theta) / evaluate_rolloff(default_rolloff(band, medium), theta) - 1
                assert np.abs(rel).max() < 0.01, (lens, medium, band, np.abs(rel).max())


def test_field_angles_from_geometry(clean):
    for ds in clean.values():
        t = dataset_to_table(ds, "obs_setting")
        spot = t[t["kind"] == "spot"]
        # flux centroid of a hard-edged port on a coarse grid: within one band pixel (about 3 deg at
        # the tiny scale), a third of one on average
        assert np.abs(spot["spot_theta_deg"] - spot["angle_deg"].abs()).max() < 1.0 * 3.0
        assert np.abs(spot["spot_theta_deg"] - spot["angle_deg"].abs()).mean() < 1.0


def test_clean_rolloff_comes_out_clean(clean, config):
    obs = observations_from_artefacts({"rolloff": list(clean.values())})
    ranked, _ = rank_missing_effects(obs, [], config)
    assert not ranked["significant"].any(), ranked.head(3).to_string()
    fig = error_figures(obs, [])
    assert (fig["rms_z"] < 1 + 2 * np.sqrt(2 / fig["dof"])).all(), fig


def test_water_closure_predicts_from_air_without_a_fitted_shape(clean, config):
    """The closure's prediction of each in-water point, from the fitted air curve and the immersion
    physics alone, against the simulator's true water roll-off at that field angle: within 4 of the
    air fit's propagated sigma plus 0.002 (the port's 1.8 deg disc averages g over about 3 deg at the
    tiny scale; g'' is at most 2e-4 per deg^2, so the mean of g and g at the mean angle differ by
    under 0.001). Clean data: the water level leaves immersion_angle insignificant (tested by
    test_clean_rolloff_comes_out_clean) and its own rms_z within the noise."""
    for ds in clean.values():
        w = dataset_to_table(ds, "obs_water")
        w = w[w["used"] == 1]
        assert len(w) > 100
        for band, g in w.groupby("band"):
            true = evaluate_rolloff(default_rolloff(band, "water"), g["theta_deg"].to_numpy(float))
            err = np.abs(g["x_scale"].to_numpy(float) - true)
            assert (err < 4 * g["air_prediction_sigma"].to_numpy(float) + 0.002).all(), (band, err.max())
        z = w["z"].to_numpy(float)
        assert np.sqrt(np.mean(z**2)) < 1 + 3 * np.sqrt(2 / len(z)), np.sqrt(np.mean(z**2))



def test_spot_search_in_a_window_finds_the_whole_image_spot():
    """The spot search labels a window around the peak, not the whole image: a disc larger than the first
    window (radius 70 px against SPOT_WINDOW_HALF_PX = 48) and a hot pixel brighter than it elsewhere (the
    first window is around the brightest pixel) must still give the disc's exact pixels, and its
    centroid within 0.01 px of the disc's centre (noise sigma 1 DN on 1000 DN over 15,000 pixels moves
    it by about 3e-4 px). The peak pixel must be the whole image's argmax of the 3 x 3 mean, as
    scipy's uniform_filter defines it, in random scenes of discs and hot pixels."""
    from scipy import ndimage

    from pipeline.stages.rolloff import SPOT_WINDOW_HALF_PX, _find_spot, _lit_image, _peak_pixel

    rng = np.random.default_rng(5)
    yy, xx = np.indices((600, 600))
    disc = np.hypot(xx - 250, yy - 300) <= 70
    assert 70 > SPOT_WINDOW_HALF_PX
    img = rng.normal(0.0, 1.0, disc.shape) + 1000.0 * disc
    img[50, 500] = 5000.0                              # 3 x 3 mean 555 DN: brighter pixel, dimmer mean
    lit = np.ones(disc.shape, bool)
    for level in (0.5, 0.05):
        dark = np.zeros(img.shape)
        cx, cy, (sy, sx) = _find_spot(img, dark, lit, level, _peak_pixel(_lit_image(img, dark, lit)))
        found = np.zeros(disc.shape, bool)
        found[sy, sx] = True
        assert np.array_equal(found, disc), level
        assert abs(cx - 250) < 0.01 and abs(cy - 300) < 0.01, (cx, cy)
    for _ in range(20):
        img = rng.normal(0.0, 2.0, (240, 300))
        for _ in range(3):
            cy, cx, r = rng.uniform(0, 240), rng.uniform(0, 300), rng.uniform(1, 30)
            img += rng.uniform(100, 1000) * (np.hypot(xx[:240, :300] - cx, yy[:240, :300] - cy) <= r)
        img[tuple(rng.integers(0, 240, 5)), tuple(rng.integers(0, 300, 5))] += rng.uniform(0, 8000, 5)
        lit = np.hypot(xx[:240, :300] - 150, yy[:240, :300] - 120) <= rng.uniform(60, 200)
        want = np.unravel_index(np.argmax(ndimage.uniform_filter(np.where(lit, img, 0.0), 3)), img.shape)
        assert _peak_pixel(_lit_image(img, np.zeros(img.shape), lit)) == tuple(int(v) for v in want)

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

"""Immersion stage on a simulated tiny dataset: I and t_aw n_w^2 against truth and Table 2."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from pipeline.runner.workflow import run_stage
from pipeline.io.artefact import read_artefact, write_artefact
from pipeline.simulate import simulate_dataset, truth_dir_for

from helpers import true_geometry_dataset

TABLE2_N2 = {"R": 1.738, "G": 1.742, "B": 1.748}


@pytest.fixture(scope="module")
def run_immersion(tmp_path_factory, config):
    root = tmp_path_factory.mktemp("imm") / "dataset"
    simulate_dataset(root, scale="tiny", seed=5, experiments=("immersion",), progress=False)
    truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())["experiments_truth"]["immersion"]
    geo = {}
    for lens in ("far", "close"):
        geo[lens] = root.parent / f"geometry_{lens}.nc"
        write_artefact(true_geometry_dataset(lens, 64), geo[lens], stage="geometry", inputs={}, config_subset={},
                       effects=[])
    outputs = {lens: root.parent / f"immersion_{lens}.nc" for lens in geo}
    run_stage("immersion", root, config, outputs, {"geometry": geo})
    return {lens: read_artefact(p, "immersion") for lens, p in outputs.items()}, truth


def test_immersion_factor_matches_truth(run_immersion):
    arts, truth = run_immersion
    for lens, ds in arts.items():
        for band in ("R", "G", "B"):
            got = float(ds["immersion_factor"].sel(band=band))
            assert abs(got - truth["immersion_factor"][band]) < 0.01, (lens, band, got)
            lo, hi = float(ds["immersion_factor_ci95_low"].sel(band=band)), float(ds["immersion_factor_ci95_high"].sel(band=band))
            assert lo < got < hi


def test_n_squared_law_matches_table2(run_immersion):
    arts, _ = run_immersion
    for ds in arts.values():
        for band in ("R", "G", "B"):
            assert abs(float(ds["n2_factor"].sel(band=band)) - TABLE2_N2[band]) < 0.003


def test_window_index_and_provenance(run_immersion):
    arts, truth = run_immersion
    for ds in arts.values():
        ng = ds["window_index"].values
        assert np.all(np.isfinite(ng)) and np.all((ng > 1.3) & (ng < 1.9))
        assert "water.yaml" in ds.attrs["input_sha256"]
        assert ds["obs_height__value_dn"].size == 3 * 11

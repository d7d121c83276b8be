"""Shared fixtures: deterministic simulated datasets, made once per test session."""

from __future__ import annotations

import single_thread_blas  # noqa: F401  (first: sets the thread count before numpy loads)
from pathlib import Path

import pytest
import yaml

from helpers import calibrate
from pipeline.calibration import BUNDLE_STAGES
from pipeline.config import load_config
from pipeline.simulate import simulate_dataset, truth_dir_for

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture(scope="session")
def config():
    return load_config()


@pytest.fixture(scope="session")
def make_dataset(tmp_path_factory):
    """Factory: simulate (once per session and arguments) a tiny dataset; returns (path, truth dict).

    By default only the dark and linearity experiments (the foundation stages) are written.
    """
    cache = {}

    def make(effects=(), seed=11, scale="tiny", experiments=("dark", "linearity"), lab_noise=False):
        key = (tuple((n, tuple(sorted(p.items()))) for n, p in effects), seed, scale, tuple(experiments),
               lab_noise)
        if key not in cache:
            root = tmp_path_factory.mktemp("sim") / "dataset"
            simulate_dataset(root, scale=scale, seed=seed, effects=list(effects), experiments=experiments,
                             progress=False, lab_noise=lab_noise)
            truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())
            cache[key] = (root, truth)
        return cache[key]

    return make


@pytest.fixture(scope="session")
def calibrated(make_dataset, config, tmp_path_factory):
    """A tiny simulated camera calibrated by the pipeline's own stages (seed 5, no effects), shared by the
    tests that apply the bundle: (root, truth, results folder, artefacts, bundle path, dataset.yaml)."""
    root, truth = make_dataset(seed=5, experiments=tuple(BUNDLE_STAGES))
    out = tmp_path_factory.mktemp("results")
    artefacts, bundle_path, meta = calibrate(root, config, out)
    return root, truth, out, artefacts, bundle_path, meta


#: the test files that take longest (wall seconds on 2 workers, measured from `pytest --durations`), run first:
#: with ``--dist loadfile`` each file goes whole to one worker in the order collected, so the long ones first
#: and the short ones filling in after is what keeps both workers busy to the end (longest-first scheduling)
LONGEST_FIRST = ("test_workflow.py", "test_workflow_default.py", "test_workflow_radiometric.py",
                 "test_field_scale_coverage.py", "test_compare.py",
                 "test_geometry_stage.py", "test_geometry_theta_accuracy.py", "test_coverage_over_seeds.py",
                 "test_report.py", "test_apply_truth_sky.py", "test_apply.py", "test_geometry_calibrate.py",
                 "test_effect_forms.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))   # stable: the rest keep their order

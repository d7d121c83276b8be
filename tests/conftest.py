"""Shared fixtures: deterministic simulated datasets, made once per test session."""

from __future__ import annotations

import single_thread_blas  # noqa: F401  (first: sets the thread count before numpy loads)
import contextlib
import fcntl
import hashlib
import os
import pickle
import shutil
from pathlib import Path

import pytest
import yaml

from helpers import calibrate
from pipeline.bundle.calibration import BUNDLE_STAGES
from pipeline.config import load_config
from pipeline.simulate import simulate_dataset, truth_dir_for

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture(scope="session")
def config():
    return load_config()


def _run_root(tmp_path_factory) -> Path:
    """The folder every worker of this test run shares: pytest-xdist gives each worker its own base temporary
    folder inside one folder per run; without workers, the base temporary folder itself."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@contextlib.contextmanager
def _exclusive(lock_path: Path):
    with open(lock_path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def shared_once(tmp_path_factory, name: str, build):
    """``build(folder)``, once per test run across the workers: the first worker to ask builds it in a folder
    of the run's shared temporary folder (the others wait on a lock, then read its pickled result). A fixture
    made this way is read-only for the tests, as a session fixture shared by the modules of one worker was."""
    root = _run_root(tmp_path_factory) / "shared-fixtures"
    root.mkdir(exist_ok=True)
    folder, result = root / name, root / f"{name}.pickle"
    with _exclusive(root / f"{name}.lock"):
        if result.exists():
            return pickle.loads(result.read_bytes())
        shutil.rmtree(folder, ignore_errors=True)   # a build that died half-way in an earlier worker
        folder.mkdir()
        value = build(folder)
        result.write_bytes(pickle.dumps(value))
        return value


@pytest.fixture(scope="session")
def make_dataset(tmp_path_factory):
    """Factory: simulate (once per test run and arguments, across workers) a tiny dataset; returns (path, truth
    dict).

    By default only the dark and linearity experiments (the foundation stages) are written.
    """
    cache = {}

    def make(effects=(), seed=11, scale="tiny", experiments=("dark", "linearity"), lab_noise=False):
        key = (tuple((n, tuple(sorted(p.items()))) for n, p in effects), seed, scale, tuple(experiments),
               lab_noise)
        if key not in cache:
            def build(folder):
                root = folder / "dataset"
                simulate_dataset(root, scale=scale, seed=seed, effects=list(effects), experiments=experiments,
                                 progress=False, lab_noise=lab_noise)
                return root, yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())

            name = "sim-" + hashlib.sha1(repr(key).encode()).hexdigest()[:16]
            cache[key] = shared_once(tmp_path_factory, name, build)
        return cache[key]

    return make


@pytest.fixture(scope="session")
def calibrated(make_dataset, config, tmp_path_factory):
    """A tiny simulated camera calibrated by the pipeline's own stages (seed 5, no effects), shared by the
    tests that apply the bundle: (root, truth, results folder, artefacts, bundle path, dataset.yaml)."""
    root, truth = make_dataset(seed=5, experiments=tuple(BUNDLE_STAGES))

    def build(out):
        artefacts, bundle_path, meta = calibrate(root, config, out)
        return root, truth, out, artefacts, bundle_path, meta

    return shared_once(tmp_path_factory, "calibrated-seed5", build)


#: the test files that take longest (wall seconds on 2 workers, measured from `pytest --durations`), run first:
#: with ``--dist loadfile --no-loadscope-reorder`` each file goes whole to one worker in the order collected
#: (without ``--no-loadscope-reorder`` the files would go out sorted by their number of tests, the few-test
#: long ones last), so the long ones first and the short ones filling in after is what keeps both workers
#: busy to the end (longest-first scheduling)
LONGEST_FIRST = ("test_workflow.py", "test_workflow_default.py", "test_workflow_radiometric.py",
                 "test_field_scale_coverage.py", "test_compare.py",
                 "test_geometry_stage.py", "test_geometry_theta_accuracy.py", "test_coverage_over_seeds.py",
                 "test_geometry_real_corners.py", "test_hidden_effects.py", "test_field_closure.py",
                 "test_field_stage.py", "test_report.py", "test_apply_truth_sky.py", "test_apply.py",
                 "test_geometry_calibrate.py", "test_effect_forms.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))   # stable: the rest keep their order

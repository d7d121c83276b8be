"""Shared fixtures: deterministic simulated datasets, made once per test session."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

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

    def make(effects=(), seed=11, scale="tiny", experiments=("dark", "linearity")):
        key = (tuple((n, tuple(sorted(p.items()))) for n, p in effects), seed, scale, tuple(experiments))
        if key not in cache:
            root = tmp_path_factory.mktemp("sim") / "dataset"
            simulate_dataset(root, scale=scale, seed=seed, effects=list(effects), experiments=experiments,
                             progress=False)
            truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())
            cache[key] = (root, truth)
        return cache[key]

    return make

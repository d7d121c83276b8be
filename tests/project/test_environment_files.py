"""The conda environment files name every package the package itself requires (pyproject.toml), so that a conda
user's run does not fail at an import that pip users never meet."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]


def _name(requirement: str) -> str:
    """The distribution name of a requirement, normalised (PEP 503: case and -_. runs alike)."""
    return re.sub(r"[-_.]+", "-", re.split(r"[<>=!~ \[;]", requirement.strip(), maxsplit=1)[0]).lower()


def _conda_names(path: Path) -> set[str]:
    names = set()
    for item in yaml.safe_load(path.read_text())["dependencies"]:
        if isinstance(item, dict):
            names |= {_name(r) for r in item.get("pip", [])}
        else:
            names.add(_name(item))
    return names


@pytest.mark.parametrize("env_file", ["environment.yml", "workflow/envs/pipeline.yaml"])
def test_conda_environment_has_every_dependency(env_file):
    required = {_name(r) for r in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]}
    missing = required - _conda_names(ROOT / env_file)
    assert not missing, f"{env_file} lacks {sorted(missing)} (pyproject.toml requires them)"

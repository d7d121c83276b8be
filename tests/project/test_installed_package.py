"""An installed (non-editable) package works without its source tree.

The package is built into a wheel with the build backend of this environment (no build isolation, no
index: nothing is downloaded), installed into a fresh virtual environment that sees this environment's
packages (numpy and the rest), and run from a folder outside the checkout: the configuration's schema
(package data) gives apply's defaults, and the commands start.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
import venv
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from pipeline.config import defaults

REPO_ROOT = Path(__file__).resolve().parents[2]
#: what the build reads besides src/: the project's metadata and its licence (the wheel's licence file)
BUILD_FILES = ("pyproject.toml", "LICENSE")
#: left out of the copy that is built: byte code and the metadata of the checkout's editable install
NOT_BUILT = shutil.ignore_patterns("__pycache__", "*.egg-info")
#: a wheel's build, its install and the commands' start-up together take a few seconds; far beyond that a
#: step waits on something (a network look-up) and the test says which
STEP_TIMEOUT_S = 120


def _unmet_build_requirements() -> list[str]:
    """The build requirements of pyproject.toml that this environment does not meet (the test builds with them)."""
    requires = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["build-system"]["requires"]
    unmet = []
    for text in requires:
        req = Requirement(text)
        try:
            installed = version(req.name)
        except PackageNotFoundError:
            installed = None
        if installed is None or installed not in req.specifier:
            unmet.append(f"{text} (installed: {installed or 'none'})")
    return unmet


def _run(args: list, cwd: Path) -> subprocess.CompletedProcess:
    """A command without this session's PYTHONPATH (which may point at the source tree), checked."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=STEP_TIMEOUT_S)
    assert done.returncode == 0, f"{' '.join(map(str, args))} exited {done.returncode}:\n{done.stdout}\n{done.stderr}"
    return done


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, Path]:
    """(the Python of a fresh environment with the package installed from its wheel, a folder outside the checkout)."""
    unmet = _unmet_build_requirements()
    assert not unmet, (f"the wheel is built with this environment's build backend, which lacks {', '.join(unmet)}: "
                       "make venv (pip install -e '.[test]') installs it")
    root = tmp_path_factory.mktemp("installed")
    source = root / "source"
    shutil.copytree(REPO_ROOT / "src", source / "src", ignore=NOT_BUILT)
    for name in BUILD_FILES:
        shutil.copy2(REPO_ROOT / name, source / name)
    wheels = root / "wheels"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", wheels, source], root)
    (wheel,) = wheels.glob("*.whl")

    env_dir = root / "env"
    venv.create(env_dir, system_site_packages=True, with_pip=False)
    python = env_dir / "bin" / "python"
    # system_site_packages reaches the base interpreter's packages; where this test runs in a virtual
    # environment, the site-packages folders of its path are listed too, after the new environment's
    # own (the installed package comes first). A folder a .pth file lists is no site folder, so the .pth
    # files in it (the checkout's editable install) are not read, and the checkout's src/ is not listed.
    purelib = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], root).stdout.strip())
    outer = [p for p in sys.path if Path(p).name == "site-packages"]
    (purelib / "test_environment.pth").write_text("".join(f"{p}\n" for p in outer))
    _run([sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", wheel], root)

    elsewhere = root / "elsewhere"
    elsewhere.mkdir()
    return python, elsewhere


def test_installed_package_has_its_schema(installed):
    """The installed package is the one imported (not the source tree), and its schema gives apply's defaults
    and, with no config/config.yaml, the configuration the settings commands read."""
    python, elsewhere = installed
    out = _run([python, "-c", "import pipeline, pipeline.config as c; print(pipeline.__file__); "
                "print(c.defaults()['apply']['negative_mean_sigma']); print(c.load_config()['store']['path'])"],
               elsewhere).stdout.splitlines()
    module, sigma, store = out
    assert Path(module).resolve().is_relative_to(python.parents[1].resolve()), module
    assert float(sigma) == defaults()["apply"]["negative_mean_sigma"]
    assert store == defaults()["store"]["path"]


@pytest.mark.parametrize("command", ["validate", "compare"])
def test_installed_commands_start(installed, command):
    python, elsewhere = installed
    out = _run([python, "-m", "pipeline", command, "--help"], elsewhere).stdout
    assert out.startswith("usage:") and command in out.splitlines()[0], out


def test_installed_package_has_the_default_cameras_data(installed):
    """The simulator's default camera reads the real camera's measured data (package data in
    pipeline/simulate/data) from the installed package: the far lens's green response at its measured
    peak (1 at 540 nm in the authors' file) and the close lens's red roll-off a0 (0.99726 as stored), and
    the licence text travels with them."""
    python, elsewhere = installed
    out = _run([python, "-c", "from importlib.resources import files; "
                "from pipeline.simulate.spectral import default_spectral_response as r; "
                "from pipeline.simulate.camera_data import authors_rolloff as a; "
                "print(float(r([540.0], 'far')['G'][0])); print(a('close', 'air', 'R')[0]); "
                "print(files('pipeline.simulate').joinpath('data', 'LICENSE-insta360.txt').read_text()[:11])"],
               elsewhere).stdout.splitlines()
    assert float(out[0]) == pytest.approx(1.0, abs=1e-9)
    assert float(out[1]) == pytest.approx(0.99726, abs=1e-5)
    assert out[2] == "MIT License"

"""Running the repository's Snakefile as a user would, and reading Snakemake's dry-run job list.

Shared by the workflow test files (each test runs snakemake in its own working
directory, results/ there).
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")
LENSES = ("far", "close")
#: the tutorial whose commands the workflow tests run, and the dataset folder its commands name (relative to
#: the folder they run in; made absolute so that the workflow records the same path as the tests' own runs)
TUTORIAL = REPO / "docs" / "tutorial.md"
TUTORIAL_DATASET = "data/tutorial"
#: the environment of the runs that do not go to SLURM: Snakemake loads its SLURM executor plugin at every start,
#: and the plugin asks ``scontrol show config`` for a help text; where the SLURM client is installed but no
#: controller answers, scontrol waits out its message timeout (10 s of wall time per Snakemake start, no CPU).
#: A local run has no use for the answer, so the client is given an empty configuration, which it refuses at
#: once; the runs through profiles/slurm keep the real one.
LOCAL_ENV = {**os.environ, "SLURM_CONF": os.devnull}


def tutorial_commands() -> list[list[str]]:
    """The shell commands of the tutorial's ```bash blocks, in order, each as its argv; a command that is
    neither ``python -m pipeline`` nor ``snakemake`` fails the test (the tutorial would say what no test runs)."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", TUTORIAL.read_text(), re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            argv = shlex.split(line)
            if argv[:3] != ["python", "-m", "pipeline"] and argv[0] != "snakemake":
                raise AssertionError(f"{TUTORIAL}: a command the test cannot run: {line}")
            commands.append(argv)
    return commands


def run_tutorial_command(argv: list[str], workdir: Path) -> subprocess.CompletedProcess:
    """One tutorial command in ``workdir``: this interpreter for ``python``, the repository's Snakefile for
    ``snakemake``, the dataset folder inside ``workdir``; fails with its stderr when it exits non-zero."""
    argv = [a.replace(TUTORIAL_DATASET, str(workdir / TUTORIAL_DATASET)) for a in argv]
    if argv[0] == "python":
        argv = [sys.executable, *argv[1:]]
    else:
        argv = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), *argv[1:]]
    proc = subprocess.run(argv, cwd=workdir, capture_output=True, text=True, timeout=600, env=LOCAL_ENV)
    if proc.returncode != 0:
        raise AssertionError(f"tutorial command failed: {shlex.join(argv)}\n{proc.stderr[-3000:]}")
    return proc


def snakemake(workdir: Path, dataset: Path, *args: str, check: bool = True,
              targets: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """Run the workflow in ``workdir`` on ``dataset``; ``targets`` (output files) before the options, which
    --config would otherwise swallow."""
    cmd = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), *targets, "--cores", "2", "--config", f"dataset={dataset}",
           *args]
    env = None if "--profile" in args else LOCAL_ENV
    proc = subprocess.run(cmd, cwd=workdir, capture_output=True, text=True, timeout=600, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake failed:\n{proc.stderr[-3000:]}")
    return proc


def planned_jobs(workdir: Path, dataset: Path, *args: str) -> dict[str, int]:
    """Jobs a dry run would execute, counted per rule (the job list)."""
    proc = snakemake(workdir, dataset, "-n", "--quiet", "rules", *args)
    jobs = {}
    for line in proc.stdout.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[1].isdigit() and parts[0] not in ("total", "job"):
            jobs[parts[0]] = int(parts[1])
    return jobs


def planned_rules(workdir: Path, dataset: Path, *args: str) -> set[str]:
    """Rules a dry run would execute."""
    return set(planned_jobs(workdir, dataset, *args))

"""Running the repository's Snakefile as a user would, and reading Snakemake's dry-run job list.

Shared by the workflow test files (each test runs snakemake in its own working
directory, results/ there).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")
LENSES = ("far", "close")


def snakemake(workdir: Path, dataset: Path, *args: str, check: bool = True,
              targets: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """Run the workflow in ``workdir`` on ``dataset``; ``targets`` (output files) before the options, which
    --config would otherwise swallow."""
    cmd = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), *targets, "--cores", "2", "--config", f"dataset={dataset}",
           *args]
    proc = subprocess.run(cmd, cwd=workdir, capture_output=True, text=True, timeout=600)
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

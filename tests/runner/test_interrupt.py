"""Ctrl-C during ``snakemake --cores 2`` ends the run as an interrupt: exit 130, one line, no traceback,
no failed-run report and no entry in the error history; the same command then resumes the run. SIGTERM
(a scheduler's, to Snakemake alone) alike with 143, once the running jobs have finished."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from workflow_runs import LOCAL_ENV, REPO, SNAKEMAKE

#: seconds the test waits for the first job's log (the start-up check and the DAG come first)
JOB_START_TIMEOUT_S = 60
#: seconds the interrupted run may take to cancel its jobs and end
STOP_TIMEOUT_S = 60


def _command(dataset: Path) -> list[str]:
    # the dark and linearity stages of both lenses: jobs still run or wait when the signal comes
    targets = [f"results/{stage}/{lens}.nc" for stage in ("dark", "linearity") for lens in ("far", "close")]
    return [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), *targets, "--cores", "2", "--config", f"dataset={dataset}"]


def _ledger(workdir: Path) -> list[Path]:
    return sorted((workdir / "results" / "diagnostics" / "ledger").glob("*"))


@pytest.mark.parametrize("signum, to_group", [(signal.SIGINT, True), (signal.SIGTERM, False)],
                         ids=["Ctrl-C", "SIGTERM"])
def test_ctrl_c_ends_the_run_as_an_interrupt_and_the_rerun_resumes(make_dataset, tmp_path, signum, to_group):
    dataset, _ = make_dataset()
    workdir = tmp_path / "work"
    workdir.mkdir()
    ledger_before = _ledger(workdir)
    # a session of its own: the signal goes to Snakemake and its jobs, as a terminal's Ctrl-C does
    proc = subprocess.Popen(_command(dataset), cwd=workdir, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, env=LOCAL_ENV)
    logs = workdir / "results" / "logs"
    deadline = time.monotonic() + JOB_START_TIMEOUT_S
    while not any(logs.glob("*/*.log")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert proc.poll() is None, f"the run ended before a job started:\n{proc.communicate()[1][-3000:]}"
    (os.killpg if to_group else os.kill)(proc.pid, signum)
    out, err = proc.communicate(timeout=STOP_TIMEOUT_S)
    assert proc.returncode == 128 + signum, err[-3000:]
    assert "Traceback" not in out + err, err[-3000:]
    ours = [line for line in err.splitlines() if line.startswith(f"interrupted ({signal.Signals(signum).name})")]
    assert len(ours) == 1, err[-3000:]
    assert "Jobs failed" not in err and not (workdir / "results" / "failed_run").exists()
    assert _ledger(workdir) == ledger_before
    resumed = subprocess.run(_command(dataset), cwd=workdir, capture_output=True, text=True, timeout=600, env=LOCAL_ENV)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert all((workdir / "results" / stage / f"{lens}.nc").is_file()
               for stage in ("dark", "linearity") for lens in ("far", "close"))


def test_ctrl_c_during_validate_is_one_line_and_130(tmp_path, monkeypatch, capsys):
    """Ctrl-C while ``python -m pipeline validate`` reads the frames' tags: exit 130 and the one line
    'interrupted', no traceback (the command line's other commands alike: one handler in main)."""
    import pipeline.io.validation
    from pipeline.cli import EXIT_INTERRUPTED, main

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline.io.validation, "inspect_dataset", interrupted)
    capsys.readouterr()
    assert main(["validate", str(tmp_path)]) == EXIT_INTERRUPTED == 130
    captured = capsys.readouterr()
    assert captured.err == "interrupted\n" and captured.out == ""

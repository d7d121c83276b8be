"""What `python -m pipeline simulate --scale tiny` writes by default calibrates end to end through the
workflow, field hour included, and new field data reruns the field job only; a run killed mid-stage
restarts to completion."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time

import pandas as pd
import xarray as xr

from pipeline.artefact import ARTEFACT_VERSIONS, read_artefact
import pytest

from report_browser import browse
from report_browser import (  # noqa: F401  (the browser's tests, collected here on the default run's report)
    test_each_check_finds_its_fault_on_a_page_made_to_fail, test_every_expected_section_is_present_with_content,
    test_every_image_is_decoded_and_non_empty, test_no_console_errors_or_failed_requests,
    test_no_horizontal_overflow_at_1280_px, test_screenshot_is_a_non_blank_png, test_the_browser_leaves_no_process_behind)
from helpers import assert_g_theta_within_a_band_pixel
from workflow_runs import LENSES, REPO, SNAKEMAKE, planned_rules, snakemake


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    """What `python -m pipeline simulate --scale tiny` writes by default (every experiment, the command line's
    default seed), run through the workflow once: (work folder, dataset, the run's output)."""
    tmp_path = tmp_path_factory.mktemp("default-run")
    dataset = tmp_path / "tiny"
    proc = subprocess.run([sys.executable, "-m", "pipeline", "simulate", "--out", str(dataset), "--scale", "tiny",
                           "--no-progress"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return tmp_path, dataset, snakemake(tmp_path, dataset)


@pytest.fixture(scope="module")
def page(default_run, tmp_path_factory):
    """What headless Chromium saw of the default run's report (tests/report_browser.py)."""
    return browse(default_run[0] / "results/report/index.html", tmp_path_factory.mktemp("browser"))


def test_the_default_runs_geometry_is_within_a_band_pixel_of_the_truth(default_run):
    """The geometry the workflow fitted to the command line's default tiny simulation (tests/helpers.py)."""
    tmp_path, dataset, _ = default_run
    assert_g_theta_within_a_band_pixel(dataset, {lens: tmp_path / f"results/geometry/{lens}.nc" for lens in LENSES})


def test_the_default_tiny_simulation_runs_through_the_whole_workflow(default_run):
    """What `python -m pipeline simulate --scale tiny` writes by default calibrates end to end."""
    tmp_path, dataset, run = default_run
    for stage in ("dark", "linearity", "geometry", "rolloff", "spectral", "absolute", "immersion"):
        for lens in LENSES:
            with xr.open_dataset(tmp_path / f"results/{stage}/{lens}.nc") as ds:
                assert ds.attrs["artefact"] == stage
    assert (tmp_path / "results/report/index.html").exists()
    assert "Calibration report:" in run.stdout + run.stderr
    # the field hour: one job for the lens at the zenith, its section in the report, its row in the error history
    assert (tmp_path / "results/field/close.nc").exists() and not (tmp_path / "results/field/far.nc").exists()
    html = (tmp_path / "results/report/index.html").read_text()
    assert 'id="field-close"' in html and "MUPD" in html
    # the report has an analogue of each of the paper's Figs. 2-10 (the captions say which), and every
    # figure is also a PNG for snakemake --report
    captions = re.findall(r"<figcaption>(.*?)</figcaption>", html, re.S)
    for n in range(2, 11):
        assert any(re.search(rf"Fig\. {n}(?!\d)", c) for c in captions), f"no analogue of Fig. {n}"
    assert len(list((tmp_path / "results/report/figures").glob("*.png"))) == len(captions)
    history = pd.read_csv(tmp_path / "results/diagnostics/error_history.csv")
    assert "field" in set(history["experiment"])
    # new field data only: the field job, the diagnostics and the report rerun, no lab stage
    from pipeline.dataset import write_md5sums

    reference = dataset / "field/reference_radiometer.csv"
    lines = reference.read_text().splitlines()
    reference.write_text("\n".join(lines[:-1]) + "\n")       # the last reading dropped
    write_md5sums(dataset)
    assert planned_rules(tmp_path, dataset) == {"field", "diagnostics", "report", "all"}


def test_a_run_killed_mid_stage_restarts_to_completion_without_a_corrupt_artefact(make_dataset, tmp_path):
    """SIGKILL of snakemake's whole process group (no clean-up: as a lost node or a power cut) while the
    linearity job runs; the restart needs ``--unlock`` (the lock stays behind), not ``--rerun-incomplete``:
    the artefacts are renamed into place only when complete, so the killed job left no output to distrust.
    One lens (dark, then linearity) keeps it cheap: each snakemake start costs about 4.5 s of CPU."""
    src, _ = make_dataset([("dark_current", {}), ("shutter_offset", {})], seed=31)
    dataset = tmp_path / "dataset"
    shutil.copytree(src, dataset)
    lens = "far"
    targets = [f"results/{stage}/{lens}.nc" for stage in ("dark", "linearity")]
    cmd = [str(SNAKEMAKE), *targets, "-s", str(REPO / "Snakefile"), "--cores", "2", "--config", f"dataset={dataset}"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    started = tmp_path / "results/logs/linearity"
    try:
        while proc.poll() is None and not (started.is_dir() and any(started.iterdir())):
            time.sleep(0.05)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, "snakemake ended before the linearity job started"
    assert not list((tmp_path / "results/linearity").glob("*.nc")), "the linearity job ended before the kill"
    dark_written = (tmp_path / f"results/dark/{lens}.nc").stat().st_mtime_ns
    # the killed run's lock is still there (the same command would stop: 'Directory cannot be locked')
    # and its job's output is marked incomplete
    assert list((tmp_path / ".snakemake/locks").glob("*")) and list((tmp_path / ".snakemake/incomplete").glob("*"))
    subprocess.run([*cmd, "--unlock"], cwd=tmp_path, check=True, capture_output=True, timeout=600)
    restart = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert restart.returncode == 0, restart.stderr[-3000:]
    assert "incomplete" not in restart.stderr.lower()
    # only the interrupted job ran again; every artefact whole, no temporary file left behind
    assert (tmp_path / f"results/dark/{lens}.nc").stat().st_mtime_ns == dark_written
    for stage in ("dark", "linearity"):
        ds = read_artefact(tmp_path / f"results/{stage}/{lens}.nc", stage)
        assert int(ds.attrs["artefact_version"]) == ARTEFACT_VERSIONS[stage] and len(ds.data_vars) > 10
    assert not [p for p in (tmp_path / "results").rglob("*") if p.name.endswith(".tmp")]
    assert not list((tmp_path / ".snakemake/incomplete").glob("*"))

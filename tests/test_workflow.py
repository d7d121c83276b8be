"""The Snakemake workflow end to end on a tiny simulated dataset, run as a user would: what it writes,
what it reruns, and how it stops on bad input.

Each test runs snakemake in its own working directory (results/ there), with
the repository's Snakefile.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pandas as pd
import pytest
import xarray as xr
import yaml

from pipeline.artefact import read_artefact
from workflow_runs import LENSES, REPO, SNAKEMAKE, planned_jobs, planned_rules, snakemake


@pytest.fixture(scope="module")
def run(make_dataset, tmp_path_factory):
    src, truth = make_dataset([("dark_current", {}), ("shutter_offset", {})], seed=31)
    dataset = tmp_path_factory.mktemp("data") / "dataset"
    shutil.copytree(src, dataset)
    workdir = tmp_path_factory.mktemp("work")
    snakemake(workdir, dataset)
    return workdir, dataset


def test_artefacts_and_report(run):
    workdir, _ = run
    for stage, version in (("dark", 1), ("linearity", 2)):
        for lens in LENSES:
            ds = xr.open_dataset(workdir / f"results/{stage}/{lens}.nc")
            assert ds.attrs["artefact"] == stage
            assert int(ds.attrs["artefact_version"]) == version
            assert len(ds.attrs["config_sha256"]) == 64
            assert ds.attrs["model_effects"] == "dark_current,hot_pixels"
            ds.close()
    html = (workdir / "results/report/index.html").read_text()
    assert "shutter_offset" in html
    ranked = pd.read_csv(workdir / "results/diagnostics/missing_effects.csv")
    for column in ("rank", "effect", "experiment", "evidence", "significant", "explained_fraction",
                   "amplitude", "amplitude_low", "amplitude_high", "units"):
        assert column in ranked
    assert ranked.iloc[0]["effect"] == "shutter_offset" and bool(ranked.iloc[0]["significant"])
    history = pd.read_csv(workdir / "results/diagnostics/error_history.csv")
    assert set(history.columns) >= {"run_time", "experiment", "model_effects", "rms_z"}
    assert set(history["experiment"]) == {"dark", "linearity"}


def test_nothing_to_do_when_nothing_changed(run):
    workdir, dataset = run
    assert planned_rules(workdir, dataset) == set()


def test_each_lens_is_its_own_job_and_the_run_ends_with_a_summary(run, tmp_path):
    workdir, dataset = run
    jobs = planned_jobs(workdir, dataset, "--forcerun", "dark")
    assert jobs["dark"] == 2 and jobs["linearity"] == 2      # one job per lens: --cores 2 runs both at once
    log = (workdir / "results/logs/dark/far.log").read_text()
    assert "dark far: wrote" in log
    with xr.open_dataset(workdir / "results/linearity/far.nc") as ds:
        hashed = json.loads(ds.attrs["input_sha256"])
    # every input by path relative to the dataset or the results folder, the upstream artefact included
    assert {"dataset.yaml", "MD5SUMS", "dark/far.nc"} <= set(hashed)
    frames = pd.read_csv(dataset / "linearity/frames.csv")
    mine = frames["lens"].isin(["far", "both"]) & (frames["kind"] == "signal")
    assert {f"linearity/{f}" for f in frames.loc[mine, "file"]} <= set(hashed)
    assert not {f"linearity/{f}" for f in frames.loc[~frames["lens"].isin(["far", "both"]), "file"]} & set(hashed)
    assert not any(Path(k).is_absolute() for k in hashed)


def test_a_mistyped_dataset_path_stops_even_with_earlier_results(run):
    workdir, dataset = run
    mistyped = dataset.parent / "datset"
    proc = snakemake(workdir, mistyped, check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert [line for line in out.splitlines() if line.startswith("error:")] == [
        f"error: {mistyped}: dataset folder not found (check the path; to simulate a dataset into it, "
        "add --config simulate=true)"]
    assert "Nothing to be done" not in out and not mistyped.exists()


def test_a_missing_dataset_is_never_simulated_unless_asked(tmp_path):
    missing = tmp_path / "mounts" / "calib2024"
    proc = snakemake(tmp_path, missing, check=False)
    assert proc.returncode != 0 and "dataset folder not found" in proc.stderr
    assert not missing.exists() and not (tmp_path / "results").exists()
    # asked for explicitly: the simulation is planned (dry run: nothing is written)
    assert "simulate_dataset" in planned_rules(tmp_path, missing, "--config", f"dataset={missing}", "simulate=true")
    assert not missing.exists()


def test_editing_the_chessboard_reruns_nothing_without_geometry(run):
    workdir, dataset = run
    meta_path = dataset / "dataset.yaml"
    original = meta_path.read_text()
    meta = yaml.safe_load(original)
    meta["chessboard"]["square_mm"]["air"] = float(meta["chessboard"]["square_mm"]["air"]) + 1.0
    meta["description"] = "edited"
    meta_path.write_text(yaml.safe_dump(meta))
    try:
        # dark and linearity read neither the chessboard nor the description
        assert planned_rules(workdir, dataset) == set()
    finally:
        meta_path.write_text(original)


def test_adding_the_missing_effect_lowers_the_error(run):
    workdir, dataset = run
    snakemake(workdir, dataset, "--config", f"dataset={dataset}",
              "model={effects: [dark_current, hot_pixels, shutter_offset]}")
    history = pd.read_csv(workdir / "results/diagnostics/error_history.csv")
    lin = history[history["experiment"] == "linearity"]
    assert len(lin) >= 2
    assert lin["rms_z"].iloc[-1] < lin["rms_z"].iloc[0]
    assert lin["rms_z"].iloc[-1] < 1.5


def test_new_dark_frames_rerun_only_what_depends_on_them(run):
    workdir, dataset = run
    # replace one dark frame by a copy of another (same settings): dark and later stages rerun
    frames = pd.read_csv(dataset / "dark/frames.csv")
    a, b = dataset / "dark" / frames["file"].iloc[0], dataset / "dark" / frames["file"].iloc[1]
    shutil.copyfile(b, a)
    from pipeline.dataset import write_md5sums

    write_md5sums(dataset)
    assert planned_rules(workdir, dataset) == {"dark", "linearity", "diagnostics", "report", "all"}


def test_missing_file_stops_with_one_line(make_dataset, tmp_path):
    src, _ = make_dataset([], seed=32)
    dataset = tmp_path / "dataset"
    shutil.copytree(src, dataset)
    frames = pd.read_csv(dataset / "linearity/frames.csv")
    (dataset / "linearity" / frames["file"].iloc[3]).unlink()
    proc = snakemake(tmp_path, dataset, check=False)
    assert proc.returncode != 0
    errors = [line for line in (proc.stdout + proc.stderr).splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "linearity/frames.csv" in errors[0] and "does not exist" in errors[0]
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "results").exists()


def test_corrupt_frame_stops_the_stage_cleanly(make_dataset, tmp_path):
    src, _ = make_dataset([], seed=33)
    dataset = tmp_path / "dataset"
    shutil.copytree(src, dataset)
    frames = pd.read_csv(dataset / "dark/frames.csv")
    victim = dataset / "dark" / frames["file"].iloc[2]
    data = bytearray(victim.read_bytes())
    data[-5000] ^= 0xFF          # pixel bytes change: tags still read, checksum does not match
    victim.write_bytes(bytes(data))
    proc = snakemake(tmp_path, dataset, check=False)
    assert proc.returncode != 0
    assert f"error: {victim}: checksum mismatch" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not list((tmp_path / "results").glob("dark/*.nc"))


def test_absent_experiment_is_skipped_and_reported(make_dataset, tmp_path):
    src, _ = make_dataset([], seed=34)
    dataset = tmp_path / "dataset"
    shutil.copytree(src, dataset, ignore=shutil.ignore_patterns("linearity"))
    lines = [line for line in (dataset / "MD5SUMS").read_text().splitlines() if "linearity/" not in line]
    (dataset / "MD5SUMS").write_text("\n".join(lines) + "\n")
    snakemake(tmp_path, dataset)
    assert (tmp_path / "results/dark/far.nc").exists()
    assert not (tmp_path / "results/linearity").exists()
    html = (tmp_path / "results/report/index.html").read_text()
    assert "the dataset has no linearity/ folder" in html


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
    for stage, version in (("dark", 1), ("linearity", 2)):
        ds = read_artefact(tmp_path / f"results/{stage}/{lens}.nc", stage)
        assert int(ds.attrs["artefact_version"]) == version and len(ds.data_vars) > 10
    assert not [p for p in (tmp_path / "results").rglob("*") if p.name.endswith(".tmp")]
    assert not list((tmp_path / ".snakemake/incomplete").glob("*"))

"""The Snakemake workflow end to end on a tiny simulated dataset, run as a user would.

Each test runs snakemake in its own working directory (results/ there), with
the repository's Snakefile.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import xarray as xr

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")
LENSES = ("far", "close")


def snakemake(workdir: Path, dataset: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    cmd = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), "--cores", "2", "--config", f"dataset={dataset}",
           *args]
    proc = subprocess.run(cmd, cwd=workdir, capture_output=True, text=True, timeout=600)
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake failed:\n{proc.stderr[-3000:]}")
    return proc


def planned_rules(workdir: Path, dataset: Path) -> set[str]:
    """Rules a dry run would execute (the job list)."""
    proc = snakemake(workdir, dataset, "-n", "--quiet", "rules")
    rules = set()
    for line in proc.stdout.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[1].isdigit() and parts[0] not in ("total", "job"):
            rules.add(parts[0])
    return rules


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
    for stage in ("dark", "linearity"):
        for lens in LENSES:
            ds = xr.open_dataset(workdir / f"results/{stage}/{lens}.nc")
            assert ds.attrs["artefact"] == stage
            assert int(ds.attrs["artefact_version"]) == 1
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


@pytest.fixture(scope="module")
def radiometric_run(tmp_path_factory):
    """The geometry and radiometric-chain experiments at the small scale (the geometry
    calibration needs more than the tiny scale's 64-pixel band images)."""
    from pipeline.simulate import simulate_dataset

    dataset = tmp_path_factory.mktemp("radiometric") / "dataset"
    simulate_dataset(dataset, scale="small", seed=41,
                     experiments=("geometry", "rolloff", "spectral", "absolute", "immersion"), progress=False)
    workdir = tmp_path_factory.mktemp("work")
    snakemake(workdir, dataset)
    return workdir, dataset


def test_radiometric_chain_runs_and_reruns_only_what_changed(radiometric_run):
    workdir, dataset = radiometric_run
    for stage in ("geometry", "rolloff", "spectral", "absolute", "immersion"):
        for lens in LENSES:
            with xr.open_dataset(workdir / f"results/{stage}/{lens}.nc") as ds:
                assert ds.attrs["artefact"] == stage
    html = (workdir / "results/report/index.html").read_text()
    assert "Immersion factor" in html and "Absolute spectral radiance" in html
    assert planned_rules(workdir, dataset) == set()

    from pipeline.dataset import write_md5sums

    # new roll-off data: only the roll-off stage and what reads it
    frames = pd.read_csv(dataset / "rolloff/frames.csv")
    shutil.copyfile(dataset / "rolloff" / frames["file"].iloc[1], dataset / "rolloff" / frames["file"].iloc[0])
    write_md5sums(dataset)
    assert planned_rules(workdir, dataset) == {"rolloff", "diagnostics", "report", "all"}

    # a new photodiode reading: the spectral response and everything computed from it
    photodiode = dataset / "spectral/photodiode.csv"
    table = pd.read_csv(photodiode)
    table.loc[0, "signal"] *= 1.001
    table.to_csv(photodiode, index=False)
    write_md5sums(dataset)
    assert planned_rules(workdir, dataset) == {"rolloff", "spectral", "absolute", "immersion", "diagnostics",
                                               "report", "all"}

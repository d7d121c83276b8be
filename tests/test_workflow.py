"""The Snakemake workflow end to end on a tiny simulated dataset, run as a user would.

Each test runs snakemake in its own working directory (results/ there), with
the repository's Snakefile.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import xarray as xr
import yaml

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


def test_editing_the_chessboard_reruns_geometry_and_what_depends_on_it(radiometric_run):
    workdir, dataset = radiometric_run
    meta_path = dataset / "dataset.yaml"
    original = meta_path.read_text()
    meta = yaml.safe_load(original)
    meta["chessboard"]["square_mm"]["air"] = float(meta["chessboard"]["square_mm"]["air"]) * 1.01
    meta_path.write_text(yaml.safe_dump(meta))
    try:
        jobs = planned_jobs(workdir, dataset)
        assert jobs["geometry"] == 2
        assert set(jobs) >= {"geometry", "rolloff", "spectral", "absolute", "immersion", "diagnostics", "report"}
    finally:
        meta_path.write_text(original)


def test_downstream_stages_on_the_fitted_geometry_recover_the_truth(radiometric_run):
    """The radiometric chain run by the workflow uses the geometry the geometry stage fitted
    (not the simulator's true maps); the results still match the truth. Tolerances: those of
    the stage tests on the true geometry (tests/test_spectral.py, test_absolute.py,
    test_immersion.py, test_rolloff.py) widened only for roll-off, where an error of the fitted
    theta map (about 0.3 degree at this scale, more in water where the board fits are 1.3-1.8 px)
    times the slope of g near 70-80 degrees (up to about 1 % per degree) adds up to 1 % in air
    and 2 % in water to the 0.2 % stated uncertainty of the fit."""
    from pipeline.radiometry.rolloff import evaluate_rolloff
    from pipeline.simulate import truth_dir_for

    workdir, dataset = radiometric_run
    truth = yaml.safe_load((truth_dir_for(dataset) / "truth.yaml").read_text())["experiments_truth"]
    for lens in LENSES:
        with xr.open_dataset(workdir / f"results/geometry/{lens}.nc") as geo:
            assert "theta_deg" in geo          # maps fitted by the pipeline, not written by a test
        spectral = xr.open_dataset(workdir / f"results/spectral/{lens}.nc")
        absolute = xr.open_dataset(workdir / f"results/absolute/{lens}.nc")
        immersion = xr.open_dataset(workdir / f"results/immersion/{lens}.nc")
        rolloff = xr.open_dataset(workdir / f"results/rolloff/{lens}.nc")
        for band in "RGB":
            s = spectral.sel(band=band)
            err = float(s["effective_wavelength_nm"]) - truth["spectral"]["bands"][band]["effective_wavelength_nm"]
            assert abs(err) < 2.0 and abs(err) < 5 * float(s["effective_wavelength_nm_sigma"]) + 0.05, (lens, band, err)
            rel = float(absolute["inverse_responsivity"].sel(band=band)) / \
                truth["absolute"]["bands"][band]["inverse_responsivity"] - 1
            assert abs(rel) < 0.02, (lens, band, rel)
            # immersion: the error within 4 of its stated standard uncertainty (0.002 to 0.004 here: the
            # log-linear fit over 11 heights of 5 frames, and the in-air mask mean) and under 1.2 % of I
            i_err = float(immersion["immersion_factor"].sel(band=band)) - truth["immersion"]["immersion_factor"][band]
            i_sigma = float(immersion["immersion_factor_sigma"].sel(band=band))
            assert abs(i_err) < 4 * i_sigma and abs(i_err) < 0.02, (lens, band, i_err, i_sigma)
            for medium, top_deg, tol in (("air", 80.0, 0.015), ("water", 70.0, 0.025)):
                theta = np.arange(0.0, top_deg + 1.0, 5.0)
                fitted = evaluate_rolloff(rolloff["rolloff_coefficients"].sel(medium=medium, band=band).values, theta)
                true = evaluate_rolloff(np.asarray(truth["rolloff"]["rolloff_coefficients"][medium][band]), theta)
                assert np.abs(fitted / true - 1).max() < tol, (lens, medium, band)
        for ds in (spectral, absolute, immersion, rolloff):
            ds.close()


def test_the_default_tiny_simulation_runs_through_the_whole_workflow(tmp_path):
    """What `python -m pipeline simulate --scale tiny` writes by default (every experiment,
    the command line's default seed) calibrates end to end."""
    dataset = tmp_path / "tiny"
    proc = subprocess.run([sys.executable, "-m", "pipeline", "simulate", "--out", str(dataset), "--scale", "tiny",
                           "--no-progress"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    run = snakemake(tmp_path, dataset)
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
    history = pd.read_csv(tmp_path / "results/diagnostics/error_history.csv")
    assert "field" in set(history["experiment"])
    # new field data only: the field job, the diagnostics and the report rerun, no lab stage
    from pipeline.dataset import write_md5sums

    reference = dataset / "field/reference_radiometer.csv"
    lines = reference.read_text().splitlines()
    reference.write_text("\n".join(lines[:-1]) + "\n")       # the last reading dropped
    write_md5sums(dataset)
    assert planned_rules(tmp_path, dataset) == {"field", "diagnostics", "report", "all"}

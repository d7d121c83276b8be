"""The Snakemake workflow end to end on a tiny simulated dataset, run as a user would: what it writes,
what it reruns, and how it stops on bad input.

Each test runs snakemake in its own working directory (results/ there), with
the repository's Snakefile.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np

import pandas as pd
import pytest
import xarray as xr
import yaml

from pipeline.io.artefact import ARTEFACT_VERSIONS
from workflow_runs import (
    LENSES,
    REPO,
    TUTORIAL_DATASET,
    planned_jobs,
    planned_rules,
    run_tutorial_command,
    snakemake,
    tutorial_commands,
)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The tutorial's first commands (docs/tutorial.md: simulate a tiny camera with dark current and a
    shutter offset that the default model lacks, run the workflow) in a fresh folder; its remaining
    commands run in :func:`test_the_tutorial_finds_the_missing_effect_and_the_error_falls`. The module's
    other tests use this run."""
    workdir = tmp_path_factory.mktemp("work")
    commands = tutorial_commands()
    first_diagnose = next(i for i, argv in enumerate(commands) if "diagnose" in argv)
    assert first_diagnose >= 2, commands          # simulate and run before the first diagnosis
    for argv in commands[:first_diagnose]:
        run_tutorial_command(argv, workdir)
    return workdir, workdir / TUTORIAL_DATASET


def test_artefacts_and_report(run):
    workdir, _ = run
    for stage in ("dark", "linearity"):
        for lens in LENSES:
            ds = xr.open_dataset(workdir / f"results/{stage}/{lens}.nc")
            assert ds.attrs["artefact"] == stage
            assert int(ds.attrs["artefact_version"]) == ARTEFACT_VERSIONS[stage]
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
    # the dark model against the linearity frames' unlit corners: the cross-experiment closure (pipeline.diagnostics.cross_closure)
    assert set(history["experiment"]) == {"dark", "linearity", "closure"}


def test_nothing_to_do_when_nothing_changed(run):
    workdir, dataset = run
    assert planned_rules(workdir, dataset) == set()


def test_snakemake_report_lists_the_figures_with_their_captions(run):
    """`snakemake --report` on the finished run: the zip holds every PNG of results/report/figures,
    and its HTML names each figure with the caption the calibration report gives it
    (figures.json) and the caption text of workflow/report/figure.rst."""
    import zipfile

    workdir, dataset = run
    figures = workdir / "results/report/figures"
    index = json.loads((figures / "figures.json").read_text(encoding="utf-8"))
    pngs = sorted(p.name for p in figures.glob("*.png"))
    assert pngs and sorted(f"{stem}.png" for stem in index) == pngs
    snakemake(workdir, dataset, "--report", "results/snakemake-report.zip")
    with zipfile.ZipFile(workdir / "results/snakemake-report.zip") as zf:
        names = zf.namelist()
        pages = "".join(zf.read(n).decode("utf-8", "replace") for n in names if n.endswith((".html", ".js")))
    for png in pngs:
        assert any(n.endswith("/" + png) for n in names), png
    assert "of the calibration report" in pages                 # workflow/report/figure.rst
    for entry in index.values():
        # the caption label, JSON-escaped in the report's data as json.dumps escapes it; the category its section
        assert json.dumps(entry["caption"])[1:-1] in pages, entry["caption"][:60]
        assert entry["category"] in pages


def slurm_unavailable() -> str | None:
    """Why the workflow cannot be sent to SLURM here, or None when a node is up."""
    if shutil.which("sinfo") is None:
        return "no SLURM client (sinfo); start the single-node cluster with scripts/slurm_single_node.sh"
    proc = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, timeout=30)
    states = proc.stdout.split()
    if proc.returncode != 0 or not {"idle", "mixed", "allocated"} & set(states):
        reason = (proc.stderr.strip().splitlines() or [f"node states {states}"])[-1]
        return f"no SLURM node up ({reason}); start one with scripts/slurm_single_node.sh"
    return None


def _sbatch_requests(out: str) -> dict[str, tuple[str, int, int]]:
    """From the run's log: SLURM job id -> (rule, threads, mem_mb) that Snakemake printed for the job."""
    declared = {}
    for block in re.split(r"\n(?=(?:local)?rule \w+:\n)", out):
        head = re.match(r"(?:local)?rule (\w+):", block)
        jobid = re.search(r"^\s+jobid: (\d+)$", block, re.M)
        if head and jobid:
            threads = re.search(r"^\s+threads: (\d+)$", block, re.M)   # printed only when more than 1
            mem = re.search(r"^\s+resources: .*\bmem_mb=(\d+)", block, re.M)
            declared[jobid.group(1)] = (head.group(1), int(threads.group(1)) if threads else 1,
                                        int(mem.group(1)))
    return {slurm: declared[job] for job, slurm in
            re.findall(r"Job (\d+) has been submitted with SLURM jobid (\d+)", out)}


def test_keep_going_finishes_the_independent_jobs_and_reports_the_failure(run, tmp_path):
    """One lens job fails on bad input that only the stage sees (a far-lens linearity frame whose bytes
    no longer match MD5SUMS, found while it decodes them): with --keep-going the close lens's job still
    finishes, the run exits non-zero, the failed job leaves no artefact, and the diagnostics and the
    report on what finished (results/failed_run/) name the failed stage and its error line. The
    rules' own report is not written, so the next run plans the failed job and what follows it.
    The dark artefacts of the module's run (same dataset) are copied in: only linearity runs."""
    workdir, src = run
    dataset = tmp_path / "dataset"
    shutil.copytree(src, dataset)
    frames = pd.read_csv(dataset / "linearity/frames.csv")
    victim = dataset / "linearity" / frames.loc[frames["lens"] == "far", "file"].iloc[0]
    data = bytearray(victim.read_bytes())
    data[-5000] ^= 0xFF
    victim.write_bytes(bytes(data))
    work = tmp_path / "work"
    (work / "results/dark").mkdir(parents=True)
    for lens in LENSES:
        shutil.copy2(workdir / f"results/dark/{lens}.nc", work / f"results/dark/{lens}.nc")
    proc = snakemake(work, dataset, "--keep-going", check=False)
    assert proc.returncode != 0
    assert f"error: {victim}: checksum mismatch" in proc.stderr and "Traceback" not in proc.stderr
    results = work / "results"
    assert (results / "linearity/close.nc").exists() and not (results / "linearity/far.nc").exists()
    assert not [p.name for p in (results / "linearity").iterdir() if p.name != "close.nc"]   # no partial file
    assert not (results / "report/index.html").exists() and not (results / "diagnostics/run_errors.csv").exists()
    assert f"  linearity: failed for lens far: {victim}: checksum mismatch" in proc.stderr
    failed = results / "failed_run"
    assert set(pd.read_csv(failed / "run_errors.csv")["experiment"]) == {"dark", "linearity", "closure"}
    html = (failed / "index.html").read_text()
    assert "This run failed: <b>linearity</b> failed for lens far: " in html and f"{victim}: checksum mismatch" in html
    assert planned_rules(work, dataset) == {"linearity", "diagnostics", "report", "all"}


@pytest.mark.slurm
def test_slurm_profile_writes_the_local_artefacts(run, tmp_path):
    """The dark and linearity jobs of both lenses sent to SLURM through profiles/slurm (the executor
    plugin, its squeue status query): each SLURM job asks for its rule's threads and memory, and the
    artefacts' variables are bit-identical to the local run's (the stages are deterministic: same frames,
    same configuration). Only the creation time and the upstream artefact's hash (which includes that
    time) differ among the attributes."""
    reason = slurm_unavailable()
    if reason:
        pytest.skip(reason)
    local, dataset = run
    targets = tuple(f"results/{stage}/{lens}.nc" for stage in ("dark", "linearity") for lens in LENSES)
    # the first status query 1 s after submission (the profile's default suits a shared cluster)
    proc = snakemake(tmp_path, dataset, "--profile", str(REPO / "profiles/slurm"),
                     "--slurm-init-seconds-before-status-checks", "1", targets=targets)
    out = proc.stdout + proc.stderr
    requests = _sbatch_requests(out)
    assert sorted(rule for rule, _, _ in requests.values()) == ["dark", "dark", "linearity", "linearity"], out[-3000:]
    for slurm_id, (rule, threads, mem_mb) in requests.items():
        # squeue keeps a finished job for MinJobAge (300 s): what SLURM granted it
        got = subprocess.run(["squeue", "-h", "--states=all", "-j", slurm_id, "-o", "%C|%m|%T"],
                             capture_output=True, text=True, timeout=30).stdout.split("|")
        assert got == [str(threads), f"{mem_mb}M", "COMPLETED\n"], (rule, slurm_id, got)
    ignored = {"created", "input_sha256"}
    for target in targets:
        with xr.open_dataset(local / target) as a, xr.open_dataset(tmp_path / target) as b:
            kept_a, kept_b = ({k: v for k, v in ds.attrs.items() if k not in ignored} for ds in (a, b))
            assert kept_a == kept_b, target
            a.attrs, b.attrs = {}, {}
            xr.testing.assert_identical(a, b)     # names, dimensions, coordinates, values, variables' attributes
            for name in a.variables:              # and bit for bit
                assert np.asarray(a[name].values).tobytes() == np.asarray(b[name].values).tobytes(), (target, name)


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


def test_closure_table(run):
    """results/closure/residuals.nc holds every measurement with its prediction, residual, noise and
    covariates (CF units).

    Against the simulator: every dark frame is there (65 frames x 2 lenses x 3 bands, counted from the
    dataset's frames.csv); the dark model is complete (dark_current and hot_pixels are in it), so each dark
    table's chi2 lies within 4 standard deviations sqrt(2 dof) of its dof; the linearity setting residuals
    lean as a shutter offset of the truth's sign does (the shortest exposures of each exposure sweep
    above the longest, by over 3 standard errors of the difference of means). CPU under 1 s (reads files)."""
    workdir, dataset = run
    truth = yaml.safe_load((dataset.parent / f"{dataset.name}.truth" / "truth.yaml").read_text())
    with xr.open_dataset(workdir / "results/closure/residuals.nc") as ds:
        assert ds.attrs["artefact"] == "closure" and int(ds.attrs["artefact_version"]) == ARTEFACT_VERSIONS["closure"]
        for name, var in ds.data_vars.items():
            assert var.attrs.get("long_name"), name
            if var.dtype.kind == "f" and name not in ("value", "prediction", "residual", "sigma"):
                assert var.attrs.get("units"), name
        table = ds.to_dataframe()
    n_dark_frames = len(pd.read_csv(dataset / "dark/frames.csv"))
    dark_frames = table[(table["experiment"] == "dark") & (table["level"] == "frame")]
    assert len(dark_frames) == n_dark_frames * len(LENSES) * 3
    tests = pd.read_csv(workdir / "results/diagnostics/residual_tests.csv")
    for _, t in tests[tests["experiment"] == "dark"].iterrows():
        chi2 = float((table.loc[(table["experiment"] == "dark") & (table["level"] == t["level"]), "z"] ** 2).sum())
        assert abs(chi2 - t["dof"]) < 4 * np.sqrt(2 * t["dof"]), (t["level"], chi2, t["dof"])
    lin = table[(table["experiment"] == "linearity") & (table["level"] == "setting") & (table["sweep"] == "exposure")]
    short = lin[lin["exposure_s"] == lin["exposure_s"].min()]["z"]
    long = lin[lin["exposure_s"] == lin["exposure_s"].max()]["z"]
    offset = truth["effects"]["shutter_offset"]["offset_s"]
    lean = short.mean() - long.mean()
    assert np.sign(lean) == np.sign(offset) and abs(lean) > 3 * np.sqrt(1 / len(short) + 1 / len(long)), lean


def test_the_tutorial_finds_the_missing_effect_and_the_error_falls(run):
    """The rest of docs/tutorial.md on the module's run: `diagnose` names the hidden shutter offset, with an
    interval that holds the simulator's value, and the line that adds it; the rerun with it in the model
    brings the linearity to the noise floor, 1 + 2 sqrt(2 / dof) for rms_z^2 = chi2/dof whose spread is
    sqrt(2 / dof) (4 of those, one-sided), from above it; the second `diagnose` has no finding and shows
    the fall in its error history. CPU: the module's run and this test together 86 s (user + sys, 2026-12-02),
    against 77 s for the run and the rerun test this one replaces (the same rerun of dark, linearity,
    diagnostics and report, plus two `diagnose` commands and the command-line simulation)."""
    workdir, dataset = run
    truth = yaml.safe_load((dataset.parent / f"{dataset.name}.truth" / "truth.yaml").read_text())
    offset = truth["effects"]["shutter_offset"]["offset_s"]
    commands = tutorial_commands()
    first_diagnose = next(i for i, argv in enumerate(commands) if "diagnose" in argv)
    outputs = [run_tutorial_command(argv, workdir).stdout for argv in commands[first_diagnose:]]

    finding = [line for line in outputs[0].splitlines() if "as a shutter_offset of" in line]
    assert len(finding) == 1 and "add `shutter_offset` to model.effects" in finding[0], outputs[0]
    low, high = (float(v) for v in re.search(r"95 % interval (\S+) s to (\S+) s", finding[0]).groups())
    assert low <= offset <= high, (low, offset, high)
    assert "shutter_offset: true exposure = nominal + constant" in outputs[0]

    history = pd.read_csv(workdir / "results/diagnostics/error_history.csv")
    lin = history[history["experiment"] == "linearity"]
    floor = 1.0 + 2.0 * np.sqrt(2.0 / lin["dof"].to_numpy())
    assert len(lin) == 2 and lin["rms_z"].iloc[0] > floor[0] and lin["rms_z"].iloc[-1] < floor[-1], lin
    assert "shutter_offset" in lin["model_effects"].iloc[-1]
    assert "Findings:\n  none:" in outputs[-1], outputs[-1]
    assert re.search(r"linearity +\d\.\d\d \[dark_current hot_pixels\] -> \d\.\d\d \[dark_current hot_pixels "
                     r"shutter_offset\]", outputs[-1]), outputs[-1]


def test_new_dark_frames_rerun_only_what_depends_on_them(run):
    workdir, dataset = run
    # replace one dark frame by a copy of another (same settings): dark and later stages rerun
    frames = pd.read_csv(dataset / "dark/frames.csv")
    a, b = dataset / "dark" / frames["file"].iloc[0], dataset / "dark" / frames["file"].iloc[1]
    shutil.copyfile(b, a)
    from pipeline.io.dataset import write_md5sums

    write_md5sums(dataset)
    assert planned_rules(workdir, dataset) == {"dark", "linearity", "diagnostics", "report", "all"}


def test_missing_file_stops_with_one_line(make_dataset, tmp_path):
    src, _ = make_dataset()   # the session's default tiny dataset, copied before it is damaged
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
    src, _ = make_dataset()   # the session's default tiny dataset, copied before it is damaged
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
    src, _ = make_dataset()   # the session's default tiny dataset, copied before it is damaged
    dataset = tmp_path / "dataset"
    shutil.copytree(src, dataset, ignore=shutil.ignore_patterns("linearity"))
    lines = [line for line in (dataset / "MD5SUMS").read_text().splitlines() if "linearity/" not in line]
    (dataset / "MD5SUMS").write_text("\n".join(lines) + "\n")
    snakemake(tmp_path, dataset)
    assert (tmp_path / "results/dark/far.nc").exists()
    assert not (tmp_path / "results/linearity").exists()
    html = (tmp_path / "results/report/index.html").read_text()
    assert "the dataset has no linearity/ folder" in html

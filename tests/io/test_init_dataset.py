"""`init-dataset`: a simulated dataset's raw files and a small lab log give back the same dataset.

The layout files (dataset.yaml, frames.csv, MD5SUMS) of a simulated dataset
are removed; what only the lab knows is written to a CSV lab log by the test;
init-dataset must lay the raw files out again so that the frames tables, the
lens regions and the stage artefacts equal the original's.
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tifffile
import xarray as xr

from pipeline import __version__
from pipeline.io.dataset import open_dataset
from pipeline.errors import InputError
from pipeline.scaffold import describe_result, init_dataset, propose_lens_regions
from pipeline.runner.workflow import run_stage
from pipeline.io.validation import validate_dataset

EXPERIMENTS = ("dark", "linearity")
LENSES = ("far", "close")
#: what only the lab knows, per experiment (the columns of the lab log)
LAB_COLUMNS = {"dark": ("temperature_c",), "linearity": ("lens", "kind", "sweep", "temperature_c")}


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, timeout=300)


def _frames(root: Path, experiment: str) -> pd.DataFrame:
    return pd.read_csv(root / experiment / "frames.csv", dtype=str, keep_default_na=False)


def _md5s(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.md5(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _raw_folder(original: Path, dest: Path, flat: bool) -> Path:
    """The original's raw files only: one sub-folder per experiment, or all in one folder."""
    for experiment in EXPERIMENTS:
        for path in sorted((original / experiment / "raw").iterdir()):
            target = dest / path.name if flat else dest / experiment / "raw" / path.name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, target)
    return dest


def _lab_log(original: Path, path: Path, with_experiment: bool) -> Path:
    """The lab's own notes: file name, (experiment,) and the columns the camera cannot know."""
    rows = []
    for experiment in EXPERIMENTS:
        for _, row in _frames(original, experiment).iterrows():
            entry = {"file": Path(row["file"]).name}
            if with_experiment:
                entry["experiment"] = experiment
            entry.update({c: row[c] for c in LAB_COLUMNS[experiment]})
            rows.append(entry)
    pd.DataFrame(rows).fillna("").to_csv(path, index=False)
    return path


@pytest.fixture(scope="module")
def original(make_dataset):
    root, _ = make_dataset()
    return root


@pytest.fixture(scope="module")
def scaffolded(original, tmp_path_factory):
    base = tmp_path_factory.mktemp("scaffold")
    raw = _raw_folder(original, base / "raw", flat=False)
    log = _lab_log(original, base / "lab_log.csv", with_experiment=False)
    before = _md5s(raw)
    result = init_dataset(raw, base / "dataset", lab_log=log)
    return result, raw, before


def test_layout_validates_and_equals_the_original(original, scaffolded):
    result, _, _ = scaffolded
    out = result.out
    assert validate_dataset(out) == [] and result.remaining == []
    assert validate_dataset(out, checksums=True) == []
    orig, new = open_dataset(original), open_dataset(out)
    assert new.lenses == orig.lenses
    assert new.meta["camera"] == orig.meta["camera"]
    assert new.experiments() == orig.experiments()
    for experiment in EXPERIMENTS:
        a, b = _frames(original, experiment), _frames(out, experiment)
        pd.testing.assert_frame_equal(b[list(a.columns)], a)
        assert list(b.columns) == list(a.columns) + ["exposure_s", "iso", "time"]


def test_tag_columns_are_what_the_simulator_wrote(scaffolded):
    """Exposure, ISO and time equal the DNG tags as tifffile reads them, and the clock in the file names."""
    result, _, _ = scaffolded
    for experiment in EXPERIMENTS:
        table = _frames(result.out, experiment)
        for _, row in table.iterrows():
            with tifffile.TiffFile(result.out / experiment / row["file"]) as tif:
                tags = tif.pages[0].tags
                num, den = tags["ExposureTime"].value
                iso = tags["ISOSpeedRatings"].value
                stamp = tags["DateTimeOriginal"].value
                subsec = tags["SubsecTimeOriginal"].value
            assert float(row["exposure_s"]) == num / den
            assert float(row["iso"]) == iso
            written = datetime.strptime(f"{stamp}.{subsec}", "%Y:%m:%d %H:%M:%S.%f")
            assert datetime.fromisoformat(row["time"]) == written
            # the simulator names each file after its clock
            assert Path(row["file"]).name.startswith(f"IMG_{written:%Y%m%d_%H%M%S}_")
        times = [datetime.fromisoformat(t) for t in table["time"]]
        assert times == sorted(times)                       # acquisition order


def test_raw_files_referenced_never_modified(scaffolded):
    result, raw, before = scaffolded
    assert _md5s(raw) == before
    links = [p for p in result.out.rglob("*.dng")]
    assert links and all(p.is_symlink() and p.resolve().is_relative_to(raw.resolve()) for p in links)
    assert not list(result.out.parent.glob(".*.partial"))


def test_lens_regions_checked_on_image_circles(scaffolded):
    result, _, _ = scaffolded
    lenses = {lens.name: lens for lens in result.plan.lenses}
    assert list(lenses) == list(LENSES)
    for lens in lenses.values():
        (r0, r1), (c0, c1) = lens.rows, lens.cols
        assert lens.radius_px is not None, lens.note
        # the simulated fisheye circle is centred in its square region and nearly fills it
        assert abs(lens.centre_row_px - (r0 + r1) / 2) < 0.05 * (r1 - r0)
        assert abs(lens.centre_col_px - (c0 + c1) / 2) < 0.05 * (c1 - c0)
        assert 0.35 * (r1 - r0) < lens.radius_px < 0.55 * (r1 - r0)
        assert lens.frame.startswith("linearity/raw/")
    text = describe_result(result)
    assert "lens regions proposed from the 256 x 128 frames" in text
    assert "far:   rows [0, 128), cols [0, 128): image circle at row" in text
    assert "the dataset validates; run: snakemake --cores 2 --config dataset=" in text


def test_propose_lens_regions():
    assert [(p.name, p.rows, p.cols) for p in propose_lens_regions(6912, 3456)] == [
        ("far", (0, 3456), (0, 3456)), ("close", (3456, 6912), (0, 3456))]
    assert [(p.name, p.rows, p.cols) for p in propose_lens_regions(1000, 2000)] == [
        ("left", (0, 1000), (0, 1000)), ("right", (0, 1000), (1000, 2000))]
    assert [(p.name, p.rows, p.cols) for p in propose_lens_regions(1157, 1734)] == [
        ("main", (0, 1156), (0, 1734))]


def test_stage_artefacts_equal_the_original(original, scaffolded, config, tmp_path):
    result, _, _ = scaffolded
    arts = {}
    for name, root in (("original", original), ("scaffolded", result.out)):
        dark = {lens: tmp_path / name / f"dark/{lens}.nc" for lens in LENSES}
        lin = {lens: tmp_path / name / f"linearity/{lens}.nc" for lens in LENSES}
        # checked=True: both folders pass validate (test_layout_validates_and_equals_the_original); what is
        # compared here is the stages' artefacts, not the tag checks every run_stage call on a folder repeats
        run_stage("dark", root, config, dark, checked=True)
        run_stage("linearity", root, config, lin, {"dark": dark}, checked=True)
        arts[name] = {(stage, lens): xr.open_dataset(p).load()
                      for stage, paths in (("dark", dark), ("linearity", lin)) for lens, p in paths.items()}
    for key, a in arts["original"].items():
        b = arts["scaffolded"][key]
        assert set(a.data_vars) == set(b.data_vars) and set(a.coords) == set(b.coords), key
        for name in list(a.data_vars) + list(a.coords):
            np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=f"{key} {name}")


def test_flat_folder_with_experiment_column_and_copy(original, tmp_path):
    raw = _raw_folder(original, tmp_path / "raw", flat=True)
    log = _lab_log(original, raw / "lab_log.csv", with_experiment=True)   # the log may sit among the files
    table = pd.read_csv(log, dtype=str, keep_default_na=False)
    table["operator"] = "A. N. Other"                                       # a column frames.csv has not
    table.to_csv(log, index=False)
    proc = _cli("init-dataset", str(raw), str(tmp_path / "dataset"), "--lab-log", str(log), "--copy")
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "dataset"
    assert f"wrote {out}:" in proc.stdout and "(copied)" in proc.stdout and "neither raw frames nor sidecars" not in proc.stdout
    assert "note: lab log columns left out: operator" in proc.stdout
    assert not any(p.is_symlink() for p in out.rglob("*"))
    for experiment in EXPERIMENTS:
        a, b = _frames(original, experiment), _frames(out, experiment)
        pd.testing.assert_frame_equal(b[list(a.columns)], a)
    proc = _cli("validate", str(out))
    assert proc.returncode == 0 and proc.stdout.startswith("ok: ") and "in 2 experiments" in proc.stdout


def test_without_a_lab_log_the_lab_columns_are_left_to_fill_in(original, tmp_path):
    raw = _raw_folder(original, tmp_path / "raw", flat=False)
    result = init_dataset(raw, tmp_path / "dataset")
    lin = _frames(result.out, "linearity")
    assert list(lin.columns) == ["file", "lens", "kind", "sweep", "exposure_s", "iso", "time"]
    assert (lin[["lens", "kind", "sweep"]] == "").all().all()
    dark = _frames(result.out, "dark")
    assert (dark["kind"] == "dark").all() and (dark["lens"] == "both").all()   # what dark/ implies
    n = len(lin)
    assert {(p.column, p.message) for p in result.remaining} == {
        ("lens", "value is empty (one of far, close, both)"), ("kind", "value is empty (one of signal, dark)"),
        ("sweep", "value is empty (one of exposure, gain)")}
    assert len(result.remaining) == 3 * n
    text = describe_result(result)
    assert f"lines 2-{n + 1}, column 'lens': value is empty (one of far, close, both) [{n} rows]" in text
    assert f"then run: python -m pipeline validate {result.out}" in text


def test_never_overwrites(original, tmp_path):
    raw = _raw_folder(original, tmp_path / "raw", flat=False)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("a user's file")
    proc = _cli("init-dataset", str(raw), str(out))
    assert proc.returncode == 1
    assert proc.stderr == f"error: {out}: already exists; init-dataset never overwrites a folder (choose another OUT)\n"
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_files_it_cannot_place_stop_before_writing(original, tmp_path):
    raw = _raw_folder(original, tmp_path / "raw", flat=True)
    log = _lab_log(original, tmp_path / "lab_log.csv", with_experiment=True)
    table = pd.read_csv(log, dtype=str, keep_default_na=False)
    orphan = table["file"].iloc[0]
    table = table.iloc[1:].copy()
    table.loc[table.index[0], "file"] = "IMG_missing.dng"
    table.loc[table.index[1], "experiment"] = "linearty"
    table.to_csv(log, index=False)
    with pytest.raises(InputError) as err:
        init_dataset(raw, tmp_path / "dataset", lab_log=log)
    found = {(p.path.name, p.line, p.column, p.message) for p in err.value.problems}
    assert ("lab_log.csv", 2, "file", "no raw file 'IMG_missing.dng' under RAW_DIR") in found
    assert ("lab_log.csv", 3, "experiment", "'linearty' is not an experiment") in found
    assert (orphan, None, None, "no experiment for this raw file") in found
    assert not (tmp_path / "dataset").exists() and not list(tmp_path.glob(".*partial"))
    proc = _cli("init-dataset", str(raw), str(tmp_path / "dataset"), "--lab-log", str(log))
    assert proc.returncode == 1
    assert "no experiment for this raw file" in proc.stderr and proc.stderr.splitlines()[-1].startswith("error: ")


def _in_process(*args) -> tuple[int, str]:
    """The command line's exit code and standard output, run in this process (argparse's exits caught)."""
    import contextlib
    import io

    from pipeline.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        try:
            code = main(list(args))
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
    return code, out.getvalue()


def test_help_and_version():
    """`python -m pipeline --help` as a user runs it (one process); the other answers of the same parser
    in this process, which costs no interpreter start-up each."""
    proc = _cli("--help")
    assert proc.returncode == 0
    for command, description in (("init-dataset", "lay out a folder of raw files as a calibration dataset"),
                                 ("validate", "list every problem of a dataset at once"),
                                 ("simulate", "write a simulated calibration dataset")):
        assert any(line.split()[:1] == [command] and description in line for line in proc.stdout.splitlines())
    assert "examples:" in proc.stdout and "exit codes:" in proc.stdout
    assert "snakemake --cores 2 --config dataset=" in proc.stdout
    code, out = _in_process("--version")
    assert code == 0 and out.strip() == f"python -m pipeline {__version__}"
    assert _in_process("no-such-command")[0] == 2
    assert _in_process("validate")[0] == 2
    for command in ("init-dataset", "validate", "simulate"):
        code, out = _in_process(command, "--help")
        assert code == 0 and "examples:" in out

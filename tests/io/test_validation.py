"""pipeline.io.validation and `python -m pipeline validate`: every problem of a dataset at once."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import tifffile
import yaml

from pipeline.errors import InputError
from pipeline.io.validation import format_problems, inspect_dataset, validate_dataset
from pipeline.runner.workflow import DatasetIndex


def _cli_process(*args):
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, timeout=300)


@pytest.fixture
def cli(capsys):
    """``python -m pipeline ARGS`` in this process (``pipeline.cli.main``, what ``__main__`` calls), which
    spares each test a Python start-up and the imports: the exit status and what it printed."""
    from pipeline.cli import main

    def run(*args):
        capsys.readouterr()
        code = main(list(args))
        out = capsys.readouterr()
        return subprocess.CompletedProcess(args, code, out.out, out.err)

    return run


def _edit_csv(path, edit):
    frame = pd.read_csv(path, dtype=str, keep_default_na=False)
    edit(frame)
    frame.to_csv(path, index=False)


@pytest.fixture
def dataset(make_dataset, tmp_path):
    src, _ = make_dataset()
    root = tmp_path / "dataset"
    shutil.copytree(src, root)
    return root.resolve()


@pytest.fixture
def planted(dataset):
    """Six distinct mistakes in one dataset; returns the dataset and (file, line, column, phrase) of each."""
    root = dataset
    lin = root / "linearity" / "frames.csv"
    dark = root / "dark" / "frames.csv"
    lin_files = pd.read_csv(lin)["file"]
    dark_files = pd.read_csv(dark)["file"]

    def lin_edit(f):
        f.loc[3, "lens"] = "Far"                 # line 5
        f.loc[7, "sweep"] = ""                   # line 9
    _edit_csv(lin, lin_edit)
    (root / "dark" / dark_files[2]).unlink()      # line 4 names a file that is gone

    def dark_edit(f):                             # a copy of a tag that disagrees with it
        f["exposure_s"] = ""
        f.loc[5, "exposure_s"] = "0.5"           # line 7
    _edit_csv(dark, dark_edit)
    victim = root / "linearity" / lin_files[10]   # a raw file whose tags were lost (plain TIFF)
    tifffile.imwrite(victim, np.zeros((256, 128), np.uint16))
    meta = yaml.safe_load((root / "dataset.yaml").read_text())
    meta["camera"]["make"] = ""
    meta["lenses"]["close"]["rows"] = [128, 300]  # beyond the 256-row frames
    (root / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    expected = [
        (root / "dataset.yaml", None, None, "camera.make must be a non-empty string"),
        (lin, 5, "lens", "'Far' is not one of far, close, both"),
        (lin, 9, "sweep", "value is empty"),
        (dark, 4, "file", f"{dark_files[2]} does not exist"),
        (dark, 7, "exposure_s", "0.5 but the file's ExposureTime tag says"),
        (victim, None, None, "ExposureTime tag is missing or not a positive number of seconds"),
        (victim, None, None, "ISOSpeedRatings tag is missing or not a positive number"),
        (victim, None, None, "DateTimeOriginal tag is missing or not a date and time (YYYY:MM:DD HH:MM:SS)"),
        (root / "dataset.yaml", None, None,
         "lenses.close (rows [128, 300), cols [0, 128)) does not fit the 256 x 128 frames"),
    ]
    return root, expected


def _find(problems, path, line, column, phrase):
    return [p for p in problems if p.path == path and p.line == line and p.column == column and phrase in p.message]


def test_clean_dataset_has_no_problems(dataset, cli):
    ds, problems = inspect_dataset(dataset)
    assert problems == [] and ds.experiments() == ["dark", "linearity"]
    proc = cli("validate", str(dataset))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    n = len(ds.frames("dark")) + len(ds.frames("linearity"))
    assert proc.stdout.strip() == f"ok: {n} frames in 2 experiments (dark, linearity)"


def test_every_planted_problem_in_one_run(planted):
    root, expected = planted
    problems = validate_dataset(root)
    for path, line, column, phrase in expected:
        assert len(_find(problems, path, line, column, phrase)) == 1, (path, line, column, phrase, problems)
    assert len(problems) == len(expected), problems
    assert all(p.fix for p in problems)          # every problem says how to fix it


def test_command_line_lists_them_grouped_and_fails(planted):
    """The one run of the real ``python -m pipeline validate`` process here (the others call main in-process)."""
    root, expected = planted
    proc = _cli_process("validate", str(root))
    assert proc.returncode == 1
    out = proc.stdout
    assert out.startswith(f"{len(expected)} problems in 4 files of {root}:")
    for header in ("dataset.yaml (2 problems)", "linearity/frames.csv (2 problems)",
                   "dark/frames.csv (2 problems)"):
        assert f"\n{header}\n" in out, out
    assert "  line 5, column 'lens': 'Far' is not one of far, close, both\n" in out
    assert "  line 9, column 'sweep': value is empty (one of exposure, gain)\n" in out
    assert "  line 7, column 'exposure_s': 0.5 but the file's ExposureTime tag says 0.001\n" in out
    assert "ExposureTime tag is missing or not a positive number of seconds" in out and out.count("fix: ") == len(expected)
    assert "Traceback" not in proc.stderr


def test_one_mistake_on_many_rows_is_one_entry(dataset):
    lin = dataset / "linearity" / "frames.csv"
    _edit_csv(lin, lambda f: f.__setitem__("sweep", f["sweep"].str.capitalize()))
    n = len(pd.read_csv(lin))
    problems = validate_dataset(dataset)
    assert len(problems) == n
    text = format_problems(problems, dataset)
    assert f"lines 2-{n + 1}, column 'sweep': 'Exposure' is not one of exposure, gain, and 1 more like it " \
           f"[{n} rows]" in text
    assert text.count("fix: ") == 1


def test_missing_dataset(tmp_path, cli):
    proc = cli("validate", str(tmp_path / "not-mounted"))
    assert proc.returncode == 1 and "dataset folder not found" in proc.stdout


def test_open_dataset_names_the_first_and_counts_the_others(planted):
    from pipeline.io.dataset import open_dataset

    root, _ = planted
    with pytest.raises(InputError) as err:
        open_dataset(root)
    msg = str(err.value)
    assert "\n" not in msg
    # open_dataset checks the layout (not the tags): 4 problems, the first one named
    assert msg == (f"{root / 'dataset.yaml'}: camera.make must be a non-empty string (and 3 more problems; "
                   f"python -m pipeline validate {root} lists them all)")
    assert len(err.value.problems) == 4


def test_workflow_start_up_check_uses_the_same_code(planted, capsys):
    root, expected = planted
    with pytest.raises(InputError) as err:
        DatasetIndex(root).load()
    assert err.value.problems == validate_dataset(root)
    assert str(err.value).startswith(f"{root / 'dataset.yaml'}: camera.make must be a non-empty string "
                                     f"(and {len(expected) - 1} more problems; listed above)")
    printed = capsys.readouterr().err
    assert printed.startswith(f"{len(expected)} problems in 4 files of {root}:")


def test_misspelt_folder_and_missing_sidecar(dataset):
    (dataset / "linearity").rename(dataset / "Linearity")
    (dataset / "spectral").mkdir()
    problems = validate_dataset(dataset)
    assert _find(problems, dataset / "Linearity", None, None, "is not an experiment")
    assert "rename it 'linearity'" in _find(problems, dataset / "Linearity", None, None, "")[0].fix
    assert _find(problems, dataset / "spectral" / "photodiode.csv", None, None, "file not found")
    assert _find(problems, dataset / "spectral" / "frames.csv", None, None, "file not found")
    md5 = [p for p in problems if p.path == dataset / "MD5SUMS"]
    assert md5 and all("linearity/" in p.message and "listed but the file is absent" in p.message for p in md5)


def test_checksums_option(dataset, cli):
    frames = pd.read_csv(dataset / "dark" / "frames.csv")
    victim = dataset / "dark" / frames["file"].iloc[1]
    data = bytearray(victim.read_bytes())
    data[-100] ^= 0xFF
    victim.write_bytes(bytes(data))
    assert validate_dataset(dataset) == []          # tags still read: only the checksum knows
    problems = validate_dataset(dataset, checksums=True)
    assert [p.path for p in problems] == [victim] and "checksum mismatch" in problems[0].message
    proc = cli("validate", str(dataset), "--checksums")
    assert proc.returncode == 1 and "checksum mismatch" in proc.stdout


def test_unlisted_file_is_a_warning(dataset, cli, capsys):
    """A frame the lab copied but did not list: validate still passes (exit 0) and names the file once."""
    extra = dataset / "dark" / "spare_0001.dng"
    shutil.copy(dataset / "dark" / pd.read_csv(dataset / "dark" / "frames.csv")["file"].iloc[0], extra)
    (dataset / "dark" / ".DS_Store").write_bytes(b"\0")           # hidden files are not the lab's frames
    proc = cli("validate", str(dataset))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0] == f"warning: {extra}: not listed in dark/frames.csv: the stages ignore it"
    assert len(lines) == 2 and lines[1].startswith("ok: ")
    DatasetIndex(dataset).load()                                   # the workflow's start-up check: on stderr
    assert capsys.readouterr().err.splitlines() == [lines[0]]


def test_the_tag_cache_spares_a_second_start_and_reads_an_edited_frame_again(make_dataset, tmp_path, monkeypatch):
    """A second check of the same dataset in a new process (the process's own cache emptied) reads no frame's
    tags; a frame written again (same bytes, new change time) is read again, alone; ``off`` reads them all."""
    import pipeline.io.validation as validation

    src, _ = make_dataset()
    root = tmp_path / "dataset"
    shutil.copytree(src, root)
    monkeypatch.setenv(validation.TAG_CACHE_ENV, str(tmp_path / "cache"))
    reads = []

    def counting(path):
        reads.append(path)
        return read_tags(path)

    read_tags = validation.read_tags
    monkeypatch.setattr(validation, "read_tags", counting)

    def start():
        validation._TAGS_SEEN.clear()
        reads.clear()
        dataset, problems = inspect_dataset(root)
        assert problems == [] and dataset is not None
        return len(reads)

    n_frames = start()
    assert n_frames > 100 and validation.tag_cache_file(root).is_file()
    assert start() == 0
    frame = sorted((root / "dark" / "raw").glob("*.dng"))[0]
    frame.write_bytes(frame.read_bytes())
    assert start() == 1 and reads[0].name == frame.name
    monkeypatch.setenv(validation.TAG_CACHE_ENV, "off")
    assert start() == n_frames

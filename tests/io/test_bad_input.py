"""The bad-input matrix: each kind of broken dataset or configuration a user can hand the pipeline.

Every case plants one mistake in a copy of the tiny simulated dataset (or the config) and checks
what the user sees: ``python -m pipeline validate`` exits 1 and names the file and the problem,
the workflow's start-up check (the code the Snakefile runs before any job) stops with one line
naming the same file and problem, and nothing in the dataset is written. The cases already
tested elsewhere are listed in the the "Bad input" section of docs/bad-input.md table with their tests.
"""

from __future__ import annotations

import shutil
import struct
from datetime import datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.cli import main
from pipeline.config import load_config
from pipeline.errors import InputError
from pipeline.io.rawio import read_tags, write_dng
from pipeline.runner.workflow import DatasetIndex, check_config
from real_dng import BLACKMAGIC, CANON, strip_tag
from workflow_runs import snakemake

_EXPOSURE_TAG, _ISO_TAG = 33434, 34855


def _zero_rational(path: Path, code: int) -> None:
    """Set the numerator of a RATIONAL tag of IFD0 to 0 (a camera or converter that wrote 0)."""
    data = bytearray(path.read_bytes())
    ifd = int.from_bytes(data[4:8], "little")
    for i in range(int.from_bytes(data[ifd:ifd + 2], "little")):
        entry = ifd + 2 + 12 * i
        if int.from_bytes(data[entry:entry + 2], "little") == code:
            offset = int.from_bytes(data[entry + 8:entry + 12], "little")
            data[offset:offset + 4] = struct.pack("<I", 0)
            path.write_bytes(bytes(data))
            return
    raise AssertionError(f"tag {code} not found")


def _edit_csv(path: Path, edit) -> None:
    frame = pd.read_csv(path, dtype=str, keep_default_na=False)
    frame = edit(frame)
    frame.to_csv(path, index=False)


def _set(column: str, row: int, value: str):
    def edit(frame):
        if column not in frame:
            frame[column] = ""
        frame.loc[row, column] = value
        return frame
    return edit


def _other_size(victim: Path) -> None:
    tags = read_tags(victim)
    rows, cols = tags["shape"]
    write_dng(victim, np.full((rows // 2, cols), 900, np.uint16), exposure_s=tags["exposure_s"], iso=tags["iso"],
              time=tags["time"] or datetime(2021, 3, 10), black_level=tags["black_level"])


def _lens_outside(root: Path) -> None:
    meta = yaml.safe_load((root / "dataset.yaml").read_text())
    rows = meta["lenses"]["close"]["rows"]
    meta["lenses"]["close"]["rows"] = [rows[0], rows[1] + 64]
    (root / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))


# case -> (plant the mistake: f(root, frames.csv, victim frame)), (the file named, phrase, one problem only)
CASES = {
    "truncated DNG": (lambda r, csv, v: v.write_bytes(v.read_bytes()[: v.stat().st_size // 2]),
                      "victim", "truncated", True),
    "not a DNG": (lambda r, csv, v: v.write_text("lab notes, saved under the frame's name\n" * 20),
                  "victim", "not a readable DNG", True),
    "no ExposureTime tag": (lambda r, csv, v: strip_tag(v, _EXPOSURE_TAG),
                            "victim", "ExposureTime tag is missing or not a positive number of seconds", True),
    "no ISO tag": (lambda r, csv, v: strip_tag(v, _ISO_TAG), "victim", "ISOSpeedRatings tag is missing or not a positive number", True),
    "zero exposure tag": (lambda r, csv, v: _zero_rational(v, _EXPOSURE_TAG),
                          "victim", "ExposureTime tag is missing or not a positive number of seconds", True),
    "negative exposure in frames.csv": (lambda r, csv, v: _edit_csv(csv, _set("exposure_s", 1, "-0.01")),
                                        "csv", "line 3, column 'exposure_s': -0.01 but the file's ExposureTime "
                                               "tag says", True),
    "frames.csv names an absent file": (lambda r, csv, v: v.unlink(), "csv", "line 3, column 'file': raw/", True),
    "duplicate row": (lambda r, csv, v: _edit_csv(csv, lambda f: pd.concat([f, f.iloc[[0]]], ignore_index=True)),
                      "csv", "already listed on line 2", True),
    "unparseable time stamp": (lambda r, csv, v: _edit_csv(csv, _set("time", 0, "10/03/2021 9h02")),
                               "csv", "line 2, column 'time': '10/03/2021 9h02' is not an ISO 8601 time", True),
    "NaN in a number column": (lambda r, csv, v: _edit_csv(csv, _set("temperature_c", 0, "nan")),
                               "csv", "line 2, column 'temperature_c': 'nan' is not a finite number", True),
    "text in a number column": (lambda r, csv, v: _edit_csv(csv, _set("temperature_c", 0, "warm")),
                                "csv", "line 2, column 'temperature_c': 'warm' is not a number", True),
    "lens region outside the frame": (lambda r, csv, v: _lens_outside(r), "yaml", "does not fit the", True),
    "frame of another size": (lambda r, csv, v: _other_size(v), "victim", "but most frames are", True),
    # the real cameras' files: no exposure tags (Canon: zero; Blackmagic: no EXIF block), another size
    "real Canon DNG as a frame": (lambda r, csv, v: shutil.copy(CANON, v), "victim",
                                  "ExposureTime tag is missing or not a positive number of seconds", False),
    "real Blackmagic DNG as a frame": (lambda r, csv, v: shutil.copy(BLACKMAGIC, v), "victim",
                                       "ExposureTime tag is missing or not a positive number of seconds", False),
}


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {p.relative_to(root).as_posix(): (p.stat().st_mtime_ns, p.stat().st_size)
            for p in root.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def clean(make_dataset):
    src, _ = make_dataset([], seed=41)
    return src


@pytest.mark.parametrize("case", list(CASES))
def test_bad_dataset_is_named_in_one_line(case, clean, tmp_path, capsys):
    """validate: exit 1 with the file and the problem; the workflow's start-up check: one line naming
    them (and, where the case is the only mistake, exactly one problem); the dataset is not written."""
    plant, named, phrase, alone = CASES[case]
    if "real" in case and not CANON.is_file():
        pytest.skip("shared/realdata/dng not present")
    root = tmp_path / "dataset"
    shutil.copytree(clean, root)
    csv = root / "linearity" / "frames.csv"
    victim = root / "linearity" / pd.read_csv(csv)["file"].iloc[1]
    plant(root, csv, victim)
    file = {"victim": victim, "csv": csv, "yaml": root / "dataset.yaml"}[named]
    before = _snapshot(root)
    capsys.readouterr()
    assert main(["validate", str(root)]) == 1
    out = capsys.readouterr().out
    assert f"\n{file.relative_to(root)} (" in out and phrase in out, out
    with pytest.raises(InputError) as err:
        DatasetIndex(root).load()
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{file}: ") and phrase in message, message
    if alone:
        assert len(err.value.problems) == 1, err.value.problems
    assert _snapshot(root) == before


@pytest.mark.parametrize("override, phrase", [
    ({"dark": {"hot_pixel_threshold_sigma": "six"}},
     "config dark.hot_pixel_threshold_sigma: 'six' is not of type 'number'"),
    ({"model": {"effects": ["dark_current", "hot_pixel"]}}, "model.effects: unknown effect 'hot_pixel'"),
    # a misspelt key would leave its default in force without a word
    ({"rolloff": {"spot_radius_degs": 2.0}}, "config rolloff.spot_radius_degs: unknown key; known there: "),
    ({"performance": {"decode_ahead_frames": -1}}, "config performance.decode_ahead_frames: -1 is outside its range [0, 64]"),
    # a sign lost: the dark job died in numpy (arange: cannot compute length) before the schema had the range
    ({"dark": {"hot_pixel_threshold_sigma": -6}}, "config dark.hot_pixel_threshold_sigma: -6 is outside its range [1, 100]"),
    ({"performance": {"decode_ahead_frames": 1.5}}, "config performance.decode_ahead_frames: 1.5 is not of type 'integer'"),
    ({"model": {"effects": ["dark_current"], "plugins": ["lab_effects_not_installed"]}},
     "model.plugins: cannot import 'lab_effects_not_installed' (ModuleNotFoundError"),
    ({"model": {"effects": ["dark_current"], "plugins": ["broken_lab_plugin"]}},
     "model.plugins: cannot import 'broken_lab_plugin' (ZeroDivisionError: division by zero)"),
])
def test_bad_config_is_named_in_one_line(override, phrase, tmp_path, monkeypatch):
    """The workflow's start-up check of the config (the Snakefile calls check_config before any job)."""
    (tmp_path / "broken_lab_plugin.py").write_text("RATE = 1 / 0\n")     # a plugin that fails while importing
    monkeypatch.syspath_prepend(str(tmp_path))
    config = load_config()
    for key, value in override.items():
        config[key] = {**config[key], **value}
    with pytest.raises(InputError) as err:
        check_config(config, "config/config.yaml")
    assert str(err.value).startswith("config/config.yaml: ") and phrase in str(err.value) and "\n" not in str(err.value)


def test_unknown_effect_stops_the_workflow_before_any_job(clean, tmp_path):
    """Through Snakemake: exit 1, one error line naming the config file, no job and no results/."""
    proc = snakemake(tmp_path, clean, "model={effects: [dark_current, hot_pixel]}", "-n", check=False)
    assert proc.returncode == 1
    errors = [line for line in (proc.stdout + proc.stderr).splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "config/config.yaml: model.effects: unknown effect 'hot_pixel'" in errors[0], errors
    assert "Traceback" not in proc.stderr and not (tmp_path / "results").exists()


def test_unlit_signal_frame_stops_the_linearity_stage(clean, tmp_path, config):
    """A linearity signal frame taken with the source off (bias plus 2 DN read noise, tags intact,
    MD5SUMS rewritten so that only the stage can tell): its mask sits within a few standard errors of
    its unlit corners, far below linearity.signal_frame_min_snr = 5 (the tiny dataset's dimmest lit
    frame is hundreds of standard errors up: 264 DN over 0.63 DN with seed 3), so the stage stops naming it
    and writes no artefact."""
    from pipeline.io.dataset import write_md5sums
    from pipeline.io.rawio import read_raw
    from pipeline.runner.workflow import run_stage

    root = tmp_path / "dataset"
    shutil.copytree(clean, root)
    frames = pd.read_csv(root / "linearity" / "frames.csv")
    victim = root / "linearity" / frames.loc[(frames["kind"] == "signal") & (frames["lens"] == "far"), "file"].iloc[3]
    raw = read_raw(victim)
    unlit = raw.black_level + np.random.default_rng(0).normal(0.0, 2.0, raw.cfa.shape)
    write_dng(victim, unlit.round().astype(np.uint16), exposure_s=raw.exposure_s, iso=raw.iso, time=raw.time,
              black_level=raw.black_level, white_level=raw.white_level)
    write_md5sums(root)
    out = tmp_path / "results"
    dark = {"far": out / "dark" / "far.nc"}
    run_stage("dark", root, config, dark)
    with pytest.raises(InputError) as err:
        run_stage("linearity", root, config, {"far": out / "linearity" / "far.nc"}, {"dark": dark})
    message = str(err.value)
    assert message.startswith(f"{victim}: signal frame is dark: its far-lens mask is ") and "\n" not in message
    assert not (out / "linearity").exists() or not list((out / "linearity").iterdir())


def test_diagnose_without_a_run_names_the_missing_file(tmp_path, capsys):
    """`diagnose` on a folder the workflow never wrote: exit 1 and one line naming the first missing file."""
    assert main(["diagnose", "--results", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {tmp_path / 'diagnostics/missing_effects.csv'}: not found: run the workflow first "
                   "(snakemake --cores 2), whose diagnostics rule writes it, or give the results folder with "
                   "--results DIR"], err


def test_numbers_in_a_command_line_override_are_read_as_numbers():
    """Snakemake hands the nested values of a ``--config`` override over as text (its own parser, used
    here, gives '0' and '6.5'); where the schema wants a number the text is read as one, so the override
    works, while text that is no number is still refused in one line."""
    from snakemake.cli import parse_config

    from pipeline.config import validate_config

    override = parse_config(["performance={decode_ahead_frames: 0}", "dark={hot_pixel_threshold_sigma: 6.5}"])
    assert override["performance"]["decode_ahead_frames"] == "0"          # what the workflow receives
    config = validate_config({"dataset": "d", **override})
    assert config["performance"]["decode_ahead_frames"] == 0
    assert isinstance(config["performance"]["decode_ahead_frames"], int)
    assert config["dark"]["hot_pixel_threshold_sigma"] == 6.5
    with pytest.raises(InputError, match="'six' is not of type 'number'"):
        validate_config({"dataset": "d", **parse_config(["dark={hot_pixel_threshold_sigma: six}"])})

"""Parts of a dataset that are each fine but do not agree: caught by ``validate`` before any stage.

Every case plants one mistake in a copy of a tiny simulated dataset (dark, linearity and field; the
checksums rewritten, so that only the consistency check can tell) and checks the line the user sees:
a problem stops ``validate`` (exit 1) and the workflow's start-up check, naming the file; a
suspicion is a warning naming what it saw, and ``validate`` still passes.
"""

from __future__ import annotations

import shutil
from dataclasses import replace
from datetime import datetime, timedelta
from pathlib import Path

import pandas as pd
import pytest
import yaml

from pipeline.cli import main
from pipeline.io.consistency import FrameTags, check_consistency
from pipeline.io.dataset import write_md5sums
from pipeline.errors import InputError
from pipeline.io.rawio import read_raw, read_tags, write_dng
from pipeline.runner.workflow import DatasetIndex


@pytest.fixture(scope="module")
def clean(make_dataset):
    root, _ = make_dataset(seed=23, experiments=("dark", "linearity", "field"))
    return root


def _frame(root: Path, experiment: str, row: int) -> Path:
    return root / experiment / pd.read_csv(root / experiment / "frames.csv")["file"].iloc[row]


def _rewrite(path: Path, **changes) -> None:
    """Write the frame again with some of its tags changed (its pixels kept)."""
    raw = read_raw(path)
    tags = dict(exposure_s=raw.exposure_s, iso=raw.iso, time=raw.time, black_level=raw.black_level,
                white_level=raw.white_level, cfa_pattern=raw.cfa_pattern, make=raw.make, model=raw.model,
                serial=raw.serial)
    write_dng(path, raw.cfa, **{**tags, **changes})


def _edit_yaml(path: Path, edit) -> None:
    data = yaml.safe_load(path.read_text())
    edit(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def _lenses(**regions):
    def edit(meta):
        for name, (rows, cols) in regions.items():
            meta["lenses"][name]["rows"], meta["lenses"][name]["cols"] = list(rows), list(cols)
    return lambda root: _edit_yaml(root / "dataset.yaml", edit)


def _site(**values):
    return lambda root: _edit_yaml(root / "field" / "site.yaml", lambda site: site.update(values))


def _channels(edit):
    return lambda root: _edit_yaml(root / "field" / "site.yaml", lambda site: edit(site["reference"]))


def _rename_column(old: str, new: str):
    def plant(root):
        path = root / "field" / "reference_radiometer.csv"
        lines = path.read_text().splitlines(keepends=True)
        lines[0] = lines[0].replace(old, new)
        path.write_text("".join(lines))
    return plant


def _without_serial(root: Path) -> None:
    _edit_yaml(root / "dataset.yaml", lambda meta: meta["camera"].pop("serial"))
    _rewrite(_frame(root, "dark", 2), serial="SIM-0002")


def _shifted(experiment: str, row: int, **delta):
    def plant(root):
        path = _frame(root, experiment, row)
        _rewrite(path, time=read_tags(path)["time"] + timedelta(**delta))
    return plant


def _at(experiment: str, row: int, stamp: datetime):
    return lambda root: _rewrite(_frame(root, experiment, row), time=stamp)


def _resized_dark(root: Path) -> None:
    path = _frame(root, "dark", 0)
    raw = read_raw(path)
    write_dng(path, raw.cfa[:, : raw.cfa.shape[1] // 2], exposure_s=raw.exposure_s, iso=raw.iso, time=raw.time,
              black_level=raw.black_level, white_level=raw.white_level)


def _victim(experiment, row, **changes):
    return lambda root: _rewrite(_frame(root, experiment, row), **changes)


def _reference_times(edit):
    """Rewrite the time column of field/reference_radiometer.csv: ``edit(datetime) -> text``."""
    def plant(root):
        path = root / "field" / "reference_radiometer.csv"
        head, *rows = path.read_text().splitlines()
        out = [head]
        for row in rows:
            stamp, rest = row.split(",", 1)
            out.append(f"{edit(datetime.fromisoformat(stamp.rstrip('Z')))},{rest}")
        path.write_text("\n".join(out) + "\n")
    return plant


def _yaml_text(old: str, new: str):
    """Edit dataset.yaml's text as a person would (no YAML round trip, which would quote the value)."""
    def plant(root):
        path = root / "dataset.yaml"
        text = path.read_text()
        assert old in text
        path.write_text(text.replace(old, new))
    return plant


def _resized(experiment: str, row: int):
    def plant(root):
        path = _frame(root, experiment, row)
        raw = read_raw(path)
        write_dng(path, raw.cfa[: raw.cfa.shape[0] // 2], exposure_s=raw.exposure_s, iso=raw.iso, time=raw.time,
                  black_level=raw.black_level, white_level=raw.white_level)
    return plant


def _regional(relative: str):
    """The table saved by a spreadsheet set to a comma-decimal region: ';' between fields, decimal commas."""
    def plant(root):
        path = root / relative
        path.write_text(path.read_text().replace(",", ";").replace(".", ","))
    return plant


#: the tiny dataset's frames are 256 x 128 pixels: far rows [0, 128), close rows [128, 256), cols [0, 128)
# case -> (plant the mistake, the file named: a frame (experiment, row) or a path in the dataset, the phrase)
PROBLEMS = {
    # 1. per-frame tags against each other and dataset.yaml
    "frame of another camera body": (
        _victim("linearity", 3, model="ONE X2", serial="SIM-0417"), ("linearity", 3),
        "Model tag says 'ONE X2' but dataset.yaml's camera.model is 'ONE' (linearity/frames.csv line 5): "
        "a frame of another camera"),
    "another body's serial only": (
        _victim("field", 1, serial="SIM-0417"), ("field", 1),
        "CameraSerialNumber tag says 'SIM-0417' but dataset.yaml's camera.serial is 'SIM-0001'"),
    "another make": (_victim("dark", 0, make="GoPro"), ("dark", 0),
                     "Make tag says 'GoPro' but dataset.yaml's camera.make is 'Insta360'"),
    "another serial, dataset.yaml without one": (
        _without_serial, ("dark", 2), "CameraSerialNumber tag says 'SIM-0002' but"),
    "dataset.yaml names another model": (
        lambda root: _edit_yaml(root / "dataset.yaml", lambda meta: meta["camera"].update(model="ONE R")),
        "dataset.yaml", "camera.model is 'ONE R' but every frame's Model tag says 'ONE'"),
    "one frame BGGR": (_victim("linearity", 2, cfa_pattern="BGGR"), ("linearity", 2),
                       "CFAPattern tag says BGGR but"),
    "one dark frame GRBG": (_victim("dark", 1, cfa_pattern="GRBG"), ("dark", 1), "CFAPattern tag says GRBG but"),
    "a 12-bit frame": (_victim("linearity", 4, white_level=4095), ("linearity", 4),
                       "WhiteLevel tag is 4095 DN (12 bits) but"),
    "another black level": (_victim("dark", 3, black_level=2048), ("dark", 3),
                            "BlackLevel tag is 2048 DN but the frames' median is 800 DN"),
    "a dark frame of another size": (_resized_dark, ("dark", 0), "frame is 256 x 64 pixels but most frames are "
                                                                 "256 x 128"),
    # 2. lens regions against each other and the frame
    "overlapping rows": (_lenses(close=((64, 192), (0, 128)), far=((0, 128), (0, 128))), "dataset.yaml",
                         "lenses.far (rows [0, 128), cols [0, 128)) and lenses.close (rows [64, 192), cols [0, 128)) "
                         "overlap in rows [64, 128), cols [0, 128)"),
    "overlapping corner": (_lenses(far=((0, 160), (0, 80)), close=((128, 256), (48, 128))), "dataset.yaml",
                           "overlap in rows [128, 160), cols [48, 80)"),
    "region wider than the frame": (_lenses(close=((128, 256), (0, 192))), "dataset.yaml",
                                    "lenses.close (rows [128, 256), cols [0, 192)) does not fit the 256 x 128 "
                                    "frames"),
    # 3. the field sidecars against each other
    "a radiometer column site.yaml does not list": (
        _rename_column("L_560,", "L_561,"), "field/reference_radiometer.csv",
        "line 1, column 'L_561': L_561 has no channel in field/site.yaml's reference.channels_nm"),
    "a channel the radiometer file lacks": (
        _channels(lambda ref: ref["channels_nm"].append(900.0)), "field/site.yaml",
        "reference.channels_nm lists 900 nm but field/reference_radiometer.csv has no L_900 column"),
    # 4. more instances of each class: camera, YAML 1.1, frame size, bit depth, CFA, lens regions
    "an unquoted serial of another body": (  # YAML 1.1 would read 0417 as the octal 271
        _yaml_text("serial: SIM-0001", "serial: 0417"), "dataset.yaml",
        "camera.serial is '0417' but every frame's CameraSerialNumber tag says 'SIM-0001'"),
    "a field frame cropped by other software": (_resized("field", 4), ("field", 4),
                                                "frame is 128 x 128 pixels but most frames are 256 x 128"),
    "a 10-bit field frame": (_victim("field", 2, white_level=1023), ("field", 2),
                             "WhiteLevel tag is 1023 DN (10 bits) but 199 of 200 frames say 16383 DN (14 bits)"),
    "a field frame GBRG": (_victim("field", 6, cfa_pattern="GBRG"), ("field", 6),
                           "CFAPattern tag says GBRG but 199 of 200 frames say RGGB"),
    "one region inside the other": (_lenses(close=((32, 96), (32, 96))), "dataset.yaml",
                                    "overlap in rows [32, 96), cols [32, 96)"),
    # 5. the field frames' UTC times against the reference radiometer's readings
    "camera clock offset two hours off": (
        _site(camera_clock_utc_offset_h=-6.0), "field/reference_radiometer.csv",
        "its readings (2021-03-18T19:59:00 to 2021-03-18T21:01:00 UTC) miss every field sky frame: their UTC times "
        "(DateTimeOriginal less camera_clock_utc_offset_h -6 h) are 2021-03-18T22:00:00 to 2021-03-18T23:00:00, "
        "none within 305 s of a reading"),
    "clock offset off by twelve hours": (_site(camera_clock_utc_offset_h=8.0), "field/reference_radiometer.csv",
                                         "with camera_clock_utc_offset_h -4 every frame would have readings "
                                         "(times +12 h)"),
    "reference logged in local time without a zone": (
        _reference_times(lambda t: (t - timedelta(hours=4)).isoformat(timespec="milliseconds")),
        "field/reference_radiometer.csv",
        "with camera_clock_utc_offset_h 0 every frame would have readings (times -4 h)"),
    # 6. a regional spreadsheet's CSV: its own line only (its header read with ',' listed no channel of site.yaml)
    "reference radiometer from a regional spreadsheet": (
        _regional("field/reference_radiometer.csv"), "field/reference_radiometer.csv",
        "line 2, column 'L_380': '3,743970e-02' has a decimal comma (fields separated by ';': a spreadsheet's "
        "regional CSV)"),
    "reference file of another day": (
        _reference_times(lambda t: (t + timedelta(days=1)).isoformat(timespec="milliseconds") + "Z"),
        "field/reference_radiometer.csv", "miss every field sky frame"),
}

def _sorted_rows(experiment: str, by: list[str]):
    """frames.csv's rows sorted by other columns (a spreadsheet's sort): the file names out of order too."""
    def plant(root):
        path = root / experiment / "frames.csv"
        pd.read_csv(path).sort_values(by, kind="stable").to_csv(path, index=False)
    return plant


#: cases whose mistake is the dataset's only problem (no other check is set off by it)
ALONE = {"an unquoted serial of another body", "a field frame cropped by other software", "a 10-bit field frame",
         "a field frame GBRG", "one region inside the other", "camera clock offset two hours off",
         "clock offset off by twelve hours", "reference logged in local time without a zone",
         "reference radiometer from a regional spreadsheet", "reference file of another day"}

# case -> (plant, the file named, the phrase of the warning)
WARNINGS = {
    "a time stamp in the future": (_at("linearity", 5, datetime(2099, 3, 10, 9, 3)), ("linearity", 5),
                                   "DateTimeOriginal 2099-03-10T09:03:00 is in the future"),
    "a field frame in the future": (_at("field", 0, datetime(2098, 3, 18, 16, 0)), ("field", 0), "is in the future"),
    "a reset clock": (_at("dark", 2, datetime(2000, 1, 1)), ("dark", 2),
                      "DateTimeOriginal 2000-01-01T00:00:00 is 7739 days from the other"),
    "last year's frame": (_shifted("linearity", 7, days=-365), ("linearity", 7), "365 days from the other"),
    "out of order": (_shifted("linearity", 6, minutes=-30), ("linearity", 6),
                     "is out of order: the camera's file names put it between"),
    "out of order, later": (_shifted("dark", 1, hours=3), ("dark", 1), "is out of order"),
    "longitude with the wrong sign": (_site(longitude_deg=71.2754), "field/site.yaml",
                                      "the sun is below the horizon for"),
    "frames.csv rows sorted by lens": (_sorted_rows("linearity", ["lens", "file"]), "linearity/frames.csv",
                                       "the rows are not in the order the frames were taken: line 2 "
                                       "(raw/IMG_20210310_090340_00052.dng, 2021-03-10T09:03:40)"),
}


def _copy(clean: Path, tmp_path: Path, plant) -> Path:
    root = tmp_path / "dataset"
    shutil.copytree(clean, root)
    plant(root)
    write_md5sums(root)
    return root


def _named(root: Path, where) -> Path:
    return _frame(root, *where) if isinstance(where, tuple) else root / where


@pytest.mark.parametrize("case", list(PROBLEMS))
def test_inconsistency_stops_validate_naming_the_file(case, clean, tmp_path, capsys):
    """validate exits 1 and lists the problem under the file it names; the workflow's start-up check
    stops with it as its one line."""
    plant, where, phrase = PROBLEMS[case]
    root = _copy(clean, tmp_path, plant)
    file = _named(root, where)
    capsys.readouterr()
    assert main(["validate", str(root)]) == 1
    out = capsys.readouterr().out
    assert "Traceback" not in out
    block = out.split(f"\n{file.relative_to(root)} (", 1)
    assert len(block) == 2 and phrase in block[1].split("\n\n")[0], out
    if case in ALONE:
        assert any(line.startswith("1 problem in 1 file ") for line in out.splitlines()), out
    with pytest.raises(InputError) as err:
        DatasetIndex(root).load()
    assert phrase in str(err.value) or any(phrase in p.message or phrase in p.text() for p in err.value.problems)
    assert all(p.path is not None for p in err.value.problems)


@pytest.mark.parametrize("case", list(WARNINGS))
def test_suspicion_is_a_warning_naming_what_it_saw(case, clean, tmp_path, capsys):
    """validate passes (exit 0) and prints one warning line naming the file and what it saw."""
    plant, where, phrase = WARNINGS[case]
    root = _copy(clean, tmp_path, plant)
    file = _named(root, where)
    capsys.readouterr()
    assert main(["validate", str(root)]) == 0
    lines = capsys.readouterr().out.splitlines()
    warned = [line for line in lines if line.startswith("warning: ")]
    assert len(warned) == 1, lines
    assert warned[0].startswith(f"warning: {file.relative_to(root)}: ") and phrase in warned[0], warned
    assert lines[-1].startswith("ok: ")


def test_wrong_longitude_says_what_pvlib_computed(clean, tmp_path, capsys):
    """The warning gives the sun's computed depression, the UTC time and the site, and what the flipped
    sign would give (the simulated site: Quebec, 16:00 local on 18 March, longitude -71.2754); the
    workflow's start-up check prints the same warning and goes on."""
    root = _copy(clean, tmp_path, _site(longitude_deg=71.2754))
    main(["validate", str(root)])
    warned = [line for line in capsys.readouterr().out.splitlines() if line.startswith("warning: ")]
    assert "deg below at 2021-03-18T20:" in warned[0] and "longitude_deg 71.2754" in warned[0], warned
    assert "with longitude_deg -71.2754 it would be" in warned[0], warned
    DatasetIndex(root).load()                      # the workflow's start-up check: the same line, on stderr
    assert capsys.readouterr().err.splitlines() == warned


def test_clean_dataset_has_neither(clean, capsys):
    capsys.readouterr()
    assert main(["validate", str(clean)]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("ok: ")


def test_checks_take_the_tags_already_read(tmp_path):
    """No file is opened for the frames' checks: the tags validation read are compared (a check on
    records alone, with a made-up model among them and a frame of 2099)."""
    base = dict(make="Insta360", model="ONE", serial="1", cfa_pattern="RGGB", white_level=16383.0,
                black_level=800.0, shape=(256, 128))
    frames = [FrameTags("dark", f"raw/IMG_{k:04d}.dng", k + 2, "dark", tmp_path / f"IMG_{k:04d}.dng",
                        {**base, "time": datetime(2021, 3, 10, 9, k)}) for k in range(6)]
    frames[4] = replace(frames[4], tags={**base, "model": "HERO9", "time": datetime(2099, 1, 1)})
    meta = {"camera": {"make": "Insta360", "model": "ONE"}}
    problems, warnings = check_consistency(tmp_path, meta, {"far": ((0, 128), (0, 128))}, frames, ["dark"],
                                           now_utc=datetime(2024, 1, 1))
    assert [p.path.name for p in problems] == ["IMG_0004.dng"] and "HERO9" in problems[0].message
    assert [w.path.name for w in warnings] == ["IMG_0004.dng"] and "in the future" in warnings[0].message


def test_frames_without_reference_readings_are_named_in_one_warning(clean, tmp_path, capsys):
    """The reference stopped at 20:30 UTC: the field frames after it (camera 16:32 to 17:00, UTC 20:32 to
    21:00, one every 2 minutes: 15 frames) have no reading within 5 s (field.reference_window_s / 2) and are
    named in one warning; validate passes (the frames before have their match-ups)."""
    def stop_early(root):
        path = root / "field" / "reference_radiometer.csv"
        head, *rows = path.read_text().splitlines()
        path.write_text("\n".join([head] + [r for r in rows if r < "2021-03-18T20:30"]) + "\n")

    root = _copy(clean, tmp_path, stop_early)
    capsys.readouterr()
    assert main(["validate", str(root)]) == 0
    warned = [line for line in capsys.readouterr().out.splitlines() if line.startswith("warning: ")]
    assert len(warned) == 1, warned
    assert warned[0].startswith("warning: field/raw/: no reference reading within 5 s of its UTC time"), warned
    assert "covers 2021-03-18T19:59:00 to 2021-03-18T20:29:59 UTC" in warned[0] and "[15 files]" in warned[0], warned


def test_black_level_of_one_iso_is_named(clean, tmp_path, capsys):
    """Every ISO 3200 dark frame's BlackLevel tag 1024 DN against 800 DN for the rest (a camera mode with
    its own black level): each frame is a problem, listed under the folder."""
    def plant(root):
        table = pd.read_csv(root / "dark" / "frames.csv")
        for name in table["file"]:
            if read_tags(root / "dark" / name)["iso"] == 3200:
                _rewrite(root / "dark" / name, black_level=1024)

    root = _copy(clean, tmp_path, plant)
    capsys.readouterr()
    assert main(["validate", str(root)]) == 1
    out = capsys.readouterr().out
    assert "\ndark/raw/ (5 problems)\n" in out and "BlackLevel tag is 1024 DN but the frames' median is 800 DN" in out, out


def test_a_stage_run_directly_makes_validates_checks(clean, tmp_path, config):
    """run_stage on a dataset folder (a stage run from Python, not by the workflow) stops with validate's
    line for a frame of another camera, before it decodes anything, and writes no artefact."""
    from pipeline.runner.workflow import run_stage

    root = _copy(clean, tmp_path, _victim("dark", 3, model="ONE X2"))
    out = tmp_path / "dark_far.nc"
    with pytest.raises(InputError) as err:
        run_stage("dark", root, config, {"far": out})
    assert str(err.value).startswith(f"{_frame(root, 'dark', 3)}: Model tag says 'ONE X2'"), err.value
    assert not out.exists()


def test_dark_stage_names_a_black_level_tag_far_from_the_data(clean, tmp_path, config):
    """Every dark frame tagged BlackLevel 0 (a converter that drops the tag) while the sensor's dark level
    is 800 DN: consistent across frames, so validate passes, but the dark stage measures 800 DN at every
    ISO's shortest exposure, more than dark.black_level_tag_max_fraction (1 %) of the 16383 DN white level
    from the tag, and says so per ISO (log and artefact attribute)."""
    from pipeline.runner.workflow import run_stage

    root = tmp_path / "dataset"
    root.mkdir()
    shutil.copytree(clean / "dark", root / "dark")
    shutil.copy(clean / "dataset.yaml", root)
    for name in pd.read_csv(root / "dark" / "frames.csv")["file"]:
        _rewrite(root / "dark" / name, black_level=0)
    write_md5sums(root)
    art = run_stage("dark", root, config, {"far": tmp_path / "far.nc"})["far"]
    note = art.attrs["black_level_tag_note"]
    assert note.startswith("ISO 100: dark level 800.") and "but the BlackLevel tag says 0 DN" in note, note
    assert note.count("ISO ") == 6 and "dark.black_level_tag_max_fraction = 0.01" in note, note


def test_a_lens_named_no_is_a_lens_named_no(clean, tmp_path, capsys):
    """YAML 1.1 reads an unquoted ``no:`` as False: a lens named ``no`` in dataset.yaml (and frames.csv)
    stays the lens 'no' (every frames.csv row names a lens dataset.yaml has), and validate passes."""
    def plant(root):
        path = root / "dataset.yaml"
        path.write_text(path.read_text().replace("  close:\n", "  no:\n"))
        for experiment in ("dark", "linearity", "field"):
            table = pd.read_csv(root / experiment / "frames.csv")
            table["lens"] = table["lens"].replace("close", "no")
            table.to_csv(root / experiment / "frames.csv", index=False)

    root = _copy(clean, tmp_path, plant)
    capsys.readouterr()
    assert main(["validate", str(root)]) == 0, capsys.readouterr().out
    assert DatasetIndex(root).lenses() == ["far", "no"]


def test_the_runs_clock_search_decides_what_no_match_up_means(clean, tmp_path):
    """The camera clock offset two hours off (frames 22:00 to 23:00 UTC, readings up to 21:01): with the
    schema's field.clock_offset_search_s (300 s) no match-up is possible, a problem; a run whose config
    searches 3 hours (the workflow's start-up check reads the run's field section) could shift the frames
    onto the readings, so the check only warns about the frames without a reading in their window."""
    from pipeline.io.validation import inspect_dataset

    root = _copy(clean, tmp_path, _site(camera_clock_utc_offset_h=-6.0))
    _, problems = inspect_dataset(root)
    assert [p.path.name for p in problems] == ["reference_radiometer.csv"], problems
    warnings = []
    _, problems = inspect_dataset(root, warnings=warnings, field_settings={"clock_offset_search_s": 10800.0})
    assert problems == []
    missed = [w for w in warnings if w.message.startswith("no reference reading within 5 s")]
    assert len(missed) == 31, warnings
    index = DatasetIndex(root, {"field": {"clock_offset_search_s": 10800.0, "reference_window_s": 10.0}})
    assert index.lenses() == ["far", "close"]

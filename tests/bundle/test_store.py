"""The calibration store (issue 12, item 4): publish, never overwrite, detect tampering, select by date.

The bundle is the session's tiny calibrated camera (the ``calibrated`` fixture, tests/conftest.py);
a second bundle of different content is the same file with one global attribute added (netCDF4),
so it is still a valid bundle of the same camera. Frames of other dates are the fixture's absolute
frame rewritten with another DateTimeOriginal (the same pixels and tags otherwise).
"""

from __future__ import annotations

import csv
import hashlib
import os
import shutil
import stat
from datetime import datetime
from pathlib import Path

import netCDF4
import pytest
import xarray as xr

from pipeline.cli import main
from pipeline.io.rawio import read_raw, read_tags, write_dng

STAGE_FOLDERS = ("dark", "linearity", "geometry", "rolloff", "spectral", "absolute", "immersion")


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _index(store: Path) -> list[dict]:
    with open(store / "index.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _variant(bundle: Path, folder: Path, note: str) -> Path:
    """A bundle of other content: the same file with a global attribute added."""
    out = folder / f"{note}.nc"
    shutil.copyfile(bundle, out)
    with netCDF4.Dataset(out, "a") as nc:
        nc.setncattr("note", note)
    return out


def _frame_at(calibrated, when: datetime, folder: Path) -> Path:
    """The fixture's first absolute frame of the close lens, rewritten with DateTimeOriginal ``when``."""
    root = calibrated[0]
    lines = [line.split(",") for line in (root / "absolute" / "frames.csv").read_text().splitlines()[1:]]
    src = read_raw(root / "absolute" / next(f for f, lens, kind in lines if lens == "close" and kind == "signal"))
    out = folder / f"sky_{when:%Y%m%d}.dng"
    write_dng(out, src.cfa, exposure_s=src.exposure_s, iso=src.iso, time=when, black_level=src.black_level,
              white_level=src.white_level, cfa_pattern=src.cfa_pattern, make=src.make, model=src.model,
              serial=src.serial)
    return out


def test_publish_files_the_bundle_dated_by_its_lab_data_and_never_twice(calibrated, tmp_path, capsys):
    root, _, _, _, bundle, meta = calibrated
    store = tmp_path / "store"
    assert main(["publish", str(bundle), "--dataset", str(root), "--store", str(store)]) == 0
    assert capsys.readouterr().out.startswith("published: ")
    [row] = _index(store)
    # the validity start: the latest DateTimeOriginal of every lab frame, read here from the files themselves
    latest = max(read_tags(p)["time"] for stage in STAGE_FOLDERS for p in (root / stage).rglob("*.dng"))
    assert row["valid_from"] == latest.replace(microsecond=0).isoformat()
    assert row["serial"] == meta["camera"]["serial"] and row["sha256"] == _sha(bundle)
    filed = store / row["file"]
    assert filed.parent.name == meta["camera"]["serial"]
    assert filed.name == f"{latest:%Y%m%dT%H%M%S}_{row['sha256'][:16]}.nc"
    assert _sha(filed) == _sha(bundle) and not filed.stat().st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH)
    # the same content again: nothing written, a message saying where it is
    before = (store / "index.csv").read_bytes()
    assert main(["publish", str(bundle), "--valid-from", "2030-01-01", "--store", str(store)]) == 0
    assert capsys.readouterr().out.startswith(f"already published: {store}/{row['file']}")
    assert (store / "index.csv").read_bytes() == before and len(list(store.glob("*/*.nc"))) == 1
    assert main(["verify-store", str(store)]) == 0
    # without a validity start the command refuses (usage error, argparse)
    with pytest.raises(SystemExit) as exc:
        main(["publish", str(bundle), "--store", str(store)])
    assert exc.value.code == 2


def test_same_date_other_content_gets_its_own_entry_and_tampering_is_detected(calibrated, tmp_path, capsys):
    bundle = calibrated[4]
    store = tmp_path / "store"
    other = _variant(bundle, tmp_path, "recalibrated")
    for path in (bundle, other):
        assert main(["publish", str(path), "--valid-from", "2021-03-01", "--store", str(store)]) == 0
    first, second = _index(store)
    assert first["valid_from"] == second["valid_from"] == "2021-03-01T00:00:00"
    assert first["file"] != second["file"] and _sha(store / first["file"]) == _sha(bundle)
    assert _sha(store / second["file"]) == _sha(other)
    capsys.readouterr()
    # of two calibrations valid from the same time the later published one is used
    frame = _frame_at(calibrated, datetime(2021, 3, 18, 16, 0, 0), tmp_path)
    out = tmp_path / "sky.nc"
    assert main(["apply", "--store", str(store), "--no-pixels", str(frame), "-o", str(out)]) == 0
    with xr.open_dataset(out) as ds:
        assert ds.attrs["calibration_bundle"] == str(store / second["file"])
    # a published file changed afterwards: verify-store and apply both name it
    victim = store / second["file"]
    os.chmod(victim, 0o644)
    with netCDF4.Dataset(victim, "a") as nc:
        nc.setncattr("note", "edited after publishing")
    capsys.readouterr()
    assert main(["verify-store", str(store)]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err == [line for line in err if line.startswith(f"error: {victim}: changed after it was published")]
    assert len(err) == 1
    assert main(["apply", "--store", str(store), "--no-pixels", "--overwrite", str(frame), "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {victim}: changed after it was published")
    # a file put into the store by hand, beside the index, is named too
    stray = victim.with_name("20210301T000000_0000000000000000.nc")
    shutil.copyfile(bundle, stray)
    assert main(["verify-store", str(store)]) == 1
    err = capsys.readouterr().err.splitlines()
    assert f"error: {stray}: is not in the store's index (added by hand?)" in err and len(err) == 2


def test_apply_selects_the_calibration_valid_at_each_frame(calibrated, tmp_path, capsys):
    bundle = calibrated[4]
    store = tmp_path / "store"
    spring = _variant(bundle, tmp_path, "spring")
    assert main(["publish", str(bundle), "--valid-from", "2021-01-01", "--store", str(store)]) == 0
    assert main(["publish", str(spring), "--valid-from", "2021-04-01T12:00:00", "--store", str(store)]) == 0
    winter, april = _index(store)
    march = _frame_at(calibrated, datetime(2021, 3, 18, 16, 0, 0), tmp_path)
    may = _frame_at(calibrated, datetime(2021, 5, 2, 9, 30, 0), tmp_path)
    out = tmp_path / "sky.nc"
    capsys.readouterr()
    assert main(["apply", "--store", str(store), "--no-pixels", str(march), str(may), "-o", str(out)]) == 0
    # one output per calibration, named after its camera and validity start
    for row, frame in ((winter, march), (april, may)):
        start = datetime.fromisoformat(row["valid_from"])
        path = tmp_path / f"sky_{row['serial']}_{start:%Y%m%dT%H%M%S}.nc"
        with xr.open_dataset(path) as ds:
            assert ds.attrs["calibration_bundle"] == str(store / row["file"])
            assert list(ds["frame_file"].values) == [str(frame)]
    # a frame older than every calibration: one line naming the frame and the earliest validity start
    old = _frame_at(calibrated, datetime(2020, 12, 31, 23, 59, 0), tmp_path)
    capsys.readouterr()
    assert main(["apply", "--store", str(store), str(old), "-o", str(tmp_path / "old.nc")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {old}: taken 2020-12-31T23:59:00: no calibration of camera {winter['serial']} in {store} "
                   "is valid then (the earliest is valid from 2021-01-01T00:00:00)"]
    assert not (tmp_path / "old.nc").exists()

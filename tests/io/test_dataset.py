"""Tests for pipeline.io.dataset: layout validation, frames.csv, MD5SUMS, sidecars."""

from __future__ import annotations

import hashlib
from datetime import datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.io.dataset import (
    EXPERIMENT_COLUMNS, EXPERIMENTS, Dataset, check_md5, inspect_layout, open_dataset, read_photodiode,
    read_reference_radiometer, read_site, read_source_reference, read_source_spectrum, read_water,
    write_md5sums,
)
from pipeline.errors import InputError
from pipeline.io.rawio import read_raw, write_dng

META = {
    "layout": 1,
    "camera": {"make": "Insta360", "model": "ONE", "serial": "SIM-0001"},
    "lenses": {"far": {"rows": [0, 32], "cols": [0, 32]}, "close": {"rows": [32, 64], "cols": [0, 32]}},
    "chessboard": {"inner_corners": [8, 6], "square_mm": {"air": 30.0, "water": 20.0}},
    "description": "tiny test dataset",
}


def _dng(path: Path, seed: int, exposure_s=0.01, iso=100) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cfa = np.random.default_rng(seed).integers(0, 16384, (64, 32), dtype=np.uint16)
    write_dng(path, cfa, exposure_s=exposure_s, iso=iso, time=datetime(2021, 3, 18, 16, 2, seed % 60),
              black_level=512)


def _frames(root: Path, experiment: str, rows: list[dict], make_files=True) -> None:
    folder = root / experiment
    folder.mkdir(parents=True, exist_ok=True)
    for i, row in enumerate(rows):
        if make_files:
            _dng(folder / row["file"], seed=i + 10 * EXPERIMENTS.index(experiment))
    pd.DataFrame(rows).to_csv(folder / "frames.csv", index=False)


def make_dataset(root: Path) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "dataset.yaml").write_text(yaml.safe_dump(META, sort_keys=False))
    _frames(root, "dark", [
        {"file": "raw/d0.dng", "lens": "both", "kind": "dark", "temperature_c": 21.5},
        {"file": "raw/d1.dng", "lens": "both", "kind": "dark", "temperature_c": ""},
    ])
    _frames(root, "linearity", [
        {"file": "raw/l0.dng", "lens": "far", "kind": "signal", "sweep": "exposure"},
        {"file": "raw/l1.dng", "lens": "far", "kind": "dark", "sweep": "gain"},
    ])
    _frames(root, "spectral", [
        {"file": "raw/s0.dng", "lens": "close", "kind": "signal", "wavelength_nm": 450},
        {"file": "raw/s1.dng", "lens": "close", "kind": "dark", "wavelength_nm": ""},
    ])
    pd.DataFrame({"wavelength_nm": [450, 550], "signal": [1.0, 2.0], "signal_std": [0.01, 0.02]}).to_csv(
        root / "spectral" / "photodiode.csv", index=False)
    write_md5sums(root)
    return root


@pytest.fixture
def ds_root(tmp_path) -> Path:
    return make_dataset(tmp_path / "ds")


def _expect(root: Path, file: Path, *phrases: str) -> str:
    with pytest.raises(InputError) as err:
        open_dataset(root)
    msg = str(err.value)
    assert msg.startswith(f"{file}: "), msg
    assert "\n" not in msg
    for phrase in phrases:
        assert phrase in msg, msg
    return msg


def _rewrite_csv(path: Path, edit) -> None:
    frame = pd.read_csv(path, dtype=str, keep_default_na=False)
    frame = edit(frame)
    frame.to_csv(path, index=False)


# --------------------------------------------------------------------- good


def test_open_valid_dataset(ds_root):
    ds = open_dataset(ds_root)
    assert isinstance(ds, Dataset)
    assert ds.root == ds_root.resolve()
    assert ds.experiments() == ["dark", "linearity", "spectral"]
    assert ds.lenses == {"far": ((0, 32), (0, 32)), "close": ((32, 64), (0, 32))}
    assert ds.meta["camera"]["model"] == "ONE"
    frames = ds.frames("spectral")
    assert list(frames["file"]) == ["raw/s0.dng", "raw/s1.dng"]
    assert frames["wavelength_nm"].iloc[0] == 450.0 and np.isnan(frames["wavelength_nm"].iloc[1])
    assert all(isinstance(p, Path) and p.is_absolute() and p.is_file() for p in frames["path"])
    dark = ds.frames("dark")
    assert dark["temperature_c"].iloc[0] == 21.5 and np.isnan(dark["temperature_c"].iloc[1])
    assert ds.raw_files("linearity") == [ds.root / "linearity/raw/l0.dng", ds.root / "linearity/raw/l1.dng"]
    with pytest.raises(InputError, match="experiment folder is absent"):
        ds.frames("field")
    with pytest.raises(ValueError):
        ds.frames("nonsense")


def test_frames_is_cached(ds_root):
    ds = open_dataset(ds_root, check_frames=False)
    first = ds.frames("linearity")
    (ds_root / "linearity" / "frames.csv").write_text("garbage\n")
    pd.testing.assert_frame_equal(ds.frames("linearity"), first)


def test_experiment_columns_cover_contract():
    assert set(EXPERIMENT_COLUMNS) == set(EXPERIMENTS)
    assert EXPERIMENT_COLUMNS["rolloff"] == ("medium", "azimuth_deg", "angle_deg")
    assert EXPERIMENT_COLUMNS["immersion"] == ("condition", "water_height_cm")


def test_write_md5sums_and_check_md5(ds_root):
    lines = (ds_root / "MD5SUMS").read_text().splitlines()
    paths = [line.split("  ", 1)[1] for line in lines]
    assert paths == sorted(paths) and "MD5SUMS" not in paths and "dataset.yaml" in paths
    rel = "linearity/raw/l0.dng"
    digest = hashlib.md5((ds_root / rel).read_bytes()).hexdigest()
    assert f"{digest}  {rel}" in lines
    ds = open_dataset(ds_root)
    check_md5(ds, rel, digest)
    check_md5(ds, ds.root / rel, read_raw(ds.root / rel).md5)  # absolute path works too
    with pytest.raises(InputError) as err:
        check_md5(ds, rel, "0" * 32)
    assert str(err.value) == (f"{ds.root / rel}: checksum mismatch "
                              f"(MD5SUMS says {digest}, file is {'0' * 32})")
    with pytest.raises(InputError, match="not listed in MD5SUMS"):
        check_md5(ds, "linearity/raw/zzz.dng", digest)


def test_md5_mismatch_after_file_changes(ds_root):
    """A raw file replaced after MD5SUMS was written is caught by read_raw + check_md5."""
    rel = "dark/raw/d0.dng"
    _dng(ds_root / rel, seed=99)
    ds = open_dataset(ds_root)
    with pytest.raises(InputError) as err:
        check_md5(ds, rel, read_raw(ds.root / rel).md5)
    assert str(err.value).startswith(f"{ds.root / rel}: checksum mismatch (MD5SUMS says ")


# --------------------------------------------------------------------- frames.csv failures


def test_row_pointing_at_absent_file(ds_root):
    (ds_root / "linearity" / "raw" / "l1.dng").unlink()
    _expect(ds_root, ds_root / "linearity" / "frames.csv", "line 3", "'file'", "raw/l1.dng does not exist")


def test_file_not_in_md5sums(ds_root):
    _dng(ds_root / "linearity" / "raw" / "l2.dng", seed=5)
    _rewrite_csv(ds_root / "linearity" / "frames.csv", lambda f: pd.concat(
        [f, pd.DataFrame([{"file": "raw/l2.dng", "lens": "far", "kind": "signal", "sweep": "gain"}])]))
    _expect(ds_root, ds_root / "linearity" / "frames.csv", "line 4", "linearity/raw/l2.dng is not listed in MD5SUMS")


def test_missing_column(ds_root):
    _rewrite_csv(ds_root / "linearity" / "frames.csv", lambda f: f.rename(columns={"sweep": "sweeps"}))
    _expect(ds_root, ds_root / "linearity" / "frames.csv", "missing column 'sweep'")


def test_missing_common_column(ds_root):
    _rewrite_csv(ds_root / "spectral" / "frames.csv", lambda f: f.drop(columns=["kind"]))
    _expect(ds_root, ds_root / "spectral" / "frames.csv", "missing column 'kind'")


def test_bad_kind(ds_root):
    def edit(f):
        f.loc[1, "kind"] = "bright"
        return f
    _rewrite_csv(ds_root / "linearity" / "frames.csv", edit)
    _expect(ds_root, ds_root / "linearity" / "frames.csv", "line 3", "column 'kind'", "'bright' is not one of signal, dark")


def test_signal_frame_in_dark_experiment(ds_root):
    def edit(f):
        f.loc[0, "kind"] = "signal"
        return f
    _rewrite_csv(ds_root / "dark" / "frames.csv", edit)
    _expect(ds_root, ds_root / "dark" / "frames.csv", "line 2", "must be 'dark'")


@pytest.mark.parametrize("column, value, phrase", [
    ("lens", "middle", "'middle' is not one of far, close, both"),
    ("sweep", "iso", "'iso' is not one of exposure, gain"),
    ("file", "../escape.dng", "not a path inside linearity/"),
])
def test_bad_values_linearity(ds_root, column, value, phrase):
    def edit(f):
        f.loc[0, column] = value
        return f
    _rewrite_csv(ds_root / "linearity" / "frames.csv", edit)
    _expect(ds_root, ds_root / "linearity" / "frames.csv", "line 2", f"column '{column}'", phrase)


@pytest.mark.parametrize("value, phrase", [("-5", "-5.0 must be positive"), ("many", "'many' is not a number")])
def test_bad_photons_per_pixel(ds_root, value, phrase):
    """The optional photon count of a linearity frame is a positive number or empty."""
    def edit(f):
        f["photons_per_pixel"] = ["120.5", ""]
        f.loc[0, "photons_per_pixel"] = value
        return f
    _rewrite_csv(ds_root / "linearity" / "frames.csv", edit)
    _expect(ds_root, ds_root / "linearity" / "frames.csv", "line 2", "'photons_per_pixel'", phrase)


def test_photons_per_pixel_is_read_as_a_number(ds_root):
    _rewrite_csv(ds_root / "linearity" / "frames.csv", lambda f: f.assign(photons_per_pixel=["120.5", ""]))
    write_md5sums(ds_root)
    frames = open_dataset(ds_root).frames("linearity")
    assert frames["photons_per_pixel"].iloc[0] == 120.5 and np.isnan(frames["photons_per_pixel"].iloc[1])


def test_non_numeric_wavelength(ds_root):
    def edit(f):
        f.loc[0, "wavelength_nm"] = "blue"
        return f
    _rewrite_csv(ds_root / "spectral" / "frames.csv", edit)
    _expect(ds_root, ds_root / "spectral" / "frames.csv", "line 2", "'wavelength_nm'", "'blue' is not a number")


def test_empty_wavelength_on_signal_frame(ds_root):
    def edit(f):
        f.loc[0, "wavelength_nm"] = ""
        return f
    _rewrite_csv(ds_root / "spectral" / "frames.csv", edit)
    _expect(ds_root, ds_root / "spectral" / "frames.csv", "line 2", "'wavelength_nm'", "value is empty")


def test_ragged_and_empty_csv(ds_root):
    path = ds_root / "dark" / "frames.csv"
    path.write_text("file,lens,kind\nraw/d0.dng,both\n")
    _expect(ds_root, path, "line 2", "2 fields but the header has 3")
    path.write_text("")
    _expect(ds_root, path, "empty file")
    path.write_text("file,lens,kind\n")
    _expect(ds_root, path, "no data rows")


def test_missing_frames_csv(ds_root):
    (ds_root / "dark" / "frames.csv").unlink()
    _expect(ds_root, ds_root / "dark" / "frames.csv", "file not found")


def test_check_frames_false_defers_validation(ds_root):
    (ds_root / "dark" / "frames.csv").write_text("file\n")
    ds = open_dataset(ds_root, check_frames=False)
    with pytest.raises(InputError, match="missing column 'lens'"):
        ds.frames("dark")


# --------------------------------------------------------------------- dataset.yaml / MD5SUMS


@pytest.mark.parametrize("edit, phrase", [
    (lambda m: m.update(layout=2), "layout is 2"),
    (lambda m: m.pop("layout"), "missing key 'layout'"),
    (lambda m: m.pop("camera"), "'camera'"),
    (lambda m: m["camera"].pop("model"), "camera.model"),
    (lambda m: m.pop("lenses"), "'lenses'"),
    (lambda m: m["lenses"]["far"].update(rows=[1, 32]), "lenses.far.rows"),
    (lambda m: m["lenses"]["far"].update(cols=[0]), "lenses.far.cols"),
    (lambda m: m["lenses"]["far"].update(cols=[32, 0]), "start < stop"),
    (lambda m: m["lenses"].update(both={"rows": [0, 2], "cols": [0, 2]}), "invalid lens name 'both'"),
    (lambda m: m["lenses"]["far"].update(projection="pinhole"), "lenses.far.projection is 'pinhole'"),
    (lambda m: m["chessboard"].update(inner_corners=[8]), "chessboard.inner_corners"),
    (lambda m: m["chessboard"]["square_mm"].update(air=-1), "chessboard.square_mm.air must be positive"),
])
def test_bad_dataset_yaml(ds_root, edit, phrase):
    meta = yaml.safe_load((ds_root / "dataset.yaml").read_text())
    edit(meta)
    (ds_root / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    _expect(ds_root, ds_root.resolve() / "dataset.yaml", phrase)


def test_dataset_yaml_syntax_error_and_absence(ds_root):
    path = ds_root.resolve() / "dataset.yaml"
    path.write_text("layout: 1\ncamera: {make: [unclosed\n")
    _expect(ds_root, path, "not valid YAML")
    path.write_text("- just\n- a list\n")
    _expect(ds_root, path, "must be a YAML mapping")
    path.unlink()
    _expect(ds_root, path, "file not found")


def test_bad_md5sums(ds_root):
    path = ds_root.resolve() / "MD5SUMS"
    text = path.read_text()
    path.write_text(text + "not-a-checksum  x\n")
    _expect(ds_root, path, f"line {len(text.splitlines()) + 1}", "expected '<32 hex digits>  <relative path>'")
    path.write_text(text + text.splitlines()[0] + "\n")
    _expect(ds_root, path, "listed twice")
    path.unlink()
    _expect(ds_root, path, "file not found")


def test_missing_root(tmp_path):
    with pytest.raises(InputError, match="dataset folder not found"):
        open_dataset(tmp_path / "nothing")


# --------------------------------------------------------------------- several problems at once


def test_several_mistakes_are_reported_together(ds_root):
    root = ds_root.resolve()
    meta = yaml.safe_load((root / "dataset.yaml").read_text())
    meta["camera"].pop("model")
    (root / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    (root / "MD5SUMS").write_text((root / "MD5SUMS").read_text() + "not-a-checksum  x\n")
    n_md5 = len((root / "MD5SUMS").read_text().splitlines())

    def lin(f):
        f.loc[0, "lens"] = "middle"
        f.loc[1, "sweep"] = "iso"
        return f
    _rewrite_csv(root / "linearity" / "frames.csv", lin)

    def spec(f):
        f.loc[0, "wavelength_nm"] = "blue"
        return f
    _rewrite_csv(root / "spectral" / "frames.csv", spec)
    (root / "dark" / "raw" / "d1.dng").unlink()
    check = inspect_layout(root)
    found = [(p.path, p.line, p.column) for p in check.problems]
    assert found == [
        (root / "dataset.yaml", None, None),
        (root / "MD5SUMS", n_md5, None),
        (root / "dark" / "frames.csv", 3, "file"),
        (root / "linearity" / "frames.csv", 2, "lens"),
        (root / "linearity" / "frames.csv", 3, "sweep"),
        (root / "spectral" / "frames.csv", 2, "wavelength_nm"),
    ]
    assert all(p.fix for p in check.problems)
    with pytest.raises(InputError) as err:
        open_dataset(root)
    assert str(err.value) == (f"{root / 'dataset.yaml'}: camera.model must be a non-empty string "
                              f"(and 5 more problems; python -m pipeline validate {root} lists them all)")
    assert err.value.problems == check.problems


def test_sidecar_reader_reports_every_bad_row(tmp_path):
    path = tmp_path / "photodiode.csv"
    path.write_text("wavelength_nm,signal,signal_std\n450,x,0.1\n460,1.0,-0.5\n470,1.0\n")
    with pytest.raises(InputError) as err:
        read_photodiode(path)
    assert [(p.line, p.column) for p in err.value.problems] == [(4, None), (2, "signal"), (3, "signal_std")]
    assert str(err.value).startswith(f"{path}: line 4: 2 fields but the header has 3 (and 2 more problems")


# --------------------------------------------------------------------- sidecars


def test_read_photodiode(ds_root):
    ds = open_dataset(ds_root)
    table = read_photodiode(ds)
    assert list(table.columns) == ["wavelength_nm", "signal", "signal_std"]
    assert table["signal"].tolist() == [1.0, 2.0]
    path = ds_root / "spectral" / "photodiode.csv"
    path.write_text("wavelength_nm,signal\n450,1\n")
    with pytest.raises(InputError) as err:
        read_photodiode(path)
    assert str(err.value) == (f"{path}: missing column 'signal_std' (required: wavelength_nm, signal, signal_std; "
                              "the header has: wavelength_nm, signal)")
    path.write_text("wavelength_nm,signal,signal_std\n450,1,-0.5\n")
    with pytest.raises(InputError, match=r"line 2, column 'signal_std': -0.5 must not be negative"):
        read_photodiode(path)


def test_read_source_files(tmp_path):
    spectrum = tmp_path / "source_spectrum.csv"
    spectrum.write_text("wavelength_nm,radiance,radiance_std\n400,0.5,0.01\n500,1.0,0.02\n")
    assert read_source_spectrum(spectrum)["radiance"].tolist() == [0.5, 1.0]
    reference = tmp_path / "source_reference.csv"
    reference.write_text("wavelength_nm,radiance_W_sr_m2_nm,uncertainty_rel\n589,0.123,0.02\n")
    assert read_source_reference(reference)["radiance_W_sr_m2_nm"].iloc[0] == 0.123
    reference.write_text("wavelength_nm,radiance_W_sr_m2_nm,uncertainty_rel\n589,,0.02\n")
    with pytest.raises(InputError, match=r"source_reference.csv: line 2, column 'radiance_W_sr_m2_nm': value is empty"):
        read_source_reference(reference)


def test_read_water(tmp_path):
    path = tmp_path / "water.yaml"
    path.write_text("temperature_c: 18.5\nsalinity_psu: 35\n")
    assert read_water(path) == {"temperature_c": 18.5, "salinity_psu": 35.0}
    path.write_text("temperature_c: warm\nsalinity_psu: 35\n")
    with pytest.raises(InputError, match=r"water.yaml: temperature_c must be a number"):
        read_water(path)
    path.write_text("temperature_c: 18\n")
    with pytest.raises(InputError, match=r"water.yaml: missing key 'salinity_psu'"):
        read_water(path)


def test_read_reference_radiometer(tmp_path):
    path = tmp_path / "reference_radiometer.csv"
    path.write_text("time,L_443,L_555\n2021-03-18T10:00:00Z,0.01,0.02\n2021-03-18T10:00:00.166,,0.021\n")
    table = read_reference_radiometer(path)
    assert table.attrs["channels_nm"] == [443.0, 555.0]
    assert str(table["time"].dt.tz) == "UTC"
    assert table["time"].iloc[1] == pd.Timestamp("2021-03-18T10:00:00.166Z")
    assert np.isnan(table["L_443"].iloc[1])
    assert table["L_555"].tolist() == [0.02, 0.021] and table["L_443"].iloc[0] == 0.01
    # a cell that is not a finite number: every such cell named with its line (the columns are converted
    # whole when all cells are valid, cell by cell otherwise)
    path.write_text("time,L_443,L_555\n2021-03-18T10:00:00Z,0.01,0.02\n2021-03-18T10:00:01Z,abc,0.02\n"
                    "2021-03-18T10:00:02Z,0.01,inf\n")
    with pytest.raises(InputError) as bad:
        read_reference_radiometer(path)
    assert "line 3, column 'L_443': 'abc' is not a number (and 1 more problem)" in str(bad.value)
    assert [p.text() for p in bad.value.problems][1].endswith("line 4, column 'L_555': 'inf' is not a finite number")
    path.write_text("time,L_443\nyesterday,0.01\n")
    with pytest.raises(InputError, match=r"line 2, column 'time': 'yesterday' is not an ISO 8601 time"):
        read_reference_radiometer(path)
    path.write_text("time,E_443\n2021-03-18T10:00:00Z,0.01\n")
    with pytest.raises(InputError, match="no radiance columns"):
        read_reference_radiometer(path)


def test_read_site(tmp_path):
    path = tmp_path / "site.yaml"
    site = {"latitude_deg": 43.7, "longitude_deg": 7.3, "camera_clock_utc_offset_h": 1,
            "reference": {"name": "C-OPS", "channels_nm": [443, 555], "fwhm_nm": 10, "half_fov_deg": 9}}
    path.write_text(yaml.safe_dump(site))
    out = read_site(path)
    assert out["reference"]["channels_nm"] == [443.0, 555.0] and out["camera_clock_utc_offset_h"] == 1.0
    site["latitude_deg"] = 123
    path.write_text(yaml.safe_dump(site))
    with pytest.raises(InputError, match=r"site.yaml: latitude_deg must be within"):
        read_site(path)
    site["latitude_deg"] = 43.7
    del site["reference"]["half_fov_deg"]
    path.write_text(yaml.safe_dump(site))
    with pytest.raises(InputError, match=r"site.yaml: missing key 'reference.half_fov_deg'"):
        read_site(path)


def test_rolloff_immersion_geometry_columns(ds_root):
    _frames(ds_root, "rolloff", [
        {"file": "raw/r0.dng", "lens": "far", "kind": "signal", "medium": "air", "azimuth_deg": 0, "angle_deg": -30.5},
        {"file": "raw/r1.dng", "lens": "far", "kind": "dark", "medium": "air", "azimuth_deg": 90, "angle_deg": ""},
    ])
    _frames(ds_root, "immersion", [
        {"file": "raw/i0.dng", "lens": "close", "kind": "signal", "condition": "air", "water_height_cm": ""},
        {"file": "raw/i1.dng", "lens": "close", "kind": "signal", "condition": "water", "water_height_cm": 5},
    ])
    _frames(ds_root, "geometry", [{"file": "raw/g0.dng", "lens": "both", "kind": "signal", "medium": "water"}])
    write_md5sums(ds_root)
    ds = open_dataset(ds_root)
    assert ds.experiments() == ["dark", "linearity", "geometry", "rolloff", "spectral", "immersion"]
    assert ds.frames("rolloff")["angle_deg"].iloc[0] == -30.5
    assert ds.frames("immersion")["water_height_cm"].iloc[1] == 5.0

    def edit(f):
        f.loc[1, "water_height_cm"] = ""
        return f
    _rewrite_csv(ds_root / "immersion" / "frames.csv", edit)
    _expect(ds_root, ds_root / "immersion" / "frames.csv", "line 3", "'water_height_cm'", "value is empty")

    def edit_medium(f):
        f.loc[0, "medium"] = "oil"
        return f
    _rewrite_csv(ds_root / "geometry" / "frames.csv", edit_medium)
    _expect(ds_root, ds_root / "geometry" / "frames.csv", "line 2", "'medium'", "'oil' is not one of air, water")


def test_projection_declared_per_lens(ds_root):
    """docs/dataset-format.md: a lens region may declare ``projection: rectilinear``; without the key it is a fisheye."""
    meta = yaml.safe_load((ds_root / "dataset.yaml").read_text())
    meta["lenses"]["far"]["projection"] = "rectilinear"
    (ds_root / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    ds = open_dataset(ds_root)
    others = [lens for lens in ds.lenses if lens != "far"]
    assert ds.projection("far") == "rectilinear"
    assert others and all(ds.projection(lens) == "fisheye" for lens in others)


def test_decode_ahead_setting_chooses_where_frames_are_decoded(ds_root, monkeypatch):
    """performance.decode_ahead_frames as the runner sets it (frames.decode_ahead): 0 decodes in the
    caller's thread, 1 or more in the background thread; the frames and their bands are the same, in order."""
    import threading

    from pipeline.io import frames as frames_mod
    from pipeline.io.bands import cut_region, split_bands

    threads = []

    def recording_read_raw(path):
        threads.append(threading.current_thread().name)
        return read_raw(path)

    monkeypatch.setattr(frames_mod, "read_raw", recording_read_raw)
    ds = open_dataset(ds_root)
    expected = [split_bands(cut_region(r.cfa, *ds.lenses["far"]), r.cfa_pattern)["G"]
                for r in (read_raw(p) for p in ds.frames("dark")["path"])]
    for ahead in (0, 1, 2):
        threads.clear()
        with frames_mod.decode_ahead(ahead):
            got = [dec.lenses["far"].bands["G"] for dec in frames_mod.iter_frames(ds, "dark", lenses=["far"])]
        assert len(got) == 2 and all(np.array_equal(g, e) for g, e in zip(got, expected))
        main = threading.current_thread().name
        assert (threads == [main, main]) if ahead == 0 else all(t.startswith("decode") for t in threads), threads
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="decode_ahead_frames must be an integer >= 0"):
            with frames_mod.decode_ahead(bad):
                pass

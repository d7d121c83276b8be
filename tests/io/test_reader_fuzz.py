"""The readers of a lab's files never stop with a traceback.

First the mistakes an ordinary lab makes, each named in one line (a frames.csv a regional spreadsheet
saved with ';' and decimal commas, header names in another case, a file in another encoding, a key
written twice in dataset.yaml, an unquoted serial number that YAML 1.1 reads as an octal number); then
random edits of a valid dataset's files (cells and keys deleted, duplicated, retyped and reordered;
files truncated and bytes flipped) through the dataset readers, ``validate`` and the config check:
each gives one clear problem line (``InputError``) or the same result as the unedited file.
"""

from __future__ import annotations

import copy
import csv
import functools
import io
from datetime import datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.cli import EXIT_BAD_INPUT, EXIT_OK
from pipeline.cli import main as cli_main
from pipeline.config import load_config
from pipeline.io.dataset import (
    inspect_layout, open_dataset, read_photodiode, read_reference_radiometer, read_site, read_water, write_md5sums,
)
from pipeline.errors import InputError
from pipeline.io.rawio import write_dng
from pipeline.io.validation import inspect_dataset
from pipeline.runner.workflow import check_config

META = {
    "layout": 1,
    "camera": {"make": "Insta360", "model": "ONE", "serial": "SIM-0001"},
    "lenses": {"far": {"rows": [0, 32], "cols": [0, 32]}, "close": {"rows": [32, 64], "cols": [0, 32]}},
    "description": "reader test dataset",
}
FRAMES = {
    "dark": [{"file": "raw/d0.dng", "lens": "both", "kind": "dark", "temperature_c": 21.5},
             {"file": "raw/d1.dng", "lens": "both", "kind": "dark", "temperature_c": ""}],
    "linearity": [{"file": "raw/l0.dng", "lens": "far", "kind": "signal", "sweep": "exposure"},
                  {"file": "raw/l1.dng", "lens": "far", "kind": "dark", "sweep": "gain"}],
    "spectral": [{"file": "raw/s0.dng", "lens": "close", "kind": "signal", "wavelength_nm": 450.5},
                 {"file": "raw/s1.dng", "lens": "close", "kind": "dark", "wavelength_nm": ""}],
    "immersion": [{"file": "raw/i0.dng", "lens": "far", "kind": "signal", "condition": "water",
                   "water_height_cm": 2.5}],
    "field": [{"file": "raw/f0.dng", "lens": "far", "kind": "signal"}],
}
PHOTODIODE = "wavelength_nm,signal,signal_std\n450,1.5,0.01\n550,2.25,0.02\n"
#: readings at the field frame's UTC time (camera 16:02:40 less camera_clock_utc_offset_h -4 h: 20:02:40 UTC)
REFERENCE = "time,L_443,L_555\n2021-03-18T20:02:40Z,0.5,0.25\n2021-03-18T20:02:41Z,0.5,\n"
WATER = "temperature_c: 20.5\nsalinity_psu: 0.0\n"
SITE = ("latitude_deg: 46.8\nlongitude_deg: -71.2\ncamera_clock_utc_offset_h: -4\n"
        "reference:\n  name: C-OPS\n  channels_nm: [443, 555]\n  fwhm_nm: 10\n  half_fov_deg: 9\n")
#: the files the fuzz edits (relative to the dataset), each with its reader (None: validate alone)
READERS = {
    "dataset.yaml": None,
    "dark/frames.csv": None,
    "linearity/frames.csv": None,
    "spectral/frames.csv": None,
    "immersion/frames.csv": None,
    "spectral/photodiode.csv": read_photodiode,
    "immersion/water.yaml": read_water,
    "field/reference_radiometer.csv": read_reference_radiometer,
    "field/site.yaml": read_site,
}
#: examples per property: the five properties together run in about 20 s on one core
EXAMPLES = 60
FUZZ = settings(max_examples=EXAMPLES, derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _write_dataset(root: Path) -> Path:
    root.mkdir(parents=True)
    (root / "dataset.yaml").write_text(yaml.safe_dump(META, sort_keys=False))
    for n, (experiment, rows) in enumerate(FRAMES.items()):
        folder = root / experiment
        for i, row in enumerate(rows):
            (folder / row["file"]).parent.mkdir(parents=True, exist_ok=True)
            cfa = np.random.default_rng(10 * n + i).integers(600, 4000, (64, 32), dtype=np.uint16)
            write_dng(folder / row["file"], cfa, exposure_s=0.01, iso=100,
                      time=datetime(2021, 3, 18, 16, 2, 10 * n + i), black_level=512)
        pd.DataFrame(rows).to_csv(folder / "frames.csv", index=False)
    (root / "spectral" / "photodiode.csv").write_text(PHOTODIODE)
    (root / "immersion" / "water.yaml").write_text(WATER)
    (root / "field" / "reference_radiometer.csv").write_text(REFERENCE)
    (root / "field" / "site.yaml").write_text(SITE)
    write_md5sums(root)
    return root


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> Path:
    root = _write_dataset(tmp_path_factory.mktemp("fuzz") / "lab")
    assert inspect_dataset(root)[1] == []
    return root


@pytest.fixture(scope="module")
def lab_read(lab):
    """The lab dataset's frames tables and each sidecar reader's result, read once: every example restores the
    file it edits, so they are what each example compares with."""
    return _frames_of(lab), {name: reader(lab / name) for name, reader in READERS.items() if reader is not None}


@pytest.fixture
def fresh(tmp_path) -> Path:
    return _write_dataset(tmp_path / "lab")


def _frames_of(root: Path) -> dict[str, pd.DataFrame]:
    dataset = open_dataset(root)
    return {exp: dataset.frames(exp).drop(columns="path") for exp in dataset.experiments()}


def _one_line(root: Path, file: Path) -> str:
    with pytest.raises(InputError) as err:
        open_dataset(root)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{file.resolve()}: "), message
    return message


# --------------------------------------------------------------------------- the lab's own mistakes


def test_european_spreadsheet_frames_csv_is_named_in_one_line(fresh, capsys):
    """';' between fields and decimal commas (a spreadsheet's regional CSV): validate names the first
    decimal comma and how to save the file, without a traceback (it ended in KeyError: 'file')."""
    path = fresh / "spectral" / "frames.csv"
    path.write_text("file;lens;kind;wavelength_nm\nraw/s0.dng;close;signal;450,5\nraw/s1.dng;close;dark;\n")
    message = _one_line(fresh, path)
    assert "line 2, column 'wavelength_nm': '450,5' has a decimal comma (fields separated by ';'" in message
    assert cli_main(["validate", str(fresh)]) == EXIT_BAD_INPUT
    out = capsys.readouterr()
    assert "Traceback" not in out.out + out.err and "decimal comma" in out.out


def test_semicolons_tabs_and_header_case_read_as_the_comma_file(fresh):
    """A table separated by ';' or tabs (points as decimal marks) and header names in another case or
    with spaces around them read as the plain file does."""
    expected = _frames_of(fresh)
    path = fresh / "spectral" / "frames.csv"
    for text in ("file;lens;kind;wavelength_nm\nraw/s0.dng;close;signal;450.5\nraw/s1.dng;close;dark;\n",
                 "file\tlens\tkind\twavelength_nm\nraw/s0.dng\tclose\tsignal\t450.5\nraw/s1.dng\tclose\tdark\t\n",
                 " File ,LENS, Kind,Wavelength_NM\nraw/s0.dng,close,signal,450.5\nraw/s1.dng,close,dark,\n"):
        path.write_text(text)
        pd.testing.assert_frame_equal(_frames_of(fresh)["spectral"], expected["spectral"])


def test_header_that_does_not_match_lists_the_expected_names(fresh):
    path = fresh / "linearity" / "frames.csv"
    path.write_text("filename,lens,kind,sweep\nraw/l0.dng,far,signal,exposure\nraw/l1.dng,far,dark,gain\n")
    message = _one_line(fresh, path)
    assert "missing column 'file' (required: file, lens, kind, sweep; the header has: filename, lens, kind, sweep)" \
        in message


def test_encodings(fresh):
    """UTF-16 with its byte order mark (a spreadsheet's "Unicode text") is read; Latin-1 is refused in one line."""
    expected = _frames_of(fresh)
    path = fresh / "dark" / "frames.csv"
    text = path.read_text()
    path.write_bytes(text.encode("utf-16"))
    pd.testing.assert_frame_equal(_frames_of(fresh)["dark"], expected["dark"])
    path.write_bytes(text.replace("21.5", "21.5 \u00b0C").encode("latin-1"))
    assert "line 2: not UTF-8 text (byte 0xb0 cannot be read; a Latin-1 or Windows-1252 file?)" in _one_line(fresh, path)


def test_duplicate_yaml_key_is_refused_naming_key_and_line(fresh):
    path = fresh / "dataset.yaml"
    text = path.read_text() + "layout: 1\n"
    path.write_text(text)
    message = _one_line(fresh, path)
    assert message == f"{path.resolve()}: line {text.count(chr(10))}: key 'layout' appears twice (first on line 1)", message
    water = fresh / "immersion" / "water.yaml"
    water.write_text(WATER + "temperature_c: 4\n")
    with pytest.raises(InputError, match=r"water.yaml: line 3: key 'temperature_c' appears twice \(first on line 1\)$"):
        read_water(water)


def test_unquoted_text_values_are_read_as_written(fresh):
    """YAML 1.1 would read serial 0123 as the octal 83 and model no as False: they stay the text written."""
    path = fresh / "dataset.yaml"
    path.write_text(path.read_text().replace("serial: SIM-0001", "serial: 0123").replace("model: ONE", "model: no"))
    camera = open_dataset(fresh).meta["camera"]
    assert camera["serial"] == "0123" and camera["model"] == "no"
    site = fresh / "field" / "site.yaml"
    site.write_text(SITE.replace("name: C-OPS", "name: 1e3"))
    assert read_site(site)["reference"]["name"] == "1e3"


# --------------------------------------------------------------------------- random edits


def _cells(text: str) -> list[list[str]]:
    return [row for row in csv.reader(io.StringIO(text))]


def _table(rows: list[list[str]]) -> str:
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    return out.getvalue()


#: text a retyped cell or YAML value may take: numbers, words a lab might write, YAML 1.1's traps, quotes
_VALUES = st.one_of(
    st.sampled_from(["", "nan", "inf", "-1", "0", "1e400", "0123", "no", "yes", "~", "null", "both", "dark",
                     "signal", "far", "air", "water", "raw/d0.dng", "../x.dng", "/abs.dng", '"', "'", "[", "{",
                     "- a", "a: b", "&a", "*a", "!!python/object:os.system", "2021-03-18", "12:30:00", "1,5"]),
    st.text(min_size=0, max_size=8),
)


@st.composite
def _csv_edit(draw, text: str) -> str:
    rows = _cells(text)
    kind = draw(st.sampled_from(["delete cell", "duplicate cell", "retype cell", "swap cells", "delete row",
                                 "duplicate row", "swap rows"]))
    r = draw(st.integers(0, len(rows) - 1))
    c = draw(st.integers(0, len(rows[r]) - 1))
    if kind == "delete cell":
        del rows[r][c]
    elif kind == "duplicate cell":
        rows[r].insert(c, rows[r][c])
    elif kind == "retype cell":
        rows[r][c] = draw(_VALUES)
    elif kind == "swap cells":
        d = draw(st.integers(0, len(rows[r]) - 1))
        rows[r][c], rows[r][d] = rows[r][d], rows[r][c]
    elif kind == "delete row":
        del rows[r]
    elif kind == "duplicate row":
        rows.insert(r, list(rows[r]))
    else:
        s = draw(st.integers(0, len(rows) - 1))
        rows[r], rows[s] = rows[s], rows[r]
    return _table(rows)


@st.composite
def _yaml_edit(draw, text: str) -> str:
    lines = text.splitlines()
    kind = draw(st.sampled_from(["delete line", "duplicate line", "retype value", "swap lines", "indent line"]))
    i = draw(st.integers(0, len(lines) - 1))
    if kind == "delete line":
        del lines[i]
    elif kind == "duplicate line":
        lines.insert(i, lines[i])
    elif kind == "retype value":
        head, sep, _ = lines[i].partition(": ")
        lines[i] = f"{head}{sep or ': '}{draw(_VALUES)}"
    elif kind == "swap lines":
        j = draw(st.integers(0, len(lines) - 1))
        lines[i], lines[j] = lines[j], lines[i]
    else:
        lines[i] = "  " + lines[i]
    return "\n".join(lines) + "\n"


@st.composite
def _byte_edit(draw, data: bytes) -> bytes:
    at = draw(st.integers(0, len(data) - 1))
    if draw(st.booleans()):
        return data[:at]
    return data[:at] + bytes([data[at] ^ draw(st.integers(1, 255))]) + data[at + 1:]


def _check_all(root: Path, relative: str) -> None:
    """Every reader of the edited file, validate and the layout check: a result or one clear InputError."""
    reader = READERS[relative]
    if reader is not None:
        try:
            reader(root / relative)
        except InputError as exc:
            assert "\n" not in str(exc) and str(exc).startswith(str(root / relative)), str(exc)
    dataset, problems = inspect_dataset(root)
    assert (dataset is None) == bool(problems)
    for problem in problems:
        assert "\n" not in str(problem) and problem.message, problem
    if not problems:
        open_dataset(root)
    layout = inspect_layout(root)
    if layout.problems:
        with pytest.raises(InputError):
            layout.dataset()


def _edited(root: Path, relative: str, edit) -> None:
    path = root / relative
    original = path.read_bytes()
    try:
        path.write_bytes(edit(original))
        _check_all(root, relative)
    finally:
        path.write_bytes(original)


@FUZZ
@given(data=st.data(), relative=st.sampled_from(sorted(READERS)))
def test_random_cell_and_key_edits_never_raise_a_traceback(lab, data, relative):
    def edit(original: bytes) -> bytes:
        text = original.decode()
        strategy = _yaml_edit(text) if relative.endswith(".yaml") else _csv_edit(text)
        return data.draw(strategy).encode()

    _edited(lab, relative, edit)


@FUZZ
@given(data=st.data(), relative=st.sampled_from(sorted(READERS)))
def test_truncated_and_byte_flipped_files_never_raise_a_traceback(lab, data, relative):
    _edited(lab, relative, lambda original: data.draw(_byte_edit(original)))


@FUZZ
@given(data=st.data(), relative=st.sampled_from(sorted(name for name in READERS if name.endswith(".csv"))))
def test_reordered_columns_and_header_case_leave_the_result_unchanged(lab, lab_read, data, relative):
    """Columns in another order, header names in another case or with spaces, ';' or tabs between
    fields: the same tables and sidecar values."""
    expected_frames, expected_sidecars = lab_read
    reader = READERS[relative]
    expected = expected_sidecars[relative] if reader is not None else None
    path = lab / relative
    original = path.read_bytes()
    rows = _cells(original.decode())
    order = data.draw(st.permutations(range(len(rows[0]))))
    rows = [[row[i] for i in order] for row in rows]
    rows[0] = [data.draw(st.sampled_from([name, name.upper(), name.title(), f" {name} "])) for name in rows[0]]
    delimiter = data.draw(st.sampled_from([",", ";", "\t"]))
    out = io.StringIO()
    csv.writer(out, delimiter=delimiter, lineterminator="\n").writerows(rows)
    try:
        path.write_text(out.getvalue())
        for experiment, table in _frames_of(lab).items():
            pd.testing.assert_frame_equal(table[expected_frames[experiment].columns], expected_frames[experiment])
        if reader is not None:
            got = reader(path)
            pd.testing.assert_frame_equal(got[expected.columns], expected)
            # the channel wavelengths follow the columns' order: the same wavelength for each column
            channels = [c for c in got.columns if c.startswith("L_")]
            assert dict(zip(channels, got.attrs.get("channels_nm", []))) == \
                dict(zip([c for c in expected.columns if c.startswith("L_")], expected.attrs.get("channels_nm", [])))
    finally:
        path.write_bytes(original)


@FUZZ
@given(data=st.data(), relative=st.sampled_from(["dataset.yaml", "immersion/water.yaml", "field/site.yaml"]))
def test_reordered_yaml_keys_leave_the_result_unchanged(lab, data, relative):
    path = lab / relative
    original = path.read_bytes()
    parsed = yaml.safe_load(original)
    reader = READERS[relative] or (lambda _: open_dataset(lab).meta)
    expected = reader(path)
    keys = data.draw(st.permutations(list(parsed)))
    try:
        path.write_text(yaml.safe_dump({key: parsed[key] for key in keys}, sort_keys=False))
        assert reader(path) == expected
    finally:
        path.write_bytes(original)


def _config_paths(config, where=()) -> list[tuple]:
    """The key paths of a config (the plugin list left out: its names are imported)."""
    out = []
    if isinstance(config, dict):
        for key, value in config.items():
            path = where + (key,)
            if path != ("model", "plugins"):
                out.append(path)
                out += _config_paths(value, path)
    return out


_CONFIG_VALUES = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
                           st.sampled_from(["", "0", "-6", "1e9", "six", "dark_current", "no", "[1, 2]"]),
                           st.lists(st.integers(-5, 5), max_size=3), st.just({}))


@functools.lru_cache(maxsize=1)
def _base_config() -> dict:
    """The shipped config, read and validated once for all the examples (each edits its own deep copy)."""
    return load_config()


@FUZZ
@given(data=st.data())
def test_random_config_edits_are_refused_in_one_line_or_accepted(data):
    """The workflow's start-up check (check_config, the Snakefile's) on a config with a key deleted,
    duplicated under another name or retyped: the config back, or one InputError naming config.yaml."""
    config = copy.deepcopy(_base_config())
    path = data.draw(st.sampled_from(_config_paths(config)))
    parent = config
    for key in path[:-1]:
        parent = parent[key]
    kind = data.draw(st.sampled_from(["delete", "rename", "retype"]))
    if kind == "delete":
        del parent[path[-1]]
    elif kind == "rename":
        parent[f"{path[-1]}_copy"] = parent[path[-1]]
    else:
        parent[path[-1]] = data.draw(_CONFIG_VALUES)
    try:
        check_config(config, "config/config.yaml")
    except InputError as exc:
        assert str(exc).startswith("config/config.yaml: ") and "\n" not in str(exc), str(exc)


def test_validate_exit_codes(lab, capsys):
    assert cli_main(["validate", str(lab)]) == EXIT_OK
    capsys.readouterr()

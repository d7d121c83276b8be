"""Reader and validator for the calibration dataset layout (docs/dataset-format.md, layout 1).

``open_dataset`` checks dataset.yaml, MD5SUMS and every present frames.csv and
returns a :class:`Dataset`.  Sidecar readers (``read_photodiode`` ...) validate
the instrument files the same way.  The checks collect every problem they
find as :class:`pipeline.errors.Problem` records (file, line, column, what is
wrong, how to fix it); ``inspect_layout`` returns them all, and the readers
raise one :class:`pipeline.errors.InputError` whose line names the first
problem and counts the others.  ``pipeline.io.validation`` adds the checks that
need the raw files' tags.
"""

from __future__ import annotations

import codecs
import csv
import difflib
import hashlib
import io
import math
import re
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import pandas as pd
import yaml

from pipeline.errors import InputError, Problem
from pipeline.yamlio import KEYS, DuplicateKey, load_yaml

__all__ = [
    "EXPERIMENTS", "COMMON_COLUMNS", "EXPERIMENT_COLUMNS", "OPTIONAL_COLUMNS", "OPTIONAL_COLUMN_EXPERIMENTS", "TAG_COLUMNS", "SIDECARS",
    "COLUMN_MEANINGS", "KINDS", "CHOICES", "LAYOUT_VERSION", "PROJECTIONS",
    "Dataset", "LayoutCheck", "open_dataset", "inspect_layout", "check_sidecars", "check_checksums", "check_md5",
    "write_md5sums", "read_csv_table",
    "read_photodiode", "read_source_spectrum", "read_source_reference",
    "read_water", "read_reference_radiometer", "read_site",
]

LAYOUT_VERSION = 1
#: projections a lens region may declare (docs/dataset-format.md, dataset.yaml): the first is the default.
#: fisheye: an image circle inside the region, unlit corners around it; rectilinear: an
#: ordinary (pinhole-like) camera whose whole region is lit.
PROJECTIONS = ("fisheye", "rectilinear")
EXPERIMENTS = ("dark", "linearity", "geometry", "rolloff", "spectral", "absolute", "immersion", "field")
COMMON_COLUMNS = ("file", "lens", "kind")
# Required columns per experiment beyond COMMON_COLUMNS (docs/dataset-format.md, frames.csv).
EXPERIMENT_COLUMNS: dict[str, tuple[str, ...]] = {
    "dark": (),
    "linearity": ("sweep",),
    "geometry": ("medium",),
    "rolloff": ("medium", "azimuth_deg", "angle_deg"),
    "spectral": ("wavelength_nm",),
    "absolute": (),
    "immersion": ("condition", "water_height_cm"),
    "field": (),
}
# Columns that may appear in any frames.csv.
OPTIONAL_COLUMNS = ("temperature_c", "photons_per_pixel")
# Optional columns that only some experiments read (init-dataset carries them into those frames.csv only).
OPTIONAL_COLUMN_EXPERIMENTS = {"photons_per_pixel": ("linearity",)}
# Copies of the tags that may appear in any frames.csv (init-dataset writes them so
# that a lab can tell its frames apart); the tags stay the truth, and a copy that
# disagrees with its tag is a problem.
TAG_COLUMNS = ("exposure_s", "iso", "time")
# Instrument files of each experiment (docs/dataset-format.md, sidecar files).
SIDECARS: dict[str, tuple[str, ...]] = {
    "spectral": ("photodiode.csv",),
    "absolute": ("source_spectrum.csv", "source_reference.csv"),
    "immersion": ("water.yaml",),
    "field": ("reference_radiometer.csv", "site.yaml"),
}
# What each frames.csv column holds (docs/dataset-format.md): the "how to fix it" of its problems.
COLUMN_MEANINGS = {
    "file": "a path inside the experiment folder, e.g. raw/IMG_0001.dng",
    "lens": "the lens that faces the source or target ({lenses}), or both",
    "kind": "signal (source on) or dark (source off or lens capped, same settings)",
    "sweep": "exposure (ISO fixed, time varies) or gain (time fixed, ISO varies)",
    "medium": "air or water",
    "azimuth_deg": "the rotation plane in degrees (0 or 90)",
    "angle_deg": "the signed camera rotation in degrees that puts the sphere port at that field angle",
    "wavelength_nm": "the monochromator setting in nm (empty for dark frames)",
    "condition": "air or water",
    "water_height_cm": "the water height above the lens in cm (empty in air)",
    "temperature_c": "the sensor or room temperature in degrees C, or empty",
    "photons_per_pixel": "the mean number of photons reaching one pixel during the frame's exposure (> 0), or empty",
    "exposure_s": "the ExposureTime tag in s, or empty",
    "iso": "the ISOSpeedRatings tag, or empty",
    "time": "the DateTimeOriginal tag as ISO 8601 (2021-03-18T16:02:00.5), or empty",
}

KINDS = ("signal", "dark")
CHOICES = {"kind": KINDS, "sweep": ("exposure", "gain"), "medium": ("air", "water"),
           "condition": ("air", "water")}
_NUMERIC = ("azimuth_deg", "angle_deg", "wavelength_nm", "water_height_cm", "temperature_c", "photons_per_pixel")
_TAG_NUMBERS = ("exposure_s", "iso")
_MD5_LINE = re.compile(r"^([0-9a-fA-F]{32}) [ *](.+)$")
#: a folder whose name is at least this similar to an experiment's (difflib ratio)
#: is taken for a misspelt experiment ("Dark", "linearty"), not for a lab's own folder
TYPO_SIMILARITY = 0.8
#: characters of a header shown in the missing-column problem (a long header is cut there)
_HEADER_SHOWN = 120
_MORE_HINT = "python -m pipeline validate {root} lists them all"


# ---------------------------------------------------------------------------
# small parsing helpers


class _Bad(Exception):
    """A value is wrong: the message (no file or line) and how to fix it."""

    def __init__(self, message: str, fix: str = ""):
        super().__init__(message)
        self.message = message
        self.fix = fix


def _note(problems: list[Problem], path: Path | None, message: str, fix: str = "", *,
          line: int | None = None, column: str | None = None) -> None:
    problems.append(Problem(path=path, line=line, column=column, message=message, fix=fix))


def _check(problems: list[Problem], path: Path, fn, *args, line: int | None = None,
           column: str | None = None, **kwargs):
    """``fn(*args, **kwargs)``, or None with a problem noted when it raises _Bad."""
    try:
        return fn(*args, **kwargs)
    except _Bad as bad:
        _note(problems, path, bad.message, bad.fix, line=line, column=column)
        return None


def _raise_if(problems: list[Problem], root: Path | None = None) -> None:
    if problems:
        hint = _MORE_HINT.format(root=root) if root is not None else ""
        raise InputError.from_problems(problems, hint)


def _relpath(text: str) -> str | None:
    """Normalised relative POSIX path, or None if absolute or escaping upwards."""
    text = text.strip().replace("\\", "/")
    if not text or text.startswith("/") or re.match(r"^[A-Za-z]:", text):
        return None
    parts = [p for p in PurePosixPath(text).parts if p != "."]
    if not parts or ".." in parts:
        return None
    return "/".join(parts)


def _read_text(path: Path, problems: list[Problem], what: str, encoding: str = "utf-8") -> str | None:
    if not path.is_file():
        _note(problems, path, "file not found", f"write {what}")
        return None
    try:
        return path.read_text(encoding=encoding)
    except UnicodeDecodeError:
        _note(problems, path, "not UTF-8 text", "save the file as UTF-8 text")
    except OSError as exc:
        _note(problems, path, f"cannot read file ({exc.strerror or exc})", "check the file's permissions")
    return None


def _read_yaml(path: Path, problems: list[Problem], what: str, text_paths=()) -> tuple[bool, Any]:
    """(True, data) when the file parses; (False, None) with a problem noted otherwise.

    Two equal keys in a mapping are refused (PyYAML would keep the last); the plain values at
    ``text_paths`` (see :func:`pipeline.yamlio.load_yaml`) are read as the text written.
    """
    text = _read_text(path, problems, what, encoding="utf-8-sig")
    if text is None:
        return False, None
    try:
        return True, load_yaml(text, text_paths)
    except DuplicateKey as dup:
        _note(problems, path, f"key {dup.key!r} appears twice (first on line {dup.first_line})",
              "keep one of the two lines (YAML would silently use the last)", line=dup.line)
        return False, None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        reason = getattr(exc, "problem", None) or "invalid YAML"
        _note(problems, path, f"{where}not valid YAML ({reason})",
              "fix the YAML syntax there (brackets, quotes, indentation)")
        return False, None


#: field separators a table may use: a spreadsheet saves ';' where the decimal mark is a comma, and tabs
#: as "text"; the one of the header line (the most frequent there outside quotes) separates every line
_DELIMITERS = (",", ";", "\t")
_DELIMITER_NAMES = {",": "','", ";": "';'", "\t": "tabs"}
#: a number written with a decimal comma (0,5 or -1,25e3), as a regional spreadsheet saves it
_DECIMAL_COMMA = re.compile(r"[+-]?\d*,\d+(?:[eE][+-]?\d+)?")
_TABLE_FIX = "save the table as CSV UTF-8 (comma-separated, '.' as the decimal mark)"


def _table_text(path: Path, problems: list[Problem], what: str) -> str | None:
    """A table's text: UTF-8 (with or without its byte order mark) or UTF-16 with one; a problem noted
    and None for any other encoding, or text that holds NUL characters (a binary file)."""
    if not path.is_file():
        _note(problems, path, "file not found", f"write {what}")
        return None
    try:
        raw = path.read_bytes()
    except OSError as exc:
        _note(problems, path, f"cannot read file ({exc.strerror or exc})", "check the file's permissions")
        return None
    encoding = "utf-16" if raw[:2] in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE) else "utf-8-sig"
    try:
        text = raw.decode(encoding)
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        _note(problems, path, f"not UTF-8 text (byte 0x{raw[exc.start]:02x} cannot be read; a Latin-1 or "
                              "Windows-1252 file?)", _TABLE_FIX, line=line)
        return None
    if "\0" in text:
        _note(problems, path, "holds NUL characters: a binary file, or UTF-16 text without its byte order mark",
              _TABLE_FIX, line=text[:text.index("\0")].count("\n") + 1)
        return None
    return text


def _delimiter(text: str) -> str:
    """The field separator of a table: the one of _DELIMITERS most frequent on its first non-blank line
    outside quotes (',' when it has none: a table of one column)."""
    first = next((line for line in text.splitlines() if line.strip()), "")
    outside = "".join(part for i, part in enumerate(first.split('"')) if i % 2 == 0)
    counts = {d: outside.count(d) for d in _DELIMITERS}
    best = max(_DELIMITERS, key=lambda d: counts[d])
    return best if counts[best] else ","


def _canonical_names(header: list[str], known, rename) -> list[str]:
    """Header names matched to ``known`` without regard to case; ``rename`` (when given) spells the others."""
    by_fold = {name.casefold(): name for name in known}
    out = []
    for name in header:
        name = by_fold.get(name.casefold(), name)
        out.append(rename(name) if rename is not None else name)
    return out


def _read_csv(path: Path, required, problems: list[Problem], what: str, as_dicts: bool = True,
              known=(), rename=None
              ) -> tuple[list[str] | None, list[tuple[int, dict[str, str] | list[str]]]]:
    """Header and (line number, row dict) pairs; values stripped, blank lines skipped.

    Notes a problem for every ragged row (which is left out), for missing
    ``required`` columns and for a table without rows.  The header is None when
    the file cannot be read as a table at all. With ``as_dicts=False`` each row is
    the list of its values in the header's order (a long table read by column).

    The separator is the header line's (``,``, ``;`` or tab: :func:`_delimiter`); a table separated by
    ``;`` or tabs whose numbers have decimal commas is refused at the first of them. Header names are
    stripped and matched to ``required`` and ``known`` without regard to case (``File `` is ``file``);
    ``rename`` spells the other names (a pattern's canonical case).
    """
    text = _table_text(path, problems, what)
    if text is None:
        return None, []
    delimiter = _delimiter(text)
    reader = csv.reader(io.StringIO(text), delimiter=delimiter)
    header: list[str] | None = None
    rows: list[tuple[int, dict[str, str]]] = []
    n_records = 0
    ragged_fix = "give every row one value per column (an empty value still needs its comma)"
    try:
        for record in reader:
            if not record or all(not f.strip() for f in record):
                continue
            if header is None:
                header = _canonical_names([h.strip() for h in record], tuple(required) + tuple(known), rename)
                if any(not h for h in header):
                    _note(problems, path, "empty column name in header", "name every column of the first line",
                          line=reader.line_num)
                    return None, []
                dupes = sorted({h for h in header if header.count(h) > 1})
                if dupes:
                    _note(problems, path, f"duplicate column {dupes[0]!r}", "keep one column of each name",
                          line=reader.line_num)
                    return None, []
                continue
            n_records += 1
            if len(record) != len(header):
                _note(problems, path, f"{len(record)} fields but the header has {len(header)}", ragged_fix,
                      line=reader.line_num)
                continue
            values = [v.strip() for v in record]
            if delimiter != ",":
                comma = next((i for i, v in enumerate(values) if _DECIMAL_COMMA.fullmatch(v)), None)
                if comma is not None:
                    _note(problems, path, f"{values[comma]!r} has a decimal comma (fields separated by "
                                          f"{_DELIMITER_NAMES[delimiter]}: a spreadsheet's regional CSV)",
                          _TABLE_FIX, line=reader.line_num, column=header[comma])
                    return None, []
            rows.append((reader.line_num, dict(zip(header, values)) if as_dicts else values))
    except csv.Error as exc:
        _note(problems, path, f"malformed CSV ({exc})", "check the quotes on that line", line=reader.line_num)
        return None, []
    if header is None:
        _note(problems, path, "empty file (no header line)", f"write {what}")
        return None, []
    missing = [c for c in required if c not in header]
    if missing:
        shown = ", ".join(header)
        _note(problems, path, f"missing column {', '.join(repr(c) for c in missing)} "
                              f"(required: {', '.join(required)}; the header has: "
                              f"{shown if len(shown) <= _HEADER_SHOWN else shown[:_HEADER_SHOWN] + '...'})",
              f"add the column{'s' if len(missing) > 1 else ''} to the header line (docs/dataset-format.md says what "
              "each holds)")
    if not n_records:
        _note(problems, path, "no data rows", "add one row per frame or reading")
    return header, rows


def read_csv_table(path, required=(), what: str = "the table") -> tuple[list[str] | None,
                                                                       list[tuple[int, dict[str, str]]],
                                                                       list[Problem]]:
    """A CSV file as (header, [(line number, row dict)], problems), checked as frames.csv is.

    Values are stripped and blank lines skipped.

    Parameters
    ----------
    path : str or pathlib.Path
        The CSV file (separated by ``,``, ``;`` or tabs).
    required : sequence of str, default ()
        Columns that must be present (matched without regard to case).
    what : str, default "the table"
        What the file should hold, in the fix of its problems.

    Returns
    -------
    header : list[str] or None
        The column names; ``None`` when the file cannot be read as a table.
    rows : list[tuple[int, dict[str, str]]]
        (line number in the file, column -> stripped value) of each row with as many values as the header.
    problems : list[pipeline.errors.Problem]
        Every problem found: ragged rows (left out of ``rows``), missing columns, no rows, decimal commas.
    """
    problems: list[Problem] = []
    header, rows = _read_csv(Path(path), tuple(required), problems, what)
    return header, rows, problems


def _number(value: str, *, allow_empty: bool = False) -> float:
    if value == "":
        if allow_empty:
            return math.nan
        raise _Bad("value is empty")
    try:
        number = float(value)
    except ValueError:
        raise _Bad(f"{value!r} is not a number") from None
    if not math.isfinite(number):
        raise _Bad(f"{value!r} is not a finite number")
    return number


def _choice(value: str, allowed) -> str:
    if value not in allowed:
        if value == "":
            raise _Bad(f"value is empty (one of {', '.join(allowed)})")
        raise _Bad(f"{value!r} is not one of {', '.join(allowed)}")
    return value


def _yaml_number(where: str, value: Any, *, low: float | None = None,
                 high: float | None = None, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Bad(f"{where} must be a number, got {value!r}")
    try:
        finite = math.isfinite(value)
    except OverflowError:          # an integer beyond a float's range
        finite = False
    if not finite:
        raise _Bad(f"{where} must be a finite number, got {value if isinstance(value, float) else 'a huge integer'}")
    if positive and value <= 0:
        raise _Bad(f"{where} must be positive, got {value!r}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise _Bad(f"{where} must be within [{low}, {high}], got {value!r}")
    return float(value)


def _md5_file(path: Path) -> str:
    digest = hashlib.md5()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# ---------------------------------------------------------------------------
# dataset.yaml and MD5SUMS

#: dataset.yaml's values that are text (docs/dataset-format.md): read as written, so that ``serial: 0123`` is '0123'
#: and not the octal 83, ``model: no`` the word and not False, a lens named ``1`` the name '1'
_META_TEXT = (("camera", "make"), ("camera", "model"), ("camera", "serial"), ("description",), ("lenses", KEYS))
_LENSES_FIX = "give each lens as name: {rows: [start, stop], cols: [start, stop]} in raw pixels"


def _parse_span(where: str, span: Any) -> tuple[int, int]:
    if (not isinstance(span, (list, tuple)) or len(span) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in span)):
        raise _Bad(f"{where} must be a [start, stop] pair of integers, got {span!r}", _LENSES_FIX)
    start, stop = span
    if not 0 <= start < stop:
        raise _Bad(f"{where} [{start}, {stop}) must have 0 <= start < stop", _LENSES_FIX)
    if start % 2 or stop % 2:
        raise _Bad(f"{where} [{start}, {stop}) must start and stop on even pixels (Bayer grid)",
                   "round start and stop to even pixel numbers")
    return start, stop


def _check_meta(path: Path, meta: Any, problems: list[Problem]
                ) -> dict[str, tuple[tuple[int, int], tuple[int, int]]] | None:
    """Check dataset.yaml; returns the lens regions (None when they are unusable)."""
    if not isinstance(meta, dict):
        _note(problems, path, "must be a YAML mapping (layout, camera, lenses, ...)",
              "write the keys of docs/dataset-format.md: layout, camera, lenses (python -m pipeline init-dataset does)")
        return None
    if "layout" not in meta:
        _note(problems, path, "missing key 'layout'", f"add 'layout: {LAYOUT_VERSION}'")
    elif meta["layout"] != LAYOUT_VERSION or isinstance(meta["layout"], bool):
        _note(problems, path, f"layout is {meta['layout']!r}; this pipeline reads layout {LAYOUT_VERSION}",
              f"lay the dataset out as docs/dataset-format.md version {LAYOUT_VERSION} says, then set 'layout: "
              f"{LAYOUT_VERSION}'")
    camera = meta.get("camera")
    camera_fix = "write camera: {make: ..., model: ..., serial: ...} as the Make and Model tags of the raw files say"
    if not isinstance(camera, dict):
        _note(problems, path, "missing or invalid 'camera' (need a mapping with make and model)", camera_fix)
    else:
        for key in ("make", "model"):
            if not isinstance(camera.get(key), str) or not camera[key].strip():
                _note(problems, path, f"camera.{key} must be a non-empty string", camera_fix)
        if "serial" in camera and not isinstance(camera["serial"], (str, int)):
            _note(problems, path, "camera.serial must be a string", "quote the serial number: serial: \"1234\"")
    lenses_raw = meta.get("lenses")
    lenses: dict[str, tuple[tuple[int, int], tuple[int, int]]] | None = {}
    if not isinstance(lenses_raw, dict) or not lenses_raw:
        _note(problems, path, "missing or empty 'lenses' (need name: {rows: [a, b], cols: [a, b]})", _LENSES_FIX)
        lenses = None
    else:
        for name, region in lenses_raw.items():
            if not isinstance(name, str) or not name or name == "both":
                _note(problems, path, f"invalid lens name {name!r}",
                      "name each lens with a word other than 'both' (e.g. far, close)")
                lenses = None
                continue
            if not isinstance(region, dict) or "rows" not in region or "cols" not in region:
                _note(problems, path, f"lenses.{name} needs rows and cols", _LENSES_FIX)
                lenses = None
                continue
            projection = region.get("projection", PROJECTIONS[0])
            if projection not in PROJECTIONS:
                _note(problems, path, f"lenses.{name}.projection is {projection!r}; known: {', '.join(PROJECTIONS)}",
                      "write projection: fisheye (an image circle with unlit corners) or rectilinear (an "
                      "ordinary camera: the whole region is lit), or leave it out for fisheye")
            rows = _check(problems, path, _parse_span, f"lenses.{name}.rows", region["rows"])
            cols = _check(problems, path, _parse_span, f"lenses.{name}.cols", region["cols"])
            if rows is None or cols is None:
                lenses = None
            elif lenses is not None:
                lenses[name] = (rows, cols)
    board = meta.get("chessboard")
    if board is not None:
        board_fix = "write chessboard: {inner_corners: [columns, rows], square_mm: {air: 30.0, water: 20.0}}"
        if not isinstance(board, dict):
            _note(problems, path, "chessboard must be a mapping", board_fix)
        else:
            corners = board.get("inner_corners")
            if (not isinstance(corners, (list, tuple)) or len(corners) != 2
                    or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 2 for v in corners)):
                _note(problems, path, f"chessboard.inner_corners must be two integers >= 2, got {corners!r}",
                      "count the inner corners of the board along each side: [columns, rows]")
            squares = board.get("square_mm")
            if not isinstance(squares, dict) or not squares:
                _note(problems, path, "chessboard.square_mm must map medium (air, water) to a size in mm",
                      board_fix)
            else:
                for medium, size in squares.items():
                    if medium not in CHOICES["medium"]:
                        _note(problems, path, f"chessboard.square_mm: unknown medium {medium!r} (air or water)",
                              board_fix)
                    else:
                        _check(problems, path, _yaml_number, f"chessboard.square_mm.{medium}", size, positive=True)
    if "description" in meta and meta["description"] is not None and not isinstance(meta["description"], str):
        _note(problems, path, "description must be text", "quote the description")
    return lenses


def _check_md5sums(path: Path, problems: list[Problem], lines_of: dict[str, int] | None = None
                   ) -> dict[str, str] | None:
    """MD5SUMS as {relative path: md5}; None when the file cannot be read.

    ``lines_of``, when given, receives the line number of each path.
    """
    text = _read_text(path, problems, "MD5SUMS: one '<md5>  <relative path>' line per file of the dataset "
                                      "(python -m pipeline init-dataset writes it)")
    if text is None:
        return None
    sums: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        match = _MD5_LINE.match(line.rstrip("\r"))
        if not match:
            _note(problems, path, "expected '<32 hex digits>  <relative path>'",
                  "write the checksum, two spaces and the path relative to the dataset folder", line=number)
            continue
        rel = _relpath(match.group(2))
        if rel is None:
            _note(problems, path, f"path {match.group(2)!r} is not relative to the dataset",
                  "write the path relative to the dataset folder, e.g. dark/raw/IMG_0001.dng", line=number)
            continue
        if rel in sums:
            _note(problems, path, f"{rel} is listed twice", "delete one of the two lines", line=number)
            continue
        sums[rel] = match.group(1).lower()
        if lines_of is not None:
            lines_of[rel] = number
    return sums


# ---------------------------------------------------------------------------
# frames.csv


def _check_frames(root: Path, experiment: str, lenses, md5sums: dict[str, str] | None,
                  problems: list[Problem]) -> tuple[pd.DataFrame, list[int]]:
    """Check one frames.csv; returns its rows (plus an absolute ``path``) and their line numbers.

    ``lenses`` and ``md5sums`` may be None when dataset.yaml or MD5SUMS could not
    be read: the checks that need them are then left out.  ``path`` is None on
    rows whose file is not a path inside the experiment folder.
    """
    folder = root / experiment
    path = folder / "frames.csv"
    specific = EXPERIMENT_COLUMNS[experiment]
    header, rows = _read_csv(path, COMMON_COLUMNS + specific, problems,
                             f"{experiment}/frames.csv: one row per raw frame with the columns "
                             f"{', '.join(COMMON_COLUMNS + specific)} (python -m pipeline init-dataset writes it)",
                             known=OPTIONAL_COLUMNS + TAG_COLUMNS)
    if header is None:
        return pd.DataFrame(columns=list(COMMON_COLUMNS + specific) + ["path"]), []
    if "path" in header:
        _note(problems, path, "column 'path' is the pipeline's own (each frame's absolute path)",
              "rename the column (e.g. lab_path)")
        return pd.DataFrame(columns=list(COMMON_COLUMNS + specific) + ["path"]), []
    lens_names = tuple(lenses) + ("both",) if lenses is not None else None
    meaning = dict(COLUMN_MEANINGS)
    meaning["lens"] = meaning["lens"].format(lenses=", ".join(lenses) if lenses else "dataset.yaml's lenses")

    def bad(line, column, message, fix=None):
        _note(problems, path, message, fix if fix is not None else f"write {meaning[column]}",
              line=line, column=column)

    def choose(line, column, value, allowed):
        try:
            _choice(value, allowed)
        except _Bad as exc:
            bad(line, column, exc.message)

    seen: dict[str, int] = {}
    records, lines = [], []
    for line, row in rows:
        rec: dict[str, Any] = dict(row)
        rec["path"] = None
        records.append(rec)
        lines.append(line)
        rel = None
        if "file" in row:
            rel = _relpath(row["file"])
            if rel is None:
                what = "value is empty" if not row["file"] else f"{row['file']!r} is not a path inside {experiment}/"
                bad(line, "file", what)
            elif rel in seen:
                bad(line, "file", f"{rel} already listed on line {seen[rel]}", "delete one of the two rows")
                rel = None
            else:
                seen[rel] = line
        kind = row.get("kind")
        if "lens" in row and lens_names is not None:
            choose(line, "lens", row["lens"], lens_names)
        for column, allowed in CHOICES.items():
            if column in row and (column == "kind" or column in specific):
                choose(line, column, row[column], allowed)
        if experiment == "dark" and kind == "signal":
            bad(line, "kind", f"{kind!r} but every frame in dark/ must be 'dark'",
                "write dark (dark/ holds only dark frames; signal frames belong to their experiment)")
        for column in _NUMERIC + _TAG_NUMBERS:
            if column not in row:
                continue
            # Numbers may be empty for dark frames, the optional temperature, the tag
            # copies and water height in air; otherwise they are required.
            allow_empty = (kind == "dark" or column in ("temperature_c", "photons_per_pixel") + _TAG_NUMBERS
                           or (column == "water_height_cm" and row.get("condition") == "air"))
            try:
                rec[column] = _number(row[column], allow_empty=allow_empty)
            except _Bad as exc:
                rec[column] = math.nan
                bad(line, column, exc.message)
                continue
            if column == "photons_per_pixel" and not rec[column] > 0 and not math.isnan(rec[column]):
                bad(line, column, f"{rec[column]!r} must be positive")
        if row.get("time"):
            try:
                datetime.fromisoformat(row["time"])
            except ValueError:
                bad(line, "time", f"{row['time']!r} is not an ISO 8601 time")
        if rel is None:
            continue
        full = folder / rel
        rec["file"] = rel
        rec["path"] = full
        if not full.is_file():
            bad(line, "file", f"{rel} does not exist",
                "put the raw file there, correct the path or delete the row")
            continue
        key = f"{experiment}/{rel}"
        if md5sums is not None and key not in md5sums:
            bad(line, "file", f"{key} is not listed in MD5SUMS", "add its '<md5>  <path>' line to MD5SUMS")
    frame = pd.DataFrame.from_records(records, columns=header + ["path"])
    # object, None where a row has no file (pandas would infer text with NaN when no row has one)
    frame["path"] = pd.Series([rec["path"] for rec in records], index=frame.index, dtype=object)
    for column in _NUMERIC + _TAG_NUMBERS:
        if column in frame:
            frame[column] = frame[column].astype(float)
    return frame, lines



@dataclass
class Dataset:
    """A validated calibration dataset (layout 1)."""

    root: Path
    meta: dict
    lenses: dict[str, tuple[tuple[int, int], tuple[int, int]]]
    md5sums: dict[str, str]
    _frames: dict[str, pd.DataFrame] = field(default_factory=dict, repr=False, compare=False)

    def projection(self, lens: str) -> str:
        """The projection lens region ``lens`` declares in dataset.yaml (PROJECTIONS; default fisheye).

        Parameters
        ----------
        lens : str
            The lens region's name in dataset.yaml.

        Returns
        -------
        str
            The projection's name, one of ``PROJECTIONS``.
        """
        region = (self.meta.get("lenses") or {}).get(lens) if isinstance(self.meta, dict) else None
        value = region.get("projection", PROJECTIONS[0]) if isinstance(region, dict) else PROJECTIONS[0]
        return str(value)

    def experiments(self) -> list[str]:
        """Experiment folders present, in the order of EXPERIMENTS.

        Returns
        -------
        list[str]
            The names of the experiment folders found under the dataset's root.
        """
        return [name for name in EXPERIMENTS if (self.root / name).is_dir()]

    def frames(self, experiment: str) -> pd.DataFrame:
        """Validated frames.csv of one experiment plus an absolute ``path`` column.

        Parameters
        ----------
        experiment : str
            One of ``EXPERIMENTS``, e.g. ``"dark"``.

        Returns
        -------
        pandas.DataFrame
            One row per frame, frames.csv's columns (numbers as floats) and ``path``, the raw file's absolute path;
            a copy, checked once and kept.

        Raises
        ------
        ValueError
            If ``experiment`` is not a known experiment.
        pipeline.errors.InputError
            If its folder is absent or its frames.csv has a problem (the first named, the others counted).
        """
        if experiment not in EXPERIMENTS:
            raise ValueError(f"unknown experiment {experiment!r}; known: {', '.join(EXPERIMENTS)}")
        if experiment not in self._frames:
            folder = self.root / experiment
            if not folder.is_dir():
                raise InputError(folder, "experiment folder is absent")
            problems: list[Problem] = []
            frame, _ = _check_frames(self.root, experiment, self.lenses, self.md5sums, problems)
            _raise_if(problems, self.root)
            self._frames[experiment] = frame
        return self._frames[experiment].copy()

    def raw_files(self, experiment: str) -> list[Path]:
        """Absolute paths of the raw files that frames.csv lists, in its order.

        Parameters
        ----------
        experiment : str
            One of ``EXPERIMENTS``.

        Returns
        -------
        list[pathlib.Path]
            The raw files.
        """
        return list(self.frames(experiment)["path"])


@dataclass
class LayoutCheck:
    """What ``inspect_layout`` found: the parsed files and every problem of the layout."""

    root: Path
    meta: Any = None
    lenses: dict[str, tuple[tuple[int, int], tuple[int, int]]] | None = None
    md5sums: dict[str, str] | None = None
    #: experiment -> (frames table as Dataset.frames gives it, CSV line of each row)
    tables: dict[str, tuple[pd.DataFrame, list[int]]] = field(default_factory=dict)
    problems: list[Problem] = field(default_factory=list)

    def experiments(self) -> list[str]:
        """Experiment folders present, in the order of EXPERIMENTS.

        Returns
        -------
        list[str]
            The names of the experiment folders found under the dataset's root.
        """
        return [name for name in EXPERIMENTS if (self.root / name).is_dir()]

    def dataset(self) -> Dataset:
        """The Dataset, or one InputError naming the first problem and counting the others.

        Returns
        -------
        Dataset
            The checked dataset, its frame tables already read.

        Raises
        ------
        pipeline.errors.InputError
            If any problem was found.
        """
        _raise_if(self.problems, self.root)
        frames = {exp: table for exp, (table, _) in self.tables.items()}
        return Dataset(root=self.root, meta=self.meta, lenses=self.lenses, md5sums=self.md5sums, _frames=frames)


def _check_folders(root: Path, problems: list[Problem]) -> None:
    """A folder named almost like an experiment is a misspelt experiment the stages would miss."""
    for child in sorted(root.iterdir()):
        if not child.is_dir() or child.name in EXPERIMENTS or child.name.startswith("."):
            continue
        close = difflib.get_close_matches(child.name.lower(), EXPERIMENTS, n=1, cutoff=TYPO_SIMILARITY)
        if close:
            _note(problems, child, f"folder {child.name!r} is not an experiment of docs/dataset-format.md",
                  f"rename it {close[0]!r} (experiment folders: {', '.join(EXPERIMENTS)})")


def inspect_layout(root, check_frames: bool = True) -> LayoutCheck:
    """Check dataset.yaml, MD5SUMS and every present frames.csv; collect every problem.

    Parameters
    ----------
    root : str or pathlib.Path
        The dataset's folder.
    check_frames : bool, default True
        Check every present experiment's frames.csv (and the files MD5SUMS lists but are absent); ``False`` checks
        dataset.yaml and MD5SUMS only.

    Returns
    -------
    LayoutCheck
        The parsed files and every problem found (none raised).
    """
    root = Path(root)
    if not root.is_dir():
        what = "is a file, not a folder" if root.exists() else "dataset folder not found"
        return LayoutCheck(root=root, problems=[Problem(
            root, message=what, fix="check the path (a mistyped name, a drive not mounted?)")])
    root = root.resolve()
    check = LayoutCheck(root=root)
    problems = check.problems
    _check_folders(root, problems)
    meta_path = root / "dataset.yaml"
    parsed, check.meta = _read_yaml(meta_path, problems, "dataset.yaml: camera, lens regions and targets as "
                                                         "docs/dataset-format.md says (python -m pipeline init-dataset "
                                                         "writes it)", _META_TEXT)
    if parsed:
        check.lenses = _check_meta(meta_path, check.meta, problems)
    md5_lines: dict[str, int] = {}
    check.md5sums = _check_md5sums(root / "MD5SUMS", problems, md5_lines)
    if not check_frames:
        return check
    referenced = set()
    for experiment in check.experiments():
        table, lines = _check_frames(root, experiment, check.lenses, check.md5sums, problems)
        check.tables[experiment] = (table, lines)
        if "file" in table:
            referenced.update(f"{experiment}/{rel}" for rel in table["file"])
    if check.md5sums is not None:
        for rel in check.md5sums:
            if rel not in referenced and not (root / rel).is_file():
                _note(problems, root / "MD5SUMS", f"{rel} is listed but the file is absent",
                      "put the file back or delete its line", line=md5_lines[rel])
    return check


def open_dataset(root, check_frames: bool = True) -> Dataset:
    """Open and validate a dataset folder.

    Raises one InputError when anything is wrong: its line names the first
    problem and counts the others (``inspect_layout`` returns them all).

    Parameters
    ----------
    root : str or pathlib.Path
        The dataset's folder.
    check_frames : bool, default True
        Check every present experiment's frames.csv now.

    Returns
    -------
    Dataset
        The validated dataset.

    Raises
    ------
    pipeline.errors.InputError
        When anything is wrong.
    """
    return inspect_layout(root, check_frames=check_frames).dataset()


def check_md5(dataset: Dataset, relative_path, md5_hex: str) -> None:
    """Raise InputError unless MD5SUMS lists ``relative_path`` with ``md5_hex``.

    Parameters
    ----------
    dataset : Dataset
        The opened dataset, whose MD5SUMS is checked against.
    relative_path : str or pathlib.Path
        The file, relative to the dataset's root or absolute inside it.
    md5_hex : str
        The MD5 of the file's bytes as read, in hexadecimal (either case).

    Raises
    ------
    pipeline.errors.InputError
        If the file is outside the dataset, not listed in MD5SUMS, or listed with another checksum.
    """
    rel_in = Path(relative_path)
    if rel_in.is_absolute():
        try:
            rel_in = rel_in.relative_to(dataset.root)
        except ValueError:
            raise InputError(rel_in, f"not inside the dataset {dataset.root}") from None
    rel = _relpath(rel_in.as_posix())
    full = dataset.root / (rel or rel_in)
    if rel is None or rel not in dataset.md5sums:
        raise InputError(full, "not listed in MD5SUMS")
    expected = dataset.md5sums[rel]
    if expected != md5_hex.lower():
        raise InputError(full, f"checksum mismatch (MD5SUMS says {expected}, file is {md5_hex.lower()})")


def check_checksums(root, md5sums: dict[str, str]) -> list[Problem]:
    """Read every file MD5SUMS lists and compare its MD5 (slow: reads every byte).

    Parameters
    ----------
    root : str or pathlib.Path
        The dataset's folder.
    md5sums : dict[str, str]
        Path relative to ``root`` -> expected MD5 in hexadecimal, as MD5SUMS lists them.

    Returns
    -------
    list[pipeline.errors.Problem]
        One per file whose MD5 differs; absent files are skipped (the layout check names them).
    """
    root = Path(root)
    problems: list[Problem] = []
    for rel, expected in md5sums.items():
        path = root / rel
        if not path.is_file():
            continue
        actual = _md5_file(path)
        if actual != expected:
            _note(problems, path, f"checksum mismatch (MD5SUMS says {expected}, file is {actual})",
                  "restore the file as it was recorded, or write its new MD5SUMS line if the change is wanted")
    return problems


def write_md5sums(root) -> None:
    """Write ROOT/MD5SUMS for every file below root (except MD5SUMS), sorted by path.

    Parameters
    ----------
    root : str or pathlib.Path
        The dataset's folder; its MD5SUMS is overwritten.
    """
    root = Path(root)
    entries = []
    for path in root.rglob("*"):
        if path.is_file():
            rel = path.relative_to(root).as_posix()
            if rel != "MD5SUMS":
                entries.append(rel)
    lines = [f"{_md5_file(root / rel)}  {rel}\n" for rel in sorted(entries)]
    (root / "MD5SUMS").write_text("".join(lines), encoding="utf-8", newline="\n")


# ---------------------------------------------------------------------------
# sidecars


def _sidecar_path(source, relative: str) -> Path:
    return source.root / relative if isinstance(source, Dataset) else Path(source)


def _numeric_table(path: Path, columns: tuple[str, ...], problems: list[Problem], what: str, *,
                   nonnegative=(), positive=()) -> pd.DataFrame:
    header, rows = _read_csv(path, columns, problems, what)
    data = {c: [] for c in columns}
    if header is None or any(c not in header for c in columns):
        return pd.DataFrame(data)
    for line, row in rows:
        for column in columns:
            value = _check(problems, path, _number, row[column], line=line, column=column)
            if value is None:
                value = math.nan
            elif column in positive and value <= 0:
                _note(problems, path, f"{value!r} must be positive", f"write {what}", line=line, column=column)
            elif column in nonnegative and value < 0:
                _note(problems, path, f"{value!r} must not be negative", f"write {what}", line=line, column=column)
            data[column].append(value)
    return pd.DataFrame(data)


def _photodiode(path: Path, problems: list[Problem]) -> pd.DataFrame:
    return _numeric_table(path, ("wavelength_nm", "signal", "signal_std"), problems,
                          "the photodiode reading per monochromator wavelength: wavelength_nm (> 0), "
                          "signal, signal_std (>= 0)",
                          positive=("wavelength_nm",), nonnegative=("signal_std",))


def _source_spectrum(path: Path, problems: list[Problem]) -> pd.DataFrame:
    return _numeric_table(path, ("wavelength_nm", "radiance", "radiance_std"), problems,
                          "the sphere port's relative spectrum: wavelength_nm (> 0), radiance, radiance_std (>= 0)",
                          positive=("wavelength_nm",), nonnegative=("radiance_std",))


def _source_reference(path: Path, problems: list[Problem]) -> pd.DataFrame:
    return _numeric_table(path, ("wavelength_nm", "radiance_W_sr_m2_nm", "uncertainty_rel"), problems,
                          "the port's absolute radiance: wavelength_nm (> 0), radiance_W_sr_m2_nm (> 0), "
                          "uncertainty_rel (>= 0)",
                          positive=("wavelength_nm", "radiance_W_sr_m2_nm"), nonnegative=("uncertainty_rel",))


def _yaml_mapping(path: Path, problems: list[Problem], what: str, mapping_message: str,
                  text_paths=()) -> dict | None:
    parsed, data = _read_yaml(path, problems, what, text_paths)
    if not parsed:
        return None
    if not isinstance(data, dict):
        _note(problems, path, mapping_message, f"write {what}")
        return None
    return data


def _water(path: Path, problems: list[Problem]) -> dict:
    what = "temperature_c and salinity_psu of the tank water"
    data = _yaml_mapping(path, problems, what, "must be a YAML mapping with temperature_c and salinity_psu")
    if data is None:
        return {}
    out = dict(data)
    for key, low, high in (("temperature_c", -5.0, 60.0), ("salinity_psu", 0.0, 60.0)):
        if key not in data:
            _note(problems, path, f"missing key {key!r}", f"write {what}")
        else:
            out[key] = _check(problems, path, _yaml_number, key, data[key], low=low, high=high)
    return out


#: a radiance column of the reference radiometer: L_<wavelength in nm>
_CHANNEL = re.compile(r"L_(\d+(?:\.\d+)?)")


def _channel_name(name: str) -> str:
    """``l_443`` spelt ``L_443`` (a radiance column's name matched without regard to case)."""
    return "L" + name[1:] if _CHANNEL.fullmatch("L" + name[1:]) and name[:1] in "lL" else name


def _reference_radiometer(path: Path, problems: list[Problem]) -> pd.DataFrame:
    what = "the reference radiometer's readings: time (ISO 8601, UTC) and one L_<nm> column per channel"
    header, records = _read_csv(path, ("time",), problems, what, as_dicts=False, rename=_channel_name)
    channels = {}
    for column in header or ():
        match = _CHANNEL.fullmatch(column)
        if match:
            channels[column] = float(match.group(1))
    if header is not None and not channels:
        _note(problems, path, "no radiance columns (expected L_<nm>, e.g. L_443)",
              "name each radiance column L_<wavelength in nm>")
    if header is None or "time" not in header or not channels:
        frame = pd.DataFrame({"time": pd.DatetimeIndex([], tz="UTC")})
        frame.attrs["channels_nm"] = list(channels.values())
        return frame
    fast = _reference_columns(header, records, channels)
    if fast is not None:
        frame = pd.DataFrame(fast)
        frame.attrs["channels_nm"] = list(channels.values())
        return frame
    rows = [(line, dict(zip(header, values))) for line, values in records]
    times, values = [], {c: [] for c in channels}
    for line, row in rows:
        try:
            stamp = pd.Timestamp(row["time"])
        except (ValueError, TypeError):
            stamp = None
        if stamp is None or pd.isna(stamp):
            _note(problems, path, f"{row['time']!r} is not an ISO 8601 time",
                  "write times as 2021-03-18T20:02:00.166Z (UTC)", line=line, column="time")
            continue
        stamp = stamp.tz_localize("UTC") if stamp.tzinfo is None else stamp.tz_convert("UTC")
        times.append(stamp)
        for column in channels:
            value = _check(problems, path, _number, row[column], allow_empty=True, line=line, column=column)
            values[column].append(math.nan if value is None else value)
    frame = pd.DataFrame({"time": pd.DatetimeIndex(times), **values})
    frame.attrs["channels_nm"] = list(channels.values())
    return frame


def _finite_cells(texts) -> np.ndarray | None:
    """The cells of one column as floats, an empty cell NaN; None when a cell is not a finite number.

    The conversion of each text is Python's ``float`` (the values of :func:`_number`), one call for the
    column instead of one per cell; None sends the column to the per-cell check, which says which cell.
    """
    try:
        values = np.array(texts, dtype=np.float64)
        empty = None
    except ValueError:
        # an empty cell (or a bad one): the empty cells apart, the others converted as they are
        empty = np.fromiter((not t for t in texts), bool, len(texts))
        try:
            values = np.array([t if t else "0" for t in texts], dtype=np.float64)
        except ValueError:
            return None
    if not np.isfinite(values).all():
        return None
    if empty is not None:
        values[empty] = np.nan
    return values


def _reference_columns(header: list[str], records: list[tuple[int, list[str]]],
                       channels: dict[str, float]) -> dict | None:
    """The reference radiometer's columns (``time`` in UTC, one float column per channel) when every
    cell is valid, converted a column at a time; None when one is not, for the per-row check's messages.

    The same values as the per-row check (a time without a zone is UTC, one with a zone is converted to
    UTC; numbers as :func:`_number`): 22,000 readings of 19 channels took 1.0 s cell by cell.
    """
    if not records:
        return None
    columns = list(zip(*(values for _, values in records)))
    try:
        times = pd.to_datetime(list(columns[header.index("time")]), format="ISO8601", utc=True)
    except (ValueError, TypeError, OverflowError):
        return None
    if times.isna().any():
        return None
    out = {"time": pd.DatetimeIndex(times)}
    for column in channels:
        values = _finite_cells(columns[header.index(column)])
        if values is None:
            return None
        out[column] = values
    return out


#: the reference radiometer's stated calibration uncertainty when site.yaml's ``reference.calibration_relative_sigma``
#: is absent (relative, one standard uncertainty): Larouche et al. 2024, Section 3.5, give their C-OPS "a
#: conservative uncertainty of 2.5 %", which "also includes possible drifts of the C-OPS in the range of 1-2 % per
#: year (instrument calibrated 19 months prior)"; the field scale closure (stages.field) counts it in each band's budget
REFERENCE_CALIBRATION_RELATIVE_SIGMA = 0.025


def _site(path: Path, problems: list[Problem]) -> dict:
    what = ("latitude_deg, longitude_deg, camera_clock_utc_offset_h and reference: "
            "{name, channels_nm, fwhm_nm, half_fov_deg}")
    data = _yaml_mapping(path, problems, what, "must be a YAML mapping", [("reference", "name")])
    if data is None:
        return {}
    out = dict(data)
    for key, low, high in (("latitude_deg", -90.0, 90.0), ("longitude_deg", -180.0, 360.0),
                           ("camera_clock_utc_offset_h", -14.0, 14.0)):
        if key not in data:
            _note(problems, path, f"missing key {key!r}", f"write {what}")
        else:
            out[key] = _check(problems, path, _yaml_number, key, data[key], low=low, high=high)
    ref = data.get("reference")
    if not isinstance(ref, dict):
        _note(problems, path, "missing or invalid 'reference' (need name, channels_nm, fwhm_nm, half_fov_deg)",
              f"write {what}")
        return out
    ref = dict(ref)
    absent = [key for key in ("name", "channels_nm", "fwhm_nm", "half_fov_deg") if key not in ref]
    for key in absent:
        _note(problems, path, f"missing key 'reference.{key}'", f"write {what}")
    if "name" in ref and (not isinstance(ref["name"], str) or not ref["name"].strip()):
        _note(problems, path, "reference.name must be a non-empty string", "name the reference instrument")
    channels = ref.get("channels_nm")
    if "channels_nm" in ref:
        if not isinstance(channels, list) or not channels:
            _note(problems, path, "reference.channels_nm must be a non-empty list of wavelengths",
                  "list the channel wavelengths in nm: [412, 443, ...]")
            channels = None
        else:
            ref["channels_nm"] = [_check(problems, path, _yaml_number, "reference.channels_nm", v, positive=True)
                                  for v in channels]
    if "fwhm_nm" in ref:
        fwhm = ref["fwhm_nm"]
        if isinstance(fwhm, list):
            if channels is not None and len(fwhm) != len(channels):
                _note(problems, path, f"reference.fwhm_nm has {len(fwhm)} values for {len(channels)} channels",
                      "give one width per channel, or one width for all")
            ref["fwhm_nm"] = [_check(problems, path, _yaml_number, "reference.fwhm_nm", v, positive=True)
                              for v in fwhm]
        else:
            ref["fwhm_nm"] = _check(problems, path, _yaml_number, "reference.fwhm_nm", fwhm, positive=True)
    if "half_fov_deg" in ref:
        ref["half_fov_deg"] = _check(problems, path, _yaml_number, "reference.half_fov_deg", ref["half_fov_deg"],
                                     low=0.0, high=90.0)
    ref["calibration_relative_sigma"] = _check(problems, path, _yaml_number, "reference.calibration_relative_sigma",
                                               ref.get("calibration_relative_sigma",
                                                       REFERENCE_CALIBRATION_RELATIVE_SIGMA), low=0.0, high=1.0)
    out["reference"] = ref
    return out


#: the reference radiometer's readings already read and checked in this process: (path as given, sha256 of the
#: file's bytes) -> (readings, problems). One stage run reads them twice (the dataset's check, then the stage), and
#: a process that runs several stages on one dataset once more per stage: an hour at 6 Hz is 22,000 rows (0.4 s to
#: parse and check, 5 ms to hash)
_REFERENCE_READ: dict[tuple[str, str], tuple[pd.DataFrame, list[Problem]]] = {}
_REFERENCE_READ_ENTRIES = 4


def _reference_radiometer_once(path: Path, problems: list[Problem]) -> pd.DataFrame:
    """:func:`_reference_radiometer`, parsed again only when the file's bytes are others; the caller gets its
    own copy of the readings."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        return _reference_radiometer(path, problems)        # says what is wrong with the path
    key = (str(path), hashlib.sha256(data).hexdigest())
    if key not in _REFERENCE_READ:
        found: list[Problem] = []
        frame = _reference_radiometer(path, found)
        while len(_REFERENCE_READ) >= _REFERENCE_READ_ENTRIES:
            _REFERENCE_READ.pop(next(iter(_REFERENCE_READ)))       # the oldest first
        _REFERENCE_READ[key] = (frame, found)
    frame, found = _REFERENCE_READ[key]
    problems += found
    copy = frame.copy(deep=True)
    copy.attrs = {name: list(value) if isinstance(value, list) else value for name, value in frame.attrs.items()}
    return copy


#: sidecar (relative to the dataset) -> its checking reader
_SIDECAR_READERS = {
    "spectral/photodiode.csv": _photodiode,
    "absolute/source_spectrum.csv": _source_spectrum,
    "absolute/source_reference.csv": _source_reference,
    "immersion/water.yaml": _water,
    "field/reference_radiometer.csv": _reference_radiometer_once,
    "field/site.yaml": _site,
}
assert set(_SIDECAR_READERS) == {f"{exp}/{name}" for exp, names in SIDECARS.items() for name in names}


def check_sidecars(root, experiments, values: dict | None = None) -> list[Problem]:
    """Every problem of the sidecar files of the given (present) experiments.

    Parameters
    ----------
    root : str or pathlib.Path
        The dataset's folder.
    experiments : iterable of str
        The experiments whose sidecars are read (an experiment without sidecars has none to check).
    values : dict or None, optional
        When given, receives what each sidecar read (its path relative to the dataset -> the reader's value)
        when that file has no problem: the consistency checks compare them without reading the files again.

    Returns
    -------
    list[pipeline.errors.Problem]
        Every problem found, in the order of the experiments.
    """
    root = Path(root)
    problems: list[Problem] = []
    for experiment in experiments:
        for name in SIDECARS.get(experiment, ()):
            found: list[Problem] = []
            value = _SIDECAR_READERS[f"{experiment}/{name}"](root / experiment / name, found)
            if values is not None and not found:
                values[f"{experiment}/{name}"] = value
            problems += found
    return problems


def _read_sidecar(source, relative: str):
    path = _sidecar_path(source, relative)
    problems: list[Problem] = []
    value = _SIDECAR_READERS[relative](path, problems)
    _raise_if(problems)
    return value


def read_photodiode(source) -> pd.DataFrame:
    """spectral/photodiode.csv: wavelength_nm, signal, signal_std (a Dataset or a path).

    Parameters
    ----------
    source : Dataset or str or pathlib.Path
        The dataset (its spectral/photodiode.csv is read) or the file itself.

    Returns
    -------
    pandas.DataFrame
        ``wavelength_nm`` (monochromator wavelength, nm), ``signal`` (the photodiode's reading of the beam,
        proportional to beam power, any unit) and ``signal_std`` (its standard deviation, same unit), floats.

    Raises
    ------
    pipeline.errors.InputError
        If the file is missing or a value is missing, not a number or out of range.
    """
    return _read_sidecar(source, "spectral/photodiode.csv")


def read_source_spectrum(source) -> pd.DataFrame:
    """absolute/source_spectrum.csv: wavelength_nm, radiance, radiance_std.

    Parameters
    ----------
    source : Dataset or str or pathlib.Path
        The dataset (its absolute/source_spectrum.csv is read) or the file itself.

    Returns
    -------
    pandas.DataFrame
        ``wavelength_nm`` (nm), ``radiance`` (the sphere port's relative spectral radiance, any unit) and
        ``radiance_std`` (its standard deviation, same unit), floats.

    Raises
    ------
    pipeline.errors.InputError
        If the file is missing or a value is missing, not a number or out of range.
    """
    return _read_sidecar(source, "absolute/source_spectrum.csv")


def read_source_reference(source) -> pd.DataFrame:
    """absolute/source_reference.csv: wavelength_nm, radiance_W_sr_m2_nm, uncertainty_rel.

    Parameters
    ----------
    source : Dataset or str or pathlib.Path
        The dataset (its absolute/source_reference.csv is read) or the file itself.

    Returns
    -------
    pandas.DataFrame
        ``wavelength_nm`` (nm), ``radiance_W_sr_m2_nm`` (the port's absolute radiance from a calibrated
        instrument, W sr-1 m-2 nm-1) and ``uncertainty_rel`` (its relative standard uncertainty), floats.

    Raises
    ------
    pipeline.errors.InputError
        If the file is missing or a value is missing, not a number or out of range.
    """
    return _read_sidecar(source, "absolute/source_reference.csv")


def read_water(source) -> dict:
    """immersion/water.yaml: {temperature_c, salinity_psu} as floats.

    Parameters
    ----------
    source : Dataset or str or pathlib.Path
        The dataset (its immersion/water.yaml is read) or the file itself.

    Returns
    -------
    dict
        The file's mapping, ``temperature_c`` (the tank water's temperature, degree Celsius, -5 to 60) and
        ``salinity_psu`` (its salinity, PSU, 0 to 60) as floats.

    Raises
    ------
    pipeline.errors.InputError
        If the file is missing, not a mapping, or a value is missing or out of range.
    """
    return _read_sidecar(source, "immersion/water.yaml")


def read_reference_radiometer(source) -> pd.DataFrame:
    """field/reference_radiometer.csv: ``time`` (UTC, tz-aware) and L_<nm> columns (floats).

    Parameters
    ----------
    source : Dataset or str or pathlib.Path
        The dataset (its field/reference_radiometer.csv is read) or the file itself.

    Returns
    -------
    pandas.DataFrame
        ``time`` (UTC, tz-aware; a time without a zone is taken as UTC) and one ``L_<nm>`` column per channel,
        the reference radiometer's radiance in W sr-1 m-2 nm-1; an empty cell (an instrument drop-out) is NaN.
        The channel wavelengths (nm) are in ``df.attrs["channels_nm"]``, in the columns' order.

    Raises
    ------
    pipeline.errors.InputError
        If the file is missing, has no ``time`` or radiance column, or a time or number cannot be read.
    """
    return _read_sidecar(source, "field/reference_radiometer.csv")


def read_site(source) -> dict:
    """field/site.yaml: position, camera clock offset and the reference instrument.

    Parameters
    ----------
    source : Dataset or str or pathlib.Path
        The dataset (its field/site.yaml is read) or the file itself.

    Returns
    -------
    dict
        The file's mapping: ``latitude_deg`` and ``longitude_deg`` (degree), ``camera_clock_utc_offset_h``
        (hours, camera time minus this is UTC), and ``reference`` (``name``; ``channels_nm`` in nm;
        ``fwhm_nm`` in nm, one or one per channel; ``half_fov_deg`` in degree; ``calibration_relative_sigma``,
        relative, default :data:`REFERENCE_CALIBRATION_RELATIVE_SIGMA`).

    Raises
    ------
    pipeline.errors.InputError
        If the file is missing, not a mapping, or a key is missing or out of range.
    """
    return _read_sidecar(source, "field/site.yaml")

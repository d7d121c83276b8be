"""Reader and validator for the calibration dataset layout (DATASET.md, layout 1).

``open_dataset`` checks dataset.yaml, MD5SUMS and every present frames.csv and
returns a :class:`Dataset`.  Sidecar readers (``read_photodiode`` ...) validate
the instrument files the same way.  Every problem raises
:class:`pipeline.errors.InputError` with one line naming the file (and the line
and column where it applies) and what is wrong; the first problem found wins.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import pandas as pd
import yaml

from pipeline.errors import InputError

__all__ = [
    "EXPERIMENTS", "COMMON_COLUMNS", "EXPERIMENT_COLUMNS", "OPTIONAL_COLUMNS",
    "Dataset", "open_dataset", "check_md5", "write_md5sums",
    "read_photodiode", "read_source_spectrum", "read_source_reference",
    "read_water", "read_reference_radiometer", "read_site",
]

LAYOUT_VERSION = 1
EXPERIMENTS = ("dark", "linearity", "geometry", "rolloff", "spectral", "absolute", "immersion", "field")
COMMON_COLUMNS = ("file", "lens", "kind")
# Required columns per experiment beyond COMMON_COLUMNS (DATASET.md, frames.csv).
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
OPTIONAL_COLUMNS = ("temperature_c",)

KINDS = ("signal", "dark")
_CHOICES = {"sweep": ("exposure", "gain"), "medium": ("air", "water"), "condition": ("air", "water")}
_NUMERIC = ("azimuth_deg", "angle_deg", "wavelength_nm", "water_height_cm", "temperature_c")
_MD5_LINE = re.compile(r"^([0-9a-fA-F]{32}) [ *](.+)$")


# ---------------------------------------------------------------------------
# small parsing helpers


def _relpath(text: str) -> str | None:
    """Normalised relative POSIX path, or None if absolute or escaping upwards."""
    text = text.strip().replace("\\", "/")
    if not text or text.startswith("/") or re.match(r"^[A-Za-z]:", text):
        return None
    parts = [p for p in PurePosixPath(text).parts if p != "."]
    if not parts or ".." in parts:
        return None
    return "/".join(parts)


def _read_yaml(path: Path) -> Any:
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        return yaml.safe_load(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise InputError(path, "not UTF-8 text") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        reason = getattr(exc, "problem", None) or "invalid YAML"
        raise InputError(path, f"{where}not valid YAML ({reason})") from None
    except OSError as exc:
        raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None


def _read_csv(path: Path, required) -> tuple[list[str], list[tuple[int, dict[str, str]]]]:
    """Header and (line number, row dict) pairs; values stripped, blank lines skipped.

    Checks the ``required`` columns are present and that there is at least one row.
    """
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(path, "not UTF-8 text") from None
    except OSError as exc:
        raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None
    reader = csv.reader(io.StringIO(text))
    header: list[str] | None = None
    rows: list[tuple[int, dict[str, str]]] = []
    try:
        for record in reader:
            if not record or all(not f.strip() for f in record):
                continue
            if header is None:
                header = [h.strip() for h in record]
                if any(not h for h in header):
                    raise InputError(path, f"line {reader.line_num}: empty column name in header")
                dupes = sorted({h for h in header if header.count(h) > 1})
                if dupes:
                    raise InputError(path, f"line {reader.line_num}: duplicate column {dupes[0]!r}")
                continue
            if len(record) != len(header):
                raise InputError(path, f"line {reader.line_num}: {len(record)} fields but the header has {len(header)}")
            rows.append((reader.line_num, {h: v.strip() for h, v in zip(header, record)}))
    except csv.Error as exc:
        raise InputError(path, f"line {reader.line_num}: malformed CSV ({exc})") from None
    if header is None:
        raise InputError(path, "empty file (no header line)")
    _require_columns(path, header, required)
    if not rows:
        raise InputError(path, "no data rows")
    return header, rows


def _require_columns(path: Path, header: list[str], required) -> None:
    missing = [c for c in required if c not in header]
    if missing:
        raise InputError(path, f"missing column {', '.join(repr(c) for c in missing)} "
                               f"(required: {', '.join(required)})")


def _number(path: Path, line: int, column: str, value: str, *, allow_empty: bool = False) -> float:
    if value == "":
        if allow_empty:
            return math.nan
        raise InputError(path, f"line {line}, column {column!r}: value is empty")
    try:
        number = float(value)
    except ValueError:
        raise InputError(path, f"line {line}, column {column!r}: {value!r} is not a number") from None
    if not math.isfinite(number):
        raise InputError(path, f"line {line}, column {column!r}: {value!r} is not a finite number")
    return number


def _choice(path: Path, line: int, column: str, value: str, allowed) -> str:
    if value not in allowed:
        raise InputError(path, f"line {line}, column {column!r}: {value!r} is not one of {', '.join(allowed)}")
    return value


def _yaml_number(path: Path, where: str, value: Any, *, low: float | None = None,
                 high: float | None = None, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(path, f"{where} must be a number, got {value!r}")
    if positive and value <= 0:
        raise InputError(path, f"{where} must be positive, got {value!r}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise InputError(path, f"{where} must be within [{low}, {high}], got {value!r}")
    return float(value)


def _md5_file(path: Path) -> str:
    digest = hashlib.md5()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# ---------------------------------------------------------------------------
# dataset.yaml and MD5SUMS


def _parse_span(path: Path, where: str, span: Any) -> tuple[int, int]:
    if (not isinstance(span, (list, tuple)) or len(span) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in span)):
        raise InputError(path, f"{where} must be a [start, stop] pair of integers, got {span!r}")
    start, stop = span
    if not 0 <= start < stop:
        raise InputError(path, f"{where} [{start}, {stop}) must have 0 <= start < stop")
    if start % 2 or stop % 2:
        raise InputError(path, f"{where} [{start}, {stop}) must start and stop on even pixels (Bayer grid)")
    return start, stop


def _validate_meta(path: Path, meta: Any) -> dict[str, tuple[tuple[int, int], tuple[int, int]]]:
    if not isinstance(meta, dict):
        raise InputError(path, "must be a YAML mapping (layout, camera, lenses, ...)")
    if "layout" not in meta:
        raise InputError(path, "missing key 'layout'")
    if meta["layout"] != LAYOUT_VERSION or isinstance(meta["layout"], bool):
        raise InputError(path, f"layout is {meta['layout']!r}; this pipeline reads layout {LAYOUT_VERSION}")
    camera = meta.get("camera")
    if not isinstance(camera, dict):
        raise InputError(path, "missing or invalid 'camera' (need a mapping with make and model)")
    for key in ("make", "model"):
        if not isinstance(camera.get(key), str) or not camera[key].strip():
            raise InputError(path, f"camera.{key} must be a non-empty string")
    if "serial" in camera and not isinstance(camera["serial"], (str, int)):
        raise InputError(path, "camera.serial must be a string")
    lenses_raw = meta.get("lenses")
    if not isinstance(lenses_raw, dict) or not lenses_raw:
        raise InputError(path, "missing or empty 'lenses' (need name: {rows: [a, b], cols: [a, b]})")
    lenses = {}
    for name, region in lenses_raw.items():
        if not isinstance(name, str) or not name or name == "both":
            raise InputError(path, f"invalid lens name {name!r}")
        if not isinstance(region, dict) or "rows" not in region or "cols" not in region:
            raise InputError(path, f"lenses.{name} needs rows and cols")
        lenses[name] = (_parse_span(path, f"lenses.{name}.rows", region["rows"]),
                        _parse_span(path, f"lenses.{name}.cols", region["cols"]))
    board = meta.get("chessboard")
    if board is not None:
        if not isinstance(board, dict):
            raise InputError(path, "chessboard must be a mapping")
        corners = board.get("inner_corners")
        if (not isinstance(corners, (list, tuple)) or len(corners) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 2 for v in corners)):
            raise InputError(path, f"chessboard.inner_corners must be two integers >= 2, got {corners!r}")
        squares = board.get("square_mm")
        if not isinstance(squares, dict) or not squares:
            raise InputError(path, "chessboard.square_mm must map medium (air, water) to a size in mm")
        for medium, size in squares.items():
            if medium not in _CHOICES["medium"]:
                raise InputError(path, f"chessboard.square_mm: unknown medium {medium!r} (air or water)")
            _yaml_number(path, f"chessboard.square_mm.{medium}", size, positive=True)
    if "description" in meta and meta["description"] is not None and not isinstance(meta["description"], str):
        raise InputError(path, "description must be text")
    return lenses


def _read_md5sums(path: Path) -> dict[str, str]:
    if not path.is_file():
        raise InputError(path, "file not found")
    sums: dict[str, str] = {}
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError:
        raise InputError(path, "not UTF-8 text") from None
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        match = _MD5_LINE.match(line.rstrip("\r"))
        if not match:
            raise InputError(path, f"line {number}: expected '<32 hex digits>  <relative path>'")
        rel = _relpath(match.group(2))
        if rel is None:
            raise InputError(path, f"line {number}: path {match.group(2)!r} is not relative to the dataset")
        if rel in sums:
            raise InputError(path, f"line {number}: {rel} is listed twice")
        sums[rel] = match.group(1).lower()
    return sums


# ---------------------------------------------------------------------------
# frames.csv


def _validate_frames(dataset: "Dataset", experiment: str) -> pd.DataFrame:
    folder = dataset.root / experiment
    path = folder / "frames.csv"
    specific = EXPERIMENT_COLUMNS[experiment]
    header, rows = _read_csv(path, COMMON_COLUMNS + specific)
    lens_names = tuple(dataset.lenses) + ("both",)
    seen: dict[str, int] = {}
    records = []
    for line, row in rows:
        rec: dict[str, Any] = dict(row)
        rel = _relpath(row["file"])
        if rel is None:
            what = "value is empty" if not row["file"] else f"{row['file']!r} is not a path inside {experiment}/"
            raise InputError(path, f"line {line}, column 'file': {what}")
        if rel in seen:
            raise InputError(path, f"line {line}, column 'file': {rel} already listed on line {seen[rel]}")
        seen[rel] = line
        _choice(path, line, "lens", row["lens"], lens_names)
        kind = _choice(path, line, "kind", row["kind"], KINDS)
        if experiment == "dark" and kind != "dark":
            raise InputError(path, f"line {line}, column 'kind': {kind!r} but every frame in dark/ must be 'dark'")
        for column, allowed in _CHOICES.items():
            if column in specific:
                _choice(path, line, column, row[column], allowed)
        for column in _NUMERIC:
            if column not in row:
                continue
            # Numbers may be empty for dark frames, the optional temperature, and
            # water height in air; otherwise they are required.
            allow_empty = (kind == "dark" or column == "temperature_c"
                           or (column == "water_height_cm" and row.get("condition") == "air"))
            rec[column] = _number(path, line, column, row[column], allow_empty=allow_empty)
        full = folder / rel
        if not full.is_file():
            raise InputError(path, f"line {line}, column 'file': {rel} does not exist")
        key = f"{experiment}/{rel}"
        if key not in dataset.md5sums:
            raise InputError(path, f"line {line}, column 'file': {key} is not listed in MD5SUMS")
        rec["file"] = rel
        rec["path"] = full
        records.append(rec)
    frame = pd.DataFrame.from_records(records, columns=header + ["path"])
    for column in _NUMERIC:
        if column in frame:
            frame[column] = frame[column].astype(float)
    return frame


@dataclass
class Dataset:
    """A validated calibration dataset (layout 1)."""

    root: Path
    meta: dict
    lenses: dict[str, tuple[tuple[int, int], tuple[int, int]]]
    md5sums: dict[str, str]
    _frames: dict[str, pd.DataFrame] = field(default_factory=dict, repr=False, compare=False)

    def experiments(self) -> list[str]:
        """Experiment folders present, in the order of EXPERIMENTS."""
        return [name for name in EXPERIMENTS if (self.root / name).is_dir()]

    def frames(self, experiment: str) -> pd.DataFrame:
        """Validated frames.csv of one experiment plus an absolute ``path`` column."""
        if experiment not in EXPERIMENTS:
            raise ValueError(f"unknown experiment {experiment!r}; known: {', '.join(EXPERIMENTS)}")
        if experiment not in self._frames:
            folder = self.root / experiment
            if not folder.is_dir():
                raise InputError(folder, "experiment folder is absent")
            self._frames[experiment] = _validate_frames(self, experiment)
        return self._frames[experiment].copy()

    def raw_files(self, experiment: str) -> list[Path]:
        """Absolute paths of the raw files that frames.csv lists, in its order."""
        return list(self.frames(experiment)["path"])


def open_dataset(root, check_frames: bool = True) -> Dataset:
    """Open and validate a dataset folder; raises InputError on the first problem."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "dataset folder not found")
    root = root.resolve()
    meta_path = root / "dataset.yaml"
    meta = _read_yaml(meta_path)
    lenses = _validate_meta(meta_path, meta)
    md5sums = _read_md5sums(root / "MD5SUMS")
    dataset = Dataset(root=root, meta=meta, lenses=lenses, md5sums=md5sums)
    if check_frames:
        for experiment in dataset.experiments():
            dataset.frames(experiment)
    return dataset


def check_md5(dataset: Dataset, relative_path, md5_hex: str) -> None:
    """Raise InputError unless MD5SUMS lists ``relative_path`` with ``md5_hex``."""
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


def write_md5sums(root) -> None:
    """Write ROOT/MD5SUMS for every file below root (except MD5SUMS), sorted by path."""
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


def _numeric_table(path: Path, columns: tuple[str, ...], *, nonnegative=(), positive=()) -> pd.DataFrame:
    header, rows = _read_csv(path, columns)
    data = {c: [] for c in columns}
    for line, row in rows:
        for column in columns:
            value = _number(path, line, column, row[column])
            if column in positive and value <= 0:
                raise InputError(path, f"line {line}, column {column!r}: {value!r} must be positive")
            if column in nonnegative and value < 0:
                raise InputError(path, f"line {line}, column {column!r}: {value!r} must not be negative")
            data[column].append(value)
    return pd.DataFrame(data)


def read_photodiode(source) -> pd.DataFrame:
    """spectral/photodiode.csv: wavelength_nm, signal, signal_std (a Dataset or a path)."""
    return _numeric_table(_sidecar_path(source, "spectral/photodiode.csv"),
                          ("wavelength_nm", "signal", "signal_std"),
                          positive=("wavelength_nm",), nonnegative=("signal_std",))


def read_source_spectrum(source) -> pd.DataFrame:
    """absolute/source_spectrum.csv: wavelength_nm, radiance, radiance_std."""
    return _numeric_table(_sidecar_path(source, "absolute/source_spectrum.csv"),
                          ("wavelength_nm", "radiance", "radiance_std"),
                          positive=("wavelength_nm",), nonnegative=("radiance_std",))


def read_source_reference(source) -> pd.DataFrame:
    """absolute/source_reference.csv: wavelength_nm, radiance_W_sr_m2_nm, uncertainty_rel."""
    return _numeric_table(_sidecar_path(source, "absolute/source_reference.csv"),
                          ("wavelength_nm", "radiance_W_sr_m2_nm", "uncertainty_rel"),
                          positive=("wavelength_nm", "radiance_W_sr_m2_nm"), nonnegative=("uncertainty_rel",))


def read_water(source) -> dict:
    """immersion/water.yaml: {temperature_c, salinity_psu} as floats."""
    path = _sidecar_path(source, "immersion/water.yaml")
    data = _read_yaml(path)
    if not isinstance(data, dict):
        raise InputError(path, "must be a YAML mapping with temperature_c and salinity_psu")
    out = dict(data)
    for key, low, high in (("temperature_c", -5.0, 60.0), ("salinity_psu", 0.0, 60.0)):
        if key not in data:
            raise InputError(path, f"missing key {key!r}")
        out[key] = _yaml_number(path, key, data[key], low=low, high=high)
    return out


def read_reference_radiometer(source) -> pd.DataFrame:
    """field/reference_radiometer.csv: ``time`` (UTC, tz-aware) and L_<nm> columns (floats).

    Empty radiance cells become NaN (instrument drop-outs).  The channel
    wavelengths are in ``df.attrs["channels_nm"]`` (same order as the columns).
    """
    path = _sidecar_path(source, "field/reference_radiometer.csv")
    header, rows = _read_csv(path, ("time",))
    channels = {}
    for column in header:
        match = re.fullmatch(r"L_(\d+(?:\.\d+)?)", column)
        if match:
            channels[column] = float(match.group(1))
    if not channels:
        raise InputError(path, "no radiance columns (expected L_<nm>, e.g. L_443)")
    times, values = [], {c: [] for c in channels}
    for line, row in rows:
        try:
            stamp = pd.Timestamp(row["time"])
        except (ValueError, TypeError):
            stamp = None
        if stamp is None or pd.isna(stamp):
            raise InputError(path, f"line {line}, column 'time': {row['time']!r} is not an ISO 8601 time")
        stamp = stamp.tz_localize("UTC") if stamp.tzinfo is None else stamp.tz_convert("UTC")
        times.append(stamp)
        for column in channels:
            values[column].append(_number(path, line, column, row[column], allow_empty=True))
    frame = pd.DataFrame({"time": pd.DatetimeIndex(times), **values})
    frame.attrs["channels_nm"] = list(channels.values())
    return frame


def read_site(source) -> dict:
    """field/site.yaml: position, camera clock offset and the reference instrument."""
    path = _sidecar_path(source, "field/site.yaml")
    data = _read_yaml(path)
    if not isinstance(data, dict):
        raise InputError(path, "must be a YAML mapping")
    out = dict(data)
    for key, low, high in (("latitude_deg", -90.0, 90.0), ("longitude_deg", -180.0, 360.0),
                           ("camera_clock_utc_offset_h", -14.0, 14.0)):
        if key not in data:
            raise InputError(path, f"missing key {key!r}")
        out[key] = _yaml_number(path, key, data[key], low=low, high=high)
    ref = data.get("reference")
    if not isinstance(ref, dict):
        raise InputError(path, "missing or invalid 'reference' (need name, channels_nm, fwhm_nm, half_fov_deg)")
    ref = dict(ref)
    for key in ("name", "channels_nm", "fwhm_nm", "half_fov_deg"):
        if key not in ref:
            raise InputError(path, f"missing key 'reference.{key}'")
    if not isinstance(ref["name"], str) or not ref["name"].strip():
        raise InputError(path, "reference.name must be a non-empty string")
    channels = ref["channels_nm"]
    if not isinstance(channels, list) or not channels:
        raise InputError(path, "reference.channels_nm must be a non-empty list of wavelengths")
    ref["channels_nm"] = [_yaml_number(path, "reference.channels_nm", v, positive=True) for v in channels]
    fwhm = ref["fwhm_nm"]
    if isinstance(fwhm, list):
        if len(fwhm) != len(channels):
            raise InputError(path, f"reference.fwhm_nm has {len(fwhm)} values for {len(channels)} channels")
        ref["fwhm_nm"] = [_yaml_number(path, "reference.fwhm_nm", v, positive=True) for v in fwhm]
    else:
        ref["fwhm_nm"] = _yaml_number(path, "reference.fwhm_nm", fwhm, positive=True)
    ref["half_fov_deg"] = _yaml_number(path, "reference.half_fov_deg", ref["half_fov_deg"], low=0.0, high=90.0)
    out["reference"] = ref
    return out

"""Lay out a folder of raw files as a calibration dataset (docs/dataset-format.md): ``init-dataset``.

A lab has folders of raw files and a lab notebook, not our layout.  From a
folder with one sub-folder per experiment (``dark/``, ``linearity/``, ...),
or one folder plus a CSV lab log whose ``experiment`` column names the
experiment of each file, :func:`init_dataset` writes the layout of docs/dataset-format.md:

- ``dataset.yaml``: make, model and serial from the tags; lens regions proposed
  from the frame size (a dual-fisheye frame of H x W with H = 2W holds two
  square regions stacked), each checked for a lit image circle with the
  geometry package's circle fit on a frame, for the user to confirm; a region
  lit to its corners (an ordinary camera) is proposed as ``projection:
  rectilinear``;
- ``<experiment>/frames.csv``: one row per raw file in acquisition order, the
  copies of the tags filled (``exposure_s``, ``iso``, ``time``) and the columns
  only the lab knows (lens, kind, sweep, ...) filled from the lab log, or empty;
- the raw files as symbolic links to the originals (``copy=True`` copies
  them), and the sidecar files found beside them; then ``MD5SUMS``.

The raw files are only read.  ``out`` must not exist: the layout is written to
a temporary sibling folder and renamed at the end, so a failure never leaves a
half-written dataset.  The dataset is then validated: what it still lacks is
what the user has to fill in.

A measurement in the EMVA1288 file format (a descriptor ``EMVA1288_Data.txt``
listing 16-bit PNG frames by exposure, as the EMVA1288 reference sets are
published) is first wrapped as DNG files and a lab log by
:func:`emva1288_raw_folder`; :func:`init_emva1288_dataset` then lays it out
with :func:`init_dataset` like any other lab's raw folder.

It uses the io layer and the geometry package's image-circle fit; only the
command line imports it.
"""

from __future__ import annotations

import difflib
import os
import shutil
from collections import Counter
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import Path, PurePosixPath

import numpy as np
import pandas as pd
import yaml

from pipeline.io.bands import cut_region, split_bands
from pipeline.io.dataset import (COMMON_COLUMNS, EXPERIMENT_COLUMNS, EXPERIMENTS, LAYOUT_VERSION,
                              OPTIONAL_COLUMN_EXPERIMENTS, OPTIONAL_COLUMNS, SIDECARS, TAG_COLUMNS, TYPO_SIMILARITY, read_csv_table, write_md5sums)
from pipeline.errors import InputError, Problem
from pipeline.io.rawio import read_raw, read_tags, write_dng

__all__ = ["RAW_SUFFIXES", "LensProposal", "RawEntry", "ScaffoldPlan", "InitResult", "plan_dataset",
           "propose_lens_regions", "find_lens_circles", "write_dataset", "init_dataset", "describe_result",
           "Emva1288Frame", "read_emva1288_descriptor", "emva1288_raw_folder", "init_emva1288_dataset"]

#: raw files the layout holds (docs/dataset-format.md: DNG), compared case-insensitively
RAW_SUFFIXES = (".dng",)
#: lab-log columns: the raw file (path relative to RAW_DIR, or its name when unique) and its experiment
LOG_FILE_COLUMN, LOG_EXPERIMENT_COLUMN = "file", "experiment"
#: lens names of a frame holding two square regions stacked (H = 2W): the dual-fisheye
#: camera of docs/dataset-format.md's example writes the far lens above the close one
STACKED_LENSES = ("far", "close")
#: lens names of a frame holding two square regions side by side (W = 2H)
SIDE_BY_SIDE_LENSES = ("left", "right")
#: lens name of a frame that is one region (any other aspect ratio)
SINGLE_LENS = "main"
#: experiments whose frames light the whole image circle first (uniform sources),
#: then those with structured scenes; dark frames never show the circle
CIRCLE_EXPERIMENTS = ("linearity", "absolute", "immersion", "spectral", "field", "geometry", "rolloff")
#: frames decoded at most to find the image circles (each decode reads a whole raw file)
MAX_CIRCLE_FRAMES = 16
#: side of the corner squares, as a fraction of the region's short side: they lie outside
#: the circle inscribed in a square region (their inner corner is at 0.53 of the side
#: from the centre, beyond the circle's 0.5)
CORNER_SIZE_FRACTION = 1 / 8
#: a lit circle stands this many noise sigmas above the unlit corners (dark frames stay near 0)
MIN_LIT_CONTRAST_SIGMA = 10.0
#: standard deviation over median absolute deviation of a normal distribution
MAD_TO_SIGMA = 1.4826
#: floor of the corners' noise in DN (integer samples: quantisation alone gives about 0.3)
NOISE_FLOOR_DN = 1.0
#: a fisheye image circle has a radius of at least this fraction of half the region's short side
MIN_CIRCLE_RADIUS_FRACTION = 0.25
#: edge points scattered more than this (band pixels RMS) about the fit are not one circle
MAX_CIRCLE_FIT_RMS_PX = 2.0
#: a fisheye's pixels outside its circle are never lit: a region lit outside the best circle by more
#: than this fraction of the inside (above the BlackLevel tag) is an ordinary camera's, lit to its
#: corners (the linearity stage's default image_circle_max_outside_fraction)
MAX_OUTSIDE_LIT_FRACTION = 0.2

#: what :func:`_circle_in` says of a region lit to its corners
RECTILINEAR = "lit to its corners"

_LOG_FIX = "give each raw file one row: file (path relative to RAW_DIR, or the file name), experiment, lab columns"


@dataclass
class RawEntry:
    """One raw file of RAW_DIR and where it goes in the dataset."""

    source: Path                 # absolute path of the original
    source_rel: str              # path relative to RAW_DIR (POSIX)
    experiment: str | None
    target: str = ""             # path relative to the experiment folder, raw/...
    tags: dict | None = None
    lab: dict[str, str] = field(default_factory=dict)   # lab-log values of frames.csv columns


@dataclass
class LensProposal:
    """A lens region (raw pixel rows and columns, [start, stop)) and what its check found."""

    name: str
    rows: tuple[int, int]
    cols: tuple[int, int]
    centre_row_px: float | None = None    # image circle, raw pixels of the frame
    centre_col_px: float | None = None
    radius_px: float | None = None
    frame: str | None = None              # dataset path of the frame the circle was fitted on
    note: str = ""
    #: fisheye, or rectilinear when a lit frame shows the region lit to its corners
    projection: str = "fisheye"


@dataclass
class ScaffoldPlan:
    """Everything init-dataset will write, found from RAW_DIR and the lab log (nothing written yet)."""

    raw_dir: Path
    lab_log: Path | None
    entries: dict[str, list[RawEntry]]            # experiment -> frames in acquisition order
    sidecars: dict[str, list[Path]]               # experiment -> instrument files to carry over
    ignored: list[str]                            # files of RAW_DIR that are neither
    lab_columns: dict[str, list[str]]             # experiment -> frames.csv columns only the lab knows
    camera: dict[str, str]
    frame_shape: tuple[int, int] | None
    lenses: list[LensProposal]
    notes: list[str] = field(default_factory=list)


@dataclass
class InitResult:
    out: Path
    plan: ScaffoldPlan
    copied: bool
    remaining: list[Problem]                      # what validate still reports: the user fills it in


# ---------------------------------------------------------------------------
# reading RAW_DIR and the lab log


def _raw_and_other_files(raw_dir: Path) -> tuple[list[Path], list[Path]]:
    raws, others = [], []
    for folder, dirs, files in os.walk(raw_dir):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            if name.startswith("."):
                continue
            path = Path(folder) / name
            (raws if path.suffix.lower() in RAW_SUFFIXES else others).append(path)
    return raws, others


def _target(source_rel: str, in_experiment_folder: bool) -> str:
    """raw/<path inside the experiment folder>, without a doubled raw/ component."""
    parts = list(PurePosixPath(source_rel).parts)
    if in_experiment_folder:
        parts = parts[1:]
    if len(parts) > 1 and parts[0].lower() == "raw":
        parts = parts[1:]
    return "/".join(["raw", *parts])


def _read_lab_log(log: Path, raws: dict[str, RawEntry], problems: list[Problem]) -> tuple[list[str], list[str]]:
    """Apply the lab log to the raw entries (experiment and lab columns).

    Returns the log's columns that frames.csv takes and those it leaves out.
    """
    header, rows, found = read_csv_table(log, (LOG_FILE_COLUMN,), _LOG_FIX)
    problems += found
    if header is None or LOG_FILE_COLUMN not in header:
        return [], []
    lab_columns = set(COMMON_COLUMNS[1:]) | set(OPTIONAL_COLUMNS) | {c for cs in EXPERIMENT_COLUMNS.values()
                                                                     for c in cs}
    usable = [c for c in header if c in lab_columns]
    unused = [c for c in header if c not in lab_columns and c not in (LOG_FILE_COLUMN, LOG_EXPERIMENT_COLUMN)]
    by_name = Counter(PurePosixPath(rel).name for rel in raws)
    name_to_rel = {PurePosixPath(rel).name: rel for rel in raws}
    seen: dict[str, int] = {}
    for line, row in rows:
        value = row[LOG_FILE_COLUMN].replace("\\", "/").strip("/")
        experiment = row.get(LOG_EXPERIMENT_COLUMN, "")
        if experiment and experiment not in EXPERIMENTS:
            close = difflib.get_close_matches(experiment.lower(), EXPERIMENTS, n=1, cutoff=TYPO_SIMILARITY)
            problems.append(Problem(log, line, LOG_EXPERIMENT_COLUMN, f"{experiment!r} is not an experiment",
                                    f"write {close[0]!r}" if close else f"write one of {', '.join(EXPERIMENTS)}"))
            experiment = ""
        rel = None
        for candidate in (value, f"{experiment}/{value}" if experiment else None):
            if candidate in raws:
                rel = candidate
                break
        if rel is None and "/" not in value:
            if by_name[value] == 1:
                rel = name_to_rel[value]
            elif by_name[value] > 1:
                problems.append(Problem(log, line, LOG_FILE_COLUMN,
                                        f"{by_name[value]} raw files are named {value!r}",
                                        "give the path relative to RAW_DIR"))
                continue
        if rel is None:
            problems.append(Problem(log, line, LOG_FILE_COLUMN, f"no raw file {value!r} under RAW_DIR",
                                    "correct the name, add the file or delete the row"))
            continue
        if rel in seen:
            problems.append(Problem(log, line, LOG_FILE_COLUMN, f"{rel} already listed on line {seen[rel]}",
                                    "delete one of the two rows"))
            continue
        seen[rel] = line
        entry = raws[rel]
        if experiment:
            if entry.experiment is not None and entry.experiment != experiment:
                problems.append(Problem(log, line, LOG_EXPERIMENT_COLUMN,
                                        f"{experiment!r} but the file is in the {entry.experiment}/ folder",
                                        "correct the experiment or move the file"))
                continue
            entry.experiment = experiment
        entry.lab = {c: row[c] for c in usable}
    return usable, unused


# ---------------------------------------------------------------------------
# lens regions


def propose_lens_regions(rows_px: int, cols_px: int) -> list[LensProposal]:
    """Lens regions of a frame of rows_px x cols_px raw pixels, on even pixels (Bayer grid).

    Two square regions stacked when rows = 2 cols (the dual-fisheye frame, lenses ``far`` above ``close``),
    side by side when cols = 2 rows (``left``, ``right``), else the whole frame as one region (``main``).

    Parameters
    ----------
    rows_px : int
        Raw pixel rows of the frame.
    cols_px : int
        Raw pixel columns of the frame.

    Returns
    -------
    list of LensProposal
        One or two regions (rows and columns [start, stop) in raw pixels, even), no image circle found yet.
    """
    def even(n):
        return n // 2 * 2

    if rows_px == 2 * cols_px:
        side = even(cols_px)
        return [LensProposal(name, (i * side, (i + 1) * side), (0, side)) for i, name in enumerate(STACKED_LENSES)]
    if cols_px == 2 * rows_px:
        side = even(rows_px)
        return [LensProposal(name, (0, side), (i * side, (i + 1) * side))
                for i, name in enumerate(SIDE_BY_SIDE_LENSES)]
    return [LensProposal(SINGLE_LENS, (0, even(rows_px)), (0, even(cols_px)))]


def _lit_contrast_sigma(band: np.ndarray) -> float:
    """(centre median - corner median) / corner noise of a band image: large for a lit circle."""
    h, w = band.shape
    k = max(1, int(min(h, w) * CORNER_SIZE_FRACTION))
    corners = np.concatenate([band[:k, :k].ravel(), band[:k, -k:].ravel(),
                              band[-k:, :k].ravel(), band[-k:, -k:].ravel()])
    yy, xx = np.ogrid[:h, :w]
    centre = band[(yy - (h - 1) / 2) ** 2 + (xx - (w - 1) / 2) ** 2 <= k ** 2]
    outside = float(np.median(corners))
    noise = max(MAD_TO_SIGMA * float(np.median(np.abs(corners - outside))), NOISE_FLOOR_DN)
    return (float(np.median(centre)) - outside) / noise


def _lit_to_corners(band: np.ndarray, black_level_dn: float) -> bool:
    """The region's corners stand well above the black level: lit, as an ordinary camera's are."""
    h, w = band.shape
    k = max(1, int(min(h, w) * CORNER_SIZE_FRACTION))
    corners = np.concatenate([band[:k, :k].ravel(), band[:k, -k:].ravel(),
                              band[-k:, :k].ravel(), band[-k:, -k:].ravel()])
    level = float(np.median(corners))
    noise = max(MAD_TO_SIGMA * float(np.median(np.abs(corners - level))), NOISE_FLOOR_DN)
    return (level - black_level_dn) / noise > MIN_LIT_CONTRAST_SIGMA


def _circle_in(band: np.ndarray, black_level_dn: float | None = None):
    """The lit image circle of a band image (geometry's circle fit), or None with the reason.

    The reason is ``RECTILINEAR`` when the region is lit to its corners (the pixels outside the best
    circle lit by more than MAX_OUTSIDE_LIT_FRACTION of the inside, or the corners far above the
    black level): an ordinary camera's region, which has no image circle.
    """
    from pipeline.geometry.image_circle import find_image_circle, outside_lit_fraction

    if _lit_contrast_sigma(band) < MIN_LIT_CONTRAST_SIGMA:
        if black_level_dn is not None and _lit_to_corners(band, black_level_dn):
            return None, RECTILINEAR
        return None, "not lit (or lit up to its corners)"
    try:
        circle = find_image_circle(band)
    except ValueError as exc:
        return None, f"no circle found ({exc})"
    if black_level_dn is not None:
        lit = outside_lit_fraction(band, circle, black_level_dn)
        if np.isfinite(lit) and lit > MAX_OUTSIDE_LIT_FRACTION:
            return None, RECTILINEAR
    h, w = band.shape
    if not (0 <= circle.xc < w and 0 <= circle.yc < h):
        return None, "the fitted circle's centre lies outside the region"
    if circle.radius < MIN_CIRCLE_RADIUS_FRACTION * min(h, w) / 2:
        return None, f"the fitted circle is small (radius {2 * circle.radius:.0f} px): a spot, not the image circle"
    if circle.rms_px > MAX_CIRCLE_FIT_RMS_PX:
        return None, f"the edge is not one circle (RMS {circle.rms_px:.1f} px)"
    return circle, ""


def _circle_candidates(entries: dict[str, list[RawEntry]]) -> list[tuple[str, RawEntry]]:
    """Frames likely to show the image circles: lit experiments first, brightest settings first."""
    out = []
    for experiment in CIRCLE_EXPERIMENTS:
        frames = [e for e in entries.get(experiment, []) if e.lab.get("kind", "") != "dark" and e.tags]
        frames.sort(key=lambda e: (-(e.tags.get("exposure_s") or 0) * (e.tags.get("iso") or 0), e.target))
        out += [(experiment, e) for e in frames]
    return out


def find_lens_circles(lenses: list[LensProposal], entries: dict[str, list[RawEntry]],
                      max_frames: int = MAX_CIRCLE_FRAMES) -> None:
    """Fit each region's image circle on the first candidate frame that lights it (fills ``lenses``).

    Candidate frames are those of the lit experiments, brightest settings first; a frame the lab log assigns to
    one lens is tried for that lens only. A region lit to its corners is marked ``projection: rectilinear``; a
    region with no circle found gets a note saying why.

    Parameters
    ----------
    lenses : list of LensProposal
        The proposed regions; each one's circle (centre and radius in raw pixels of the frame), frame, note and
        projection are set in place.
    entries : dict[str, list of RawEntry]
        Experiment -> its raw files (tags read), as in :class:`ScaffoldPlan`.
    max_frames : int, optional
        Frames decoded at most (each decode reads a whole raw file); default ``MAX_CIRCLE_FRAMES`` (16).
    """
    reasons: dict[str, str] = {}
    decoded = 0
    for experiment, entry in _circle_candidates(entries):
        if all(lens.radius_px is not None or lens.projection == "rectilinear" for lens in lenses) \
                or decoded >= max_frames:
            break
        # a frame the lab log assigns to one lens lights only that lens
        todo = [lens for lens in lenses if lens.radius_px is None and lens.projection == "fisheye"
                and entry.lab.get("lens", "") in ("", "both", lens.name)]
        if not todo:
            continue
        try:
            raw = read_raw(entry.source, require=())
        except InputError:
            continue
        decoded += 1
        for lens in todo:
            try:
                region = cut_region(raw.cfa, lens.rows, lens.cols)
            except ValueError as exc:
                reasons[lens.name] = f"the region does not fit the frame ({exc})"
                continue
            band = split_bands(region, raw.cfa_pattern)["G"]
            circle, reason = _circle_in(band, raw.black_level)
            if reason == RECTILINEAR:
                lens.projection = "rectilinear"
                lens.frame = f"{experiment}/{entry.target}"
                lens.note = (f"lit to its corners ({lens.frame}): no image circle, proposed as "
                             "'projection: rectilinear' (an ordinary camera)")
                continue
            if circle is None:
                reasons.setdefault(lens.name, reason)
                continue
            # band pixel i covers raw pixels 2i and 2i + 1 of the region
            lens.centre_row_px = lens.rows[0] + 2 * circle.yc + 0.5
            lens.centre_col_px = lens.cols[0] + 2 * circle.xc + 0.5
            lens.radius_px = 2 * circle.radius
            lens.frame = f"{experiment}/{entry.target}"
            lens.note = ""
    for lens in lenses:
        if lens.radius_px is None and lens.projection == "fisheye":
            why = reasons.get(lens.name, "no frame outside dark/ to look at")
            lens.note = (f"no lit image circle found in {decoded} frame{'s' if decoded != 1 else ''} "
                         f"({why}): check this region; a rectilinear lens (the whole region lit) "
                         "needs 'projection: rectilinear'")


# ---------------------------------------------------------------------------
# the plan


def plan_dataset(raw_dir, lab_log=None, *, find_circles: bool = True) -> ScaffoldPlan:
    """Find the raw files, their experiments, tags and lab-log values, and propose the lens regions.

    Reads RAW_DIR and the lab log only (nothing is written).

    Parameters
    ----------
    raw_dir : str or pathlib.Path
        The lab's folder of raw files: one sub-folder per experiment, or files that the lab log assigns.
    lab_log : str or pathlib.Path, optional
        The CSV lab log (a ``file`` column, and ``experiment`` and lab columns); default none.
    find_circles : bool, optional
        Decode frames to check each proposed lens region for a lit image circle (:func:`find_lens_circles`);
        default True.

    Returns
    -------
    ScaffoldPlan
        The frames of each experiment in acquisition order, the sidecars, the ignored files, the camera from the
        tags, the frame shape and the proposed lens regions.

    Raises
    ------
    InputError
        When ``raw_dir`` is not a folder or holds no raw file, or (one error with every problem in ``problems``)
        when a raw file cannot be placed: no experiment folder and no lab-log experiment, a lab-log row naming no
        file, two files with the same target, ...
    """
    raw_dir = Path(raw_dir)
    if not raw_dir.is_dir():
        raise InputError(raw_dir, "raw folder not found" if not raw_dir.exists() else "is not a folder")
    raw_dir = raw_dir.resolve()
    log = Path(lab_log).resolve() if lab_log is not None else None
    raw_paths, other_paths = _raw_and_other_files(raw_dir)
    if not raw_paths:
        raise InputError(raw_dir, f"no raw files ({', '.join(RAW_SUFFIXES)}) in this folder or below")
    problems: list[Problem] = []
    raws: dict[str, RawEntry] = {}
    for path in raw_paths:
        rel = path.relative_to(raw_dir).as_posix()
        top = rel.split("/", 1)[0] if "/" in rel else None
        raws[rel] = RawEntry(source=path, source_rel=rel, experiment=top if top in EXPERIMENTS else None)
    log_columns, unused_columns = _read_lab_log(log, raws, problems) if log is not None else ([], [])
    for rel, entry in raws.items():
        if entry.experiment is None:
            top = rel.split("/", 1)[0] if "/" in rel else ""
            close = difflib.get_close_matches(top.lower(), EXPERIMENTS, n=1, cutoff=TYPO_SIMILARITY) if top else []
            fix = (f"rename the folder {top!r} to {close[0]!r}, or give the file's experiment in the lab log"
                   if close else "put it in an experiment folder (dark/, linearity/, ...) or give its "
                                 "experiment in the lab log (--lab-log)")
            problems.append(Problem(entry.source, message="no experiment for this raw file", fix=fix))
            continue
        entry.target = _target(rel, in_experiment_folder=rel.split("/", 1)[0] == entry.experiment)
    entries: dict[str, list[RawEntry]] = {}
    for entry in raws.values():
        if entry.experiment is not None:
            entries.setdefault(entry.experiment, []).append(entry)
    for experiment, items in entries.items():
        targets = Counter(e.target for e in items)
        for e in items:
            if targets[e.target] > 1:
                problems.append(Problem(e.source, message=f"another raw file also becomes {experiment}/{e.target}",
                                        fix="rename one of them"))
    if problems:
        raise InputError.from_problems(problems, "the list above says what to change")
    # tags (each file's header only)
    for items in entries.values():
        for e in items:
            try:
                e.tags = read_tags(e.source)
            except InputError:
                e.tags = None   # validation reports the file after it is laid out
        items.sort(key=lambda e: (e.tags is None or e.tags.get("time") is None,
                                  e.tags.get("time").isoformat() if e.tags and e.tags.get("time") else "",
                                  e.target))
    ordered = {exp: entries[exp] for exp in EXPERIMENTS if exp in entries}
    # sidecars beside the raw files (in the experiment folder, or at the top for a flat folder)
    sidecars: dict[str, list[Path]] = {}
    ignored = []
    owners = {name: exp for exp, names in SIDECARS.items() for name in names}
    for path in other_paths:
        rel = path.relative_to(raw_dir).as_posix()
        parts = rel.split("/")
        name = parts[-1]
        experiment = owners.get(name)
        placed = experiment in ordered and (parts[:-1] == [experiment] or len(parts) == 1)
        if log is not None and path == log:
            continue
        if placed:
            sidecars.setdefault(experiment, []).append(path)
        else:
            ignored.append(rel)
    notes = []
    if unused_columns:
        notes.append(f"lab log columns left out: {', '.join(unused_columns)} (frames.csv holds only the columns "
                     "of docs/dataset-format.md; the tags give exposure, ISO and time)")
    camera, shape = _camera_and_shape(ordered, notes)
    lenses = propose_lens_regions(*shape) if shape else []
    if find_circles and lenses:
        find_lens_circles(lenses, ordered)
    lab_columns = {exp: list(COMMON_COLUMNS[1:]) + list(EXPERIMENT_COLUMNS[exp])
                   + [c for c in OPTIONAL_COLUMNS if c in log_columns
                      and exp in OPTIONAL_COLUMN_EXPERIMENTS.get(c, (exp,))] for exp in ordered}
    return ScaffoldPlan(raw_dir=raw_dir, lab_log=log, entries=ordered, sidecars=sidecars, ignored=ignored,
                        lab_columns=lab_columns, camera=camera, frame_shape=shape, lenses=lenses, notes=notes)


def _camera_and_shape(entries: dict[str, list[RawEntry]], notes: list[str]):
    tags = [e.tags for items in entries.values() for e in items if e.tags]
    camera = {}
    for key in ("make", "model", "serial"):
        values = Counter(t[key] for t in tags if t.get(key))
        if values:
            camera[key] = values.most_common(1)[0][0]
            if len(values) > 1:
                notes.append(f"the raw files name {len(values)} values of the {key} tag "
                             f"({', '.join(sorted(values))}): one camera per dataset")
        elif key != "serial":
            camera[key] = ""
    if "serial" not in camera:
        notes.append("the tags give no serial number: add camera.serial to dataset.yaml if you know it")
    shapes = Counter(t["shape"] for t in tags if t.get("shape"))
    shape = shapes.most_common(1)[0][0] if shapes else None
    if shape is None:
        notes.append("no frame size in the tags: give the lens regions in dataset.yaml by hand")
    return camera, shape


# ---------------------------------------------------------------------------
# writing


def _frames_table(experiment: str, items: list[RawEntry], lab_columns: list[str]) -> pd.DataFrame:
    defaults = {"kind": "dark", "lens": "both"} if experiment == "dark" else {}
    rows = []
    for e in items:
        row = {"file": e.target}
        for column in lab_columns:
            row[column] = e.lab.get(column, "") or defaults.get(column, "")
        tags = e.tags or {}
        row["exposure_s"] = repr(float(tags["exposure_s"])) if tags.get("exposure_s") else ""
        row["iso"] = f"{tags['iso']:g}" if tags.get("iso") else ""
        row["time"] = tags["time"].isoformat() if tags.get("time") else ""
        rows.append(row)
    return pd.DataFrame(rows, columns=["file", *lab_columns, *TAG_COLUMNS])


def _dataset_yaml(plan: ScaffoldPlan) -> str:
    meta = {"layout": LAYOUT_VERSION, "camera": plan.camera,
            "lenses": {lens.name: {"rows": list(lens.rows), "cols": list(lens.cols),
                                   **({"projection": lens.projection} if lens.projection != "fisheye" else {})}
                       for lens in plan.lenses},
            "description": ""}
    head = ("# Laid out by `python -m pipeline init-dataset` from the raw files' tags (docs/dataset-format.md).\n"
            "# Confirm the lens regions ([start, stop) raw pixel rows and columns) and write a description.\n")
    return head + yaml.safe_dump(meta, sort_keys=False, default_flow_style=None)


def _place(source: Path, target: Path, copy: bool) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    if copy:
        shutil.copy2(source, target)
        return
    try:
        target.symlink_to(source)
    except OSError as exc:
        raise InputError(target, f"cannot create a symbolic link here ({exc.strerror or exc}); "
                                 "use --copy to copy the raw files") from None


def write_dataset(plan: ScaffoldPlan, out, copy: bool = False) -> Path:
    """Write the layout of ``plan`` to ``out`` (which must not exist), through a temporary folder.

    Parameters
    ----------
    plan : ScaffoldPlan
        What to write (:func:`plan_dataset`).
    out : str or pathlib.Path
        The dataset folder; written as a hidden sibling ``.<name>.partial`` and renamed at the end.
    copy : bool, optional
        Copy the raw files and sidecars; default False (symbolic links to the originals).

    Returns
    -------
    pathlib.Path
        ``out``: dataset.yaml, each experiment's frames.csv, raw files and sidecars, and MD5SUMS.

    Raises
    ------
    InputError
        When ``out`` exists, or a symbolic link cannot be made there (use ``copy``).
    """
    out = Path(out)
    if out.exists() or out.is_symlink():
        raise InputError(out, "already exists; init-dataset never overwrites a folder (choose another OUT)")
    tmp = out.parent / f".{out.name}.partial"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        (tmp / "dataset.yaml").write_text(_dataset_yaml(plan), encoding="utf-8")
        for experiment, items in plan.entries.items():
            folder = tmp / experiment
            folder.mkdir()
            for e in items:
                _place(e.source, folder / e.target, copy)
            for path in plan.sidecars.get(experiment, []):
                _place(path, folder / path.name, copy)
            _frames_table(experiment, items, plan.lab_columns[experiment]).to_csv(
                folder / "frames.csv", index=False)
        write_md5sums(tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    tmp.rename(out)
    return out


def init_dataset(raw_dir, out, lab_log=None, copy: bool = False) -> InitResult:
    """Plan, write and validate: the dataset at ``out`` and what the user must still fill in.

    Parameters
    ----------
    raw_dir : str or pathlib.Path
        The lab's folder of raw files (see :func:`plan_dataset`).
    out : str or pathlib.Path
        The dataset folder to write; it must not exist.
    lab_log : str or pathlib.Path, optional
        The CSV lab log; default none.
    copy : bool, optional
        Copy the raw files instead of linking them; default False.

    Returns
    -------
    InitResult
        The folder written, the plan, whether files were copied, and the problems validation still reports.

    Raises
    ------
    InputError
        When ``out`` exists or the raw files cannot be laid out (see :func:`plan_dataset`).
    """
    from pipeline.io.validation import validate_dataset

    out = Path(out)
    if out.exists() or out.is_symlink():
        raise InputError(out, "already exists; init-dataset never overwrites a folder (choose another OUT)")
    plan = plan_dataset(raw_dir, lab_log)
    write_dataset(plan, out, copy=copy)
    return InitResult(out=out, plan=plan, copied=copy, remaining=validate_dataset(out))


# ---------------------------------------------------------------------------
# what the terminal shows


def _span(span: tuple[int, int]) -> str:
    return f"[{span[0]}, {span[1]})"


def describe_result(result: InitResult) -> str:
    """What init-dataset wrote, the lens regions to confirm, and what is left to fill in.

    Parameters
    ----------
    result : InitResult
        What :func:`init_dataset` returned.

    Returns
    -------
    str
        The lines the terminal shows: files written, lens regions (with the image circle found, in raw pixels),
        notes, and the problems left or the command to run next.
    """
    from pipeline.io.validation import format_problems

    plan = result.plan
    lines = [f"wrote {result.out}:"]
    width = max(len(f"{exp}/frames.csv") for exp in plan.entries) + 2
    cam = " ".join(plan.camera.get(k, "") for k in ("make", "model", "serial") if plan.camera.get(k))
    lenses = ", ".join(lens.name for lens in plan.lenses) or "none"
    lines.append(f"  {'dataset.yaml':<{width}s}camera {cam or '(unknown)'}; lenses {lenses}")
    how = "copied" if result.copied else "linked to the originals"
    for experiment, items in plan.entries.items():
        extra = [p.name for p in plan.sidecars.get(experiment, [])]
        lines.append(f"  {experiment + '/frames.csv':<{width}s}{len(items)} frames ({how})"
                     + (f"; {', '.join(extra)}" if extra else ""))
    n_files = sum(1 for line in (result.out / "MD5SUMS").read_text().splitlines() if line.strip())
    lines.append(f"  {'MD5SUMS':<{width}s}{n_files} files")
    if plan.frame_shape:
        rows, cols = plan.frame_shape
        lines.append("")
        lines.append(f"lens regions proposed from the {rows} x {cols} frames (confirm them in dataset.yaml):")
        name_width = max(len(lens.name) for lens in plan.lenses)
        for lens in plan.lenses:
            where = f"  {lens.name + ':':<{name_width + 1}s} rows {_span(lens.rows)}, cols {_span(lens.cols)}"
            if lens.radius_px is not None:
                where += (f": image circle at row {lens.centre_row_px:.1f}, col {lens.centre_col_px:.1f}, "
                          f"radius {lens.radius_px:.1f} px ({lens.frame})")
            else:
                where += f": {lens.note}"
            lines.append(where)
    if plan.notes:
        lines.append("")
        lines += [f"note: {note}" for note in plan.notes]
    if plan.ignored:
        shown = ", ".join(plan.ignored[:5]) + (", ..." if len(plan.ignored) > 5 else "")
        lines.append(f"note: left out {len(plan.ignored)} file{'s' if len(plan.ignored) != 1 else ''} that are "
                     f"neither raw frames nor sidecars: {shown}")
    if not result.copied:
        lines.append("note: the raw files are symbolic links into the raw folder: use --copy for a dataset "
                     "to move or upload")
    lines.append("")
    if result.remaining:
        lines.append("still to fill in (python -m pipeline validate lists the same):")
        lines.append(format_problems(result.remaining, result.out))
        lines.append("")
        lines.append("fill these in the frames.csv files (or correct the lab log and run init-dataset again into "
                     "a new folder),")
        lines.append(f"then run: python -m pipeline validate {result.out}")
    else:
        lines.append("the dataset validates; run: snakemake --cores 2 --config dataset=" + str(result.out.resolve()))
    return "\n".join(lines)


# ---------------------------------------------------------------------------
# EMVA1288 measurements (descriptor and PNG frames) as DNG files and a lab log

#: the DNG's ISO for a camera with one gain: ISO 100 is gain 1 (radiometry.exposure.gain_from_iso), so the dark
#: model's per-ISO-100 figures (dark current in DN/s) are the camera's own
EMVA1288_ISO = 100
#: acquisition times written to the DNGs: the descriptor gives none, so the frames get this start and one
#: second per frame in descriptor order (init-dataset orders frames by time: the descriptor's order is kept)
EMVA1288_START = datetime(2011, 1, 1, 0, 0, 0)
#: the lab-log name written beside the DNGs
EMVA1288_LAB_LOG = "lab_log.csv"


@dataclass(frozen=True)
class Emva1288Frame:
    """One image of an EMVA1288 descriptor: bright (b) or dark (d), its exposure and photons per pixel."""

    image: Path                   # the PNG file
    kind: str                     # "signal" (a ``b`` block) or "dark" (a ``d`` block)
    exposure_s: float
    photons_per_pixel: float      # the descriptor's photon count of a bright block; NaN for a dark one
    step: int                     # index of the block among its kind, in descriptor order


def read_emva1288_descriptor(path) -> tuple[int, tuple[int, int], list[Emva1288Frame]]:
    """The bits, (height, width) and frames of an EMVA1288 descriptor (``EMVA1288_Data.txt``).

    The format: ``n BITS WIDTH HEIGHT``, then blocks ``b EXPOSURE_NS PHOTONS`` (bright) and ``d EXPOSURE_NS``
    (dark), each followed by its images ``i RELATIVE_PATH`` (Windows separators allowed); ``#`` comments and
    the ``v`` version line are skipped.

    Parameters
    ----------
    path : str or pathlib.Path
        The descriptor file; image paths are relative to its folder.

    Returns
    -------
    bits : int
        The bit depth of the frames.
    shape : tuple of (int, int)
        (height, width) of the frames, pixels.
    frames : list of Emva1288Frame
        Every image in descriptor order, with its kind, exposure (s) and photons per pixel.

    Raises
    ------
    InputError
        When the file is missing, a line is malformed (named), or there is no ``n`` line or no image.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "EMVA1288 descriptor not found")
    bits, shape, frames, block = None, None, [], None
    steps = Counter()
    for number, line in enumerate(path.read_text(encoding="latin-1").splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#") or fields[0] == "v":
            continue
        try:
            if fields[0] == "n":
                bits, shape = int(fields[1]), (int(fields[3]), int(fields[2]))
            elif fields[0] in ("b", "d"):
                kind = "signal" if fields[0] == "b" else "dark"
                photons = float(fields[2]) if kind == "signal" else float("nan")
                block = (kind, float(fields[1]) * 1e-9, photons, steps[kind])
                steps[kind] += 1
            elif fields[0] == "i":
                if block is None:
                    raise ValueError("an image before any b or d block")
                image = path.parent / PurePosixPath(line.split(None, 1)[1].strip().replace("\\", "/"))
                frames.append(Emva1288Frame(image, block[0], block[1], block[2], block[3]))
            else:
                raise ValueError(f"unknown line type {fields[0]!r}")
        except (IndexError, ValueError) as exc:
            raise InputError(path, f"line {number} is not EMVA1288 descriptor syntax ({exc}): {line.strip()!r}") \
                from None
    if bits is None or not frames:
        raise InputError(path, "no 'n BITS WIDTH HEIGHT' line or no images: not an EMVA1288 descriptor")
    return bits, shape, frames


def emva1288_raw_folder(descriptor, raw_dir, *, make: str, model: str, serial: str,
                        crop_px: tuple[int, int] | None = None) -> Path:
    """Wrap an EMVA1288 measurement as a lab's raw folder: DNG files under ``dark/`` and ``linearity/`` and a lab log.

    Each PNG becomes one DNG (:func:`pipeline.io.rawio.write_dng`) holding its values unchanged: ExposureTime from
    the descriptor, ISO ``EMVA1288_ISO`` (one gain), the acquisition time ``EMVA1288_START`` plus one second per
    frame in descriptor order (the descriptor gives none), BlackLevel 0 (the files carry none: the dark stage
    measures it), WhiteLevel 2^bits - 1 and an RGGB CFA tag over the monochrome data (each band is a quarter
    or, for G, half of the same sensor's pixels: the per-pixel statistics are the sensor's).  Dark blocks go to
    ``dark/``, bright ones to ``linearity/`` as an exposure sweep of the one lens region ``main``.  The lab log
    also holds the descriptor's photons per pixel (``photons_per_pixel``, which init-dataset carries into
    linearity/frames.csv: the linearity stage's responsivity and quantum efficiency) and block index
    (``emva1288_step``, which frames.csv leaves out).

    Parameters
    ----------
    descriptor : str or pathlib.Path
        The EMVA1288 descriptor (:func:`read_emva1288_descriptor`).
    raw_dir : str or pathlib.Path
        The raw folder to write; it must not exist.
    make : str
        The camera's make, written in the DNG tags (the descriptor does not name the camera) and so in dataset.yaml.
    model : str
        The camera's model, likewise.
    serial : str
        The camera's serial number, likewise.
    crop_px : tuple of (int, int), optional
        (rows, cols), even, of the centre of each frame to keep; default None (the whole frame).

    Returns
    -------
    pathlib.Path
        The lab log's path (for :func:`init_dataset`).

    Raises
    ------
    InputError
        When ``raw_dir`` exists, the crop is odd or larger than the frames, or an image cannot be read, is not a
        16-bit PNG of the descriptor's size, or holds values above the bit depth.
    """
    import cv2

    raw_dir = Path(raw_dir)
    if raw_dir.exists():
        raise InputError(raw_dir, "already exists; the EMVA1288 wrapper never writes into an existing folder")
    bits, (height, width), frames = read_emva1288_descriptor(descriptor)
    rows, cols = crop_px if crop_px is not None else (height, width)
    if rows % 2 or cols % 2 or not (0 < rows <= height and 0 < cols <= width):
        raise InputError(None, f"crop {rows} x {cols} must be even and within the {height} x {width} frames")
    top, left = (height - rows) // 4 * 2, (width - cols) // 4 * 2        # on the CFA grid
    white = 2 ** bits - 1
    log_rows = []
    for k, frame in enumerate(frames):
        values = cv2.imread(str(frame.image), cv2.IMREAD_UNCHANGED)
        if values is None:
            raise InputError(frame.image, "cannot be read as an image")
        if values.shape != (height, width) or values.dtype != np.uint16:
            raise InputError(frame.image, f"is {values.shape} {values.dtype}, the descriptor says {height} x {width} "
                                          f"{bits}-bit (16-bit PNG)")
        if int(values.max()) > white:
            raise InputError(frame.image, f"holds {int(values.max())}, above the {bits}-bit range")
        experiment = "dark" if frame.kind == "dark" else "linearity"
        name = f"{experiment}/{frame.image.stem}.dng"
        target = raw_dir / name
        target.parent.mkdir(parents=True, exist_ok=True)
        write_dng(target, values[top:top + rows, left:left + cols], exposure_s=frame.exposure_s,
                  iso=EMVA1288_ISO, time=EMVA1288_START + timedelta(seconds=k), black_level=0, white_level=white,
                  cfa_pattern="RGGB", make=make, model=model, serial=serial)
        log_rows.append({LOG_FILE_COLUMN: name, LOG_EXPERIMENT_COLUMN: experiment,
                         "lens": SINGLE_LENS if experiment == "linearity" else "both", "kind": frame.kind,
                         "sweep": "exposure" if experiment == "linearity" else "",
                         "photons_per_pixel": frame.photons_per_pixel, "emva1288_step": frame.step})
    log = raw_dir / EMVA1288_LAB_LOG
    pd.DataFrame(log_rows).to_csv(log, index=False)
    return log


def init_emva1288_dataset(descriptor, raw_dir, out, *, make: str, model: str, serial: str,
                          crop_px: tuple[int, int] | None = None) -> InitResult:
    """An EMVA1288 measurement as a dataset: :func:`emva1288_raw_folder` into ``raw_dir``, then :func:`init_dataset`.

    The dataset is written into ``out`` with the wrapper's lab log (the DNGs linked).  The one lens region is lit
    to its corners in the bright frames, so init-dataset proposes it ``projection: rectilinear``.

    Parameters
    ----------
    descriptor : str or pathlib.Path
        The EMVA1288 descriptor (``EMVA1288_Data.txt``).
    raw_dir : str or pathlib.Path
        The raw folder of DNGs and lab log to write; it must not exist.
    out : str or pathlib.Path
        The dataset folder to write; it must not exist.
    make : str
        The camera's make (DNG tags, dataset.yaml).
    model : str
        The camera's model.
    serial : str
        The camera's serial number.
    crop_px : tuple of (int, int), optional
        (rows, cols), even, of the centre of each frame to keep; default None (the whole frame).

    Returns
    -------
    InitResult
        As :func:`init_dataset`.
    """
    log = emva1288_raw_folder(descriptor, raw_dir, make=make, model=model, serial=serial, crop_px=crop_px)
    return init_dataset(raw_dir, out, lab_log=log)

"""Every problem of a dataset at once: layout, the tags of every frame, sidecars, and their consistency.

``validate_dataset(root)`` returns a list of :class:`pipeline.errors.Problem`
(file, line, column, what is wrong, how to fix it), empty when the dataset is
fine; ``format_problems`` groups them for a person to read (one block per
file, identical problems on many rows merged into line ranges, identical
problems of many raw files merged per folder).  The command line's
``validate`` and the workflow's start-up check both call ``inspect_dataset``.
"""

from __future__ import annotations

import hashlib
import math
import os
import pickle
import re
from collections import Counter
from datetime import datetime
from pathlib import Path

from pipeline.io.consistency import FrameTags, check_consistency
from pipeline.io.dataset import SIDECARS, Dataset, LayoutCheck, check_checksums, check_sidecars, inspect_layout
from pipeline.errors import InputError, Problem
from pipeline.io import rawio
from pipeline.io.rawio import TAG_NAMES, read_tags, tag_problem

__all__ = ["REQUIRED_TAGS", "validate_dataset", "inspect_dataset", "check_tags", "format_problems", "ok_line",
           "unlisted_files", "warning_lines", "grouped_warning_lines"]

#: tags every calibration frame needs (RawFrame field -> tag name); frames.csv never replaces them
REQUIRED_TAGS = {key: TAG_NAMES[key] for key in ("exposure_s", "iso", "time")}
#: a copy of ExposureTime in frames.csv matches its tag within this relative difference
#: (the copy init-dataset writes is exact; a hand-typed 0.0083 for 1/120 s is not a copy)
EXPOSURE_COPY_REL_TOL = 1e-6
#: a copy of DateTimeOriginal in frames.csv matches its tag within this many seconds
#: (a copy written to whole seconds still matches)
TIME_COPY_TOL_S = 1.0
#: line ranges listed per merged problem before the rest is only counted
MAX_RANGES_SHOWN = 6
#: file names listed per merged folder problem before the rest is only counted
MAX_NAMES_SHOWN = 4

_TAG_FIX = ("use the file exactly as the camera wrote it (a converted or edited copy may have lost "
            "its tags); the tags are the truth about each exposure")


#: (path, size, modification and change times, inode) -> the file's tags as read_tags gave them: the stages of
#: one calibration run from Python check overlapping experiments (linearity reads dark's frames' tags again,
#: rolloff and the others geometry's), and a file that changed has another key
_TAGS_SEEN: dict[tuple, dict] = {}
#: entries kept before the cache starts again (a few full-scale datasets' frames)
_TAGS_SEEN_MAX = 20000


def _tags_seen(raw_path: Path) -> dict:
    stat = Path(raw_path).stat()
    key = (str(Path(raw_path).resolve()), stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_ino)
    tags = _TAGS_SEEN.get(key)
    if tags is None:
        if len(_TAGS_SEEN) >= _TAGS_SEEN_MAX:
            _TAGS_SEEN.clear()
        tags = _TAGS_SEEN[key] = read_tags(raw_path)
    return {**tags, "path": Path(raw_path)}


#: environment variable naming the folder of the tag cache (``off``: no cache, every start reads every file)
TAG_CACHE_ENV = "PIPELINE_CACHE_DIR"


def tag_cache_file(root) -> Path | None:
    """The file that keeps the tags of the frames under dataset folder ``root`` between processes.

    A workflow run checks the whole dataset at every start, a dry run included, and reading the tags of
    thousands of frames is most of that check. The file lies in ``$PIPELINE_CACHE_DIR`` or the user's cache
    folder (``$XDG_CACHE_HOME``, else ``~/.cache``), under ``camera-radiometer-pipeline/tags/``, one per
    dataset folder; an entry is used only for a file of the same path, size, modification and change times
    and inode (an edited or replaced frame is read again), and only by the reader that wrote it (the key
    holds a hash of ``pipeline.io.rawio``'s source). None when the variable is ``off``.

    Parameters
    ----------
    root : str or pathlib.Path
        The dataset's folder.

    Returns
    -------
    pathlib.Path or None
        The cache file (named by a hash of the folder's resolved path; it may not exist yet), or ``None``.
    """
    where = os.environ.get(TAG_CACHE_ENV, "")
    if where.lower() == "off":
        return None
    base = Path(where) if where else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / \
        "camera-radiometer-pipeline"
    name = hashlib.sha256(str(Path(root).resolve()).encode()).hexdigest()[:24]
    return base / "tags" / f"{name}.pickle"


def _reader_version() -> str:
    return hashlib.sha256(Path(rawio.__file__).read_bytes()).hexdigest()


def _load_tag_cache(root) -> int:
    """The cached tags of ``root``'s frames into the process's own cache; the number of entries found."""
    path = tag_cache_file(root)
    if path is None or not path.is_file():
        return 0
    try:
        version, entries = pickle.loads(path.read_bytes())
    except Exception:  # noqa: BLE001 - a cache that cannot be read costs only the time of reading the frames
        return 0
    if version != _reader_version() or not isinstance(entries, dict):
        return 0
    for key, tags in entries.items():
        _TAGS_SEEN.setdefault(key, tags)
    return len(entries)


def _save_tag_cache(root) -> None:
    """The tags read of ``root``'s frames, written atomically (a process reading it meanwhile sees the old
    file whole); a cache folder that cannot be written costs only time."""
    path = tag_cache_file(root)
    if path is None:
        return
    prefix = str(Path(root).resolve()) + os.sep
    entries = {key: tags for key, tags in _TAGS_SEEN.items() if key[0].startswith(prefix)}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        part = path.with_name(f"{path.name}.{os.getpid()}.part")
        part.write_bytes(pickle.dumps((_reader_version(), entries), protocol=pickle.HIGHEST_PROTOCOL))
        os.replace(part, path)
    except OSError:
        pass


def check_tags(raw_path: Path) -> tuple[dict | None, list[Problem]]:
    """The tags of one raw file and the problems of the tags a calibration frame needs.

    Parameters
    ----------
    raw_path : pathlib.Path
        The raw file.

    Returns
    -------
    tags : dict or None
        The tags as :func:`pipeline.io.rawio.read_tags` gives them (``path`` set to ``raw_path``); ``None`` when
        the file cannot be read.
    problems : list[pipeline.errors.Problem]
        One per required tag (:data:`REQUIRED_TAGS`) absent or zero, or the one problem of an unreadable file.
    """
    try:
        tags = _tags_seen(raw_path)
    except InputError as exc:
        return None, [Problem(Path(raw_path), message=exc.problem,
                              fix="replace it with the file as the camera wrote it")]
    problems = [Problem(Path(raw_path), message=tag_problem(key), fix=_TAG_FIX)
                for key in REQUIRED_TAGS if tags.get(key) in (None, 0, 0.0)]
    return tags, problems


def _copy_problems(csv_path: Path, line: int, row: dict, tags: dict) -> list[Problem]:
    """Problems of the tag copies (exposure_s, iso, time) a frames.csv row may hold."""
    out = []

    def differs(column, tag_value, text):
        out.append(Problem(csv_path, line, column, f"{text} but the file's {REQUIRED_TAGS[column]} tag says "
                                                   f"{tag_value}",
                           "the tags are the truth: copy the tag's value or leave the cell empty"))

    exposure, iso, stamp = row.get("exposure_s"), row.get("iso"), row.get("time")
    if (isinstance(exposure, float) and not math.isnan(exposure) and tags.get("exposure_s")
            and abs(exposure - tags["exposure_s"]) > EXPOSURE_COPY_REL_TOL * tags["exposure_s"]):
        differs("exposure_s", f"{tags['exposure_s']:.9g}", f"{exposure:.9g}")
    if isinstance(iso, float) and not math.isnan(iso) and tags.get("iso") and iso != tags["iso"]:
        differs("iso", f"{tags['iso']:g}", f"{iso:g}")
    if isinstance(stamp, str) and stamp and tags.get("time") is not None:
        try:
            copy = datetime.fromisoformat(stamp)
        except ValueError:
            copy = None  # frames.csv's own check reports it
        if copy is not None and abs((copy - tags["time"]).total_seconds()) > TIME_COPY_TOL_S:
            differs("time", tags["time"].isoformat(), stamp)
    return out


def _frame_problems(check: LayoutCheck, read: list[FrameTags] | None = None, experiments=None) -> list[Problem]:
    """Tags of every frame frames.csv lists, its tag copies, and the frame size against the lenses.

    ``read``, when given, receives each readable frame with its tags (for ``pipeline.io.consistency``);
    ``experiments``, when given, the experiments whose frames are read (default: all).
    """
    problems: list[Problem] = []
    shapes: dict[tuple[int, int], list[Path]] = {}
    for experiment, (table, lines) in check.tables.items():
        if experiments is not None and experiment not in experiments:
            continue
        csv_path = check.root / experiment / "frames.csv"
        for (_, row), line in zip(table.iterrows(), lines):
            path = row["path"]
            if not isinstance(path, Path) or not path.is_file():     # None (or pandas' NaN): no file
                continue
            tags, found = check_tags(path)
            problems += found
            if tags is None:
                continue
            problems += _copy_problems(csv_path, line, row.to_dict(), tags)
            if read is not None:
                read.append(FrameTags(experiment, str(row["file"]), line, str(row.get("kind")), Path(path), tags))
            if tags.get("shape"):
                shapes.setdefault(tags["shape"], []).append(Path(path))
    if not shapes:
        return problems
    common = max(shapes, key=lambda s: len(shapes[s]))
    for shape, paths in shapes.items():
        if shape != common:
            problems += [Problem(p, message=f"frame is {shape[0]} x {shape[1]} pixels but most frames are "
                                            f"{common[0]} x {common[1]}",
                                 fix="keep one camera mode per dataset (same resolution in every frame)")
                         for p in paths]
    if check.lenses:
        rows_px, cols_px = common
        for name, ((r0, r1), (c0, c1)) in check.lenses.items():
            if r1 > rows_px or c1 > cols_px:
                problems.append(Problem(check.root / "dataset.yaml",
                                        message=f"lenses.{name} (rows [{r0}, {r1}), cols [{c0}, {c1})) does "
                                                f"not fit the {rows_px} x {cols_px} frames",
                                        fix="give the region in raw pixels of the frame "
                                            "(python -m pipeline init-dataset proposes regions)"))
    return problems


def _chessboard_problems(check: LayoutCheck) -> list[Problem]:
    """The geometry stage needs the chessboard of dataset.yaml, with a square size per medium used."""
    if "geometry" not in check.tables or not isinstance(check.meta, dict):
        return []
    path = check.root / "dataset.yaml"
    fix = "write chessboard: {inner_corners: [columns, rows], square_mm: {air: 30.0, water: 20.0}}"
    board = check.meta.get("chessboard")
    if board is None:
        return [Problem(path, message="geometry/ is present but there is no 'chessboard' entry", fix=fix)]
    squares = board.get("square_mm") if isinstance(board, dict) else None
    if not isinstance(squares, dict):
        return []  # the layout check reports it
    table, _ = check.tables["geometry"]
    used = sorted({m for m in table.get("medium", []) if m in ("air", "water")})
    return [Problem(path, message=f"chessboard.square_mm has no size for medium {m!r} "
                                  "(geometry/frames.csv uses it)", fix=f"add square_mm: {{{m}: <size in mm>}}")
            for m in used if m not in squares]


def inspect_dataset(root, *, checksums: bool = False, warnings: list[Problem] | None = None,
                    experiments=None, field_settings: dict | None = None) -> tuple[Dataset | None, list[Problem]]:
    """The dataset (None unless it is fine) and every problem found.

    Checks dataset.yaml, MD5SUMS, every frames.csv, the tags every frame needs
    (and the copies of them a frames.csv may hold), the frame size against the
    lens regions, the chessboard when geometry/ is present, the sidecar files,
    and the parts against each other (``pipeline.io.consistency``: the frames'
    camera, CFA pattern and levels, the lens regions, the field sidecars).
    The tags read are kept between processes (:func:`tag_cache_file`).

    Parameters
    ----------
    root : str or pathlib.Path
        The dataset's folder.
    checksums : bool, default False
        Also read every file and compare its MD5 with MD5SUMS (slow: the stages compare them anyway while
        they decode).
    warnings : list[pipeline.errors.Problem] or None, optional
        When given, receives what can only be suspected (time stamps, the sun below the horizon at the field
        site): the caller prints them.
    experiments : collection of str or None, optional
        When given, limits the frames, sidecars and their consistency to those experiments (a stage run on its
        own reads no other frames); dataset.yaml, MD5SUMS and every frames.csv are checked in any case.
    field_settings : dict or None, optional
        The run's ``field`` config section (the reference's match-up window and clock search); default the
        schema's.

    Returns
    -------
    dataset : Dataset or None
        The opened dataset when no problem was found, else ``None``.
    problems : list[pipeline.errors.Problem]
        Every problem found; empty when the dataset is fine.
    """
    check = inspect_layout(root)
    if not check.root.is_dir():
        return None, list(check.problems)
    present = [e for e in check.experiments() if experiments is None or e in experiments]
    problems = list(check.problems)
    if "geometry" in present:
        problems += _chessboard_problems(check)
    sidecars: dict = {}
    problems += check_sidecars(check.root, present, sidecars)
    frames: list[FrameTags] = []
    cached = _load_tag_cache(check.root)
    seen_before = len(_TAGS_SEEN)
    problems += _frame_problems(check, frames, present)
    if len(_TAGS_SEEN) != seen_before or not cached:
        _save_tag_cache(check.root)
    found, suspected = check_consistency(check.root, check.meta, check.lenses, frames, present, sidecars=sidecars,
                                         field_settings=field_settings)
    problems += found
    if warnings is not None:
        warnings += suspected
    if checksums and check.md5sums:
        problems += check_checksums(check.root, check.md5sums)
    if problems:
        return None, problems
    return check.dataset(), []


def validate_dataset(root, *, checksums: bool = False) -> list[Problem]:
    """Every problem of the dataset at ``root``; empty when it is fine.

    Parameters
    ----------
    root : str or pathlib.Path
        The dataset's folder.
    checksums : bool, default False
        Also compare every file's MD5 with MD5SUMS (reads every byte).

    Returns
    -------
    list[pipeline.errors.Problem]
        Every problem found (:func:`inspect_dataset`); warnings are not included.
    """
    return inspect_dataset(root, checksums=checksums)[1]


def unlisted_files(dataset: Dataset) -> list[Problem]:
    """Files inside an experiment folder that its frames.csv does not list (nor a sidecar): warnings.

    The stages read only the frames frames.csv lists, so such a file is ignored; it is
    a warning, not a problem, because a lab may keep notes or spare frames beside them.
    Hidden files (``.name``) are left out.

    Parameters
    ----------
    dataset : Dataset
        The opened dataset.

    Returns
    -------
    list[pipeline.errors.Problem]
        One warning per unlisted file, in the order of the experiments and the files' paths.
    """
    found = []
    for experiment in dataset.experiments():
        folder = dataset.root / experiment
        known = {"frames.csv", *SIDECARS.get(experiment, ())}
        listed = set(dataset.frames(experiment)["file"].astype(str))
        for path in sorted(folder.rglob("*")):
            rel = path.relative_to(folder).as_posix()
            if not path.is_file() or rel in known or rel in listed or any(
                    part.startswith(".") for part in path.relative_to(folder).parts):
                continue
            found.append(Problem(path, message=f"not listed in {experiment}/frames.csv: the stages ignore it",
                                 fix=f"add a row for it to {experiment}/frames.csv, or move it out of the dataset"))
    return found


def warning_lines(warnings: list[Problem]) -> list[str]:
    """``warning: <file>: <problem>`` per warning.

    Parameters
    ----------
    warnings : list[pipeline.errors.Problem]
        The warnings to print.

    Returns
    -------
    list[str]
        One line per warning, in order.
    """
    return [f"warning: {w}" for w in warnings]


def grouped_warning_lines(warnings: list[Problem], root=None) -> list[str]:
    """``warning: <file>: <what was seen>; fix: <how>`` per kind of warning and file, those of one kind
    in many files of a folder merged (``warning: linearity/raw/: ...: a.dng, b.dng [2 files]``).

    Parameters
    ----------
    warnings : list[pipeline.errors.Problem]
        The warnings to print.
    root : str or pathlib.Path or None, optional
        The dataset's folder: files are shown relative to it; ``None`` (default) shows them as given.

    Returns
    -------
    list[str]
        One line per merged warning, in order of first appearance.
    """
    if root is not None:
        root = Path(root).resolve() if Path(root).exists() else Path(root)
    out = []
    for header, entries in _group(warnings, root).items():
        for entry in entries:
            fix = f"; fix: {entry['fix']}" if entry["fix"] else ""
            out.append(f"warning: {header}: {_entry_text(entry)}{fix}")
    return out


def ok_line(dataset: Dataset) -> str:
    """``ok: 169 frames in 2 experiments (dark, linearity)``.

    Parameters
    ----------
    dataset : Dataset
        The opened dataset.

    Returns
    -------
    str
        The line: the number of frames listed and the experiments present.
    """
    experiments = dataset.experiments()
    n = sum(len(dataset.frames(e)) for e in experiments)
    return (f"ok: {n} frame{'s' if n != 1 else ''} in {len(experiments)} experiment"
            f"{'s' if len(experiments) != 1 else ''} ({', '.join(experiments) or 'none'})")


# ---------------------------------------------------------------------------
# formatting


def _ranges(lines: list[int]) -> tuple[str, int]:
    """'2-40, 42, 50-60' (at most MAX_RANGES_SHOWN ranges) and the number of lines."""
    values = sorted(set(lines))
    spans: list[list[int]] = []
    for v in values:
        if spans and v == spans[-1][1] + 1:
            spans[-1][1] = v
        else:
            spans.append([v, v])
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in spans[:MAX_RANGES_SHOWN])
    if len(spans) > MAX_RANGES_SHOWN:
        text += ", ..."
    return text, len(values)


def _display(path: Path | None, root: Path | None) -> str:
    if path is None:
        return "(no file)"
    if root is not None:
        try:
            rel = Path(path).relative_to(root).as_posix()
            return rel if rel not in ("", ".") else str(path)
        except ValueError:
            pass
    return str(path)


#: the parts of a message that vary from row to row (quoted values, paths, numbers)
_VARYING = re.compile(r"'[^']*'|\"[^\"]*\"|[\w.\-]*/[\w./\-]*|\b\d+(?:\.\d+)?\b")


def _template(message: str) -> str:
    """The message with its varying parts blanked: problems of one kind share it."""
    return _VARYING.sub("_", message)


def _group(problems: list[Problem], root: Path | None) -> dict[str, list[dict]]:
    """Header (file, or folder for per-file problems) -> merged entries, in order of appearance.

    Problems of one kind (same file, column, fix and message template) on
    several lines merge into one entry; so do file-level problems of one kind
    in several files of one folder (the tags of many raw files, say).
    """
    folder_count = Counter((p.path.parent, _template(p.message), p.fix) for p in problems
                           if p.path is not None and p.line is None and p.column is None)
    blocks: dict[str, list[dict]] = {}
    index: dict[tuple, dict] = {}
    for p in problems:
        per_file = p.path is not None and p.line is None and p.column is None
        if per_file and folder_count[(p.path.parent, _template(p.message), p.fix)] > 1:
            header = _display(p.path.parent, root).rstrip("/") + "/"
            key = ("folder", p.path.parent, _template(p.message), p.fix)
        else:
            header = _display(p.path, root)
            key = ("file", p.path, p.column, _template(p.message), p.fix)
        entry = index.get(key)
        if entry is None:
            entry = index[key] = {"problems": [], "column": p.column, "fix": p.fix, "folder": key[0] == "folder"}
            blocks.setdefault(header, []).append(entry)
        entry["problems"].append(p)
    return blocks


def _entry_text(entry: dict) -> str:
    problems = entry["problems"]
    first = problems[0]
    variants = len({p.message for p in problems})
    if entry["folder"]:
        names = sorted(p.path.name for p in problems)
        shown = ", ".join(names[:MAX_NAMES_SHOWN]) + (", ..." if len(names) > MAX_NAMES_SHOWN else "")
        text = first.message if variants == 1 else f"{first.message} (and {variants - 1} more like it)"
        return f"{text}: {shown} [{len(names)} files]"
    lines = [p.line for p in problems if p.line is not None]
    where = []
    if lines:
        ranges, count = _ranges(lines)
        where.append(f"line{'s' if count > 1 else ''} {ranges}")
    if entry["column"] is not None:
        where.append(f"column {entry['column']!r}")
    text = (", ".join(where) + ": " if where else "") + first.message
    if variants > 1:
        text += f", and {variants - 1} more like it"
    if len(problems) > 1:
        text += f" [{len(problems)} rows]" if lines else f" [{len(problems)} times]"
    return text


def format_problems(problems: list[Problem], root=None) -> str:
    """The problems grouped by file, with a count, for a person to read (several lines).

    Parameters
    ----------
    problems : list[pipeline.errors.Problem]
        The problems found, in the order they were found.
    root : str or pathlib.Path or None, optional
        The dataset's folder: files are shown relative to it and it is named in the first line; ``None``
        (default) shows them as given.

    Returns
    -------
    str
        A first line counting the problems and files, then one block per file (or folder, for identical
        problems of several files), problems of one kind on several lines merged into line ranges, each
        followed by its fix.
    """
    if root is not None:
        root = Path(root).resolve() if Path(root).exists() else Path(root)
    blocks = _group(problems, root)
    n_files = len({p.path for p in problems})
    out = [f"{len(problems)} problem{'s' if len(problems) != 1 else ''} in {n_files} "
           f"file{'s' if n_files != 1 else ''}" + (f" of {root}" if root is not None else "") + ":"]
    for header, entries in blocks.items():
        count = sum(len(e["problems"]) for e in entries)
        out.append("")
        out.append(f"{header} ({count} problem{'s' if count != 1 else ''})")
        for entry in entries:
            out.append(f"  {_entry_text(entry)}")
            if entry["fix"]:
                out.append(f"      fix: {entry['fix']}")
    return "\n".join(out)

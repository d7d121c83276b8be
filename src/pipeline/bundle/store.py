"""The calibration store: published calibration bundles, append-only, and the one valid at a frame's time.

A calibration feeds years of field data, so a published one is never
overwritten or lost. ``python -m pipeline publish BUNDLE`` files a bundle
(``results/calibration/<serial>.nc``, :mod:`pipeline.bundle.calibration`) into a
store folder::

    STORE/index.csv                                   one row per published bundle
    STORE/<serial>/<valid_from>_<sha256[:16]>.nc      read-only copies, never rewritten

Each bundle is valid from a time on the camera's clock (the frames'
DateTimeOriginal, local time as the camera wrote it): by default the latest
time stamp of the lab frames it was made from (``--dataset``: the dataset the
calibration ran on), or the ``--valid-from`` a user gives (a calibration meant
for frames taken after a given day). It stays valid until a newer one of the
same camera begins. The file name holds the validity start and the first 16
hex digits of the file's sha256; the index holds the whole sha256, so a store
file changed after publishing is detected (:func:`verify_store`, and before
``apply`` uses a selected bundle).

Publishing the same content (sha256) again writes nothing and says where it is;
a different content with the same validity start gets its own entry, and the
later publication wins the selection. The index is rewritten to a temporary
file and renamed under an exclusive lock on ``STORE/.lock``, so concurrent
publications append one after the other and a crash leaves the old index.
"""

from __future__ import annotations

import csv
import fcntl
import os
import re
import shutil
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

from pipeline.io.artefact import sha256_file
from pipeline.bundle.calibration import read_bundle
from pipeline.io.dataset import open_dataset
from pipeline.errors import InputError
from pipeline.io.rawio import read_tags

__all__ = ["INDEX_NAME", "INDEX_COLUMNS", "publish", "read_index", "verify_store", "select_calibration",
           "calibrations_for_frames", "lab_data_end", "parse_valid_from", "output_for", "check_entry"]

INDEX_NAME = "index.csv"
INDEX_COLUMNS = ("serial", "valid_from", "sha256", "file", "published_utc", "valid_from_source", "source")
#: characters a camera serial may hold to become a folder name of the store
SERIAL_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
TIME_FORMAT = "%Y-%m-%dT%H:%M:%S"
FILE_TIME_FORMAT = "%Y%m%dT%H%M%S"
#: hex digits of the sha256 in a store file's name (the index holds all 64)
NAME_HASH_DIGITS = 16


def parse_valid_from(text: str) -> datetime:
    """``2024-05-01`` or ``2024-05-01T08:30[:00]`` (camera clock, no zone) -> datetime.

    Parameters
    ----------
    text : str
        The validity start, ISO 8601 without a time zone (the camera clock's local time).

    Returns
    -------
    datetime.datetime
        The naive time, to the second.

    Raises
    ------
    InputError
        When the text is not a date, or carries a time zone.
    """
    try:
        stamp = datetime.fromisoformat(str(text).strip())
    except ValueError:
        raise InputError(None, f"--valid-from {text!r} is not a date (write 2024-05-01 or 2024-05-01T08:30:00)") from None
    if stamp.tzinfo is not None:
        raise InputError(None, f"--valid-from {text!r} has a time zone; write the camera clock's local time without one "
                               "(the frames' DateTimeOriginal has none)")
    return stamp.replace(microsecond=0)


def lab_data_end(dataset_root: str | Path, experiments: list[str], serial: str) -> datetime:
    """The latest DateTimeOriginal of the frames of ``experiments`` in the dataset (the calibration's data).

    Parameters
    ----------
    dataset_root : str or pathlib.Path
        The dataset the calibration was made from.
    experiments : list of str
        The experiments (stages) the bundle was made from.
    serial : str
        The bundle's camera serial, checked against the dataset's.

    Returns
    -------
    datetime.datetime
        The latest frame time, camera clock, to the second.

    Raises
    ------
    InputError
        When the dataset is of another camera, lacks an experiment, has a frame without a time or no frames.
    """
    ds = open_dataset(dataset_root, check_frames=False)
    found = str(ds.meta.get("camera", {}).get("serial", "")) if isinstance(ds.meta, dict) else ""
    if found != serial:
        raise InputError(ds.root / "dataset.yaml", f"is for camera serial '{found}', the bundle for '{serial}'; "
                                                   "give the dataset the calibration was made from")
    latest = None
    for experiment in experiments:
        if experiment not in ds.experiments():
            raise InputError(ds.root / experiment, "experiment folder is absent, but the bundle was made from it; "
                                                   "give the dataset the calibration was made from")
        for path in ds.raw_files(experiment):
            stamp = read_tags(path)["time"]
            if stamp is None:
                raise InputError(path, "has no DateTimeOriginal tag; give the validity start with --valid-from")
            latest = stamp if latest is None or stamp > latest else latest
    if latest is None:
        raise InputError(ds.root, "has no frames of the bundle's experiments; give the validity start with --valid-from")
    return latest.replace(microsecond=0)


@contextmanager
def _locked(store: Path):
    store.mkdir(parents=True, exist_ok=True)
    with open(store / ".lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def read_index(store: str | Path) -> list[dict]:
    """The store's entries in publication order; an empty list for a store not yet written.

    Parameters
    ----------
    store : str or pathlib.Path
        The store folder.

    Returns
    -------
    list of dict
        One dict per entry, keyed by ``INDEX_COLUMNS`` (all values str).

    Raises
    ------
    InputError
        When the folder holds files but no index, or the index's columns or times are malformed.
    """
    store = Path(store)
    path = store / INDEX_NAME
    if not path.exists():
        if store.exists() and any(p for p in store.iterdir() if p.name != ".lock"):
            raise InputError(path, "is missing: the folder is not a calibration store (or its index was deleted)")
        return []
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        if tuple(reader.fieldnames or ()) != INDEX_COLUMNS:
            raise InputError(path, f"is not a calibration store index (columns {reader.fieldnames}, "
                                   f"expected {', '.join(INDEX_COLUMNS)})")
        rows = list(reader)
    for line, row in enumerate(rows, start=2):
        try:
            datetime.strptime(row["valid_from"], TIME_FORMAT)
        except (TypeError, ValueError):
            raise InputError(path, f"line {line}: valid_from {row['valid_from']!r} is not {TIME_FORMAT}") from None
    return rows


def _write_index(store: Path, rows: list[dict]) -> None:
    tmp = store / f".{INDEX_NAME}.tmp"
    with open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=INDEX_COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, store / INDEX_NAME)


def _bundle_identity(bundle_path: Path) -> tuple[str, list[str]]:
    """(camera serial, stages) of a calibration bundle; refuses anything else."""
    bundle = read_bundle(bundle_path, load=False)
    try:
        serial = str(bundle.attrs.get("camera_serial", ""))
        stages = [s for s in str(bundle.attrs.get("stages", "")).split(",") if s]
    finally:
        bundle.close()
    if not serial:
        raise InputError(bundle_path, "has no camera serial (dataset.yaml camera.serial); the store files bundles per camera")
    if not SERIAL_PATTERN.match(serial):
        raise InputError(bundle_path, f"camera serial {serial!r} cannot name a store folder (letters, digits, . _ - only)")
    return serial, stages


def publish(bundle_path: str | Path, store: str | Path, *, valid_from: datetime | None = None,
            dataset: str | Path | None = None) -> tuple[dict, bool]:
    """File ``bundle_path`` into ``store``.

    Parameters
    ----------
    bundle_path : str or pathlib.Path
        The calibration bundle (NetCDF).
    store : str or pathlib.Path
        The store folder (created when absent).
    valid_from : datetime.datetime, optional
        The validity start, camera clock.
    dataset : str or pathlib.Path, optional
        The dataset the bundle was made from: without ``valid_from``, the validity start is its latest lab frame
        time (:func:`lab_data_end`). One of the two is needed.

    Returns
    -------
    entry : dict
        The bundle's index entry.
    written : bool
        False when the same content (sha256) was already published (nothing written).

    Raises
    ------
    InputError
        Without a validity start, when the store was changed by hand, the bundle changed while published, or the
        filesystem has no hard links.
    """
    bundle_path, store = Path(bundle_path), Path(store)
    serial, stages = _bundle_identity(bundle_path)
    if valid_from is not None:
        source = "given"
    elif dataset is not None:
        valid_from, source = lab_data_end(dataset, stages, serial), "latest lab frame"
    else:
        raise InputError(bundle_path, "needs a validity start: --dataset DATASET (the latest lab frame time of the "
                                      "data it was made from) or --valid-from DATE")
    digest = sha256_file(bundle_path)
    with _locked(store):
        rows = read_index(store)
        for row in rows:
            if row["sha256"] == digest:
                return row, False
        name = f"{serial}/{valid_from.strftime(FILE_TIME_FORMAT)}_{digest[:NAME_HASH_DIGITS]}.nc"
        target = store / name
        if target.exists():
            raise InputError(target, "exists but is not in the index: the store was changed by hand; "
                                     "restore its index.csv from a backup")
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.name}.tmp")
        tmp.unlink(missing_ok=True)     # left by a publication that was killed (never in the index)
        shutil.copyfile(bundle_path, tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        if sha256_file(tmp) != digest:
            tmp.unlink()
            raise InputError(bundle_path, "changed while it was being published; publish it again")
        os.chmod(tmp, 0o444)
        try:
            os.link(tmp, target)        # fails rather than replace an existing file
        except FileExistsError:
            raise InputError(target, "appeared while it was being published; publish again") from None
        except OSError as exc:
            raise InputError(store, f"cannot link files on this filesystem ({exc.strerror}); the store needs one "
                                    "with hard links (never-overwrite rename)") from None
        finally:
            tmp.unlink(missing_ok=True)
        row = {"serial": serial, "valid_from": valid_from.strftime(TIME_FORMAT), "sha256": digest, "file": name,
               "published_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
               "valid_from_source": source, "source": str(bundle_path.resolve())}
        _write_index(store, rows + [row])
    return row, True


def check_entry(store: Path, row: dict) -> Path:
    """The store file of index entry ``row``, after checking it is there and unchanged (sha256).

    Parameters
    ----------
    store : pathlib.Path
        The store folder.
    row : dict
        An index entry (:func:`read_index`): ``serial``, ``valid_from``, ``sha256``, ``file``, ``published_utc``,
        ``valid_from_source``, ``source``.

    Returns
    -------
    pathlib.Path
        The bundle file.

    Raises
    ------
    InputError
        When the file is missing or its sha256 differs from the index's.
    """
    path = store / row["file"]
    if not path.is_file():
        raise InputError(path, f"is in the store's index (published {row['published_utc']}) but missing; "
                               "restore it from a backup")
    found = sha256_file(path)
    if found != row["sha256"]:
        raise InputError(path, f"changed after it was published: sha256 {found[:16]}..., the index says "
                               f"{row['sha256'][:16]}...; the store is append-only: restore the file from a backup")
    return path


def verify_store(store: str | Path) -> list[str]:
    """Every problem of the store, one line each: a listed file missing or changed, a file not in the index.

    Parameters
    ----------
    store : str or pathlib.Path
        The store folder.

    Returns
    -------
    list of str
        The problems, one line each; empty for a sound store.
    """
    store = Path(store)
    rows = read_index(store)
    problems = []
    for row in rows:
        try:
            check_entry(store, row)
        except InputError as exc:
            problems.append(str(exc))
    listed = {row["file"] for row in rows}
    for path in sorted(store.glob("*/*.nc")):
        if path.relative_to(store).as_posix() not in listed:
            problems.append(f"{path}: is not in the store's index (added by hand?)")
    return problems


def select_calibration(store: str | Path, serial: str | None, when: datetime, frame: str | Path | None = None) -> dict:
    """The entry valid at ``when`` for camera ``serial``: the newest validity start not after it (of two
    with the same start, the later published). A frame without a serial tag takes the store's only camera.

    Parameters
    ----------
    store : str or pathlib.Path
        The store folder.
    serial : str or None
        The frame's camera serial; None when the frame has no serial tag.
    when : datetime.datetime
        The frame's time, camera clock.
    frame : str or pathlib.Path, optional
        The frame, named in the error messages.

    Returns
    -------
    dict
        The index entry (:func:`read_index`).

    Raises
    ------
    InputError
        When the store is empty, holds no calibration of the camera valid at ``when``, or several cameras for a
        frame without a serial.
    """
    store = Path(store)
    rows = read_index(store)
    if not rows:
        raise InputError(store, "holds no calibration; publish one with: python -m pipeline publish BUNDLE --store "
                                f"{store}")
    if serial is None:
        serials = sorted({row["serial"] for row in rows})
        if len(serials) != 1:
            raise InputError(frame, f"has no camera serial tag and the store holds cameras {', '.join(serials)}; "
                                    "give --calibration BUNDLE instead")
        serial = serials[0]
    mine = [(datetime.strptime(row["valid_from"], TIME_FORMAT), i, row) for i, row in enumerate(rows)
            if row["serial"] == serial]
    if not mine:
        raise InputError(frame, f"is from camera {serial}; {store} holds no calibration of it")
    valid = [entry for entry in mine if entry[0] <= when]
    if not valid:
        earliest = min(entry[0] for entry in mine)
        raise InputError(frame, f"taken {when.strftime(TIME_FORMAT)}: no calibration of camera {serial} in {store} "
                                f"is valid then (the earliest is valid from {earliest.strftime(TIME_FORMAT)})")
    return max(valid, key=lambda entry: (entry[0], entry[1]))[2]


def calibrations_for_frames(store: str | Path, raw_paths) -> list[tuple[Path, dict, list[str]]]:
    """Group frames by the calibration valid at each one's DateTimeOriginal.

    Each bundle's sha256 is checked against the index before it is used.

    Parameters
    ----------
    store : str or pathlib.Path
        The store folder.
    raw_paths : sequence of str or pathlib.Path
        The raw frames.

    Returns
    -------
    list of tuple
        ``(bundle path, index entry, frames)`` per calibration, in order of serial and validity; ``frames`` the
        raw paths (str) it covers.

    Raises
    ------
    InputError
        For a frame without a time, or no valid or an altered calibration.
    """
    store = Path(store)
    groups: dict[str, tuple[dict, list[str]]] = {}
    for raw in raw_paths:
        tags = read_tags(raw)
        if tags["time"] is None:
            raise InputError(raw, "has no DateTimeOriginal tag: the store selects the calibration by the frame's "
                                  "time; give --calibration BUNDLE instead")
        row = select_calibration(store, tags["serial"], tags["time"], raw)
        groups.setdefault(row["sha256"], (row, []))[1].append(str(raw))
    out = [(check_entry(store, row), row, frames) for row, frames in groups.values()]
    return sorted(out, key=lambda g: (g[1]["serial"], g[1]["valid_from"]))


def output_for(out: str | Path, row: dict, n_calibrations: int) -> Path:
    """``apply``'s output for the frames of one calibration.

    Parameters
    ----------
    out : str or pathlib.Path
        The output path given to ``apply``.
    row : dict
        An index entry (:func:`read_index`): ``serial``, ``valid_from``, ``sha256``, ``file``, ``published_utc``,
        ``valid_from_source``, ``source``.
    n_calibrations : int
        The number of calibrations the frames need.

    Returns
    -------
    pathlib.Path
        OUT itself when one calibration covers all frames, else OUT's name with the camera serial and the
        validity start (``sky_SIM-0001_20210318T160000.nc``).
    """
    out = Path(out)
    if n_calibrations == 1:
        return out
    start = datetime.strptime(row["valid_from"], TIME_FORMAT).strftime(FILE_TIME_FORMAT)
    return out.with_name(f"{out.stem}_{row['serial']}_{start}{out.suffix}")

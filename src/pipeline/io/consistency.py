"""Consistency of a dataset's parts with each other: frames, dataset.yaml and sidecars, before any stage.

Each file may be fine on its own and the dataset still wrong: one linearity frame
from another camera body, one frame whose CFAPattern says BGGR among RGGB ones,
a 12-bit frame among 14-bit ones, two lens regions that share pixels, a site
whose longitude has the wrong sign (the sun far below the horizon for daylight
sky frames), reference radiometer columns that are not the channels site.yaml
lists.  :func:`check_consistency` compares the tags ``pipeline.io.validation``
has already read (no file is decoded or read again) with each other and with
dataset.yaml, the lens regions with each other, and the field sidecars with
each other and with the frames' time stamps.

It returns (problems, warnings), both :class:`pipeline.errors.Problem`
records naming the file: a problem stops ``validate`` and the workflow before
any stage; a warning is a suspicion (a time stamp in the future, out of order
or far from its experiment's other frames, the sun below the horizon) that
names what it saw and lets the run go on.  The thresholds are module
constants because ``validate`` runs without a config.
"""

from __future__ import annotations

import csv
import math
import re
from bisect import bisect_right
from collections import Counter
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

from pipeline.io.dataset import read_site
from pipeline.errors import InputError, Problem

__all__ = ["FrameTags", "check_consistency", "lens_overlap_problems", "BLACK_LEVEL_TOLERANCE_FRACTION",
           "MAX_CLOCK_AHEAD_OF_UTC_H", "FRAME_TIME_GAP_MAX_DAYS", "SUN_MIN_ELEVATION_DEG"]

#: a frame's BlackLevel may differ from the median of the dataset's frames by this fraction of the white level:
#: a converter that measures each frame's black level in its masked pixels moves it by a few DN (the Canon 550D
#: file of the real-data folder reads about 2050 DN there against a tag of 2056, 0.04 % of its 15000 DN range);
#: another bit depth, camera mode or camera moves it by a large part of the range
BLACK_LEVEL_TOLERANCE_FRACTION = 0.01
#: the farthest a camera clock set to local time can run ahead of UTC (hours): the easternmost time zone is
#: UTC+14 (Kiribati's Line Islands), so a DateTimeOriginal later than now plus this is in the future anywhere
MAX_CLOCK_AHEAD_OF_UTC_H = 14.0
#: frames of one experiment separated from its largest group of frames by a gap longer than this (days) are
#: "far from the experiment's others": a lab session lasts hours to days and a field campaign weeks with short
#: breaks, while a reset camera clock (2000-01-01) or a frame from another campaign is months or years away
FRAME_TIME_GAP_MAX_DAYS = 30.0
#: the field experiment's frames are daylight sky frames: the sun's apparent elevation (deg, refraction
#: included) at their UTC times must be above the horizon; below it the site's position or clock offset is wrong
SUN_MIN_ELEVATION_DEG = 0.0
#: field frames of this kind look at the sky (dark frames are taken with the lens capped, at any hour)
_SKY_KIND = "signal"
_CHANNEL_COLUMN = re.compile(r"L_(\d+(?:\.\d+)?)")


@dataclass(frozen=True)
class FrameTags:
    """One frame frames.csv lists and its tags as ``pipeline.io.rawio.read_tags`` gives them."""

    experiment: str
    file: str            # the path frames.csv gives, relative to the experiment folder
    line: int            # its line in frames.csv
    kind: str
    path: Path
    tags: dict

    def where(self) -> str:
        """Where the frame is listed, for a message.

        Returns
        -------
        str
            E.g. ``"dark/frames.csv line 3"``.
        """
        return f"{self.experiment}/frames.csv line {self.line}"


def check_consistency(root: Path, meta, lenses, frames: list[FrameTags], experiments,
                      now_utc: datetime | None = None, sidecars: dict | None = None,
                      field_settings: dict | None = None) -> tuple[list[Problem], list[Problem]]:
    """(problems, warnings) of the frames' tags against each other and dataset.yaml, the lens regions
    against each other, and the field sidecars against each other and the frames' times.

    Parameters
    ----------
    root : pathlib.Path
        The dataset's folder.
    meta : dict or None
        dataset.yaml as parsed; ``None`` when unreadable.
    lenses : dict or None
        The lens regions of dataset.yaml, lens -> ``((row0, row1), (col0, col1))`` in mosaic pixels; ``None``
        when unusable.
    frames : list[FrameTags]
        Every frame the frames.csv files list, with its tags.
    experiments : collection of str
        The experiments present (the field checks run when ``"field"`` is among them).
    now_utc : datetime.datetime or None, optional
        Naive UTC time when "the future" starts; default the clock.
    sidecars : dict or None, optional
        What ``pipeline.io.dataset.check_sidecars`` read (path relative to the dataset -> value), of which the
        reference radiometer's times are compared with the field frames' (not read again here); ``None``
        (default): the reference radiometer's header is read for its channel check only.
    field_settings : dict or None, optional
        The run's ``field`` config section, whose match-up window and clock-offset search the time check uses;
        default the schema's.

    Returns
    -------
    problems : list[pipeline.errors.Problem]
        What stops the run, such as another camera, CFA pattern or black/white level than the others, overlapping lens
        regions, unusable reference radiometer channels or times.
    warnings : list[pipeline.errors.Problem]
        What is suspect but does not stop it, such as time stamps in the future, far from the experiment's others or out
        of order, field frames with the sun below the horizon, reference times that suggest a clock offset.
    """
    root = Path(root)
    problems: list[Problem] = []
    warnings: list[Problem] = []
    if lenses:
        problems += lens_overlap_problems(root / "dataset.yaml", lenses)
    camera = meta.get("camera") if isinstance(meta, dict) else None
    problems += _camera_problems(root, camera if isinstance(camera, dict) else {}, frames)
    problems += _cfa_problems(frames)
    problems += _level_problems(frames)
    timed = _time_warnings(frames, now_utc if now_utc is not None else datetime.now(timezone.utc).replace(tzinfo=None))
    warnings += timed
    # a frame whose time stamp is already suspect (in the future, far from the others) is named once, for that
    suspect = {w.path for w in timed if "is out of order" not in w.message}
    if "field" in experiments:
        reference = (sidecars or {}).get("field/reference_radiometer.csv")
        if sidecars is None:
            problems += _channel_problems(root / "field", _reference_header(root / "field" / "reference_radiometer.csv"))
        elif reference is not None:         # a file with problems of its own (a regional CSV) has them named
            problems += _channel_problems(root / "field", [str(c) for c in reference.columns])
        field_frames = [f for f in frames if f.experiment == "field"]
        warnings += _sun_warnings(root / "field", field_frames)
        if reference is not None:
            found, suspected = _reference_time_checks(root / "field", [f for f in field_frames if f.path not in suspect],
                                                      reference, field_settings)
            problems += found
            warnings += suspected
    warnings += _row_order_warnings(frames)
    return problems, warnings


# ---------------------------------------------------------------------------
# lens regions


def lens_overlap_problems(yaml_path: Path, lenses: dict) -> list[Problem]:
    """One problem per pair of lens regions that share pixels (each pixel belongs to one lens).

    Parameters
    ----------
    yaml_path : pathlib.Path
        The dataset.yaml the regions come from, named in each problem.
    lenses : dict
        Lens -> ``((row0, row1), (col0, col1))``, its half-open row and column spans in mosaic pixels.

    Returns
    -------
    list[pipeline.errors.Problem]
        One per overlapping pair, naming both regions and the shared rows and columns; empty when none overlap.
    """
    out = []
    names = list(lenses)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            (ar, ac), (br, bc) = lenses[a], lenses[b]
            rows = (max(ar[0], br[0]), min(ar[1], br[1]))
            cols = (max(ac[0], bc[0]), min(ac[1], bc[1]))
            if rows[0] < rows[1] and cols[0] < cols[1]:
                out.append(Problem(yaml_path, message=(
                    f"lenses.{a} (rows [{ar[0]}, {ar[1]}), cols [{ac[0]}, {ac[1]})) and lenses.{b} (rows "
                    f"[{br[0]}, {br[1]}), cols [{bc[0]}, {bc[1]})) overlap in rows [{rows[0]}, {rows[1]}), cols "
                    f"[{cols[0]}, {cols[1]})"),
                    fix="give each lens its own pixels: a region holds one lens's image "
                        "(python -m pipeline init-dataset proposes regions)"))
    return out


# ---------------------------------------------------------------------------
# tags against each other and dataset.yaml


def _norm(text) -> str:
    return " ".join(str(text).split()).casefold()


def _model_key(model, make) -> str:
    """The model without a leading make: Canon writes Model 'Canon EOS 550D' with Make 'Canon'."""
    model, make = _norm(model), _norm(make) if make else ""
    if make and model.startswith(make + " "):
        model = model[len(make) + 1:]
    return model


def _majority(values: list) -> tuple[object, int]:
    """The most common value and how many have it (the first seen among equals)."""
    value, count = Counter(values).most_common(1)[0]
    return value, count


def _camera_problems(root: Path, camera: dict, frames: list[FrameTags]) -> list[Problem]:
    """Make, Model and CameraSerialNumber of every frame against dataset.yaml's camera (or, for a serial
    dataset.yaml does not give, against the other frames)."""
    yaml_path = root / "dataset.yaml"
    make_yaml = camera.get("make") if isinstance(camera.get("make"), str) else None
    out: list[Problem] = []
    for key, tag_name in (("make", "Make"), ("model", "Model"), ("serial", "CameraSerialNumber")):
        seen = [f for f in frames if f.tags.get(key)]
        if not seen:
            continue
        if key == "model":
            keys = [_model_key(f.tags[key], f.tags.get("make") or make_yaml) for f in seen]
        else:
            keys = [_norm(f.tags[key]) for f in seen]
        given = camera.get(key)
        if isinstance(given, (str, int)) and not isinstance(given, bool) and str(given).strip():
            want = _model_key(given, make_yaml) if key == "model" else _norm(given)
            bad = [(f, k) for f, k in zip(seen, keys) if k != want]
            if not bad:
                continue
            if len(bad) == len(seen) and len({k for _, k in bad}) == 1:
                out.append(Problem(yaml_path, message=(
                    f"camera.{key} is {str(given)!r} but every frame's {tag_name} tag says "
                    f"{seen[0].tags[key]!r}"),
                    fix=f"write camera.{key} as the raw files' {tag_name} tag says"))
                continue
            for f, _ in bad:
                out.append(Problem(f.path, message=(
                    f"{tag_name} tag says {f.tags[key]!r} but dataset.yaml's camera.{key} is {str(given)!r} "
                    f"({f.where()}): a frame of another camera"),
                    fix=f"take the frame again with the camera dataset.yaml names, or delete its row from "
                        f"{f.experiment}/frames.csv (a camera's calibration is its own)"))
        else:
            common, count = _majority(keys)
            for f, k in zip(seen, keys):
                if k != common:
                    shown = next(g.tags[key] for g, kk in zip(seen, keys) if kk == common)
                    out.append(Problem(f.path, message=(
                        f"{tag_name} tag says {f.tags[key]!r} but {count} of {len(seen)} frames say {shown!r} "
                        f"({f.where()}): a frame of another camera"),
                        fix=f"take the frame again with the dataset's camera, or delete its row from "
                            f"{f.experiment}/frames.csv; write camera.{key} in dataset.yaml"))
    return out


def _cfa_problems(frames: list[FrameTags]) -> list[Problem]:
    """Every frame's CFAPattern is the dataset's: it says which pixel is red, green or blue."""
    seen = [f for f in frames if f.tags.get("cfa_pattern")]
    if not seen:
        return []
    common, count = _majority([f.tags["cfa_pattern"] for f in seen])
    return [Problem(f.path, message=(f"CFAPattern tag says {f.tags['cfa_pattern']} but {count} of {len(seen)} "
                                     f"frames say {common} ({f.where()})"),
                    fix="keep one camera and one raw mode per dataset: the pattern decides which pixels are red, "
                        "green and blue (a frame cropped or converted by other software shifts it); take the "
                        "frame again or delete its row")
            for f in seen if f.tags["cfa_pattern"] != common]


def _bits(white_dn: float) -> int:
    """The bit depth a white level stands for (4095 -> 12, 16383 -> 14)."""
    return int(white_dn).bit_length()


def _level_problems(frames: list[FrameTags]) -> list[Problem]:
    """WhiteLevel (bit depth) and BlackLevel of every frame against the dataset's other frames."""
    out: list[Problem] = []
    whites = [f for f in frames if f.tags.get("white_level")]
    white = None
    if whites:
        white, count = _majority([f.tags["white_level"] for f in whites])
        for f in whites:
            value = f.tags["white_level"]
            if value != white:
                out.append(Problem(f.path, message=(
                    f"WhiteLevel tag is {value:g} DN ({_bits(value)} bits) but {count} of {len(whites)} frames say "
                    f"{white:g} DN ({_bits(white)} bits) ({f.where()})"),
                    fix="keep one camera mode (one bit depth) per dataset: the saturation level and the "
                        "linear range differ; take the frame again or delete its row"))
    blacks = [f for f in frames if f.tags.get("black_level") is not None]
    if blacks and white:
        ordered = sorted(f.tags["black_level"] for f in blacks)
        median = ordered[len(ordered) // 2]
        tolerance = BLACK_LEVEL_TOLERANCE_FRACTION * white
        for f in blacks:
            value = f.tags["black_level"]
            if abs(value - median) > tolerance:
                out.append(Problem(f.path, message=(
                    f"BlackLevel tag is {value:g} DN but the frames' median is {median:g} DN (more than "
                    f"{BLACK_LEVEL_TOLERANCE_FRACTION:.0%} of the {white:g} DN white level apart; {f.where()})"),
                    fix="keep one camera and one raw mode per dataset (the black level is subtracted from "
                        "every pixel); take the frame again or delete its row"))
    return out


# ---------------------------------------------------------------------------
# time stamps (warnings)


def _natural_key(text: str) -> list:
    """IMG_9.dng before IMG_10.dng: the numbers in a name compared as numbers."""
    return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", text) if part]


def _ordered_subset(times: list[datetime]) -> set[int]:
    """Indices of a longest non-decreasing subsequence of ``times`` (the frames in order)."""
    tails: list[datetime] = []      # smallest last time of an ordered run of each length
    tail_index: list[int] = []
    previous = [-1] * len(times)
    for i, t in enumerate(times):
        k = bisect_right(tails, t)
        if k == len(tails):
            tails.append(t)
            tail_index.append(i)
        else:
            tails[k], tail_index[k] = t, i
        previous[i] = tail_index[k - 1] if k else -1
    kept, i = set(), tail_index[-1] if tail_index else -1
    while i >= 0:
        kept.add(i)
        i = previous[i]
    return kept


def _largest_group(times: list[datetime]) -> set[int]:
    """Indices of the largest group of times with no gap longer than FRAME_TIME_GAP_MAX_DAYS inside."""
    order = sorted(range(len(times)), key=lambda i: times[i])
    gap = timedelta(days=FRAME_TIME_GAP_MAX_DAYS)
    groups: list[list[int]] = [[order[0]]]
    for a, b in zip(order, order[1:]):
        if times[b] - times[a] > gap:
            groups.append([])
        groups[-1].append(b)
    return set(max(groups, key=len))


def _time_warnings(frames: list[FrameTags], now_utc: datetime) -> list[Problem]:
    """Per frame at most one: a time stamp in the future, far from its experiment's others, or out of
    order against the file names (the camera's counter)."""
    out: list[Problem] = []
    latest = now_utc + timedelta(hours=MAX_CLOCK_AHEAD_OF_UTC_H)
    clock_fix = ("set the camera's clock; if the frame belongs to another session, delete its row "
                 "(the field stage matches frames to the reference radiometer by time)")
    by_experiment: dict[str, list[FrameTags]] = {}
    for f in frames:
        if f.tags.get("time") is not None:
            by_experiment.setdefault(f.experiment, []).append(f)
    for experiment, group in by_experiment.items():
        flagged: set[int] = set()
        for i, f in enumerate(group):
            if f.tags["time"] > latest:
                flagged.add(i)
                out.append(Problem(f.path, message=(
                    f"DateTimeOriginal {f.tags['time'].isoformat()} is in the future (now is "
                    f"{now_utc.isoformat(timespec='seconds')} UTC; no clock is more than "
                    f"{MAX_CLOCK_AHEAD_OF_UTC_H:g} h ahead of UTC; {f.where()})"), fix=clock_fix))
        rest = [i for i in range(len(group)) if i not in flagged]
        if len(rest) > 1:
            times = [group[i].tags["time"] for i in rest]
            main = {rest[k] for k in _largest_group(times)}
            lo = min(group[i].tags["time"] for i in main)
            hi = max(group[i].tags["time"] for i in main)
            for i in rest:
                if i in main:
                    continue
                t = group[i].tags["time"]
                days = (lo - t if t < lo else t - hi).total_seconds() / 86400.0
                flagged.add(i)
                out.append(Problem(group[i].path, message=(
                    f"DateTimeOriginal {t.isoformat()} is {days:.0f} days from the other {len(main)} frames of "
                    f"{experiment}/ ({lo.isoformat(timespec='minutes')} to {hi.isoformat(timespec='minutes')}; "
                    f"more than {FRAME_TIME_GAP_MAX_DAYS:g} days; {group[i].where()})"), fix=clock_fix))
        rest = sorted((i for i in range(len(group)) if i not in flagged), key=lambda i: _natural_key(group[i].file))
        kept = _ordered_subset([group[i].tags["time"] for i in rest])
        for k, i in enumerate(rest):
            if k in kept:
                continue
            f = group[i]
            before = next((group[rest[j]] for j in range(k - 1, -1, -1) if j in kept), None)
            after = next((group[rest[j]] for j in range(k + 1, len(rest)) if j in kept), None)
            around = " and ".join(f"{g.file} ({g.tags['time'].isoformat()})" for g in (before, after) if g)
            out.append(Problem(f.path, message=(
                f"DateTimeOriginal {f.tags['time'].isoformat()} is out of order: the camera's file names put it "
                f"between {around} ({f.where()})"), fix=clock_fix))
    return out


# ---------------------------------------------------------------------------
# the field sidecars against each other and the frames


def _site(folder: Path) -> dict | None:
    """site.yaml when it reads without a problem (``check_sidecars`` reports the problems)."""
    try:
        return read_site(folder / "site.yaml")
    except InputError:
        return None


def _reference_header(path: Path) -> list[str] | None:
    """The first non-blank line of reference_radiometer.csv as column names (the rows are not read)."""
    try:
        with path.open(encoding="utf-8-sig", newline="") as fh:
            for record in csv.reader(fh):
                if record and any(v.strip() for v in record):
                    return [v.strip() for v in record]
    except (OSError, UnicodeDecodeError, csv.Error):
        return None
    return None


def _channel_problems(folder: Path, header: list[str] | None) -> list[Problem]:
    """The L_<nm> columns of reference_radiometer.csv (``header``, its column names) are the channels
    site.yaml's reference lists."""
    site = _site(folder)
    if not site or header is None:
        return []
    listed = site.get("reference", {}).get("channels_nm")
    if not isinstance(listed, list) or any(v is None for v in listed):
        return []
    columns = {c: float(m.group(1)) for c in header if (m := _CHANNEL_COLUMN.fullmatch(c))}
    csv_path, site_path = folder / "reference_radiometer.csv", folder / "site.yaml"
    shown = ", ".join(f"{v:g}" for v in listed)
    out = [Problem(csv_path, line=1, column=c,
                   message=f"{c} has no channel in field/site.yaml's reference.channels_nm ({shown})",
                   fix=f"add {nm:g} to reference.channels_nm if the instrument measures it, or delete the column "
                       "(a column of another instrument or a mistyped wavelength)")
           for c, nm in columns.items() if not any(math.isclose(nm, v) for v in listed)]
    out += [Problem(site_path, message=(f"reference.channels_nm lists {nm:g} nm but field/reference_radiometer.csv "
                                        f"has no L_{nm:g} column"),
                    fix="list the channels the radiometer's file holds, or add the channel's column")
            for nm in listed if not any(math.isclose(nm, v) for v in columns.values())]
    return out


def _sun_elevation_deg(times_utc: list[datetime], latitude_deg: float, longitude_deg: float) -> list[float]:
    """The sun's apparent elevation (deg) at naive UTC times, by pvlib's SPA."""
    import pandas as pd
    from pvlib.solarposition import get_solarposition

    index = pd.DatetimeIndex(times_utc).tz_localize("UTC")
    return get_solarposition(index, latitude_deg, longitude_deg)["apparent_elevation"].tolist()


def _sun_warnings(folder: Path, frames: list[FrameTags]) -> list[Problem]:
    """The sun above the horizon at the field sky frames' UTC times (camera time - site.yaml's offset)."""
    sky = [f for f in frames if f.kind == _SKY_KIND and f.tags.get("time") is not None]
    site = _site(folder)
    if not sky or not site:
        return []
    lat, lon, offset = (site.get(k) for k in ("latitude_deg", "longitude_deg", "camera_clock_utc_offset_h"))
    if lat is None or lon is None or offset is None:
        return []
    utc = [f.tags["time"] - timedelta(hours=offset) for f in sky]
    elevation = _sun_elevation_deg(utc, lat, lon)
    below = [k for k, e in enumerate(elevation) if e < SUN_MIN_ELEVATION_DEG]
    if not below:
        return []
    worst = min(below, key=lambda k: elevation[k])
    hint = ""
    for what, alt_lon, alt_offset in ((f"longitude_deg {-lon:g}", -lon, offset),
                                      (f"camera_clock_utc_offset_h {-offset:g}", lon, -offset)):
        if alt_lon == lon and alt_offset == offset:
            continue
        alt = _sun_elevation_deg([f.tags["time"] - timedelta(hours=alt_offset) for f in sky], lat, alt_lon)
        if min(alt) >= SUN_MIN_ELEVATION_DEG:
            hint = f"; with {what} it would be {min(alt):.0f} to {max(alt):.0f} deg up"
            break
    return [Problem(folder / "site.yaml", message=(
        f"the sun is below the horizon for {len(below)} of {len(sky)} field sky frames: pvlib puts it "
        f"{-elevation[worst]:.1f} deg below at {utc[worst].isoformat(timespec='seconds')} UTC ({sky[worst].file}: "
        f"DateTimeOriginal {sky[worst].tags['time'].isoformat(timespec='seconds')} less camera_clock_utc_offset_h "
        f"{offset:g} h) at latitude_deg {lat:g}, longitude_deg {lon:g}{hint}"),
        fix="check latitude_deg and longitude_deg (north and east positive, west negative) and "
            "camera_clock_utc_offset_h (camera time minus UTC, in hours)")]


def _iso(t: datetime) -> str:
    return t.isoformat(timespec="seconds")


#: time-zone offsets tried (hours, smallest change first: whole hours, then half and quarter hours, as the world's
#: zones are) when the field frames miss the reference's records, to say which camera_clock_utc_offset_h would fit
_SHIFTS_H = sorted({k / 4 for k in range(-28 * 4, 28 * 4 + 1)}, key=lambda h: (h % 1 != 0, h % 0.5 != 0, abs(h)))


def _reference_time_checks(folder: Path, frames: list[FrameTags], reference,
                           settings: dict | None = None) -> tuple[list[Problem], list[Problem]]:
    """The field sky frames' UTC times against the reference radiometer's readings: none of them within the
    reach of the stage's match-up (its window and the clock offset it searches) is a problem, since no
    match-up is possible: a time zone or daylight-saving mistake in camera_clock_utc_offset_h, the
    reference's local times written without a zone, or a file of another day; some frames without a reading
    in their window is a warning naming them (the stage counts them and leaves them out).

    The window and the search are ``field.reference_window_s`` and ``field.clock_offset_search_s`` of
    ``settings`` (the workflow's config), the schema's defaults without it (``validate`` runs without a
    config)."""
    import numpy as np
    import pandas as pd

    from pipeline.config import defaults

    sky = [f for f in frames if f.kind == _SKY_KIND and f.tags.get("time") is not None]
    site = _site(folder)
    times = pd.DatetimeIndex(reference["time"]) if "time" in reference else pd.DatetimeIndex([])
    if not sky or not site or site.get("camera_clock_utc_offset_h") is None or len(times) == 0:
        return [], []
    field = {**defaults()["field"], **(settings or {})}
    half_window_s = float(field["reference_window_s"]) / 2.0
    reach_s = half_window_s + float(field["clock_offset_search_s"])
    offset = float(site["camera_clock_utc_offset_h"])
    ref_s = np.sort((times.tz_convert("UTC").tz_localize(None) - pd.Timestamp(0)).total_seconds().to_numpy(float))
    utc = [f.tags["time"] - timedelta(hours=offset) for f in sky]
    cam_s = np.array([(t - datetime(1970, 1, 1)).total_seconds() for t in utc])

    def distance(s: np.ndarray) -> np.ndarray:
        """Seconds from each time to the nearest reading."""
        k = np.clip(np.searchsorted(ref_s, s), 1, len(ref_s) - 1) if len(ref_s) > 1 else np.zeros(len(s), int)
        return np.minimum(np.abs(ref_s[k] - s), np.abs(ref_s[np.maximum(k - 1, 0)] - s))

    far = distance(cam_s)
    first, last = (datetime(1970, 1, 1) + timedelta(seconds=float(v)) for v in (ref_s[0], ref_s[-1]))
    csv_path = folder / "reference_radiometer.csv"
    if (far > reach_s).all():
        hint = ""
        for h in _SHIFTS_H:
            if h and -14.0 <= offset - h <= 14.0 and (distance(cam_s + 3600.0 * h) <= half_window_s).all():
                hint = (f"; with camera_clock_utc_offset_h {offset - h:g} every frame would have readings "
                        f"(times {h:+g} h)")
                break
        return [Problem(csv_path, message=(
            f"its readings ({_iso(first)} to {_iso(last)} UTC) miss every field sky frame: their UTC times "
            f"(DateTimeOriginal less camera_clock_utc_offset_h {offset:g} h) are {_iso(min(utc))} to "
            f"{_iso(max(utc))}, none within {reach_s:g} s of a reading (field.reference_window_s / 2 + "
            f"field.clock_offset_search_s){hint}"),
            fix="check camera_clock_utc_offset_h in field/site.yaml (camera time minus UTC; daylight saving "
                "time?) and that the reference's times are UTC (a time without a zone is read as UTC: write "
                "2021-03-18T20:02:00Z or the zone, +hh:mm), or use the reference file of the frames' day")], []
    missed = np.flatnonzero(far > half_window_s)
    return [], [Problem(sky[k].path, message=(
        f"no reference reading within {half_window_s:g} s of its UTC time {utc[k].isoformat(sep=' ', timespec='seconds')} "
        f"(field/reference_radiometer.csv covers {_iso(first)} to {_iso(last)} UTC; {sky[k].where()}): "
        f"not a match-up"),
        fix="the field stage leaves it out; add the reference's readings of that time, or delete the row")
        for k in missed]


def _row_order_warnings(frames: list[FrameTags]) -> list[Problem]:
    """One warning per frames.csv whose rows are in neither the order the frames were taken nor the file
    names' (the camera's counter; a frame out of that order is :func:`_time_warnings`'): the stages take
    the rows' order for the order of acquisition (a drift against frame order, a frame's order within
    its setting), so the rows out of place are named."""
    out: list[Problem] = []
    by_experiment: dict[str, list[FrameTags]] = {}
    for f in frames:
        if f.tags.get("time") is not None:
            by_experiment.setdefault(f.experiment, []).append(f)
    for group in by_experiment.values():
        rows = sorted(group, key=lambda f: f.line)
        if [f.file for f in rows] == [f.file for f in sorted(rows, key=lambda f: _natural_key(f.file))]:
            continue
        kept = _ordered_subset([f.tags["time"] for f in rows])
        if len(kept) == len(rows):
            continue
        moved = [f for k, f in enumerate(rows) if k not in kept]
        shown = ", ".join(f"line {f.line} ({f.file}, {_iso(f.tags['time'])})" for f in moved[:3])
        more = f" and {len(moved) - 3} more" if len(moved) > 3 else ""
        out.append(Problem(_frames_csv(rows[0]), message=(
            f"the rows are not in the order the frames were taken: {shown}{more} sit among rows of other "
            f"times (the stages take the rows' order for the order of acquisition: a drift against frame "
            f"order, a frame's order within its setting)"),
            fix="sort the rows by DateTimeOriginal (python -m pipeline init-dataset writes them in that order)"))
    return out


def _frames_csv(frame: FrameTags) -> Path:
    """The frames.csv that lists ``frame``: its experiment folder's (``file`` is relative to it)."""
    path = frame.path
    for _ in Path(frame.file).parts:
        path = path.parent
    return path / "frames.csv"

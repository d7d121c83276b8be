"""Dark-frame stage (Larouche et al. 2024, Sections 2.8 and 3.7; Fig. 9).

Streams the dark frames once, one setting at a time (running sums for each lens
and band of the setting being read only, each finished setting reduced at once to
the statistics below, so memory does not grow with the number of settings), and
reduces them to:

* per setting (ISO, exposure time): mean level and temporal spread, the
  histogram of the frame-averaged image with its Gaussian centre and width;
* the fixed-pattern (offset) map at the shortest exposure of the lowest ISO;
* the hot-pixel mask (pixels whose dark signal is an outlier in every one of
  the longest exposures) and the read noise per ISO;
* the dark model fitted to one value per setting:
  ``level = b0 + b1 (gain - 1) [+ D gain t]`` per lens and band, with the
  effects of ``model.effects`` (``dark_current`` adds D; ``hot_pixels`` leaves
  the flagged pixels out of the means; ``bias_drift`` removes each frame's
  offset measured on its unlit pixels: the corners outside a fisheye's image
  circle, or, for a rectilinear region (lit to its edges), the sensor's
  optically black pixels when the DNG declares them, or else, since every
  pixel of a dark frame is dark, half of the region's own pixels: a fixed
  random half of each row of band pixels measures each frame's level, the
  other half is the value (:func:`dark_reference_mask`); the lit stages have no such
  reference then, and the artefact's ``bias_reference`` says "none" for them);
* the observation tables with the model's predictions and the residuals
  normalised by the expected noise, for closure and the diagnostics.
"""

from __future__ import annotations

import logging
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.io.dataset import Dataset
from pipeline.effects.catalogue import drift_sigma
from pipeline.errors import InputError
from pipeline.stats.fitting import base_design
from pipeline.stages.observations import fit_with_effects, table_to_dataset
from pipeline.io.frames import SITES_PER_BAND_PIXEL, iter_frames
from pipeline.stats.moments import RunningMoments, histogram_counts, unlit_mask
from pipeline.radiometry.exposure import gain_from_iso
from pipeline.io.rawio import read_tags

STAGE = "dark"
log = logging.getLogger("pipeline.stages.dark")


def _setting_key(raw) -> tuple[float, float]:
    return (float(raw.iso), round(float(raw.exposure_s), 9))


def bias_reference(projection: str, has_optical_black: bool) -> str:
    """What measures each lit frame's black level: the unlit corners, the optically black pixels, or nothing.

    Parameters
    ----------
    projection : str
        The lens region's projection (``"fisheye"`` or ``"rectilinear"``).
    has_optical_black : bool
        Whether the frames' DNG declares optically black pixels.

    Returns
    -------
    str
        ``"unlit corners"`` (a fisheye), ``"optically black pixels"`` or ``"none"`` (a rectilinear region).
    """
    if projection != "rectilinear":
        return "unlit corners"
    return "optically black pixels" if has_optical_black else "none"


#: what measures each dark frame's black level in a rectilinear region without optically black pixels
DARK_HALF_REFERENCE = "half the region's pixels (a fixed random half of each row of band pixels, dark frames only)"
#: seed of that half: any fixed value (the same pixels in every frame and every run)
DARK_HALF_SEED = 1288


def dark_bias_reference(projection: str, has_optical_black: bool) -> str:
    """What measures each dark frame's black level: as in the lit frames (:func:`bias_reference`), or, where
    they have nothing, half of the region itself (:func:`dark_reference_mask`).

    Parameters
    ----------
    projection : str
        The lens region's projection (``"fisheye"`` or ``"rectilinear"``).
    has_optical_black : bool
        Whether the frames' DNG declares optically black pixels.

    Returns
    -------
    str
        As :func:`bias_reference`, with :data:`DARK_HALF_REFERENCE` in place of ``"none"``.
    """
    reference = bias_reference(projection, has_optical_black)
    return DARK_HALF_REFERENCE if reference == "none" else reference


def dark_reference_mask(shape: tuple[int, int], projection: str, min_radius_fraction: float,
                        has_optical_black: bool) -> np.ndarray:
    """The band pixels that measure a dark frame's own black level, left out of the dark model's pixels.

    A fisheye's unlit corners (:func:`pipeline.stats.moments.unlit_mask`); none for a rectilinear region whose DNG
    declares optically black pixels (they are the reference); else, in each row of band pixels, a fixed random
    half of its pixels (seed ``DARK_HALF_SEED``).  In a dark frame every pixel is dark, so one half measures the
    frame's level and the other half, the value, is tested against it: a bias common to the frame moves both
    alike, and the frame-level residual is the two halves' own noise.  Each row holds both halves in equal
    numbers, so a row's offset (a readout's line noise) is common to both; the random choice inside the row
    shares no period with a readout pattern that repeats every few pixels (interference on the pixel clock,
    alternating column channels), which a regular split (a checkerboard of band pixels) would align with and
    see as a difference of the halves: the EMVA1288 reference CCD has such a pattern, repeating every 4 sites
    along the rows and down the columns, and its checkerboard halves differ by 14 to 19 times their noise
    (docs/real-sensor-emva1288.md).

    Parameters
    ----------
    shape : tuple[int, int]
        (rows, columns) of the lens's band plane, in band pixels.
    projection : str
        The lens region's projection (``"fisheye"`` or ``"rectilinear"``).
    min_radius_fraction : float
        For a fisheye, the radius beyond which a pixel counts as an unlit corner, as a fraction of the half
        diagonal (``bias.corner_min_radius_fraction``).
    has_optical_black : bool
        Whether the frames' DNG declares optically black pixels.

    Returns
    -------
    numpy.ndarray
        Boolean, ``shape``: True on the reference pixels.
    """
    if projection != "rectilinear" or has_optical_black:
        return unlit_mask(shape, projection, min_radius_fraction)
    draws = np.random.default_rng(DARK_HALF_SEED).random(shape)
    return np.argsort(draws, axis=1, kind="stable") < shape[1] // 2


def _tag_key(path) -> tuple[float, float]:
    """The (ISO, exposure) setting of one dark frame from its tags, without decoding its pixels."""
    tags = read_tags(path)
    if not tags["iso"] or not tags["exposure_s"]:
        raise InputError(path, "dark frame without ISOSpeedRatings or ExposureTime tag")
    return (float(tags["iso"]), round(float(tags["exposure_s"]), 9))


#: frames a setting needs for its temporal (read) noise, a frame-to-frame variance
MIN_FRAMES_PER_SETTING = 2


def check_frames_per_setting(counts: Counter, keys: list, paths: list) -> None:
    """Stop with one line when a setting has a single dark frame.

    The temporal noise of a setting (the read noise, and the weight of each setting in the dark model) is a
    frame-to-frame variance, which one frame cannot give.

    Parameters
    ----------
    counts : collections.Counter
        Setting (ISO, exposure time in s) -> number of dark frames.
    keys : list[tuple[float, float]]
        Each frame's setting, in frames.csv order.
    paths : list[pathlib.Path]
        Each frame's raw file, in the same order (the first frame of a single-frame setting is named).

    Raises
    ------
    pipeline.errors.InputError
        If a setting has fewer than :data:`MIN_FRAMES_PER_SETTING` frames.
    """
    single = [k for k in counts if counts[k] < MIN_FRAMES_PER_SETTING]
    if single:
        iso, t = single[0]
        raise InputError(paths[keys.index(single[0])],
                         f"is the only dark frame at ISO {iso:g}, {t:g} s ({len(single)} of {len(counts)} settings "
                         f"have one frame): the temporal (read) noise needs at least {MIN_FRAMES_PER_SETTING} "
                         "frames of each setting")


def hot_mask_settings(settings, persistence: int) -> list[tuple[float, float]]:
    """The settings the hot-pixel mask is made from: the shortest and the ``persistence`` longest exposures
    of the lowest ISO (only the shortest when that ISO has too few exposures for the mask).

    Parameters
    ----------
    settings : iterable of tuple[float, float]
        The dark frames' settings (ISO, exposure time in s).
    persistence : int
        The number of longest exposures a pixel must be an outlier in (``dark.hot_pixel_persistence``).

    Returns
    -------
    list[tuple[float, float]]
        The settings, the shortest exposure first.
    """
    iso = min(s[0] for s in settings)
    times = sorted({s[1] for s in settings if s[0] == iso})
    if len(times) < persistence + 1:
        return [(iso, times[0])]
    return [(iso, times[0])] + [(iso, t) for t in times[-persistence:]]


def summarise_setting(mean: np.ndarray, var: np.ndarray, circle: np.ndarray, hot: np.ndarray,
                      corners: np.ndarray, edges: np.ndarray) -> dict:
    """What the fit and the artefact need of one setting's mean and variance maps, for both pixel sets that
    ``analyse_dark`` may use (the whole image circle, or the circle without the hot pixels).

    Parameters
    ----------
    mean : numpy.ndarray
        The setting's frame-averaged band image, DN, shape (rows, columns).
    var : numpy.ndarray
        Each pixel's temporal variance over the setting's frames, DN^2, same shape.
    circle : numpy.ndarray
        Boolean, same shape: the pixels the dark model reads (all but the black-level reference).
    hot : numpy.ndarray
        Boolean, same shape: the hot-pixel mask.
    corners : numpy.ndarray
        Boolean, same shape: the black-level reference pixels (:func:`dark_reference_mask`).
    edges : numpy.ndarray
        The histogram's bin edges, DN (:func:`histogram_edges`).

    Returns
    -------
    dict
        ``corner_var_dn2`` (mean temporal variance of the reference pixels, DN^2; NaN without any),
        ``n_corner``, ``n_hot`` (hot pixels in the circle), ``n_pixels``, and for each of ``"circle"`` and
        ``"nonhot"`` a dict: ``hist`` (counts of the mean image per bin), ``centre_dn`` and ``width_dn`` (mean
        and standard deviation of the mean image, DN), ``var_dn2`` (mean temporal variance, DN^2), ``n_used``.
    """
    nonhot = circle & ~hot
    out = {"corner_var_dn2": float(var[corners].mean()) if corners.any() else float("nan"),
           "n_corner": int(corners.sum()),
           "n_hot": int((hot & circle).sum()), "n_pixels": int(circle.sum())}
    for name, used in (("circle", circle), ("nonhot", nonhot)):
        m = mean[used]
        out[name] = {"hist": histogram_counts(m, edges), "centre_dn": float(m.mean()),
                     "width_dn": float(m.std()), "var_dn2": float(var[used].mean()), "n_used": int(used.sum())}
    return out


class _Pending:
    """A finished setting's maps kept until the hot-pixel mask is known, in float32 deviations.

    Precision: the mean map is stored as its deviation from the setting's shift (the first
    frame's mean level), which is the fixed pattern plus dark signal, a few DN and at most the
    ADC range (4095 DN) for a hot pixel; float32 keeps 24 bits of it, an error below 1e-6 DN on
    typical pixels and 2.4e-4 DN at worst, against the frame-averaged pixel's temporal noise of
    about 1 DN / sqrt(frames) and the histogram bins of 0.5 DN. The variance map keeps 1 part in
    1.7e7 of itself. The dark results move by far less than a hundredth of their uncertainty
    (tests/radiometry/test_dark_reduction.py, tests/regression/test_regression.py).
    """

    def __init__(self, moments: RunningMoments):
        self.shift = moments.shift
        self.n = moments.n
        self.deviation = (moments.s1 / moments.n).astype(np.float32)
        self.var = moments.variance().astype(np.float32)

    def mean(self) -> np.ndarray:
        return self.deviation.astype(np.float64) + self.shift


def reduce_dark(dataset: Dataset, config: dict, progress: bool = False) -> dict:
    """Stream the dark frames one setting at a time; returns per-lens/band/setting summaries and per-frame
    statistics.

    The frames' settings are read from their tags first; the frames are then decoded grouped by
    setting (the hot-pixel mask's settings first), so that only one setting's running sums are open
    at a time and each finished setting is reduced at once to what the fit needs
    (:func:`summarise_setting`). Only the few settings the hot-pixel mask is made from are kept as
    maps until it is known, so memory does not grow with the number of settings.

    Each frame's black-level reference (``corner_dn``) is the mean of its unlit corners
    (fisheye) or of the sensor's optically black pixels (rectilinear, when the DNG
    declares them; NaN otherwise). The histograms' range (``dark.histogram_range_dn``) keeps its
    width and moves to the data when the dark level of the first setting lies outside it (another
    camera's black level, a 12-bit phone's 256 DN), the dark level at 30 % of it.

    Parameters
    ----------
    dataset : pipeline.io.dataset.Dataset
        The dataset; its ``dark`` experiment's frames are read, for every lens it holds.
    config : dict
        The run's configuration (sections ``dark`` and ``bias``).
    progress : bool, default False
        Show a progress bar.

    Returns
    -------
    dict
        ``stats`` ((lens, band, setting) -> :func:`summarise_setting` plus ``n_frames``), ``settings`` (sorted
        (ISO, exposure s) pairs), ``hot`` and ``corners`` ((lens, band) -> boolean maps), ``base`` ((lens, band)
        -> the shortest exposure's mean map), ``frames`` (one row per frame, lens and band: ``circle_mean_dn``,
        ``corner_dn`` in DN, ...), ``inputs`` (file -> sha256), ``lenses``, ``edges``, ``projections``,
        ``tag_levels`` (frame index -> BlackLevel and WhiteLevel tags, DN), ``paths``, ``bias_reference`` and
        ``dark_bias_reference`` (lens -> text).

    Raises
    ------
    pipeline.errors.InputError
        If a frame lacks its ISO or exposure tag, a setting has a single frame, or a frame's decoded setting
        differs from its tags.
    """
    cfg = config["dark"]
    frames = dataset.frames(STAGE).reset_index(drop=True)
    lenses = list(dataset.lenses)
    corner_fraction = config["bias"]["corner_min_radius_fraction"]
    projections = {lens: dataset.projection(lens) for lens in lenses}
    edges: dict = {}                               # lens -> histogram bin edges (histogram_edges)
    keys = [_tag_key(p) for p in frames["path"]]
    counts = Counter(keys)
    check_frames_per_setting(counts, keys, list(frames["path"]))
    first_seen = list(dict.fromkeys(keys))
    mask_settings = hot_mask_settings(first_seen, cfg["hot_pixel_persistence"])
    rank = {s: k for k, s in enumerate(mask_settings + [s for s in first_seen if s not in mask_settings])}
    order = sorted(range(len(frames)), key=lambda k: rank[keys[k]])    # stable: frames.csv order inside a setting

    open_moments: dict = {}                        # (lens, band) -> RunningMoments of the setting being read
    open_key = None
    pending: dict = {}                             # setting -> (lens, band) -> _Pending, until the mask is known
    stats: dict = {}                               # (lens, band, setting) -> summarise_setting(...)
    hot: dict = {}
    base: dict = {}                                # (lens, band) -> mean map of the mask's shortest exposure
    corners = {}
    circles = {}
    frame_rows = []
    tag_levels: dict[int, tuple[float, float]] = {}   # file_index -> (BlackLevel, WhiteLevel) tags
    inputs = {}
    optical_black = []
    dark_reference = {}                            # lens -> what measures each dark frame's black level

    def finish(key):
        pending[key] = {lb: _Pending(m) for lb, m in open_moments.items()}
        open_moments.clear()
        if not hot and all(s in pending for s in mask_settings):
            for lens, band in pending[mask_settings[0]]:
                means = {s: pending[s][(lens, band)].mean() for s in mask_settings}
                n_frames = {s: pending[s][(lens, band)].n for s in mask_settings}
                hot[(lens, band)] = find_hot_pixels(means, mask_settings[0][0], cfg["hot_pixel_threshold_sigma"],
                                                    cfg["hot_pixel_persistence"], n_frames,
                                                    quantisation_var_dn2(cfg["quantisation_step_dn"], band))
                base[(lens, band)] = pending[mask_settings[0]][(lens, band)]
            for lens in {lens for lens, _ in hot}:
                b = base[(lens, BANDS[0])]
                level = float(np.median(b.mean()[~corners[(lens, BANDS[0])] & ~hot[(lens, BANDS[0])]]))
                edges[lens] = histogram_edges(cfg, level)
        if hot:
            for s in list(pending):
                for (lens, band), p in pending.pop(s).items():
                    cm = corners[(lens, band)]
                    stats[(lens, band, s)] = {"n_frames": p.n, **summarise_setting(
                        p.mean(), p.var.astype(np.float64), ~cm, hot[(lens, band)], cm, edges[lens])}
                    p.var = None

    sub = frames.iloc[order]
    for i, dec in zip(order, iter_frames(dataset, STAGE, sub, lenses, progress=progress)):
        key = _setting_key(dec.raw)
        if key != keys[i]:
            raise InputError(dec.row["path"], f"setting {key} differs from the tags read before decoding {keys[i]}")
        if open_key is not None and key != open_key:
            finish(open_key)
        open_key = key
        inputs[dec.row["file"]] = dec.raw.sha256
        optical_black.append(dec.raw.optical_black_dn is not None)
        for lens, images in dec.lenses.items():
            for band in BANDS:
                img = images.bands[band]
                if (lens, band) not in corners:
                    corners[(lens, band)] = dark_reference_mask(img.shape, projections[lens], corner_fraction,
                                                                dec.raw.optical_black_dn is not None)
                    dark_reference.setdefault(lens, dark_bias_reference(projections[lens],
                                                                        dec.raw.optical_black_dn is not None))
                    circles[(lens, band)] = ~corners[(lens, band)]
                cm = corners[(lens, band)]
                open_moments.setdefault((lens, band), RunningMoments()).add(img)
                if cm.any():
                    corner_dn, n_ob = float(img[cm].mean()), 0
                elif dec.raw.optical_black_dn is not None:
                    corner_dn, n_ob = dec.raw.optical_black_dn, dec.raw.optical_black_count
                else:
                    corner_dn, n_ob = np.nan, 0
                tag_levels[i] = (float(dec.raw.black_level), float(dec.raw.white_level))
                frame_rows.append({
                    "lens": lens, "band": band, "iso": key[0], "exposure_s": key[1], "file_index": i,
                    "circle_mean_dn": float(img[circles[(lens, band)]].mean()), "corner_dn": corner_dn,
                    "n_optical_black": n_ob,
                    "temperature_c": dec.row.get("temperature_c", np.nan),
                })
    if open_key is not None:
        finish(open_key)
    # the frame table in frames.csv order, as the frames were listed
    table = pd.DataFrame(frame_rows).sort_values("file_index", kind="stable").reset_index(drop=True)
    has_ob = bool(optical_black) and all(optical_black)
    return {"stats": stats, "settings": sorted(counts), "hot": hot, "base": base, "frames": table,
            "corners": corners, "inputs": inputs, "lenses": lenses, "edges": edges, "projections": projections,
            "tag_levels": tag_levels, "paths": list(frames["path"]),
            "bias_reference": {lens: bias_reference(p, has_ob) for lens, p in projections.items()},
            "dark_bias_reference": dark_reference}


def histogram_edges(cfg: dict, level_dn: float | None = None) -> np.ndarray:
    """Bin edges of the dark histograms (``dark.histogram_range_dn``, ``dark.histogram_bin_dn``); a dark level
    ``level_dn`` outside the range moves the range, its width kept, to put the level at 30 % of it.

    Parameters
    ----------
    cfg : dict
        The ``dark`` section of the configuration.
    level_dn : float or None, optional
        The dark level, DN; ``None`` (default) keeps the configured range.

    Returns
    -------
    numpy.ndarray
        The bin edges, DN, ascending, ``dark.histogram_bin_dn`` apart.
    """
    lo, hi = (float(v) for v in cfg["histogram_range_dn"])
    if level_dn is not None and not lo <= level_dn <= hi:
        lo, hi = level_dn - 0.3 * (hi - lo), level_dn + 0.7 * (hi - lo)
    return np.arange(lo, hi + 1e-9, cfg["histogram_bin_dn"])


def quantisation_var_dn2(step_dn: float, band: str) -> float:
    """Variance of the rounding of one band pixel in one frame (DN^2).

    It is step^2 / 12 per raw site (a value rounded to a step of ``step_dn`` carries a uniform error over one
    step), over the sites a band pixel averages (two for G). E.g. 1 DN steps: 1/12 = 0.083 DN^2 for R,
    0.042 DN^2 for G.

    Parameters
    ----------
    step_dn : float
        The raw values' quantisation step, DN (``dark.quantisation_step_dn``).
    band : str
        ``"R"``, ``"G"`` or ``"B"``.

    Returns
    -------
    float
        The variance, DN^2.
    """
    return step_dn ** 2 / 12.0 / SITES_PER_BAND_PIXEL[band]


def find_hot_pixels(means: dict[tuple[float, float], np.ndarray], iso: float, threshold_sigma: float,
                    persistence: int, n_frames: dict[tuple[float, float], int] | None = None,
                    quantisation_dn2: float = 0.0) -> np.ndarray:
    """Pixels whose dark rise over the shortest exposure is an outlier in the ``persistence`` longest.

    The outlier test is robust: z = (rise - median) / sigma with sigma = 1.4826 MAD, so the
    fixed pattern and the temporal noise set the scale, not the hot pixels. The spread is
    floored at the quantisation limit: a rise is the difference of two frame averages of
    rounded values, each frame's rounding an error of variance ``quantisation_dn2`` (step^2 / 12,
    :func:`quantisation_var_dn2`), so sigma >= sqrt(quantisation_dn2 (1/n_short + 1/n_long)) with
    n the frames averaged at each setting. Without the floor, a sensor whose dark noise is below
    one step (an 8-bit camera at 0.3 DN) has most pixels at the same rounded value in every frame,
    a MAD of exactly zero, and a rise of one step over a few frames counts as many sigma.

    Parameters
    ----------
    means : dict[tuple[float, float], numpy.ndarray]
        Setting (ISO, exposure time in s) -> frame-averaged band image, DN; all of one shape.
    iso : float
        The ISO whose exposures are compared.
    threshold_sigma : float
        The robust z above which a pixel's rise is an outlier (``dark.hot_pixel_threshold_sigma``).
    persistence : int
        The number of longest exposures a pixel must be an outlier in.
    n_frames : dict[tuple[float, float], int] or None, optional
        Setting -> number of frames averaged (for the quantisation floor); ``None`` counts one per setting.
    quantisation_dn2 : float, default 0.0
        The rounding variance of one band pixel in one frame, DN^2 (:func:`quantisation_var_dn2`).

    Returns
    -------
    numpy.ndarray
        Boolean, the images' shape: True on hot pixels; all False when ``iso`` has fewer than
        ``persistence + 1`` exposure times.
    """
    times = sorted(t for (i, t) in means if i == iso)
    if len(times) < persistence + 1:
        return np.zeros_like(next(iter(means.values())), dtype=bool)
    base = means[(iso, times[0])]
    count = n_frames or {}
    hot = None
    for t in times[-persistence:]:
        rise = means[(iso, t)] - base
        med = np.median(rise)
        mad = 1.4826 * np.median(np.abs(rise - med))
        frames_inv = 1.0 / count.get((iso, times[0]), 1) + 1.0 / count.get((iso, t), 1)
        floor = np.sqrt(quantisation_dn2 * frames_inv)
        z = (rise - med) / max(mad, floor, np.finfo(float).tiny)
        flag = z > threshold_sigma
        hot = flag if hot is None else hot & flag
    return hot


def measurable_parameters(settings: list[tuple[float, float]], with_dark_current: bool) -> dict[str, bool]:
    """Which parameters of the dark model the settings (ISO, exposure) of the dark frames determine.

    ``gain`` (b1, the black level's change with ISO/100): more than one ISO. ``dark_current`` (D):
    the setting-level design [1, (g - 1), g t] (without g - 1 for one ISO) over the distinct settings
    has full column rank; one exposure time makes g t a combination of the other columns, so D is
    not measured then. A parameter the data do not determine is left out of the fit and fixed at 0,
    never solved for from a rank-deficient design.

    Parameters
    ----------
    settings : list[tuple[float, float]]
        The dark frames' settings (ISO, exposure time in s).
    with_dark_current : bool
        Whether ``dark_current`` is among the model's effects.

    Returns
    -------
    dict[str, bool]
        ``{"gain": ..., "dark_current": ...}``: True where the parameter is measured.
    """
    gain = len({iso for iso, _ in settings}) > 1
    g = gain_from_iso(np.array([iso for iso, _ in settings], float))
    t = np.array([t for _, t in settings], float)
    columns = [np.ones_like(g)] + ([g - 1.0] if gain else []) + [g * t]
    design = np.column_stack(columns)
    dark_current = with_dark_current and int(np.linalg.matrix_rank(design)) == design.shape[1]
    return {"gain": gain, "dark_current": dark_current}


def mark_not_measured(ds: xr.Dataset, design: dict[str, bool], with_dark_current: bool,
                      settings: list[tuple[float, float]], persistence: int) -> None:
    """Say in the artefact which of its parameters the dark frames' design left unmeasured (fixed at 0).

    Each of ``bias_per_gain_dn``, ``dark_current_dn_per_s`` and ``hot_pixel_mask`` gets the attribute
    ``measured`` (1 or 0) and, when 0, a ``not_measured`` reason; with one ISO ``bias_dn`` is the black
    level at that ISO (its ``reference_iso`` attribute; 100 otherwise, where g - 1 = 0).

    Parameters
    ----------
    ds : xarray.Dataset
        The lens's dark artefact, modified in place.
    design : dict[str, bool]
        What :func:`measurable_parameters` found.
    with_dark_current : bool
        Whether ``dark_current`` is among the model's effects.
    settings : list[tuple[float, float]]
        The dark frames' settings (ISO, exposure time in s).
    persistence : int
        ``dark.hot_pixel_persistence``: the hot-pixel test needs ``persistence + 1`` exposure times at the lowest
        ISO.
    """
    isos = sorted({iso for iso, _ in settings})
    times = sorted({t for iso, t in settings if iso == isos[0]})
    if design["gain"]:
        ds["bias_dn"].attrs["reference_iso"] = 100.0
        ds["bias_per_gain_dn"].attrs["measured"] = 1
    else:
        ds["bias_dn"].attrs.update(long_name=f"black level at ISO {isos[0]:g}, the one ISO of the dark frames (b0)",
                                   reference_iso=float(isos[0]))
        for name in ("bias_per_gain_dn", "bias_per_gain_dn_sigma"):
            ds[name].attrs.update(measured=0, not_measured=(f"every dark frame is at ISO {isos[0]:g} (no gain sweep): "
                                                            "b1 fixed at 0; the dark model holds at that ISO only"))
        ds["bias_per_gain_dn"].attrs["long_name"] = "not measured (fixed at 0): black level change per unit of ISO/100"
    if with_dark_current and not design["dark_current"]:
        for name in ("dark_current_dn_per_s", "dark_current_dn_per_s_sigma"):
            ds[name].attrs.update(measured=0, not_measured=(
                "the dark frames' exposure times do not separate D g t from the black level (one exposure time): "
                "D fixed at 0, its dark signal in b0; the dark model holds at the dark frames' exposure only"))
        ds["dark_current_dn_per_s"].attrs["long_name"] = "not measured (fixed at 0): dark current at ISO 100 (D)"
    elif with_dark_current:
        ds["dark_current_dn_per_s"].attrs["measured"] = 1
    else:
        ds["dark_current_dn_per_s"].attrs.update(measured=0, not_measured="dark_current is not in model.effects")
    if len(times) < persistence + 1:
        ds["hot_pixel_mask"].attrs.update(measured=0, not_measured=(
            f"the hot-pixel test needs {persistence + 1} exposure times at ISO {isos[0]:g} (the shortest and "
            f"dark.hot_pixel_persistence = {persistence} longest), the dark frames have {len(times)}: no pixel flagged"))
    else:
        ds["hot_pixel_mask"].attrs["measured"] = 1


def black_level_tag_note(fr: pd.DataFrame, reduced: dict, max_fraction: float) -> str:
    """The ISOs whose dark level sits far from the median BlackLevel tag of its frames.

    The dark level is measured at the ISO's shortest exposure (the image circle's mean of each frame and
    band, their median: dark current and hot pixels negligible there). The stages subtract the measured dark
    level, but the tag sets the full scale (saturation margins, the sun seen in a field frame): a tag far from
    the data is another raw mode's, or light reached the sensor.

    Parameters
    ----------
    fr : pandas.DataFrame
        The frame table of one lens (``iso``, ``exposure_s``, ``file_index``, ``circle_mean_dn`` in DN).
    reduced : dict
        What :func:`reduce_dark` returned (its ``tag_levels`` and ``paths``).
    max_fraction : float
        The largest distance allowed, as a fraction of the white level (``dark.black_level_tag_max_fraction``).

    Returns
    -------
    str
        One clause per ISO beyond it (measured level and tag, DN, and the first frame's name) and the reasons
        such a difference has; empty when none is.
    """
    levels = reduced.get("tag_levels") or {}
    paths = reduced.get("paths") or []
    found = []
    for iso, rows in fr.groupby("iso", sort=True):
        shortest = rows[rows["exposure_s"] == rows["exposure_s"].min()]
        tags = [levels[i] for i in sorted(set(shortest["file_index"].astype(int))) if i in levels]
        if not tags:
            continue
        tag = float(np.median([b for b, _ in tags]))
        white = float(np.median([w for _, w in tags]))
        measured = float(np.median(shortest["circle_mean_dn"]))
        if abs(measured - tag) > max_fraction * white:
            first = int(shortest["file_index"].min())
            name = Path(paths[first]).name if first < len(paths) else f"frame {first}"
            found.append(f"ISO {iso:g}: dark level {measured:.1f} DN at {float(shortest['exposure_s'].iloc[0]):g} s "
                         f"but the BlackLevel tag says {tag:g} DN ({name} and {len(tags) - 1} more)")
    if not found:
        return ""
    return ("; ".join(found) + f": more than dark.black_level_tag_max_fraction = {max_fraction:g} of the white level "
            "apart (a tag of another raw mode or converter, or light reaching the sensor through the cap)")


def analyse_dark(reduced: dict, config: dict, effects: list[str]) -> dict[str, xr.Dataset]:
    """Fit the dark model and build one artefact Dataset per lens.

    The settings' noise table, the frame table (values, corners and bias drift) with its fit, the setting-level
    dark model, the frames' common offsets; then per lens the artefact, its bias reference and temperature terms.

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_dark` returned.
    config : dict
        The run's configuration (sections ``dark`` and ``bias``).
    effects : list[str]
        The model's effects (``model.effects``): ``dark_current``, ``hot_pixels``, ``bias_drift``,
        ``temperature`` change the fit.

    Returns
    -------
    dict[str, xarray.Dataset]
        Lens -> its dark artefact: black level b0 and b1 (DN), dark current (DN s-1), bias drift, read and
        temporal noise (DN), histograms, fixed-pattern map and hot-pixel mask, DSNU1288, and the observation
        tables ``obs_setting`` and ``obs_frame``.
    """
    lenses = reduced["lenses"]
    use_drift = "bias_drift" in effects
    settings = reduced["settings"]
    ref_iso = sorted({s[0] for s in settings})[0]
    pixels = "nonhot" if "hot_pixels" in effects else "circle"
    st = _setting_noise_table(reduced, config, pixels)
    fr, testable, drift, pixel_sigma = _frame_table(reduced["frames"], st, "hot_pixels" in effects, use_drift)
    ffit, _ = fit_with_effects(fr, "frame", effects, STAGE)
    fr["pred_dn"] = ffit.pred
    fr["z"] = ffit.z
    st, fit, design, params, dark_rate, temperature = _fit_dark_model(st, fr, pixel_sigma, drift, settings, effects)
    offset_var = _common_offset_variance(fr) if use_drift and testable else {}
    out = {lens: _lens_dataset(lens, st, fr, reduced, pixels, offset_var, params, dark_rate, drift, fit, ffit,
                               config, settings, ref_iso)
           for lens in lenses}
    for ds in out.values():
        mark_not_measured(ds, design, "dark_current" in effects, settings, config["dark"]["hot_pixel_persistence"])
    for lens, ds in out.items():
        _describe_black_level_reference(ds, lens, fr, reduced, config, testable, settings, ref_iso)
    if temperature is not None:
        for ds in out.values():
            _add_temperature_model(ds, temperature)
    return out


def _setting_noise_table(reduced: dict, config: dict, pixels: str) -> pd.DataFrame:
    """One row per lens, band and setting: the temporal variance of a pixel (``pixels``: "circle" or "nonhot")
    and of the black-level reference, floored at the quantisation step's, the counts and the hot pixels' excess."""
    stats = reduced["stats"]
    setting_rows = []
    for lens in reduced["lenses"]:
        for band in BANDS:
            for s in reduced["settings"]:
                d = stats[(lens, band, s)]
                # the reference's own noise: the corners' temporal variance, or (optically black
                # pixels, all CFA sites, read noise only) that of one raw pixel of the band
                corner_var = (d["corner_var_dn2"] if d["n_corner"] > 0
                              else d[pixels]["var_dn2"] * SITES_PER_BAND_PIXEL[band])
                # a frame's pixel cannot be known better than its rounding: the temporal variance of
                # rounded values below one step (an 8-bit sensor's 0.3 DN) is floored at step^2 / 12
                floor = quantisation_var_dn2(config["dark"]["quantisation_step_dn"], band)
                setting_rows.append({
                    "lens": lens, "band": band, "iso": s[0], "exposure_s": s[1],
                    "n_frames": d["n_frames"],
                    "pixel_var_dn2": max(d[pixels]["var_dn2"], floor),
                    "corner_var_dn2": max(corner_var, floor if d["n_corner"] > 0
                                          else floor * SITES_PER_BAND_PIXEL[band]),
                    "n_used": d[pixels]["n_used"], "n_corner": d["n_corner"],
                    "hot_excess_dn": d["circle"]["centre_dn"] - d["nonhot"]["centre_dn"],
                    "n_hot": d["n_hot"], "n_pixels": d["n_pixels"],
                })
    st = pd.DataFrame(setting_rows)
    st["gain"] = gain_from_iso(st["iso"])
    st["group"] = st["lens"] + "/" + st["band"]
    st["setting"] = st.groupby(["iso", "exposure_s"], sort=True).ngroup()
    return st


def _frame_table(frames: pd.DataFrame, st: pd.DataFrame, use_hot: bool, use_drift: bool):
    """The frame table: each frame's value (less the hot pixels' excess with hot_pixels, less its corners'
    deviation with bias_drift), its noise and the columns of the frame-level model.

    Returns (frame table, whether the bias drift is testable (every frame has a black-level reference), the
    drift's sigma terms of :func:`drift_sigma` (zeros without bias_drift in the model, NaN when not testable),
    the frames' pixel noise alone).
    """
    fr = frames.merge(st[["lens", "band", "iso", "exposure_s", "setting", "hot_excess_dn", "pixel_var_dn2",
                          "corner_var_dn2", "n_used", "n_corner"]], on=["lens", "band", "iso", "exposure_s"])
    fr["value_dn"] = fr["circle_mean_dn"] - (fr["hot_excess_dn"] if use_hot else 0.0)
    # optically black pixels (rectilinear regions) stand in for the corners
    fr["n_corner"] = np.where(fr["n_corner"] > 0, fr["n_corner"], fr.pop("n_optical_black"))
    testable = bool(fr["corner_dn"].notna().all())
    drift = (0.0, 0.0, 0.0)
    if testable:
        fr["corner_dev_dn"] = fr["corner_dn"] - fr.groupby(["lens", "band", "setting"])["corner_dn"].transform("mean")
        fr["sigma_corner_dn"] = np.sqrt(fr["corner_var_dn2"] / fr["n_corner"])
    else:
        # nothing measures a frame's own black level: the drift can be neither removed nor
        # tested (the candidate effect has no covariate), and the artefact says so
        fr = fr.drop(columns=["corner_dn"])
        drift = (np.nan, np.nan, np.nan)
    if use_drift and testable:
        fr["value_dn"] -= fr["corner_dev_dn"]
        drift = drift_sigma(fr)
    # A frame's value scatters by the temporal noise of its pixels; the drift that the
    # model removed (or that is left in, without the effect) is not part of this noise.
    fr["sigma_dn"] = np.sqrt(np.maximum(fr["pixel_var_dn2"] - np.nan_to_num(drift[0]) ** 2, 1e-12) / fr["n_used"])
    pixel_sigma = fr["sigma_dn"].copy()
    if use_drift and testable:
        # the corner correction adds the corners' own noise to each frame (not to a setting's mean: the
        # corners' deviations from their setting mean sum to zero over its frames)
        fr["sigma_dn"] = np.hypot(fr["sigma_dn"], fr["sigma_corner_dn"])
    fr["group"] = fr["lens"] + "/" + fr["band"] + "/" + fr["setting"].astype(str)
    fr["frame"] = fr.groupby(["lens", "band", "setting"]).cumcount()
    fr["x_level"] = 1.0
    if fr["temperature_c"].notna().all():
        fr["temperature_ref_c"] = float(fr["temperature_c"].mean())
    return fr, testable, drift, pixel_sigma


def _fit_dark_model(st: pd.DataFrame, fr: pd.DataFrame, pixel_sigma, drift, settings, effects: list[str]):
    """The setting-level dark model: the frames averaged per setting and fitted with the measurable effects.

    Returns (setting table with ``pred_dn`` and ``z``, the fit, the measurable parameters of
    :func:`measurable_parameters`, {parameter: (value, sigma)} (b1 fixed at 0 with one ISO), the dark current's
    (rate, sigma) in DN/s, the temperature terms (coef, sigma, reference_c) or None).
    """
    agg = fr.assign(pixel_sigma_dn=pixel_sigma).groupby(["lens", "band", "setting"]).agg(
        value_dn=("value_dn", "mean"), frame_sigma=("pixel_sigma_dn", "mean"),
        temperature_c=("temperature_c", "mean")).reset_index()
    st = st.merge(agg, on=["lens", "band", "setting"])
    st["sigma_dn"] = np.sqrt(st["frame_sigma"] ** 2 / st["n_frames"] + np.nan_to_num(drift[0]) ** 2 / st["n_frames"])
    design = measurable_parameters(settings, "dark_current" in effects)
    st["x_b0"] = 1.0
    if design["gain"]:
        st["x_b1"] = st["gain"] - 1.0
    if "temperature_ref_c" in fr:
        st["temperature_ref_c"] = fr["temperature_ref_c"].iloc[0]
    setting_effects = [e for e in effects if e != "dark_current" or design["dark_current"]]
    fit, effect_params = fit_with_effects(st, "setting", setting_effects, STAGE)
    st["pred_dn"] = fit.pred
    st["z"] = fit.z
    names = base_design(st)[1]
    params = {name: (fit.coef[k], np.sqrt(fit.cov[k, k])) for k, name in enumerate(names)}
    if not design["gain"]:
        # b1 is fixed at 0: b0 is the black level at the one ISO of the dark frames
        params.update({f"{g}:b1": (0.0, 0.0) for g in st["group"].unique()})
    dark_rate = tuple(float(v[0]) for v in effect_params.get("dark_current", ((0.0,), (0.0,))))
    temperature = effect_params.get("temperature")
    if temperature is not None:
        temperature = {"coef": temperature[0], "sigma": temperature[1],
                       "reference_c": float(st["temperature_ref_c"].iloc[0])}
    return st, fit, design, params, dark_rate, temperature


def _common_offset_variance(fr: pd.DataFrame) -> dict:
    """Per (lens, band) and setting the variance of the frames' common black-level offsets (bias_drift).

    Each setting's frames share their black-level offsets, whose sample variance every pixel's temporal
    variance holds; the unlit pixels measure it (less their own noise): the read noise of a pixel is what is
    left. Returns {(lens, band): {(iso, exposure_s): variance in DN^2, at least 0}}.
    """
    offset_var: dict = {}
    per = fr.groupby(["lens", "band", "iso", "exposure_s"])
    offsets = (per["corner_dev_dn"].apply(lambda d: float(np.sum(np.square(d))) / max(len(d) - 1, 1))
               - per["sigma_corner_dn"].apply(lambda v: float(np.mean(np.square(v)))))
    for (lens, band, iso, t), v in offsets.items():
        offset_var.setdefault((lens, band), {})[(float(iso), float(t))] = max(float(v), 0.0)
    return offset_var


def _describe_black_level_reference(ds: xr.Dataset, lens: str, fr: pd.DataFrame, reduced: dict, config: dict,
                                    testable: bool, settings, ref_iso: float) -> None:
    """The lens artefact's black-level reference: the BlackLevel tag check, the projection, the reference of
    the lit and the dark frames, whether bias_drift is testable and, with optically black pixels, their offset
    from the region's dark level (``optical_black_offset_dn``)."""
    note = black_level_tag_note(fr[fr["lens"] == lens], reduced, config["dark"]["black_level_tag_max_fraction"])
    if note:
        log.warning("dark %s: %s", lens, note)
        ds.attrs["black_level_tag_note"] = note
    reference = reduced.get("bias_reference", {}).get(lens, "unlit corners")
    ds.attrs["projection"] = reduced.get("projections", {}).get(lens, "fisheye")
    ds.attrs["bias_reference"] = reference
    ds.attrs["dark_bias_reference"] = reduced.get("dark_bias_reference", {}).get(lens, reference)
    ds.attrs["bias_drift_testable"] = int(testable)
    if not testable:
        ds.attrs["bias_drift_note"] = ("bias_drift not testable: a rectilinear region has no unlit corners and "
                                       "the DNG declares no optically black pixels (ActiveArea/MaskedAreas)")
    elif reference == "none":
        ds.attrs["bias_drift_note"] = (
            f"bias_drift measured in the dark frames on {DARK_HALF_REFERENCE}; the lit frames have no unlit "
            "corners and no optically black pixels (ActiveArea/MaskedAreas): their drift cannot be removed")
    if reference == "optically black pixels":
        # the black-level reference of the later stages: optically black mean less the
        # region's dark level, at the shortest exposure of the lowest ISO (no dark current)
        shortest = min(t for (i, t) in settings if i == ref_iso)
        sel = fr[(fr["lens"] == lens) & (fr["iso"] == ref_iso) & (fr["exposure_s"] == shortest)]
        offset = sel.groupby("band").apply(lambda g: float((g["corner_dn"] - g["circle_mean_dn"]).mean()),
                                           include_groups=False)
        ds["optical_black_offset_dn"] = ("band", offset.reindex(list(BANDS)).to_numpy(float),
                                         {"long_name": "mean of the optically black pixels less the region's "
                                                       "dark level (shortest exposure, lowest ISO)", "units": "DN"})


def _add_temperature_model(ds: xr.Dataset, temperature: dict) -> None:
    """The dark model's temperature terms (black level and dark current per degree C, reference temperature)."""
    ds["temperature_bias_dn_per_c"] = ((), temperature["coef"][0],
                                       {"long_name": "black-level change per degree C", "units": "DN degree_C-1"})
    ds["temperature_bias_dn_per_c_sigma"] = ((), temperature["sigma"][0], {"units": "DN degree_C-1"})
    ds["temperature_dark_dn_per_s_per_c"] = ((), temperature["coef"][1],
                                             {"long_name": "dark-current change per degree C (ISO 100)",
                                              "units": "DN s-1 degree_C-1"})
    ds["temperature_dark_dn_per_s_per_c_sigma"] = ((), temperature["sigma"][1], {"units": "DN s-1 degree_C-1"})
    ds["temperature_reference_c"] = ((), temperature["reference_c"],
                                     {"long_name": "reference temperature of the dark model", "units": "degree_C"})


def _lens_dataset(lens, st, fr, reduced, pixels, offset_var, params, dark_rate, drift, fit, ffit, config,
                  settings, ref_iso) -> xr.Dataset:
    edges = reduced["edges"][lens]
    st_l = st[st["lens"] == lens].reset_index(drop=True)
    fr_l = fr[fr["lens"] == lens].reset_index(drop=True)
    n_set = len(settings)
    hist = np.zeros((len(BANDS), n_set, len(edges) - 1))
    centre = np.zeros((len(BANDS), n_set))
    width = np.zeros((len(BANDS), n_set))
    temporal = np.zeros((len(BANDS), n_set))
    shape = reduced["hot"][(lens, BANDS[0])].shape
    fpn = np.zeros((len(BANDS),) + shape, dtype=np.float32)
    hot = np.zeros((len(BANDS),) + shape, dtype=np.uint8)
    fpn_corner = np.full(len(BANDS), np.nan)
    b0 = np.zeros((len(BANDS), 2))
    b1 = np.zeros((len(BANDS), 2))
    for bi, band in enumerate(BANDS):
        for si, s in enumerate(settings):
            d = reduced["stats"][(lens, band, s)][pixels]
            hist[bi, si] = d["hist"]
            centre[bi, si] = d["centre_dn"]
            width[bi, si] = d["width_dn"]
            # temporal noise of one raw pixel (the G band pixel averages two sites)
            common = offset_var.get((lens, band), {}).get((float(s[0]), float(s[1])), 0.0)
            temporal[bi, si] = np.sqrt(max(d["var_dn2"] - common, 0.0) * SITES_PER_BAND_PIXEL[band])
        hot_map = reduced["hot"][(lens, band)]
        cm = reduced["corners"][(lens, band)]
        used = ~cm & ~hot_map if pixels == "nonhot" else ~cm
        m0 = reduced["base"][(lens, band)].mean()
        fpn[bi] = (m0 - m0[used].mean()).astype(np.float32)
        if cm.any() and reduced.get("dark_bias_reference", {}).get(lens) != DARK_HALF_REFERENCE:
            # over the corner pixels the dark model predicts: without the hot ones when it fits the others
            # (radiometry.unlit_corners.corner_sites)
            corner_used = cm & ~hot_map if pixels == "nonhot" else cm
            fpn_corner[bi] = float(fpn[bi][corner_used].mean()) if corner_used.any() else float(fpn[bi][cm].mean())
        hot[bi] = hot_map.astype(np.uint8)
        b0[bi] = params[f"{lens}/{band}:b0"]
        b1[bi] = params[f"{lens}/{band}:b1"]

    iso_s = np.array([s[0] for s in settings])
    t_s = np.array([s[1] for s in settings])
    isos = sorted(set(iso_s))
    read = np.zeros((len(BANDS), len(isos)))
    for k, iso in enumerate(isos):
        shortest = min(t for (i, t) in settings if i == iso)
        read[:, k] = temporal[:, settings.index((iso, shortest))]

    ds = xr.Dataset(
        coords={
            "band": ("band", list(BANDS)),
            "setting": ("setting", np.arange(n_set)),
            "iso": ("iso", np.array(isos, float), {"long_name": "ISO speed", "units": "1"}),
            "hist_bin_centre_dn": ("hist_bin", 0.5 * (edges[1:] + edges[:-1]), {"units": "DN"}),
            "y": ("y", np.arange(shape[0])), "x": ("x", np.arange(shape[1])),
        },
        data_vars={
            "setting_iso": ("setting", iso_s, {"long_name": "ISO speed of the setting", "units": "1"}),
            "setting_exposure_s": ("setting", t_s, {"long_name": "exposure time", "units": "s"}),
            "dark_centre_dn": (("band", "setting"), centre,
                               {"long_name": "mean of the frame-averaged dark image (Gaussian centre, Fig. 9c)", "units": "DN"}),
            "dark_width_dn": (("band", "setting"), width,
                              {"long_name": "spatial spread of the frame-averaged dark image (Gaussian width, Fig. 9c)", "units": "DN"}),
            "temporal_noise_dn": (("band", "setting"), temporal,
                                  {"long_name": "temporal noise of one raw pixel (with bias_drift in the model, "
                                                "the frames' common offsets left out)", "units": "DN"}),
            "dark_histogram": (("band", "setting", "hist_bin"), hist,
                               {"long_name": "histogram of the frame-averaged dark image (Fig. 9a-b)", "units": "count"}),
            "read_noise_dn": (("band", "iso"), read,
                              {"long_name": "temporal noise of one raw pixel at the shortest exposure", "units": "DN"}),
            "bias_dn": ("band", b0[:, 0], {"long_name": "black level at ISO 100 (b0)", "units": "DN"}),
            "bias_dn_sigma": ("band", b0[:, 1], {"long_name": "standard error of b0", "units": "DN"}),
            "bias_per_gain_dn": ("band", b1[:, 0], {"long_name": "black level change per unit of ISO/100 (b1)", "units": "DN"}),
            "bias_per_gain_dn_sigma": ("band", b1[:, 1], {"long_name": "standard error of b1", "units": "DN"}),
            "dark_current_dn_per_s": ((), dark_rate[0], {"long_name": "dark current at ISO 100 (D); 0 when not in the model", "units": "DN s-1"}),
            "dark_current_dn_per_s_sigma": ((), dark_rate[1], {"long_name": "standard error of D", "units": "DN s-1"}),
            "bias_drift_dn": ((), drift[0], {"long_name": "frame-to-frame black-level spread (0 when not in the model, "
                                                          "NaN when not testable)", "units": "DN"}),
            "bias_drift_dn_low": ((), drift[1], {"long_name": "lower 95 % bound of bias_drift_dn", "units": "DN"}),
            "bias_drift_dn_high": ((), drift[2], {"long_name": "upper 95 % bound of bias_drift_dn", "units": "DN"}),
            "fpn_map_dn": (("band", "y", "x"), fpn,
                           {"long_name": "offset fixed pattern at the shortest exposure and lowest ISO, mean removed", "units": "DN"}),
            "fpn_corner_mean_dn": ("band", fpn_corner,
                                   {"long_name": "fpn_map_dn averaged over the unlit corner pixels (NaN without "
                                                 "any: a rectilinear region's dark reference is lit in lit "
                                                 "frames), which every lit stage's black-level reference needs; "
                                                 "without the hot pixels when hot_pixels_excluded is 1",
                                    "units": "DN",
                                    "corner_min_radius_fraction": float(config["bias"]["corner_min_radius_fraction"]),
                                    "hot_pixels_excluded": int(pixels == "nonhot")}),
            "hot_pixel_mask": (("band", "y", "x"), hot, {"long_name": "hot pixel (1) flagged in the longest exposures", "units": "1"}),
            "hot_pixel_count": ("band", hot.reshape(len(BANDS), -1).sum(axis=1), {"long_name": "number of hot band pixels", "units": "1"}),
            "rms_z": ((), np.sqrt((fit.chi2 + ffit.chi2) / max(fit.dof + ffit.dof, 1)),
                      {"long_name": "RMS of the noise-normalised residuals of the dark model (1 at the noise floor)", "units": "1"}),
        },
    )
    ds = ds.merge(dsnu_dataset(reduced, lens, settings))
    ds = ds.merge(table_to_dataset(st_l, "obs_setting")).merge(table_to_dataset(fr_l, "obs_frame"))
    return ds


def dsnu_dataset(reduced: dict, lens: str, settings: list) -> xr.Dataset:
    """DSNU1288 per band (EMVA1288 release 3.0) from the setting with the most frames (a dark stack).

    The dark half of :func:`pipeline.radiometry.emva1288.spatial_nonuniformity`: the spatial variance of the
    stack's frame-averaged image over every pixel of the region the dark model reads (hot pixels included, as
    the standard has it; a rectilinear region without optically black pixels: the half that is not its
    black-level reference), less the part its temporal noise leaves there (mean temporal variance over the
    frames); NaN below 2 frames or when the temporal part exceeds the spatial variance. Of a band pixel: the
    G band averages two raw sites.

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_dark` returned.
    lens : str
        The lens.
    settings : list[tuple[float, float]]
        The dark frames' settings (ISO, exposure time in s).

    Returns
    -------
    xarray.Dataset
        ``dark_spatial_var_dn2`` (DN2) and ``dsnu1288_dn`` (DN) along ``band``, with the stack's ISO, exposure
        time and frame count as attributes.
    """
    stack = max(settings, key=lambda s: reduced["stats"][(lens, BANDS[0], s)]["n_frames"])
    n = int(reduced["stats"][(lens, BANDS[0], stack)]["n_frames"])
    s2 = np.full(len(BANDS), np.nan)
    for bi, band in enumerate(BANDS):
        d = reduced["stats"][(lens, band, stack)]["circle"]
        if n >= 2 and d["n_used"] >= 2:
            s2[bi] = d["width_dn"] ** 2 * d["n_used"] / (d["n_used"] - 1) - d["var_dn2"] / n
    attrs = {"setting_iso": float(stack[0]), "setting_exposure_s": float(stack[1]), "n_frames": n}
    dsnu = np.where(s2 >= 0, np.sqrt(np.maximum(s2, 0.0)), np.nan)
    return xr.Dataset({
        "dark_spatial_var_dn2": ("band", s2, {"long_name": "spatial variance of the dark stack's frame-averaged "
                                                           "image less its temporal part (s^2_y.dark)",
                                              "units": "DN2", **attrs}),
        "dsnu1288_dn": ("band", dsnu, {"long_name": "dark signal non-uniformity DSNU1288 of a band pixel (sqrt of "
                                                     "dark_spatial_var_dn2; NaN when it is negative or fewer than 2 "
                                                     "frames)", "units": "DN", **attrs}),
    }, coords={"band": list(BANDS)})


def compute(ctx) -> xr.Dataset:
    """The dark artefact of one lens (the stage runner's contract).

    Parameters
    ----------
    ctx : pipeline.runner.workflow.StageContext
        The job: the lens's dataset, the configuration and the model's effects.

    Returns
    -------
    xarray.Dataset
        The lens's dark artefact (:func:`analyse_dark`); the frames' sha256 are recorded in ``ctx``.
    """
    reduced = reduce_dark(ctx.dataset, ctx.config, progress=ctx.progress)
    ctx.record_frames(reduced["inputs"])
    return analyse_dark(reduced, ctx.config, ctx.effects)[ctx.lens]

"""Linearity stage (Larouche et al. 2024, Sections 2.2 and 3.1; Figs. 2 and 3).

Streams the exposure-time and gain sweeps once and reduces them to:

* per-pixel Pearson r maps of single frames against exposure time and gain
  (Fig. 2), saturated samples left out;
* the mean dark-corrected DN in a small mask around the optical axis against
  exposure time and gain, with ordinary regressions and 95 % intervals
  (Fig. 3) and the nonlinearity residuals in percent;
* the saturation level, found in the data (plateau of the mean, stall or collapse of the
  variance, radiometry.saturation: full well or ADC, whichever comes first); saturated settings
  are left out of every fit and counted, and "not reached" is said when nothing saturated;
* settings whose mean leaves the sweep's rise with exposure (taken under other light), found
  before the saturation (:func:`sweep_settings`): each named in one line in the log and the
  artefact (``n_other_light_settings``) and left out of every fit; when more than
  ``linearity.non_monotonic_max_fraction`` of a sweep's settings do, the sweep has no one light
  and the stage stops with one line (a few stray series are a lab's slip and the rest of the
  sweep still measures the sensor; most of it is no sweep);
* the photon-transfer curve: temporal variance against mean signal gives the
  conversion gain (DN per electron, and electrons per DN) and the read noise
  in electrons;
* the model fitted to one value per setting: ``y = rate * gain * t`` per lens,
  band and sweep, plus the effects of ``model.effects`` (``shutter_offset``,
  ``nonlinearity``, ``iso_gain``; ``hot_pixels`` and ``bias_drift`` correct the
  data), with predictions and noise-normalised residuals.

Without a geometry artefact the mask's field angles come from the projection the
lens region declares (dataset.yaml): a fisheye's lit image circle, whose radius
stands for the nominal half field of view (equidistant projection), or a
rectilinear region's centre and nominal half diagonal field of view (r = f tan
theta); a fisheye region whose frames show no image circle stops the stage with
one line naming it. The artefact's ``projection`` and ``field_angles_from``
attributes say which was used.
"""

from __future__ import annotations

import logging
from collections import defaultdict

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.io.dataset import Dataset
from pipeline.effects import get as get_effect
from pipeline.effects.catalogue import drift_sigma
from pipeline.errors import ImpossibleResult, InputError
from pipeline.stats.fitting import base_design, ols_line, wls
from pipeline.io.frames import SITES_PER_BAND_PIXEL, iter_frames
from pipeline.geometry.image_circle import find_image_circle, outside_lit_fraction
from pipeline.stats.moments import RunningMoments, RunningPearson, radius_map
from pipeline.stages.observations import corner_table_dataset, effect_coefficients, fit_with_effects, table_to_dataset
from pipeline.radiometry import emva1288 as emva
from pipeline.radiometry.dark import dark_level_dn, temperature_shift_dn
from pipeline.radiometry.exposure import exposure_gain_s, gain_from_iso
from pipeline.radiometry.response import linear_signal
from pipeline.radiometry.saturation import (expected_between_neighbours, non_monotonic_settings, saturated_settings,
                                            signal_fraction)
from pipeline.radiometry.unlit_corners import (corner_mean_dn, corner_noise_dn, corner_pattern_dn, corner_pixels,
                                               corner_sites, frame_time_s, predicted_corner_dn)
from pipeline.stages.flatfield import flatfield

STAGE = "linearity"
log = logging.getLogger("pipeline.linearity")
#: linear-model effects this stage fits as columns (others correct the data)
COLUMN_EFFECTS = ("shutter_offset", "nonlinearity", "iso_gain")
#: what ``line_slope`` is regressed on: a number on both sweeps, so that one unit (DN) serves the two rows
SLOPE_REGRESSOR = ("the slope against the sweep's variable as a number: the exposure time in ms (sweep exposure, "
                   "so DN per ms) or the gain ISO/100 (sweep gain)")


def _no_circle(lens: str, why: str) -> InputError:
    return InputError(None, f"lens region '{lens}' is declared fisheye but its linearity frames show no image "
                            f"circle ({why}); an ordinary camera whose whole region is lit needs "
                            f"'projection: rectilinear' for lens '{lens}' in dataset.yaml")


def fisheye_circle(g_image: np.ndarray, dark_level_dn: float, config: dict, lens: str):
    """The lit image circle of a fisheye region, or one InputError naming the region when there is none.

    A region without one (lit to its corners, or dark) must not get a circle fitted to its noise:
    the pixels outside the fitted circle must be lit by less than
    ``linearity.image_circle_max_outside_fraction`` of the inside (both above the dark level),
    and the inside by more than ``linearity.signal_frame_min_snr`` times the pixel noise outside.

    Parameters
    ----------
    g_image : numpy.ndarray
        The lens's G band image of its first linearity frame, DN, shape (rows, columns) in band pixels.
    dark_level_dn : float
        The dark level of that frame's setting from the dark model, DN.
    config : dict
        The run's configuration (section ``linearity``).
    lens : str
        The lens region's name, for the message.

    Returns
    -------
    pipeline.geometry.image_circle.ImageCircle
        The circle's centre (``xc``, ``yc``) and ``radius``, in band pixels.

    Raises
    ------
    pipeline.errors.InputError
        If no circle is found, or the best one fails either test above.
    """
    try:
        circle = find_image_circle(g_image)
    except ValueError as exc:
        raise _no_circle(lens, str(exc)) from None
    limit = config[STAGE]["image_circle_max_outside_fraction"]
    lit = outside_lit_fraction(g_image, circle, dark_level_dn, min_snr=config[STAGE]["signal_frame_min_snr"])
    if not np.isfinite(lit) or lit > limit:
        what = ("no unlit pixel outside it or nothing lit inside it" if not np.isfinite(lit)
                else f"outside it the frame is lit at {lit:.2g} of the inside, more than "
                     f"linearity.image_circle_max_outside_fraction = {limit:g}")
        raise _no_circle(lens, f"the best circle, radius {circle.radius:.3g} band px, has {what}")
    return circle


def axis_masks(g_image: np.ndarray, geometry: xr.Dataset | None, config: dict, *, lens: str = "",
               projection: str = "fisheye", dark_level_dn: float = 0.0
               ) -> tuple[tuple, np.ndarray, np.ndarray, str]:
    """The averaging mask and the photon-transfer region of one lens, in band pixels.

    With the lens's geometry artefact, both are field-angle cones of the fitted
    in-air theta map (``mask_half_angle_deg``, ``ptc_half_angle_deg``). Without
    it, the field angles come from the projection the lens region declares: for
    a fisheye the lit image circle is found in the frame (:func:`fisheye_circle`)
    and the angles become radii through an equidistant projection with
    ``nominal_half_fov_deg`` at the circle's edge; for a rectilinear region the
    axis is the region's centre and the radii are f tan(theta), the focal length
    f putting ``rectilinear_nominal_half_fov_deg`` at the region's half diagonal.

    Parameters
    ----------
    g_image : numpy.ndarray
        The lens's G band image of its first linearity frame, DN, shape (rows, columns).
    geometry : xarray.Dataset or None
        The lens's geometry artefact (its in-air G ``theta_deg`` map, degree), or ``None``.
    config : dict
        The run's configuration (section ``linearity``).
    lens : str, optional
        The lens region's name, for messages.
    projection : str, default "fisheye"
        The projection the lens region declares (``"fisheye"`` or ``"rectilinear"``).
    dark_level_dn : float, default 0.0
        The frame's dark level, DN (for the fisheye's circle test).

    Returns
    -------
    geometry : tuple[float, float, float, float]
        (cx, cy, radius, mask radius) in band pixels: the centre, the circle's radius (rectilinear: the half
        diagonal) and the mask's radius (with the geometry artefact, that of a disc of the mask's area).
    mask : numpy.ndarray
        Boolean, ``g_image``'s shape: the averaging mask.
    ptc_region : numpy.ndarray
        Boolean, same shape: the photon-transfer region.
    source : str
        Where the field angles came from.

    Raises
    ------
    pipeline.errors.InputError
        If the geometry artefact's maps have another shape than the frames, or a fisheye region shows no image
        circle.
    """
    cfg = config[STAGE]
    if projection == "rectilinear":
        h, w = g_image.shape
        cx, cy, radius = (w - 1) / 2.0, (h - 1) / 2.0, float(np.hypot(w, h) / 2.0)
        focal_px = radius / np.tan(np.radians(cfg["rectilinear_nominal_half_fov_deg"]))

        def angle_radius(theta_deg):
            return focal_px * np.tan(np.radians(theta_deg))
        source = "region centre and rectilinear_nominal_half_fov_deg"
    else:
        circle = fisheye_circle(g_image, dark_level_dn, config, lens)
        cx, cy, radius = circle.xc, circle.yc, circle.radius

        def angle_radius(theta_deg):
            return radius * theta_deg / cfg["nominal_half_fov_deg"]
        source = "image circle and nominal_half_fov_deg"
    r_mask = angle_radius(cfg["mask_half_angle_deg"])
    if geometry is not None:
        theta = geometry["theta_deg"].sel(medium="air", band="G").values.astype(float)
        if theta.shape != g_image.shape:
            raise InputError(None, f"geometry artefact maps are {theta.shape} band pixels, the linearity frames "
                                   f"{g_image.shape}: the artefact belongs to another camera or lens region")
        theta = np.where(np.isfinite(theta), theta, np.inf)
        mask, ptc_region = theta <= cfg["mask_half_angle_deg"], theta <= cfg["ptc_half_angle_deg"]
        if mask.any():
            return (cx, cy, radius, float(np.sqrt(mask.sum() / np.pi))), mask, ptc_region, "geometry artefact"
    rmap = radius_map(g_image.shape, (cx, cy))
    mask = rmap <= r_mask
    ptc_region = rmap <= angle_radius(cfg["ptc_half_angle_deg"])
    return (cx, cy, radius, r_mask), mask, ptc_region, source


def reduce_linearity(dataset: Dataset, dark: dict[str, xr.Dataset], config: dict, effects: list[str],
                     progress: bool = False, geometry: dict[str, xr.Dataset] | None = None) -> dict:
    """Stream the linearity frames of every lens; one decode per frame.

    Parameters
    ----------
    dataset : pipeline.io.dataset.Dataset
        The dataset; the ``signal`` frames of its ``linearity`` experiment are read.
    dark : dict[str, xarray.Dataset]
        Lens -> its dark artefact (dark level, hot pixels, unlit-corner sites).
    config : dict
        The run's configuration (sections ``linearity`` and ``bias``).
    effects : list[str]
        The model's effects (``hot_pixels`` leaves the dark stage's hot pixels out of the masks).
    progress : bool, default False
        Show a progress bar.
    geometry : dict[str, xarray.Dataset] or None, optional
        Lens -> geometry artefact, which gives the field angles of the masks (:func:`axis_masks`).

    Returns
    -------
    dict
        ``moments`` ((lens, band, sweep, setting) -> running moments of the photon-transfer region's pixels),
        ``pearson`` ((lens, band, sweep) -> per-pixel correlation with exposure or gain), ``frames`` (one row per
        frame, lens and band: ``mask_mean_dn``, ``corner_dn`` in DN, ``saturated``, ...), ``masks``, ``corners``,
        ``ptc``, ``geometry`` (lens -> :func:`axis_masks`'s circle), ``angle_source``, ``projection``,
        ``inputs`` (file -> sha256), ``paths``, ``times`` (frame index -> time stamp, s since 1970 UTC), ``max_raw_dn`` and
        ``white_level_dn`` (DN).
    """
    cfg = config["linearity"]
    frames = dataset.frames(STAGE)
    frames = frames[frames["kind"] == "signal"]
    corner_fraction = config["bias"]["corner_min_radius_fraction"]
    use_hot = "hot_pixels" in effects
    masks, corners, ptc, taken = {}, {}, {}, {}
    moments = defaultdict(RunningMoments)     # (lens, band, sweep, setting) -> moments of mask pixels
    pearson = defaultdict(RunningPearson)     # (lens, band, sweep) -> per-pixel r
    first_of_setting = set()
    frame_rows, inputs, circles, angle_source, projection = [], {}, {}, {}, {}
    times = {}                                # file_index -> the frame's time stamp (s), for obs_corner
    paths = []                                # file_index -> the frame's path, for messages only
    max_raw = 0.0
    white = None
    for i, dec in enumerate(iter_frames(dataset, STAGE, frames,
                                        saturation_margin_dn=cfg["saturation_margin_dn"], progress=progress)):
        row = dec.row
        inputs[row["file"]] = dec.raw.sha256
        paths.append(str(row["path"]))
        times[i] = frame_time_s(dec.raw)
        white = dec.raw.white_level
        lenses = list(dataset.lenses) if row["lens"] == "both" else [row["lens"]]
        key = (float(dec.raw.iso), round(float(dec.raw.exposure_s), 9))
        sweep = row["sweep"]
        for lens in lenses:
            images = dec.lenses[lens]
            if lens not in masks:
                g = images.bands["G"]
                projection[lens] = dataset.projection(lens)
                level = dark_level_dn(dark[lens], "G", key[0], key[1])
                circles[lens], mask, ptc_region, angle_source[lens] = axis_masks(
                    g, (geometry or {}).get(lens), config, lens=lens, projection=projection[lens],
                    dark_level_dn=level)
                masks[lens], ptc[lens] = {}, {}
                for band in BANDS:
                    m = mask.copy()
                    p = ptc_region.copy()
                    if use_hot:
                        good = dark[lens]["hot_pixel_mask"].sel(band=band).values == 0
                        m &= good
                        p &= good
                    masks[lens][band] = m
                    # the mask's pixels within the photon-transfer region, to split its moments
                    ptc[lens][band] = (p, m[p])
                    # the same pixels as flat indices, taken from each band image (the same values in the same
                    # order as the boolean masks, without scanning the whole mask at every frame)
                    taken[lens, band] = (np.flatnonzero(m), np.flatnonzero(p))
                # per band: without the dark stage's hot pixels where its model leaves them out (corner_sites)
                corners[lens] = corner_sites(dark[lens], corner_pixels(g.shape, projection[lens], corner_fraction))
            max_raw = max(max_raw, float(dec.raw.cfa.max()))
            first = (lens, sweep, key) not in first_of_setting
            first_of_setting.add((lens, sweep, key))
            for band in BANDS:
                img = images.bands[band]
                flat = img.reshape(-1)
                m_at, region_at = taken[lens, band]
                moments[(lens, band, sweep, key)].add(flat.take(region_at))
                if first:
                    x = key[1] if sweep == "exposure" else gain_from_iso(key[0])
                    pearson[(lens, band, sweep)].add(x, img, ~images.saturated[band])
                # the frame's black-level reference: its unlit corners (fisheye), else the
                # sensor's optically black pixels when the DNG declares them, else none (NaN)
                corner_dn, n_corner_sites = corner_mean_dn(img, corners[lens][band], band, dec.raw)
                frame_rows.append({
                    "lens": lens, "band": band, "sweep": sweep, "iso": key[0], "exposure_s": key[1],
                    "file_index": i, "mask_mean_dn": float(flat.take(m_at).mean()),
                    "corner_dn": corner_dn, "n_corner_sites": n_corner_sites,
                    "saturated": bool(images.saturated[band].reshape(-1).take(m_at).any()),
                    "temperature_c": float(row.get("temperature_c", np.nan)),
                    "photons_per_pixel": float(row.get("photons_per_pixel", np.nan)),
                    "white_level_dn": float(dec.raw.white_level),
                })
    return {"moments": moments, "pearson": pearson, "frames": pd.DataFrame(frame_rows), "masks": masks,
            "corners": corners, "geometry": circles, "angle_source": angle_source, "projection": projection, "ptc": ptc, "inputs": inputs,
            "paths": paths, "times": times, "max_raw_dn": max_raw,
            "white_level_dn": white}


def _fit_model(st: pd.DataFrame, effects: list[str]):
    """Weighted fit of the setting table; linearised effect columns iterate on the prediction."""
    used = st["used"].to_numpy()
    y = st["value_dn"].to_numpy()
    sig = st["sigma_dn"].to_numpy()
    X, names = base_design(st)
    fit = wls(y[used], sig[used], X[used])
    coef_base = fit.coef
    col_effects = [e for e in effects if e in COLUMN_EFFECTS]
    extra = []
    for _ in range(3):
        pred_linear = X @ coef_base[: X.shape[1]]
        st["pred_linear_dn"] = pred_linear
        st["rate_dn_per_s"] = np.where(st["x_rate"] > 0, pred_linear / np.maximum(st["x_rate"], 1e-12), 0.0)
        extra = [(e, get_effect(e).columns(STAGE, "setting", st)) for e in col_effects]
        extra = [(e, c) for e, c in extra if c is not None]
        if not extra:
            break
        Xfull = np.hstack([X] + [c for _, c in extra])
        fit = wls(y[used], sig[used], Xfull[used])
        coef_base = fit.coef
    Xfull = np.hstack([X] + [c for _, c in extra]) if extra else X
    pred = Xfull @ fit.coef
    return fit, names, extra, pred


def _stop_on_unlit_frames(fr: pd.DataFrame, reduced: dict, dark: dict[str, xr.Dataset], min_snr: float) -> None:
    """A signal frame whose mask is no brighter than its own unlit corners (source off, lens capped)
    stops the stage with one line naming it, before it bends the fit.

    The statistic is the frame's dark-corrected mask mean less its dark-corrected corner mean, in the
    green band (a bias offset of the frame moves both alike), over its standard error for a dark frame:
    the dark stage's read noise at the frame's ISO times sqrt(1/n_mask + 1/n_corner). Without unlit
    pixels (a rectilinear region whose DNG declares no optically black ones) the lift is taken
    against the dark model alone, noise read noise times sqrt(1/n_mask).
    """
    g = fr[fr["band"] == "G"]
    for lens, rows in g.groupby("lens"):
        n_mask = int(reduced["masks"][lens]["G"].sum())
        read = dark[lens]["read_noise_dn"].sel(band="G")
        for _, row in rows.iterrows():
            read_dn = float(read.sel(iso=row["iso"], method="nearest"))
            if np.isfinite(row["corner_dn"]):
                # n_corner_sites / 2 band pixels of corners (optically black pixels count as sites)
                noise = read_dn * np.sqrt(1 / n_mask + SITES_PER_BAND_PIXEL["G"] / row["n_corner_sites"])
                lift = (row["mask_mean_dn"] - row["dark_mask_dn"]) - (row["corner_dn"] - row["dark_corner_dn"])
                against = "its unlit pixels"
            else:  # no unlit pixels in the frame: against the dark model alone
                noise = read_dn * np.sqrt(1 / n_mask)
                lift = row["mask_mean_dn"] - row["dark_mask_dn"]
                against = "the dark level"
            if lift < min_snr * noise:
                path = reduced["paths"][int(row["file_index"])]
                raise InputError(path, f"signal frame is dark: its {lens}-lens mask is {lift:.3g} DN above "
                                       f"{against} ({lift / noise:.2g} standard errors, fewer than "
                                       f"linearity.signal_frame_min_snr = {min_snr:g}); was the source off "
                                       "or the lens capped? Retake it, or list it as kind dark")


def sweep_settings(fr: pd.DataFrame, cfg: dict) -> pd.DataFrame:
    """One row per (lens, band, sweep, setting) with its flags.

    ``other_light``: the mean leaves the sweep's rise with exposure
    (:func:`~pipeline.radiometry.saturation.non_monotonic_settings`, among the settings not clipped at the white
    level); ``saturated_in_data``: plateau, variance stall or collapse among the others.

    A setting mean's standard error is the larger of its frames' scatter over sqrt(frames) (flicker, drift)
    and the pixel noise over sqrt(mask pixels x frames); a setting variance's relative standard error is
    sqrt(2 / (N (n - 1))) over the photon-transfer region's N pixels and n frames (the variance the
    saturation test and the photon-transfer fit read).

    Parameters
    ----------
    fr : pandas.DataFrame
        The frame table, dark-corrected (``value_dn`` in DN, ``pixel_var_dn2`` and ``ptc_var_dn2`` in DN^2,
        ``n_mask``, ``n_ptc``, ``n_frames``, ``saturated``).
    cfg : dict
        The ``linearity`` section of the configuration (the saturation tests' thresholds).

    Returns
    -------
    pandas.DataFrame
        The settings with ``value_dn`` (mean, DN), ``value_se_dn`` (DN), ``variance_rel_se``, ``clipped``,
        ``other_light``, ``saturated_in_data`` and ``expected_dn`` (the value the neighbouring settings give a
        setting under other light, DN; NaN elsewhere).
    """
    per = fr.groupby(["lens", "band", "sweep", "setting"]).agg(
        iso=("iso", "first"), exposure_s=("exposure_s", "first"), value_dn=("value_dn", "mean"),
        value_sd_dn=("value_dn", "std"), n_rows=("value_dn", "size"), pixel_var_dn2=("pixel_var_dn2", "first"),
        ptc_var_dn2=("ptc_var_dn2", "first"), n_mask=("n_mask", "first"), n_ptc=("n_ptc", "first"),
        n_frames=("n_frames", "first"), clipped=("saturated", "any")).reset_index()
    pixel_se = np.sqrt(np.maximum(per["pixel_var_dn2"], 0.0) / (per["n_mask"] * per["n_frames"]))
    frame_se = (per["value_sd_dn"] / np.sqrt(per["n_rows"])).fillna(0.0)
    per["value_se_dn"] = np.maximum(pixel_se, frame_se)
    frames_less_one = (per["n_frames"] - 1).to_numpy(float)
    with np.errstate(divide="ignore"):
        per["variance_rel_se"] = np.where(frames_less_one > 0,
                                          np.sqrt(2.0 / (per["n_ptc"] * np.maximum(frames_less_one, 1.0))), np.inf)
    per["saturated_in_data"] = False
    per["other_light"] = False
    per["expected_dn"] = np.nan
    for _, g in per.groupby(["lens", "band", "sweep"]):
        x = exposure_gain_s(g["exposure_s"], g["iso"]).to_numpy(float)
        clipped = g["clipped"].to_numpy(bool)
        stray = np.zeros(len(g), dtype=bool)
        stray[~clipped] = non_monotonic_settings(x[~clipped], g["value_dn"].to_numpy()[~clipped],
                                                 g["value_se_dn"].to_numpy()[~clipped], cfg["saturation_noise_sigma"])
        rest = ~stray
        saturated = np.zeros(len(g), dtype=bool)
        saturated[rest] = saturated_settings(
            x[rest], g["value_dn"].to_numpy()[rest], g["ptc_var_dn2"].to_numpy()[rest],
            cfg["saturation_plateau_fraction"], cfg["saturation_variance_drop"], clipped=clipped[rest],
            stall_fraction=cfg["saturation_variance_stall_fraction"],
            variance_rel_se=g["variance_rel_se"].to_numpy()[rest], noise_sigma=cfg["saturation_noise_sigma"])
        per.loc[g.index, "saturated_in_data"] = saturated
        per.loc[g.index, "other_light"] = stray
        per.loc[g.index[stray], "expected_dn"] = [expected_between_neighbours(x, g["value_dn"], i, stray | saturated)
                                                  for i in np.flatnonzero(stray)]
    return per


def other_light_lines(stray: pd.DataFrame, fr: pd.DataFrame, paths: list[str]) -> list[tuple[str, str]]:
    """One (lens, line) per setting whose mean leaves its sweep's rise: its frames, its settings, and the
    signal its neighbours give against the one measured (the band that departs most).

    Parameters
    ----------
    stray : pandas.DataFrame
        The rows of :func:`sweep_settings` flagged ``other_light``.
    fr : pandas.DataFrame
        The frame table (``lens``, ``sweep``, ``setting``, ``file_index``).
    paths : list[str]
        Each frame's raw file, by frame index.

    Returns
    -------
    list[tuple[str, str]]
        (lens, message) per setting, sorted by lens, sweep and setting.
    """
    out = []
    for (lens, sweep, setting), rows in stray.groupby(["lens", "sweep", "setting"], sort=True):
        worst = rows.loc[(rows["value_dn"] - rows["expected_dn"]).abs().idxmax()]
        files = sorted({paths[int(i)] for i in fr.loc[(fr["lens"] == lens) & (fr["sweep"] == sweep)
                                                      & (fr["setting"] == setting), "file_index"]})
        named = files[0] + (f" and {len(files) - 1} more" if len(files) > 1 else "")
        out.append((lens, f"linearity {sweep} sweep, lens {lens}: setting ISO {worst['iso']:g}, "
                          f"{worst['exposure_s']:g} s ({named}) leaves the sweep's rise with exposure: its "
                          f"neighbours give {worst['expected_dn']:.4g} DN, it measured {worst['value_dn']:.4g} DN "
                          f"(band {worst['band']}, {len(rows)} band(s) beyond linearity.saturation_noise_sigma); "
                          "taken under other light? Left out of the fits"))
    return out


def _stop_on_stray_sweeps(per: pd.DataFrame, fr: pd.DataFrame, notes: list[tuple[str, str]],
                          max_fraction: float) -> None:
    """Stop with one line when more than ``max_fraction`` of a sweep's settings leave its rise: the
    sweep has no light of its own to hold the others to (a few stray settings are named and left out)."""
    for (lens, sweep), rows in per.groupby(["lens", "sweep"]):
        n_settings = rows["setting"].nunique()
        stray = rows.loc[rows["other_light"], "setting"].nunique()
        if stray > max_fraction * n_settings:
            first = next(line for lens_, line in notes if lens_ == lens and f" {sweep} sweep" in line)
            raise InputError(None, f"linearity {sweep} sweep, lens {lens}: {stray} of {n_settings} settings leave "
                                   f"the sweep's rise with exposure, more than linearity.non_monotonic_max_fraction "
                                   f"= {max_fraction:g}, so the sweep has no one light to fit; the first: "
                                   f"{first.split(': ', 1)[1].split('; taken')[0]}")


def analyse_linearity(reduced: dict, dark: dict[str, xr.Dataset], config: dict,
                      effects: list[str]) -> dict[str, xr.Dataset]:
    """The linearity artefact of every lens from the reduced sweeps (:func:`reduce_linearity`).

    The frames dark-corrected and given their noise, the settings under other light and the saturated ones
    flagged, the frame-level and setting-level fits, the flat field; one dataset per lens.

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_linearity` returned.
    dark : dict[str, xarray.Dataset]
        Lens -> its dark artefact.
    config : dict
        The run's configuration.
    effects : list[str]
        The model's effects (``bias_drift``, ``nonlinearity``, ``hot_pixels``... change the fits).

    Returns
    -------
    dict[str, xarray.Dataset]
        Lens -> its linearity artefact: the response fit, saturation level, photon-transfer and EMVA1288
        figures, flat field and the observation tables.
    """
    fr = reduced["frames"].copy()
    # bias_drift needs each frame's own black level: unlit corners or optically black pixels
    testable = bool(fr["corner_dn"].notna().all())
    use_drift = "bias_drift" in effects and testable
    fr = _dark_corrected_frames(fr, reduced, dark, config, testable, use_drift)
    fr = _with_temporal_variance(fr, reduced)
    fr, drift = _frame_noise(fr, dark, effects, testable, use_drift)
    cfg = config[STAGE]
    fr = _flag_other_light_and_saturation(fr, reduced, cfg)
    ffit = _fit_frames(fr)
    st, fit, names, saturation, effect_params = _setting_table(fr, reduced, effects)
    _flat_field(reduced, dark, st, fr, effect_params, effects, cfg, use_drift)
    return {lens: _lens_dataset(lens, reduced, st, fr, fit, ffit, names, effect_params, drift, saturation,
                                dark[lens], effects)
            for lens in reduced["geometry"]}


def _dark_corrected_frames(fr: pd.DataFrame, reduced: dict, dark: dict[str, xr.Dataset], config: dict,
                           testable: bool, use_drift: bool) -> pd.DataFrame:
    """Every frame's mask mean less the dark stage's model: ``value_dn``, with the predicted dark of the mask
    and the corners (``dark_mask_dn``, ``dark_corner_dn``), the setting index and the corners' deviation from
    their setting mean; with bias_drift the corners' measured black level is taken out too (Section 3.7).
    Unlit frames stop the stage (:func:`_stop_on_unlit_frames`)."""
    # the corners' prediction is radiometry.unlit_corners' (the temperature term is added below, to the mask's
    # and the corners' alike); the offset map's means over the mask and the corners, once per lens and band
    # (the map stays on disk)
    pattern = {}
    for lens, band in fr[["lens", "band"]].drop_duplicates().itertuples(index=False):
        fpn = dark[lens]["fpn_map_dn"].sel(band=band).values
        pattern[lens, band] = (float(fpn[reduced["masks"][lens][band]].mean()),
                               corner_pattern_dn(dark[lens], band, reduced["corners"][lens][band],
                                                 config["bias"]["corner_min_radius_fraction"]))

    def dark_pred(row, what):
        d = dark[row["lens"]]
        mask_dn, corner_dn = pattern[row["lens"], row["band"]]
        if what == "corner":
            return predicted_corner_dn(d, row["band"], row["iso"], row["exposure_s"],
                                       reduced["corners"][row["lens"]][row["band"]],
                                       pattern_dn=corner_dn)
        return dark_level_dn(d, row["band"], row["iso"], row["exposure_s"]) + mask_dn

    keys = fr[["lens", "band", "iso", "exposure_s"]].drop_duplicates()
    keys["dark_mask_dn"] = keys.apply(dark_pred, axis=1, what="mask")
    keys["dark_corner_dn"] = keys.apply(dark_pred, axis=1, what="corner")
    fr = fr.merge(keys, on=["lens", "band", "iso", "exposure_s"])
    # the dark model's temperature term, frame by frame, when the dark stage fitted one
    for lens, d in dark.items():
        if "temperature_bias_dn_per_c" in d and fr["temperature_c"].notna().all():
            sel = fr["lens"] == lens
            shift = temperature_shift_dn(d, fr.loc[sel, "iso"].to_numpy(), fr.loc[sel, "exposure_s"].to_numpy(),
                                         fr.loc[sel, "temperature_c"].to_numpy())
            fr.loc[sel, "dark_mask_dn"] += shift
            fr.loc[sel, "dark_corner_dn"] += shift
    fr["setting"] = fr.groupby(["sweep", "iso", "exposure_s"], sort=True).ngroup()
    if testable:
        fr["corner_dev_dn"] = fr["corner_dn"] - fr.groupby(["lens", "band", "sweep", "setting"])["corner_dn"].transform("mean")
    fr["value_dn"] = fr["mask_mean_dn"] - fr["dark_mask_dn"]
    _stop_on_unlit_frames(fr, reduced, dark, config["linearity"]["signal_frame_min_snr"])
    if use_drift:
        # the unlit corners measure each frame's black level (Section 3.7)
        fr["value_dn"] -= fr["corner_dn"] - fr["dark_corner_dn"]
    return fr


def _with_temporal_variance(fr: pd.DataFrame, reduced: dict) -> pd.DataFrame:
    """The frames with their setting's temporal variance (mean over the mask and over the photon-transfer
    pixels) and the setting's frame and pixel counts."""
    var_rows = []
    for (lens, band, sweep, key), mom in reduced["moments"].items():
        in_mask = reduced["ptc"][lens][band][1]
        v = mom.variance()
        var_rows.append({"lens": lens, "band": band, "sweep": sweep, "iso": key[0], "exposure_s": key[1],
                         "n_frames": mom.n, "n_mask": int(in_mask.sum()), "n_ptc": int(v.size),
                         "pixel_var_dn2": float(v[in_mask].mean()),
                         "ptc_var_dn2": float(v.mean()), "ptc_mean_dn": float(mom.mean().mean())})
    var = pd.DataFrame(var_rows)
    return fr.merge(var, on=["lens", "band", "sweep", "iso", "exposure_s"])


def _frame_noise(fr: pd.DataFrame, dark: dict[str, xr.Dataset], effects: list[str], testable: bool,
                 use_drift: bool):
    """Each frame's stated noise ``sigma_dn`` and the columns of the frame-level model (gain, group, x_level).

    Returns (frames, the bias drift's sigma terms of :func:`drift_sigma`: zeros without bias_drift in the model,
    NaN without unlit corners).
    """
    # temporal noise of an unlit raw pixel: the dark stage's read noise at that ISO, averaged over the
    # reference's sites (a band pixel of the corners averages SITES_PER_BAND_PIXEL of them)
    if testable:
        rows = list(fr[["lens", "band", "iso", "n_corner_sites"]].itertuples(index=False, name=None))
        noise = {key: corner_noise_dn(dark[key[0]], key[1], key[2], key[3]) for key in set(rows)}  # once per setting
        fr["sigma_corner_dn"] = [noise[key] for key in rows]
    else:
        fr = fr.drop(columns=["corner_dn"])
    drift = drift_sigma(fr) if use_drift else ((0.0, 0.0, 0.0) if testable else (np.nan, np.nan, np.nan))
    # photon transfer: the black level of every frame moves (bias drift, temperature), so a pixel's temporal
    # variance over a setting's frames holds the sample variance of those common offsets; the unlit corners
    # measure each frame's offset (corner_dev_dn, with their own noise sigma_corner_dn)
    fr["offset_var_dn2"] = 0.0
    if use_drift:
        per_setting = fr.groupby(["lens", "band", "sweep", "setting"])["corner_dev_dn"]
        n_frames = per_setting.transform("count").clip(lower=2)
        fr["offset_var_dn2"] = (per_setting.transform(lambda d: float(np.sum(np.square(d)))) / (n_frames - 1)
                                - fr["sigma_corner_dn"] ** 2)
    fr["sigma_dn"] = np.sqrt(np.maximum(fr["pixel_var_dn2"] - np.nan_to_num(drift[0]) ** 2, 1e-12) / fr["n_mask"])
    if use_drift:
        fr["sigma_dn"] = np.hypot(fr["sigma_dn"], fr["sigma_corner_dn"])
    # lit frames without any dark reference (no unlit corners, no optically black pixels): the black level's
    # frame-to-frame spread that the dark stage measured in its dark frames (bias_drift) cannot be removed
    # from them, so it enters each frame's stated noise instead of its residual
    fr["unremoved_drift_dn"] = 0.0
    if "bias_drift" in effects and not testable:
        for lens in fr["lens"].unique():
            spread = dark_drift_dn(dark[lens])
            if spread > 0:
                fr.loc[fr["lens"] == lens, "unremoved_drift_dn"] = spread
        fr["sigma_dn"] = np.hypot(fr["sigma_dn"], fr["unremoved_drift_dn"])
    fr["gain"] = gain_from_iso(fr["iso"])
    fr["group"] = fr["lens"] + "/" + fr["band"] + "/" + fr["sweep"] + "/" + fr["setting"].astype(str)
    fr["x_level"] = 1.0
    return fr, drift


def _flag_other_light_and_saturation(fr: pd.DataFrame, reduced: dict, cfg: dict) -> pd.DataFrame:
    """The settings taken under other light (the mean leaves the sweep's rise), then saturation from the data.

    Saturation is the plateau of the mean, the stall or collapse of the variance (full well or ADC), whichever
    comes first; a setting above a saturated one is saturated too (:func:`sweep_settings`). A setting under
    other light in one band is left out in all. Too many such settings stop the stage; the others are logged
    and listed in ``reduced["other_light"]``.
    """
    fr["clipped_at_white_level"] = fr["saturated"]
    per = sweep_settings(fr, cfg)
    stray = per[per["other_light"]]
    fr = fr.merge(per[["lens", "band", "sweep", "setting", "saturated_in_data", "other_light"]],
                  on=["lens", "band", "sweep", "setting"])
    # a setting under other light in one band is left out in all (the light is the setting's)
    fr["other_light"] = fr.groupby(["lens", "sweep", "setting"])["other_light"].transform("any")
    notes = other_light_lines(stray, fr, reduced["paths"])
    _stop_on_stray_sweeps(per, fr, notes, cfg["non_monotonic_max_fraction"])
    for _, line in notes:
        log.warning(line)
    reduced["other_light"] = notes
    fr["saturated"] = fr["saturated"] | fr["saturated_in_data"]
    return fr


def _fit_frames(fr: pd.DataFrame):
    """The frame-level fit of the base model (weighted least squares) on the frames neither saturated nor under
    other light; adds ``pred_dn``, ``z`` (NaN on the others) and ``signal_fraction`` to ``fr``, returns the fit."""
    # saturated frames carry no information on drift or noise: left out of the frame-level fit
    ok = ~(fr["saturated"] | fr["other_light"]).to_numpy()
    ffit = wls(fr["value_dn"].to_numpy()[ok], fr["sigma_dn"].to_numpy()[ok], base_design(fr[ok])[0])
    fr["pred_dn"] = np.nan
    fr["z"] = np.nan
    fr.loc[ok, "pred_dn"] = ffit.pred
    fr.loc[ok, "z"] = ffit.z
    # the signal level each frame's row predicts, as a fraction of its raw range (a covariate of the residuals)
    fr["signal_fraction"] = signal_fraction(fr["pred_dn"], fr["dark_mask_dn"], fr["white_level_dn"])
    return ffit


def _setting_table(fr: pd.DataFrame, reduced: dict, effects: list[str]):
    """The setting table (the frames averaged per setting), its saturation levels and the model's fit on it.

    Returns (setting table with ``pred_dn``, ``z`` and ``signal_fraction``, the fit, its parameter names, the
    saturation levels of :func:`saturation_levels`, the effects' coefficients).
    """
    st = fr.groupby(["lens", "band", "sweep", "setting", "iso", "exposure_s"]).agg(
        value_dn=("value_dn", "mean"), frame_sigma=("sigma_dn", "mean"), n_frames=("n_frames", "first"),
        pixel_var_dn2=("pixel_var_dn2", "first"), ptc_var_dn2=("ptc_var_dn2", "first"),
        ptc_mean_dn=("ptc_mean_dn", "first"), offset_var_dn2=("offset_var_dn2", "first"), saturated=("saturated", "any"),
        clipped_at_white_level=("clipped_at_white_level", "any"), other_light=("other_light", "any"),
        dark_mask_dn=("dark_mask_dn", "mean"), temperature_c=("temperature_c", "mean"),
        photons_per_pixel=("photons_per_pixel", "mean"), white_level_dn=("white_level_dn", "min")).reset_index()
    st["gain"] = gain_from_iso(st["iso"])
    # with bias_drift in the model each frame is corrected against the dark level of the
    # unlit corners, so no drift is left in the setting mean; without it the drift is
    # unmodelled and not part of the expected noise
    st["sigma_dn"] = st["frame_sigma"] / np.sqrt(st["n_frames"])
    st["used"] = ~(st["saturated"] | st["other_light"])
    st["group"] = st["lens"] + "/" + st["band"] + "/" + st["sweep"]
    st["x_rate"] = exposure_gain_s(st["exposure_s"], st["iso"])
    saturation = saturation_levels(st, reduced)
    # scale of the nonlinearity term: the saturation level, or the ADC range where nothing saturated
    st["full_scale_dn"] = saturation["level_dn"] if saturation["reached"] else saturation["adc_range_dn"]
    fit, names, extra, pred = _fit_model(st, effects)
    st["pred_dn"] = pred
    st["signal_fraction"] = signal_fraction(pred, st["dark_mask_dn"], st["white_level_dn"])
    st["z"] = (st["value_dn"] - pred) / st["sigma_dn"]
    st.loc[~st["used"], "z"] = np.nan
    return st, fit, names, saturation, effect_coefficients(fit, len(names), extra)


def _flat_field(reduced: dict, dark: dict[str, xr.Dataset], st: pd.DataFrame, fr: pd.DataFrame, effect_params: dict,
                effects: list[str], cfg: dict, use_drift: bool) -> None:
    """The flat field (level "flat"): the spatial variance beyond the known noise (:func:`flatfield`) at the
    exposure sweep's lowest ISO, fitted with the model's effects; stored as ``reduced["flat"]`` (table, maps,
    fit), its effects' coefficients added to ``effect_params``."""
    exposure_isos = st.loc[st["sweep"] == "exposure", "iso"]
    beta = float(effect_params["nonlinearity"][0][0]) if "nonlinearity" in effect_params else 0.0
    full_scale = float(st["full_scale_dn"].iloc[0]) if len(st) else float("nan")
    offsets = {}
    if use_drift:   # the frames' common offsets, measured by the unlit pixels, per setting
        per = fr.groupby(["lens", "band", "iso", "exposure_s"])["offset_var_dn2"].first()
        offsets = {(lens, band, (float(iso), round(float(t), 9))): float(v) for (lens, band, iso, t), v in per.items()}
    flat, flat_maps = flatfield(reduced, dark, float(exposure_isos.min()), beta, full_scale, offsets,
                                cfg["flat_field_rectilinear_degree"]) \
        if len(exposure_isos) else (pd.DataFrame(), {})
    flat_fit = None
    if len(flat):
        flat_fit, flat_params = fit_with_effects(flat, "flat", effects, STAGE)
        flat["pred_dn"] = flat_fit.pred
        flat["z"] = flat_fit.z
        effect_params.update(flat_params)
    reduced["flat"] = (flat, flat_maps, flat_fit)


def dark_drift_dn(dark_ds: xr.Dataset) -> float:
    """The frame-to-frame black-level spread the dark stage measured in its dark frames (``bias_drift_dn``).

    Parameters
    ----------
    dark_ds : xarray.Dataset
        The lens's dark artefact.

    Returns
    -------
    float
        The spread, DN; 0 when it was not measured (not in its model, not testable, or NaN).
    """
    if "bias_drift_dn" not in dark_ds:
        return 0.0
    value = float(dark_ds["bias_drift_dn"])
    return value if np.isfinite(value) and value > 0 else 0.0


def saturation_levels(st: pd.DataFrame, reduced: dict) -> dict:
    """Saturation level above dark from the saturated settings, or "not reached" with a lower bound.

    Where the raw values reached the white level, the level is the ADC top minus the dark level;
    where the full well clipped first, the plateau: the largest mean of the saturated settings.

    Parameters
    ----------
    st : pandas.DataFrame
        The setting table of one lens: ``value_dn`` (dark-corrected mean, DN), ``saturated``, ``band``,
        ``dark_mask_dn`` (DN) and ``clipped_at_white_level``.
    reduced : dict
        What :func:`reduce_linearity` returned (``white_level_dn`` and ``max_raw_dn``).

    Returns
    -------
    dict
        ``reached`` (bool), ``n_saturated_settings``, ``lower_bound_dn`` (the largest unsaturated mean, DN),
        ``adc_range_dn`` (white level less the lowest dark level, DN), ``level_dn`` (the saturation level above
        dark, DN; NaN when not reached) and ``by`` (``"ADC white level"``, ``"full well (plateau)"`` or
        ``"not reached"``).
    """
    adc_range = reduced["white_level_dn"] - float(st["dark_mask_dn"].min())
    sat = st[st["saturated"]]
    unsat = st[~st["saturated"]]
    lower = float(unsat["value_dn"].max()) if len(unsat) else float("nan")
    out = {"reached": bool(len(sat)), "n_saturated_settings": int(len(sat)), "lower_bound_dn": lower,
           "adc_range_dn": adc_range, "level_dn": float("nan"), "by": "not reached"}
    if len(sat):
        if reduced["max_raw_dn"] >= reduced["white_level_dn"] - 1 and bool(sat["clipped_at_white_level"].any()):
            out.update(level_dn=reduced["max_raw_dn"] - float(st["dark_mask_dn"].min()), by="ADC white level")
        else:
            # each band's plateau; the sensor saturates at the lowest
            out.update(level_dn=float(sat.groupby("band")["value_dn"].max().min()), by="full well (plateau)")
    return out


def photon_transfer(st_l: pd.DataFrame, dark_ds: xr.Dataset, beta: float = 0.0,
                    full_scale_dn: float = float("nan"), offsets_removed: bool = False) -> dict:
    """Conversion gain and read noise from temporal variance against mean signal (Janesick 2007).

    For one raw pixel: var = K * signal + c, with K in DN per electron and c the
    zero-signal variance (read noise and rounding). The G band pixel averages two
    sites, so its variance is doubled first. K is the slope of the exposure sweep,
    fitted with one intercept c per band (a band's sites have their own read noise,
    and the dark stage's temporal noise at its shortest exposure holds the black-level
    offsets of other frames), weighted by the model, 1 / (K signal + c)^2 (a sample
    variance scatters in proportion to itself), iterated from the unweighted fit:
    weights from the noisy variances themselves would favour the points that came out
    low. The read noise in electrons is the dark stage's (``read_noise_dn`` at the
    sweep's ISO, mean over bands) over K; for the gain sweep K at each ISO is
    (var - read_var(ISO)) / signal.

    With ``offsets_removed`` (``bias_drift`` in the model) each exposure-sweep setting's
    variance loses the sample variance of its frames' common black-level offsets
    (``offset_var_dn2``, from the unlit corners): with a few frames per setting it
    scatters the curve's low points by several per cent, and it is no electron noise.

    With a fitted nonlinearity m = s (1 - beta s / F) the points are taken back
    to the linear signal first: the sensor bends the noisy signal, so a reading
    m has signal variance N'(s)^2 K s with N'(s) = 1 - 2 beta s / F =
    sqrt(1 - 4 beta m / F); the curve is that variance over N'^2 against s
    (left bent, K comes out low by about 3 beta s / F).

    Parameters
    ----------
    st_l : pandas.DataFrame
        The lens's setting table: ``used``, ``band``, ``sweep``, ``iso``, ``ptc_mean_dn`` and ``dark_mask_dn``
        (DN), ``ptc_var_dn2`` (temporal variance of a band pixel over the photon-transfer region, DN^2), and
        ``offset_var_dn2`` (DN^2) when the offsets are removed.
    dark_ds : xarray.Dataset
        The lens's dark artefact (its ``read_noise_dn`` by band and ISO, DN).
    beta : float, default 0.0
        The fitted nonlinearity's coefficient (0: a linear response).
    full_scale_dn : float, default nan
        The full scale F of the nonlinearity, DN.
    offsets_removed : bool, default False
        Whether ``bias_drift`` is in the model.

    Returns
    -------
    dict
        With an exposure sweep: ``conversion_gain_dn_per_e`` (K, DN per electron) and ``gain_e_per_dn`` (1/K),
        ``read_noise_e`` (electron), each a (value, standard error) pair, and ``ptc_iso``; always
        ``gain_sweep``, a list of (ISO, K at that ISO in DN per electron).
    """
    out = {}
    rows = st_l[st_l["used"]].copy()
    sites = rows["band"].map(SITES_PER_BAND_PIXEL)
    rows["site_var"] = rows["ptc_var_dn2"] * sites
    if offsets_removed and "offset_var_dn2" in rows:
        exposure = rows["sweep"] == "exposure"
        rows.loc[exposure, "site_var"] -= rows.loc[exposure, "offset_var_dn2"] * sites[exposure]
    # the dark stage's read noise of each band at the nearest ISO, squared (one look-up per row, plain arrays)
    read_noise = dark_ds["read_noise_dn"].transpose("band", "iso")
    band_index = {str(b): i for i, b in enumerate(read_noise["band"].values)}
    iso_index = np.abs(rows["iso"].to_numpy(float)[:, None] - read_noise["iso"].values[None, :]).argmin(axis=1)
    rows["read_var"] = read_noise.values[rows["band"].map(band_index).to_numpy(int), iso_index] ** 2
    # mean dark-corrected signal over the photon-transfer region
    rows["ptc_signal_dn"] = rows["ptc_mean_dn"] - rows["dark_mask_dn"]
    if beta and np.isfinite(full_scale_dn) and full_scale_dn > 0:
        signal, slope = linear_signal(rows["ptc_signal_dn"].to_numpy(), beta, full_scale_dn)
        # only the signal's part of the variance is bent; the zero-signal variance is added after the response
        # (the dark stage's read variance stands for it here: the bend is a few per cent of a small term)
        read = rows["read_var"].to_numpy()
        rows["site_var"] = read + (rows["site_var"].to_numpy() - read) * slope**2
        rows["ptc_signal_dn"] = signal
    ex = rows[rows["sweep"] == "exposure"]
    bands = [b for b, n in ex["band"].value_counts().items() if n >= 2]
    ex = ex[ex["band"].isin(bands)]
    if len(ex) > len(bands):
        iso = float(ex["iso"].iloc[0])
        y = ex["ptc_signal_dn"].to_numpy()
        v = ex["site_var"].to_numpy()
        design = np.column_stack([y] + [(ex["band"] == b).to_numpy(float) for b in sorted(bands)])
        coef = np.linalg.lstsq(design, v, rcond=None)[0]
        for _ in range(5):
            w = 1.0 / np.maximum(design @ coef, 1e-9)
            coef = np.linalg.lstsq(design * w[:, None], v * w, rcond=None)[0]
        aw = design * w[:, None]
        resid = (v - design @ coef) * w
        dof = max(len(y) - design.shape[1], 1)
        cov = np.linalg.pinv(aw.T @ aw) * float(np.sum(resid**2) / dof)
        k, k_se = float(coef[0]), float(np.sqrt(max(cov[0, 0], 0.0)))
        out["conversion_gain_dn_per_e"] = (k, k_se)
        out["gain_e_per_dn"] = (1.0 / k, k_se / k**2)
        # zero-signal point: the dark stage's temporal noise at this ISO
        read_dn = float(dark_ds["read_noise_dn"].sel(iso=iso, method="nearest").mean())
        read_dn_se = float(dark_ds["read_noise_dn"].sel(iso=iso, method="nearest").std())
        read_e = read_dn / k
        out["read_noise_e"] = (read_e, read_e * np.hypot(read_dn_se / read_dn, k_se / k))
        out["ptc_iso"] = iso
    gs = rows[rows["sweep"] == "gain"]
    per_iso = []
    for iso, grp in gs.groupby("iso"):
        rv = grp["read_var"] if iso in dark_ds["iso"] else 0.0
        per_iso.append((iso, float(((grp["site_var"] - rv) / grp["ptc_signal_dn"]).mean())))
    out["gain_sweep"] = per_iso
    return out


def _lens_dataset(lens, reduced, st, fr, fit, ffit, names, effect_params, drift, saturation, dark_ds,
                  effects) -> xr.Dataset:
    """The linearity artefact of one lens: the sweeps' lines and rates, saturation, photon transfer, the EMVA1288
    figures, the effects' coefficients, the setting, frame and flat tables and the flat-field map."""
    st_l = st[st["lens"] == lens].reset_index(drop=True)
    fr_l = fr[fr["lens"] == lens].reset_index(drop=True)
    other_light = [line for lens_, line in reduced.get("other_light", []) if lens_ == lens]
    sweeps = ("exposure", "gain")
    data = _sweep_line_variables(lens, reduced, st_l, fit, names, sweeps)
    ptc = _checked_photon_transfer(lens, st_l, dark_ds, effect_params, effects)
    emva = emva1288_figures(st_l, dark_ds, ptc, saturation["reached"])
    emva.update(prnu_figures(st_l, reduced["moments"], lens, dark_ds))
    flat, flat_maps, flat_fit = reduced["flat"]
    data.update(_saturation_variables(st, saturation, other_light))
    data.update(_photon_transfer_variables(ptc))
    data.update(_mask_and_residual_variables(reduced, lens, drift, st, fit, ffit, flat_fit))
    data.update(emva)
    for name, (coef, se) in effect_params.items():
        data[f"effect_{name}"] = (f"{name}_param", coef, {"long_name": f"fitted parameter(s) of {name}", "units": get_effect(name).amplitude_units})
        data[f"effect_{name}_sigma"] = (f"{name}_param", se, {"units": get_effect(name).amplitude_units})
        if name == "iso_gain":
            data[f"effect_{name}_iso"] = (f"{name}_param", np.array(get_effect(name).isos_fitted(st)), {"units": "1"})
    if ptc.get("gain_sweep"):
        isos, kk = zip(*ptc["gain_sweep"])
        data["ptc_gain_sweep_conversion_gain_dn_per_e"] = ("ptc_iso", np.array(kk),
                                                          {"long_name": "conversion gain at each ISO of the gain sweep", "units": "DN/electron"})
        data["ptc_iso"] = ("ptc_iso", np.array(isos), {"units": "1"})
    ds = xr.Dataset(data, coords={"sweep": list(sweeps), "band": list(BANDS)})
    ds = _with_tables(ds, lens, reduced, st_l, fr_l, ptc)
    if lens in flat_maps:
        flat_map, flat_sigma = flat_maps[lens]
        ds["flat_field"] = (("band", "y", "x"), flat_map,
                            {"long_name": "relative pixel sensitivity in the photon-transfer region (1 = mean)",
                             "units": "1"})
        ds["flat_field_sigma"] = (("band", "y", "x"), flat_sigma,
                                  {"long_name": "standard uncertainty of flat_field (noise of the sweep frames and "
                                                "of the dark offset map)", "units": "1"})
    # stored uncompressed: noisy values near 1 deflate to 0.6 of their size only, which cost 0.9 s of a
    # full-resolution job's write (its 72 MB in 0.44 s against 1.33 s for the artefact, 71 MB against 44 MB)
    ds["pearson_r"].encoding["zlib"] = False
    return ds


def _sweep_line_variables(lens, reduced, st_l: pd.DataFrame, fit, names, sweeps) -> dict:
    """Per sweep and band the per-pixel Pearson r map, the straight line through the used settings' means
    (slope, intercept, r) and the model's rate; adds ``ols_pred_dn`` and ``nonlinearity_pct`` to ``st_l``."""
    shape = reduced["masks"][lens]["G"].shape
    rmap = np.full((len(sweeps), len(BANDS)) + shape, np.nan, dtype=np.float32)
    slope = np.full((len(sweeps), len(BANDS), 2), np.nan)
    intercept = np.full((len(sweeps), len(BANDS), 2), np.nan)
    r_line = np.full((len(sweeps), len(BANDS)), np.nan)
    rate = np.full((len(sweeps), len(BANDS), 2), np.nan)
    for si, sweep in enumerate(sweeps):
        for bi, band in enumerate(BANDS):
            if (lens, band, sweep) in reduced["pearson"]:
                rmap[si, bi] = reduced["pearson"][(lens, band, sweep)].r(rmap.dtype)
            sel = st_l[(st_l["band"] == band) & (st_l["sweep"] == sweep) & st_l["used"]]
            if len(sel) >= 3:
                x = sel["exposure_s"] * 1e3 if sweep == "exposure" else sel["gain"]
                line = ols_line(x, sel["value_dn"])
                slope[si, bi] = line["slope"], line["slope_ci"]
                intercept[si, bi] = line["intercept"], line["intercept_ci"]
                r_line[si, bi] = line["r"]
                st_l.loc[sel.index, "ols_pred_dn"] = line["slope"] * x + line["intercept"]
            name = f"{lens}/{band}/{sweep}:rate"
            if name in names:
                k = names.index(name)
                rate[si, bi] = fit.coef[k], np.sqrt(fit.cov[k, k])
    if "ols_pred_dn" in st_l:
        st_l["nonlinearity_pct"] = 100.0 * (st_l["value_dn"] - st_l["ols_pred_dn"]) / st_l["ols_pred_dn"]
    return {
        "pearson_r": (("sweep", "band", "y", "x"), rmap,
                      {"long_name": "per-pixel Pearson r of single frames against exposure time or gain (Fig. 2)", "units": "1"}),
        "line_slope": (("sweep", "band"), slope[..., 0],
                       {"long_name": "regression slope of mean dark-corrected DN (per ms, or per unit ISO/100)", "units": "DN",
                        "comment": SLOPE_REGRESSOR}),
        "line_slope_ci95": (("sweep", "band"), slope[..., 1], {"long_name": "95 % half-interval of line_slope", "units": "DN",
                                                                "comment": SLOPE_REGRESSOR}),
        "line_intercept_dn": (("sweep", "band"), intercept[..., 0], {"long_name": "regression intercept", "units": "DN"}),
        "line_intercept_ci95_dn": (("sweep", "band"), intercept[..., 1], {"long_name": "95 % half-interval of the intercept", "units": "DN"}),
        "line_r": (("sweep", "band"), r_line, {"long_name": "Pearson r of the mask means (Fig. 3)", "units": "1"}),
        "rate_dn_per_s": (("sweep", "band"), rate[..., 0],
                          {"long_name": "model slope: dark-corrected DN per second at ISO 100", "units": "DN s-1"}),
        "rate_dn_per_s_sigma": (("sweep", "band"), rate[..., 1], {"long_name": "standard error of rate_dn_per_s", "units": "DN s-1"}),
    }


def _checked_photon_transfer(lens, st_l: pd.DataFrame, dark_ds: xr.Dataset, effect_params: dict,
                             effects) -> dict:
    """:func:`photon_transfer` of the lens's settings; a conversion gain or read noise that is not positive stops
    the stage (``ImpossibleResult``)."""
    beta = float(effect_params["nonlinearity"][0][0]) if "nonlinearity" in effect_params else 0.0
    ptc = photon_transfer(st_l, dark_ds, beta, float(st_l["full_scale_dn"].iloc[0]) if len(st_l) else np.nan,
                          offsets_removed="bias_drift" in effects)
    for key, what, unit in (("conversion_gain_dn_per_e", "conversion gain", "DN/electron"),
                            ("read_noise_e", "read noise", "electron")):
        value = ptc.get(key, (float("nan"),))[0]
        if key in ptc and not value > 0:
            raise ImpossibleResult(None, f"linearity, lens {lens}: the photon-transfer {what} is {value:.4g} {unit}, "
                                         f"which is not physical; {int((~st_l['used']).sum())} settings were found "
                                         "saturated and left out: check the sweep (signal level, saturation) and "
                                         "linearity.saturation_* in the config")
    return ptc


def _saturation_variables(st: pd.DataFrame, saturation: dict, other_light: list[str]) -> dict:
    """The saturation level (or its lower bound), the nonlinearity's full scale and the settings left out."""
    return {
        "saturation_dn": ((), saturation["level_dn"],
                          {"long_name": "saturation level above the dark level (NaN when not reached)", "units": "DN",
                           "reached": int(saturation["reached"]), "saturated_by": saturation["by"]}),
        "nonlinearity_full_scale_dn": ((), float(st["full_scale_dn"].iloc[0]) if len(st) else np.nan,
                                       {"long_name": "full scale F of the nonlinearity s (1 - beta s / F): the saturation "
                                                     "level, or the ADC range where nothing saturated", "units": "DN"}),
        "saturation_lower_bound_dn": ((), saturation["lower_bound_dn"],
                                      {"long_name": "largest unsaturated signal above dark (a lower bound of saturation)",
                                       "units": "DN"}),
        "n_saturated_settings": ((), saturation["n_saturated_settings"],
                                 {"long_name": "settings (lens, band, sweep) left out of every fit as saturated", "units": "1"}),
        "n_other_light_settings": ((), len(other_light),
                                   {"long_name": "settings whose mean signal leaves the sweep's rise with exposure "
                                                 "(taken under other light), named in the attribute settings and "
                                                 "left out of every fit", "units": "1",
                                    "settings": " | ".join(other_light)}),
    }


def _photon_transfer_variables(ptc: dict) -> dict:
    """The photon-transfer conversion gain, its inverse and the read noise with their standard errors."""
    nan2 = (np.nan, np.nan)
    return {
        "conversion_gain_dn_per_e": ((), ptc.get("conversion_gain_dn_per_e", nan2)[0],
                                     {"long_name": "photon-transfer conversion gain at the exposure-sweep ISO", "units": "DN/electron"}),
        "conversion_gain_dn_per_e_sigma": ((), ptc.get("conversion_gain_dn_per_e", nan2)[1], {"units": "DN/electron"}),
        "gain_e_per_dn": ((), ptc.get("gain_e_per_dn", nan2)[0], {"long_name": "electrons per DN at the exposure-sweep ISO", "units": "electron/DN"}),
        "gain_e_per_dn_sigma": ((), ptc.get("gain_e_per_dn", nan2)[1], {"units": "electron/DN"}),
        "read_noise_e": ((), ptc.get("read_noise_e", nan2)[0], {"long_name": "read noise from the photon-transfer intercept", "units": "electron"}),
        "read_noise_e_sigma": ((), ptc.get("read_noise_e", nan2)[1], {"units": "electron"}),
    }


def _mask_and_residual_variables(reduced: dict, lens, drift, st: pd.DataFrame, fit, ffit, flat_fit) -> dict:
    """The mask's geometry, the bias drift and the RMS of the noise-normalised residuals over the setting,
    frame and flat tables (with each table's own share as attributes)."""
    cx, cy, radius, r_mask = reduced["geometry"][lens]
    flat_chi2 = flat_fit.chi2 if flat_fit is not None else 0.0
    flat_dof = flat_fit.dof if flat_fit is not None else 0
    return {
        "mask_centre_x_px": ((), cx, {"long_name": "mask centre (band image column)", "units": "pixel"}),
        "mask_centre_y_px": ((), cy, {"long_name": "mask centre (band image row)", "units": "pixel"}),
        "image_circle_radius_px": ((), radius, {"long_name": "radius of the lit image circle (rectilinear region: its "
                                                              "half diagonal)", "units": "pixel"}),
        "mask_radius_px": ((), r_mask, {"long_name": "radius of the averaging mask (equivalent circle)", "units": "pixel",
                                        "field_angles_from": reduced["angle_source"][lens]}),
        "bias_drift_dn": ((), drift[0], {"long_name": "frame-to-frame black-level spread (0 when not in the model, "
                                                          "NaN when not testable)", "units": "DN"}),
        "rms_z": ((), np.sqrt((np.nansum(st["z"] ** 2) + ffit.chi2 + flat_chi2) / max(fit.dof + ffit.dof + flat_dof, 1)),
                  {"long_name": "RMS of the noise-normalised residuals of the linearity model (1 at the noise floor)", "units": "1",
                   # each table's own share (chi2 over its degrees of freedom): where the residual structure sits
                   "setting_table": _rms(float(np.nansum(st["z"] ** 2)), fit.dof),
                   "frame_table": _rms(ffit.chi2, ffit.dof), "flat_table": _rms(flat_chi2, flat_dof)}),
    }


def _with_tables(ds: xr.Dataset, lens, reduced: dict, st_l: pd.DataFrame, fr_l: pd.DataFrame, ptc: dict) -> xr.Dataset:
    """``ds`` with the lens's setting, frame, corner and flat tables (``obs_setting``, ``obs_frame``, the
    corners', ``obs_flat``), the note on photon-transfer figures not measured and the provenance attributes."""
    flat = reduced["flat"][0]
    st_store = st_l.drop(columns=[c for c in ("used",) if c in st_l]).assign(
        used=st_l["used"].astype(int), saturated=st_l["saturated"].astype(int),
        other_light=st_l["other_light"].astype(int))
    fr_store = fr_l.assign(saturated=fr_l["saturated"].astype(int), other_light=fr_l["other_light"].astype(int),
                           used=(~(fr_l["saturated"] | fr_l["other_light"])).astype(int))
    ds = ds.merge(table_to_dataset(st_store, "obs_setting")).merge(table_to_dataset(fr_store, "obs_frame"))
    if "conversion_gain_dn_per_e" not in ptc:
        # one exposure time (a gain sweep only, or no exposure sweep at all): no photon-transfer curve
        for name in ("conversion_gain_dn_per_e", "gain_e_per_dn", "read_noise_e"):
            ds[name].attrs.update(measured=0, not_measured=(
                "the photon-transfer curve needs an exposure sweep (several exposure times at one ISO); "
                "the linearity frames have none"))
    ds.attrs["projection"] = reduced.get("projection", {}).get(lens, "fisheye")
    ds.attrs["field_angles_from"] = reduced["angle_source"][lens]
    ds.attrs["bias_drift_testable"] = int("corner_dn" in fr_l)
    if "corner_dn" in fr_l:     # each frame's unlit corners against the dark model, for the closure
        ds = ds.merge(corner_table_dataset(corner_records(fr_l, reduced["times"])))
    if "corner_dn" not in fr_l:
        ds.attrs["bias_drift_note"] = ("bias_drift not testable: the frames have neither unlit corners nor "
                                       "optically black pixels declared in the DNG")
    if len(flat):
        ds = ds.merge(table_to_dataset(flat[flat["lens"] == lens].reset_index(drop=True), "obs_flat"))
    return ds


#: the EMVA1288 figures of the artefact: name -> (long name, units)
EMVA1288_VARIABLES = {
    "temporal_dark_noise_dn": ("temporal dark noise of one raw pixel at the exposure-sweep ISO (the dark stage's "
                               "read_noise_dn), sigma_y,dark", "DN"),
    "saturation_signal_dn": ("mean dark-corrected signal at the saturation point (the last unsaturated setting of the "
                             "exposure sweep), mu_y,sat", "DN"),
    "saturation_photons_per_pixel": ("photons per pixel at the saturation point, mu_p,sat (NaN without "
                                     "photons_per_pixel in frames.csv)", "photon"),
    "saturation_capacity_e": ("saturation capacity mu_e,sat: eta mu_p,sat with the photon counts, else "
                              "mu_y,sat / K", "electron"),
    "dynamic_range": ("dynamic range mu_e,sat / (sigma_y,dark / K + 1/2) (EMVA1288 release 3.0)", "1"),
    "dynamic_range_db": ("dynamic range, 20 log10, in decibels (UDUNITS-2 has no decibel: units 1)", "1"),
    "dynamic_range_bits": ("dynamic range, log2", "bit"),
    "snr_max": ("largest signal-to-noise ratio sqrt(mu_e,sat)", "1"),
    "snr_max_db": ("largest signal-to-noise ratio, 20 log10, in decibels (UDUNITS-2 has no decibel: units 1)", "1"),
    "linearity_error_min_pct": ("least relative deviation of the mean signal from the straight line fitted over "
                                "5-95 % of the saturation signal (EMVA1288 LE_min)", "%"),
    "linearity_error_max_pct": ("largest relative deviation from that line (EMVA1288 LE_max)", "%"),
    "responsivity_dn_per_photon": ("responsivity R: slope of the mean signal against the photons per pixel up to "
                                   "70 % of the saturation signal, through the origin", "DN/photon"),
    "responsivity_dn_per_photon_sigma": ("standard error of responsivity_dn_per_photon (residual scatter)",
                                         "DN/photon"),
    "quantum_efficiency": ("quantum efficiency eta = R / K", "electron/photon"),
    "quantum_efficiency_sigma": ("standard uncertainty of quantum_efficiency (R's and K's errors)",
                                 "electron/photon"),
}


def emva1288_figures(st_l: pd.DataFrame, dark_ds: xr.Dataset, ptc: dict, reached: bool) -> dict:
    """The EMVA1288 figures per band (:mod:`pipeline.radiometry.emva1288`) from the exposure sweep's used settings.

    Saturation point, saturation capacity, dynamic range, SNR_max, linearity error and, when every used setting
    has ``photons_per_pixel`` (frames.csv), responsivity and quantum efficiency. NaN where the data do not give
    them (no photon-transfer curve, saturation not reached, no photon counts), with a ``not_measured`` reason.

    Parameters
    ----------
    st_l : pandas.DataFrame
        The lens's setting table (``band``, ``sweep``, ``used``, ``exposure_s``, ``value_dn`` in DN, and
        ``photons_per_pixel`` when frames.csv gives it).
    dark_ds : xarray.Dataset
        The lens's dark artefact (its ``read_noise_dn``, DN).
    ptc : dict
        What :func:`photon_transfer` returned.
    reached : bool
        Whether the exposure sweep reached saturation.

    Returns
    -------
    dict
        Variable name of ``EMVA1288_VARIABLES`` -> ``("band", values, attrs)``, ready for an
        :class:`xarray.Dataset`; the units are in the attributes.
    """
    out = {name: np.full(len(BANDS), np.nan) for name in EMVA1288_VARIABLES}
    k, k_se = ptc.get("conversion_gain_dn_per_e", (np.nan, np.nan))
    iso = ptc.get("ptc_iso", np.nan)
    reasons = {}
    if not np.isfinite(k):
        reasons["all"] = "no photon-transfer curve (no exposure sweep)"
    elif not reached:
        reasons["saturation"] = "the exposure sweep did not reach saturation"
    for bi, band in enumerate(BANDS):
        sel = st_l[(st_l["band"] == band) & (st_l["sweep"] == "exposure") & st_l["used"]].sort_values("exposure_s")
        if not np.isfinite(k) or not len(sel):
            continue
        dark_dn = float(dark_ds["read_noise_dn"].sel(band=band).sel(iso=iso, method="nearest"))
        out["temporal_dark_noise_dn"][bi] = dark_dn
        if not reached:
            continue
        top = sel["value_dn"].idxmax()
        sat_dn = float(sel.loc[top, "value_dn"])
        out["saturation_signal_dn"][bi] = sat_dn
        photons = sel["photons_per_pixel"].to_numpy(float) if "photons_per_pixel" in sel else np.full(len(sel), np.nan)
        capacity = emva.saturation_capacity_e(sat_dn, k)
        x = sel["exposure_s"].to_numpy(float)
        if np.all(np.isfinite(photons)) and np.all(photons > 0):
            r, r_se, _ = emva.responsivity(photons, sel["value_dn"], sat_dn)
            qe = r / k
            out["responsivity_dn_per_photon"][bi], out["responsivity_dn_per_photon_sigma"][bi] = r, r_se
            out["quantum_efficiency"][bi] = qe
            out["quantum_efficiency_sigma"][bi] = qe * np.hypot(r_se / r, k_se / k)
            p_sat = float(sel.loc[top, "photons_per_pixel"])
            out["saturation_photons_per_pixel"][bi] = p_sat
            capacity = qe * p_sat
            x = photons
        else:
            reasons["photons"] = ("frames.csv of linearity/ gives no photons_per_pixel on every used setting of "
                                  "the exposure sweep")
        out["saturation_capacity_e"][bi] = capacity
        dr = emva.dynamic_range(capacity, dark_dn, k)
        out["dynamic_range"][bi], out["dynamic_range_db"][bi], out["dynamic_range_bits"][bi] = (
            dr, emva.decibels(dr), emva.bits(dr))
        snr = emva.snr_max(capacity)
        out["snr_max"][bi], out["snr_max_db"][bi] = snr, emva.decibels(snr)
        le = emva.linearity_error(x, sel["value_dn"], sat_dn)
        out["linearity_error_min_pct"][bi], out["linearity_error_max_pct"][bi] = le.min_pct, le.max_pct
    data = {}
    for name, (long_name, units) in EMVA1288_VARIABLES.items():
        attrs = {"long_name": long_name, "units": units}
        if not np.any(np.isfinite(out[name])):
            why = reasons.get("all") or (reasons.get("photons") if name.startswith(("responsivity", "quantum",
                                                                                    "saturation_photons"))
                                         else reasons.get("saturation"))
            if why:
                attrs.update(measured=0, not_measured=why)
        data[name] = ("band", out[name], attrs)
    return data


def _rms(chi2: float, dof: int) -> float:
    """sqrt(chi2 / dof), NaN without degrees of freedom."""
    return float(np.sqrt(chi2 / dof)) if dof > 0 else float("nan")


def prnu_figures(st_l: pd.DataFrame, moments: dict, lens: str, dark_ds: xr.Dataset) -> dict:
    """PRNU1288 per band (EMVA1288 release 3.0) from the exposure sweep's used setting with the most frames.

    Over the photon-transfer region of that bright stack, the spatial variance of its frame-averaged image less
    the part its temporal noise leaves there and less the dark stack's (the dark artefact's
    ``dark_spatial_var_dn2``, 0 without it), over the mean dark-corrected signal, in per cent. Of a band pixel (the
    G band averages two raw sites); the region is the photon-transfer region's pixels without the hot ones,
    nothing smooth removed (the flat field's ``prnu`` is the pattern left after a smooth surface).

    Parameters
    ----------
    st_l : pandas.DataFrame
        The lens's setting table (``sweep``, ``used``, ``n_frames``, ``band``, ``iso``, ``exposure_s``,
        ``ptc_mean_dn`` and ``dark_mask_dn`` in DN).
    moments : dict
        (lens, band, sweep, setting) -> running moments of the photon-transfer region (:func:`reduce_linearity`).
    lens : str
        The lens.
    dark_ds : xarray.Dataset
        The lens's dark artefact.

    Returns
    -------
    dict
        ``{"prnu1288_pct": ("band", values in %, attrs)}``; NaN where the excess variance or the signal is not
        positive, and all NaN (``measured`` 0) when no setting has two frames.
    """
    prnu = np.full(len(BANDS), np.nan)
    attrs: dict = {"long_name": "photo response non-uniformity PRNU1288 of a band pixel over the photon-transfer "
                                "region", "units": "%"}
    sweep = st_l[(st_l["sweep"] == "exposure") & st_l["used"]]
    if not len(sweep) or int(sweep["n_frames"].max()) < 2:
        attrs.update(measured=0, not_measured="no setting of the exposure sweep has two frames or more")
        return {"prnu1288_pct": ("band", prnu, attrs)}
    top = sweep.loc[sweep["n_frames"].idxmax()]
    key = (float(top["iso"]), float(top["exposure_s"]))
    attrs.update(setting_iso=key[0], setting_exposure_s=key[1], n_frames=int(top["n_frames"]))
    for bi, band in enumerate(BANDS):
        mom = moments.get((lens, band, "exposure", key))
        row = sweep[(sweep["band"] == band) & np.isclose(sweep["exposure_s"], key[1]) & (sweep["iso"] == key[0])]
        if mom is None or mom.n < 2 or not len(row):
            continue
        mean, var = mom.mean(), mom.variance()
        s2_bright = float(np.var(mean, ddof=1) - var.mean() / mom.n)
        s2_dark = float(dark_ds["dark_spatial_var_dn2"].sel(band=band)) if "dark_spatial_var_dn2" in dark_ds else 0.0
        signal = float(row["ptc_mean_dn"].iloc[0] - row["dark_mask_dn"].iloc[0])
        excess = s2_bright - (s2_dark if np.isfinite(s2_dark) else 0.0)
        if excess >= 0 and signal > 0:
            prnu[bi] = 100.0 * np.sqrt(excess) / signal
    return {"prnu1288_pct": ("band", prnu, attrs)}


def corner_records(fr_l: pd.DataFrame, times: dict[int, float]) -> pd.DataFrame:
    """One lens's ``obs_corner`` rows (:mod:`pipeline.radiometry.unlit_corners`).

    Every frame's unlit-corner mean with the dark model's prediction (its temperature term as the frames'
    correction has it) and noise.

    Parameters
    ----------
    fr_l : pandas.DataFrame
        The lens's frame table after the dark correction (``corner_dn``, ``dark_corner_dn``, ``sigma_corner_dn``
        in DN, ``n_corner_sites`` and the frame's keys).
    times : dict[int, float]
        Frame index -> the frame's time stamp, s since 1970-01-01 UTC.

    Returns
    -------
    pandas.DataFrame
        One row per frame and band, sorted by frame and band, with ``time_s`` and ``saturated`` (0 or 1).
    """
    keys = ["lens", "band", "sweep", "file_index", "iso", "exposure_s", "temperature_c"]
    out = fr_l[keys + ["corner_dn", "n_corner_sites", "dark_corner_dn", "sigma_corner_dn"]].copy()
    out["time_s"] = out["file_index"].map(times).astype(float)
    out["saturated"] = fr_l["saturated"].astype(int)
    return out.sort_values(["file_index", "band"], kind="stable").reset_index(drop=True)


def compute(ctx) -> xr.Dataset:
    """The linearity artefact of one lens (the stage runner's contract); frames dark-corrected by its dark model.

    Parameters
    ----------
    ctx : pipeline.runner.workflow.StageContext
        The job: the lens's dataset, the configuration, the model's effects and the upstream ``dark`` (and,
        when given, ``geometry``) artefacts.

    Returns
    -------
    xarray.Dataset
        The lens's linearity artefact (:func:`analyse_linearity`); the frames' sha256 are recorded in ``ctx``.
    """
    dark = {ctx.lens: ctx.upstream["dark"]}
    geometry = {ctx.lens: ctx.upstream["geometry"]} if "geometry" in ctx.upstream else None
    reduced = reduce_linearity(ctx.dataset, dark, ctx.config, ctx.effects, progress=ctx.progress, geometry=geometry)
    ctx.record_frames(reduced["inputs"])
    return analyse_linearity(reduced, dark, ctx.config, ctx.effects)[ctx.lens]

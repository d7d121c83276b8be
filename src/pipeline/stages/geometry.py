"""Geometric calibration stage (Larouche et al. 2024, Sections 2.3 and 3.2; Fig. 4, Fig. S1).

Streams the ``geometry/`` frames once. Per frame, for the lens in its
``lens`` column and each band (R, G, B) of that lens:

* corners: :func:`pipeline.geometry.corners.detect_corners_coarse_to_fine`
  on the G band image (the board located on the image resampled to
  ``geometry.coarse_search_size_px``, its corners found at full resolution
  in a crop ``geometry.crop_margin_squares`` squares around it); R and B are
  detected in a crop around G's corners (same upsampling), which is several
  times faster than searching the whole image; when G fails the R/B image is
  searched coarse to fine. Only the corner lists are kept.
* image circle: a running maximum of every band image per lens and medium (the
  lit wall around the board makes each frame bright inside the circle and
  dark outside); after the stream :func:`find_image_circle` fits it to the edge of
  the lit region (``geometry.image_circle_lit_fraction``), not to the strongest
  edge of that maximum (the union of the boards' white squares).
* frames where the board is not found keep a small block-mean thumbnail, so
  that the reason can be told once the circle is known: a board cut by the
  rim of the image circle, no board visible, or a board that is visible but
  not found (wrong ``inner_corners``?).

Then per lens, medium and band: :func:`pipeline.geometry.calibrate.calibrate`
(degree ``geometry.polynomial_degree``; G first with the centre search, R and
B initialised at G's centre), half field of view through the fitted model on
the fitted image circle (Section 3.2), maps (:func:`maps_dataset`), projection
curves against the equidistant, stereographic and orthographic references
(Fig. 4a-b), band differences against G (Fig. 4c-d), reprojection errors
(mean, per frame, against radius, Fig. S1) and the dropped frames with reasons;
the covariance of the fitted model (``geometry.covariance``) and the theta
uncertainty it gives (``theta_deg_sigma`` per band pixel,
``theta_deg_sigma_at_field_angle`` at ``geometry.theta_sigma_summary_deg``;
:mod:`pipeline.geometry.theta_uncertainty`).

A lens region declared ``projection: rectilinear`` (an ordinary camera) is fitted with OpenCV's
pinhole model instead, without an image circle (:mod:`pipeline.stages.geometry_rectilinear`):
the same maps, its own parameters.

Artefact ``results/geometry/<lens>.nc``: the layout of
:mod:`pipeline.stages.geometry_maps` plus the variables listed in
:func:`lens_dataset`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.io.dataset import Dataset
from pipeline.errors import InputError
from pipeline.io.frames import iter_frames
from pipeline.geometry.calibrate import calibrate
from pipeline.geometry.chessboard import Board
from pipeline.geometry.corners import (CROP_PAD_PX, upsample_factor, corner_spacing_px, detect_corners_coarse_to_fine,
                                       detect_in_crop)
from pipeline.geometry.image_circle import find_image_circle, half_fov_from_circle
from pipeline.stages.geometry_rectilinear import rectilinear_lens_dataset
from pipeline.geometry.scaramuzza import field_angle_rad
from pipeline.geometry.theta_uncertainty import theta_sigma_at_field_angles, theta_sigma_map
from pipeline.stages.observations import table_to_dataset
from pipeline.stages.geometry_maps import MEDIA, maps_dataset

STAGE = "geometry"
log = logging.getLogger("pipeline.geometry")
#: block size (band pixels) of the thumbnails kept for frames without a board
THUMB_BLOCK = {"min": 2, "target_px": 192}
BOARD_SIZE_HINT = "chessboard inner_corners/square_mm in dataset.yaml may be wrong"


def board_of(dataset: Dataset, medium: str) -> Board:
    """The chessboard dataset.yaml declares for the frames taken in ``medium``.

    Parameters
    ----------
    dataset : pipeline.io.dataset.Dataset
        The dataset (its dataset.yaml's ``chessboard`` entry).
    medium : str
        ``"air"`` or ``"water"``: dataset.yaml declares a square size per medium.

    Returns
    -------
    pipeline.geometry.chessboard.Board
        The board's inner corners (nx, ny) and square size, mm.

    Raises
    ------
    pipeline.errors.InputError
        If dataset.yaml has no ``chessboard`` entry or no square size for ``medium``.
    """
    cb = dataset.meta.get("chessboard")
    path = dataset.root / "dataset.yaml"
    if not cb:
        raise InputError(path, "no 'chessboard' entry: the geometry stage needs inner_corners and square_mm")
    nx, ny = (int(n) for n in cb["inner_corners"])
    sq = cb.get("square_mm", {}).get(medium)
    if sq is None:
        raise InputError(path, f"chessboard.square_mm has no size for medium '{medium}'")
    return Board(nx, ny, float(sq))


def _thumb(img: np.ndarray) -> tuple[np.ndarray, int]:
    k = max(THUMB_BLOCK["min"], int(min(img.shape) // THUMB_BLOCK["target_px"]))
    h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
    return img[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3)).astype(np.float32), k


def _match_order(corners, reference):
    """Reorder corners (a symmetric board may come out rotated by 180 degrees) to follow reference."""
    if corners is None or reference is None:
        return corners
    flipped = corners[::-1]
    if np.linalg.norm(flipped - reference, axis=1).mean() < np.linalg.norm(corners - reference, axis=1).mean():
        return flipped
    return corners


def reduce_geometry(dataset: Dataset, config: dict, progress: bool = False) -> dict:
    """Stream the geometry frames once: corners per frame and band, running maxima, thumbnails.

    Parameters
    ----------
    dataset : pipeline.io.dataset.Dataset
        The dataset; its ``geometry`` experiment's frames are read.
    config : dict
        The run's configuration (section ``geometry``: the corner search).
    progress : bool, default False
        Show a progress bar.

    Returns
    -------
    dict
        ``rows`` (one dict per frame, lens and band: ``found``, ``corners`` in band pixels, ``method``,
        ``detector_message``), ``maxima`` ((lens, medium, band) -> the band images' running maximum, DN),
        ``thumbs`` ((frame, lens, band) -> (thumbnail, block size) of the frames without a board), ``inputs``
        (file -> sha256), ``boards`` (medium -> :class:`~pipeline.geometry.chessboard.Board`), ``n_frames`` and
        ``projections`` (lens -> projection).

    Raises
    ------
    pipeline.errors.InputError
        If dataset.yaml declares no board for a medium of the frames, or a frame cannot be read.
    """
    frames = dataset.frames(STAGE)
    rows, maxima, thumbs, inputs = [], {}, {}, {}
    boards = {m: board_of(dataset, m) for m in sorted(set(frames["medium"]))}
    cfg = config[STAGE]
    search = {"coarse_size_px": int(cfg["coarse_search_size_px"]), "margin_squares": float(cfg["crop_margin_squares"])}
    for i, dec in enumerate(iter_frames(dataset, STAGE, frames, progress=progress)):
        inputs[dec.row["file"]] = dec.raw.sha256
        lens, medium = dec.row["lens"], dec.row["medium"]
        lenses = list(dec.lenses) if lens == "both" else [lens]
        board = boards[medium]
        for ln in lenses:
            images = dec.lenses[ln].bands
            g = None
            for band in ("G", "R", "B"):
                img = images[band]
                key = (ln, medium, band)
                if key not in maxima:
                    maxima[key] = img.copy()
                else:
                    np.maximum(maxima[key], img, out=maxima[key])
                if band == "G" or g is None:
                    res = detect_corners_coarse_to_fine(img, board.nx, board.ny, **search)
                else:
                    margin = search["margin_squares"] * corner_spacing_px(g, board.nx, board.ny) + CROP_PAD_PX
                    res = detect_in_crop(img, g, board.nx, board.ny, upsample=upsample_factor(img.shape),
                                         margin_px=margin)
                    if not res.found:
                        res = detect_corners_coarse_to_fine(img, board.nx, board.ny, **search)
                    res.corners = _match_order(res.corners, g)
                if band == "G" and res.found:
                    g = res.corners
                if not res.found:
                    thumbs[(i, ln, band)] = _thumb(img)
                rows.append({"frame": i, "file": dec.row["file"], "lens": ln, "medium": medium, "band": band,
                             "found": res.found, "corners": res.corners, "method": res.method,
                             "detector_message": res.message})
    return {"rows": rows, "maxima": maxima, "thumbs": thumbs, "inputs": inputs, "boards": boards,
            "n_frames": len(frames), "projections": {lens: dataset.projection(lens) for lens in dataset.lenses}}


def classify_missing(thumb: np.ndarray, k: int, circle, contrast_threshold: float) -> str:
    """Why no board was found in a frame: cut by the rim, nothing visible, or not recognised.

    High-contrast blocks (local spread of the thumbnail above
    ``contrast_threshold`` times the frame's bright level) mark a board;
    blocks within two thumbnail blocks of the circle's rim are not counted
    as rim contacts unless they lie inside it (the rim itself is an edge).

    Parameters
    ----------
    thumb : numpy.ndarray
        The frame's band image averaged in k x k blocks, DN.
    k : int
        The block size, band pixels.
    circle : pipeline.geometry.image_circle.ImageCircle
        The lens's image circle, band pixels.
    contrast_threshold : float
        The fraction of the bright level a block's local spread must exceed to count as board
        (``geometry.board_contrast_fraction``).

    Returns
    -------
    str
        The reason, one sentence for the frame's row and the log.
    """
    from scipy.ndimage import generic_filter  # noqa: F401 (kept light: use max/min filters)
    from scipy.ndimage import maximum_filter, minimum_filter

    spread = maximum_filter(thumb, 3) - minimum_filter(thumb, 3)
    yy, xx = np.mgrid[0:thumb.shape[0], 0:thumb.shape[1]]
    # thumbnail block centres in band pixels
    r = np.hypot((xx + 0.5) * k - 0.5 - circle.xc, (yy + 0.5) * k - 0.5 - circle.yc)
    inside = r < circle.radius - 2.5 * k
    bright = np.percentile(thumb[inside], 90) if inside.any() else thumb.max()
    board = inside & (spread > contrast_threshold * bright)
    if not board.any():
        return "no board visible in the frame"
    near_rim = board & (r > circle.radius - 6 * k)
    if near_rim.sum() >= 3:
        az = np.degrees(np.arctan2(((yy + 0.5) * k - circle.yc)[near_rim], ((xx + 0.5) * k - circle.xc)[near_rim]))
        return (f"board partly outside the image circle (cut by its rim near azimuth "
                f"{float(np.median(az)):.0f} deg); no complete board found")
    return "a board is visible but no complete board with the declared inner corners was found"


def _projection_curves(model, rho):
    theta = np.degrees(model.theta_of_rho(rho))
    f0 = model.poly[0]
    with np.errstate(invalid="ignore"):
        ref = {"equidistant": np.degrees(rho / f0),
               "stereographic": np.degrees(2 * np.arctan(rho / (2 * f0))),
               "orthographic": np.degrees(np.arcsin(np.where(rho <= f0, rho / f0, np.nan)))}
    return theta, ref


def analyse_geometry(reduced: dict, config: dict, dataset_root: Path) -> dict[str, xr.Dataset]:
    """Calibrate every lens's projection in each medium and band from the detected corners; one artefact per lens.

    A fisheye lens is fitted with the Scaramuzza model (:func:`pipeline.geometry.calibrate.calibrate`), its
    image circle found in the frames' running maximum and its frames without a board explained
    (:func:`classify_missing`); a rectilinear lens with the pinhole model
    (:func:`~pipeline.stages.geometry_rectilinear.rectilinear_lens_dataset`).

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_geometry` returned.
    config : dict
        The run's configuration (section ``geometry``).
    dataset_root : pathlib.Path
        The dataset's folder (its ``geometry`` folder is named in the errors).

    Returns
    -------
    dict[str, xarray.Dataset]
        Lens -> its geometry artefact (:func:`lens_dataset`).

    Raises
    ------
    pipeline.errors.InputError
        If frames.csv lists no frames, a board is found in too few frames (``geometry.min_found_fraction``,
        ``geometry.min_frames``), the calibration fails, or its mean reprojection error exceeds
        ``geometry.max_mean_error_px``.
    """
    cfg = config[STAGE]
    folder = Path(dataset_root) / STAGE
    table = pd.DataFrame(reduced["rows"])
    out = {}
    if table.empty:
        raise InputError(folder, "frames.csv lists no frames")
    for lens in sorted(set(table["lens"])):
        tl = table[table["lens"] == lens]
        media = [m for m in MEDIA if m in set(tl["medium"])]
        if reduced.get("projections", {}).get(lens) == "rectilinear":
            # an ordinary camera: OpenCV's pinhole model, no image circle (stages.geometry_rectilinear)
            for medium in media:
                board = reduced["boards"][medium]
                found_any = tl[tl["medium"] == medium].groupby("frame")["found"].any()
                if found_any.mean() < cfg["min_found_fraction"]:
                    raise InputError(folder, (f"lens {lens}, {medium}: a {board.nx}x{board.ny} board was found in "
                                              f"only {int(found_any.sum())} of {len(found_any)} frames; "
                                              f"{BOARD_SIZE_HINT}"))
            shape = reduced["maxima"][(lens, media[0], "G")].shape
            out[lens] = rectilinear_lens_dataset(tl, reduced["boards"], shape, cfg, folder, lens, BOARD_SIZE_HINT)
            continue
        models, results, circles, frame_rows, points_rows = {}, {}, {}, [], []
        for medium in media:
            board = reduced["boards"][medium]
            tm = tl[tl["medium"] == medium]
            n_frames = tm["frame"].nunique()
            found_any = tm.groupby("frame")["found"].any()
            if found_any.mean() < cfg["min_found_fraction"]:
                raise InputError(folder, (f"lens {lens}, {medium}: a {board.nx}x{board.ny} board was found in only "
                                          f"{int(found_any.sum())} of {n_frames} frames; {BOARD_SIZE_HINT}"))
            centre = None
            for band in ("G", "R", "B"):
                tb = tm[tm["band"] == band].sort_values("frame")
                circle = find_image_circle(reduced["maxima"][(lens, medium, band)],
                                           lit_fraction=cfg["image_circle_lit_fraction"])
                circles[(medium, band)] = circle
                reasons = {}
                for _, r in tb.iterrows():
                    if not r["found"]:
                        thumb, k = reduced["thumbs"][(r["frame"], lens, band)]
                        reasons[r["frame"]] = classify_missing(thumb, k, circle, cfg["board_contrast_fraction"])
                pts = [r["corners"] if r["found"] else None for _, r in tb.iterrows()]
                n_good = sum(p is not None for p in pts)
                if n_good < cfg["min_frames"]:
                    raise InputError(folder, (f"lens {lens}, {medium}, band {band}: only {n_good} frames with a board "
                                              f"(need geometry.min_frames = {cfg['min_frames']})"))
                t0 = time.perf_counter()
                try:
                    res = calibrate(pts, board.corners_mm(), reduced["maxima"][(lens, medium, band)].shape,
                                    degree=cfg["polynomial_degree"], stretch=cfg["stretch"],
                                    min_frames=cfg["min_frames"], outlier_factor=cfg["frame_outlier_factor"],
                                    point_outlier_factor=cfg["corner_outlier_factor"], centre_guess=centre,
                                    covariance=cfg["covariance"], stretch_significance=cfg["stretch_significance"],
                                    jackknife_refit_max_boards=cfg["jackknife_refit_max_boards"])
                except ValueError as exc:
                    raise InputError(folder, f"lens {lens}, {medium}, band {band}: calibration failed ({exc})") from None
                if res.mean_error_px > cfg["max_mean_error_px"]:
                    raise InputError(folder, (f"lens {lens}, {medium}, band {band}: mean reprojection error "
                                              f"{res.mean_error_px:.2f} px > geometry.max_mean_error_px "
                                              f"{cfg['max_mean_error_px']}; {BOARD_SIZE_HINT}"))
                if band == "G":
                    centre = (res.model.xc, res.model.yc)
                hf = half_fov_from_circle(res.model, circle)
                model = replace(res.model, half_fov_deg=hf)
                models[(medium, band)] = model
                results[(medium, band)] = res
                log.info("geometry %s %s %s: %d/%d frames, mean error %.3f px, centre (%.2f, %.2f), half FOV %.2f deg "
                         "(%.1f s)", lens, medium, band, len(res.used_frames), len(pts), res.mean_error_px,
                         model.xc, model.yc, hf, time.perf_counter() - t0)
                for j, (_, r) in enumerate(tb.iterrows()):
                    reason = reasons.get(r["frame"], res.dropped.get(j, ""))
                    if reason:
                        log.warning("geometry %s %s %s: %s dropped: %s", lens, medium, band, r["file"], reason)
                    frame_rows.append({"file": r["file"], "medium": medium, "band": band,
                                       "board_found": bool(r["found"]), "used": j in res.used_frames,
                                       "rms_error_px": float(res.frame_rms_px[j]), "reason": reason,
                                       "detector": r["method"]})
                points_rows.append(_points(res, board))
                dist = [np.linalg.norm(p[1]) for p in res.poses if p is not None]
                log.info("geometry %s %s: median board distance %.0f mm (square_mm %.1f scales it)",
                         lens, medium, float(np.median(dist)), board.square_mm)
        band_shape = next(iter(models.values())).shape
        out[lens] = lens_dataset(models, results, circles, frame_rows, points_rows, band_shape, cfg, reduced, lens)
    return out


def _points(res, board):
    """Per used corner: radius of the detected point, theta of the board point (fitted pose), error."""
    obj = board.corners_mm()
    thetas = []
    from pipeline.geometry.calibrate import rodrigues
    for i in res.used_frames:
        rvec, t = res.poses[i]
        cam = obj @ rodrigues(rvec[None])[0].T + t
        thetas.append(np.degrees(field_angle_rad(cam)))
    # used corners after single-corner outlier removal are a subset: report radius and error only
    return {"rho_px": res.residual_rho_px, "error_px": np.linalg.norm(res.residuals_px, axis=1),
            "theta_board_deg": np.concatenate(thetas) if thetas else np.array([])}


def lens_dataset(models, results, circles, frame_rows, points_rows, band_shape, cfg, reduced, lens) -> xr.Dataset:
    """The geometry artefact of one lens (see module docstring).

    Parameters
    ----------
    models : dict[tuple[str, str], pipeline.geometry.scaramuzza.FisheyeModel]
        (medium, band) -> the fitted model, its half field of view set from the image circle.
    results : dict[tuple[str, str], pipeline.geometry.calibrate.CalibrationResult]
        (medium, band) -> the calibration's result (poses, residuals, covariance).
    circles : dict[tuple[str, str], pipeline.geometry.image_circle.ImageCircle]
        (medium, band) -> the image circle, band pixels.
    frame_rows : list[dict]
        One row per frame, medium and band: board found, used, RMS error (band pixels), reason, detector.
    points_rows : list[pandas.DataFrame]
        The corners used by each (medium, band) fit, with their residuals.
    band_shape : tuple[int, int]
        (rows, columns) of the band images.
    cfg : dict
        The ``geometry`` section of the configuration (curve samples, radius bins, uncertainty settings).
    reduced : dict
        What :func:`reduce_geometry` returned.
    lens : str
        The lens.

    Returns
    -------
    xarray.Dataset
        The maps (:func:`~pipeline.stages.geometry_maps.maps_dataset`) with the projection curves, the
        reprojection errors against radius, the image circles, the theta uncertainty, and the ``obs_frame`` and
        ``used_corner`` tables.
    """
    ds = maps_dataset(models, band_shape)
    media = list(ds["medium"].values)
    nb, nm = len(BANDS), len(media)
    n_rho = int(cfg["curve_samples"])
    n_bins = int(cfg["radius_bins"])
    r_max = max(c.radius for c in circles.values())
    rho = np.linspace(0.0, r_max, n_rho)
    theta_curve = np.full((nm, nb, n_rho), np.nan)
    refs = {k: np.full((nm, nb, n_rho), np.nan) for k in ("equidistant", "stereographic", "orthographic")}
    diff_curve = np.full((nm, nb, n_rho), np.nan)
    diff_map_max = np.full((nm, nb), np.nan)
    scal = {k: np.full((nm, nb), np.nan) for k in ("mean_error_px", "rms_error_px", "n_frames_used", "n_frames",
                                                   "n_corners_dropped", "circle_xc_px", "circle_yc_px",
                                                   "circle_radius_px", "circle_fit_rms_px", "deg_per_px_axis")}
    err_bins = np.full((nm, nb, n_bins), np.nan)
    err_count = np.zeros((nm, nb, n_bins))
    bin_rho = np.full((nm, nb, n_bins), np.nan)
    for (medium, band), model in models.items():
        i, j = media.index(medium), BANDS.index(band)
        th, ref = _projection_curves(model, rho)
        theta_curve[i, j] = th
        for k in refs:
            refs[k][i, j] = ref[k]
        res = results[(medium, band)]
        c = circles[(medium, band)]
        scal["mean_error_px"][i, j] = res.mean_error_px
        scal["rms_error_px"][i, j] = res.rms_error_px
        scal["n_frames_used"][i, j] = len(res.used_frames)
        scal["n_frames"][i, j] = len(res.poses)
        scal["n_corners_dropped"][i, j] = res.n_points_dropped
        scal["circle_xc_px"][i, j], scal["circle_yc_px"][i, j] = c.xc, c.yc
        scal["circle_radius_px"][i, j], scal["circle_fit_rms_px"][i, j] = c.radius, c.rms_px
        scal["deg_per_px_axis"][i, j] = np.degrees(1.0 / model.poly[0])
        # reprojection error against radius on fixed bins up to the circle radius (Fig. S1)
        edges = np.linspace(0.0, r_max, n_bins + 1)
        idx = np.clip(np.digitize(res.residual_rho_px, edges) - 1, 0, n_bins - 1)
        e = np.linalg.norm(res.residuals_px, axis=1)
        cnt = np.bincount(idx, minlength=n_bins)
        sm = np.bincount(idx, weights=e, minlength=n_bins)
        with np.errstate(invalid="ignore", divide="ignore"):
            err_bins[i, j] = sm / cnt
        err_count[i, j] = cnt
        bin_rho[i, j] = 0.5 * (edges[1:] + edges[:-1])
    for medium in media:
        i = media.index(medium)
        g = BANDS.index("G")
        for j in range(len(BANDS)):
            diff_curve[i, j] = theta_curve[i, j] - theta_curve[i, g]
            d = ds["theta_deg"].values[i, j] - ds["theta_deg"].values[i, g]
            inside = ds["theta_deg"].values[i, g] <= ds["half_fov_deg"].values[i, g]
            diff_map_max[i, j] = float(np.nanmax(np.abs(d[inside]))) if inside.any() else np.nan
    dims2, dims3 = ("medium", "band"), ("medium", "band", "rho")
    ds = ds.assign_coords(rho_px=("rho", rho, {"long_name": "radial distance from the principal point", "units": "pixel"}),
                          radius_bin=("radius_bin", np.arange(n_bins)))
    attrs = {
        "mean_error_px": {"long_name": "mean Euclidean reprojection error over the used corners", "units": "pixel"},
        "rms_error_px": {"long_name": "RMS reprojection error", "units": "pixel"},
        "n_frames_used": {"long_name": "frames used in the final fit", "units": "1"},
        "n_frames": {"long_name": "frames of this medium", "units": "1"},
        "n_corners_dropped": {"long_name": "single outlier corners removed", "units": "1"},
        "circle_xc_px": {"long_name": "image circle centre column", "units": "pixel"},
        "circle_yc_px": {"long_name": "image circle centre row", "units": "pixel"},
        "circle_radius_px": {"long_name": "image circle radius (max over frames of the lit region)", "units": "pixel"},
        "circle_fit_rms_px": {"long_name": "RMS distance of the edge points from the circle", "units": "pixel"},
        "deg_per_px_axis": {"long_name": "angular size of a pixel on the optical axis (1/a0)", "units": "degree"},
    }
    for k, v in scal.items():
        ds[k] = (dims2, v, attrs[k])
    ds["projection_theta_deg"] = (dims3, theta_curve, {"long_name": "fitted projection theta(rho) (Fig. 4a-b)", "units": "degree"})
    for k, v in refs.items():
        ds[f"reference_{k}_theta_deg"] = (dims3, v, {"long_name": f"{k} projection with focal length a0", "units": "degree"})
    ds["theta_difference_vs_green_deg"] = (dims3, diff_curve, {"long_name": "theta(rho) of the band minus G (Fig. 4c-d)", "units": "degree"})
    ds = ds.merge(_theta_uncertainty(models, results, media, band_shape, cfg))
    ds["theta_map_max_difference_vs_green_deg"] = (dims2, diff_map_max,
                                                   {"long_name": "largest |theta - theta_G| over the field of view", "units": "degree"})
    ds["error_vs_radius_px"] = (("medium", "band", "radius_bin"), err_bins,
                                {"long_name": "mean reprojection error in radial bins (Fig. S1)", "units": "pixel"})
    ds["error_vs_radius_count"] = (("medium", "band", "radius_bin"), err_count, {"long_name": "corners in the radial bin", "units": "1"})
    ds["error_vs_radius_rho_px"] = (("medium", "band", "radius_bin"), bin_rho, {"long_name": "radial bin centre", "units": "pixel"})
    # per-frame table (obs_frame) and per-corner points (points)
    fr = pd.DataFrame(frame_rows)
    ds = ds.merge(table_to_dataset(fr, "obs_frame"))
    pts = []
    for (medium, band), pr in zip([(m, b) for m in media for b in ("G", "R", "B") if (m, b) in models], points_rows):
        n = len(pr["rho_px"])
        th = pr["theta_board_deg"]
        pts.append(pd.DataFrame({"medium": [medium] * n, "band": [band] * n, "rho_px": pr["rho_px"],
                                 "error_px": pr["error_px"]}))
    ds = ds.merge(table_to_dataset(pd.concat(pts, ignore_index=True), "used_corner"))
    # detected corners of every frame of this lens (NaN where none), for checks and figures
    table = pd.DataFrame(reduced["rows"])
    tl = table[table["lens"] == lens]
    frames_l = sorted(set(tl["frame"]))
    n_c = max((len(c) for c in tl["corners"] if c is not None), default=0)
    corners = np.full((len(frames_l), nb, n_c, 2), np.nan, dtype=np.float32)
    files = [""] * len(frames_l)
    frame_medium = [""] * len(frames_l)
    for _, r in tl.iterrows():
        k = frames_l.index(r["frame"])
        files[k], frame_medium[k] = r["file"], r["medium"]
        if r["corners"] is not None:
            corners[k, BANDS.index(r["band"]), :len(r["corners"])] = r["corners"]
    ds = ds.assign_coords(lens_frame=("lens_frame", np.arange(len(frames_l))))
    ds["lens_frame_file"] = ("lens_frame", np.array(files, dtype=str))
    ds["lens_frame_medium"] = ("lens_frame", np.array(frame_medium, dtype=str))
    ds["corners_px"] = (("lens_frame", "band", "board_corner", "uv"), corners,
                        {"long_name": "detected inner corners (u, v), OpenCV order", "units": "pixel"})
    ds.attrs["lens"] = lens
    ds.attrs["projection"] = "fisheye"
    return ds


def _theta_uncertainty(models, results, media, band_shape, cfg) -> xr.Dataset:
    """Covariance of the fitted model parameters and the theta uncertainty it gives (map and 1-D summary)."""
    names = next(iter(results.values())).parameter_names
    n_p, nb, nm = len(names), len(BANDS), len(media)
    summary_deg = np.asarray(cfg["theta_sigma_summary_deg"], float)
    cov = np.full((nm, nb, n_p, n_p), np.nan)
    chi2 = np.full((nm, nb), np.nan)
    stretch_model = np.full((nm, nb), "", dtype=object)
    wald, p_value = np.full((nm, nb), np.nan), np.full((nm, nb), np.nan)
    methods = set()
    sigma = np.full((nm, nb) + tuple(band_shape), np.nan, dtype=np.float32)
    summary = np.full((nm, nb, summary_deg.size), np.nan)
    for (medium, band), model in models.items():
        i, j = media.index(medium), BANDS.index(band)
        res = results[(medium, band)]
        cov[i, j], chi2[i, j] = res.parameter_covariance, res.reduced_chi2_px2
        stretch_model[i, j] = res.stretch_selection["chosen"]
        wald[i, j] = res.stretch_selection.get("wald_statistic", np.nan)
        p_value[i, j] = res.stretch_selection.get("p_value", np.nan)
        methods.add(res.covariance_method)
        sigma[i, j] = theta_sigma_map(model, names, res.parameter_covariance, band_shape)
        summary[i, j] = theta_sigma_at_field_angles(model, names, res.parameter_covariance, summary_deg)
    how = {"board_jackknife": "leave-one-board-out jackknife", "board_clustered": "cluster-robust over the boards",
           "reduced_chi2": "scaled by the reduced chi-square of the corner residuals"}[cfg["covariance"]]
    how = ("first-order propagation of the fitted model's parameter covariance (centre, stretch, f(rho) "
           f"coefficients; board poses profiled out; {how})")
    return xr.Dataset(
        {"theta_deg_sigma": (("medium", "band", "y", "x"), sigma, {
             "long_name": f"standard uncertainty of theta_deg at the band pixel centre: {how}", "units": "degree"}),
         "theta_deg_sigma_at_field_angle": (("medium", "band", "theta_summary"), summary, {
             "long_name": "standard uncertainty of theta, RMS over azimuth, at the field angles theta_summary_deg "
                          "(NaN beyond the half field of view)", "units": "degree"}),
         "geometry_parameter_covariance": (("medium", "band", "geometry_parameter", "geometry_parameter_b"), cov, {
             "long_name": "covariance of the fitted model parameters, board poses profiled out",
             "estimate": ", ".join(sorted(methods)),
             "units": "1", "comment": "element (i, j) in geometry_parameter_units[i] times geometry_parameter_units[j] "
                                      "(a pixel counted as 1)"}),
         "stretch_model": (("medium", "band"), stretch_model.astype(str), {
             "long_name": "stretch matrix model of the fit (geometry.stretch; with auto the test's choice, "
                          "the covariance then the symmetric fit's)",
             "configured": cfg["stretch"]}),
         "stretch_test_wald_statistic": (("medium", "band"), wald, {
             "long_name": "Wald statistic of no stretch (c = 1, d = e = 0) from the symmetric fit's covariance "
                          "(geometry.stretch auto; NaN when a model was configured)", "units": "1"}),
         "stretch_test_p_value": (("medium", "band"), p_value, {
             "long_name": "p-value of that statistic (Hotelling T^2 over the boards, F(2, boards - 2); "
                          "chi-square(2) with covariance reduced_chi2); the stretch is kept below "
                          "geometry.stretch_significance", "units": "1",
             "significance": float(cfg["stretch_significance"])}),
         "corner_residual_reduced_chi2_px2": (("medium", "band"), chi2, {
             "long_name": "squared corner reprojection residual per degree of freedom (the corner noise variance "
                          "the covariance assumes)", "units": "pixel^2"})},
        coords={"theta_summary_deg": ("theta_summary", summary_deg, {"long_name": "field angle of the summary",
                                                                      "units": "degree"}),
                "geometry_parameter": ("geometry_parameter", list(names)),
                "geometry_parameter_b": ("geometry_parameter_b", list(names)),
                "geometry_parameter_units": ("geometry_parameter", [_parameter_units(n) for n in names])})


def _parameter_units(name: str) -> str:
    if name.endswith("_px"):
        return "pixel"
    if name.startswith("stretch"):
        return "1"
    return f"pixel^{1 - int(name[1:])}"


def compute(ctx) -> xr.Dataset:
    """The geometry artefact of one lens (the stage runner's contract).

    Parameters
    ----------
    ctx : pipeline.runner.workflow.StageContext
        The job: the lens's dataset and the configuration.

    Returns
    -------
    xarray.Dataset
        The lens's geometry artefact (:func:`analyse_geometry`); the frames' sha256 are recorded in ``ctx``.

    Raises
    ------
    pipeline.errors.InputError
        If the geometry frames hold none of the lens.
    """
    reduced = reduce_geometry(ctx.dataset, ctx.config, progress=ctx.progress)
    ctx.record_frames(reduced["inputs"])
    arts = analyse_geometry(reduced, ctx.config, ctx.dataset.root)
    if ctx.lens not in arts:
        raise InputError(ctx.dataset.root / STAGE, f"no frames for lens {ctx.lens}")
    return arts[ctx.lens]

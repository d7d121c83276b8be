"""The geometry stage for a rectilinear lens region (dataset.yaml ``projection: rectilinear``).

The chessboard corners that :func:`pipeline.stages.geometry.reduce_geometry` found in every band
image are fitted per medium and band with OpenCV's pinhole model and its radial and tangential
distortion (:func:`pipeline.geometry.pinhole.calibrate_pinhole`); the artefact carries the same maps
as the fisheye geometry (``theta_deg``, ``phi_deg``, ``solid_angle_sr``, ``theta_deg_sigma``, dims
medium, band, y, x) so that the stages reading field angles use them unchanged, with
``half_fov_deg`` the largest field angle in the region (its corner), the reprojection errors, the
per-frame table, the fitted intrinsics and distortion (``pinhole_*``) and their covariance. There is
no image circle: its variables are NaN and the artefact's ``projection`` says ``rectilinear``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.errors import InputError
from pipeline.geometry.pinhole import PARAMETERS, calibrate_pinhole, pinhole_maps
from pipeline.stages.observations import table_to_dataset

MEDIA = ("air", "water")


def rectilinear_lens_dataset(tl: pd.DataFrame, boards: dict, shape: tuple[int, int], cfg: dict,
                             folder: Path, lens: str, board_hint: str) -> xr.Dataset:
    """The geometry artefact of one rectilinear lens from its rows of detected corners.

    Parameters
    ----------
    tl : pandas.DataFrame
        The lens's rows of :func:`pipeline.stages.geometry.reduce_geometry` (``frame``, ``file``, ``medium``,
        ``band``, ``found``, ``corners`` in band pixels, ``method``).
    boards : dict[str, pipeline.geometry.chessboard.Board]
        Medium -> the chessboard.
    shape : tuple[int, int]
        (rows, columns) of the band images.
    cfg : dict
        The ``geometry`` section of the configuration (``min_frames``, ``max_mean_error_px``).
    folder : pathlib.Path
        The dataset's geometry folder, named in the errors.
    lens : str
        The lens.
    board_hint : str
        What to check when the board is not found or fits badly, appended to the error message.

    Returns
    -------
    xarray.Dataset
        Over (medium, band, y, x): ``theta_deg``, ``phi_deg`` (degree), ``solid_angle_sr`` (sr) and
        ``theta_deg_sigma`` (degree); the pinhole parameters and their covariance; the reprojection errors
        (band pixels) and half field of view (degree); NaN image-circle variables; the ``obs_frame`` table.

    Raises
    ------
    pipeline.errors.InputError
        If a band has fewer than ``min_frames`` frames with a board, the calibration fails, or its mean
        reprojection error exceeds ``max_mean_error_px``.
    """
    media = [m for m in MEDIA if m in set(tl["medium"])]
    nm, nb = len(media), len(BANDS)
    maps = {k: np.full((nm, nb) + tuple(shape), np.nan, dtype=np.float32)
            for k in ("theta_deg", "phi_deg", "solid_angle_sr", "theta_deg_sigma")}
    n_par = len(PARAMETERS) - 1   # k3 fixed at 0
    params = np.full((nm, nb, n_par), np.nan)
    cov = np.full((nm, nb, n_par, n_par), np.nan)
    scal = {k: np.full((nm, nb), np.nan) for k in ("mean_error_px", "rms_error_px", "n_frames_used", "n_frames",
                                                   "half_fov_deg", "deg_per_px_axis", "xc_px", "yc_px",
                                                   "corner_residual_reduced_chi2_px2")}
    frame_rows = []
    for i, medium in enumerate(media):
        board = boards[medium]
        tm = tl[tl["medium"] == medium]
        for band in ("G", "R", "B"):
            j = BANDS.index(band)
            tb = tm[tm["band"] == band].sort_values("frame")
            pts = [r["corners"] if r["found"] else None for _, r in tb.iterrows()]
            n_good = sum(p is not None for p in pts)
            if n_good < cfg["min_frames"]:
                raise InputError(folder, (f"lens {lens}, {medium}, band {band}: only {n_good} frames with a board "
                                          f"(need geometry.min_frames = {cfg['min_frames']})"))
            try:
                res = calibrate_pinhole(pts, board.corners_mm(), shape)
            except (ValueError, np.linalg.LinAlgError) as exc:
                raise InputError(folder, f"lens {lens}, {medium}, band {band}: calibration failed ({exc})") from None
            if res.mean_error_px > cfg["max_mean_error_px"]:
                raise InputError(folder, (f"lens {lens}, {medium}, band {band}: mean reprojection error "
                                          f"{res.mean_error_px:.2f} px > geometry.max_mean_error_px "
                                          f"{cfg['max_mean_error_px']}; {board_hint}"))
            m = pinhole_maps(res.model, res.parameter_covariance, res.parameter_names)
            for k in maps:
                maps[k][i, j] = m[k]
            params[i, j] = res.model.parameters()[:n_par]
            cov[i, j] = res.parameter_covariance
            scal["mean_error_px"][i, j] = res.mean_error_px
            scal["rms_error_px"][i, j] = res.rms_error_px
            scal["n_frames_used"][i, j] = len(res.used_frames)
            scal["n_frames"][i, j] = len(pts)
            scal["half_fov_deg"][i, j] = float(np.nanmax(m["theta_deg"]))
            scal["deg_per_px_axis"][i, j] = np.degrees(1.0 / res.model.fx)
            scal["xc_px"][i, j], scal["yc_px"][i, j] = res.model.cx, res.model.cy
            scal["corner_residual_reduced_chi2_px2"][i, j] = res.reduced_chi2_px2
            used = set(res.used_frames)
            rms = dict(zip(res.used_frames, res.per_frame_rms_px))
            for k, (_, r) in enumerate(tb.iterrows()):
                frame_rows.append({"file": r["file"], "medium": medium, "band": band,
                                   "board_found": bool(r["found"]), "used": k in used,
                                   "rms_error_px": float(rms.get(k, np.nan)),
                                   "reason": "" if r["found"] else
                                   "no complete board with the declared inner corners was found",
                                   "detector": r["method"]})
    dims = ("medium", "band", "y", "x")
    attrs = {
        "theta_deg": {"long_name": "angle of the viewing direction from the optical axis", "units": "degree"},
        "phi_deg": {"long_name": "azimuth of the viewing direction (from +x towards +y)", "units": "degree"},
        "solid_angle_sr": {"long_name": "solid angle seen by the band pixel", "units": "sr"},
        "theta_deg_sigma": {"long_name": "standard uncertainty of theta_deg at the band pixel centre: first-order "
                                         "propagation of the pinhole fit's parameter covariance (board poses "
                                         "profiled out)", "units": "degree"},
    }
    ds = xr.Dataset({k: (dims, v, attrs[k]) for k, v in maps.items()},
                    coords={"medium": media, "band": list(BANDS),
                            "pinhole_parameter": ("pinhole_parameter", list(PARAMETERS[:n_par])),
                            "pinhole_parameter_b": ("pinhole_parameter_b", list(PARAMETERS[:n_par]))})
    ds["pinhole_parameters"] = (("medium", "band", "pinhole_parameter"), params,
                                {"long_name": "fitted fx, fy, cx, cy (band pixels) and distortion k1, k2, p1, p2 "
                                              "(OpenCV's model, k3 = 0)", "units": "1",
                                 "comment": "fx, fy, cx, cy in band pixels (a pixel counted as 1), k1, k2, p1, p2 "
                                            "dimensionless"})
    ds["pinhole_parameter_covariance"] = (("medium", "band", "pinhole_parameter", "pinhole_parameter_b"), cov,
                                          {"long_name": "covariance of pinhole_parameters, board poses profiled out",
                                           "units": "1", "comment": "element (i, j) in the units of parameter i times "
                                                                    "those of parameter j (pinhole_parameters)"})
    long = {"mean_error_px": "mean Euclidean reprojection error over the used corners",
            "rms_error_px": "RMS reprojection error (OpenCV)", "n_frames_used": "frames used in the fit",
            "n_frames": "frames of this medium", "half_fov_deg": "largest field angle in the region (its corner)",
            "deg_per_px_axis": "angular size of a pixel on the optical axis (1/fx)",
            "xc_px": "principal point column", "yc_px": "principal point row",
            "corner_residual_reduced_chi2_px2": "squared corner reprojection residual per degree of freedom"}
    units = {"n_frames_used": "1", "n_frames": "1", "half_fov_deg": "degree", "deg_per_px_axis": "degree",
             "corner_residual_reduced_chi2_px2": "pixel^2"}
    for k, v in scal.items():
        ds[k] = (("medium", "band"), v, {"long_name": long[k], "units": units.get(k, "pixel")})
    for k in ("circle_xc_px", "circle_yc_px", "circle_radius_px"):
        ds[k] = (("medium", "band"), np.full((nm, nb), np.nan), {"long_name": "no image circle (rectilinear)",
                                                                  "units": "pixel"})
    ds = ds.merge(table_to_dataset(pd.DataFrame(frame_rows), "obs_frame"))
    ds.attrs["lens"] = lens
    ds.attrs["projection"] = "rectilinear"
    return ds

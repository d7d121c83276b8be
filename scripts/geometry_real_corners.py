"""Figures of docs/geometry-real-corners.md: the geometry fit on the authors' Insta360 ONE corners.

    PYTHONPATH=src python scripts/geometry_real_corners.py [REALDATA] > docs/figures-data/geometry_real_corners.csv

REALDATA holds ``insta360-larouche/`` (default: ``$PIPELINE_REALDATA``). Per lens: the
fit with the configuration's defaults (:func:`pipeline.geometry.calibrate.calibrate`, as the geometry stage
calls it) against the authors' solution, the stretch test, the stated sigma of the centre and of the field
angle (at 5, 30, 60, 80 and 85 degrees, four azimuths) against a full leave-one-board-out refit (the whole
fit redone from the corners without each board, centre grid search included), the same with the outlier
rules switched off, the symmetric fit's covariance (the former default's) against the same refit, and the
symmetric stretch's fit for comparison. Writes CSV to stdout, one row per lens, with date, commit, machine
and command columns.
"""

from __future__ import annotations

import csv
import datetime
import platform
import subprocess
import os
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.config import load_config
from pipeline.geometry.calibrate import _project, rodrigues, calibrate
from pipeline.geometry.matlab_fisheye import read_fisheye_params
from pipeline.geometry.theta_uncertainty import theta_covariance

FILES = {"close": "FishParamsClose_01_05_2019.mat", "far": "FishParamsFar_01_05_2019.mat"}
#: field angles (degree) at which the fitted projection is compared with the authors'
THETA_DEG = np.linspace(1.0, 85.0, 85)
#: field angles (degree) and azimuths (degree) at which the stated sigma of theta is compared with the refit's
SIGMA_THETA_DEG = (5.0, 30.0, 60.0, 80.0, 85.0)
SIGMA_PHI_DEG = (0.0, 90.0, 180.0, 270.0)
#: outlier factors that reject nothing (the linearised jackknife against the refit without rejection)
NO_REJECTION = {"outlier_factor": 1.0e3, "point_outlier_factor": 1.0e3}


def centre_sigma(res):
    names = list(res.parameter_names)
    return np.sqrt(np.diag(res.parameter_covariance))[[names.index("xc_px"), names.index("yc_px")]]


def theta_pixels(model):
    """Pixels (u, v), flattened (field angle, azimuth), where ``model`` puts SIGMA_THETA_DEG at SIGMA_PHI_DEG."""
    rho = model.rho_of_theta(np.radians(SIGMA_THETA_DEG))[:, None]
    phi = np.radians(SIGMA_PHI_DEG)[None]
    return (model.xc + rho * np.cos(phi)).ravel(), (model.yc + rho * np.sin(phi)).ravel()


def theta_sigma(res, u, v):
    """Stated sigma (degree) of theta at pixels (u, v)."""
    return np.sqrt(np.diag(theta_covariance(res.model, list(res.parameter_names), res.parameter_covariance, u, v)))


def per_angle(ratio):
    """RMS over the azimuths of each field angle (ratio of stated to refit sigma at every pixel)."""
    return np.sqrt(np.mean(np.reshape(ratio, (len(SIGMA_THETA_DEG), len(SIGMA_PHI_DEG))) ** 2, axis=1))


def leave_one_board_out(authors, shape, used, options, u, v):
    """The jackknife sd of the centre and of theta at (u, v) over full refits, each board left out."""
    centres, thetas = [], []
    for g in used:
        without = [None if k == g else uv for k, uv in enumerate(authors["corners"])]
        fit = calibrate(without, authors["board_mm"], shape, **{**options, "covariance": "reduced_chi2"})
        centres.append((fit.model.xc, fit.model.yc))
        thetas.append(fit.model.theta_phi(u, v)[0])
    return jackknife_sd(centres), jackknife_sd(thetas)


def jackknife_sd(values):
    values = np.asarray(values, float)
    n = len(values)
    return np.sqrt((n - 1) / n * np.sum((values - values.mean(axis=0)) ** 2, axis=0))


def all_corner_mean_error(res, authors):
    errors = []
    for k, uv in enumerate(authors["corners"]):
        if res.poses[k] is not None:
            rvec, t = res.poses[k]
            errors.append(np.linalg.norm(_project(res.model, rodrigues(rvec[None])[0], t, authors["board_mm"]) - uv,
                                         axis=1))
    return float(np.mean(np.concatenate(errors)))


def main() -> None:
    if len(sys.argv) < 2 and not os.environ.get("PIPELINE_REALDATA"):
        sys.exit("usage: geometry_real_corners.py REALDATA (or set PIPELINE_REALDATA): the folder holding insta360-larouche/")
    root = Path(sys.argv[1] if len(sys.argv) > 1 else os.environ["PIPELINE_REALDATA"])
    cfg = load_config()["geometry"]
    options = dict(degree=cfg["polynomial_degree"], stretch="auto", min_frames=cfg["min_frames"],
                   outlier_factor=cfg["frame_outlier_factor"], point_outlier_factor=cfg["corner_outlier_factor"],
                   covariance=cfg["covariance"], stretch_significance=cfg["stretch_significance"],
                   jackknife_refit_max_boards=cfg["jackknife_refit_max_boards"])
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    meta = {"date": datetime.date.today().isoformat(), "commit": commit,
            "machine": f"{platform.node()} {platform.machine()} {platform.processor() or ''}".strip(),
            "command": "PYTHONPATH=src python scripts/geometry_real_corners.py"}
    writer = None
    for lens, name in FILES.items():
        authors = read_fisheye_params(root / "insta360-larouche" / name)
        shape = authors["image_shape"]
        t0 = time.perf_counter()
        res = calibrate(authors["corners"], authors["board_mm"], shape, **options)
        seconds = time.perf_counter() - t0
        sig = centre_sigma(res)
        chosen = res.stretch_selection["chosen"]
        sym = calibrate(authors["corners"], authors["board_mm"], shape, **{**options, "stretch": "symmetric"})
        sym_refit = calibrate(authors["corners"], authors["board_mm"], shape,
                              **{**options, "stretch": "symmetric", "jackknife_refit_max_boards": 1000})
        u, v = theta_pixels(res.model)
        refit, refit_theta = leave_one_board_out(authors, shape, res.used_frames, {**options, "stretch": chosen}, u, v)
        stated_theta = theta_sigma(res, u, v) / refit_theta
        sym_theta = theta_sigma(sym, u, v) / refit_theta
        plain = {**options, **NO_REJECTION, "stretch": chosen}
        plain_fit = calibrate(authors["corners"], authors["board_mm"], shape, **plain)
        plain_refit, plain_refit_theta = leave_one_board_out(authors, shape, plain_fit.used_frames, plain, u, v)
        plain_theta = theta_sigma(plain_fit, u, v) / plain_refit_theta
        a = authors["model"]
        rho = a.rho_of_theta(np.radians(THETA_DEG))
        dtheta = np.degrees(res.model.theta_of_rho(rho)) - THETA_DEG
        sym_sig = centre_sigma(sym)
        row = {
            "lens": lens, "boards": len(authors["corners"]), "boards_used": len(res.used_frames),
            "corners_dropped": res.n_points_dropped, "stretch_chosen": res.stretch_selection["chosen"],
            "stretch_wald": round(res.stretch_selection["wald_statistic"], 3),
            "stretch_p_value": round(res.stretch_selection["p_value"], 3),
            "covariance_method": res.covariance_method,
            "authors_xc_px": round(a.xc, 2), "authors_yc_px": round(a.yc, 2),
            "fit_xc_px": round(res.model.xc, 2), "fit_yc_px": round(res.model.yc, 2),
            "sigma_xc_px": round(sig[0], 2), "sigma_yc_px": round(sig[1], 2),
            "offset_xc_sigma": round((res.model.xc - a.xc) / sig[0], 2),
            "offset_yc_sigma": round((res.model.yc - a.yc) / sig[1], 2),
            "max_abs_dtheta_to_85_deg": round(float(np.max(np.abs(dtheta))), 4),
            "mean_error_px": round(res.mean_error_px, 3), "mean_error_all_corners_px": round(all_corner_mean_error(res, authors), 3),
            "authors_mean_error_px": round(authors["mean_error_px"], 3),
            "refit_sigma_xc_px": round(refit[0], 2), "refit_sigma_yc_px": round(refit[1], 2),
            "stated_over_refit_xc": round(sig[0] / refit[0], 2), "stated_over_refit_yc": round(sig[1] / refit[1], 2),
            **{f"refit_sigma_theta_{t:.0f}_deg": round(float(x), 3)
               for t, x in zip(SIGMA_THETA_DEG, np.sqrt(np.mean(refit_theta.reshape(len(SIGMA_THETA_DEG), -1) ** 2, axis=1)))},
            **{f"stated_over_refit_theta_{t:.0f}": round(float(x), 2) for t, x in zip(SIGMA_THETA_DEG, per_angle(stated_theta))},
            "stated_over_refit_theta_min": round(float(stated_theta.min()), 2),
            "stated_over_refit_theta_max": round(float(stated_theta.max()), 2),
            "symmetric_cov_over_refit_xc": round(centre_sigma(sym)[0] / refit[0], 2),
            "symmetric_cov_over_refit_yc": round(centre_sigma(sym)[1] / refit[1], 2),
            "symmetric_cov_over_refit_theta_min": round(float(sym_theta.min()), 2),
            "symmetric_cov_over_refit_theta_max": round(float(sym_theta.max()), 2),
            "no_rejection_stated_over_refit_xc": round(centre_sigma(plain_fit)[0] / plain_refit[0], 2),
            "no_rejection_stated_over_refit_yc": round(centre_sigma(plain_fit)[1] / plain_refit[1], 2),
            "no_rejection_stated_over_refit_theta_min": round(float(plain_theta.min()), 2),
            "no_rejection_stated_over_refit_theta_max": round(float(plain_theta.max()), 2),
            "symmetric_xc_px": round(sym.model.xc, 2), "symmetric_yc_px": round(sym.model.yc, 2),
            "symmetric_offset_xc_sigma": round((sym.model.xc - a.xc) / sym_sig[0], 2),
            "symmetric_offset_yc_sigma": round((sym.model.yc - a.yc) / sym_sig[1], 2),
            "symmetric_sigma_xc_px": round(sym_sig[0], 2), "symmetric_sigma_yc_px": round(sym_sig[1], 2),
            "symmetric_linearised_over_refit_sigma_xc": round(sym_sig[0] / centre_sigma(sym_refit)[0], 2),
            "symmetric_linearised_over_refit_sigma_yc": round(sym_sig[1] / centre_sigma(sym_refit)[1], 2),
            "fit_seconds": round(seconds, 1), **meta}
        if writer is None:
            writer = csv.DictWriter(sys.stdout, fieldnames=list(row))
            writer.writeheader()
        writer.writerow(row)
        sys.stdout.flush()


if __name__ == "__main__":
    main()

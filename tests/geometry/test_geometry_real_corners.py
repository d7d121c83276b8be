"""The geometry fit on the real Insta360 ONE corners of Larouche et al. (2024), against the authors' solution.

Data: the authors' MATLAB fisheye calibrations (``FishParamsClose_01_05_2019.mat``,
``FishParamsFar_01_05_2019.mat``; MIT licence, (c) 2021 Raphael Larouche, repository
RaphaelLarouche/radiance_camera_insta360), read from ``../shared/realdata/insta360-larouche/`` beside the
repository or from the folder the environment variable ``PIPELINE_REALDATA`` names (holding
``insta360-larouche/``); the tests skip with one line when it is absent. Each file holds the corners
MATLAB detected on every board (``ReprojectedPoints - ReprojectionErrors``, 1-based pixel coordinates of
the 3456-px green image; 0-based here: minus 1), the 8 x 6 inner corners of the 25 mm board, and the
authors' solution: f(rho) = a0 + a2 rho^2 + a3 rho^3 + a4 rho^4, tan(theta) = rho / f(rho), their
distortion centre, no stretch (``EstimateAlignment`` 0). The project's fit
(:func:`pipeline.geometry.calibrate.calibrate` with the geometry section's defaults, as the stage calls
it) is compared with that solution: nothing is compared with the pipeline itself.

Measured (docs/geometry-real-corners.md; 2-core machine): stretch auto keeps no stretch on both lenses
(p = 0.88 close, 0.22 far) and states the no-stretch fit's linearised jackknife with the outlier rules
re-applied per board; centre 0.74 and 0.35 sigma (close), 0.30 and 0.24 sigma (far) from the authors';
field angle within 0.063 (close) and 0.076 (far) degree of theirs up to 85 degrees; mean error on all
corners 0.596 and 0.924 px against their 0.600 and 0.951; the stated sigma of the centre 1.02 and 1.03
(close), 1.05 and 0.98 (far) times the full leave-one-board-out refit's, of the field angle at 5 to 85
degrees and four azimuths 0.94-1.06 (close) and 0.98-1.06 (far). About a minute per lens on a shared
machine (11 and 14 boards, a refit per board).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.geometry.calibrate import _project, rodrigues, calibrate
from pipeline.geometry.matlab_fisheye import read_fisheye_params
from pipeline.geometry.theta_uncertainty import theta_covariance

_ENV = os.environ.get("PIPELINE_REALDATA")
REALDATA = (Path(_ENV) if _ENV else Path(__file__).resolve().parents[2].parent / "shared" / "realdata")
FOLDER = REALDATA / "insta360-larouche"
FILES = {"close": "FishParamsClose_01_05_2019.mat", "far": "FishParamsFar_01_05_2019.mat"}
#: the authors' image (rows, cols): the full-resolution lens image
SHAPE = (3456, 3456)
#: the centre within this many of the fit's stated standard uncertainties of the authors' (the brief's bar)
CENTRE_SIGMAS = 2.0
#: field angles (degree) compared with the authors' projection: up to 85 degrees (the brief's range)
THETA_DEG = np.linspace(1.0, 85.0, 85)
#: largest |theta_fit - theta_authors| (degree) allowed at the same pixel radius (the brief's bar)
THETA_TOLERANCE_DEG = 0.1
#: the fit's mean reprojection error may not exceed the authors' (it drops outlier corners, they kept all)
#: and must be at least this fraction of it (a fit far below it would drop good corners)
MEAN_ERROR_LOWER_FRACTION = 0.5
#: the stated sigma of the centre and of the field angle agree with a full leave-one-board-out refit within this
#: fraction (the brief's bar)
REFIT_AGREEMENT = 0.30
#: field angles (degree) and azimuths (degree) where the stated sigma of theta is compared with the refit's
SIGMA_THETA_DEG = np.array([5.0, 30.0, 60.0, 80.0, 85.0])
SIGMA_PHI_DEG = np.array([0.0, 90.0, 180.0, 270.0])

needs_data = pytest.mark.skipif(not all((FOLDER / f).is_file() for f in FILES.values()),
                                reason=f"{FOLDER} not present (set PIPELINE_REALDATA)")


def load_authors(lens: str) -> dict:
    """The authors' corners (0-based, per board), board points (mm) and solution of one lens."""
    authors = read_fisheye_params(FOLDER / FILES[lens])
    assert authors["image_shape"] == SHAPE
    assert authors["model"].c == 1.0 and authors["model"].d == 0.0 and authors["model"].e == 0.0
    return authors


def fit_options() -> dict:
    """The calibrate options the geometry stage passes, from the configuration's defaults (geometry.stretch auto:
    the stretch chosen by evidence)."""
    cfg = load_config()["geometry"]
    assert cfg["stretch"] == "auto"
    return dict(degree=cfg["polynomial_degree"], stretch=cfg["stretch"], min_frames=cfg["min_frames"],
                outlier_factor=cfg["frame_outlier_factor"], point_outlier_factor=cfg["corner_outlier_factor"],
                covariance=cfg["covariance"], stretch_significance=cfg["stretch_significance"],
                jackknife_refit_max_boards=cfg["jackknife_refit_max_boards"])


@pytest.fixture(scope="module", params=["close", "far"])
def fitted(request):
    authors = load_authors(request.param)
    res = calibrate(authors["corners"], authors["board_mm"], SHAPE, **fit_options())
    return request.param, authors, res


@needs_data
def test_centre_within_two_stated_sigma_of_the_authors(fitted):
    lens, authors, res = fitted
    names = list(res.parameter_names)
    sigma = np.sqrt(np.diag(res.parameter_covariance))[[names.index("xc_px"), names.index("yc_px")]]
    off = np.array([res.model.xc - authors["model"].xc, res.model.yc - authors["model"].yc])
    assert np.all(np.abs(off) < CENTRE_SIGMAS * sigma), (lens, off, sigma)


@needs_data
def test_field_angle_within_a_tenth_of_a_degree_to_85_degrees(fitted):
    lens, authors, res = fitted
    rho = authors["model"].rho_of_theta(np.radians(THETA_DEG))
    theta_fit = np.degrees(res.model.theta_of_rho(rho))
    assert np.all(np.isfinite(rho))
    assert np.max(np.abs(theta_fit - THETA_DEG)) < THETA_TOLERANCE_DEG, lens


@needs_data
def test_mean_reprojection_error_comparable_to_the_authors(fitted):
    lens, authors, res = fitted
    assert MEAN_ERROR_LOWER_FRACTION * authors["mean_error_px"] < res.mean_error_px <= authors["mean_error_px"], lens
    # on every corner, the rejected ones too, the fit's error is within 10 % of the authors' (same corners)
    errors = []
    for k, uv in enumerate(authors["corners"]):
        rvec, t = res.poses[k] if res.poses[k] is not None else (None, None)
        if rvec is None:
            continue
        proj = _project(res.model, rodrigues(rvec[None])[0], t, authors["board_mm"])
        errors.append(np.linalg.norm(proj - uv, axis=1))
    all_corners = float(np.mean(np.concatenate(errors)))
    assert all_corners == pytest.approx(authors["mean_error_px"], rel=0.1), (lens, all_corners)


@needs_data
def test_stretch_chosen_by_the_test_is_the_authors_none(fitted):
    lens, _, res = fitted
    sel = res.stretch_selection
    assert sel["chosen"] == "none" and sel["p_value"] >= sel["significance"], (lens, sel)
    assert res.model.c == 1.0 and res.model.d == 0.0 and res.model.e == 0.0


@pytest.fixture(scope="module")
def refits(fitted):
    """Each board left out and the whole fit redone from the authors' corners (centre grid search and outlier
    rules included, the chosen stretch kept): the fitted models, one per left-out board."""
    lens, authors, res = fitted
    options = {**fit_options(), "stretch": res.stretch_selection["chosen"], "covariance": "reduced_chi2"}
    models = []
    for g in res.used_frames:
        without = [None if k == g else uv for k, uv in enumerate(authors["corners"])]
        models.append(calibrate(without, authors["board_mm"], SHAPE, **options).model)
    return models


def jackknife_sd(values) -> np.ndarray:
    """Leave-one-out jackknife standard deviation over the first axis."""
    values = np.asarray(values, float)
    n = len(values)
    return np.sqrt((n - 1) / n * np.sum((values - values.mean(axis=0)) ** 2, axis=0))


@needs_data
def test_stated_centre_sigma_agrees_with_a_full_leave_one_board_out_refit(fitted, refits):
    """The jackknife spread of the refitted centres against the sigma the default states, within 30 %."""
    lens, authors, res = fitted
    refit_sigma = jackknife_sd([(m.xc, m.yc) for m in refits])
    names = list(res.parameter_names)
    stated = np.sqrt(np.diag(res.parameter_covariance))[[names.index("xc_px"), names.index("yc_px")]]
    assert np.all(np.abs(stated / refit_sigma - 1.0) < REFIT_AGREEMENT), (lens, stated, refit_sigma)


@needs_data
def test_stated_field_angle_sigma_agrees_with_a_full_leave_one_board_out_refit(fitted, refits):
    """At the pixels where the fit puts ``SIGMA_THETA_DEG`` (up to 85 degrees), at four azimuths: the
    jackknife spread of the refitted models' theta there against the sigma the default states, within 30 %."""
    lens, authors, res = fitted
    rho = res.model.rho_of_theta(np.radians(SIGMA_THETA_DEG))
    phi = np.radians(SIGMA_PHI_DEG)
    u = (res.model.xc + rho[:, None] * np.cos(phi)[None]).ravel()
    v = (res.model.yc + rho[:, None] * np.sin(phi)[None]).ravel()
    refit_sigma = jackknife_sd([m.theta_phi(u, v)[0] for m in refits])
    stated = np.sqrt(np.diag(theta_covariance(res.model, list(res.parameter_names), res.parameter_covariance, u, v)))
    ratio = (stated / refit_sigma).reshape(rho.size, phi.size)
    assert np.all(np.abs(ratio - 1.0) < REFIT_AGREEMENT), (lens, np.round(ratio, 2))

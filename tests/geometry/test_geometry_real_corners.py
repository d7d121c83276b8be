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
(p = 0.71 close, 0.14 far) and states the symmetric fit's one-step jackknife; centre 0.59 and 0.30 sigma
(close), 0.40 and 0.18 sigma (far) from the authors'; field angle within 0.063 (close) and 0.076 (far)
degree of theirs up to 85 degrees; mean error on all corners 0.596 and 0.924 px against their 0.600 and
0.951; the stated sigma of the centre 1.29 and 1.20 (close), 0.79 and 1.29 (far) times the full
leave-one-board-out refit's. About a minute per lens on a shared machine (11 and 14 boards, a refit per
board).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.geometry.calibrate import _project, rodrigues, calibrate
from pipeline.geometry.matlab_fisheye import read_fisheye_params

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
#: the stated sigma of the centre agrees with a full leave-one-board-out refit within this fraction
REFIT_AGREEMENT = 0.30

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


@needs_data
def test_stated_centre_sigma_agrees_with_a_full_leave_one_board_out_refit(fitted):
    """Each board left out and the whole fit redone from the authors' corners (centre grid search and
    outlier rules included, the stated model kept): the jackknife spread of the centre against the sigma
    the default states, within 30 %."""
    lens, authors, res = fitted
    options = {**fit_options(), "stretch": res.stretch_selection["chosen"], "covariance": "reduced_chi2"}
    centres = []
    for g in res.used_frames:
        without = [None if k == g else uv for k, uv in enumerate(authors["corners"])]
        fit = calibrate(without, authors["board_mm"], SHAPE, **options)
        centres.append((fit.model.xc, fit.model.yc))
    centres = np.array(centres)
    n = len(centres)
    refit_sigma = np.sqrt((n - 1) / n * np.sum((centres - centres.mean(axis=0)) ** 2, axis=0))
    names = list(res.parameter_names)
    stated = np.sqrt(np.diag(res.parameter_covariance))[[names.index("xc_px"), names.index("yc_px")]]
    assert np.all(np.abs(stated / refit_sigma - 1.0) < REFIT_AGREEMENT), (lens, stated, refit_sigma)

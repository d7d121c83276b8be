"""Rectilinear geometry: OpenCV's pinhole calibration recovers the simulated phone lens.

The truth is the simulator's own forward model (:class:`pipeline.simulate.smartphone.PinholeOptics`,
Brown-Conrady written in numpy, inverted by a fixed-point iteration), not OpenCV's code. Corners of a
9 x 6 board in 14 poses are projected through it and 0.1 px of Gaussian noise is added.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.geometry.pinhole import calibrate_pinhole, pinhole_maps
from pipeline.simulate.smartphone import PinholeOptics

SHAPE = (240, 320)          # band image (rows, cols)
NOISE_PX = 0.1


def _board(nx=9, ny=6, square_mm=20.0):
    gx, gy = np.meshgrid(np.arange(nx), np.arange(ny))
    return np.stack([gx.ravel() * square_mm, gy.ravel() * square_mm, np.zeros(nx * ny)], axis=1)


@pytest.fixture(scope="module")
def fitted():
    optics = PinholeOptics()
    board = _board()
    centre = board.mean(axis=0)
    rng = np.random.default_rng(3)
    f = optics.intrinsics(SHAPE)[0]
    points = []
    for _ in range(14):
        rot = Rotation.from_rotvec(rng.normal(0, 0.35, 3))
        z = rng.uniform(260, 420)
        # aim the board somewhere in the field: its centre at a random pixel offset
        shift = np.array([rng.uniform(-0.3, 0.3) * SHAPE[1], rng.uniform(-0.3, 0.3) * SHAPE[0]]) * z / f
        cam = rot.apply(board - centre) + np.array([shift[0], shift[1], z])
        u, v = optics.project(cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2], SHAPE)
        uv = np.stack([u, v], axis=1) + NOISE_PX * rng.standard_normal((len(u), 2))
        inside = (uv[:, 0] > 0) & (uv[:, 0] < SHAPE[1] - 1) & (uv[:, 1] > 0) & (uv[:, 1] < SHAPE[0] - 1)
        points.append(uv if inside.all() else None)
    cal = calibrate_pinhole(points, board, SHAPE)
    maps = pinhole_maps(cal.model, cal.parameter_covariance, cal.parameter_names)
    v, u = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(float)
    true_theta, true_phi = optics.theta_phi_deg(u, v, SHAPE)
    return optics, cal, maps, true_theta, true_phi


def test_reprojection_error_is_the_injected_noise(fitted):
    """2-D Gaussian corner noise of 0.1 px per axis: RMS over both axes 0.1 px, within 20 %."""
    _, cal, _, _, _ = fitted
    assert len(cal.used_frames) >= 10
    per_axis = np.sqrt(np.mean(cal.residuals_px**2))
    assert per_axis == pytest.approx(NOISE_PX, rel=0.2)


def test_intrinsics_against_truth(fitted):
    """Focal length, centre and distortion within 4 of their stated standard errors of the truth."""
    optics, cal, _, _, _ = fitted
    fx, fy, cx, cy = optics.intrinsics(SHAPE)
    truth = np.array([fx, fy, cx, cy, optics.k1, optics.k2, optics.p1, optics.p2])
    got = cal.model.parameters()[:8]
    se = np.sqrt(np.diag(cal.parameter_covariance))
    assert np.all(np.abs(got - truth) < 4 * se), (got - truth) / se


def test_theta_and_phi_maps_against_truth(fitted):
    """theta within 4 stated sigmas (plus 1e-4 degrees of numerical inversion) at every pixel; phi, 5
    degrees and more off axis (undefined on it), within what 4 sigmas of the principal point allow. The principal point is the weak parameter
    (about 0.5 px here): 0.13 to 0.18 degrees of stated sigma, and the error map is one draw of a smooth
    field, so its RMS in sigmas is of order 1 (below 2), not a chi-square over 77,000 pixels."""
    _, _, maps, true_theta, true_phi = fitted
    d = maps["theta_deg"] - true_theta
    sigma = maps["theta_deg_sigma"]
    assert np.all(np.isfinite(sigma)) and sigma.max() < 0.5
    assert np.all(np.abs(d) < 4 * sigma + 1e-4), float(np.max(np.abs(d) / sigma))
    assert np.sqrt(np.mean((d / sigma) ** 2)) < 2.0
    # phi: a principal point off by delta turns the azimuth at radius rho by up to delta / rho
    _, cal, _, _, _ = fitted
    sigma_c = float(np.sqrt(np.max(np.diag(cal.parameter_covariance)[2:4])))
    rho = cal.model.fx * np.tan(np.radians(true_theta))
    off_axis = true_theta > 5.0
    dphi = (maps["phi_deg"] - true_phi + 180.0) % 360.0 - 180.0
    assert np.all(np.abs(dphi[off_axis]) < np.degrees(4 * sigma_c / rho[off_axis]) + 0.01)


def test_solid_angle_against_truth(fitted):
    """Per-pixel solid angle against the truth's, the truth from the simulator's inverse mapping by
    finite differences (its own code): within 0.5 % (the fitted focal length is known to 0.1 %), and
    1 / (fx fy) on the axis."""
    optics, cal, maps, _, _ = fitted
    v, u = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(float)
    h = 0.5
    xr, yr = optics.ray(u + h, v, SHAPE)
    xl, yl = optics.ray(u - h, v, SHAPE)
    xd, yd = optics.ray(u, v + h, SHAPE)
    xt, yt = optics.ray(u, v - h, SHAPE)
    x, y = optics.ray(u, v, SHAPE)
    area = np.abs((xr - xl) * (yd - yt) - (yr - yl) * (xd - xt)) / (2 * h) ** 2
    true = area / (1 + x * x + y * y) ** 1.5
    np.testing.assert_allclose(maps["solid_angle_sr"], true, rtol=5e-3)
    m = cal.model
    iy, ix = int(round(m.cy)), int(round(m.cx))
    assert maps["solid_angle_sr"][iy, ix] == pytest.approx(1.0 / (m.fx * m.fy), rel=2e-3)

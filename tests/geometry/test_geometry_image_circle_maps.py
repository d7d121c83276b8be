"""Image circle fit, half FOV, per-pixel maps and solid angles."""

import numpy as np
import pytest

from pipeline.geometry.image_circle import find_image_circle, half_fov_from_circle
from pipeline.geometry.maps import mask_within, pixel_of_direction, solid_angle_map, theta_phi_maps
from pipeline.simulate.flat_field import render_flat_field
from pipeline.simulate.lens import default_model


@pytest.mark.parametrize("lens,medium,size", [("close", "air", 288), ("far", "water", 288),
                                              ("close", "air", 64)])
def test_image_circle_within_one_pixel(lens, medium, size):
    m = default_model(lens, medium, size)
    rng = np.random.default_rng(3)
    img = render_flat_field(m, supersample=4) + rng.normal(0, 0.01, m.shape)
    c = find_image_circle(img)
    # 1 px is the brief's bar; the sub-pixel edge of a supersampled circle
    # is located to a few hundredths of a pixel.
    assert abs(c.xc - m.xc) < 1 and abs(c.yc - m.yc) < 1
    assert abs(c.radius - m.image_circle_radius()) < 1
    # half FOV through the true model: 0.5 deg bar (1 px ~ 0.7 deg at 288 px,
    # the fit is far better than 1 px).
    assert half_fov_from_circle(m, c) == pytest.approx(m.half_fov_deg, abs=0.5)


@pytest.mark.parametrize("medium", ["air", "water"])
def test_solid_angle_sums_to_cap(medium):
    m = default_model("close", medium, 288)
    th, ph = theta_phi_maps(m)
    sa = solid_angle_map(m)
    cap = 2 * np.pi * (1 - np.cos(np.radians(m.half_fov_deg)))
    # 1 %: the pixelated rim of the circle (about 840 half-cut pixels of
    # ~0.0003 sr each) adds up to ~0.1 %; the rest is the midpoint rule.
    assert sa[mask_within(th, m.half_fov_deg)].sum() == pytest.approx(cap, rel=0.01)
    # the Jacobian density agrees with the corner-ray area of one pixel
    u, v = 200.0, 90.0
    corners = m.cam2world(np.array([u - .5, u + .5, u + .5, u - .5]),
                          np.array([v - .5, v - .5, v + .5, v + .5]))
    a = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    b = np.cross(corners[2] - corners[0], corners[3] - corners[0])
    area = 0.5 * (np.linalg.norm(a) + np.linalg.norm(b))
    assert sa[int(v), int(u)] == pytest.approx(area, rel=1e-3)


def test_maps_and_inverse_direction():
    m = default_model("far", "air", 288)
    th, ph = theta_phi_maps(m)
    assert th.shape == (288, 288) and ph.shape == (288, 288)
    assert th.min() < 1.0 and th[mask_within(th, 91)].max() <= 91
    rows, cols = np.nonzero(mask_within(th, 90.0))
    sel = slice(None, None, 97)
    u, v = pixel_of_direction(m, th[rows[sel], cols[sel]], ph[rows[sel], cols[sel]])
    assert np.max(np.hypot(u - cols[sel], v - rows[sel])) < 1e-6

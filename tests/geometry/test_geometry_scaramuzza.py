"""Scaramuzza model: round trips, scaling, published half field of view."""

import numpy as np
import pytest

from pipeline.geometry.scaramuzza import FisheyeModel
from pipeline.simulate.lens import default_model


def _rays(theta_max_deg, n=4001):
    th = np.radians(np.linspace(0.0, theta_max_deg, n))
    ph = np.radians(np.linspace(-180.0, 180.0, n)) * 7.3  # many azimuths
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1)


@pytest.mark.parametrize("lens", ["close", "far"])
@pytest.mark.parametrize("medium", ["air", "water"])
@pytest.mark.parametrize("size", [64, 288, 1728])
def test_world2cam_cam2world_round_trip(lens, medium, size):
    m = default_model(lens, medium, size)
    # Whole field and beyond 90 degrees (f < 0); 1e-6 px is the brief's bar,
    # Newton-polished inversion reaches rounding error.
    u, v = m.world2cam(_rays(100.0))
    assert np.all(np.isfinite(u))
    u2, v2 = m.world2cam(m.cam2world(u, v))
    assert np.max(np.hypot(u2 - u, v2 - v)) < 1e-6
    # And pixels -> rays -> pixels over the whole image.
    vv, uu = np.mgrid[0:size:max(1, size // 50), 0:size:max(1, size // 50)].astype(float)
    ru, rv = m.world2cam(m.cam2world(uu, vv))
    assert np.max(np.hypot(ru - uu, rv - vv)) < 1e-6


def test_stretch_round_trip():
    m = FisheyeModel((100.0, 0.0, -3e-3, -2e-6, -4e-8), 140.2, 141.7, 1.01, 0.02, -0.01,
                     shape=(288, 288))
    u, v = m.world2cam(_rays(98.0))
    u2, v2 = m.world2cam(m.cam2world(u, v))
    assert np.max(np.hypot(u2 - u, v2 - v)) < 1e-6


def test_published_model_half_fov_at_published_circle():
    # The close lens reaches 91 degrees at rho = 1600 raw pixels (the
    # published image circle); scaling must keep the angle at the scaled
    # radius (pure rescaling, exact up to rounding). 0.2 degrees covers the
    # rounding of the published circle radius to 1600 px.
    for size in (1728, 288, 64):
        m = default_model("close", "air", size)
        rho_band = 1600.0 * size / 3456
        assert np.degrees(m.theta_of_rho(rho_band)) == pytest.approx(91.0, abs=0.2)
        # default models carry their image circle: theta there is the half FOV
        assert np.degrees(m.theta_of_rho(m.image_circle_radius())) == pytest.approx(91.0, abs=1e-6)
        w = default_model("close", "water", size)
        # the water model keeps the image circle on the sensor (0.05 % of radius,
        # refit error of the polynomial) and sees 76 degrees there
        assert w.image_circle_radius() == pytest.approx(m.image_circle_radius(), rel=5e-4)
        assert np.degrees(w.theta_of_rho(m.image_circle_radius())) == pytest.approx(76.0, abs=0.1)


def test_band_pixel_convention_and_scaling():
    m = default_model("close", "air", 1728)
    # band pixel i covers raw pixels 2i, 2i+1: u_band = (u_raw - 0.5) / 2
    assert m.xc == pytest.approx((1731.51 - 0.5) / 2)
    assert m.yc == pytest.approx((1710.86 - 0.5) / 2)
    # scaling preserves angles at corresponding points
    s = m.scaled(1 / 6)
    th1, ph1 = m.theta_phi(1000.0, 300.0)
    th2, ph2 = s.theta_phi((1000.0 + 0.5) / 6 - 0.5, (300.0 + 0.5) / 6 - 0.5)
    assert th1 == pytest.approx(th2, abs=1e-9) and ph1 == pytest.approx(ph2, abs=1e-9)


def test_dict_round_trip():
    m = default_model("far", "water", 288)
    m2 = FisheyeModel.from_dict(m.to_dict())
    assert m2 == m


def test_bad_lens_or_medium():
    with pytest.raises(ValueError):
        default_model("middle", "air", 64)
    with pytest.raises(ValueError):
        default_model("close", "oil", 64)

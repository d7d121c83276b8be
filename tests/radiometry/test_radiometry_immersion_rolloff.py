"""In-water roll-off from the in-air roll-off: outer-surface incidence angles and the Fresnel ratio."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.radiometry.immersion_rolloff import outer_surface_incidence_deg, water_rolloff_factor


def t_unpolarised(n1, n2, i_deg):
    """Fresnel power transmittance written out from the s and p amplitude ratios (Born and Wolf 1.5)."""
    i = np.radians(i_deg)
    r = np.arcsin(n1 / n2 * np.sin(i))
    rs = ((n1 * np.cos(i) - n2 * np.cos(r)) / (n1 * np.cos(i) + n2 * np.cos(r))) ** 2
    rp = ((n2 * np.cos(i) - n1 * np.cos(r)) / (n2 * np.cos(i) + n1 * np.cos(r))) ** 2
    return 1.0 - 0.5 * (rs + rp)


def test_flat_port_incidence_is_the_field_angle():
    """A flat port (theta_a from Snell, sin theta_a = n_w sin theta_w) has an untilted surface: i = theta."""
    tw = np.array([0.0, 10.0, 30.0, 45.0])
    ta = np.degrees(np.arcsin(1.333 * np.sin(np.radians(tw))))
    ia, iw = outer_surface_incidence_deg(ta, tw, 1.333)
    assert np.allclose(ia, ta, atol=1e-9) and np.allclose(iw, tw, atol=1e-9)


def test_compressed_field_obeys_snell_on_a_tilted_surface():
    """theta_w = theta_a 76 / 91 (the default camera): the incidence angles satisfy Snell, the tilt grows
    with field angle (a convex surface) and reaches about 41 deg at the 91 deg edge."""
    ta = np.linspace(1.0, 91.0, 50)
    tw = ta * 76.0 / 91.0
    ia, iw = outer_surface_incidence_deg(ta, tw, 1.334)
    assert np.allclose(np.sin(np.radians(ia)), 1.334 * np.sin(np.radians(iw)), atol=1e-12)
    beta = ta - ia
    assert np.all(np.diff(beta) > 0) and beta[-1] == pytest.approx(40.9, abs=0.2)


def test_fresnel_ratio_by_hand():
    """1 on the axis; at a flat port's 30 deg in water the written-out Fresnel ratio."""
    n_w, n_g = 1.333, 1.5
    assert water_rolloff_factor(0.0, 0.0, n_w, n_g) == pytest.approx(1.0, abs=1e-12)
    tw = 30.0
    ta = np.degrees(np.arcsin(n_w * np.sin(np.radians(tw))))
    want = (t_unpolarised(n_w, n_g, tw) / t_unpolarised(n_w, n_g, 0.0)) / (
        t_unpolarised(1.0, n_g, ta) / t_unpolarised(1.0, n_g, 0.0))
    assert water_rolloff_factor(ta, tw, n_w, n_g) == pytest.approx(want, rel=1e-12)
    assert want > 1.0

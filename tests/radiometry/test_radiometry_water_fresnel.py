"""Tests of pipeline.radiometry.water and pipeline.radiometry.fresnel."""

import numpy as np
import pytest

from pipeline.radiometry.fresnel import (
    fresnel_reflectance,
    fresnel_reflectance_normal,
    fresnel_transmittance,
    fresnel_transmittance_normal,
    refraction_angle_deg,
    transmittance_air_water,
)
from pipeline.radiometry.water import refractive_index_air, refractive_index_water


# Handbook values for pure water at 20 C (F, D, C Fraunhofer lines, as used
# for the Abbe number): 486.1 nm 1.33712, 589.3 nm 1.33299, 656.3 nm 1.33110.
# Quan and Fry quote an accuracy of ~3e-5 against Austin and Halikas; 2e-4
# leaves room for the different data sets.
@pytest.mark.parametrize(
    "wavelength_nm, expected",
    [(486.1, 1.33712), (589.3, 1.33299), (656.3, 1.33110)],
)
def test_pure_water_20c_handbook_values(wavelength_nm, expected):
    assert refractive_index_water(wavelength_nm, 20.0, 0.0) == pytest.approx(expected, abs=2e-4)


def test_hand_computed_quan_fry_589nm_20c():
    # n0 + n4 T^2 + (n5 + n7 T)/l + n8/l^2 + n9/l^3 at l = 589, T = 20, S = 0
    lam, t = 589.0, 20.0
    hand = 1.31405 - 2.02e-6 * t**2 + (15.868 - 0.00423 * t) / lam - 4382.0 / lam**2 + 1.1455e6 / lam**3
    assert refractive_index_water(lam, t, 0.0) == pytest.approx(hand, abs=1e-12)
    assert hand == pytest.approx(1.33301, abs=2e-5)


def test_paper_example_600nm():
    # Larouche et al. 2024 (Table 2 text) use n_w = 1.3317 at 600 nm, 25 C
    # from Hale and Querry (1973); Quan and Fry give 1.3322.  The two data
    # sets differ by ~5e-4 here.
    assert refractive_index_water(600.0, 25.0, 0.0) == pytest.approx(1.3317, abs=6e-4)


def test_salinity_increment_35psu():
    # Seawater of 35 PSU is about 0.0064 above pure water at 589 nm, 20 C
    # (Austin and Halikas 1976 / Millard and Seaver 1990).
    d = refractive_index_water(589.3, 20.0, 35.0) - refractive_index_water(589.3, 20.0, 0.0)
    assert d == pytest.approx(0.0064, abs=2e-4)


def test_dispersion_and_temperature_trends_and_broadcasting():
    wl = np.arange(400.0, 701.0, 10.0)
    n = refractive_index_water(wl, 20.0, 0.0)
    assert np.all(np.diff(n) < 0)  # normal dispersion
    nt = refractive_index_water(550.0, np.array([5.0, 15.0, 25.0]), 0.0)
    assert np.all(np.diff(nt) < 0)
    grid = refractive_index_water(wl[:, None], np.array([0.0, 25.0])[None, :], 35.0)
    assert grid.shape == (wl.size, 2)


def test_air_index():
    assert refractive_index_air() == 1.0
    assert np.all(refractive_index_air(np.array([400.0, 500.0])) == 1.0)


def test_normal_incidence_air_glass():
    # ((1.5 - 1) / 2.5)^2 = 0.04
    assert fresnel_reflectance_normal(1.0, 1.5) == pytest.approx(0.04, abs=1e-15)
    assert fresnel_transmittance_normal(1.0, 1.5) == pytest.approx(0.96, abs=1e-15)
    assert fresnel_reflectance(1.0, 1.5, 0.0) == pytest.approx(0.04, abs=1e-15)


def test_brewster_angle_unpolarised():
    # At Brewster's angle R_p = 0 and R_s = ((n^2 - 1)/(n^2 + 1))^2, so R = R_s / 2.
    n = 1.5
    theta_b = np.rad2deg(np.arctan(n))
    rs = ((n**2 - 1) / (n**2 + 1)) ** 2
    assert fresnel_reflectance(1.0, n, theta_b) == pytest.approx(rs / 2, rel=1e-12)


def test_grazing_and_total_internal_reflection():
    assert fresnel_reflectance(1.0, 1.33, 90.0) == pytest.approx(1.0, abs=1e-12)
    crit = np.rad2deg(np.arcsin(1.0 / 1.33))
    assert fresnel_reflectance(1.33, 1.0, crit + 1.0) == 1.0
    assert fresnel_transmittance(1.33, 1.0, 60.0) == 0.0
    assert fresnel_reflectance(1.33, 1.0, crit - 5.0) < 1.0
    assert np.isnan(refraction_angle_deg(1.33, 1.0, 60.0))


def test_reciprocity_of_transmittance():
    # Stokes relations: T(n1 -> n2, i) = T(n2 -> n1, t) for each polarisation,
    # hence for unpolarised light.
    i = np.linspace(0.0, 80.0, 17)
    t = refraction_angle_deg(1.0, 1.34, i)
    assert np.allclose(fresnel_transmittance(1.0, 1.34, i), fresnel_transmittance(1.34, 1.0, t), atol=1e-12)


def test_t_aw_paper_value():
    # Paper: t_aw = 0.9797 at 600 nm (with n_w = 1.3317); hand: 1 - (0.3317/2.3317)^2 = 0.97976.
    assert fresnel_transmittance_normal(1.0, 1.3317) == pytest.approx(1 - (0.3317 / 2.3317) ** 2, rel=1e-14)
    assert fresnel_transmittance_normal(1.0, 1.3317) == pytest.approx(0.9797, abs=1e-4)
    assert transmittance_air_water(600.0) == pytest.approx(0.9797, abs=2e-4)

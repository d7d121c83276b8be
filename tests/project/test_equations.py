"""One function per equation of Larouche et al. (2024), each against a value worked by hand or printed in the paper.

The table "Equations and the functions that implement them" of docs/equations.md lists
the same functions; the stages call these and keep no second copy.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.geometry.scaramuzza import FisheyeModel, field_angle_rad
from pipeline.radiometry import absolute, exposure
from pipeline.radiometry.absolute import absolute_calibration_budget, inverse_responsivity
from pipeline.radiometry.exposure import dn_per_second, exposure_gain_s, gain_from_iso
from pipeline.radiometry.fresnel import transmittance_air_water
from pipeline.radiometry.immersion import n_squared_law_factor
from pipeline.radiometry.rolloff import evaluate_rolloff, rolloff_design_matrix, rolloff_slope
from pipeline.radiometry.spectral import (
    band_statistics,
    band_weights,
    bandwidth,
    effective_band_radiance,
    effective_wavelength,
    peak_normalise_response,
)
from pipeline.radiometry.water import refractive_index_water


# ----------------------------------------------------------------------------- Eq. (2)
def test_gain_is_iso_over_100():
    # "0.01 scaling S_ISO relative to x1 instead of x100" (Section 2.1)
    assert gain_from_iso(100) == 1.0
    assert np.array_equal(gain_from_iso(np.array([200.0, 400.0, 3200.0])), [2.0, 4.0, 32.0])
    assert list(gain_from_iso(pd.Series([100.0, 800.0]))) == [1.0, 8.0]


def test_exposure_gain_product_table1_setting():
    # Table 1: 0.1 s at "ISO x 0.01 gain" 1.0 -> 0.1 s; 0.05 s at ISO 400 -> 0.2 s
    assert exposure_gain_s(0.1, 100.0) == pytest.approx(0.1, rel=1e-15)
    assert exposure_gain_s(0.05, 400.0) == pytest.approx(0.2, rel=1e-15)


def test_dn_per_second_hand_values_and_single_home():
    # (6900 - 800) ADU / (0.1 s * 1) = 61000 ADU/s, Table 1's red y_DN
    assert dn_per_second(6900.0, 800.0, 0.1, 100.0) == pytest.approx(61e3)
    # the same signal at ISO 200 and half the exposure: same y_DN
    assert dn_per_second(6900.0, 800.0, 0.05, 200.0) == pytest.approx(61e3)
    assert absolute.dn_per_second is exposure.dn_per_second


# ----------------------------------------------------------------------------- Eq. (3) and Eq. (8)
WL3 = np.array([500.0, 510.0, 520.0])


def test_band_weights_hand():
    # trapezoid weights on 500, 510, 520 nm: 5, 10, 5 nm; with S = (1, 1, 0): w S = (5, 10, 0) / 15
    k = band_weights(WL3, [1.0, 1.0, 0.0])
    assert np.allclose(k, [1 / 3, 2 / 3, 0.0], rtol=1e-15)
    assert np.allclose(np.sum(band_weights(WL3, np.array([[1.0, 0.5, 0.2], [0.1, 1.0, 0.3]])), axis=-1), 1.0)


def test_eq8_is_eq3_of_lambda_hand():
    s = np.array([1.0, 1.0, 0.0])
    # hand: (5 * 500 + 10 * 510) / 15 = 506.667 nm
    assert effective_wavelength(WL3, s) == pytest.approx(7600.0 / 15.0, rel=1e-14)
    assert effective_band_radiance(WL3, WL3, s) == effective_wavelength(WL3, s)
    # Eq. (3) of a spectrum 2, 4, 6 W sr-1 m-2 nm-1: (5 * 2 + 10 * 4) / 15 = 3.333
    assert effective_band_radiance(WL3, [2.0, 4.0, 6.0], s) == pytest.approx(50.0 / 15.0, rel=1e-14)
    # along another axis
    two = np.stack([s, s[::-1]], axis=0)
    assert np.allclose(effective_wavelength(WL3, two.T, axis=0), [7600.0 / 15.0, 2 * 510.0 - 7600.0 / 15.0])


def test_band_statistics_is_eq8_and_bandwidth():
    s = np.array([0.2, 1.0, 0.4])
    st = band_statistics(WL3, s)
    # hand: Lambda = 5 * 0.2 + 10 * 1 + 5 * 0.4 = 13 nm
    assert st["bandwidth_nm"] == pytest.approx(13.0, rel=1e-14) == bandwidth(WL3, s)
    assert st["effective_wavelength_nm"] == effective_wavelength(WL3, s)
    assert st["effective_wavelength_nm"] == pytest.approx((500 + 5100 + 1040) / 13.0, rel=1e-14)
    assert st["half_bandwidth_nm"] == pytest.approx(6.5)


def test_peak_normalisation_hand_with_an_unlit_wavelength():
    # r = dn / pd = (0, 10, 5), peak 10: S = (0, 1, 0.5); sigma_r = 1 each, u_p = 0.1.
    # var(S_0) = 1 / 100 + 0 = 0.01; var(S_2) = 1 / 100 + 0.25 * 0.01 = 0.0125;
    # cov(S_0, S_2) = S_0 S_2 u_p^2 = 0; the peak has zero uncertainty.
    s, sigma, cov = peak_normalise_response([0.0, 20.0, 10.0], [1.0, 2.0, 2.0], [1.0, 2.0, 2.0], 0.0,
                                            return_covariance=True)
    assert np.allclose(s, [0.0, 1.0, 0.5])
    assert np.allclose(sigma, [0.1, 0.0, np.sqrt(0.0125)])
    assert np.allclose(cov, np.diag([0.01, 0.0, 0.0125]))
    # photodiode uncertainty of 10 % on the 0.5 point alone adds (0.5 * 0.1)^2
    _, sigma2 = peak_normalise_response([0.0, 20.0, 10.0], [1.0, 2.0, 2.0], [1.0, 2.0, 2.0], [0.0, 0.0, 0.2])
    assert sigma2[2] == pytest.approx(np.sqrt(0.0125 + 0.05**2))


# ----------------------------------------------------------------------------- Eq. (9)
def test_budget_uses_eq9():
    wl = np.arange(400.0, 701.0, 10.0)
    flat = np.ones_like(wl)
    out = absolute_calibration_budget(wl, flat, np.ones_like(wl), 61e3, 1e3, reference_value=0.74e-3,
                                      reference_sigma=0.0, lamp_relative_sigma=None, extra_components={"a": 0.08, "b": 0.06})
    # flat source scaled to 0.74 mW: L = 0.74e-3, u_L = hypot(8 %, 6 %) = 10 %; R^-1 = 0.74e-3 / 61e3 = 1.2131e-8,
    # relative sigma hypot(0.10, 1 / 61) = 10.13 %
    assert out["inverse_responsivity"] == pytest.approx(1.2131e-8, rel=1e-4)
    assert out["relative_sigma"] == pytest.approx(np.hypot(0.1, 1 / 61), rel=1e-12)
    _, s = inverse_responsivity(0.74e-3, 61e3, 0.074e-3, 1e3)
    assert out["inverse_responsivity_sigma"] == pytest.approx(float(s), rel=1e-12)


# ----------------------------------------------------------------------------- Eq. (11), n-squared law
def test_n_squared_law_worked_example():
    # docs/design.md, "Immersion": 0.9797 x 1.3317^2 = 1.737 at 600 nm (Table 2); the printed t_aw n_w would be 1.305
    assert float(n_squared_law_factor(0.9797, 1.3317)) == pytest.approx(1.737, abs=5e-4)


def test_immersion_stage_normalises_by_eq2_and_uses_n_squared(monkeypatch):
    """A hand-made frame table through the immersion stage's analysis: exact I back.

    In-air frames at 0.1 s, ISO 100; in-water frames at 0.05 s, ISO 400 (twice
    the exposure-gain product), so a stage that skipped Eq. (2) would be off by 2.
    """
    from pipeline.stages import immersion

    water = {"temperature_c": 25.0, "salinity_psu": 0.0}
    lam = {"R": 600.0, "G": 540.0, "B": 480.0}
    true_i = {"R": 1.69, "G": 1.70, "B": 1.71}
    dn_air_per_s, k_per_cm = 5267.0, 0.03
    heights = np.arange(6.0, 11.01, 0.5)
    wiggle = np.array([1.0, -1.0, 0.5, -0.5, 0.0]) * 1e-3     # frame-to-frame scatter, mean ~ 0 in ln
    rows = []
    for band in "RGB":
        n2 = 0.9797 * 1.3317**2 if band == "R" else float(
            transmittance_air_water(lam[band], 25.0, 0.0) * refractive_index_water(lam[band], 25.0, 0.0) ** 2)
        for f in range(5):
            rows.append(dict(lens="far", band=band, condition="air", water_height_cm=0.0, n_mask=10,
                             dn=dn_air_per_s * 0.1 * (1 + wiggle[f]), exposure_s=0.1, iso=100.0))
        for z in heights:
            for f in range(5):
                y = dn_air_per_s * n2 / true_i[band] * np.exp(-k_per_cm * z) * (1 + wiggle[f])
                rows.append(dict(lens="far", band=band, condition="water", water_height_cm=z, n_mask=10,
                                 dn=y * 0.05 * 4.0, exposure_s=0.05, iso=400.0))
    # the red band at the paper's worked example: t_aw = 0.9797, n_w = 1.3317 (Table 2, 600 nm)
    monkeypatch.setattr(immersion, "transmittance_air_water",
                        lambda wl, t, s: 0.9797 if wl == 600.0 else transmittance_air_water(wl, t, s))
    monkeypatch.setattr(immersion, "refractive_index_water",
                        lambda wl, t, s: 1.3317 if wl == 600.0 else refractive_index_water(wl, t, s))
    art = immersion.analyse_immersion({"frames": pd.DataFrame(rows)}, water, lam)["far"]
    assert float(art["n2_factor"].sel(band="R")) == pytest.approx(1.737, abs=5e-4)   # Larouche et al. 2024, Table 2
    assert np.allclose(art["n2_factor"], art["t_aw"] * art["n_w"] ** 2, rtol=1e-15)
    assert np.allclose(art["dn_air"], dn_air_per_s, rtol=1e-6)
    assert np.allclose(art["immersion_factor"], [true_i[b] for b in art["band"].values], rtol=1e-5)


# ----------------------------------------------------------------------------- Eq. (13)
def test_rolloff_design_matrix_hand_and_shapes():
    # theta = 45 deg, scale 90 deg: u = 0.5 -> 1, 0.25, 0.0625, 0.015625, 0.00390625
    assert np.allclose(rolloff_design_matrix(45.0, 90.0), [1.0, 0.25, 0.0625, 0.015625, 0.00390625], rtol=1e-15)
    assert rolloff_design_matrix([10.0, 20.0, 30.0]).shape == (3, 5)
    assert rolloff_design_matrix(np.zeros((2, 4))).shape == (2, 4, 5)
    # the paper's red, close lens, air: 0.99726 - 7.806e-5 * 80^2 + ... = 0.5769 (Section 3.3: 0.577)
    a = np.array([0.99726, -7.806e-5, 4.074e-9, -4.884e-13, 2.406e-17])
    assert float(rolloff_design_matrix(80.0) @ a) == pytest.approx(0.5769, abs=1e-4)
    assert evaluate_rolloff(a, 80.0) == float(rolloff_design_matrix(80.0) @ a)


def test_rolloff_slope_hand():
    # g = 1 - 1e-4 theta^2 + 1e-8 theta^4: g' = -2e-4 theta + 4e-8 theta^3; at 10 deg -1.96e-3 per deg
    c = [1.0, -1e-4, 1e-8, 0.0, 0.0]
    assert rolloff_slope(c, 10.0) == pytest.approx(-1.96e-3, rel=1e-12)
    assert rolloff_slope(c, 0.0) == 0.0
    assert np.allclose(rolloff_slope(c, np.array([-10.0, 10.0])), [1.96e-3, -1.96e-3])


def test_rolloff_stage_columns_are_the_design_matrix():
    from pipeline.stages import rolloff as stage

    cols = stage._poly_columns(np.array([45.0, 90.0]))
    assert list(cols) == ["x_p0", "x_p2", "x_p4", "x_p6", "x_p8"]
    assert np.allclose(np.column_stack(list(cols.values())), rolloff_design_matrix([45.0, 90.0], stage.THETA_SCALE_DEG))
    assert np.allclose(cols["x_p4"], [0.0625, 1.0])


# ----------------------------------------------------------------------------- Eq. (5)-(7)
def test_field_angle_of_rays_eq7_hand():
    rays = np.array([[1.0, 0.0, 1.0], [0.0, 3.0, 0.0], [0.0, 0.0, -2.0], [3.0, 4.0, 5.0]])
    # 45, 90, 180 and atan(5 / 5) = 45 degrees
    assert np.allclose(np.degrees(field_angle_rad(rays)), [45.0, 90.0, 180.0, 45.0])


def test_theta_phi_is_eq7_of_eq6():
    # f(rho) = 100 - 1e-3 rho^2 (Eq. 5), centre (50, 40), no stretch: pixel (80, 80) is at
    # (x', y') = (30, 40), rho = 50, f = 97.5; tan(theta) = 50 / 97.5 (Eq. 7) -> 27.150 deg
    m = FisheyeModel((100.0, 0.0, -1e-3), 50.0, 40.0, shape=(100, 100))
    theta, phi = m.theta_phi(80.0, 80.0)
    assert float(theta) == pytest.approx(np.degrees(np.arctan(50.0 / 97.5)), rel=1e-14)
    assert float(phi) == pytest.approx(np.degrees(np.arctan2(40.0, 30.0)), rel=1e-14)
    # with a stretch [[c, d], [e, 1]] = [[1.1, 0.1], [0.1, 1]]: [u - xc, v - yc] = A [x', y'] (Eq. 6)
    s = FisheyeModel((100.0, 0.0, -1e-3), 50.0, 40.0, 1.1, 0.1, 0.1, shape=(100, 100))
    u = 50.0 + 1.1 * 30.0 + 0.1 * 40.0
    v = 40.0 + 0.1 * 30.0 + 40.0
    assert float(s.theta_phi(u, v)[0]) == pytest.approx(float(theta), rel=1e-12)
    uu, vv = s.world2cam(np.array([30.0, 40.0, 97.5]))
    assert (float(uu), float(vv)) == pytest.approx((u, v), rel=1e-9)


# ----------------------------------------------------------------------------- Eq. (12)
def test_mupd_eq12_hand():
    from pipeline.stats.matchup import mupd

    # pairs (reference, camera) (1, 3) and (2, 2): 2 * 100 / 2 * (|1 - 3| / 4 + 0) = 50 %
    assert mupd(np.array([3.0, 2.0]), np.array([1.0, 2.0])) == pytest.approx(50.0)

"""Tests of pipeline.radiometry.immersion against Larouche et al. (2024) Table 2 and round trips."""

import numpy as np
import pytest
from scipy import stats

from pipeline.radiometry.immersion import (
    fit_immersion_factor,
    fit_log_linear_attenuation,
    immersion_factor_flat_window,
    immersion_factor_from_intercept,
    in_water_dn,
    n_squared_law_factor,
    n_squared_law_factor_at,
    window_index_from_immersion_factor,
)
from pipeline.radiometry.water import refractive_index_water

LAMBDA_EFF_NM = np.array([600.0, 540.0, 480.0])  # R, G, B
TABLE2_N2 = np.array([1.738, 1.742, 1.748])
TABLE2_DN_AIR = np.array([5267.0, 8259.0, 3737.0])
TABLE2_DN_AIR_SIGMA = np.array([68.0, 90.0, 60.0])
TABLE2_DN_BELOW_OVER_N2 = np.array([3111.0, 4877.0, 2191.0])
TABLE2_DN_BELOW_OVER_N2_SIGMA = np.array([12.0, 26.0, 12.0])
TABLE2_I = np.array([1.69, 1.69, 1.71])
TABLE2_I_SIGMA = np.array([0.02, 0.02, 0.03])
PAPER_NG = np.array([1.60, 1.63, 1.58])
# water heights of the experiment: 6 to 11 cm by 0.5 cm, 5 frames each
HEIGHTS_CM = np.repeat(np.arange(6.0, 11.0 + 1e-9, 0.5), 5)


def test_n_squared_law_worked_example():
    # 0.9797 * 1.3317^2 = 1.73742 (paper: 1.737)
    assert n_squared_law_factor(0.9797, 1.3317) == pytest.approx(0.9797 * 1.3317**2, rel=1e-15)
    assert n_squared_law_factor(0.9797, 1.3317) == pytest.approx(1.737, abs=5e-4)


def test_n_squared_law_against_table2():
    # Quan and Fry indices versus the paper's Hale and Querry: within 0.003.
    got = n_squared_law_factor_at(LAMBDA_EFF_NM, 25.0, 0.0)
    assert np.allclose(got, TABLE2_N2, atol=0.003)


def test_table2_immersion_factor_and_uncertainty():
    # Column 4 of Table 2 is y(0-) already divided by t_aw n_w^2, so n2 = 1.
    i, s = immersion_factor_from_intercept(
        TABLE2_DN_AIR, TABLE2_DN_AIR_SIGMA, TABLE2_DN_BELOW_OVER_N2, TABLE2_DN_BELOW_OVER_N2_SIGMA, 1.0
    )
    # hand: 5267/3111 = 1.6930, 8259/4877 = 1.6935, 3737/2191 = 1.7056
    assert np.allclose(i, [1.6930, 1.6935, 1.7056], atol=1e-4)
    assert np.allclose(i, TABLE2_I, atol=0.005 + 1e-9)  # published to 2 decimals
    assert np.allclose(s, TABLE2_I_SIGMA, atol=0.005)


def test_eq10_forward_reproduces_table2_from_paper_ng():
    # The paper's n_g (1.60, 1.63, 1.58) with n_w at lambda_eff, 25 C, must
    # give back its I (1.69, 1.69, 1.71); the paper rounds to 0.01.
    n_w = refractive_index_water(LAMBDA_EFF_NM, 25.0, 0.0)
    assert np.allclose(immersion_factor_flat_window(n_w, PAPER_NG), TABLE2_I, atol=0.006)
    # hand value, red: 1.3322 * 2.9322^2 / 2.6^2 = 1.6944
    assert immersion_factor_flat_window(1.3322, 1.60) == pytest.approx(1.6944, abs=1e-4)


def test_eq10_limits():
    # n_g = 1: I = n_w (n_w + 1)^2 / 4 (= n_w^2 / t_aw, the bare n-squared law);
    # n_g -> infinity: I -> n_w.
    assert immersion_factor_flat_window(1.34, 1.0) == pytest.approx(1.34 * 2.34**2 / 4)
    assert immersion_factor_flat_window(1.34, 1.0) == pytest.approx(1.34**2 / (4 * 1.34 / 2.34**2))
    assert immersion_factor_flat_window(1.34, 1e9) == pytest.approx(1.34, rel=1e-8)


def test_eq10_inverse_round_trip_and_paper():
    n_w = 1.334
    n_g = np.linspace(1.35, 2.2, 30)
    back = window_index_from_immersion_factor(immersion_factor_flat_window(n_w, n_g), n_w)
    assert np.allclose(back, n_g, rtol=1e-12)
    # Paper's I rounded to 0.01: dn_g/dI ~ 7 here, so rounding alone moves
    # n_g by up to ~0.035; allow 0.05.
    n_wl = refractive_index_water(LAMBDA_EFF_NM, 25.0, 0.0)
    assert np.allclose(window_index_from_immersion_factor(TABLE2_I, n_wl), PAPER_NG, atol=0.05)
    assert np.isnan(window_index_from_immersion_factor(1.2, 1.334))  # I < n_w: no solution


def test_eq10_inverse_uncertainty_matches_numerical_derivative():
    n_w, i0, h = 1.3322, 1.693, 1e-6
    ng, s = window_index_from_immersion_factor(i0, n_w, immersion_factor_sigma=0.02)
    num = (window_index_from_immersion_factor(i0 + h, n_w) - window_index_from_immersion_factor(i0 - h, n_w)) / (2 * h)
    assert s == pytest.approx(abs(num) * 0.02, rel=1e-5)


def test_log_linear_fit_matches_scipy_linregress():
    rng = np.random.default_rng(3)
    dn = 3000 * np.exp(-0.004 * HEIGHTS_CM) * np.exp(0.01 * rng.standard_normal(HEIGHTS_CM.size))
    fit = fit_log_linear_attenuation(HEIGHTS_CM, dn)
    ref = stats.linregress(HEIGHTS_CM, np.log(dn))
    assert fit["intercept"] == pytest.approx(ref.intercept, rel=1e-12)
    assert fit["intercept_se"] == pytest.approx(ref.intercept_stderr, rel=1e-10)
    assert fit["slope_per_cm"] == pytest.approx(-ref.slope, rel=1e-12)
    assert fit["r_squared"] == pytest.approx(ref.rvalue**2, rel=1e-10)


def test_forward_then_fit_noise_free_recovers_truth():
    n2, i_true, att = 1.7387, 1.69, 35.0  # att in m^-1, deliberately large
    dn = in_water_dn(5267.0, HEIGHTS_CM, att, n2, i_true)
    # hand: at z = 10 cm, 5267 * 1.7387 / 1.69 * exp(-3.5)
    assert in_water_dn(5267.0, 10.0, att, n2, i_true) == pytest.approx(5267 * 1.7387 / 1.69 * np.exp(-3.5))
    fit = fit_immersion_factor(HEIGHTS_CM, dn, 5267.0, n2, dn_air_sigma=1e-9)
    assert fit.immersion_factor == pytest.approx(i_true, rel=1e-10)
    assert fit.attenuation_per_cm == pytest.approx(att / 100.0, rel=1e-10)


def test_forward_then_fit_with_noise_and_ci_coverage():
    # 1 % multiplicative noise per frame, 10 in-air frames with 1 % noise.
    # Each fit must land within 4 sigma; over 400 seeds the 95 % interval
    # must cover the truth in 95 % of cases (binomial sd ~1.1 %: accept 91-99 %).
    n2, i_true, att = 1.7437, 1.69, 0.06
    clean = in_water_dn(8259.0, HEIGHTS_CM, att, n2, i_true)
    rng = np.random.default_rng(12345)
    hits = 0
    n_seeds = 400
    for _ in range(n_seeds):
        dn = clean * (1 + 0.01 * rng.standard_normal(clean.size))
        air = 8259.0 * (1 + 0.01 * rng.standard_normal(10))
        fit = fit_immersion_factor(HEIGHTS_CM, dn, air, n2)
        assert abs(fit.immersion_factor - i_true) < 4.5 * fit.immersion_factor_sigma
        lo, hi = fit.immersion_factor_ci95
        hits += lo <= i_true <= hi
        assert fit.dn_below_ci95[0] < fit.dn_below < fit.dn_below_ci95[1]
    assert 0.91 <= hits / n_seeds <= 0.99


def test_fit_input_validation():
    with pytest.raises(ValueError):
        fit_immersion_factor(HEIGHTS_CM, np.ones_like(HEIGHTS_CM), 1.0, 1.7)  # scalar air needs sigma
    with pytest.raises(ValueError):
        fit_log_linear_attenuation([1.0, 1.0, 1.0], [1.0, 2.0, 3.0])

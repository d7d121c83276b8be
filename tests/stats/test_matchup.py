"""The match-up statistics on hand-computable cases (pipeline.stats.matchup)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.stats import matchup as mu


def test_proportional_camera_gives_the_hand_values():
    x = np.array([0.01, 0.02, 0.05, 0.1, 0.12])
    y = 1.1 * x
    # |x - y| / (x + y) = 0.1 / 2.1 for every pair
    assert mu.mupd(y, x) == pytest.approx(2 * 100 * 0.1 / 2.1, rel=1e-12)
    assert mu.median_symmetric_accuracy(y, x) == pytest.approx(10.0, rel=1e-12)
    assert mu.signed_symmetric_bias(y, x) == pytest.approx(10.0, rel=1e-12)
    assert mu.signed_symmetric_bias(x, y) == pytest.approx(-10.0, rel=1e-12)
    assert mu.rmse_one_to_one(y, x) == pytest.approx(np.sqrt(np.mean((0.1 * x) ** 2)), rel=1e-12)
    assert mu.rmse_about_fit(y, x) == pytest.approx(0.0, abs=1e-15)
    assert mu.pearson_r(y, x) == pytest.approx(1.0, abs=1e-12)
    ols = mu.ols_fit(y, x)
    assert ols["slope"] == pytest.approx(1.1, rel=1e-10)
    assert ols["intercept"] == pytest.approx(0.0, abs=1e-12)


def test_symmetric_errors_have_no_bias_and_the_median_accuracy():
    x = np.ones(4)
    y = np.array([1.2, 1 / 1.2, 1.05, 1 / 1.05])
    # |ln(y/x)| = ln 1.2, ln 1.2, ln 1.05, ln 1.05: median (ln 1.2 + ln 1.05) / 2
    assert mu.median_symmetric_accuracy(y, x) == pytest.approx(100 * (np.sqrt(1.2 * 1.05) - 1), rel=1e-12)
    # ln(y/x) symmetric about 0: median 0, no bias
    assert mu.signed_symmetric_bias(y, x) == pytest.approx(0.0, abs=1e-12)
    # swapping camera and reference leaves MUPD and zeta unchanged (symmetric metrics)
    assert mu.mupd(y, x) == pytest.approx(mu.mupd(x, y))
    assert mu.median_symmetric_accuracy(y, x) == pytest.approx(mu.median_symmetric_accuracy(x, y))
    expected = 2 * 100 * np.mean(np.abs(y - 1) / (y + 1))
    assert mu.mupd(y, x) == pytest.approx(expected, rel=1e-12)


def test_rmse_about_the_fit_and_one_to_one_differ_for_an_offset_line():
    x = np.array([1.0, 2.0, 3.0, 4.0])
    y = x + 0.5 + np.array([0.1, -0.1, -0.1, 0.1])
    # about the 1:1 line: residuals 0.6, 0.4, 0.4, 0.6
    assert mu.rmse_one_to_one(y, x) == pytest.approx(np.sqrt((0.36 + 0.16 + 0.16 + 0.36) / 4))
    # the OLS line of this y is y = x + 0.5 (the pattern is orthogonal to 1 and x): residuals +-0.1
    assert mu.rmse_about_fit(y, x) == pytest.approx(0.1, rel=1e-10)


def _synthetic(n, rng):
    x = rng.uniform(0.01, 0.12, n)
    return x * np.exp(rng.normal(0.0, 0.1, n)), x


def test_bootstrap_interval_contains_the_estimate_and_shrinks_as_one_over_root_n():
    rng = np.random.default_rng(20261201)
    widths = {}
    for n in (100, 400):
        y, x = _synthetic(n, rng)
        est = mu.mupd(y, x)
        lo, hi = mu.bootstrap_interval(mu.mupd, y, x, 0.95, 2000, seed=3)
        assert lo < est < hi
        widths[n] = hi - lo
    # width ~ sd / sqrt(N): ratio 2 for 4 times the match-ups. The ratio's own scatter: the sample sd of
    # |d|/(x+y) at N = 100 varies by ~7 %, the 2.5/97.5 % percentiles of 2000 resamples by ~3.5 %,
    # so the ratio is 2 within about 9 % (1 sigma); 3 sigma gives the bounds
    assert 2 * (1 - 0.27) < widths[100] / widths[400] < 2 * (1 + 0.27)


def test_bootstrap_is_paired_and_reproducible():
    rng = np.random.default_rng(7)
    y, x = _synthetic(50, rng)
    a = mu.bootstrap_interval(mu.signed_symmetric_bias, y, x, 0.9, 500, seed=1)
    b = mu.bootstrap_interval(mu.signed_symmetric_bias, y, x, 0.9, 500, seed=1)
    assert a == b
    # y = 1.1 x exactly: every paired resample has SSPB 10 %; an unpaired one would not
    lo, hi = mu.bootstrap_interval(mu.signed_symmetric_bias, 1.1 * x, x, 0.95, 500, seed=1)
    assert lo == pytest.approx(10.0) and hi == pytest.approx(10.0)


def test_ols_interval_is_student_t_at_the_level():
    rng = np.random.default_rng(11)
    x = np.linspace(0.0, 1.0, 30)
    y = 2.0 * x + 0.3 + rng.normal(0, 0.05, x.size)
    fit95 = mu.ols_fit(y, x, 0.95)
    fit68 = mu.ols_fit(y, x, 0.68)
    from scipy import stats
    t95 = stats.t.ppf(0.975, 28)
    assert fit95["slope_high"] - fit95["slope"] == pytest.approx(t95 * fit95["slope_se"])
    assert fit68["slope_high"] - fit68["slope_low"] < fit95["slope_high"] - fit95["slope_low"]
    # the slope's standard error for noise 0.05 on 30 evenly spaced x in [0, 1]: 0.05 / sqrt(sum (x - xbar)^2)
    expected_se = 0.05 / np.sqrt(np.sum((x - x.mean()) ** 2))
    assert fit95["slope_se"] == pytest.approx(expected_se, rel=0.3)
    assert abs(fit95["slope"] - 2.0) < 4 * expected_se


def test_odr_recovers_the_slope_with_errors_in_both():
    rng = np.random.default_rng(5)
    n, slope, intercept = 200, 1.3, 0.002
    x_true = rng.uniform(0.01, 0.12, n)
    sx, sy = 0.004, 0.005
    x = x_true + rng.normal(0, sx, n)
    y = slope * x_true + intercept + rng.normal(0, sy, n)
    fit = mu.odr_fit(y, x, np.full(n, sy), np.full(n, sx))
    # slope error of a straight-line fit with errors in both: var = (sy^2 + b^2 sx^2) / (N var(x_true))
    se = np.sqrt((sy**2 + slope**2 * sx**2) / (n * np.var(x_true)))
    assert abs(fit["slope"] - slope) < 4 * se
    assert fit["slope_se"] == pytest.approx(se, rel=0.3)
    # OLS is biased low by the attenuation factor var(x) / (var(x) + sx^2) (regression dilution)
    ols = mu.ols_fit(y, x)
    attenuation = np.var(x_true) / (np.var(x_true) + sx**2)
    assert ols["slope"] == pytest.approx(slope * attenuation, abs=4 * se)
    assert ols["slope"] < fit["slope"]


def test_matchup_statistics_names_and_small_samples():
    x = np.array([0.02, 0.04, 0.06, 0.08])
    y = 1.1 * x
    out = mu.matchup_statistics(y, x, 0.01 * y, 0.01 * x, n_resamples=200)
    for name in mu.BOOTSTRAPPED:
        assert {name, f"{name}_low", f"{name}_high"} <= set(out)
    assert out["n"] == 4
    assert out["odr_slope"] == pytest.approx(1.1, rel=1e-6)
    few = mu.matchup_statistics(y[:2], x[:2], 0.01, 0.01)
    assert few["n"] == 2 and np.isnan(few["mupd"]) and np.isnan(few["odr_slope"])

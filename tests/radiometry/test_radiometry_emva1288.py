"""pipeline.radiometry.emva1288 against independent references: the published figures of the EMVA1288 Reference
Set 001 (their own inputs give their own outputs), the closed-form normal equations of the linearity fit, and stacks
drawn with known spatial non-uniformities."""

from __future__ import annotations

import numpy as np

from pipeline.radiometry import emva1288 as emva

#: the reference implementation's published figures for the EMVA1288 Reference Set 001 (its documentation,
#: datasets_results.rst): K, sigma_y,dark, mu_e,sat, and what follows from them
K_DN_PER_E = 0.280769
DARK_NOISE_DN = 3.07342
CAPACITY_E = 13972.6
DYNAMIC_RANGE = 1220.7
SNR_MAX = 118.2
#: the published figures have four or five digits: they agree with the formulas within half their last digit
PUBLISHED_ROUNDING = 1e-4


def test_dynamic_range_and_snr_max_give_the_published_figures():
    """DR = mu_e,sat / (sigma_y,dark / K + 1/2) and SNR_max = sqrt(mu_e,sat) from the published K, dark noise and
    saturation capacity give the published 1220.7 (61.7 dB) and 118.2."""
    dr = emva.dynamic_range(CAPACITY_E, DARK_NOISE_DN, K_DN_PER_E)
    assert abs(dr / DYNAMIC_RANGE - 1) < PUBLISHED_ROUNDING, dr
    assert round(emva.decibels(dr)) == 62
    assert abs(emva.snr_max(CAPACITY_E) / SNR_MAX - 1) < 5e-4   # 118.2 has four digits
    assert emva.saturation_capacity_e(K_DN_PER_E * CAPACITY_E, K_DN_PER_E) == CAPACITY_E


def test_linearity_error_is_the_relative_least_squares_line():
    """On a bent response (y = x (1 - 0.05 x / x_max) plus 0.3 % noise) the fitted line is the one of the closed-form
    normal equations of sum(((y - a x - b) / y)^2), written out here term by term, the deviations are relative to
    it in per cent, and only the points from 5 to 95 % of the saturation signal enter the fit and the extremes."""
    rng = np.random.default_rng(1)
    x = np.linspace(10, 1000, 50)
    y = x * (1 - 0.05 * x / x.max()) * (1 + 0.003 * rng.standard_normal(x.size))
    sat = y[-3]
    out = emva.linearity_error(x, y, sat)
    keep = (y >= 0.05 * sat) & (y <= 0.95 * sat)
    np.testing.assert_array_equal(out.in_range, keep)
    xs, ys = x[keep], y[keep]
    sxy, sxy2, sx2y2 = np.sum(xs / ys), np.sum(xs / ys**2), np.sum((xs / ys) ** 2)
    s1y, s1y2 = np.sum(1 / ys), np.sum(1 / ys**2)
    b = (sxy * sxy2 - sx2y2 * s1y) / (sxy2**2 - sx2y2 * s1y2)
    a = (sxy - b * sxy2) / sx2y2
    np.testing.assert_allclose([out.slope, out.offset_dn], [a, b], rtol=1e-9)
    dev = 100 * (y - (a * x + b)) / (a * x + b)
    np.testing.assert_allclose(out.deviation_pct, dev, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose([out.min_pct, out.max_pct], [dev[keep].min(), dev[keep].max()], rtol=1e-9)


def test_responsivity_is_the_slope_through_the_origin_to_70_percent():
    """A response of 0.2 DN per photon with an offset-free 0.1 % scatter gives 0.2 within 5 of its stated errors,
    the points above 70 % of saturation (clipped flat here) left out."""
    rng = np.random.default_rng(2)
    photons = np.linspace(100, 20000, 40)
    signal = 0.2 * photons * (1 + 0.001 * rng.standard_normal(photons.size))
    sat = 0.8 * signal.max()
    below = signal <= 0.7 * sat
    signal = np.minimum(signal, sat)
    r, se, n = emva.responsivity(photons, signal, sat)
    assert n == int(below.sum())
    assert abs(r - 0.2) < 5 * se, (r, se)


def test_spatial_nonuniformity_recovers_the_drawn_dsnu_and_prnu():
    """Stacks of 50 frames over 40,000 pixels with a dark offset pattern of 0.5 DN, a response pattern of 1 % on a
    1000 DN signal and 3 DN of temporal noise: DSNU1288 and PRNU1288 recover 0.5 DN and 1 %. The tolerance: the
    spatial variance of the mean image (0.25 + 9 / 50 DN^2) is known to sqrt(2 / 40,000) of itself, 0.6 % of the
    DSNU after the temporal part is taken off (1.1 % for the PRNU, whose excess variance holds the shot noise of
    10,000 DN^2 / 50); 5 times that."""
    rng = np.random.default_rng(3)
    n_pixels, n_frames, noise = 40_000, 50, 3.0
    offset = 20 + 0.5 * rng.standard_normal(n_pixels)
    gain = 1 + 0.01 * rng.standard_normal(n_pixels)
    dark = offset + noise * rng.standard_normal((n_frames, n_pixels))
    bright = offset + 1000 * gain + noise * rng.standard_normal((n_frames, n_pixels))
    out = emva.spatial_nonuniformity(bright.mean(0), bright.var(0, ddof=1), n_frames,
                                     dark.mean(0), dark.var(0, ddof=1), n_frames)
    drawn_dsnu, drawn_prnu = offset.std(ddof=1), 100 * gain.std(ddof=1) * 1000 / (1000 * gain.mean())
    assert abs(out.dsnu_dn / drawn_dsnu - 1) < 5 * 0.006, (out.dsnu_dn, drawn_dsnu)
    assert abs(out.prnu_pct / drawn_prnu - 1) < 5 * 0.011, (out.prnu_pct, drawn_prnu)

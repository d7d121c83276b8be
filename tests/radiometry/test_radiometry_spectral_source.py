"""Tests of pipeline.radiometry.spectral and pipeline.radiometry.source, and of the
simulator's default response and source against the published values."""

import numpy as np
import pytest

from pipeline.radiometry.source import (
    planck_radiance,
    scale_to_reference,
)
from pipeline.radiometry.spectral import (
    band_statistics,
    bandwidth,
    effective_band_radiance,
    effective_wavelength,
    peak_normalise_response,
    trapezoid_weights,
)
from pipeline.simulate.absolute import default_source_radiance
from pipeline.simulate.camera_data import measured_response
from pipeline.simulate.spectral import default_spectral_response

GRID_NM = np.arange(400.0, 700.0 + 1e-9, 10.0)
# Larouche et al. 2024 Section 3.4: lambda_eff +/- Lambda/2
PUBLISHED_BANDS = {"R": (600.0, 38.0), "G": (540.0, 60.0), "B": (480.0, 49.0)}
PUBLISHED_PEAKS = {"R": 600.0, "G": 520.0, "B": 460.0}


def test_trapezoid_weights_match_numpy():
    x = np.array([400.0, 410.0, 430.0, 460.0])
    y = np.array([1.0, 3.0, -2.0, 5.0])
    assert np.sum(trapezoid_weights(x) * y) == pytest.approx(np.trapezoid(y, x), rel=1e-14)


def test_triangle_band_hand_computed():
    # Triangle of peak 1 at 550 nm, base 500-600: Lambda = 50 nm exactly with
    # the trapezoid rule on a grid containing the vertices; symmetric -> 550.
    s = np.clip(1 - np.abs(GRID_NM - 550.0) / 50.0, 0, None)
    assert bandwidth(GRID_NM, s) == pytest.approx(50.0, rel=1e-12)
    assert effective_wavelength(GRID_NM, s) == pytest.approx(550.0, rel=1e-12)


def test_right_triangle_effective_wavelength():
    # Samples s_k = k / 10 at 500 + 10 k (k = 0..10), zero elsewhere.  Hand:
    # Lambda = 10 * sum_{k=1..10} k / 10 = 55 nm;
    # int l s = sum_{k=1..10} 10 (500 + 10 k) k / 10 = 500 * 55 + 10 * 385 = 31350;
    # lambda_eff = 31350 / 55 = 570 nm.
    s = np.clip((GRID_NM - 500.0) / 100.0, 0, None) * (GRID_NM <= 600.0)
    assert bandwidth(GRID_NM, s) == pytest.approx(55.0, rel=1e-12)
    assert effective_wavelength(GRID_NM, s) == pytest.approx(570.0, rel=1e-12)


@pytest.mark.parametrize("lens", ["close", "far"])
def test_default_response_matches_published_bands(lens):
    """The simulator's true response on the monochromator's grid is the real camera's measured one: its
    statistics are those of the authors' own points within 0.5 nm (the far lens's 410 nm point is
    missing, the close lens's 610 and 620 nm: there the smooth interpolation stands in). The published
    bands (Section 3.4, PUBLISHED_BANDS) are within 4.5 nm of the close lens's (603.3 / 38.3, 544.4 / 64.6,
    483.6 / 50.5 nm); the far lens's lie 5 nm longer."""
    r = default_spectral_response(GRID_NM, lens)
    wl, measured, _ = measured_response(lens)
    for band, (lam_eff, half_bw) in PUBLISHED_BANDS.items():
        st = band_statistics(GRID_NM, r[band])
        own = band_statistics(wl, measured[band])
        assert st["effective_wavelength_nm"] == pytest.approx(own["effective_wavelength_nm"], abs=0.5), band
        assert st["half_bandwidth_nm"] == pytest.approx(own["half_bandwidth_nm"], abs=0.5), band
        if lens == "close":
            assert st["effective_wavelength_nm"] == pytest.approx(lam_eff, abs=4.5), band
            assert st["half_bandwidth_nm"] == pytest.approx(half_bw, abs=4.7), band
    far_minus_close = [band_statistics(GRID_NM, default_spectral_response(GRID_NM, "far")[b])["effective_wavelength_nm"]
                       - band_statistics(GRID_NM, default_spectral_response(GRID_NM, "close")[b])["effective_wavelength_nm"]
                       for b in "RGB"]
    assert all(4.5 < d < 6.0 for d in far_minus_close), far_minus_close


def test_default_response_is_zero_outside_the_measured_range():
    close = default_spectral_response(np.array([399.9, 400.0, 670.0, 670.1, 700.0]), "close")
    far = default_spectral_response(np.array([399.9, 700.0, 700.1]), "far")
    for band in "RGB":
        assert close[band][0] == 0.0 and close[band][3] == 0.0 and close[band][4] == 0.0
        assert close[band][1] > 0.0 and close[band][2] > 0.0
        assert far[band][0] == 0.0 and far[band][2] == 0.0 and far[band][1] > 0.0


def test_default_response_shape():
    fine = np.arange(380.0, 720.0 + 1e-9, 0.5)
    r = default_spectral_response(fine)
    for band, peak in PUBLISHED_PEAKS.items():
        assert r[band].max() == pytest.approx(1.0, abs=1e-4)
        assert abs(fine[np.argmax(r[band])] - peak) <= 8.0, band
        assert np.all(r[band] >= 0)
    # broad and overlapping: at 500 nm both B and G respond, at 580 nm both G and R
    at = default_spectral_response(np.array([500.0, 580.0]))
    assert at["B"][0] > 0.2 and at["G"][0] > 0.2
    assert at["G"][1] > 0.2 and at["R"][1] > 0.2


def test_peak_normalise_values_and_uncertainty():
    dn = np.array([100.0, 400.0, 250.0])
    pd = np.array([1.0, 2.0, 0.5])  # ratios 100, 200, 500 -> peak at index 2
    s, sig = peak_normalise_response(dn, pd, dn_sigma=0.01 * dn, photodiode_sigma=0.02 * pd)
    assert np.allclose(s, [0.2, 0.4, 1.0])
    u = np.hypot(0.01, 0.02)  # relative of every ratio
    assert sig[2] == 0.0
    assert np.allclose(sig[:2], s[:2] * np.sqrt(2) * u)


def test_peak_normalise_covariance_monte_carlo():
    # The covariance from peak_normalise_response against 20000 Monte Carlo
    # draws; the sample covariance has ~1 % relative noise at this size,
    # compare with 5 %.
    rng = np.random.default_rng(7)
    r = default_spectral_response(GRID_NM)["G"] * 1e4 + 50.0
    pd = np.full_like(r, 3.0)
    dn_sig = 0.01 * r
    s, sig, cov = peak_normalise_response(r, pd, dn_sig, 0.005 * pd, return_covariance=True)
    assert np.allclose(np.sqrt(np.diag(cov)), sig)
    draws = (r + dn_sig * rng.standard_normal((20000, r.size))) / (pd + 0.015 * rng.standard_normal((20000, r.size)))
    ip = np.argmax(r / pd)
    mc = draws / draws[:, ip : ip + 1]
    mc_cov = np.cov(mc, rowvar=False)
    big = np.abs(cov) > 1e-3 * cov.max()
    assert np.allclose(mc_cov[big], cov[big], rtol=0.05)
    # and the propagated band statistics
    st = band_statistics(GRID_NM, s, cov)
    mc_eff = [effective_wavelength(GRID_NM, m) for m in mc[:4000]]
    assert st["effective_wavelength_nm_sigma"] == pytest.approx(np.std(mc_eff), rel=0.1)
    mc_bw = bandwidth(GRID_NM, mc[:4000])
    assert st["bandwidth_nm_sigma"] == pytest.approx(np.std(mc_bw), rel=0.1)


def test_effective_band_radiance_linear_spectrum():
    # For L = a + b lambda, Eq. (3) gives exactly a + b lambda_eff.
    s = default_spectral_response(GRID_NM)["B"]
    lam_eff = effective_wavelength(GRID_NM, s)
    assert effective_band_radiance(GRID_NM, 2.0 + 0.01 * GRID_NM, s) == pytest.approx(2.0 + 0.01 * lam_eff)


def test_effective_band_radiance_uncertainty_hand():
    wl = np.array([500.0, 510.0, 520.0])
    s = np.array([0.5, 1.0, 0.5])  # trapezoid weights 5, 10, 5 -> w*s = 2.5, 10, 2.5 -> k = 1/6, 2/3, 1/6
    L = np.array([1.0, 2.0, 3.0])
    l_eff, sig = effective_band_radiance(wl, L, s, radiance_sigma=np.array([0.6, 0.3, 0.6]))
    assert l_eff == pytest.approx(1 / 6 + 4 / 3 + 3 / 6)
    assert sig == pytest.approx(np.sqrt((0.1) ** 2 + (0.2) ** 2 + (0.1) ** 2))
    _, sig_c = effective_band_radiance(wl, L, s, radiance_sigma_correlated=0.05 * L)
    assert sig_c == pytest.approx(0.05 * l_eff)


def test_planck_wien_and_stefan_boltzmann():
    t = 2796.0
    fine = np.arange(800.0, 1300.0, 0.01)
    peak = fine[np.argmax(planck_radiance(fine, t))]
    assert peak == pytest.approx(2.897771955e6 / t, abs=0.02)  # Wien: b / T in nm
    wl = np.geomspace(50.0, 1e6, 200001)
    total = np.pi * np.trapezoid(planck_radiance(wl, t), wl)  # W m-2
    assert total == pytest.approx(5.670374419e-8 * t**4, rel=1e-4)


def test_planck_hand_value_589nm():
    # 2 h c^2 / l^5 / (exp(hc / l k T) - 1) * 1e-9 at 589 nm, 2796 K
    h, c, k = 6.62607015e-34, 299792458.0, 1.380649e-23
    lam = 589e-9
    hand = 2 * h * c**2 / lam**5 / np.expm1(h * c / (lam * k * 2796.0)) * 1e-9
    assert planck_radiance(589.0, 2796.0) == pytest.approx(hand, rel=1e-12)
    assert planck_radiance(589.0, 2796.0) == pytest.approx(269.9, abs=0.1)


def test_default_source_reference_and_band_radiances():
    assert default_source_radiance(589.0) == pytest.approx(6.8e-4, rel=1e-12)
    # Table 1: 0.74, 0.48, 0.26 mW sr-1 m-2 nm-1 (+/- 0.08, 0.05, 0.03). A pure 2796 K Planck curve
    # through the close lens's measured response lands within 6 % for R and G (+0.8, +4.7 %) and +12 %
    # for B, within Table 1's 11.5 % for B: the measured B keeps 0.08-0.12 of its peak from 540 to
    # 650 nm, where the lamp is 2-4 times brighter than at 480 nm.
    L = default_source_radiance(GRID_NM)
    r = default_spectral_response(GRID_NM)
    for band, ref, rel in zip("RGB", (0.74e-3, 0.48e-3, 0.26e-3), (0.06, 0.06, 0.13)):
        assert effective_band_radiance(GRID_NM, L, r[band]) == pytest.approx(ref, rel=rel), band


def test_scale_to_reference_interpolates_and_carries_uncertainty():
    wl = np.array([580.0, 590.0, 600.0])
    spec = np.array([10.0, 20.0, 30.0])  # linear: 19 at 589 nm
    out = scale_to_reference(wl, spec, 589.0, 0.68e-3, 0.02e-3)
    assert out["scale"] == pytest.approx(0.68e-3 / 19.0)
    assert out["radiance"][1] == pytest.approx(20.0 * 0.68e-3 / 19.0)
    assert out["relative_sigma_correlated"] == pytest.approx(2 / 68)
    out2 = scale_to_reference(wl, spec, 589.0, 0.68e-3, 0.02e-3, spectrum_sigma=np.array([0.1, 0.2, 0.3]))
    # interpolated noise: hypot(0.1 * 0.1, 0.9 * 0.2) / 19
    u_ref = np.hypot(0.1 * 0.1, 0.9 * 0.2) / 19.0
    assert out2["relative_sigma_correlated"] == pytest.approx(np.hypot(2 / 68, u_ref))
    with pytest.raises(ValueError):
        scale_to_reference(wl, spec, 700.0, 1.0, 0.1)

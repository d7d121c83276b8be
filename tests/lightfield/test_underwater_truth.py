"""The light field in water against the simulator's truth (issue 33, item 6).

The tiny camera that the session fixture ``calibrated`` calibrated (its bundle
has the immersion stage: media air and water) is put at 3 m under a flat
surface (:mod:`pipeline.simulate.underwater`: the refracted CIE sky and a soft
sun inside Snell's window with Fresnel transmission and the n-squared law, a
diffuse field exp(k (cos Z - 1)) over the sphere), tilted by up to 7 degrees
in roll and pitch with any heading, with an attitude log of stated noise (0.2,
0.2, 1.0 degree). One bracket per seed of five exposures 1/4000 s to 1 s;
``light_field_from_brackets(..., medium="water", attitude log)`` on a 9 degree
grid. The truth is the simulator's fine quadrature of the true radiance, never
the pipeline's code.

- The truth's quadrature against a closed form: with the beam attenuation so
  large that no refracted light is left, the field is C exp(k cos Z) and every
  quantity has a closed form (as tests/lightfield/test_lightfield.py's).
- The truth's refraction: just below the surface with no attenuation and no
  diffuse light, E_d equals the sky's Fresnel-transmitted irradiance
  integrated on the air side (the n-squared law and the solid angle's
  compression cancel).
- Over 20 seeds and 3 bands (60 values per quantity): every deviation of E_d,
  E_u, E_0, mu_d, mu_u and L_u within 3 of its stated sigma; the HDR map spans
  at least five decades.
- The HDR map of one bracket per band pixel (both lenses, the water chain)
  against the truth at the same pixels, as test_hdr_brackets.py in air: band
  scale within 3 of the stated R^-1 and immersion-factor sigma, z spread 0.6
  to 1.5 over at least five decades (measured, seed 0: 5.7 decades, k - 1 of
  -0.0004, 0.003, 0.008 against u = 0.026, spread 0.96 to 0.99).
- Unit spread of z = (pipeline - truth) / stated sigma: the root mean square
  of 60 values within the 99 % interval of sqrt(chi2_60 / 60), 0.74 to 1.30.
  NOT MET (strict xfail). Measured over the 20 seeds, with the band between
  the lenses filled in ln L (pipeline.lightfield.fill): rms z 1.07 (E_d),
  0.030 (E_u), 0.53 (E_0), 0.29 (mu_d), 0.004 (mu_u), 0.14 (L_u); with the
  earlier linear fill in L and its bound-like sigma: 0.066, 0.001, 0.006,
  0.007, 0.002, 0.16. Without the fill sigma in the statement the fill in
  ln L leaves E_u at mean z +0.58 (linear in L: +2.94) and mu_u at +0.04
  (-2.02): its error is small, but two stated terms are far above the errors
  made: the fill sigma of E_u and mu_u (the quadratic fits to ln L beside
  the band, on this 9 degree grid near the lower lens's field edge, give a
  curvature of about 2 per rad^2 while the run's own changes sign at the
  horizon), and the quadrature error (difference from the half-resolution
  grid: 5.7 % of E_u and 7 to 12 % of mu_u, against errors of 1 to 2 %
  and 0.3 to 1.5 %); without the fill sigma E_u's rms z is 0.64 and mu_u's
  0.09. L_u (the nadir cap filled across the pole) is at 0.14. Not done
  here: a standard (not bound-like) quadrature error, and a fill sigma
  from the run's own curvature where it changes sign.

Run time: about 30 s of CPU with the session fixture ``calibrated`` (measured 29.5 s user).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import xarray as xr
from scipy.stats import chi2

from pipeline.bundle.apply import BandChain
from pipeline.bundle.calibration import read_bundle
from pipeline.io.artefact import model_effects
from pipeline.io.bands import BANDS
from pipeline.io.rawio import read_raw
from pipeline.lightfield.hdr import exposure_maps, merge_exposures
from pipeline.lightfield.command import light_field_from_brackets
from pipeline.simulate.underwater import (WATER_INDEX, UnderwaterScene, fresnel_transmission, light_field_truth,
                                          render_underwater_bracket)

SEEDS = range(20)
GRID_DEG = 9.0
LOG_SIGMA_DEG = (0.2, 0.2, 1.0)
CHECKED = ("E_d", "E_u", "E_0", "mu_d", "mu_u", "L_u")
COVERAGE_Z = 3.0


def _scene(seed):
    rng = np.random.default_rng([seed, 33, 6])
    tilt = rng.uniform(-7.0, 7.0, 2)
    return replace(UnderwaterScene(), attitude_deg=(float(tilt[0]), float(tilt[1]), float(rng.uniform(0, 360))))


@pytest.fixture(scope="module")
def runs(calibrated, tmp_path_factory):
    """Per seed: the light field of its bracket and the truth (the truth computed once: the scene's light field
    does not depend on the camera's attitude)."""
    bundle = calibrated[4]
    out = []
    for seed in SEEDS:
        folder = tmp_path_factory.mktemp(f"uw{seed}")
        info = render_underwater_bracket(folder, _scene(seed), seed=seed, attitude_log_sigma_deg=LOG_SIGMA_DEG)
        ds = light_field_from_brackets(bundle, info["files"], info["frames_csv"], "water", info["attitude_log"],
                                       grid_deg=GRID_DEG)
        out.append((info, ds))
    return out


def _z(runs, q):
    return np.array([[(float(ds[q][0, b]) - info["light_field_truth"][q][b]) / float(ds[f"{q}_sigma"][0, b])
                      for b in range(3)] for info, ds in runs]).ravel()


def test_truth_quadrature_against_the_closed_form():
    scene = replace(UnderwaterScene(), beam_attenuation_per_m=(1e4, 1e4, 1e4))
    t = light_field_truth(scene, azimuth_step_deg=2.0)
    k = 0.5 * np.log(1.0 / scene.nadir_ratio)
    c = np.cos(np.radians(5.0))
    for b in range(3):
        C = scene.diffuse_factor * scene.zenith_radiance[b] * np.exp(
            -scene.diffuse_attenuation_per_m[b] * scene.depth_m) * np.exp(-k)
        closed = {"E_d": 2 * np.pi * C * (np.exp(k) * (k - 1) + 1) / k ** 2,
                  "E_u": 2 * np.pi * C * (1 - np.exp(-k) * (1 + k)) / k ** 2,
                  "E_0d": 2 * np.pi * C * (np.exp(k) - 1) / k, "E_0u": 2 * np.pi * C * (1 - np.exp(-k)) / k,
                  "L_d": C * (np.exp(k) - np.exp(k * c)) / (k * (1 - c)),
                  "L_u": C * (np.exp(-k * c) - np.exp(-k)) / (k * (1 - c))}
        # midpoint rule on rows of 0.05 to 0.25 degree: relative error below (0.25 deg)^2 k^2 / 24, about 1e-5
        for q, v in closed.items():
            assert t[q][b] == pytest.approx(v, rel=1e-4), (q, b)


def test_truth_conserves_the_transmitted_irradiance():
    """Just below the surface, no attenuation, no diffuse light: the refracted field's E_d is the transmitted
    irradiance of the sky, the integral over the air side of t_F(Z_a) L_a(Z_a) cos Z_a (the n-squared law and
    Snell's compression of solid angle cancel); both by midpoint rules of about 1e-5 relative error."""
    scene = replace(UnderwaterScene(), depth_m=0.0, diffuse_factor=0.0)
    t = light_field_truth(scene, azimuth_step_deg=0.5)
    edges = np.radians(np.arange(0.0, 90.0 + 1e-9, 0.02))
    z1, z2 = edges[:-1], edges[1:]
    n_a = 720
    Z, A = np.meshgrid(np.degrees(0.5 * (z1 + z2)), (np.arange(n_a) + 0.5) * 360.0 / n_a, indexing="ij")
    for b in range(3):
        L = scene.air_radiance(Z, A, np.full(Z.shape, b)) * fresnel_transmission(Z, WATER_INDEX[b])
        e = np.sum(L.sum(axis=1) * 0.5 * (np.sin(z2) ** 2 - np.sin(z1) ** 2) * 2 * np.pi / n_a)
        assert t["E_d"][b] == pytest.approx(e, rel=1e-4), b


def test_truth_in_water_within_stated_uncertainty(runs):
    for q in CHECKED:
        z = _z(runs, q)
        assert z.size == 60 and np.all(np.isfinite(z)), q
        assert np.all(np.abs(z) <= COVERAGE_Z), (q, np.abs(z).max())
    for _, ds in runs:
        assert float(ds["tilt_deg"][0]) <= 10.0
        assert (ds["hdr_dynamic_range_decades"][0].values >= 5.0).all()
        assert (ds["hdr_pixel_dynamic_range_decades"][0].values >= 5.0).all()
        assert not (ds["hdr_cell_flag"].values > 0).any()        # the refracted sun is measured, not a bound


def test_hdr_map_in_water_within_its_stated_uncertainty_over_five_decades(calibrated, runs):
    """One bracket's merged band pixels (both lenses, the water chain) against the truth at the same pixels, as
    test_hdr_brackets.py in air: the band-common scale (R^-1 and the immersion factor, one number per band) within
    3 of its stated relative sigma; the deviations from the scaled truth over the stated sigma of what is not
    band-scale, spread 0.6 to 1.5, over at least five decades of true radiance."""
    bundle = read_bundle(calibrated[4])
    effects = model_effects(bundle)
    lenses = [str(x) for x in bundle["lens"].values]
    chains = {(lens, band): BandChain(bundle, lens, band, "water", effects) for lens in lenses for band in BANDS}
    info, _ = runs[0]
    m = merge_exposures([exposure_maps(read_raw(p), bundle, chains, lenses, "water", effects) for p in info["files"]])
    with xr.open_dataset(info["truth"]) as t:
        truth = t["radiance"].sel(lens=lenses).values
    u = np.hypot(bundle["inverse_responsivity_relative_sigma"].sel(lens=lenses).values,
                 (bundle["immersion_factor_sigma"] / bundle["immersion_factor"]).sel(lens=lenses).values)
    for b, band in enumerate(BANDS):
        L, T = m.radiance[:, b], truth[:, b]
        ok = np.isfinite(L) & np.isfinite(T) & (L >= 3 * np.hypot(m.random_sigma[:, b], m.fixed_sigma[:, b]))
        assert np.log10(T[ok].max() / T[ok].min()) >= 5.0, band
        shape = np.sqrt(np.clip(m.common_sigma[:, b] ** 2 - (np.max(u[:, b]) * L) ** 2, 0.0, None))
        s = np.sqrt(m.random_sigma[:, b] ** 2 + m.fixed_sigma[:, b] ** 2 + np.sum(m.exposure_sigma[:, :, b] ** 2, 0)
                    + shape ** 2)
        L, T, s = L[ok], T[ok], s[ok]
        k = np.sum(L * T / s ** 2) / np.sum(T ** 2 / s ** 2)
        assert abs(k - 1.0) <= 3 * float(np.max(u[:, b])), (band, k)
        z = (L - k * T) / s
        assert 0.6 <= z.std() <= 1.5, (band, z.std())


@pytest.mark.xfail(strict=True, reason="the stated fill-model sigma and quadrature error of E_u and mu_u are far "
                                       "above the errors made in water (module docstring)")
def test_truth_in_water_unit_spread(runs):
    n = len(SEEDS) * 3
    low, high = np.sqrt(chi2.ppf([0.005, 0.995], n) / n)
    for q in CHECKED:
        spread = float(np.sqrt(np.mean(_z(runs, q) ** 2)))
        assert low <= spread <= high, (q, spread, low, high)

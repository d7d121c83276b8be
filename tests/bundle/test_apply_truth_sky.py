"""Truth test of the whole measurement chain on a sky of known radiance (issue 8, first "Done means").

A tiny simulated camera with every lab effect of the catalogue on (in the simulator and in
``model.effects``) is calibrated by the pipeline's own stages into a bundle. The same camera
(same seed, same effect objects drawn in the same order, hence the same PRNU, hot pixels and
offset pattern) then photographs a sky-like scene DEFINED HERE, over the whole field of both
lenses, in air and in water; ``apply`` turns the frames back into radiance, compared pixel by
pixel with the scene.

The deviation d = L_applied - L_true of one lens, band and medium is checked the way the
chain splits its uncertainty:

* random part: d minus its smooth part (a weighted polynomial in the image plane plus a
  piecewise-linear function of theta, which take the band-common calibration error and any smooth
  error of the calibration, such as the roll-off's near the rim of the field), over the stated
  random sigma, must have unit spread; with n pixels and p fitted terms the spread rests on
  n - p independent residuals (shot, read and dark noise are drawn per pixel; stray light
  spreads the mean light before the photon noise, PRNU is fixed per pixel but divided out by
  the flat field, bias drift is one offset per frame and goes into the smooth part), so its
  sampling error is 1 / sqrt(2 (n - p)); the 6 spreads of a lens share one more error, that of the
  fitted shot-noise gain (see :func:`spread_z`), so they are checked about their mean, the mean about 1
  with that gain's stated sigma, and water against air;
* systematic part: the band-mean deviation over the stated systematic sigma of the band mean
  (one draw per lens, band and medium, all 12 correlated through the shared calibration terms);
* shape: the deviation relative to the truth, averaged in cells of field angle and azimuth,
  against the axis, over the stated uncertainty of that difference (roll-off and the other
  terms that are not a common scale of the band), which is where an effect the chain leaves
  uncorrected across the field (an azimuthal roll-off, stray light at the rim) shows.

The systematic check is one-sided in effect: it bounds the deviations from above. Whether the stated
systematic sigma is also not too large (band-mean z of order 1) cannot be told from one dataset (a perfect
lab: the lab's systematic errors are not drawn here, and the stated R^-1 sigma of about 3 % is mostly the
reference radiometer's 2.5 %); that is the coverage test over seeds, tests/stages/test_coverage_over_seeds.py.

Run time: about 40 to 60 s, nearly all of it the module fixture (simulating and calibrating the tiny
dataset with every effect on).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from datetime import datetime

import numpy as np
import pytest
import xarray as xr
from scipy import stats

from helpers import LAB_EFFECTS, calibrate
from pipeline.bundle.apply import apply_calibration
from pipeline.io.bands import BANDS, split_bands
from pipeline.bundle.calibration import BUNDLE_STAGES, read_bundle
from pipeline.config import load_config
from pipeline.effects import get as get_effect
from pipeline.io.rawio import write_dng
from pipeline.simulate.camera import Camera
from pipeline.simulate.dataset import SCALES
from pipeline.simulate.immersion import true_immersion_factors
from pipeline.simulate.plan import FrameSpec
from pipeline.simulate.render import Renderer

LENSES = ("far", "close")
MEDIA = ("air", "water")
SEED = 23
#: field angle up to which the radiance is checked (issue 8: 80 degrees in air, 70 in water)
THETA_LIMIT_DEG = {"air": 80.0, "water": 70.0}
#: sky frames: inside the dark model's exposures (1/4000 to 2 s) and the linearity sweeps
#: (8.33 to 500 ms; ISO 200 has a fitted gain factor), signals about 1,000 to 10,000 DN
SKY_ISO = 200.0
SKY_EXPOSURE_S = 1 / 60
#: logged sensor temperature of the sky frames (apply has no temperature: the frame's unlit corners tell the bias)
SKY_TEMPERATURE_C = 27.0
#: experiment ids of the sky frames for the renderer's per-frame noise (the dataset uses 1 to 7)
SKY_EXPERIMENT_ID = {"air": 41, "water": 42}


# --------------------------------------------------------------------------- the scene
@dataclass(frozen=True)
class GradientSky:
    """A smooth sky-like scene, W sr-1 m-2 nm-1 per band: brighter towards one horizon, bluish overhead.

    In the sphere coordinates of ``apply`` (the close lens looks at the zenith, the far lens at the
    nadir, its azimuth mirrored), with u the unit direction and s that of a low sun:
        L_b = base_b * (1 + slope_b * u.s) * (1 + horizon_b * sin^2(zenith angle)).
    Not a form the package uses anywhere.
    """

    base: tuple = (1.5e-3, 1.9e-3, 2.6e-3)        # R, G, B
    slope: tuple = (0.70, 0.60, 0.45)             # redder towards the sun
    horizon: tuple = (0.35, 0.30, 0.20)
    sun_zenith_deg: float = 62.0
    sun_azimuth_deg: float = 40.0

    def band_radiance(self, lens, theta_deg, phi_deg, band_index):
        th, ph = np.radians(theta_deg), np.radians(phi_deg)
        if lens == "close":
            zen, azi = th, ph
        else:
            zen, azi = np.pi - th, -ph
        u = np.stack([np.sin(zen) * np.cos(azi), np.sin(zen) * np.sin(azi), np.cos(zen)])
        sz, sa = np.radians(self.sun_zenith_deg), np.radians(self.sun_azimuth_deg)
        s = np.array([np.sin(sz) * np.cos(sa), np.sin(sz) * np.sin(sa), np.cos(sz)])
        cos_sun = np.tensordot(s, u, axes=1)
        base, slope, horizon = (np.asarray(v)[band_index] for v in (self.base, self.slope, self.horizon))
        return base * (1.0 + slope * cos_sun) * (1.0 + horizon * np.sin(zen) ** 2)

    def __call__(self, lens, geo, band_index):
        return self.band_radiance(lens, geo.theta_deg, geo.phi_deg, band_index)


class InWaterResponse:
    """The camera's in-water response is the in-air one over the true immersion factor (as simulate/immersion.py)."""

    def __init__(self):
        factors = true_immersion_factors()["immersion_factor"]
        self.values = np.array([1.0 / factors[b] for b in BANDS])

    def __call__(self, band_index):
        return self.values[band_index]


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def calibrated(make_dataset, tmp_path_factory):
    root, truth = make_dataset(effects=tuple((name, {}) for name in LAB_EFFECTS), seed=SEED,
                               experiments=tuple(BUNDLE_STAGES))
    config = load_config(overrides={"model": {"effects": list(LAB_EFFECTS), "plugins": []}})
    _, bundle_path, meta = calibrate(root, config, tmp_path_factory.mktemp("results_sky"))
    return root, truth, bundle_path, meta, config


@pytest.fixture(scope="module")
def sky(calibrated, tmp_path_factory):
    """Sky frames of the calibrated camera, applied; returns {medium: (applied Dataset, {lens: {band: truth}})}."""
    _, _, bundle_path, meta, config = calibrated
    camera = Camera()
    scale = SCALES["tiny"]
    # the dataset's effect objects, drawn in the same order from the same seed: the same static patterns
    renderer = Renderer(camera, scale.lens_px, SEED, [get_effect(name) for name in LAB_EFFECTS])
    scene = GradientSky()
    folder = tmp_path_factory.mktemp("sky")
    result = {}
    for medium in MEDIA:
        spec = FrameSpec("both", "signal", SKY_ISO, SKY_EXPOSURE_S, radiance=scene, medium=medium,
                         temperature_c=SKY_TEMPERATURE_C,
                         light_factor=InWaterResponse() if medium == "water" else 1.0)
        frame = renderer.render(0, SKY_EXPERIMENT_ID[medium], spec)
        path = folder / f"sky_{medium}.dng"
        write_dng(path, frame, exposure_s=SKY_EXPOSURE_S, iso=SKY_ISO, time=datetime(2021, 3, 18, 16, 0, 0),
                  black_level=round(camera.sensor.bias_dn), white_level=camera.sensor.adc_max_dn,
                  cfa_pattern="RGGB", make=camera.make, model=camera.model, serial=camera.serial)
        truth = {}
        for lens in LENSES:
            geo = renderer.geometry(lens, medium)
            per_site = scene(lens, geo, renderer.band_index)
            # a band pixel is the R site, the B site, or the mean of the two G sites (pipeline.io.bands.split_bands)
            radiance = split_bands(per_site, "RGGB")
            theta = split_bands(geo.theta_deg, "RGGB")
            truth[lens] = {b: (radiance[b].astype(float), theta[b].astype(float)) for b in BANDS}
        out = folder / f"applied_{medium}.nc"
        apply_calibration(bundle_path, [path], medium, out, config=config)
        result[medium] = (xr.open_dataset(out).load(), truth)
    return result


#: degree of the smooth part removed from d before the random check: a polynomial in the image plane of
#: total degree 6 (28 terms), enough for the smooth calibration errors (roll-off and azimuth up to 80 deg)
SMOOTH_DEGREE = 6
#: plus a piecewise-linear function of the field angle (knots every THETA_KNOT_DEG): a roll-off or geometry
#: error grows steeply towards the rim of the field (g(theta) falls fastest there), faster than the
#: polynomial follows; it is common to the pixels of a ring, not pixel-to-pixel noise
THETA_KNOT_DEG = 5.0
#: the random spreads are checked as 16 draws, per lens its 6 spreads about their mean, that mean about 1 and
#: the water spreads' mean less the air spreads' (:func:`spread_z`), Bonferroni at CONFIDENCE (c about 2.96)
SPREAD_DRAWS = 16
#: confidence of the systematic and shape bounds (Bonferroni over the draws: valid whatever their correlation)
CONFIDENCE = 0.95
#: shape cells: rings of field angle (deg) from the reference disc out to the limit, four azimuth quadrants
RING_DEG = 10.0
QUADRANTS = 4


def _poly_basis(x, y, degree):
    return np.column_stack([x**i * y**j for i in range(degree + 1) for j in range(degree + 1 - i)])


@dataclass
class Group:
    """One lens, band and medium: the unflagged band pixels up to the field-angle limit."""

    medium: str
    lens: str
    band: str
    deviation: np.ndarray        # L_applied - L_true
    truth: np.ndarray
    random_sigma: np.ndarray
    systematic_sigma: np.ndarray
    theta_deg: np.ndarray        # true field angle of the pixel
    phi_deg: np.ndarray
    x: np.ndarray
    y: np.ndarray
    scale_rel_sigma: float       # the stated systematic terms that are one scale for the whole band
    shot_gain_rel_sigma: float   # stated relative sigma of the shot noise's gain K_100 f_ISO at the sky ISO


def _scale_rel_sigma(bundle, lens, band, medium):
    """Relative sigma of the calibration terms that scale every pixel of the band alike (R^-1, immersion,
    shutter offset at the sky exposure, ISO gain factor at the sky ISO)."""
    b = bundle.sel(lens=lens, band=band)
    var = float(b["inverse_responsivity_relative_sigma"]) ** 2
    if medium == "water":
        var += (float(b["immersion_factor_sigma"]) / float(b["immersion_factor"])) ** 2
    if "shutter_offset_s" in b:
        var += (float(b["shutter_offset_s_sigma"]) / (SKY_EXPOSURE_S + float(b["shutter_offset_s"]))) ** 2
    if "iso_gain_factor" in b:
        f = b.sel(gain_iso=SKY_ISO)
        var += (float(f["iso_gain_factor_sigma"]) / float(f["iso_gain_factor"])) ** 2
    return float(np.sqrt(var))


def _shot_gain_rel_sigma(bundle, lens):
    """Relative sigma of the photon-transfer gain at the sky ISO, K_100 f_ISO (the linearity stage's stated
    sigmas of K_100 and of the ISO gain factor, independent fits): the shot variance the chain states for every
    pixel of the lens is K_100 f_ISO (ISO / 100) times the signal, so an error of K_100 f_ISO is one
    factor on the stated shot variance of all its pixels, common to the lens's 6 spreads."""
    b = bundle.sel(lens=lens)
    rel = float(b["conversion_gain_dn_per_e_sigma"]) / float(b["conversion_gain_dn_per_e"])
    if "iso_gain_factor" in b:
        f = b.sel(gain_iso=SKY_ISO)
        rel = float(np.hypot(rel, float(f["iso_gain_factor_sigma"]) / float(f["iso_gain_factor"])))
    return rel


@pytest.fixture(scope="module")
def groups(calibrated, sky):
    bundle = read_bundle(calibrated[2])
    out = []
    for medium in MEDIA:
        ds, truth = sky[medium]
        for lens in LENSES:
            for band in BANDS:
                def get(name):
                    return ds[name].sel(frame=0, lens=lens, band=band).values.astype(float)
                radiance, flags = get("radiance"), ds["quality_flag"].sel(frame=0, lens=lens, band=band).values
                true, theta = truth[lens][band]
                sel = (theta <= THETA_LIMIT_DEG[medium]) & (flags == 0) & np.isfinite(radiance)
                y, x = np.nonzero(sel)
                out.append(Group(medium, lens, band, (radiance - true)[sel], true[sel], get("radiance_random_sigma")[sel],
                                 get("radiance_systematic_sigma")[sel], theta[sel],
                                 np.mod(ds["phi_deg"].sel(lens=lens, band=band).values[sel], 360.0), x, y,
                                 _scale_rel_sigma(bundle, lens, band, medium), _shot_gain_rel_sigma(bundle, lens)))
    return out


def test_the_sky_is_seen_over_the_whole_field(groups):
    """Every lens, band and medium keeps most of its pixels up to the limit (the checks below rest on them)."""
    for g in groups:
        assert len(g.deviation) > 1500, (g.medium, g.lens, g.band, len(g.deviation))
        assert g.theta_deg.max() > THETA_LIMIT_DEG[g.medium] - 2.0


def random_spread(g: Group) -> tuple[float, int]:
    """Spread of (d - smooth part of d) / random sigma, and its degrees of freedom n - p.

    The smooth part is the weighted least-squares fit of a polynomial of :data:`SMOOTH_DEGREE` in the
    image plane plus a piecewise-linear function of theta; chi^2 / (n - p) estimates the variance
    ratio, so the spread is sqrt(chi^2 / (n - p)).
    """
    knots = np.arange(THETA_KNOT_DEG, g.theta_deg.max() + THETA_KNOT_DEG, THETA_KNOT_DEG)
    hats = np.clip(1.0 - np.abs(g.theta_deg[:, None] - knots[None, :]) / THETA_KNOT_DEG, 0.0, None)
    basis = np.hstack([_poly_basis((g.x - g.x.mean()) / 32.0, (g.y - g.y.mean()) / 32.0, SMOOTH_DEGREE), hats])
    w = 1.0 / g.random_sigma
    coef, *_ = np.linalg.lstsq(basis * w[:, None], g.deviation * w, rcond=None)
    resid = (g.deviation - basis @ coef) * w
    dof = len(resid) - basis.shape[1]
    return float(np.sqrt(np.sum(resid**2) / dof)), dof


def spread_z(groups, lens) -> tuple[list[tuple[str, float]], float, float]:
    """The lens's 6 spreads as 8 draws: each spread about the lens's mean spread (z, the 6 contrasts), that
    mean about 1 (z of the mean) and the mean of the water spreads less that of the air spreads (z of the media).

    A spread s_k (:func:`random_spread`) has the sampling standard error e_k = 1 / sqrt(2 (n_k - p - 1)). Besides,
    the chain states every pixel's shot variance as K_100 f_ISO (ISO / 100) times its signal, with K_100 f_ISO
    the linearity stage's fit (stated relative sigma ``shot_gain_rel_sigma``, about 1.4 to 1.8 %): an error delta
    of it multiplies the stated variance of the shot fraction f of every pixel of the lens by (1 + delta), so
    all 6 spreads move together by -f delta / 2 (f is 0.66 to 0.90 here; bounded by 1). Hence
      contrast: s_k - mean(s), free of delta, variance e_k^2 (1 - 2/6) + sum(e^2) / 36;
      mean: mean(s) - 1, variance sum(e^2) / 36 + (shot_gain_rel_sigma / 2)^2;
      media: mean(s, water) - mean(s, air), free of delta, variance sum(e^2) / 9
    (a random sigma wrong in one medium only, by a factor, moves the media's z most).
    """
    gs = [g for g in groups if g.lens == lens]
    spreads, ses = [], []
    for g in gs:
        spread, dof = random_spread(g)
        spreads.append(spread)
        ses.append(1.0 / np.sqrt(2.0 * (dof - 1)))
    spreads, ses = np.array(spreads), np.array(ses)
    n = len(spreads)
    mean, se_mean = spreads.mean(), np.sqrt(np.sum(ses**2)) / n
    contrast = (spreads - mean) / np.sqrt(ses**2 * (1.0 - 2.0 / n) + se_mean**2)
    shot_gain = max(g.shot_gain_rel_sigma for g in gs)
    z_mean = (mean - 1.0) / np.hypot(se_mean, shot_gain / 2.0)
    water = np.array([g.medium == "water" for g in gs])
    z_media = (spreads[water].mean() - spreads[~water].mean()) / (np.sqrt(np.sum(ses**2)) / (n / 2))
    names = [f"{g.medium}/{g.lens}/{g.band} {s:.3f}" for g, s in zip(gs, spreads)]
    return list(zip(names, contrast.tolist())), float(z_mean), float(z_media)


@pytest.mark.parametrize("lens", ["close", "far"])
def test_random_part_has_unit_spread(groups, lens):
    """The stated random sigma of each lens, band and medium is the spread of the random part: the lens's 6
    spreads about their mean, that mean about 1 and water against air (:func:`spread_z`), all |z| within the
    Bonferroni bound over the 16 draws of both lenses at 95 % (c = 2.96; the spreads are close to normal at
    n - p ~ 2,000; the residuals' excess kurtosis over the seeds below was -0.04 to 0.06).

    The shared shot-gain term is why the spreads of one lens scatter more than their sampling error of about
    0.016 (issue 8): over the dataset seeds 1 to 30 (SEED here; 12 and 15 stop in the roll-off stage, and the
    12 of the other 112 lenses and media whose roll-off fit failed, reduced chi-square 12 to 335, are left out:
    45 lenses with all 6 groups), the spreads' sd was 0.017 to 0.025 against 0.015
    to 0.016, their lens means' sd 0.012 to 0.014 against 0.006, correlated (r = -0.5, -0.65) with the fitted
    K_100 f_ISO's error (slope -0.55, -0.52: -f / 2). Water is not overstated: pooled mean spread 1.0047 +- 0.0015
    in water (141), 1.0029 +- 0.0017 in air (159); water/far/R 1.000 +- 0.004 (23 seeds), its 0.950 at this seed
    a low draw. With each spread against 3 sampling errors 6 of the 45 lens draws failed (nominal 1.6 %); with
    this test the contrasts' z had sd 1.06 (270), the lens means' 1.18 (mean +0.34), water less air 1.11 (mean
    +0.19, largest 2.53), 1 of 45 failed (seed 8, far, mean z 3.55). Measured again on the simulator with one
    optics for every experiment and the roll-off linearised (2026-12-04, seeds 1 to 30, all 60 lenses ran): the
    contrasts' z sd 1.02 (360), the lens means' 1.12 (mean +0.32), water less air 1.16 (mean -0.03, largest
    3.16), 2 of 60 failed (seed 20 far, water less air +3.00; seed 25 close, -3.16), about the 5 % the bound
    allows per seed; the lens means still follow the fitted gain's error (r = -0.62, slope -0.43); pooled mean
    spread 1.0030 +- 0.0014 in water, 1.0033 +- 0.0013 in air (180 each): the stated random sigma is low by
    about 0.3 % in both media, the lens-common excess of the lens means. Here: far contrast z down to -2.26
    (water R), mean z -1.96, media -0.78. (The close lens's G spreads
    were 1.055 and 1.052 while its photon-transfer gain came out 3 sigma low and its PRNU spread 7 % low: see
    tests/radiometry/test_photon_transfer.py and the flat field on the linearised signal.)"""
    c = stats.norm.ppf(1.0 - (1.0 - CONFIDENCE) / (2 * SPREAD_DRAWS))
    contrasts, z_mean, z_media = spread_z(groups, lens)
    print(f"{lens}: spreads " + ", ".join(f"{name} (z {z:+.2f})" for name, z in contrasts)
          + f"; lens mean z {z_mean:+.2f}, water less air z {z_media:+.2f}, bound {c:.2f}")
    bad = [f"{name}: contrast z {z:+.2f}" for name, z in contrasts if abs(z) > c]
    bad += [f"{lens} {what}: z {z:+.2f}" for what, z in (("mean spread", z_mean), ("water less air", z_media))
            if abs(z) > c]
    assert not bad, f"random spread off unity beyond {c:.2f}: " + "; ".join(bad)


def test_random_spread_check_sees_a_water_sigma_5_percent_high(groups):
    """The check above could fail: the water pixels' random sigma stated 5 % too high (the question of issue 8)
    drops the 3 water spreads of a lens by 1 - 1 / 1.05 = 0.048, the media's z by 0.048 / (sqrt(6) 0.0153 / 3)
    = 3.8 against the bound 2.96 (over the 45 seed draws of the media's z, sd 1.11, this shift takes about 70 % of the
    lenses beyond it); at this seed the media's z are -0.78 (far) and +1.07 (close), so about -4.6 and -2.7: the
    far lens fails."""
    c = stats.norm.ppf(1.0 - (1.0 - CONFIDENCE) / (2 * SPREAD_DRAWS))
    inflated = [replace(g, random_sigma=g.random_sigma * 1.05) if g.medium == "water" else g for g in groups]
    z_media = {lens: spread_z(inflated, lens)[2] for lens in LENSES}
    assert min(z_media.values()) < -c, z_media


def test_band_mean_deviation_within_the_systematic_sigma(groups):
    """One draw per lens, band and medium: z = mean(d) / sigma(mean), sigma(mean)^2 = mean(systematic
    sigma)^2 (common to the pixels) + sum(random sigma^2) / n^2. The 12 draws share calibration terms
    (one R^-1 per lens and band in both media, one reference radiometer for all), so no chi-square of
    independent draws applies; the Bonferroni bound does whatever the correlation:
    P(max |z| > c) <= 12 P(|z| > c) = 5 % for c = 2.87."""
    c = stats.norm.ppf(1.0 - (1.0 - CONFIDENCE) / (2 * len(groups)))
    zs = {}
    for g in groups:
        n = len(g.deviation)
        sigma = np.hypot(np.mean(g.systematic_sigma), np.sqrt(np.sum(g.random_sigma**2)) / n)
        zs[f"{g.medium}/{g.lens}/{g.band}"] = float(np.mean(g.deviation) / sigma)
    bad = {k: round(v, 2) for k, v in zs.items() if abs(v) > c}
    assert not bad, f"band-mean deviation beyond {c:.2f} systematic sigma: {bad}"


def shape_z(g: Group) -> list[tuple[str, float]]:
    """Relative deviation r = d / L_true averaged in cells (ring x quadrant) minus its mean on the axis
    (theta < RING_DEG, where the normalised roll-off g(0) = 1 has no uncertainty), over the stated
    uncertainty of that difference: the random standard errors of the two means in quadrature, plus the
    sum of their shape sigmas (systematic terms that are not a common scale of the band: roll-off with
    its azimuthal term, dark model, nonlinearity), sigma_shape^2 = (systematic / L)^2 - sigma_scale^2,
    added linearly because the two are correlated."""
    rel = g.deviation / g.truth
    rel_rand = g.random_sigma / g.truth
    shape_rel = np.sqrt(np.clip((g.systematic_sigma / g.truth) ** 2 - g.scale_rel_sigma**2, 0.0, None))
    ref = g.theta_deg < RING_DEG
    r_ref, se_ref = rel[ref].mean(), np.sqrt(np.sum(rel_rand[ref] ** 2)) / ref.sum()
    s_ref = shape_rel[ref].mean()
    out = []
    edges = np.arange(RING_DEG, THETA_LIMIT_DEG[g.medium] + 1e-9, RING_DEG)
    for lo, hi in zip(edges[:-1], edges[1:]):
        for q in range(QUADRANTS):
            cell = (g.theta_deg >= lo) & (g.theta_deg < hi) & (g.phi_deg >= 360.0 * q / QUADRANTS) \
                & (g.phi_deg < 360.0 * (q + 1) / QUADRANTS)
            if cell.sum() < 10:
                continue
            se = np.sqrt(np.sum(rel_rand[cell] ** 2)) / cell.sum()
            sigma = np.hypot(np.hypot(se, se_ref), shape_rel[cell].mean() + s_ref)
            out.append((f"{g.medium}/{g.lens}/{g.band} theta {lo:.0f}-{hi:.0f} quadrant {q}",
                        float((rel[cell].mean() - r_ref) / sigma)))
    return out


#: the far lens failed here (strict xfail) until the geometry's covariance became the leave-one-board-out
#: jackknife and the roll-off took the principal point's error as a correlated term (2026-12-02): R in air,
#: azimuth quadrant 3, cells at 60-70 and 70-80 deg at z = -3.7 and -4.0 against the bound 3.6, the tiny-scale
#: fit's centre and field-angle scale off the truth beyond the board-clustered covariance, the azimuthal
#: roll-off term absorbing part of it. Then (the printed line): far -3.20 (air/far/R 70-80 deg, quadrant 3),
#: close +1.92, of 156 cells each; since every experiment is rendered through the geometry experiment's optics
#: (2026-12-03): far -3.01 (water/far/R 10-20 deg, quadrant 2), close -1.66. Over the dataset seeds 1 to 30 that
#: left 6 of 60 lenses beyond the bound, every one a G cell low by up to 5.8 sigma, most at 50-60 deg in air: the
#: roll-off stage took its ratios to the axis from bent readings (the nonlinearity not inverted, the ratio
#: beta s0 (1 - g) / F = 0.6 % high at 55 deg, tests/stages/test_rolloff.py). With the roll-off linearised: none of 60
#: (largest |z| per lens median 1.54, at most 3.42), and here far -2.75, close -1.22 (2026-12-04)
@pytest.mark.parametrize("lens", ["close", "far"])
def test_shape_across_the_field_within_its_stated_uncertainty(groups, lens):
    """All cells of the lens's 6 groups (about 150) at once, Bonferroni bound at 95 % (c about 3.6).
    Without the chain's azimuthal roll-off step this fails for both lenses (|z| up to 4.5)."""
    cells = [z for g in groups if g.lens == lens for z in shape_z(g)]
    c = stats.norm.ppf(1.0 - (1.0 - CONFIDENCE) / (2 * len(cells)))
    bad = [f"{name}: {z:+.1f}" for name, z in cells if abs(z) > c]
    worst = max(cells, key=lambda nz: abs(nz[1]))
    print(f"{lens}: largest |z| {worst[1]:+.2f} ({worst[0]}) of {len(cells)} cells, bound {c:.2f}")
    assert not bad, f"{len(bad)} of {len(cells)} cells beyond {c:.2f}: " + "; ".join(bad[:12])

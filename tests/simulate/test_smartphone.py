"""Any RAW camera: the simulated smartphone (one rectilinear region, 12-bit, GRBG, optically black
margins, a gain table not proportional to ISO) calibrated by the same dark and linearity stages,
against the simulator's truth.

Tiny scale: 64 x 96 band pixels, 5 dark frames and 4 linearity frames per setting. Tolerances are
derived from the injected noise in each test.
"""

from __future__ import annotations

import shutil
from datetime import datetime

import numpy as np
import pytest
import xarray as xr
import yaml

from cf_units_check import units_problems
from pipeline.io.dataset import write_md5sums
from pipeline.errors import InputError
from pipeline.report.formatting import bias_drift_text
from pipeline.scaffold import _dataset_yaml, plan_dataset
from pipeline.simulate import truth_dir_for
from pipeline.simulate.smartphone import Smartphone, simulate_smartphone_dataset
from pipeline.runner.workflow import run_stage

LENS = "main"
DRIFT_DN = 0.5              # injected frame-to-frame black-level spread
N_OPTICAL_BLACK = 8 * 208 + 128 * 16   # masked raw pixels of a tiny frame (8 rows on top, 16 columns left)
TRUE_EFFECTS = [("dark_current", {}), ("hot_pixels", {}), ("prnu", {}), ("bias_drift", {"sigma_dn": DRIFT_DN})]
MODEL = ["dark_current", "hot_pixels", "iso_gain", "prnu", "bias_drift"]


def _load(path) -> xr.Dataset:
    """An artefact read into memory and its file closed (an open netCDF handle must not outlive the read)."""
    with xr.open_dataset(path) as ds:
        return ds.load()


@pytest.fixture(scope="module")
def phone(config, tmp_path_factory):
    """The tiny phone (seed 4) through the dark, linearity (without geometry) and geometry stages."""
    base = tmp_path_factory.mktemp("phone")
    root = simulate_smartphone_dataset(base / "dataset", scale="tiny", seed=4, effects=TRUE_EFFECTS)
    truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())
    cfg = {**config, "model": {**config["model"], "effects": MODEL}}
    dark = {LENS: base / "results/dark/main.nc"}
    lin = {LENS: base / "results/linearity/main.nc"}
    geo = {LENS: base / "results/geometry/main.nc"}
    # checked=True: the frames' tag checks (what validate makes, which every run_stage call on a folder repeats) are
    # not what these tests assert; the simulator's datasets pass them (tests/io/test_validation.py, test_consistency.py),
    # as helpers.calibrate runs its stages
    run_stage("dark", root, cfg, dark, checked=True)
    run_stage("linearity", root, cfg, lin, {"dark": dark}, checked=True)
    run_stage("geometry", root, cfg, geo, checked=True)
    return root, truth, cfg, dark, _load(dark[LENS]), _load(lin[LENS]), geo


def test_projection_and_bias_reference_are_recorded(phone):
    _, _, _, _, dark, lin, _ = phone
    assert dark.attrs["projection"] == lin.attrs["projection"] == "rectilinear"
    # the dark histograms hold the phone's 256-DN frames (the default range is the 800-DN camera's)
    assert float(dark["dark_histogram"].sum()) > 0
    assert dark.attrs["bias_reference"] == "optically black pixels"
    assert "rectilinear" in lin.attrs["field_angles_from"]


def test_bias_read_noise_and_dark_current(phone):
    _, truth, _, _, dark, _, _ = phone
    s = truth["camera"]["sensor"]
    k = s["conversion_gain_dn_per_e_iso100"]
    # bias over the whole region (no corners left out): the sample mean of the offset pattern,
    # sqrt(0.6^2 + (0.42 * 0.5)^2) = 0.64 DN over ~3000 band pixels -> 0.012 DN, and the injected bias
    # drift (0.5 DN per frame) that the setting means keep: 0.5 / sqrt(45 frames) = 0.07 DN, which the stated
    # standard error (from the settings' scatter) carries; 4 stated sigmas plus 5 x 0.012 DN
    tol = 4 * dark["bias_dn_sigma"].values + 5 * np.hypot(s["offset_fpn_dn"], k * s["offset_fpn_e"]) / np.sqrt(3000)
    assert np.all(np.abs(dark["bias_dn"].values - truth["derived"]["bias_dn"]) < tol)
    assert np.all(dark["bias_dn_sigma"].values < 0.15)
    # read noise: 5 frames x 6000 band pixels, relative error of a standard deviation ~0.6 % (3 %
    # allowed, as for the fisheye camera), plus the removal of the frames' common offsets: their sample
    # variance, measured on the masked pixels (noise sigma_c = 0.73 DN / sqrt(3712)), carries the cross
    # term 2 sum(o_i e_i) / (n - 1), standard deviation 2 sqrt(n) / (n - 1) sigma_drift sigma_c per raw
    # site, doubled in the G band pixel's two sites; 4 of those in the variance
    read_true = truth["derived"]["read_noise_dn_iso100"]
    n = 5
    cross = 2 * np.sqrt(n) / (n - 1) * DRIFT_DN * read_true / np.sqrt(N_OPTICAL_BLACK)
    sites = np.array([1, 2, 1])
    got = dark["read_noise_dn"].sel(iso=100.0).values
    assert np.all(np.abs(got**2 - read_true**2) < 0.06 * read_true**2 + 4 * cross * sites), got
    # dark current: stated standard error, 4 sigma
    d_true = truth["derived"]["dark_current_dn_per_s_iso100"]
    assert abs(float(dark["dark_current_dn_per_s"]) - d_true) < 4 * float(dark["dark_current_dn_per_s_sigma"])


def test_bias_drift_from_optically_black_pixels(phone):
    """The frames' black level moves by N(0, 0.5 DN); the masked margins (8 rows x 208 + 128 rows x 16 =
    3712 raw pixels, read noise 0.73 DN: 0.012 DN per frame) see it: the stated 95 % interval contains
    0.5 DN, and the read noise (test above) is what is left once the frames' common offsets are out."""
    _, _, _, _, dark, lin, _ = phone
    assert int(dark.attrs["bias_drift_testable"]) == 1
    assert float(dark["bias_drift_dn_low"]) < DRIFT_DN < float(dark["bias_drift_dn_high"])
    assert float(dark["bias_drift_dn_low"]) > 0.2     # resolved: the masked pixels see 0.012 DN
    assert "obs_frame__corner_dev_dn" in dark and "obs_frame__corner_dev_dn" in lin


def test_gain_table_recovered(phone):
    """Photon transfer at ISO 100 and the per-ISO gain factors of the table (iso_gain) against truth,
    4 stated sigmas (plus 0.3 % on K: the PTC's intercept and the flat-field share)."""
    _, truth, _, _, _, lin, _ = phone
    k_true = truth["derived"]["conversion_gain_dn_per_e_iso100"]
    k, k_sigma = float(lin["conversion_gain_dn_per_e"]), float(lin["conversion_gain_dn_per_e_sigma"])
    assert abs(k - k_true) < 4 * k_sigma + 0.003 * k_true
    factors = truth["derived"]["iso_gain_factors"]
    got = lin["effect_iso_gain"].values
    sig = lin["effect_iso_gain_sigma"].values
    isos = lin["effect_iso_gain_iso"].values
    expected = np.array([factors[str(int(iso))] - 1.0 for iso in isos])
    assert np.all(np.abs(got - expected) < 4 * sig), (got, expected, sig)
    # the table is far from proportional: ISO 1600 gives 35 % less than ISO/100 says
    assert expected[-1] < -0.3
    # read noise in electrons from the PTC against the truth (amplified plus rounding), 4 sigma + 0.05 e-
    expected_e = truth["derived"]["read_noise_dn_iso100"] / k_true
    assert abs(float(lin["read_noise_e"]) - expected_e) < 4 * float(lin["read_noise_e_sigma"]) + 0.05


def test_flat_field_amplitude(phone):
    """PRNU of 1 % (truth) from the exposure sweep: prnu coefficient sigma_rel^2 within 4 stated sigmas."""
    _, truth, _, _, _, lin, _ = phone
    sigma_rel = truth["effects"]["prnu"]["sigma_rel"]
    coef, se = float(lin["effect_prnu"].values[0]), float(lin["effect_prnu_sigma"].values[0])
    assert abs(coef - sigma_rel**2) < 4 * se, (np.sqrt(coef), sigma_rel)


def test_same_phone_declared_fisheye_stops_naming_the_region(phone, tmp_path):
    """The issue's case: the ordinary camera's dataset without ``projection: rectilinear`` (a fisheye by
    default) must stop the linearity stage with one line naming the lens region, not fit a circle."""
    root, _, cfg, dark_paths, _, _, _ = phone
    copy = tmp_path / "as_fisheye"
    shutil.copytree(root, copy)
    meta = yaml.safe_load((copy / "dataset.yaml").read_text())
    del meta["lenses"][LENS]["projection"]
    (copy / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    write_md5sums(copy)
    with pytest.raises(InputError) as info:
        run_stage("linearity", copy, cfg, {LENS: tmp_path / "lin.nc"}, {"dark": dark_paths})
    message = str(info.value)
    assert "\n" not in message and "lens region 'main' is declared fisheye" in message
    assert not (tmp_path / "lin.nc").exists()


def test_dark_frames_measure_their_own_drift_without_optically_black_pixels(config, tmp_path):
    """No masked margins in the DNG (ActiveArea the whole mosaic) and no unlit corners: in the dark frames every
    pixel is dark, so a fixed random half of each row measures each frame's black level and the other half is
    tested against it. A drift of DRIFT_DN injected: the dark stage finds it within its 95 % interval and its
    frame and setting tables at the noise floor; the lit frames still have no reference (bias_reference none)."""
    root = simulate_smartphone_dataset(tmp_path / "dataset", scale="tiny", seed=6, experiments=("dark",),
                                       phone=Smartphone(black_margin_px=(0, 0)),
                                       effects=[("bias_drift", {"sigma_dn": DRIFT_DN})])
    cfg = {**config, "model": {**config["model"], "effects": ["dark_current", "bias_drift"]}}
    out = {LENS: tmp_path / "dark.nc"}
    run_stage("dark", root, cfg, out)
    ds = _load(out[LENS])
    assert ds.attrs["bias_reference"] == "none" and int(ds.attrs["bias_drift_testable"]) == 1
    assert ds.attrs["dark_bias_reference"].startswith("half the region's pixels")
    assert "their drift cannot be removed" in ds.attrs["bias_drift_note"]
    # the drift's estimate against the injected one: a spread measured on dof = frames - settings deviations has
    # a relative standard error of 1 / sqrt(2 dof); within 4 of them
    dof = len(np.unique(ds["obs_frame__file_index"].values)) - len(np.unique(ds["obs_setting__setting"].values))
    assert abs(float(ds["bias_drift_dn"]) - DRIFT_DN) < 4 * DRIFT_DN / np.sqrt(2.0 * dof), float(ds["bias_drift_dn"])
    assert "obs_frame__corner_dev_dn" in ds and "not testable" not in bias_drift_text(ds)
    # the noise floor: rms z within 5 of its sampling spread 1 / sqrt(2 n) of 1 (n residuals, a bound on the dof)
    n = ds["obs_frame__z"].size + ds["obs_setting__z"].size
    assert float(ds["rms_z"]) < 1.0 + 5.0 / np.sqrt(2.0 * n)
    # the bias from the dark frames: 256 DN within 5 of the stated sigma (which holds the drift) and the
    # offset pattern's mean over the half of the pixels the model uses
    n_used = int(ds["obs_setting__n_used"].min())
    tol = 5 * np.hypot(ds["bias_dn_sigma"].values, 0.64 / np.sqrt(n_used))
    assert np.all(np.abs(ds["bias_dn"].values - 256.0) < tol), (ds["bias_dn"].values, tol)


def _true_theta_phi(truth: dict, band: str, shape) -> tuple[np.ndarray, np.ndarray]:
    """The truth's field angles of a band image: its band intrinsics and the distortion, inverted here by
    a fixed-point iteration (the simulator's forward model, not OpenCV's undistortion)."""
    k = truth["derived"]["band_intrinsics_px"][band]
    dist = truth["derived"]["distortion"]
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    xd, yd = (u - k["cx"]) / k["fx"], (v - k["cy"]) / k["fy"]
    x, y = xd.copy(), yd.copy()
    for _ in range(40):
        r2 = x * x + y * y
        radial = 1 + dist["k1"] * r2 + dist["k2"] * r2 * r2
        ex = x * radial + 2 * dist["p1"] * x * y + dist["p2"] * (r2 + 2 * x * x) - xd
        ey = y * radial + dist["p1"] * (r2 + 2 * y * y) + 2 * dist["p2"] * x * y - yd
        x, y = x - ex, y - ey
    return np.degrees(np.arctan(np.hypot(x, y))), np.degrees(np.arctan2(y, x))


def test_rectilinear_geometry_against_truth(phone):
    """OpenCV's pinhole fit of the chessboard frames (12 poses, 5 x 4 inner corners, 64 x 96 band pixels):
    theta within 4 stated sigmas (0.25 to 0.4 degrees: the principal point of so small an image is known to
    about 1 band pixel) plus 0.01 degrees for the G band pixel averaging two sites; the focal length
    within 4 sigmas; no image circle."""
    _, truth, _, _, _, _, geo_paths = phone
    geo = _load(geo_paths[LENS])
    assert geo.attrs["projection"] == "rectilinear" and np.isnan(float(geo["circle_radius_px"].sel(
        medium="air", band="G")))
    for band in ("G", "R", "B"):
        g = geo.sel(medium="air", band=band)
        theta, _ = _true_theta_phi(truth, band, g["theta_deg"].shape)
        d = g["theta_deg"].values - theta
        assert np.all(np.abs(d) < 4 * g["theta_deg_sigma"].values + 0.01), (band, float(np.max(np.abs(d))))
        fx_true = truth["derived"]["band_intrinsics_px"][band]["fx"]
        fx, var = float(g["pinhole_parameters"].values[0]), float(g["pinhole_parameter_covariance"].values[0, 0])
        assert abs(fx - fx_true) < 4 * np.sqrt(var)
    # the half diagonal of the region sees about 39 degrees (truth: the optics' corner angle)
    assert 35.0 < float(geo["half_fov_deg"].sel(medium="air", band="G")) < 43.0


def test_linearity_takes_field_angles_from_the_rectilinear_geometry(phone, tmp_path):
    """With the phone's own geometry artefact the 5-degree mask is a cone of the fitted theta map (not the
    nominal field of view), and the conversion gain stays within its tolerance of the truth."""
    root, truth, cfg, dark_paths, _, _, geo_paths = phone
    out = {LENS: tmp_path / "lin.nc"}
    run_stage("linearity", root, cfg, out, {"dark": dark_paths, "geometry": geo_paths})
    lin = _load(out[LENS])
    assert lin.attrs["field_angles_from"] == "geometry artefact"
    k_true = truth["derived"]["conversion_gain_dn_per_e_iso100"]
    k, k_sigma = float(lin["conversion_gain_dn_per_e"]), float(lin["conversion_gain_dn_per_e_sigma"])
    assert abs(k - k_true) < 4 * k_sigma + 0.003 * k_true


def test_init_dataset_proposes_a_rectilinear_region(phone):
    """init-dataset on the phone's raw files: the vignetted region is lit to its corners (cos^4 at 39
    degrees leaves about a third of the centre there, far above the 256-DN black level), so no image
    circle is claimed and dataset.yaml proposes projection: rectilinear."""
    root = phone[0]
    plan = plan_dataset(root)
    (lens,) = plan.lenses
    assert lens.name == LENS and lens.projection == "rectilinear" and lens.radius_px is None
    meta = yaml.safe_load(_dataset_yaml(plan))
    assert meta["lenses"][LENS]["projection"] == "rectilinear"


def test_vignetting_against_truth(phone, tmp_path):
    """The roll-off stage, unchanged, on the phone's port frames and its own rectilinear geometry: the
    fitted g(theta) (Eq. 13) against the simulator's vignetting, cos^4 theta times the mechanical fall-off,
    at 10 to 30 degrees, within 4 sigmas: the fit's own (its covariance) and the field angle's, the geometry
    artefact's theta_deg_sigma at the port times dg/dtheta (0.3 to 0.4 degrees on 64 x 96 band pixels)."""
    from pipeline.radiometry.rolloff import evaluate_rolloff, rolloff_design_matrix, rolloff_slope

    root, truth, cfg, _, _, _, geo_paths = phone
    out = {LENS: tmp_path / "rolloff.nc"}
    run_stage("rolloff", root, cfg, out, {"geometry": geo_paths})
    ro = _load(out[LENS])
    geo = _load(geo_paths[LENS])
    vig = truth["experiments_truth"]["rolloff"]
    theta = np.array([10.0, 20.0, 25.0, 30.0])
    for band in ("R", "G", "B"):
        coef = ro["rolloff_coefficients"].sel(medium="air", band=band).values
        cov = ro["rolloff_covariance"].sel(medium="air", band=band).values
        X = rolloff_design_matrix(theta)
        fit_sigma = np.sqrt(np.einsum("ij,jk,ik->i", X, cov, X))
        sigma_theta = float(np.nanmax(geo["theta_deg_sigma"].sel(medium="air", band=band).values))
        sigma = np.hypot(fit_sigma, rolloff_slope(coef, theta) * sigma_theta)
        true_g = (np.cos(np.radians(theta)) ** 4
                  * (1 - vig["mechanical_at_corner"][band] * (theta / vig["corner_theta_deg"]) ** 4))
        got = evaluate_rolloff(coef, theta)
        assert np.all(np.abs(got - true_g) < 4 * sigma), (band, got, true_g, sigma)
    # the fall-off is real and strongest in red (lens colour shading): about half the axis at 30 degrees
    assert evaluate_rolloff(ro["rolloff_coefficients"].sel(medium="air", band="R").values, 30.0) < 0.6


def test_effective_wavelengths_and_inverse_responsivity_against_truth(phone, tmp_path):
    """The spectral and absolute stages, unchanged, on the phone (its own dark, linearity and rectilinear
    geometry): effective wavelengths within 4 stated sigmas plus 0.3 nm (the 10-nm monochromator grid
    against the truth on the same grid), R^-1 within 4 stated sigmas (2.7 %, the reference reading's
    2.5 % dominating; the perfect simulated lab draws no systematic error, and the 5-degree mask averages
    a vignetting of about 1 %, inside that)."""
    root, truth, cfg, dark_paths, _, _, geo_paths = phone
    lin_paths = {LENS: tmp_path / "lin.nc"}
    run_stage("linearity", root, cfg, lin_paths, {"dark": dark_paths})
    spec = {LENS: tmp_path / "spectral.nc"}
    absolute = {LENS: tmp_path / "absolute.nc"}
    up = {"geometry": geo_paths, "dark": dark_paths, "linearity": lin_paths}
    run_stage("spectral", root, cfg, spec, up)
    run_stage("absolute", root, cfg, absolute, {**up, "spectral": spec})
    s = _load(spec[LENS])
    a = _load(absolute[LENS])
    for band in ("R", "G", "B"):
        want = truth["experiments_truth"]["spectral"]["lenses"][LENS]["bands"][band]["effective_wavelength_nm"]
        got, se = float(s["effective_wavelength_nm"].sel(band=band)), float(s["effective_wavelength_nm_sigma"].sel(band=band))
        assert abs(got - want) < 4 * se + 0.3, (band, got, want, se)
        want = truth["experiments_truth"]["absolute"]["bands"][band]["inverse_responsivity"]
        got, se = float(a["inverse_responsivity"].sel(band=band)), float(a["inverse_responsivity_sigma"].sel(band=band))
        assert abs(got - want) < 4 * se, (band, got / want - 1, se / want)


#: the uniform scene applied: half the lab sphere's radiance, 1/30 s at ISO 100 (about 700 to 1100 DN above
#: the 256-DN black level on the axis, far from the 12-bit top); an experiment id the dataset does not use
APPLY_FRACTION, APPLY_EXPOSURE_S, APPLY_ISO, APPLY_EXPERIMENT_ID = 0.5, 1 / 30, 100.0, 99


@pytest.fixture(scope="module")
def phone_bundle(phone, tmp_path_factory):
    """The rest of the phone's chain (linearity with its geometry, roll-off, spectral, absolute) gathered
    into the calibration bundle, and one frame of a known uniform radiance rendered by the dataset's own
    renderer (same seed, same effects: the same static patterns), with and without the optically black
    margins; returns (bundle path, bundle, frame paths {with, without}, true radiance {band: L}, the frame's
    true black-level offset in DN)."""
    from pipeline.bundle.calibration import build_bundle, read_bundle
    from pipeline.effects import get as get_effect
    from pipeline.io.rawio import write_dng
    from pipeline.simulate.plan import FrameSpec
    from pipeline.simulate.smartphone import PHONE_SCALES, PhoneRenderer

    root, _, cfg, dark, _, _, geo = phone
    base = tmp_path_factory.mktemp("phone_bundle")
    paths = {s: {LENS: base / f"{s}.nc"} for s in ("linearity", "rolloff", "spectral", "absolute")}
    run_stage("linearity", root, cfg, paths["linearity"], {"dark": dark, "geometry": geo}, checked=True)
    run_stage("rolloff", root, cfg, paths["rolloff"], {"geometry": geo}, checked=True)
    up = {"geometry": geo, "dark": dark, "linearity": paths["linearity"]}
    run_stage("spectral", root, cfg, paths["spectral"], up, checked=True)
    run_stage("absolute", root, cfg, paths["absolute"], {**up, "spectral": paths["spectral"]}, checked=True)
    meta = yaml.safe_load((root / "dataset.yaml").read_text())
    bundle_path = base / "calibration" / "phone.nc"
    build_bundle({"dark": dark, "geometry": geo, **paths}, bundle_path, meta["camera"], meta["lenses"], cfg)
    phone_ = Smartphone()
    renderer = PhoneRenderer(phone_, PHONE_SCALES["tiny"], 4, [get_effect(n, **p) for n, p in TRUE_EFFECTS])
    radiance = {b: APPLY_FRACTION * phone_.sphere_band_radiance[b] for b in ("R", "G", "B")}
    # the frame's common black-level offset as the renderer draws it (the first draw of the frame's generator)
    offset_dn = sum(e.frame_offset_dn(np.random.default_rng([4, APPLY_EXPERIMENT_ID, 0])) for e in renderer.effects)
    raw, (top, left, _, _) = renderer.render(0, APPLY_EXPERIMENT_ID,
                                             FrameSpec(LENS, "signal", APPLY_ISO, APPLY_EXPOSURE_S, radiance=radiance))
    tags = dict(exposure_s=APPLY_EXPOSURE_S, iso=APPLY_ISO, time=datetime(2024, 6, 1, 12, 0, 0),
                black_level=round(phone_.sensor.bias_dn), white_level=phone_.sensor.adc_max_dn,
                cfa_pattern=phone_.cfa_pattern, make=phone_.make, model=phone_.model, serial=phone_.serial)
    frames = {"with": base / "uniform.dng", "without": base / "uniform_no_black.dng"}
    write_dng(frames["with"], raw, active_area=(top, left) + raw.shape, **tags)
    write_dng(frames["without"], np.ascontiguousarray(raw[top:, left:]), **tags)
    return bundle_path, read_bundle(bundle_path), frames, radiance, offset_dn, {**paths, "dark": dark, "geometry": geo}


def test_rectilinear_artefacts_units_parse_with_udunits(phone_bundle):
    """The phone's artefacts (the pinhole geometry's parameters and covariance among them) and its bundle: every
    units attribute a UDUNITS-2 unit (tests/support/cf_units_check.py; docs/artefact-units.md)."""
    bundle_path, *_, paths = phone_bundle
    files = [bundle_path] + [path for by_lens in paths.values() for path in by_lens.values()]
    assert len(files) == 7
    problems = [line for path in files for line in units_problems(path)]
    assert not problems, "\n".join(problems)


def test_black_level_from_the_optically_black_pixels(phone, phone_bundle):
    """The frame's black level from its optically black pixels against the truth: bias 256 DN plus the
    frame's injected offset (-0.48 DN for this seed) plus the dark current over 1/30 s. Errors: the masked
    pixels' mean (3712 raw pixels, 0.73 DN each: 0.012 DN), the dark stage's optical_black_offset_dn (the
    same over 5 dark frames, with the region's mean: about 0.01 DN) and the region's offset-pattern mean
    (0.64 DN over ~3000 band pixels: 0.012 DN); 4 x 0.02 DN plus 5 x 0.012 DN. The dark model's bias alone
    misses the offset (its stated sigma, ~0.07 DN, does not cover 0.48 DN)."""
    from pipeline.bundle.apply import optical_black_level
    from pipeline.io.rawio import read_raw

    truth = phone[1]
    bundle, frames, offset = phone_bundle[1], phone_bundle[2], phone_bundle[4]
    assert abs(offset) > 0.3     # the seed's draw: a drift the test can see
    want = (truth["derived"]["bias_dn"] + offset
            + truth["derived"]["dark_current_dn_per_s_iso100"] * APPLY_EXPOSURE_S)
    raw = read_raw(frames["with"])
    for band in ("R", "G", "B"):
        level, var = optical_black_level(raw, bundle, LENS, band)
        assert abs(level - want) < 4 * 0.02 + 5 * 0.012, (band, level, want)
        assert 0.005 < np.sqrt(var) < 0.03
        assert abs(float(bundle["bias_dn"].sel(lens=LENS, band=band)) - want) > 0.3
    assert optical_black_level(read_raw(frames["without"]), bundle, LENS, "G") is None


def test_apply_recovers_a_uniform_radiance(phone_bundle, tmp_path):
    """apply on a phone frame of uniform radiance L (truth) against L, per band pixel.

    Tolerances from the injected noise and the stated budget. Within 20 degrees of the axis every unflagged
    pixel's error is within 4 times its total stated sigma (random: shot noise of ~1000 DN, 2 to 3 %, read
    noise, the flat field's noise; systematic: R^-1's 2.7 %, roll-off, field angle, dark model), all but
    0.5 % of them (a correct budget leaves 0.006 % outside), and the band mean within 4 times its standard
    uncertainty (the systematic sigma, common to the band, and the random sigma over sqrt(n) in quadrature).
    Beyond 20 degrees the tiny phone's R and B geometry is loose (theta sigma up to 1.9 degrees at the
    corners, errors up to 3 of them, where g(theta) falls by 3 to 5 % per degree): its errors are common to
    whole corners, not pixel noise, so over the whole calibrated field the check is on G, whose geometry is
    tight (0.4 degrees): the spread of the pixels about their mean matches the stated random sigma
    (reduced chi-square 0.8 to 1.25; its own standard error is 0.02 over ~5000 pixels, and the roll-off's
    smooth error across the field adds under 0.1). The black level comes from the frame's optically black
    pixels (the frame carries an injected offset of N(0, 0.5 DN)); without them the output says the bias
    drift was not corrected. No pixel is outside an image circle, the pixels beyond the roll-off's largest
    field angle are flagged, and the sphere grid holds only the lens's field (NaN elsewhere).
    """
    from pipeline.bundle.apply import apply_calibration
    from pipeline.radiometry import measurement as mm

    bundle_path, bundle, frames, radiance, *_ = phone_bundle
    assert str(bundle["projection"].sel(lens=LENS).values) == "rectilinear"
    assert list(bundle["medium"].values) == ["air"]
    out = apply_calibration(bundle_path, [frames["with"]], "air", tmp_path / "applied.nc")
    with xr.open_dataset(out) as ds:
        ds = ds.load()
    assert "optically black pixels" in ds.attrs["black_level"] and "bias_drift_note" not in ds.attrs
    reach = float(bundle["calibrated_field_angle_deg"].sel(lens=LENS, medium="air"))
    assert 25.0 < reach < float(np.nanmax(ds["theta_deg"].values))
    for band, want in radiance.items():
        d = ds.sel(frame=0, lens=LENS, band=band)
        flags = d["quality_flag"].values
        assert not np.any(flags & mm.FLAG_OUTSIDE_IMAGE_CIRCLE)
        np.testing.assert_array_equal((flags & mm.FLAG_BEYOND_CALIBRATED_ANGLE) != 0, d["theta_deg"].values > reach)
        good = flags == 0
        got = d["radiance"].values[good].astype(float)
        rnd = d["radiance_random_sigma"].values[good].astype(float)
        sy = d["radiance_systematic_sigma"].values[good].astype(float)
        assert np.all(np.isfinite(got)) and np.all(rnd > 0) and np.all(sy > 0)
        near = d["theta_deg"].values[good] <= 20.0
        assert near.sum() > 1500, band
        within = np.abs(got[near] - want) < 4 * np.hypot(rnd[near], sy[near])
        assert within.mean() > 0.995, (band, within.mean())
        se = np.hypot(np.mean(sy[near]), np.sqrt(np.mean(rnd[near] ** 2) / near.sum()))
        assert abs(got[near].mean() - want) < 4 * se, (band, got[near].mean() / want - 1, se / want)
        if band == "G":
            chi2 = np.mean(((got - got.mean()) / rnd) ** 2)
            assert 0.8 < chi2 < 1.25, chi2
    # the sphere grid: cells only within the lens's field (its largest field angle, plus one cell)
    zen = ds["zenith"].values
    lit = np.any(ds["sphere_count"].values[0] > 0, axis=(0, 2))
    assert lit.any() and not np.any(lit & (zen > float(np.nanmax(ds["theta_deg"].values)) + ds.attrs["grid_deg"]))
    assert np.all(np.isnan(ds["sphere_radiance"].values[0][:, ~lit]))
    # without the optically black margins: the dark model's bias, and the output says so
    out2 = apply_calibration(bundle_path, [frames["without"]], "air", tmp_path / "applied_no_black.nc", pixels=False)
    with xr.open_dataset(out2) as ds2:
        assert "bias drift not corrected" in ds2.attrs["bias_drift_note"]


def test_report_of_the_phone_shows_its_sections_with_the_rectilinear_geometry(phone_bundle, tmp_path):
    """The report built from the phone's artefacts (one lens, air only, no immersion or field): it is written
    (the summary's half field of view in water is n/a, not a failure: the phone has no water geometry), the
    geometry and dark sections say the lens is rectilinear, and the absolute section shows R^-1."""
    from pipeline.report import build_report

    bundle_path, *_, artefacts = phone_bundle
    missing = tmp_path / "absent.csv"        # no diagnostics files: the report says so
    html = build_report(**artefacts, calibration=bundle_path, missing_effects=missing, unexplained=missing,
                        run_errors=missing, error_history=missing, out_html=tmp_path / "index.html",
                        skipped={"immersion": "the dataset has no immersion/ folder"}).read_text()
    for anchor in ("summary", "dark", "linearity", "geometry", "rolloff", "spectral", "absolute"):
        assert f'id="{anchor}"' in html, anchor
    geometry = html.split('id="geometry"', 1)[1].split("<section", 1)[0]
    assert "rectilinear region (dataset.yaml), fitted with the pinhole model" in geometry and "<img" in geometry
    assert "rectilinear" in html.split('id="dark"', 1)[1].split("<section", 1)[0]
    assert "the dataset has no immersion/ folder" in html

"""The field match-up stage on a field folder written here, independently of the field simulator.

The lab calibration is the pipeline's own (the shared ``calibrated`` fixture:
a tiny simulated camera, seed 5). The sky frames are rendered through the
TRUE camera of that simulation (responsivity, roll-off, noise: the
simulator's Renderer with the same seed, so the same sensor patterns) with a
sky of known radiance, uniform over the lens, that changes with time; the
reference radiometer's series is written from the same sky:

* sky spectrum L(lambda, t) = A(t) (1 + SLOPE (lambda - 550 nm)), linear in
  wavelength, so that Eq. (3) of any response gives A(t) (1 + SLOPE
  (lambda_eff - 550)) exactly, lambda_eff the response's Eq. (8) centroid;
* the camera band sees A(t) (1 + SLOPE (lambda_true - 550)), lambda_true the
  centroid of the simulator's true response;
* the reference reads REF_SCALE x the spectrum at each channel's centre,
  times a noise factor common to all channels of a sample (so each sample's
  spectrum stays linear in wavelength and the hand values stay exact).
"""

from __future__ import annotations

import copy
from datetime import datetime, timedelta

import numpy as np
import pytest
import xarray as xr
import yaml

from cf_units_check import units_problems
from pipeline.bundle.calibration import read_bundle
from pipeline.io.dataset import write_md5sums
from pipeline.diagnostics.tables import observations_from_artefacts
from pipeline.diagnostics.missing_effects import rank_missing_effects
from pipeline.errors import InputError
from pipeline.stages.observations import dataset_to_table
from pipeline.io.rawio import write_dng
from pipeline.simulate.camera import Camera
from pipeline.simulate.plan import FrameSpec
from pipeline.simulate.render import Renderer
from pipeline.simulate.spectral import default_spectral_response
from pipeline.runner.workflow import run_stage

BANDS = ("R", "G", "B")
CHANNELS_NM = (380, 395, 412, 443, 465, 490, 510, 532, 555, 560, 589, 625, 665, 683, 694, 710, 765, 780, 875)
T0_UTC = datetime(2021, 3, 18, 20, 0, 0)
UTC_OFFSET_H = -4.0
N_FRAMES = 11
FRAME_STEP_S = 120.0
EXPOSURE_S = 1e-3          # in the dark experiment's list: the bundle's dark model covers it
SLOPE_PER_NM = -0.002
REF_SCALE = 1.03
REF_NOISE = 0.003
REF_RATE_HZ = 6.0
#: a clock offset no other test uses
CLOCK_OFFSET_S = 17.0
#: dataset A: a step of the sky just after frame STEP_FRAME, and a reference gap at GAP_FRAME
STEP_FRAME, STEP_AFTER_S, STEP_FACTOR = 3, 2.0, 1.3
GAP_FRAME, GAP_HALF_S = 7, 20.0
WINDOW_S = 10.0            # field.reference_window_s default
LENS = "close"


def sky_amplitude(t_s, step_at_s=None):
    """A(t) in W sr-1 m-2 nm-1 at 550 nm: a ramp (+50 % per hour) times a 10-minute oscillation (+-20 %)."""
    t = np.asarray(t_s, float)
    a = 0.04 * (1.0 + 0.5 * t / 3600.0) * (1.0 + 0.2 * np.sin(2 * np.pi * t / 600.0))
    if step_at_s is not None:
        a = a * np.where(t >= step_at_s, STEP_FACTOR, 1.0)
    return a


def true_centroid_nm() -> dict[str, float]:
    """Eq. (8) of the simulator's TRUE response on a fine uniform grid (independent of the bundle)."""
    wl = np.arange(380.0, 760.0, 0.05)
    s = default_spectral_response(wl)
    return {b: float(np.sum(wl * s[b]) / np.sum(s[b])) for b in BANDS}


def write_field_dataset(root, meta, renderer, *, clock_offset_s=0.0, step=False, gap=False, experiment_id=8,
                        seed=0):
    """A dataset with only field/: frames, reference_radiometer.csv, site.yaml; returns what was written."""
    root.mkdir(parents=True)
    (root / "field" / "raw").mkdir(parents=True)
    (root / "dataset.yaml").write_text(yaml.safe_dump({k: meta[k] for k in ("layout", "camera", "lenses")}))
    camera = renderer.camera
    lam = true_centroid_nm()
    step_at = STEP_FRAME * FRAME_STEP_S + STEP_AFTER_S if step else None
    frame_t = np.arange(N_FRAMES) * FRAME_STEP_S
    rows, true_band = [], np.zeros((N_FRAMES, 3))
    for f, t in enumerate(frame_t):
        a = float(sky_amplitude(t, step_at))
        values = np.array([a * (1 + SLOPE_PER_NM * (lam[b] - 550.0)) for b in BANDS])
        true_band[f] = values

        def scene(lens, geometry, band_index, values=values):
            # the zenith lens sees the sky, the other one the ground at 0.2 x the sky
            return values[band_index] * (1.0 if lens == LENS else 0.2)

        spec = FrameSpec("both", "signal", 100.0, EXPOSURE_S, radiance=scene)
        cfa = renderer.render(f, experiment_id, spec)
        local = T0_UTC + timedelta(seconds=float(t) + clock_offset_s, hours=UTC_OFFSET_H) + timedelta(microseconds=123000)
        name = f"raw/SKY_{f:03d}.dng"
        write_dng(root / "field" / name, cfa, exposure_s=EXPOSURE_S, iso=100.0, time=local,
                  black_level=round(camera.sensor.bias_dn), white_level=camera.sensor.adc_max_dn, cfa_pattern="RGGB",
                  make=camera.make, model=camera.model, serial=camera.serial)
        rows.append(f"{name},{LENS},signal")
    (root / "field" / "frames.csv").write_text("file,lens,kind\n" + "\n".join(rows) + "\n")
    # the frames' true times carry the 0.123 s sub-second part too
    frame_t = frame_t + 0.123
    # reference: 6 Hz from 90 s before the first frame to 90 s after the last, times in whole milliseconds
    t_ref = np.round(np.arange(-90.0, frame_t[-1] + 90.0, 1.0 / REF_RATE_HZ), 3)
    if gap:
        t_ref = t_ref[np.abs(t_ref - frame_t[GAP_FRAME]) > GAP_HALF_S]
    rng = np.random.default_rng(seed)
    level = REF_SCALE * sky_amplitude(t_ref, None if step_at is None else step_at + 0.123) \
        * (1.0 + REF_NOISE * rng.standard_normal(t_ref.size))
    factor = 1.0 + SLOPE_PER_NM * (np.array(CHANNELS_NM, float) - 550.0)
    level = np.array([float(f"{v:.10g}") for v in level])
    lines = ["time," + ",".join(f"L_{c}" for c in CHANNELS_NM)]
    for t, v in zip(t_ref, level):
        stamp = (T0_UTC + timedelta(seconds=float(t))).isoformat(timespec="milliseconds") + "Z"
        lines.append(stamp + "," + ",".join(f"{v * k:.10g}" for k in factor))
    (root / "field" / "reference_radiometer.csv").write_text("\n".join(lines) + "\n")
    site = {"latitude_deg": 46.78, "longitude_deg": -71.2754, "camera_clock_utc_offset_h": UTC_OFFSET_H,
            "reference": {"name": "C-OPS-like test radiometer", "channels_nm": list(CHANNELS_NM), "fwhm_nm": 10.0,
                          "half_fov_deg": 9.0}}
    (root / "field" / "site.yaml").write_text(yaml.safe_dump(site))
    write_md5sums(root)
    return {"frame_t": frame_t, "t_ref": t_ref, "level": level, "true_band": true_band, "step_at": step_at}


@pytest.fixture(scope="module")
def field(calibrated, config, tmp_path_factory):
    root, _, _, _, bundle_path, meta = calibrated
    renderer = Renderer(Camera(), meta["lenses"][LENS]["cols"][1], seed=5, effects=[])
    base = tmp_path_factory.mktemp("field")
    written = {
        "A": write_field_dataset(base / "A", meta, renderer, step=True, gap=True, experiment_id=8, seed=1),
        "B": write_field_dataset(base / "B", meta, renderer, clock_offset_s=CLOCK_OFFSET_S, experiment_id=9, seed=2),
    }

    def run(name, effects):
        cfg = copy.deepcopy(config)
        cfg["model"]["effects"] = list(effects)
        out = base / "results" / f"{name}-{'-'.join(effects) or 'base'}" / "field" / f"{LENS}.nc"
        return run_stage("field", base / name, cfg, {LENS: out}, bundle=bundle_path)[LENS]

    arts = {"A": run("A", []), "B": run("B", []), "B_clock": run("B", ["clock_offset"]),
            "A_spectral": run("A", ["spectral_mismatch"])}
    return {"written": written, "arts": arts, "bundle": read_bundle(bundle_path), "base": base, "config": config,
            "bundle_path": bundle_path}


def _window(written, centre_s):
    t = written["t_ref"]
    sel = np.abs(t - centre_s) <= WINDOW_S / 2 + 1e-9
    return written["level"][sel]


def _hand_reference(written, field, band_index, wavelength_nm, shift_s=0.0):
    """Window means of the reference at ``wavelength_nm`` of a linear spectrum, frame by frame."""
    k = 1.0 + SLOPE_PER_NM * (wavelength_nm - 550.0)
    out, counts = [], []
    for t in written["frame_t"] - shift_s:
        level = _window(written, t)
        out.append(level.mean() * k if level.size else np.nan)
        counts.append(level.size)
    return np.array(out), np.array(counts)


def test_camera_radiance_is_the_known_sky_within_the_stated_uncertainty(field):
    ds = field["arts"]["A"]
    true = field["written"]["A"]["true_band"]
    for j, band in enumerate(BANDS):
        cam = ds["camera_radiance"].sel(band=band).values
        rnd = ds["camera_random_sigma"].sel(band=band).values
        sysm = ds["camera_systematic_sigma"].sel(band=band).values
        ratio = cam / true[:, j]
        # the calibration error is common to all frames: the mean ratio is 1 within 3 systematic sigmas
        assert abs(ratio.mean() - 1.0) < 3 * np.mean(sysm / cam), (band, ratio.mean())
        # what varies from frame to frame is the random error: ratios about their mean in units of it
        z = (ratio - ratio.mean()) / (rnd / true[:, j])
        # rms of 11 normal deviates is 1 +- 0.22; 2 is more than 4 sigma above
        assert np.sqrt(np.sum(z**2) / (len(z) - 1)) < 2.0, band
        assert np.all(ds["mask_n_pixels"].sel(band=band).values >= field["config"]["field"]["min_mask_pixels"])
        assert np.all(ds["camera_spatial_spread"].sel(band=band).values > 0)


def test_reference_window_straddling_a_step_and_a_gap(field):
    ds, w = field["arts"]["A"], field["written"]["A"]
    k = STEP_FRAME
    level = _window(w, w["frame_t"][k])
    before = REF_SCALE * sky_amplitude(w["frame_t"][k])
    # samples on both sides of the step: the mean lies between the two levels, weighted by the counts
    assert 0 < np.sum(level > 1.15 * before) < level.size
    for band in BANDS:
        lam = float(ds["nearest_channel_nm"].sel(band=band))
        factor = 1.0 + SLOPE_PER_NM * (lam - 550.0)
        got = float(ds["reference_nearest"].sel(frame=k, band=band))
        assert got == pytest.approx(level.mean() * factor, rel=1e-7)
        assert int(ds["reference_nearest_count"].sel(frame=k, band=band)) == level.size
        assert before * factor < got < STEP_FACTOR * before * factor
        # the step is variation within the window: the reference's uncertainty there dwarfs the other frames'
        sig = ds["reference_nearest_sigma"].sel(band=band).values
        assert sig[k] > 10 * np.nanmedian(np.delete(sig, [k, GAP_FRAME]))
    # the gap: no reference sample within 20 s of frame GAP_FRAME, so it is no match-up
    assert int(ds["n_frames_without_reference"]) == 1
    assert ds["is_matchup"].sel(frame=GAP_FRAME).values.sum() == 0
    assert np.all(ds["n_matchups"].values == N_FRAMES - 1)
    table = dataset_to_table(ds, "obs_frame")
    assert GAP_FRAME not in set(table["frame"]) and len(table) == 3 * (N_FRAMES - 1)


def test_nearest_channel_and_band_convolved_reference(field):
    ds, w, bundle = field["arts"]["A"], field["written"]["A"], field["bundle"]
    lam_eff = bundle["effective_wavelength_nm"].sel(lens=LENS).values
    for j, band in enumerate(BANDS):
        nearest = CHANNELS_NM[int(np.argmin(np.abs(np.array(CHANNELS_NM) - lam_eff[j])))]
        assert float(ds["nearest_channel_nm"].sel(band=band)) == nearest
        # the measured response lies inside 380-875 nm: nothing is cut off, so Eq. (3) of the linear
        # spectrum is the spectrum at the response's Eq. (8) centroid, the bundle's effective wavelength
        assert float(ds["response_outside_reference_fraction"].sel(band=band)) == 0.0
        hand, counts = _hand_reference(w, field, j, lam_eff[j])
        got = ds["reference_convolved"].sel(band=band).values
        ok = counts > 0
        np.testing.assert_allclose(got[ok], hand[ok], rtol=1e-7)
        assert np.all(np.isnan(got[~ok]))
        assert float(ds["convolution_weight"].sel(band=band).sum()) == pytest.approx(1.0, abs=1e-12)


def test_matchup_statistics_against_hand_values(field):
    ds, w = field["arts"]["A"], field["written"]["A"]
    lam_eff = field["bundle"]["effective_wavelength_nm"].sel(lens=LENS).values
    for j, band in enumerate(BANDS):
        ok = ds["is_matchup"].sel(band=band).values.astype(bool)
        y = ds["camera_radiance"].sel(band=band).values[ok]
        for comp, lam in (("nearest", float(ds["nearest_channel_nm"].sel(band=band))), ("convolved", lam_eff[j])):
            x = _hand_reference(w, field, j, lam)[0][ok]
            sel = {"band": band, "comparison": comp}
            assert float(ds["stat_mupd"].sel(sel)) == pytest.approx(200 * np.mean(np.abs(x - y) / (x + y)), rel=1e-6)
            lr = np.log(y / x)
            assert float(ds["stat_median_symmetric_accuracy"].sel(sel)) == pytest.approx(
                100 * (np.exp(np.median(np.abs(lr))) - 1), rel=1e-6)
            assert float(ds["stat_signed_symmetric_bias"].sel(sel)) == pytest.approx(
                100 * np.sign(np.median(lr)) * (np.exp(abs(np.median(lr))) - 1), rel=1e-6)
            slope, intercept = np.polyfit(x, y, 1)
            assert float(ds["stat_ols_slope"].sel(sel)) == pytest.approx(slope, rel=1e-6)
            assert float(ds["stat_ols_intercept"].sel(sel)) == pytest.approx(intercept, rel=1e-5, abs=1e-9)
            assert float(ds["stat_pearson_r"].sel(sel)) == pytest.approx(np.corrcoef(x, y)[0, 1], rel=1e-9)
            assert float(ds["stat_rmse_one_to_one"].sel(sel)) == pytest.approx(np.sqrt(np.mean((y - x) ** 2)), rel=1e-6)
            for name in ("mupd", "median_symmetric_accuracy", "signed_symmetric_bias"):
                lo, hi = (float(ds[f"stat_{name}_{e}"].sel(sel)) for e in ("low", "high"))
                assert lo <= float(ds[f"stat_{name}"].sel(sel)) <= hi
            assert float(ds["stat_ols_slope_low"].sel(sel)) < slope < float(ds["stat_ols_slope_high"].sel(sel))
            assert np.isfinite(float(ds["stat_odr_slope"].sel(sel)))
            assert int(ds["n_matchups"].sel(sel)) == ok.sum()


def test_known_clock_offset_is_recovered_and_diagnosed(field):
    fitted = field["arts"]["B_clock"]
    assert abs(float(fitted["clock_offset_s"]) - CLOCK_OFFSET_S) < 2.0
    assert 0 < float(fitted["clock_offset_s_sigma"]) < 2.0
    base = field["arts"]["B"]
    assert float(base["clock_offset_s"]) == 0.0
    # shifting the reference removes the structure the wrong clock leaves: back to the noise floor
    # (30 rows, 3 scales and the offset: rms_z = 1 +- 0.14; the diagnostics call 1.5 structured)
    assert float(fitted["rms_z"]) < 1.5 < float(base["rms_z"])
    assert float(field["arts"]["A"]["rms_z"]) < 1.5
    # without the effect in the model, the diagnostics find it in the field table, with the offset as amplitude
    obs = observations_from_artefacts({"field": [base]})
    # the match-up table and the scale closure (one row per band, the scale against the lab's prediction)
    assert [(o.experiment, o.level) for o in obs] == [("field", "frame"), ("field", "scale")]
    ranked, _ = rank_missing_effects(obs, [], field["config"])
    top = ranked.iloc[0]
    assert top["effect"] == "clock_offset" and bool(top["significant"])
    assert abs(top["amplitude"] - CLOCK_OFFSET_S) < 2.0


def test_prediction_follows_the_model(field):
    base = dataset_to_table(field["arts"]["A"], "obs_frame")
    spectral = dataset_to_table(field["arts"]["A_spectral"], "obs_frame")
    np.testing.assert_array_equal(base["x_scale"], base["ref_nearest"])
    np.testing.assert_array_equal(spectral["x_scale"], spectral["ref_convolved"])
    assert field["arts"]["A_spectral"].attrs["prediction"] == "convolved"
    for table in (base, spectral):
        assert {"group", "band", "frame", "time_s", "value_dn", "sigma_dn", "x_scale", "pred_dn", "z", "ref_nearest",
                "ref_convolved", "dref_dt", "spectral_slope", "sun_zenith_deg"} <= set(table.columns)
    # the linear test spectrum has d ln L / d ln lambda = SLOPE lambda / (1 + SLOPE (lambda - 550)) < 0
    assert np.all(base["spectral_slope"] < 0)
    # sun zenith at 16:00-16:20 local on 18 March 2021 in Quebec: 62.5 to 65 degrees (elevation 27.5 down)
    assert np.all((base["sun_zenith_deg"] > 61) & (base["sun_zenith_deg"] < 67))


def test_artefact_variables_have_units_and_the_sky_map(field):
    ds = field["arts"]["A"]
    for name, var in ds.data_vars.items():
        if var.dtype.kind in "fiu":
            assert "units" in var.attrs and "long_name" in var.attrs, name
    bundle = field["bundle"]
    for j, band in enumerate(BANDS):
        sky = ds["sky_radiance"].sel(band=band).values
        zen = ds["zenith"].values
        # the zenith lens fills the upper hemisphere (to its half field of view) and nothing below
        half_fov = float(bundle["half_fov_deg"].sel(lens=LENS, medium="air", band=band))
        assert np.all(np.isnan(sky[zen > half_fov + field["config"]["field"]["sky_map_grid_deg"]]))
        # every unflagged pixel is binned: the counts add up to the pixels with a direction within the roll-off's reach
        theta = bundle["theta_deg"].sel(lens=LENS, medium="air", band=band).values
        reach = float(bundle["calibrated_field_angle_deg"].sel(lens=LENS, medium="air"))
        inside = np.isfinite(theta) & (theta <= min(reach, half_fov))
        assert int(ds["sky_count"].sel(band=band).sum()) >= 0.9 * inside.sum()
        # a uniform sky: the map near the zenith is the known radiance within the calibration's error (<25 %)
        true = field["written"]["A"]["true_band"][N_FRAMES // 2, j]
        assert float(np.nanmedian(sky[zen < 30])) == pytest.approx(true, rel=0.25)


def test_field_artefacts_units_parse_with_udunits(field):
    """Every units attribute of the field artefacts (with and without effects in the model) is a UDUNITS-2 unit
    (tests/support/cf_units_check.py; the lab stages' files are checked in tests/io/test_artefact_units.py)."""
    paths = sorted((field["base"] / "results").glob("*/field/*.nc"))
    assert len(paths) == len(field["arts"])
    problems = [line for path in paths for line in units_problems(path)]
    assert not problems, "\n".join(problems)


def test_reference_that_misses_the_frames_is_refused(field, tmp_path):
    src = field["base"] / "A"
    import shutil
    root = tmp_path / "late"
    shutil.copytree(src, root)
    path = root / "field" / "reference_radiometer.csv"
    lines = path.read_text().splitlines()
    late = [lines[0]] + [line.replace("2021-03-18T", "2021-03-19T", 1) for line in lines[1:]]     # a day late
    path.write_text("\n".join(late) + "\n")
    write_md5sums(root)
    with pytest.raises(InputError, match="reference_radiometer.csv"):
        run_stage("field", root, field["config"], {LENS: tmp_path / "out" / "field" / f"{LENS}.nc"},
                  bundle=field["bundle_path"])


def test_artefact_round_trip(field, tmp_path):
    ds = field["arts"]["A"]
    path = tmp_path / "a.nc"
    ds.to_netcdf(path)
    back = xr.open_dataset(path).load()
    assert float(back["stat_mupd"].sel(band="G", comparison="nearest")) == pytest.approx(
        float(ds["stat_mupd"].sel(band="G", comparison="nearest")))


def test_negative_radiance_stops_the_stage(field, tmp_path):
    import shutil

    from pipeline.errors import ImpossibleResult
    from pipeline.io.rawio import read_raw

    root = tmp_path / "dark-sky"
    shutil.copytree(field["base"] / "A", root)
    path = root / "field" / "raw" / "SKY_000.dng"
    raw = read_raw(path)
    # 40 DN below the black level everywhere: a mask mean of -40 DN against a per-pixel noise of a few DN
    cfa = np.full(raw.cfa.shape, round(raw.black_level) - 40, np.uint16)
    write_dng(path, cfa, exposure_s=raw.exposure_s, iso=raw.iso, time=raw.time, black_level=raw.black_level,
              white_level=raw.white_level, make=raw.make, model=raw.model, serial=raw.serial)
    write_md5sums(root)
    with pytest.raises(ImpossibleResult, match="SKY_000.dng.*below zero"):
        run_stage("field", root, field["config"], {LENS: tmp_path / "out" / "field" / f"{LENS}.nc"},
                  bundle=field["bundle_path"])

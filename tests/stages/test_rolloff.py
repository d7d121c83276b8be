"""Roll-off stage on a simulated tiny dataset: curves within 1 % of truth, field angles, clean closure."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.io.artefact import read_artefact, write_artefact
from pipeline.diagnostics.tables import observations_from_artefacts
from pipeline.diagnostics.missing_effects import error_figures, rank_missing_effects
from pipeline.radiometry.rolloff import evaluate_rolloff
from pipeline.simulate import simulate_dataset
from pipeline.stages.observations import dataset_to_table
from pipeline.simulate.lens import default_rolloff
from pipeline.simulate.rolloff import ANGLES_DEG
from pipeline.runner.workflow import run_stage

from helpers import true_geometry_dataset


def run_rolloff(tmp_path_factory, config, effects=(), seed=3, model=None):
    root = tmp_path_factory.mktemp("roll") / "dataset"
    simulate_dataset(root, scale="tiny", seed=seed, effects=list(effects), experiments=("rolloff",), progress=False)
    geo = {}
    for lens in ("far", "close"):
        geo[lens] = root.parent / f"geometry_{lens}.nc"
        write_artefact(true_geometry_dataset(lens, 64), geo[lens], stage="geometry", inputs={}, config_subset={},
                       effects=[])
    cfg = {**config, "model": {**config["model"], "effects": list(model or [])}}
    outputs = {lens: root.parent / f"rolloff_{lens}.nc" for lens in geo}
    # checked=True: the frames' tag checks (what validate makes, which every run_stage call on a folder repeats) are
    # not what these tests assert; the simulator's datasets pass them (tests/io/test_validation.py, test_consistency.py),
    # as helpers.calibrate runs its stages
    run_stage("rolloff", root, cfg, outputs, {"geometry": geo}, checked=True)
    return {lens: read_artefact(p, "rolloff") for lens, p in outputs.items()}



@pytest.fixture(scope="module")
def config(config):
    """The session config with exact field angles: these tests use the simulator's true
    geometry maps, so the field angle carries no calibration error."""
    return {**config, "rolloff": {**config["rolloff"], "field_angle_sigma_px": 0.0}}

@pytest.fixture(scope="module")
def clean(tmp_path_factory, config):
    return run_rolloff(tmp_path_factory, config)


def test_rolloff_within_one_percent(clean):
    for lens, ds in clean.items():
        for medium in ("air", "water"):
            theta = np.abs(ANGLES_DEG[medium])
            for band in ("R", "G", "B"):
                c = ds["rolloff_coefficients"].sel(medium=medium, band=band).values
                rel = evaluate_rolloff(c, theta) / evaluate_rolloff(default_rolloff(band, medium, lens), theta) - 1
                assert np.abs(rel).max() < 0.01, (lens, medium, band, np.abs(rel).max())


def test_field_angles_from_geometry(clean):
    for ds in clean.values():
        t = dataset_to_table(ds, "obs_setting")
        spot = t[t["kind"] == "spot"]
        # flux centroid of a hard-edged port on a coarse grid: within one band pixel (about 3 deg at
        # the tiny scale), a third of one on average
        assert np.abs(spot["spot_theta_deg"] - spot["angle_deg"].abs()).max() < 1.0 * 3.0
        assert np.abs(spot["spot_theta_deg"] - spot["angle_deg"].abs()).mean() < 1.0


def test_clean_rolloff_comes_out_clean(clean, config):
    obs = observations_from_artefacts({"rolloff": list(clean.values())})
    ranked, _ = rank_missing_effects(obs, [], config)
    assert not ranked["significant"].any(), ranked.head(3).to_string()
    fig = error_figures(obs, [])
    assert (fig["rms_z"] < 1 + 2 * np.sqrt(2 / fig["dof"])).all(), fig


def test_water_closure_predicts_from_air_without_a_fitted_shape(clean, config):
    """The closure's prediction of each in-water point, from the fitted air curve and the immersion
    physics alone, against the simulator's true water roll-off at that field angle: within 4 of the
    air fit's propagated sigma plus 0.002 (the port's 1.8 deg disc averages g over about 3 deg at the
    tiny scale; g'' is at most 2e-4 per deg^2, so the mean of g and g at the mean angle differ by
    under 0.001). Clean data: the water level leaves immersion_angle insignificant (tested by
    test_clean_rolloff_comes_out_clean) and its own rms_z within the noise."""
    for lens, ds in clean.items():
        w = dataset_to_table(ds, "obs_water")
        w = w[w["used"] == 1]
        assert len(w) > 100
        for band, g in w.groupby("band"):
            true = evaluate_rolloff(default_rolloff(band, "water", lens), g["theta_deg"].to_numpy(float))
            err = np.abs(g["x_scale"].to_numpy(float) - true)
            assert (err < 4 * g["air_prediction_sigma"].to_numpy(float) + 0.002).all(), (band, err.max())
        z = w["z"].to_numpy(float)
        assert np.sqrt(np.mean(z**2)) < 1 + 3 * np.sqrt(2 / len(z)), np.sqrt(np.mean(z**2))



#: the simulator's default nonlinearity (effects.catalogue.Nonlinearity): m = s (1 - beta s / F) per raw site,
#: F the ADC's range above the bias
NONLINEARITY_BETA = 0.05
BENT_MODEL = ["dark_current", "hot_pixels", "nonlinearity"]


@pytest.fixture(scope="module")
def bent(tmp_path_factory, config):
    """Roll-off frames of a sensor that bends its readings (the simulator's default nonlinearity), with the dark
    and linearity experiments; the roll-off stage run on the same frames with the lens's linearity artefact (its
    fitted beta inverted at every pixel) and without it. The true geometry, as in :func:`run_rolloff`."""
    base = tmp_path_factory.mktemp("bent")
    root = base / "dataset"
    simulate_dataset(root, scale="tiny", seed=3, effects=[("dark_current", {}), ("hot_pixels", {}), ("nonlinearity", {})],
                     experiments=("dark", "linearity", "rolloff"), progress=False)
    cfg = {**config, "model": {**config["model"], "effects": BENT_MODEL}}
    geo = {}
    for lens in ("far", "close"):
        geo[lens] = base / f"geometry_{lens}.nc"
        write_artefact(true_geometry_dataset(lens, 64), geo[lens], stage="geometry", inputs={}, config_subset={},
                       effects=[])
    dark = {lens: base / f"dark_{lens}.nc" for lens in geo}
    lin = {lens: base / f"linearity_{lens}.nc" for lens in geo}
    run_stage("dark", root, cfg, dark, checked=True)
    run_stage("linearity", root, cfg, lin, {"dark": dark, "geometry": geo}, checked=True)
    out = {}
    for name, upstream in (("with", {"geometry": geo, "dark": dark, "linearity": lin}),
                           ("without", {"geometry": geo, "dark": dark})):
        paths = {lens: base / f"rolloff_{name}_{lens}.nc" for lens in geo}
        run_stage("rolloff", root, cfg, paths, upstream, checked=True)
        out[name] = {lens: read_artefact(p, "rolloff") for lens, p in paths.items()}
    return out


def _curve_against_truth(ds, medium, band, lens):
    theta = np.unique(np.abs(ANGLES_DEG[medium]))[1:]
    g, sigma = evaluate_rolloff(ds["rolloff_coefficients"].sel(medium=medium, band=band).values, theta,
                                ds["rolloff_covariance"].sel(medium=medium, band=band).values)
    return theta, g, sigma, evaluate_rolloff(default_rolloff(band, medium, lens), theta)


def test_bent_readings_are_linearised_before_the_ratio(bent):
    """A roll-off point is the light at an angle over that on the axis; a sensor that bends its bright readings
    (beta 0.05 at F = 15,583 DN, the G axis near 11,000 DN) compresses the axis more, so the ratio comes out
    high by about beta s0 (1 - g) / F: 0.6 % at 55 degrees, six times the curve's stated 0.09 % for G.

    With the linearity artefact the stage inverts the fitted nonlinearity at every pixel (and carries its
    uncertainty into the covariance): every point of every curve within 3.5 stated sigma of the simulator's
    true curve (306 points, correlated along a curve; measured at seed 3: largest 2.24, rms 1.08). Without
    it, on the same frames, R and G at 55 degrees in air are high by the predicted bias, within a third of it
    (measured +0.56 to +0.90 % against z of 5.6 to 7.8): the test sees the effect it guards against. The
    predicted bias takes the axis signal from the corrected run's table (its linearised DN at angle 0) and the
    simulator's beta and F."""
    from pipeline.simulate.camera import Camera

    sensor = Camera().sensor
    full_scale = sensor.adc_max_dn - sensor.bias_dn
    zs = []
    for lens, ds in bent["with"].items():
        assert ds.attrs["response_corrections"] == "nonlinearity"
        assert np.abs(ds["rolloff_nonlinearity_shift"].values).max() > 0
        for medium in ("air", "water"):
            for band in "RGB":
                _, g, sigma, true = _curve_against_truth(ds, medium, band, lens)
                zs.append((g - true) / sigma)
    zs = np.concatenate(zs)
    assert np.abs(zs).max() < 3.5 and np.sqrt(np.mean(zs**2)) < 1 + 3 * np.sqrt(2 / zs.size), \
        (np.abs(zs).max(), np.sqrt(np.mean(zs**2)))
    for lens, ds in bent["without"].items():
        assert ds.attrs["response_corrections"] == ""
        table = dataset_to_table(bent["with"][lens], "obs_setting")
        for band in ("R", "G"):
            theta, g, sigma, true = _curve_against_truth(ds, "air", band, lens)
            k = int(np.argmin(np.abs(theta - 55.0)))
            axis = table[(table["kind"] == "spot") & (table["medium"] == "air") & (table["band"] == band)
                         & (table["angle_deg"] == 0.0)]
            s0 = float(axis["signal_dn"].mean())
            predicted = (1 - NONLINEARITY_BETA * s0 * true[k] / full_scale) / (1 - NONLINEARITY_BETA * s0 / full_scale) - 1
            measured = g[k] / true[k] - 1
            assert abs(measured - predicted) < predicted / 3 and (g[k] - true[k]) / sigma[k] > 3, \
                (lens, band, measured, predicted, (g[k] - true[k]) / sigma[k])


def test_spot_search_in_a_window_finds_the_whole_image_spot():
    """The spot search labels a window around the peak, not the whole image: a disc larger than the first
    window (radius 70 px against SPOT_WINDOW_HALF_PX = 48) and a hot pixel brighter than it elsewhere (the
    first window is around the brightest pixel) must still give the disc's exact pixels, and its
    centroid within 0.01 px of the disc's centre (noise sigma 1 DN on 1000 DN over 15,000 pixels moves
    it by about 3e-4 px). The peak pixel must be the whole image's argmax of the 3 x 3 mean, as
    scipy's uniform_filter defines it, in random scenes of discs and hot pixels."""
    from scipy import ndimage

    from pipeline.stages.rolloff import SPOT_WINDOW_HALF_PX, _find_spot, _lit_image, _peak_pixel

    rng = np.random.default_rng(5)
    yy, xx = np.indices((600, 600))
    disc = np.hypot(xx - 250, yy - 300) <= 70
    assert 70 > SPOT_WINDOW_HALF_PX
    img = rng.normal(0.0, 1.0, disc.shape) + 1000.0 * disc
    img[50, 500] = 5000.0                              # 3 x 3 mean 555 DN: brighter pixel, dimmer mean
    lit = np.ones(disc.shape, bool)
    for level in (0.5, 0.05):
        dark = np.zeros(img.shape)
        cx, cy, (sy, sx) = _find_spot(img, dark, lit, level, _peak_pixel(_lit_image(img, dark, lit)))
        found = np.zeros(disc.shape, bool)
        found[sy, sx] = True
        assert np.array_equal(found, disc), level
        assert abs(cx - 250) < 0.01 and abs(cy - 300) < 0.01, (cx, cy)
    for _ in range(20):
        img = rng.normal(0.0, 2.0, (240, 300))
        for _ in range(3):
            cy, cx, r = rng.uniform(0, 240), rng.uniform(0, 300), rng.uniform(1, 30)
            img += rng.uniform(100, 1000) * (np.hypot(xx[:240, :300] - cx, yy[:240, :300] - cy) <= r)
        img[tuple(rng.integers(0, 240, 5)), tuple(rng.integers(0, 300, 5))] += rng.uniform(0, 8000, 5)
        lit = np.hypot(xx[:240, :300] - 150, yy[:240, :300] - 120) <= rng.uniform(60, 200)
        want = np.unravel_index(np.argmax(ndimage.uniform_filter(np.where(lit, img, 0.0), 3)), img.shape)
        assert _peak_pixel(_lit_image(img, np.zeros(img.shape), lit)) == tuple(int(v) for v in want)


def test_a_spot_without_light_or_beyond_the_field_is_dropped_not_fitted(config):
    """The roll-off guard (stages.rolloff._setting_masks, check_settings). A lit field that holds no light above
    the noise (the port beyond a too-short image circle: the spot outside the lit mask, whose dark-subtracted
    pixels are only noise; with all of them below the dark the 3 x 3 mean's rounding, 4e-15 DN, crashed the peak
    search, seeds 12 and 15) must give a reason, not a crash; a port beyond the field's edge, whose wing inside the
    field is all the stage would find (seed 16: 14-20 DN against 8,000), gives a reason; a spot inside, also one
    whose disc touches the edge, gives its pixels. The
    stage stops with one line naming frames.csv when a lens and medium keeps fewer than rolloff.min_settings.

    Numbers: noise sigma 3 DN per pixel, so a 3 x 3 mean's noise is 1 DN; rolloff.min_spot_snr 10 puts the bar at
    10 DN. Port 400 DN at its centre (a dim but real spot; its 3 x 3 mean about 250 sigma of that mean); the no-light case's brightest 3 x 3 mean of
    pure noise inside a 64 x 64 field is about 3.5 DN, below the bar by a factor 3."""
    from pipeline.errors import InputError
    from pipeline.stages.rolloff import _setting_masks, check_settings

    cfg = config["rolloff"]
    rng = np.random.default_rng(7)
    n, sigma = 64, 3.0
    yy, xx = np.indices((n, n))
    lit = np.hypot(xx - 31.5, yy - 31.5) <= 20.0            # a short field: radius 20 of the true 29 px
    darks = {b: np.zeros((n, n)) for b in ("R", "G", "B")}

    def frame(cx, cy):
        # a port blurred into a cone of radius 3 px, 400 DN at its centre
        port = np.clip(1.0 - np.hypot(xx - cx, yy - cy) / 3.0, 0.0, None)
        return {b: rng.normal(0.0, sigma, (n, n)) + 400.0 * port for b in ("R", "G", "B")}

    noise_3x3 = sigma / 3.0
    masks, reason = _setting_masks(frame(31.5 + 26.0, 31.5), darks, lit, 1.0, 3.0, cfg, noise_3x3)
    assert masks is None and reason.startswith("no light above the noise"), reason
    # every lit pixel below the dark (0 to -10 DN): the 3 x 3 means' rounding is the only "light" (this image
    # crashed the peak search with "zero-size array" before the guard)
    below = -np.round(np.random.default_rng(0).uniform(0.0, 10.0, (n, n)), 3)
    masks, reason = _setting_masks({b: below for b in ("R", "G", "B")}, darks, lit, 1.0, 3.0, cfg, noise_3x3)
    assert masks is None and reason.startswith("no light above the noise"), reason
    # a port centred 1 px beyond the field's edge (lit to x = 51): the field holds its wing, 200 DN at x = 51
    # against 333 DN at x = 52 outside
    masks, reason = _setting_masks(frame(31.5 + 21.0, 31.5), darks, lit, 1.0, 3.0, cfg, noise_3x3)
    assert masks is None and reason.startswith("port beyond the edge of the lit field"), reason
    # a port centred 1 px inside the edge is measured, although its spot touches the edge (333 DN at x = 50
    # inside, 200 DN at x = 52 outside)
    masks, reason = _setting_masks(frame(31.5 + 19.0, 31.5), darks, lit, 1.0, 3.0, cfg, noise_3x3)
    assert reason == "" and masks is not None, reason
    masks, reason = _setting_masks(frame(31.5 + 10.0, 31.5 - 4.0), darks, lit, 1.0, 3.0, cfg, noise_3x3)
    assert reason == "" and masks is not None
    cx, cy = masks[4]
    # the port's centre: its spot (above half its peak) is the 12 pixels within 1.6 px of it, symmetric about it;
    # the noise (3 DN on about 250 DN over 12 pixels) moves the centroid by about 0.01 px
    assert abs(cx - 41.5) < 0.1 and abs(cy - 27.5) < 0.1, (cx, cy)

    # the count check: one lens and medium with 3 measured settings and 2 dropped stops the stage in one line
    reduced = {"static": {("far", "air"): {}}, "masks": {("far", "air", 0.0, float(a)): masks for a in range(3)},
               "dropped": {("far", "air", 0.0, 80.0): "no light above the noise in the lit field (...)",
                           ("far", "air", 0.0, 75.0): "no light above the noise in the lit field (...)"}}
    with pytest.raises(InputError, match=r"frames\.csv.*lens far, air: only 3 roll-off settings with a measurable "
                                         r"spot \(need rolloff\.min_settings = 10\); 2 dropped") as err:
        check_settings(reduced, config, "dataset/rolloff/frames.csv")
    assert "\n" not in str(err.value)
    reduced["masks"].update({("far", "air", 0.0, float(a)): masks for a in range(3, 10)})
    check_settings(reduced, config, "dataset/rolloff/frames.csv")      # 10 kept: enough

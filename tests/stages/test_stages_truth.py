"""Dark and linearity stages recover the simulator's truth.

Tolerances come from the injected noise: the tiny dataset has 64 x 64 band
pixels per lens, 5 dark frames and 4 linearity frames per setting.
"""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
import yaml

from pipeline.report.render import render_fragment
from pipeline.report.sections.linearity import _linearity_section
from pipeline.runner.workflow import run_stage

LENSES = ("far", "close")


@pytest.fixture(scope="module")
def artefacts(make_dataset, config, tmp_path_factory):
    root, truth = make_dataset([("dark_current", {}), ("hot_pixels", {})], seed=21)
    out = tmp_path_factory.mktemp("results")
    dark = {lens: out / f"dark/{lens}.nc" for lens in LENSES}
    lin = {lens: out / f"linearity/{lens}.nc" for lens in LENSES}
    # checked=True: the frames' tag checks (what validate makes, which every run_stage call on a folder repeats) are
    # not what these tests assert; the simulator's datasets pass them (tests/io/test_validation.py, test_consistency.py),
    # as helpers.calibrate runs its stages
    run_stage("dark", root, config, dark, checked=True)
    run_stage("linearity", root, config, lin, {"dark": dark}, checked=True)
    return ({k: xr.open_dataset(v).load() for k, v in dark.items()},
            {k: xr.open_dataset(v).load() for k, v in lin.items()}, truth)


def test_bias_level(artefacts):
    dark, _, truth = artefacts
    sensor = truth["camera"]["sensor"]
    # The mean of the circle pixels carries the sample mean of the fixed pattern:
    # sqrt(1.5^2 + (0.8 * 1.4)^2) DN over ~3200 band pixels (R, B) -> 0.033 DN; 5 sigma.
    fpn = np.hypot(sensor["offset_fpn_dn"], sensor["conversion_gain_dn_per_e_iso100"] * sensor["offset_fpn_e"])
    tol = 5 * fpn / np.sqrt(3000)
    for lens in LENSES:
        np.testing.assert_allclose(dark[lens]["bias_dn"].values, truth["derived"]["bias_dn"], atol=tol)


def test_read_noise(artefacts):
    dark, lin, truth = artefacts
    expected = truth["derived"]["read_noise_dn_iso100"]
    for lens in LENSES:
        # temporal variance from 5 frames over ~4000 pixels: relative error of the
        # standard deviation ~ 1/sqrt(2 * 4 * 4000) = 0.8 %; the G band pools two sites
        # whose fixed pattern differs, allow 3 %.
        got = dark[lens]["read_noise_dn"].sel(iso=100.0).values
        np.testing.assert_allclose(got, expected, rtol=0.03)
        # photon transfer: read noise in electrons, 2 e- RMS amplified plus rounding
        expected_e = expected / truth["derived"]["conversion_gain_dn_per_e_iso100"]
        assert abs(float(lin[lens]["read_noise_e"]) - expected_e) < 4 * float(lin[lens]["read_noise_e_sigma"]) + 0.05


def test_photon_transfer_gain(artefacts):
    _, lin, truth = artefacts
    k_true = truth["derived"]["conversion_gain_dn_per_e_iso100"]
    for lens in LENSES:
        k = float(lin[lens]["conversion_gain_dn_per_e"])
        k_se = float(lin[lens]["conversion_gain_dn_per_e_sigma"])
        # 4 frames per setting: each variance point has ~ sqrt(2/(3 * N_mask)) relative error
        assert abs(k - k_true) < max(4 * k_se, 0.05 * k_true), (k, k_se, k_true)
        np.testing.assert_allclose(float(lin[lens]["gain_e_per_dn"]), 1 / k_true, rtol=0.08)


def test_dark_current(artefacts):
    dark, _, truth = artefacts
    expected = truth["derived"]["dark_current_dn_per_s_iso100"]
    for lens in LENSES:
        d = float(dark[lens]["dark_current_dn_per_s"])
        se = float(dark[lens]["dark_current_dn_per_s_sigma"])
        assert abs(d - expected) < 4 * se + 0.01 * expected, (d, se, expected)


def test_saturation_level(artefacts):
    _, lin, truth = artefacts
    for lens in LENSES:
        # the exposure sweep saturates G at 500 ms: the level is the ADC top minus the
        # dark level, known to the FPN sample mean (0.1 DN)
        assert int(lin[lens]["saturation_dn"].attrs["reached"]) == 1
        assert abs(float(lin[lens]["saturation_dn"]) - truth["derived"]["saturation_dn"]) < 2.0


def test_hot_pixels_found(artefacts):
    dark, _, truth = artefacts
    counts = truth["effects"]["hot_pixels"]["count_raw_pixels"]
    for lens in LENSES:
        found = int(dark[lens]["hot_pixel_count"].sum())
        # log-normal rates (median 400 e-/s) put every hot pixel far above 6 sigma at 1-2 s;
        # two hot sites may share a G band pixel
        assert counts[lens] - 2 <= found <= counts[lens]


def test_linearity_pearson_and_rate(artefacts):
    _, lin, truth = artefacts
    resp = truth["camera"]["radiometry"]["responsivity_dn_s_per_radiance"]
    sphere = truth["camera"]["radiometry"]["sphere_band_radiance"]
    source = truth["experiments_truth"]["linearity"]["exposure_source_band_radiance"]
    for lens in LENSES:
        ds = lin[lens]
        for band in ("R", "G", "B"):
            # exposure sweep source at half the sphere radiance (camera.LinearityPlan) as this lens's response
            # weighs the lamp (the close lens's is the camera's sphere_band_radiance, the far lens's 3 to 6 %
            # more); roll-off within 5 degrees is below 0.5 %
            assert source[lens][band] == pytest.approx(0.5 * sphere[band], rel=0.07)
            expected = resp[band] * source[lens][band]
            got = float(ds["rate_dn_per_s"].sel(sweep="exposure", band=band))
            np.testing.assert_allclose(got, expected, rtol=0.01)
        assert float(ds["line_r"].min()) > 0.999


@pytest.fixture(scope="module")
def full_well_artefacts(config, tmp_path_factory):
    """A camera whose full well fills at 10,000 DN above the bias at ISO 100 (12,500 e- at
    0.8 DN/e-), below the ADC's 15,583: the 500 ms point of the exposure sweep plateaus
    below the white level, so no raw value marks it."""
    from pipeline.simulate import simulate_dataset, truth_dir_for

    root = tmp_path_factory.mktemp("fullwell") / "dataset"
    simulate_dataset(root, scale="tiny", seed=22, effects=[("dark_current", {}), ("hot_pixels", {})],
                     experiments=("dark", "linearity"), progress=False, sensor={"full_well_e": 12500.0})
    truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())
    out = tmp_path_factory.mktemp("results")
    dark = {lens: out / f"dark/{lens}.nc" for lens in LENSES}
    lin = {lens: out / f"linearity/{lens}.nc" for lens in LENSES}
    run_stage("dark", root, config, dark, checked=True)
    run_stage("linearity", root, config, lin, {"dark": dark}, checked=True)
    return {k: xr.open_dataset(v).load() for k, v in lin.items()}, truth


def test_full_well_before_the_adc_is_found_and_left_out(full_well_artefacts):
    lin, truth = full_well_artefacts
    assert truth["derived"]["saturated_by"] == "full well"
    k_true = truth["derived"]["conversion_gain_dn_per_e_iso100"]
    for lens in LENSES:
        ds = lin[lens]
        sat = ds["saturation_dn"]
        assert int(sat.attrs["reached"]) == 1 and sat.attrs["saturated_by"] == "full well (plateau)"
        # every pixel of the mask sits at K x full well: the plateau is known to the read noise over
        # the mask (2 DN / sqrt(~100 pixels x 4 frames)) plus the dark model's level (0.1 DN)
        assert abs(float(sat) - truth["derived"]["saturation_dn"]) < 2.0, float(sat)
        assert int(ds["n_saturated_settings"]) >= 1
        # with the plateau left out, photon transfer gives the true gain (same tolerance as above),
        # where before it gave a negative gain and read noise
        k = float(ds["conversion_gain_dn_per_e"])
        assert abs(k - k_true) < max(4 * float(ds["conversion_gain_dn_per_e_sigma"]), 0.05 * k_true), k
        assert float(ds["read_noise_e"]) > 0
    # counted in the artefact and said in the report's linearity section (one lens: the figures cost)
    ds = lin[LENSES[0]]
    n = int(ds["n_saturated_settings"])
    html = render_fragment(_linearity_section(LENSES[0], ds, None))
    assert f"(reached; {n} saturated setting{'s' if n > 1 else ''} left out of the fits)" in html

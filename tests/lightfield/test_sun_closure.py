"""The sun as a closure of attitude and geometry, and the attitude fitted from it, against the simulator's truth.

The tiny camera that the session fixture ``calibrated`` calibrated photographs
the bracket scene (:mod:`pipeline.simulate.brackets`) with its sun where pvlib
puts it for the frame's site and UTC time, the camera tilted by a known
attitude, and an attitude log whose noise is stated. Only the shortest
exposures are rendered: the centroid uses the shortest alone.

- Closure over 8 seeds (site, time, roll and pitch up to 8 degrees, any
  heading; log noise 0.2, 0.2, 1.0 degree): every frame's chi^2 (2 dof)
  below its 0.999 quantile; the 16 residual components over their stated
  sigma with a spread within the 99 % interval of a unit normal's for 16
  values, sqrt(chi2_16 quantiles / 16) = 0.57 to 1.46 (measured 0.75), and a
  mean within 3 / sqrt(16). The geometry's stated theta sigma (about 0.9
  degree at the sun) is the largest term and is conservative here: over 24
  other seeds the spread is 0.67.
- A log whose heading is 5 degrees off (a good compass, stated sigma 0.3
  degree), at the seed whose sun is lowest: the horizontal component beyond
  3 sigma and naming the attitude's heading (its expected z, 5 sin Z / sigma,
  is checked to be at least 4 first); the offset within 3 sigma of 5.
- No log, the horizon level: the heading fitted from the sun within 3 of its
  stated sigma of the truth in each of 4 seeds; ``heading_tilt`` likewise, and
  its tilt within 3 sigma of 0.
- The command writes the sun variables (units) and the ``obs_sun`` rows; bad
  input (no site) one line.

Run time: about 10 s beyond the session fixture ``calibrated``.
"""

from __future__ import annotations

from dataclasses import replace
from datetime import datetime, timedelta

import numpy as np
import pandas as pd
import pytest
import xarray as xr
from scipy.stats import chi2

from pipeline.bundle.apply import BandChain
from pipeline.bundle.calibration import read_bundle
from pipeline.cli import main
from pipeline.geometry.sphere import ZENITH_LENS
from pipeline.io.artefact import model_effects
from pipeline.io.rawio import read_raw
from pipeline.lightfield.attitude import attitude_at, read_attitude, solar_position
from pipeline.lightfield.command import _full_scale_dn
from pipeline.lightfield.hdr import exposure_maps
from pipeline.lightfield.sun import fit_attitude_from_sun, sun_centroid, sun_closure
from pipeline.simulate.brackets import BracketScene, render_bracket, write_attitude_log

LOG_SIGMA_DEG = (0.2, 0.2, 1.0)
TILTED_SEEDS = range(8)
LEVEL_SEEDS = range(20, 24)
Z_LIMIT = 3.0


def _case(seed, tilted=True):
    rng = np.random.default_rng([seed, 7])
    site = (float(rng.uniform(30, 60)), float(rng.uniform(-80, -60)))
    start = datetime(2021, 3, 18, 14, 0, 0) + timedelta(minutes=float(rng.uniform(0, 240)))
    tilt = rng.uniform(-8, 8, 2) if tilted else np.zeros(2)
    return site, start, (float(tilt[0]), float(tilt[1]), float(rng.uniform(0, 360)))


def _solar(start, site):
    sz, sa = solar_position(pd.DatetimeIndex([pd.Timestamp(start, tz="UTC")]), *site)
    return float(sz[0]), float(sa[0])


@pytest.fixture(scope="module")
def camera(calibrated):
    bundle = read_bundle(calibrated[4])
    effects = model_effects(bundle)
    lenses = [str(x) for x in bundle["lens"].values]
    chains = {(lens, "G"): BandChain(bundle, lens, "G", "air", effects) for lens in lenses}
    full = _full_scale_dn(bundle, lenses)[:, 1]

    def centroid(path):
        maps = exposure_maps(read_raw(path), bundle, chains, lenses, "air", effects, ["G"])
        return sun_centroid(maps, bundle, lenses, "air", ZENITH_LENS, full, "G", 0)
    return centroid


def _render(tmp_path_factory, seed, tilted, exposures, name):
    site, start, att = _case(seed, tilted)
    folder = tmp_path_factory.mktemp(name)
    info = render_bracket(folder, BracketScene(attitude_deg=att), exposures, seed=seed, start=start, site=site,
                          attitude_log_sigma_deg=LOG_SIGMA_DEG)
    return {"seed": seed, "site": site, "start": start, "attitude": att, "info": info, "folder": folder}


@pytest.fixture(scope="module")
def tilted(camera, tmp_path_factory):
    out = []
    for seed in TILTED_SEEDS:
        case = _render(tmp_path_factory, seed, True, (1 / 4000,), f"tilted{seed}")
        case["centroid"] = camera(case["info"]["files"][0])
        case["solar"] = _solar(case["start"], case["site"])
        out.append(case)
    return out


@pytest.fixture(scope="module")
def level(camera, tmp_path_factory):
    out = []
    for seed in LEVEL_SEEDS:
        case = _render(tmp_path_factory, seed, False, (1 / 4000, 1 / 1000), f"level{seed}")
        case["centroid"] = camera(case["info"]["files"][0])
        case["solar"] = _solar(case["start"], case["site"])
        out.append(case)
    return out


def test_the_simulated_sun_is_where_pvlib_puts_it(tilted):
    for case in tilted:
        scene = case["info"]["scene"]
        assert (scene.sun_zenith_deg, scene.sun_azimuth_deg) == pytest.approx(case["solar"], abs=1e-9)


def test_closure_within_its_stated_uncertainty_over_seeds(tilted):
    """Every frame's chi^2 (2 dof) below its 0.999 quantile; the 16 components over their stated sigma with a
    spread within the 99 % interval of a unit normal's for 16 values and a mean within 3 / sqrt(16)."""
    z = []
    for case in tilted:
        att = attitude_at(read_attitude(case["info"]["attitude_log"]),
                          pd.DatetimeIndex([pd.Timestamp(case["start"], tz="UTC")]))[0]
        res = sun_closure(case["centroid"], att, *case["solar"], Z_LIMIT)
        assert res["chi2"] <= chi2.ppf(0.999, 2), (case["seed"], res)
        z += [res["z_zenith"], res["z_horizontal"]]
    z = np.array(z)
    lo, hi = np.sqrt(chi2.ppf([0.005, 0.995], z.size) / z.size)
    assert lo <= z.std() <= hi, (z.std(), lo, hi)
    assert abs(z.mean()) <= 3 / np.sqrt(z.size), z.mean()


def test_a_wrong_heading_is_significant_and_names_the_attitude(tilted, tmp_path):
    case = max(tilted, key=lambda c: c["solar"][0])             # the lowest sun: a heading error shows most
    sigma = (0.2, 0.2, 0.3)
    log = write_attitude_log(tmp_path / "att.csv", case["attitude"], case["start"], 1.0, seed=case["seed"],
                             sigma_deg=sigma, heading_bias_deg=5.0)
    att = attitude_at(read_attitude(log), pd.DatetimeIndex([pd.Timestamp(case["start"], tz="UTC")]))[0]
    res = sun_closure(case["centroid"], att, *case["solar"], Z_LIMIT)
    expected = 5.0 * np.sin(np.radians(case["solar"][0])) / res["residual_horizontal_sigma_deg"]
    assert expected >= 4.0, expected                            # the test's power, before its outcome
    assert abs(res["z_horizontal"]) > Z_LIMIT and "attitude heading" in res["named"], res
    assert abs(res["heading_offset_deg"] - 5.0) <= 3 * res["heading_offset_sigma_deg"], res
    right = sun_closure(case["centroid"], replace(att, heading_deg=att.heading_deg - 5.0), *case["solar"], Z_LIMIT)
    assert "attitude heading" not in right["named"]


@pytest.mark.parametrize("model", ["heading", "heading_tilt"])
def test_heading_fitted_from_the_sun_within_its_uncertainty(level, model):
    for case in level:
        fit = fit_attitude_from_sun(case["centroid"], *case["solar"], model)
        d = (fit["heading_deg"] - case["attitude"][2] + 180.0) % 360.0 - 180.0
        assert abs(d) <= 3 * fit["heading_sigma_deg"], (case["seed"], d, fit["heading_sigma_deg"])
        assert fit["heading_sigma_deg"] < 5.0
        if model == "heading_tilt":
            assert abs(fit["tilt_deg"]) <= 3 * fit["tilt_sigma_deg"], (case["seed"], fit)
        else:
            assert fit["dof"] == 1 and fit["chi2"] <= chi2.ppf(0.999, 1)    # the level assumption checked


def test_command_writes_the_closure_and_the_fitted_attitude(calibrated, level, tmp_path):
    case = level[0]
    info = case["info"]
    site = ",".join(f"{v:.6f}" for v in case["site"])
    files = [str(p) for p in info["files"]]
    common = ["lightfield", "--calibration", str(calibrated[4]), "--frames", str(info["frames_csv"]),
              "--grid-deg", "18", "--site", site, *files]
    assert main([*common, "--attitude", str(info["attitude_log"]), "-o", str(tmp_path / "log.nc")]) == 0
    with xr.open_dataset(tmp_path / "log.nc") as ds:
        assert ds["sun_angle_deg"].attrs["units"] == "degree" and ds["sun_z"].attrs["units"] == "1"
        assert ds["obs_sun__z"].size == 2
        assert float(ds["sun_chi2"][0]) <= chi2.ppf(0.999, 2)
        assert str(ds["sun_closure_named"].values[0]) == ""
    assert main([*common, "--attitude-from-sun", "heading", "-o", str(tmp_path / "fit.nc")]) == 0
    with xr.open_dataset(tmp_path / "fit.nc") as ds:
        d = (float(ds["heading_deg"][0]) - case["attitude"][2] + 180.0) % 360.0 - 180.0
        assert abs(d) <= 3 * float(ds["heading_sigma_deg"][0])
        assert "fitted from the sun" in ds.attrs["attitude"]


def test_attitude_from_sun_without_a_site_is_one_line(calibrated, level, tmp_path, capsys):
    info = level[0]["info"]
    args = ["lightfield", "--calibration", str(calibrated[4]), "--frames", str(info["frames_csv"]),
            "--attitude-from-sun", "heading", *map(str, info["files"]), "-o", str(tmp_path / "x.nc")]
    assert main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--site" in err[0]

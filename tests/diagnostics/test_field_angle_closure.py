"""The geometric calibration against the roll-off's rotation stage (``closure/field_angle``,
:mod:`pipeline.diagnostics.field_angle_closure`).

The simulator puts the sphere port at field angle |angle_deg| in the logged azimuth plane
(docs/dataset-format.md, rolloff); the geometry stage fits its own lens model to chessboards. On the tiny camera of
seed 5 (the shared ``calibrated`` fixture) the model's field angles sit 0.2 to 1.5 deg below the truth
(more towards the rim, where the boards do not reach), inside the geometry's stated covariance; the table
must hold that. A rotation stage whose logged angles are long by 4 % (the lab's gearing misread; the
frames.csv column rewritten here, a form no code of the package writes) must be found there. The table's
power against a pure scale error is bounded by the geometry's own stated scale error (about 1 % on the tiny
camera, one direction of its covariance): the same 4 % the other way, partly cancelling this geometry's
low field angles, stays inside it (chi2 459 for 408 dof against 460 clean).
"""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from pipeline.io.artefact import read_artefact
from pipeline.diagnostics.cross_closure import closure_observations
from pipeline.io.dataset import write_md5sums
from pipeline.diagnostics.tables import fit_observations, model_design
from pipeline.diagnostics.missing_effects import residual_tests
from pipeline.stats.fitting import base_design, wls
from pipeline.diagnostics.field_angle_closure import LEVEL, PRIOR_KIND, in_plane_angle_deg
from pipeline.geometry.scaramuzza import FisheyeModel
from pipeline.runner.workflow import run_stage, stage_params

LENSES = ("far", "close")
#: the logged angles' scale error of the hidden test: 4 % puts the 70 and 80 deg settings 2.8 and 3.2 deg
#: off (on top of this geometry's own 0.3 to 1.5 deg low), against the geometry's stated sigma there of
#: about 0.7 deg (air) and 0.5 deg (water), correlated over a lens and medium, and the centroid noise the
#: roll-off stage computes (about 0.1 band px here, 0.25 deg)
STAGE_SCALE = 1.04


def _loaded(artefacts: dict) -> dict:
    return {stage: [read_artefact(artefacts[stage][lens], stage) for lens in LENSES]
            for stage in ("geometry", "rolloff")}


def _field_angle(loaded, config):
    obs = [o for o in closure_observations(loaded, stage_params(config, "diagnostics")) if o.level == LEVEL]
    assert len(obs) == 1
    return obs[0]


def test_in_plane_angle_of_an_equidistant_lens():
    """An ideal equidistant lens (f(rho) from tan theta = rho / f, theta = rho / 20 rad per px near the axis):
    a pixel at distance rho along the plane's azimuth is at +theta, on the other side at -theta, and one
    across the plane at 0."""
    # f(rho) = a0 + a2 rho^2 with a0 = 20: theta ~ rho / 20 for small rho
    model = FisheyeModel(poly=(20.0, 0.0, 0.0), xc=10.0, yc=10.0, shape=(21, 21))
    expected = np.degrees(np.arctan2(2.0, 20.0))
    # azimuth 90: the image direction +y
    got = in_plane_angle_deg(model, np.array([10.0, 10.0, 12.0]), np.array([12.0, 8.0, 10.0]), 90.0)
    np.testing.assert_allclose(got, [expected, -expected, 0.0], atol=1e-12)


def test_clean_geometry_agrees_with_the_rotation_stage(calibrated, config):
    """Chi-square of the table (generalised least squares under the geometry's covariance and the centroid
    noise) within the two-sided 99 % range of its dof; one free zero per lens, medium and plane."""
    _, _, _, artefacts, _, _ = calibrated
    obs = _field_angle(_loaded(artefacts), config)
    t = obs.table
    spots = t[t["kind"] == "spot"]
    # both lenses and both media, both azimuth planes (air every 5 deg from -80 to 80, water every 2 deg from
    # -70 to 70, as the simulator's stride of the tiny scale leaves them)
    assert set(zip(spots["lens"], spots["medium"])) == {(lens, m) for lens in LENSES for m in ("air", "water")}
    assert set(spots["azimuth_deg"]) == {0.0, 90.0}
    fit = fit_observations(obs, model_design(obs, list(config["model"]["effects"])))
    lo, hi = stats.chi2.ppf([0.005, 0.995], fit.dof)
    assert lo < fit.chi2 < hi, (fit.chi2, fit.dof, lo, hi)
    tests = residual_tests([obs], list(config["model"]["effects"]), pd.DataFrame(), config["diagnostics"])
    assert not tests["significant"].any(), tests[["chi2", "dof", "p_value"]]
    # the lens model moved within its stated covariance: its prior rows' chi2 below the 99.5 % point
    prior = (t["kind"] == PRIOR_KIND).to_numpy()
    assert float(np.sum(fit.z[prior] ** 2)) < stats.chi2.ppf(0.995, int(prior.sum()))
    # the zeros of the planes: the simulator's stage reads 0 on the axis; each fitted zero within 1 deg
    # (the geometry's stated centre error on the tiny camera is about 0.4 deg, the centroid's 0.25 deg)
    X, names = base_design(t)
    zeros = wls(t["value_dn"].to_numpy(float), t["sigma_dn"].to_numpy(float), X).coef[
        [i for i, n in enumerate(names) if ":zero_az" in n]]
    assert len(zeros) == 2 * 2 * 2 and np.all(np.abs(zeros) < 1.0), zeros


#: degree of the polynomial in the angle that takes the centroids' smooth bias out of their error against the truth
#: (towards the axis, growing with the angle: the roll-off across the port and the cut's half-lit edge pixels;
#: :mod:`pipeline.diagnostics.field_angle_closure`), per lens, medium and azimuth plane
BIAS_DEGREE = 5


def test_the_centroid_sigma_holds_the_error_against_the_true_port(calibrated, config):
    """The roll-off's computed centroid uncertainty (``spot_x_sigma_px``, ``spot_y_sigma_px``, through the lens
    model's d a / d (u, v): each row's ``sigma_dn``) against the centroid's error in the truth: the in-plane angle of
    the measured centroid through the simulator's true G optics minus the logged angle (the simulator's stage reads
    0 on the axis). The smooth bias is not what the sigma states: a polynomial of degree ``BIAS_DEGREE`` in the
    angle per lens, medium and plane takes it out. If the rest is the sigma's Gaussian noise, independent from spot
    to spot, its sum of z^2 is chi-square with n - 8 (BIAS_DEGREE + 1) dof; the two-sided 99 % interval of that
    (about +/- 9 % in sigma at 368 dof) is the tolerance. Measured on this seed: rms z 0.98 (nine tiny seeds 0.96
    to 1.02; a fixed 0.1 px gave about 0.96 here and 0.76 at the small scale, where the computed sigma gives 0.96)."""
    from pipeline.simulate.rolloff import true_band_models

    _, _, _, artefacts, _, _ = calibrated
    t = _field_angle(_loaded(artefacts), config).table
    spots = t[t["kind"] == "spot"]
    band_px = int(read_artefact(artefacts["geometry"]["far"], "geometry")["theta_deg"].shape[-1])
    z, n_fit = [], 0
    for (lens, medium, az), g in spots.groupby(["lens", "medium", "azimuth_deg"]):
        true = true_band_models(lens, band_px)[(medium, "G")]
        err = np.ravel(in_plane_angle_deg(true, g["spot_x_px"].to_numpy(float), g["spot_y_px"].to_numpy(float),
                                          az)) - g["angle_deg"].to_numpy(float)
        X = np.vander(g["angle_deg"].to_numpy(float) / 90.0, BIAS_DEGREE + 1)
        rest = err - X @ np.linalg.lstsq(X, err, rcond=None)[0]
        z.append(rest / g["sigma_dn"].to_numpy(float))
        n_fit += X.shape[1]
    z = np.concatenate(z)
    dof = z.size - n_fit
    lo, hi = stats.chi2.ppf([0.005, 0.995], dof)
    assert lo < float(np.sum(z ** 2)) < hi, (float(np.sqrt(np.mean(z ** 2))), dof, lo, hi)


@pytest.fixture(scope="module")
def long_stage(calibrated, config, tmp_path_factory):
    """The roll-off rerun on the same frames with every logged angle times ``STAGE_SCALE``."""
    root, _, _, artefacts, _, _ = calibrated
    dst = tmp_path_factory.mktemp("long_stage") / "dataset"
    dst.mkdir(parents=True)
    shutil.copy(root / "dataset.yaml", dst / "dataset.yaml")
    shutil.copytree(root / "rolloff", dst / "rolloff")
    frames = pd.read_csv(dst / "rolloff" / "frames.csv", dtype={"angle_deg": str})
    lit = frames["angle_deg"].fillna("") != ""
    frames.loc[lit, "angle_deg"] = [f"{STAGE_SCALE * float(a):.6g}" for a in frames.loc[lit, "angle_deg"]]
    frames.to_csv(dst / "rolloff" / "frames.csv", index=False)
    write_md5sums(dst)
    out = tmp_path_factory.mktemp("long_stage_results")
    rolloff = {lens: out / "rolloff" / f"{lens}.nc" for lens in LENSES}
    run_stage("rolloff", dst, config, rolloff, {"geometry": artefacts["geometry"]})
    return {"geometry": artefacts["geometry"], "rolloff": rolloff}


def test_a_long_rotation_stage_is_found_in_the_field_angle_table(long_stage, config):
    obs = _field_angle(_loaded(long_stage), config)
    tests = residual_tests([obs], list(config["model"]["effects"]), pd.DataFrame(), config["diagnostics"])
    row = tests.set_index("level").loc[LEVEL]
    assert bool(row["significant"]), row[["chi2", "dof", "p_value"]]
    # where it shows: the geometry's nuisance columns take the smooth part of the angle error, so the lens
    # model is pulled far beyond its stated covariance and its prior rows carry the excess (clean: chi2 23 for
    # their 28 rows; here 248), beside a larger scatter of the spots (clean 437, here 500, 416 spots)
    fit = fit_observations(obs, model_design(obs, list(config["model"]["effects"])))
    prior = (obs.table["kind"] == PRIOR_KIND).to_numpy()
    assert prior.any()
    assert float(np.sum(fit.z[prior] ** 2)) > stats.chi2.isf(1e-6, int(prior.sum()))

"""Absolute-radiance stage recovers R^-1 (Larouche et al. 2024, Sections 2.6, 3.5; Table 1).

The whole chain runs on a tiny simulated dataset: spectral stage (measured
response) then absolute stage.  The camera saw the source through the TRUE
response on a 0.1 nm grid; the pipeline integrates Eq. (3) with its measured
10 nm response over 400-700 nm, which moves B's R^-1 by about +0.9 %
(unmeasured tail below 400 nm), within the 2 % asked.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import yaml

from pipeline.runner.workflow import run_stage
from pipeline.io.artefact import read_artefact
from pipeline.errors import InputError
from pipeline.simulate import simulate_dataset, truth_dir_for
from pipeline.stages.observations import dataset_to_table

from helpers import write_default_geometry

LENSES = ("far", "close")
BAND_SHAPE = (64, 64)   # tiny scale: 128 raw pixels per lens side


@pytest.fixture(scope="module")
def chain(tmp_path_factory, config):
    root = tmp_path_factory.mktemp("sim_absolute") / "dataset"
    simulate_dataset(root, scale="tiny", seed=8, experiments=("spectral", "absolute"), progress=False)
    truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())["experiments_truth"]
    out = tmp_path_factory.mktemp("results")
    geometry = write_default_geometry(out / "geometry", LENSES, BAND_SHAPE, media=("air",))
    spec = {lens: out / "spectral" / f"{lens}.nc" for lens in LENSES}
    run_stage("spectral", root, config, spec, {"geometry": geometry})
    outputs = {lens: out / "absolute" / f"{lens}.nc" for lens in LENSES}
    run_stage("absolute", root, config, outputs, {"spectral": spec, "geometry": geometry})
    arts = {lens: read_artefact(p, "absolute") for lens, p in outputs.items()}
    return root, truth["absolute"], arts, spec, geometry


def test_inverse_responsivity_within_2_percent(chain):
    _, truth, arts, _, _ = chain
    for lens in LENSES:
        for band in "RGB":
            a = arts[lens].sel(band=band)
            t = truth["bands"][band]
            rel = float(a["inverse_responsivity"]) / t["inverse_responsivity"] - 1
            assert abs(rel) < 0.02, (lens, band, rel)
            port = truth["lenses"][lens]["bands"][band]["effective_band_radiance_W_sr_m2_nm"]
            l_rel = float(a["effective_radiance"]) / port - 1
            assert abs(l_rel) < 0.02, (lens, band, l_rel)
    # Table 1 orders of magnitude: 1.2e-8, 7.5e-9, 1.2e-8 W sr-1 m-2 nm-1 per ADU/s
    np.testing.assert_allclose(arts["far"]["inverse_responsivity"].values, [1.2e-8, 7.4e-9, 1.2e-8], rtol=0.05)


def test_uncertainty_budget(chain):
    _, _, arts, _, _ = chain
    for lens in LENSES:
        a = arts[lens]
        rel = a["relative_sigma"].values
        # the reference reading's stated 2.5 % dominates; the lamp's scale cancels in the rescaling at
        # 589 nm and its colour-temperature part leaves 0.1-1 % (R to B); the region's spread ~1-2 %
        assert np.all((rel > 0.025) & (rel < 0.05)), rel
        assert list(a["dominant_term"].values) == ["reference"] * 3
        contrib = a["uncertainty_contribution"]
        np.testing.assert_allclose(np.sqrt((contrib**2).sum("term")).values, rel, rtol=1e-9)
        assert np.all(contrib.sel(term="reference").values == pytest.approx(0.025, rel=1e-4))
        lamp = contrib.sel(term="lamp_calibration").values
        assert 0 < lamp[0] < lamp[1] < lamp[2] < 0.015, lamp


def test_paper_lamp_counting_stays_available(chain, config, tmp_path):
    """absolute.lamp_model: profile counts the lamp in full, as Section 3.5 does: 7.5-9 % of 8-9.5 %."""
    root, _, arts, spec, geometry = chain
    cfg = {**config, "absolute": {**config["absolute"], "lamp_model": "profile"}}
    out = tmp_path / "far.nc"
    run_stage("absolute", root, cfg, {"far": out}, {"spectral": spec, "geometry": geometry})
    paper = read_artefact(out, "absolute")
    np.testing.assert_allclose(paper["inverse_responsivity"].values, arts["far"]["inverse_responsivity"].values,
                               rtol=1e-12)
    lamp = paper["uncertainty_contribution"].sel(term="lamp_calibration").values
    assert np.all((lamp > 0.075) & (lamp < 0.09)), lamp
    assert list(paper["dominant_term"].values) == ["lamp_calibration"] * 3


def test_observation_table_at_noise_floor(chain):
    _, _, arts, _, _ = chain
    for lens in LENSES:
        table = dataset_to_table(arts[lens], "obs_frame")
        for col in ("group", "value_dn", "sigma_dn", "pred_dn", "z", "x_level"):
            assert col in table
        assert len(table) == 3 * (10 + 5)
        assert 0.6 < float(arts[lens]["rms_z"]) < 1.5


def _copy(root, tmp_path):
    dst = tmp_path / "dataset"
    shutil.copytree(root, dst)
    return dst


def test_missing_reference_wavelength(chain, config, tmp_path):
    root, _, _, spec, geometry = chain
    dst = _copy(root, tmp_path)
    path = dst / "absolute" / "source_reference.csv"
    path.write_text("wavelength_nm,radiance_W_sr_m2_nm,uncertainty_rel\n625.0,0.0008,0.03\n")
    with pytest.raises(InputError, match=r"source_reference.csv.*589 nm"):
        run_stage("absolute", dst, config, {"far": tmp_path / "far.nc"}, {"spectral": spec, "geometry": geometry})


def test_spectrum_missing_column(chain, config, tmp_path):
    root, _, _, spec, geometry = chain
    dst = _copy(root, tmp_path)
    path = dst / "absolute" / "source_spectrum.csv"
    lines = path.read_text().splitlines()
    path.write_text("\n".join(",".join(line.split(",")[:2]) for line in lines) + "\n")
    with pytest.raises(InputError, match=r"source_spectrum.csv.*radiance_std"):
        run_stage("absolute", dst, config, {"far": tmp_path / "far.nc"}, {"spectral": spec, "geometry": geometry})


def test_spectrum_not_covering_response(chain, config, tmp_path):
    root, _, _, spec, geometry = chain
    dst = _copy(root, tmp_path)
    path = dst / "absolute" / "source_spectrum.csv"
    lines = path.read_text().splitlines()
    keep = [lines[0]] + [line for line in lines[1:] if float(line.split(",")[0]) >= 450]
    path.write_text("\n".join(keep) + "\n")
    with pytest.raises(InputError, match=r"source_spectrum.csv.*400-700 nm"):
        run_stage("absolute", dst, config, {"far": tmp_path / "far.nc"}, {"spectral": spec, "geometry": geometry})


def test_named_extra_uncertainty_components_enter_the_budget(chain, config, tmp_path):
    """absolute.extra_uncertainty: none by default; each named component adds in quadrature, and
    the R^-1 value itself does not move."""
    root, _, arts, spec, geometry = chain
    for lens in LENSES:
        assert float(arts[lens]["uncertainty_contribution"].sel(term="extra").max()) == 0.0
    components = [{"name": "sphere_drift", "relative_sigma": 0.03, "reason": "lab log, 2 h warm-up"},
                  {"name": "stray_light", "relative_sigma": 0.04}]
    cfg = {**config, "absolute": {**config["absolute"], "extra_uncertainty": components}}
    out = tmp_path / "far.nc"
    run_stage("absolute", root, cfg, {"far": out}, {"spectral": spec, "geometry": geometry})
    new, old = read_artefact(out, "absolute"), arts["far"]
    np.testing.assert_allclose(new["uncertainty_contribution"].sel(term="extra").values, 0.05, rtol=1e-12)
    np.testing.assert_allclose(new["inverse_responsivity"].values, old["inverse_responsivity"].values, rtol=1e-12)
    np.testing.assert_allclose(new["relative_sigma"].values ** 2, old["relative_sigma"].values ** 2 + 0.05**2, rtol=1e-9)
    assert "sphere_drift" in new.attrs["extra_uncertainty"]
    twice = {**config, "absolute": {**config["absolute"], "extra_uncertainty": components[:1] * 2}}
    with pytest.raises(InputError, match="given twice"):
        run_stage("absolute", root, twice, {"far": tmp_path / "x.nc"}, {"spectral": spec, "geometry": geometry})

"""Immersion stage with the fitted response: air and water frames through the measurement chain.

The simulated camera bends its response (``nonlinearity``, beta = 0.1 of the ADC range);
air frames are brighter than the water frames below them, so a nominal Eq. (2) biases
the air/water ratio and hence I. With the lens's linearity artefact (which fitted beta)
the stage linearises both before the log-linear fit (radiometry.response).
"""

from __future__ import annotations

import pytest
import yaml

from helpers import true_geometry_dataset
from pipeline.io.artefact import read_artefact, write_artefact
from pipeline.simulate import simulate_dataset, truth_dir_for
from pipeline.runner.workflow import run_stage

LENSES = ("far", "close")


@pytest.fixture(scope="module")
def runs(config, tmp_path_factory):
    d = tmp_path_factory.mktemp("imm_response")
    root = d / "dataset"
    simulate_dataset(root, scale="tiny", seed=7, effects=[("dark_current", {}), ("nonlinearity", {"beta": 0.1})],
                     experiments=("dark", "linearity", "immersion"), progress=False)
    truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())["experiments_truth"]["immersion"]
    cfg = {**config, "model": {**config["model"], "effects": ["dark_current", "hot_pixels", "nonlinearity"]}}
    geo = {lens: write_artefact(true_geometry_dataset(lens, 64), d / f"geometry_{lens}.nc", stage="geometry",
                                inputs={}, config_subset={}, effects=[]) for lens in LENSES}
    dark = {lens: d / f"dark_{lens}.nc" for lens in LENSES}
    lin = {lens: d / f"linearity_{lens}.nc" for lens in LENSES}
    run_stage("dark", root, cfg, dark)
    run_stage("linearity", root, cfg, lin, {"dark": dark})
    out = {}
    for label, upstream in (("chain", {"geometry": geo, "linearity": lin}), ("nominal", {"geometry": geo})):
        paths = {lens: d / f"immersion_{label}_{lens}.nc" for lens in LENSES}
        run_stage("immersion", root, cfg, paths, upstream)
        out[label] = {lens: read_artefact(p, "immersion") for lens, p in paths.items()}
    return out, truth


def test_immersion_through_the_fitted_response(runs):
    out, truth = runs
    for lens in LENSES:
        chain, nominal = out["chain"][lens], out["nominal"][lens]
        assert chain.attrs["response_corrections"] == "nonlinearity"
        assert nominal.attrs["response_corrections"] == ""
        for band in "RGB":
            err = float(chain["immersion_factor"].sel(band=band)) - truth["immersion_factor"][band]
            sigma = float(chain["immersion_factor_sigma"].sel(band=band))
            # the fit's stated uncertainty (log-linear fit over 11 heights, 5 frames each) explains the error
            assert abs(err) < 3 * sigma, (lens, band, err, sigma)
        # G has the largest signals, so the largest nonlinearity bias between air and water: removed. Both runs
        # reduce the same frames, so their difference is the bias the chain removes, free of most of the frames'
        # noise (0.0017 in each): +0.0025 to +0.0028 for both lenses at seeds 7, 8 and 9 (the simulator's
        # measured-response camera and the former one alike). Comparing |error| of the two runs instead is a
        # coin flip weighted about 3 to 1 per lens (the chain's error, N(0, 0.0017), need only fall below minus
        # half the bias to lose), which the measured-response camera's far lens lost at seed 7 (-0.0018 against
        # +0.0010); the chain's own error is held to its stated sigma above.
        err_chain = float(chain["immersion_factor"].sel(band="G")) - truth["immersion_factor"]["G"]
        err_nominal = float(nominal["immersion_factor"].sel(band="G")) - truth["immersion_factor"]["G"]
        assert err_nominal - err_chain > 0.0015, (lens, err_chain, err_nominal)

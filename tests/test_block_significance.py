"""Significance at the level of independent measurements: rows of one raw frame share its fluctuations.

The lab's noise (source flicker, black-level jitter; :mod:`pipeline.simulate.lab_noise`) is common to all
rows of one frame (both lenses, three bands). The diagnostics group such rows into blocks and test each
candidate with a cluster-robust covariance by block (:mod:`pipeline.diagnostics`). Here:

* synthetic dark frame-level tables with block-correlated noise that the stated ``sigma_dn`` leaves out,
  and a candidate (``temperature``) whose signature varies from frame to frame but has no effect: the
  false-alarm rate at the nominal level must stay within the binomial bound, while the test of rows as
  independent alarms in most draws (which shows the data are hard enough);
* one tiny simulated dataset with the lab noise on: the lab's black-level jitter is found as the
  ``bias_drift`` it physically is, at its simulated size, and nothing else; with ``bias_drift`` in the model
  nothing is significant;
* a real hidden effect (``shutter_offset``) is still ranked first and significant with the lab noise on.

The tolerances: the binomial 0.999 quantile for the false-alarm count; the jitter's sigma inside the
interval the diagnostics state for it (95 %, widened by the chi-square interval of a variance).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from pipeline.diagnostics import Observations, candidate_significance
from pipeline.simulate.lab_noise import LabNoise

from test_hidden_effects import CASES, analyse

#: frames per setting, settings, and the frame-common noise in units of the stated per-row sigma
N_FRAMES, N_SETTINGS, BLOCK_SIGMA = 8, 5, 2.0


def synthetic_dark_frames(rng: np.random.Generator) -> pd.DataFrame:
    """Dark frame-level rows (2 lenses x 3 bands per frame); a constant level per lens/band/setting, plus
    noise common to a frame (BLOCK_SIGMA x sigma) and independent noise (sigma); the logged temperature
    wanders from frame to frame but has no effect."""
    rows = []
    sigma = 0.03
    for setting in range(N_SETTINGS):
        for f in range(N_FRAMES):
            file_index = setting * N_FRAMES + f
            common = BLOCK_SIGMA * sigma * rng.standard_normal()
            temp = 25.0 + 0.3 * rng.standard_normal()
            for lens in ("far", "close"):
                for band in ("R", "G", "B"):
                    rows.append({"lens": lens, "band": band, "setting": setting, "file_index": file_index,
                                 "frame": f, "temperature_c": temp, "x_level": 1.0, "sigma_dn": sigma,
                                 "value_dn": 800.0 + common + sigma * rng.standard_normal()})
    table = pd.DataFrame(rows)
    table["group"] = table["lens"] + "/" + table["band"] + "/" + table["setting"].astype(str)
    return table


def test_false_alarm_rate_with_block_correlated_noise_is_nominal(config):
    """400 draws at level 0.05: at most the binomial 0.999 quantile of false alarms (35 of 400; measured 18,
    and 5 of 400 at level 0.01). CPU about 7 s."""
    n_draws, level = 400, 0.05
    rng = np.random.default_rng(20261201)
    p_block, p_rows = [], []
    for _ in range(n_draws):
        obs = [Observations("dark", "frame", synthetic_dark_frames(rng))]
        r = candidate_significance("temperature", obs, [], config)
        p_block.append(r["p_value"])
        p_rows.append(r["p_value_model"])
    alarms = int(np.sum(np.array(p_block) < level))
    bound = stats.binom.ppf(0.999, n_draws, level)
    assert alarms <= bound, (alarms, bound)
    # rows treated as independent: the frame-common noise makes the wandering temperature look significant
    assert np.mean(np.array(p_rows) < level) > 0.3
    # not merely conservative: at least half the binomial 0.001 quantile (8) of the 20 expected
    assert alarms >= stats.binom.ppf(0.001, n_draws, level) / 2, alarms


@pytest.fixture(scope="module")
def lab_noise_dataset(make_dataset):
    return make_dataset([], seed=211, lab_noise=True)


def test_lab_noise_jitter_is_found_as_bias_drift_and_nothing_else(lab_noise_dataset, config):
    root, truth = lab_noise_dataset
    _, _, ranked, _ = analyse(root, config, [])
    significant = ranked[ranked["significant"]]
    assert list(significant["effect"]) == ["bias_drift"], ranked.head(4).to_string()
    jitter = truth["lab_noise"]["bias_jitter_dn"]
    row = significant.iloc[0]
    assert row["amplitude_low"] <= jitter <= row["amplitude_high"], (row["amplitude_low"], row["amplitude_high"])


def test_clean_data_with_lab_noise_comes_out_clean(lab_noise_dataset, config):
    root, _ = lab_noise_dataset
    _, _, ranked, figures = analyse(root, config, ["bias_drift"])
    assert not ranked["significant"].any(), ranked.head(3).to_string()
    # 4 standard deviations of chi2/dof above 1, as in the hidden-effect tests
    assert (figures["rms_z"].to_numpy() < 1.0 + 2.0 * np.sqrt(2.0 / figures["dof"].to_numpy())).all(), figures


def test_hidden_effect_found_with_lab_noise(make_dataset, config):
    root, _ = make_dataset([("shutter_offset", CASES["shutter_offset"])], seed=212,
                           lab_noise=LabNoise())
    _, _, ranked, _ = analyse(root, config, ["bias_drift"])
    assert ranked.iloc[0]["effect"] == "shutter_offset", ranked.head(3).to_string()
    assert bool(ranked.iloc[0]["significant"])

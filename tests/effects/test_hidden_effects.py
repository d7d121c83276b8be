"""Hidden-effect cases: the diagnostics find each effect from the residuals alone.

For each effect: simulate the camera with it switched on (at a parameter value
other than the simulator's default, so nothing is tuned to one value), run
the base model, check that the diagnostics rank the effect first and call it
significant; then put the effect in the model and check that the residuals
fall to the noise floor and that the fitted parameter matches the truth. The
diagnostics read only the stage artefacts, never the truth folder.
"""

from __future__ import annotations

import numpy as np
import pytest

from hidden_effects import CASES, analyse

def noise_floor(figures):
    """rms_z^2 = chi2/dof has spread sqrt(2/dof): allow 4 of those (one-sided)."""
    return 1.0 + 2.0 * np.sqrt(2.0 / figures["dof"].to_numpy())


@pytest.mark.parametrize("effect", list(CASES))
def test_hidden_effect_found_and_fixed(effect, make_dataset, config):
    root, truth = make_dataset([(effect, CASES[effect])], seed=101)

    _, _, ranked, figures = analyse(root, config, [])
    assert ranked.iloc[0]["effect"] == effect, ranked.head(3).to_string()
    assert bool(ranked.iloc[0]["significant"])
    assert (figures["rms_z"] > noise_floor(figures)).any()

    dark, lin, ranked_after, figures_after = analyse(root, config, [effect])
    assert (figures_after["rms_z"].to_numpy() < noise_floor(figures_after)).all(), figures_after
    assert not ranked_after["significant"].any(), ranked_after.head(3).to_string()
    # nor any table's residual chi-square beyond its dof (per experiment and level)
    assert not len(analyse.unexplained), analyse.unexplained["message"].tolist()

    check_parameter(effect, truth, dark, lin)


def check_parameter(effect, truth, dark, lin):
    t = truth["effects"][effect]
    k100 = truth["derived"]["conversion_gain_dn_per_e_iso100"]
    if effect == "dark_current":
        d = float(dark["far"]["dark_current_dn_per_s"])
        se = float(dark["far"]["dark_current_dn_per_s_sigma"])
        # 4 standard errors, plus 1 % for the fixed pattern's gain dependence
        assert abs(d - t["rate_e_per_s"] * k100) < 4 * se + 0.01 * d
    elif effect == "hot_pixels":
        for lens, count in t["count_raw_pixels"].items():
            found = int(dark[lens]["hot_pixel_count"].sum())
            assert count - 2 <= found <= count   # two hot sites may share a G band pixel
    elif effect in ("shutter_offset", "nonlinearity"):
        key = {"shutter_offset": "offset_s", "nonlinearity": "beta"}[effect]
        got = float(lin["far"][f"effect_{effect}"].values[0])
        se = float(lin["far"][f"effect_{effect}_sigma"].values[0])
        assert abs(got - t[key]) < 4 * se, (got, se, t[key])
    elif effect == "iso_gain":
        ds = lin["far"]
        isos = ds["effect_iso_gain_iso"].values
        got = ds["effect_iso_gain"].values
        se = ds["effect_iso_gain_sigma"].values
        expected = np.array([t["factors"][str(int(i))] - 1 for i in isos])
        assert np.all(np.abs(got - expected) < 4 * se + 1e-3), (got, expected, se)
    elif effect == "prnu":
        lo, hi = [float(v) for v in lin["far"]["effect_prnu"].values[:1]] * 2
        got = float(np.sqrt(lin["far"]["effect_prnu"].values[0]))
        se_sq = float(lin["far"]["effect_prnu_sigma"].values[0])
        # the coefficient is sigma^2; 4 standard errors on it
        assert abs(got**2 - t["sigma_rel"] ** 2) < 4 * se_sq, (got, t["sigma_rel"])
    elif effect == "temperature":
        got = float(dark["far"]["temperature_bias_dn_per_c"])
        se = float(dark["far"]["temperature_bias_dn_per_c_sigma"])
        assert abs(got - t["bias_dn_per_c"]) < 4 * se + 0.01, (got, se)
    elif effect == "bias_drift":
        lo, hi = float(dark["far"]["bias_drift_dn_low"]), float(dark["far"]["bias_drift_dn_high"])
        assert lo <= t["sigma_dn"] <= hi, (lo, hi)


@pytest.mark.parametrize("seed", [201, 202, 203])
def test_clean_data_comes_out_clean(seed, make_dataset, config):
    root, _ = make_dataset([], seed=seed)
    _, _, ranked, figures = analyse(root, config, [])
    assert not ranked["significant"].any(), ranked.head(3).to_string()
    assert (figures["rms_z"].to_numpy() < noise_floor(figures)).all()
    # the residual chi-square of every table within its dof (family-wise level diagnostics.structure_level)
    assert not len(analyse.unexplained), analyse.unexplained["message"].tolist()

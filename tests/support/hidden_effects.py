"""The hidden-effect cases (an effect at a value other than the simulator's default) and the dark and linearity
analysis the diagnostics rank them from, shared by the hidden-effect and block-significance tests."""

from __future__ import annotations

from pipeline.diagnostics.missing_effects import error_figures, rank_missing_effects
from pipeline.diagnostics.tables import observations_from_artefacts
from pipeline.io.dataset import open_dataset
from pipeline.stages.dark import analyse_dark, reduce_dark
from pipeline.stages.linearity import analyse_linearity, reduce_linearity

CASES = {
    "prnu": {"sigma_rel": 0.015},
    "temperature": {"bias_dn_per_c": 0.4, "dark_doubling_c": 6.0},
    "dark_current": {"rate_e_per_s": 1.3},
    "hot_pixels": {"fraction": 8e-4, "median_rate_e_per_s": 300.0},
    "shutter_offset": {"offset_s": 6e-4},
    "nonlinearity": {"beta": 0.04},
    "iso_gain": {"rel_sigma": 0.025},
    "bias_drift": {"sigma_dn": 2.5},
}


_REDUCED = {}


def analyse(root, config, model):
    ds = open_dataset(root)
    if root not in _REDUCED:           # the dark reduction does not depend on the model
        _REDUCED[root] = reduce_dark(ds, config)
    dark = analyse_dark(_REDUCED[root], config, model)
    lin = analyse_linearity(reduce_linearity(ds, dark, config, model), dark, config, model)
    obs = observations_from_artefacts({"dark": list(dark.values()), "linearity": list(lin.values())})
    ranked, unexplained = rank_missing_effects(obs, model, config)
    analyse.unexplained = unexplained
    return dark, lin, ranked, error_figures(obs, model)

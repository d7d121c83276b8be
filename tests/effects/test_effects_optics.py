"""Hidden-effect cases for rolloff_azimuth, immersion_angle and stray_light (as tests/effects/test_hidden_effects.py).

``immersion_angle`` is injected in a form the package does not use (:func:`coating_loss`, defined
here): an absorbing layer on the outer surface whose path grows as 1 / cos of the refracted angle in
the glass. The package's own term is (theta / 60)^4 against the closure's prediction from air.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.diagnostics.tables import observations_from_artefacts

from pipeline.diagnostics.missing_effects import error_figures, rank_missing_effects
from pipeline.simulate import simulate_dataset
from pipeline.io.dataset import open_dataset
from pipeline.effects.optics import ImmersionAngle
from pipeline.simulate.rolloff import ANGLES_DEG
from pipeline.stages.rolloff import analyse_rolloff, reduce_rolloff

from helpers import true_geometry_dataset

CASES = {
    "rolloff_azimuth": {"amplitude": 0.02, "phi0_deg": 50.0},
    # immersion_angle: the optical depth tau of the coating (coating_loss), passed as the effect's parameter
    "immersion_angle": {"kappa": 0.06},
    "stray_light": {"fraction": 0.01},
}

#: water and front-surface indices of the coating's refraction (the simulator's tank and window, G)
COATING_N_WATER, COATING_N_GLASS = 1.334, 1.63


def coating_loss(self, lens, medium, theta_deg, phi_deg, band_index):
    """In-water transmission exp(-tau (1 / cos theta_g - 1)), theta_g the refracted angle in the glass."""
    if medium != "water":
        return 1.0
    s = np.sin(np.radians(np.minimum(np.asarray(theta_deg, float), 90.0))) * COATING_N_WATER / COATING_N_GLASS
    return np.exp(-self.params["kappa"] * (1.0 / np.sqrt(1.0 - s**2) - 1.0))


def coating_kappa(tau: float) -> float:
    """The package's kappa that best matches the coating's loss over the water field angles (least squares
    of kappa (theta / 60)^4 against 1 - transmission, 0 to 70 deg): the value the closure should find."""
    theta = np.abs(ANGLES_DEG["water"])
    u4 = (theta / 60.0) ** 4
    loss = 1.0 - coating_loss(type("P", (), {"params": {"kappa": tau}})(), "", "water", theta, 0.0, 0)
    return float(np.sum(u4 * loss) / np.sum(u4 * u4))


@pytest.fixture(scope="module")
def config(config):
    """The session config with exact field angles: these tests use the simulator's true
    geometry maps, so the field angle carries no calibration error."""
    return {**config, "rolloff": {**config["rolloff"], "field_angle_sigma_px": 0.0}}

@pytest.fixture(scope="module")
def reduced(tmp_path_factory, config):
    cache = {}

    def get(effect):
        if effect not in cache:
            root = tmp_path_factory.mktemp("fx") / "dataset"
            with pytest.MonkeyPatch.context() as mp:
                if effect == "immersion_angle":
                    mp.setattr(ImmersionAngle, "optics_factor", coating_loss)
                simulate_dataset(root, scale="tiny", seed=17, effects=[(effect, CASES[effect])],
                                 experiments=("rolloff",), progress=False)
            geo = {lens: true_geometry_dataset(lens, 64) for lens in ("far", "close")}
            cache[effect] = reduce_rolloff(open_dataset(root), geo, config)
        return cache[effect]

    return get


def analyse(red, config, model):
    arts = analyse_rolloff(red, config, model)
    obs = observations_from_artefacts({"rolloff": list(arts.values())})
    ranked, _ = rank_missing_effects(obs, model, config)
    return arts, ranked, error_figures(obs, model)


def noise_floor(figures):
    return 1.0 + 2.0 * np.sqrt(2.0 / figures["dof"].to_numpy())


@pytest.mark.parametrize("effect", ["rolloff_azimuth", "immersion_angle", "stray_light"])
def test_optics_effect_found_and_fixed(effect, reduced, config):
    red = reduced(effect)
    _, ranked, figures = analyse(red, config, [])
    assert ranked.iloc[0]["effect"] == effect, ranked.head(3).to_string()
    assert bool(ranked.iloc[0]["significant"])
    assert (figures["rms_z"] > noise_floor(figures)).any()

    arts, ranked_after, figures_after = analyse(red, config, [effect])
    assert (figures_after["rms_z"].to_numpy() < noise_floor(figures_after)).all(), figures_after
    assert not ranked_after["significant"].any(), ranked_after.head(3).to_string()

    ds = arts["far"]
    got = float(ds[f"effect_{effect}"].values[0])
    se = float(ds[f"effect_{effect}_sigma"].values[0])
    if effect == "rolloff_azimuth":
        assert abs(got - CASES[effect]["amplitude"]) < 4 * se + 0.002, (got, se)
        phi0 = float(ds["effect_rolloff_azimuth_phi0_deg"])
        assert abs(phi0 - CASES[effect]["phi0_deg"]) < 10.0, phi0
    elif effect == "immersion_angle":
        # another functional form: kappa is the best (theta/60)^4 match of the coating's loss, within
        # 4 sigma plus 15 % of it (the fit weights the angles by their noise, the projection does not)
        want = coating_kappa(CASES[effect]["kappa"])
        assert abs(got - want) < 4 * se + 0.15 * want, (got, se, want)
    else:
        # the spot itself loses the spread fraction: coefficient f / (1 - f)
        assert abs(got - CASES[effect]["fraction"]) < 4 * se + 0.1 * CASES[effect]["fraction"], (got, se)


@pytest.mark.parametrize("lens", ["far", "close"])
def test_azimuthal_rolloff_recovered_for_each_lens(lens, reduced, config):
    """The stage fits each lens alone (one job per lens): A and phi0 of that lens's own settings, on the
    simulator's true geometry, within 3 of their stated sigmas of the injected 0.02 and 50 deg (about
    0.0005 and 1.4 deg: spot noise only, the field angles exact)."""
    red = reduced("rolloff_azimuth")
    one = {"acc": {k: v for k, v in red["acc"].items() if k[0] == lens},
           "masks": {k: v for k, v in red["masks"].items() if k[0] == lens},
           "static": {k: v for k, v in red["static"].items() if k[0] == lens}, "inputs": red["inputs"]}
    ds = analyse_rolloff(one, config, ["rolloff_azimuth"])[lens]
    amp, amp_se = float(ds["effect_rolloff_azimuth"].values[0]), float(ds["effect_rolloff_azimuth_sigma"].values[0])
    phi0, phi0_se = float(ds["effect_rolloff_azimuth_phi0_deg"]), float(ds["effect_rolloff_azimuth_phi0_deg_sigma"])
    assert abs(amp - CASES["rolloff_azimuth"]["amplitude"]) < 3 * amp_se, (amp, amp_se)
    assert abs(phi0 - CASES["rolloff_azimuth"]["phi0_deg"]) < 3 * phi0_se, (phi0, phi0_se)

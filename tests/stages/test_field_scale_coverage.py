"""The field scale closure's stated uncertainty covers the lab calibration's real error, over simulated labs.

Each seed is a new lab session and field hour of the same camera: ``simulate_dataset(..., lab_errors=True)``
draws the absolute experiment's systematic errors (the reference radiometer's scale at 589 nm, ~ N(0, 2.5 %);
the spectrometer lamp's colour-temperature shape) and the field simulation draws the field reference's own
calibration error (~ N(0, 2.5 %) common to its channels, N(0, 0.5 %) per channel), besides every frame's
noise. The rest of the calibration (dark, linearity, geometry, roll-off, spectral) is one, the session's
``calibrated`` camera (conftest.py, the quiet lab of seed 5). Per seed: the absolute stage on the field lens, the
bundle of the field lens, the field stage on that seed's hour; per band z_b = ln k_b / sigma_b of the scale closure.

Bound (the issue's): the fraction of bands with |z_b| <= 1.96 lies between 0.85 and 1.0. With the stated
budget right it is about 0.95; the budget counts the field reference's 2.5 % and the lab reference's 2.5 %
(inside R^-1's) as independent, which they are here (two draws), and states neither the field reference's
per-channel 0.5 % nor the camera's in-band mismatch between the lamp and the sky (the default camera's B reads
a few percent high against the 490 nm channel, the measured response's unmeasured tail below 400 nm weighing
the blue sky more than the 2796 K lamp); a budget that left out the reference's calibration (2.5 %) would
bring the fraction near 0.75, one that counted the paper's lamp profile (8 %) near 1.0 with z spread 0.4.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from pipeline.bundle.calibration import BUNDLE_STAGES, build_bundle
from pipeline.stages.observations import dataset_to_table
from pipeline.simulate import simulate_dataset
from pipeline.runner.workflow import run_stage

N_LABS = 20
FIRST_SEED = 2000
#: the lens field/frames.csv names (the one at the zenith)
FIELD_LENS = "close"
#: the scale closure does not use the match-up statistics' bootstrap: its smallest allowed count keeps the job short
BOOTSTRAP_RESAMPLES = 100


@pytest.fixture(scope="module")
def scales(calibrated, config, tmp_path_factory):
    """Per lab and band: the field scale closure's row."""
    _, _, _, artefacts, _, meta = calibrated
    cfg = copy.deepcopy(config)
    cfg["field"]["bootstrap_resamples"] = BOOTSTRAP_RESAMPLES
    # the field lens alone: the bundle of the lens the field frames are of
    upstream = {stage: {FIELD_LENS: artefacts[stage][FIELD_LENS]} for stage in BUNDLE_STAGES if stage != "absolute"}
    rows = []
    for i in range(N_LABS):
        seed = FIRST_SEED + i
        work = tmp_path_factory.mktemp(f"field-lab{seed}")
        data = simulate_dataset(work / "dataset", scale="tiny", seed=seed, experiments=("absolute", "field"),
                                progress=False, lab_errors=True)
        absolute = {FIELD_LENS: work / "absolute" / f"{FIELD_LENS}.nc"}
        run_stage("absolute", data, cfg, absolute,
                  {name: upstream[name] for name in ("spectral", "geometry", "dark", "linearity")})
        bundle = work / "calibration.nc"
        build_bundle({**upstream, "absolute": absolute}, bundle, meta["camera"], {FIELD_LENS: meta["lenses"][FIELD_LENS]},
                     cfg)
        art = run_stage("field", data, cfg, {FIELD_LENS: work / "field.nc"}, bundle=bundle)[FIELD_LENS]
        table = dataset_to_table(art, "obs_scale")
        table["seed"] = seed
        rows.append(table)
    import pandas as pd

    return pd.concat(rows, ignore_index=True)


def test_field_scale_interval_covers_the_lab_calibrations_error(scales):
    z = (scales["value_dn"] / scales["sigma_dn"]).to_numpy(float)
    assert scales["seed"].nunique() == N_LABS >= 20
    covered = float(np.mean(np.abs(z) <= 1.96))
    info = (f"{covered:.2f} of {z.size} bands within 1.96 stated sigma; z per band: "
            + "; ".join(f"{b} mean {np.mean(z[scales['band'] == b]):+.2f} sd {np.std(z[scales['band'] == b], ddof=1):.2f}"
                        for b in ("R", "G", "B")))
    print(info)
    assert 0.85 <= covered <= 1.0, info


def test_the_labs_and_the_field_references_differ(scales):
    """The scales scatter by the two references' draws (about 3.5 % in quadrature), not by the frames' noise alone
    (the fit term, under 0.5 %): a spread below 1.5 % has chance under 1e-4 at N = 20."""
    for band in ("R", "G", "B"):
        t = scales[scales["band"] == band]
        assert float(np.std(t["value_dn"], ddof=1)) > 0.015, band
        assert float(t["sigma_fit"].max()) < 0.01, band

"""Units that parse: every ``units`` attribute of the tiny run's files is a UDUNITS-2 unit (issue 32, item 5).

The files are those of the shared ``calibrated`` fixture (the seven lab stages of both lenses and the
bundle), with what the pipeline makes from them in a second or two here: ``apply`` on one frame (the
per-pixel maps and the sphere grid), the closure table and the comparison of the bundle with itself. Each
file claims ``Conventions: CF-1.10``; UDUNITS-2 itself (the C library that cf-units bundles) parses every
``units``, and where a variable keeps the camera's spelling (``camera_units``) it is the same unit once
DN, electron, photon and pixel are counted (tests/support/cf_units_check.py). The field stage's artefact is checked in
tests/stages/test_field_stage.py, on the one that file's fixture writes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from cf_units_check import camera_unit, count_units, units_problems, udunits
from pipeline.bundle.apply import apply_calibration
from pipeline.io.artefact import read_artefact
from pipeline.bundle.calibration import BUNDLE_STAGES
from pipeline.bundle.compare import compare_bundles, write_comparison
from pipeline.diagnostics.tables import observations_from_artefacts
from pipeline.diagnostics.missing_effects import write_closure_table
from pipeline.io.units import udunits_spelling


def _signal_frame(root: Path, lens: str) -> Path:
    rows = [line.split(",") for line in (root / "absolute" / "frames.csv").read_text().splitlines()[1:]]
    return root / "absolute" / next(f for f, ln, kind in rows if ln == lens and kind == "signal")


@pytest.fixture(scope="module")
def tiny_run(calibrated, config, tmp_path_factory):
    """Every NetCDF file of the tiny run: {kind: path}."""
    root, _, _, artefacts, bundle_path, meta = calibrated
    out = tmp_path_factory.mktemp("units")
    files = {f"{stage}/{lens}": Path(path) for stage in BUNDLE_STAGES for lens, path in artefacts[stage].items()}
    files["calibration"] = Path(bundle_path)
    lens = next(iter(meta["lenses"]))
    files["apply"] = apply_calibration(bundle_path, [_signal_frame(root, lens)], "air", out / "apply.nc")
    loaded = {stage: [read_artefact(path, stage) for path in paths.values()] for stage, paths in artefacts.items()}
    # the closure artefact's attributes are the same whichever tables it holds: the smaller ones (all but the
    # roll-off's settings and the spectral frames, 10 s of fits) still give it rows in DN, DN2 and 1
    observations = [obs for obs in observations_from_artefacts(loaded) if len(obs.table) < 1000]
    files["closure"] = write_closure_table(observations, [], config, out / "closure" / "residuals.nc", inputs={})
    files["compare"] = write_comparison(compare_bundles(bundle_path, bundle_path, config), out / "compare.nc")
    return files


def test_every_units_attribute_of_the_tiny_run_parses_with_udunits(tiny_run):
    problems = [line for path in tiny_run.values() for line in units_problems(path)]
    assert not problems, "\n".join(problems)
    # the check saw the files' units: each file has some (485 in the stage artefacts and the bundle alone)
    counts = {kind: count_units(path) for kind, path in tiny_run.items()}
    assert all(n > 0 for n in counts.values()), counts


def test_camera_units_are_kept_and_read_back_as_written(tiny_run):
    """DN, electron, photon and pixel (not UDUNITS-2 units) are on disk as counts with the camera's spelling beside them,
    and an artefact read by the pipeline has the units its stage wrote."""
    with xr.open_dataset(tiny_run["linearity/far"]) as raw:
        assert raw["read_noise_e"].attrs["units"] == "count" and raw["read_noise_e"].attrs["camera_units"] == "electron"
        assert raw["rate_dn_per_s"].attrs["units"] == "count s-1"
        assert raw["conversion_gain_dn_per_e"].attrs["units"] == "1"
    read = read_artefact(tiny_run["linearity/far"], "linearity")
    assert read["rate_dn_per_s"].attrs["units"] == "DN s-1" and "camera_units" not in read["rate_dn_per_s"].attrs
    assert read["conversion_gain_dn_per_e"].attrs["units"] == "DN/electron"
    with xr.open_dataset(tiny_run["absolute/close"]) as raw:
        r_inv = raw["inverse_responsivity"].attrs
    # R^-1 in W sr-1 m-2 nm-1 per DN s-1: UDUNITS-2 gives it the dimension of radiance times time
    assert udunits(r_inv["units"]) == udunits("W m-2 sr-1 nm-1 s")
    assert r_inv["camera_units"] == "W sr-1 m-2 nm-1 s DN-1"


@pytest.mark.parametrize("camera, spelled", [
    ("DN", "count"), ("DN s-1", "count s-1"), ("DN2", "count2"), ("electron", "count"), ("DN/electron", "1"),
    ("electron/DN", "1"), ("pixel", "1"), ("pixel^2", "1"), ("DN s-1 degree_C-1", "count s-1 degree_C-1"),
    ("W sr-1 m-2 nm-1 s DN-1", "W sr-1 m-2 nm-1 s count-1"), ("DN/photon", "1"), ("photon", "count"),
    ("degree", "degree"), ("1", "1")])
def test_the_udunits_spelling_is_the_camera_unit_for_udunits(camera, spelled):
    """Against UDUNITS-2: the spelling parses and is the unit the camera's notation means (DN, electron, photon and
    pixel counted), and it is the short form written here."""
    assert udunits_spelling(camera) == spelled
    assert udunits(spelled) is not None and udunits(spelled) == camera_unit(camera)


def test_a_unit_the_spelling_cannot_read_is_refused():
    for text in ("pixel^(1-k)", "DN ms-1 | DN", "DN/s/electron"):
        with pytest.raises(ValueError, match="units"):
            udunits_spelling(text)


def test_text_columns_naming_units_use_the_camera_notation(tiny_run):
    """The closure table's ``value_units`` (a text column, not an attribute) is in the camera's notation, each
    value a UDUNITS-2 unit once DN, electron, photon and pixel are counted."""
    with xr.open_dataset(tiny_run["closure"]) as closure:
        values = set(np.unique(closure["value_units"].values.astype(str)))
    assert {"DN", "DN2", "1"} <= values, values
    assert all(camera_unit(v) is not None for v in values), values


def test_every_effect_states_its_amplitude_in_units_that_parse():
    """The diagnostics' tables (``missing_effects.csv``, the lens tests, the closure figures) give a candidate's
    amplitude in the units its effect states, per experiment: each a UDUNITS-2 unit once DN, electron and pixel
    are counted."""
    from pipeline.effects import available, get as get_effect
    from pipeline.runner.workflow import STAGE_EXPERIMENTS

    experiments = sorted({exp for exps in STAGE_EXPERIMENTS.values() for exp in exps} | {"closure"})
    labels = {(name, exp): get_effect(name).amplitude_label(exp)[1] for name in available() for exp in experiments}
    assert len(set(labels.values())) > 2, labels
    bad = {key: units for key, units in labels.items() if camera_unit(units) is None}
    assert not bad, bad

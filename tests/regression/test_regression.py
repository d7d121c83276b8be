"""Regression on fixture data and bit-identical reruns (issue 12, item 3).

The tiny simulated camera that the session fixture ``calibrated`` calibrates (tests/conftest.py)
is the regression's dataset: its key numbers per stage, lens and band are committed in
``tests/regression/tiny.json`` (with the tolerance and its reason), and a fresh calibration of the
same dataset with the same configuration must reproduce them. Refresh the file on purpose with
``PYTHONPATH=src .venv/bin/python tests/regression/refresh.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import xarray as xr

from helpers import key_results
from pipeline.bundle.calibration import BUNDLE_STAGES
from pipeline.runner.workflow import run_stage

REGRESSION = Path(__file__).with_name("tiny.json")
#: global attributes that hold the time of writing, the only ones allowed to differ between two runs
TIME_ATTRS = ("created",)


def _moved(committed: dict, fresh: dict[str, dict]) -> list[str]:
    """Key results of ``fresh`` outside the committed values' tolerance: 1e-6 of the value, or a hundredth of
    its stated uncertainty where smaller, so that a change of method is caught even inside its error bar; the
    stated uncertainty itself (a change of the budget is a change of method) within 1e-6 of it."""
    rtol, sigma_fraction = float(committed["tolerance"]["relative"]), float(committed["tolerance"]["sigma_fraction"])
    moved = []
    for name, old in committed["values"].items():
        new = fresh[name]
        if (old["sigma"] is None) != (new["sigma"] is None) or (
                old["sigma"] is not None and abs(new["sigma"] - old["sigma"]) > rtol * old["sigma"]):
            moved.append(f"{name} sigma: {old['sigma']!r} -> {new['sigma']!r}")
        if old["value"] is None or new["value"] is None:
            if old["value"] != new["value"]:
                moved.append(f"{name}: {old['value']} -> {new['value']}")
            continue
        tolerance = rtol * abs(old["value"])
        if old["sigma"]:
            tolerance = min(tolerance, sigma_fraction * old["sigma"])
        if abs(new["value"] - old["value"]) > tolerance:
            moved.append(f"{name}: {old['value']!r} -> {new['value']!r}")
    return moved


def test_a_fresh_calibration_reproduces_the_committed_key_results(calibrated):
    committed = json.loads(REGRESSION.read_text())
    dataset = committed["dataset"]
    assert (dataset["scale"], dataset["seed"], dataset["effects"], tuple(dataset["experiments"])) == (
        "tiny", 5, [], tuple(BUNDLE_STAGES)), "tiny.json was made from another dataset than the fixture's"
    fresh = key_results(calibrated[4])
    assert set(fresh) == set(committed["values"]), "the set of key results changed: refresh tiny.json on purpose"
    moved = _moved(committed, fresh)
    assert not moved, "key results moved (refresh tiny.json on purpose if the change is meant):\n" + "\n".join(moved)


def test_the_comparison_catches_a_shift_far_inside_the_stated_uncertainty():
    """R^-1 moved by 2 % of its sigma (a change no interval would notice) is flagged, float rounding is not;
    its stated sigma changed by 1 % is flagged."""
    committed = json.loads(REGRESSION.read_text())
    name = "absolute.inverse_responsivity.close.G"
    old = committed["values"][name]
    for shift, caught in ((0.02 * old["sigma"], True), (4 * np.spacing(old["value"]), False)):
        fresh = {**committed["values"], name: {**old, "value": old["value"] + shift}}
        assert bool(_moved(committed, fresh)) == caught, shift
    # a budget that states another uncertainty for the same value
    fresh = {**committed["values"], name: {**old, "sigma": old["sigma"] * 0.99}}
    assert _moved(committed, fresh) == [f"{name} sigma: {old['sigma']!r} -> {old['sigma'] * 0.99!r}"]


def test_the_same_inputs_and_config_give_bit_identical_data_variables(make_dataset, config, tmp_path):
    """The dark stage run twice on the same tiny dataset: every data variable and coordinate equal bit for
    bit (NaN where NaN), and every attribute but the time of writing."""
    root, _ = make_dataset()
    runs = []
    for i in (1, 2):
        outputs = {lens: tmp_path / f"run{i}" / "dark" / f"{lens}.nc" for lens in ("far", "close")}
        run_stage("dark", root, config, outputs)
        runs.append({lens: xr.open_dataset(path).load() for lens, path in outputs.items()})
    for lens in ("far", "close"):
        a, b = runs[0][lens], runs[1][lens]
        assert set(a.variables) == set(b.variables) and len(a.data_vars) > 10
        for name in a.variables:
            va, vb = a[name].values, b[name].values
            assert va.dtype == vb.dtype and va.shape == vb.shape, name
            if va.dtype.kind in "fiub":
                assert va.tobytes() == vb.tobytes(), f"{lens} {name} differs"      # bits, NaN included
            else:
                assert np.array_equal(va, vb), f"{lens} {name} differs"
            assert a[name].attrs == b[name].attrs, name
        assert {k: v for k, v in a.attrs.items() if k not in TIME_ATTRS} == \
               {k: v for k, v in b.attrs.items() if k not in TIME_ATTRS}

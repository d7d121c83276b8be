"""Refresh tests/regression/tiny.json on purpose: the key results of the tiny simulated camera.

    PYTHONPATH=src .venv/bin/python tests/regression/refresh.py

Simulates the dataset of the test session's ``calibrated`` fixture (tests/conftest.py: tiny
scale, seed 5, no effect switched on, the seven lab experiments), calibrates it with the pipeline's
own stages and the default configuration (tests/helpers.calibrate), and rewrites the JSON file
with the bundle's key numbers (tests/helpers.key_results). Run it when a change of method is
meant to move the calibration, and say in the commit why the numbers moved.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1] / "support"
sys.path.insert(0, str(TESTS))

from helpers import calibrate, key_results  # noqa: E402
from pipeline.bundle.calibration import BUNDLE_STAGES  # noqa: E402
from pipeline.config import load_config  # noqa: E402
from pipeline.simulate import simulate_dataset  # noqa: E402

#: the dataset of the ``calibrated`` fixture (tests/conftest.py)
DATASET = {"scale": "tiny", "seed": 5, "effects": [], "experiments": list(BUNDLE_STAGES)}
#: |fresh - committed| <= min(RELATIVE_TOLERANCE * |committed|, SIGMA_FRACTION * committed sigma);
#: a stated sigma within RELATIVE_TOLERANCE of itself
RELATIVE_TOLERANCE = 1e-6
SIGMA_FRACTION = 0.01
TOLERANCE_NOTE = (
    "Deterministic numbers: the same seed and configuration give the same frames (the simulator writes the same "
    "bytes) and the same fits, so a fresh calibration reproduces each value to float rounding (amplified by the "
    "iterative fits, still far below 1e-9 relative). The tolerance of a value is 1e-6 of it, or a hundredth of "
    "its stated sigma where that is smaller: room for another BLAS or platform, while any change of method that "
    "moves a value, even well inside its own uncertainty, is caught. A stated sigma is compared within 1e-6 of "
    "itself (a change of the uncertainty budget is a change of method). Refresh on purpose with: "
    "PYTHONPATH=src .venv/bin/python tests/regression/refresh.py")
OUT = Path(__file__).with_name("tiny.json")


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "dataset"
        simulate_dataset(root, scale=DATASET["scale"], seed=DATASET["seed"], effects=DATASET["effects"],
                         experiments=tuple(DATASET["experiments"]), progress=False)
        _, bundle, _ = calibrate(root, load_config(), Path(tmp) / "results")
        values = key_results(bundle)
    doc = {"dataset": DATASET, "config": "the defaults (config/config.yaml, src/pipeline/schema.yaml)",
           "tolerance": {"relative": RELATIVE_TOLERANCE, "sigma_fraction": SIGMA_FRACTION, "note": TOLERANCE_NOTE}, "values": values}
    OUT.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {OUT}: {len(values)} values")


if __name__ == "__main__":
    main()

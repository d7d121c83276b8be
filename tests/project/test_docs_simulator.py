"""docs/simulator.md's tables of the default camera (spectral bands and roll-off per lens) are the ones
scripts/simulator_camera_table.py computes from the simulator's truth (run the script with --write when this fails)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "simulator.md"


def _script():
    spec = importlib.util.spec_from_file_location("simulator_camera_table", ROOT / "scripts" / "simulator_camera_table.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_default_camera_tables_are_current():
    script = _script()
    text = DOC.read_text(encoding="utf-8")
    body = script.spectral_table() + "\n" + script.rolloff_table()
    assert script.splice(text, body) == text, \
        "docs/simulator.md's default-camera tables are stale: PYTHONPATH=src python scripts/simulator_camera_table.py --write"
    # the close lens's G band is nearest the 555 nm channel, the paper's 540 nm was nearest 532 nm
    assert "| close | G | 544.4 |" in text and "| 555 | 540 +- 60 |" in text

"""docs/simulator.md's tables of the default camera (spectral bands and roll-off per lens) are the ones
scripts/simulator_camera_table.py computes from the simulator's truth (run the script with --write when this fails)."""

from __future__ import annotations

from pathlib import Path

from repo_scripts import load_script

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "simulator.md"


def test_default_camera_tables_are_current():
    script = load_script("simulator_camera_table")
    text = DOC.read_text(encoding="utf-8")
    body = script.spectral_table() + "\n" + script.rolloff_table()
    assert script.splice(text, body) == text, \
        "docs/simulator.md's default-camera tables are stale: PYTHONPATH=src python scripts/simulator_camera_table.py --write"
    # the close lens's G band is nearest the 555 nm channel, the paper's 540 nm was nearest 532 nm
    assert "| close | G | 544.4 |" in text and "| 555 | 540 +- 60 |" in text

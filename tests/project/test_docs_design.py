"""docs/design.md lists every effect of the catalogue, and its table is the one scripts/effect_catalogue_table.py
writes from pipeline.effects (run the script with --write when this fails)."""

from __future__ import annotations

from pathlib import Path

from repo_scripts import load_script

from pipeline.effects import CATALOGUE

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "design.md"


def test_design_names_every_catalogue_effect():
    text = DOC.read_text(encoding="utf-8")
    missing = [name for name in CATALOGUE if f"| `{name}` |" not in text]
    assert not missing, f"docs/design.md does not list the effects {missing}"


def test_catalogue_table_is_current():
    script = load_script("effect_catalogue_table")
    text = DOC.read_text(encoding="utf-8")
    assert script.splice(text, script.table()) == text, \
        "docs/design.md's effect table is stale: PYTHONPATH=src python scripts/effect_catalogue_table.py --write"

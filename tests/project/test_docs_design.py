"""docs/design.md lists every effect of the catalogue, and its table is the one scripts/effect_catalogue_table.py
writes from pipeline.effects (run the script with --write when this fails)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from pipeline.effects import CATALOGUE

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "design.md"


def _script():
    spec = importlib.util.spec_from_file_location("effect_catalogue_table", ROOT / "scripts" / "effect_catalogue_table.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_design_names_every_catalogue_effect():
    text = DOC.read_text(encoding="utf-8")
    missing = [name for name in CATALOGUE if f"| `{name}` |" not in text]
    assert not missing, f"docs/design.md does not list the effects {missing}"


def test_catalogue_table_is_current():
    script = _script()
    text = DOC.read_text(encoding="utf-8")
    assert script.splice(text, script.table()) == text, \
        "docs/design.md's effect table is stale: PYTHONPATH=src python scripts/effect_catalogue_table.py --write"

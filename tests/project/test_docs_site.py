"""The documentation site: its generated reference pages are those the code gives now, every page is in the
index's table of contents, and the changelog knows every current artefact version.

The site itself is built by ``make docs`` (Sphinx, warnings as errors) in CI; these checks are the fast part.
"""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest
from repo_scripts import load_script

from pipeline.io.artefact import ARTEFACT_VERSIONS

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"


@pytest.fixture(scope="module")
def reference_pages():
    return load_script("reference_pages")


def test_generated_reference_pages_are_current(reference_pages):
    assert reference_pages.stale() == [], "PYTHONPATH=src python scripts/reference_pages.py --write"


def _keys(schema: dict, path: str = ""):
    """Every key the schema names (sections, their keys, the keys of a list's mapping items as key[].name)."""
    for key, sub in (schema.get("properties") or {}).items():
        dotted = f"{path}.{key}" if path else key
        yield dotted
        yield from _keys(sub, dotted)
        if isinstance(sub.get("items"), dict):
            yield from _keys(sub["items"], f"{dotted}[]")


def test_configuration_reference_has_every_key_with_its_default():
    """Every key of the schema, with its default as the schema gives it: the page is the schema's, not a copy."""
    from pipeline.config import SCHEMA_PATH, _read_yaml

    text = (DOCS / "reference" / "configuration-keys.md").read_text(encoding="utf-8")
    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `([^`]+)`(?: \(required\))? \|.*$", text, re.M)}
    keys = list(_keys(_read_yaml(SCHEMA_PATH)))
    assert len(keys) > 100
    missing = [key for key in keys if key not in rows and f"\n## `{key}`\n" not in text]
    assert not missing, f"keys of the schema missing from the reference: {missing}"
    # a default and a range as the schema states them, on the key's own row
    assert "| `6.0` | [1, 100] |" in rows["dark.hot_pixel_threshold_sigma"]
    assert "| `0.95` | (0, 1) |" in rows["field.confidence_level"]
    assert "| degree |" in rows["linearity.mask_half_angle_deg"]


def test_cli_reference_has_every_command_and_option():
    from pipeline.cli import build_parser

    text = (DOCS / "reference" / "cli.md").read_text(encoding="utf-8")
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, command in sub.choices.items():
        assert f"## `python -m pipeline {name}`" in text, name
        for action in command._actions:
            for option in action.option_strings:
                if option not in ("-h", "--help"):
                    assert f"`{option}" in text or f", {option}" in text, f"{name} {option}"


def _toctree_entries(index: str) -> list[str]:
    entries = []
    for block in re.findall(r"```\{toctree\}\n(.*?)```", index, re.S):
        entries += [line.strip() for line in block.splitlines() if line.strip() and not line.startswith(":")]
    return entries


def test_every_docs_page_is_in_the_toctree():
    entries = _toctree_entries((DOCS / "index.md").read_text(encoding="utf-8"))
    pages = sorted(str(p.relative_to(DOCS).with_suffix("")) for p in DOCS.rglob("*.md")
                   if "_build" not in p.parts and "figures-data" not in p.parts and p.name != "index.md")
    assert len(pages) > 20
    assert sorted(set(pages) - set(entries)) == [], "pages missing from the toctree of docs/index.md"
    assert sorted(set(entries) - set(pages)) == [], "toctree entries of docs/index.md without a page"
    assert len(entries) == len(set(entries)), "a page listed twice"


def test_changelog_has_every_current_artefact_version():
    """A version bump without its changelog entry fails here: each artefact's newest entry is its current version."""
    text = (DOCS / "changelog.md").read_text(encoding="utf-8")
    for stage, version in ARTEFACT_VERSIONS.items():
        section = re.search(rf"^### `{stage}`.*?$(.*?)(?=^### |\Z)", text, re.M | re.S)
        assert section, f"docs/changelog.md has no section for the {stage} artefact"
        listed = [int(v) for v in re.findall(r"^- \*\*(\d+)\*\*", section.group(1), re.M)]
        assert listed and listed[0] == version == max(listed), \
            f"docs/changelog.md: the {stage} artefact is at version {version}, its newest entry is {listed[:1]}"


def test_performance_tables_are_rendered_from_the_benchmark_results():
    """No timing typed by hand into a table of docs/performance.md: each is its CSV's rows."""
    module = load_script("bench_tables")
    text = (DOCS / "performance.md").read_text(encoding="utf-8")
    blocks = module.BLOCK.findall(text)
    assert len(blocks) > 20
    # every Markdown table of the page lies inside a rendered block
    outside = module.BLOCK.sub("", text)
    assert not re.search(r"^\|.*\|$", outside, re.M), "a table typed by hand in docs/performance.md"
    assert module.render(text) == text, "python scripts/bench_tables.py --write"


def test_every_pages_benchmark_tables_are_rendered_from_the_benchmark_results():
    """Every docs page's bench-table blocks are their CSVs' rows (python scripts/bench_tables.py --check), and
    the detection benchmark's section of docs/effects-and-diagnostics.md holds no table typed by hand and no
    timing in its prose: its runs are rows of benchmarks/results/bench_detection_*.csv."""
    module = load_script("bench_tables")
    rendered = module.render_all()
    names = {p.name for p in rendered}
    assert {"performance.md", "effects-and-diagnostics.md"} <= names
    stale = [p.name for p, new in rendered.items() if new != p.read_text(encoding="utf-8")]
    assert stale == [], "python scripts/bench_tables.py --write"
    text = (DOCS / "effects-and-diagnostics.md").read_text(encoding="utf-8")
    section = re.search(r"^## Detection benchmark$(.*?)^## ", text, re.M | re.S).group(1)
    assert len(module.BLOCK.findall(section)) >= 10
    prose = module.BLOCK.sub("", section)
    assert not re.search(r"^\|.*\|$", prose, re.M), "a table typed by hand in the detection benchmark's section"
    assert not re.search(r"\d ?s (CPU|wall)|load (average )?(about |of )?\d", prose), "a timing typed into the detection benchmark's prose"


def test_readme_docs_table_points_at_pages():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    linked = re.findall(r"\]\((docs/[^)#]+\.md)", readme)
    assert linked
    assert [p for p in linked if not (ROOT / p).exists()] == []


def _resolve(dotted: str):
    """The object ``pipeline.<dotted>`` names: the longest importable module, then attributes."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module("pipeline." + ".".join(parts[:cut]))
        except ImportError:
            continue
        for name in parts[cut:]:
            obj = getattr(obj, name, None)
            if obj is None:
                return None
        return obj
    return None


def test_equation_table_names_functions_that_exist():
    """The equation-to-function table of docs/equations.md names code that is there (a rename or a move of a
    module fails here until the table follows)."""
    text = (DOCS / "equations.md").read_text(encoding="utf-8")
    rows = [line for line in text.splitlines() if line.startswith("| (") or line.startswith("| B(") or line.startswith("| -")]
    named = sorted({m for row in rows for m in re.findall(r"`([a-z_]+(?:\.[A-Za-z_][A-Za-z0-9_]*)+)`", row.rsplit("|", 2)[-2])})
    assert len(named) > 30
    missing = [name for name in named if _resolve(name) is None]
    assert not missing, f"docs/equations.md names what the package does not have: {missing}"

"""Sphinx configuration of the documentation site: ``make docs`` (warnings are errors).

The pages are the Markdown files of this folder (MyST); the API reference is read from the
package's docstrings (autodoc, numpydoc sections through napoleon). The configuration, command-line
and artefact references under ``reference/`` are written by ``scripts/reference_pages.py`` from the
schema, the parsers and the artefacts' code, and ``tests/project/test_docs_site.py`` checks they are current.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from pipeline import __version__  # noqa: E402

project = "camera-radiometer-pipeline"
author = "the camera-radiometer-pipeline authors"
copyright = "the camera-radiometer-pipeline authors, BSD-3-Clause"  # noqa: A001
release = version = __version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "figures-data/*.md", "Thumbs.db", ".DS_Store"]

# MyST: CommonMark and tables as GitHub shows the same pages (no extension that would read a page's $ or :
# as markup); heading anchors so that [text](page.md#a-heading) links resolve
myst_enable_extensions: list[str] = []
myst_heading_anchors = 4

# numpydoc docstrings (Parameters, Returns, ...) through napoleon
napoleon_google_docstring = False
napoleon_numpy_docstring = True
# an Attributes section as a plain field list: a dataclass's fields are then not described twice (by the
# section and by autodoc), and their short names (rows, k) are not made into ambiguous cross-references
napoleon_custom_sections = [("Attributes", "params_style")]
# parameters and returns as plain field lists too: their type slots hold shapes and prose ("(k, 2) arrays"),
# not type names to link
napoleon_use_param = False
napoleon_use_rtype = False
autodoc_member_order = "bysource"
autodoc_typehints = "none"
autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": False}

html_theme = "alabaster"
html_title = f"camera-radiometer-pipeline {__version__}"
html_static_path: list[str] = []


def _escape_bars(app, what, name, obj, options, lines):
    """The docstrings write absolute values and norms as |x - y| (plain text): outside literals, a bar is
    escaped so that reStructuredText does not read |...| as a substitution."""
    for i, line in enumerate(lines):
        parts = re.split(r"(``.*?``|`[^`]*`)", line)
        lines[i] = "".join(part if part.startswith("`") else part.replace("|", "\\|") for part in parts)


def _attribute_docstring_as_written(self) -> list[str]:
    """An attribute's or constant's docstring (the ``#:`` comments) as written: napoleon would read the text
    before its first colon as the attribute's type, and this package's comments are prose whose first
    colon introduces an explanation (``#: stages a bundle is gathered from: ...``)."""
    return self._consume_to_end()


def setup(app):
    from sphinx.ext.napoleon.docstring import GoogleDocstring

    GoogleDocstring._parse_attribute_docstring = _attribute_docstring_as_written
    app.connect("autodoc-process-docstring", _escape_bars, priority=400)

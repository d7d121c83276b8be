"""The package's layout: subpackages by layer, and no module reaching for another module's private names.

The layers and the absence of import cycles are import contracts (``pyproject.toml``, checked by ``make lint``);
what a contract cannot see is an underscore name imported from another module, which ties the importer to
the other module's internals. A private module of a package (``report/sections/_common.py``) is the
package's own: importing from it inside the package is allowed, a name with a leading underscore is not.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pipeline

PACKAGE = Path(pipeline.__file__).resolve().parent

#: the modules a package may keep at its root: the entry points and the few base modules every layer uses
ROOT_MODULES = {"__init__", "__main__", "cli", "config", "entry", "errors", "scaffold", "yamlio"}


def _imports_of_private_names(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("pipeline"):
            for alias in node.names:
                if alias.name.startswith("_") and alias.name != "__version__":
                    yield node.lineno, node.module, alias.name


def test_no_private_name_is_imported_from_another_module():
    found = [f"{path.relative_to(PACKAGE)}:{line}: {name} from {module}"
             for path in sorted(PACKAGE.rglob("*.py"))
             for line, module, name in _imports_of_private_names(path)]
    assert found == []


def test_the_package_root_holds_only_entry_points_and_base_modules():
    modules = {p.stem for p in PACKAGE.glob("*.py")}
    assert modules <= ROOT_MODULES, sorted(modules - ROOT_MODULES)


def test_every_test_module_sits_in_the_subfolder_of_its_layer():
    tests = Path(__file__).resolve().parents[1]
    assert sorted(p.name for p in tests.glob("test_*.py")) == []
    assert sorted(p.name for p in tests.glob("*.py")) == ["conftest.py"]

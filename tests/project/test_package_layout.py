"""The package's layout: subpackages by layer, and no module reaching for another module's private names.

The layers and the absence of import cycles are import contracts (``pyproject.toml``, checked by ``make lint``);
what a contract cannot see is an underscore name imported from another module, which ties the importer to
the other module's internals. A private module of a package (``report/sections/_common.py``) is the
package's own: importing from it inside the package is allowed, a name with a leading underscore is not.
"""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

import pipeline

PACKAGE = Path(pipeline.__file__).resolve().parent

#: the modules a package may keep at its root: the entry points and the few base modules every layer uses
ROOT_MODULES = {"__init__", "__main__", "cli", "config", "entry", "errors", "scaffold", "yamlio"}
#: the longest a function may be, in lines from its ``def`` to its last line less its docstring: past it, named steps
#: read better
MAX_FUNCTION_LINES = 120
#: the functions longer than that today, to be split into named steps; the list may only shrink: a function split
#: below the limit leaves it (the test says so), and a new long function fails the test
LONG_FUNCTIONS = {"simulate/field.py::plan_field"}


@cache
def _parsed(path: Path) -> ast.Module:
    """The syntax tree of a module of the package, parsed once for the tests of this file."""
    return ast.parse(path.read_text(), filename=str(path))


def _imports_of_private_names(path: Path):
    tree = _parsed(path)
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


def _function_lengths(tree: ast.AST, prefix: str = ""):
    """(qualified name, lines from ``def`` to the last line, its docstring left out) of every function in
    ``tree``, nested ones included (``outer.inner``, ``Class.method``): the limit is on the code a reader follows,
    not on its documentation."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            name = f"{prefix}{node.name}"
            if not isinstance(node, ast.ClassDef):
                yield name, node.end_lineno - node.lineno + 1 - _docstring_lines(node)
            yield from _function_lengths(node, f"{name}.")
        else:
            yield from _function_lengths(node, prefix)


def _docstring_lines(node: ast.FunctionDef) -> int:
    first = node.body[0]
    is_doc = isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str)
    return first.end_lineno - first.lineno + 1 if is_doc else 0


def _long_functions(limit: int) -> dict[str, int]:
    return {f"{path.relative_to(PACKAGE).as_posix()}::{name}": lines
            for path in sorted(PACKAGE.rglob("*.py"))
            for name, lines in _function_lengths(_parsed(path))
            if lines > limit}


def test_function_lengths_count_every_line_of_nested_functions_and_methods():
    tree = ast.parse("def outer():\n    def inner():\n        return 1\n\n    return inner\n\n\n"
                     "class A:\n    def method(self):\n        pass\n")
    assert dict(_function_lengths(tree)) == {"outer": 5, "outer.inner": 2, "A.method": 2}


def test_no_function_is_longer_than_the_limit_but_the_listed_ones():
    long = _long_functions(MAX_FUNCTION_LINES)
    new = {name: lines for name, lines in long.items() if name not in LONG_FUNCTIONS}
    assert not new, (f"longer than {MAX_FUNCTION_LINES} lines: split into steps with names that say what they "
                     f"compute: {new}")
    assert LONG_FUNCTIONS <= set(long), (f"no longer over {MAX_FUNCTION_LINES} lines: take them off LONG_FUNCTIONS: "
                                         f"{sorted(LONG_FUNCTIONS - set(long))}")

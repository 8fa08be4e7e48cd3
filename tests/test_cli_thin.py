"""The command line is thin: its modules parse, call the library and print, and leave the numerics
(numpy, scipy, the grid, the kernels, features and warp) to the library; and its functions are
short enough to read.  Checked statically, by parsing each module of ``volreg/cli`` (imports
inside functions count; those under ``if TYPE_CHECKING:``, for annotations only, do not)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import volreg

CLI = Path(volreg.__file__).resolve().parent / "cli"

#: Modules whose imports name any of these (or a submodule) do numerical work themselves.
NUMERICS = ("numpy", "scipy", "volreg.kernels", "volreg.features", "volreg.warp", "volreg.grid")

#: The longest a function of the command line may be, in lines from its ``def`` to its last line.
MAX_FUNCTION_LINES = 100

MODULES = sorted(CLI.glob("*.py"))


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imported_modules(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, module) of every import in ``tree``, skipping ``if TYPE_CHECKING:`` blocks."""
    found: list[tuple[int, str]] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level:
            module = node.module or ""
            found.append((node.lineno, module))
            found.extend((node.lineno, f"{module}.{alias.name}") for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def _numerics(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    return sorted({f"line {line}: {module}" for line, module in _imported_modules(tree)
                   if any(module == n or module.startswith(n + ".") for n in NUMERICS)})


def _long_functions(path: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            lines = node.end_lineno - node.lineno + 1
            if lines > limit:
                found.append(f"{node.name} (line {node.lineno}): {lines} lines")
    return found


def test_the_command_line_has_modules_to_check():
    assert {"__init__.py", "apply.py", "surface.py", "register_surfaces.py"} <= {p.name for p in MODULES}


@pytest.mark.parametrize("path", MODULES, ids=[p.name for p in MODULES])
def test_a_command_module_imports_no_numerics(path):
    assert _numerics(path) == [], f"{path.name} imports numerical modules itself"


@pytest.mark.parametrize("path", MODULES, ids=[p.name for p in MODULES])
def test_no_command_line_function_is_over_the_limit(path):
    assert _long_functions(path) == [], f"{path.name} has functions over {MAX_FUNCTION_LINES} lines"


def test_the_check_sees_imports_inside_functions_and_not_annotations_only(tmp_path):
    source = tmp_path / "m.py"
    source.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import numpy as np\n"
                      "def f():\n    from volreg.warp.model import KernelWarp\n    import scipy.ndimage\n"
                      "from volreg import warp\nfrom volreg.grid import world_box\nimport volreg.gridlike\n")
    assert _numerics(source) == ["line 5: volreg.warp.model", "line 5: volreg.warp.model.KernelWarp",
                                 "line 6: scipy.ndimage", "line 7: volreg.warp", "line 8: volreg.grid",
                                 "line 8: volreg.grid.world_box"]


def test_the_length_check_counts_every_line_of_a_function(tmp_path):
    source = tmp_path / "m.py"
    body = "".join("    x = 1\n" for _ in range(MAX_FUNCTION_LINES - 1))
    source.write_text(f"def short():\n{body}\n\ndef long():\n{body}    return x\n")
    assert _long_functions(source) == [f"long (line {MAX_FUNCTION_LINES + 3}): {MAX_FUNCTION_LINES + 1} lines"]

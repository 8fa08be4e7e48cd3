"""The examples use the public API: `import volreg` and `volreg.NAME` with NAME in the public API, plus
only the helpers that make their data (`volreg.synthetic`) or run a command (`volreg.cli`)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import volreg

EXAMPLES = sorted((Path(__file__).resolve().parent.parent / "examples").glob("*.py"))

#: Submodules an example may import from besides the top level.
ALLOWED_MODULES = {"volreg", "volreg.synthetic", "volreg.cli"}


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_example_uses_the_public_api(path):
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "volreg":
            assert node.module in ALLOWED_MODULES, f"{path.name} imports from {node.module}"
            if node.module == "volreg":
                private = [a.name for a in node.names if a.name not in volreg._API]
                assert not private, f"{path.name} imports {private}, not in the public API"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "volreg":
                    assert alias.name in ALLOWED_MODULES, f"{path.name} imports {alias.name}"
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "volreg":
            assert node.attr in volreg._API, f"{path.name} uses volreg.{node.attr}, not in the public API"

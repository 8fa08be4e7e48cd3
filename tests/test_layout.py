"""The package's layout: every module imports on its own, no import cycles, the stages in order, no
private name across packages, the public API resolves."""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import volreg

PACKAGE = Path(volreg.__file__).resolve().parent


def _modules() -> list[str]:
    names = ["volreg"]
    for info in pkgutil.walk_packages([str(PACKAGE)], prefix="volreg."):
        names.append(info.name)
    return sorted(names)


MODULES = _modules()


@pytest.mark.system
def test_every_module_imports_first_in_a_fresh_interpreter():
    # One interpreter per module, each importing that module before anything else of volreg:
    # a cycle shows as "partially initialized module" here, whatever order the tests run in.
    code = "import importlib, sys; importlib.import_module(sys.argv[1])"
    failures = []
    for name in MODULES:
        run = subprocess.run([sys.executable, "-c", code, name], capture_output=True, text=True, timeout=120)
        if run.returncode != 0:
            failures.append(f"{name}: {run.stderr.strip().splitlines()[-1] if run.stderr.strip() else run.returncode}")
    assert not failures, "\n".join(failures)


def _imports(path: Path, module: str) -> set[str]:
    """The volreg modules that ``path`` imports at module level or inside functions."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("volreg")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.startswith("volreg"):
                out.add(target)
                out |= {f"{target}.{a.name}" for a in node.names}
    return out & set(MODULES)


def test_no_two_modules_import_each_other():
    files = {}
    for name in MODULES:
        rel = name.split(".")[1:]
        path = PACKAGE.joinpath(*rel)
        files[name] = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    graph = {name: _imports(path, name) - {name} for name, path in files.items()}
    pairs = sorted({tuple(sorted((a, b))) for a in graph for b in graph[a] if a in graph.get(b, set())
                    and not (a == "volreg" or b == "volreg")})
    assert not pairs, f"modules that import each other: {pairs}"


@pytest.mark.parametrize("name", sorted(volreg._API))
def test_public_name_resolves(name):
    value = getattr(volreg, name)
    assert value is not None
    assert name in dir(volreg)


def test_unknown_public_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'register_everything'"):
        volreg.register_everything  # noqa: B018


def test_every_user_facing_error_derives_from_the_base():
    from volreg import errors

    classes = [getattr(errors, n) for n in errors.__all__ if isinstance(getattr(errors, n), type)]
    failures = [c.__name__ for c in classes if not issubclass(c, Warning) and not issubclass(c, errors.VolregError)]
    assert failures == []
    # no other module of the package defines its own public exception class
    defined = []
    for name in MODULES:
        rel = name.split(".")[1:]
        path = PACKAGE.joinpath(*rel)
        path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.ClassDef) and not node.name.startswith("_") and node.name.endswith(("Error", "Diverged")):
                defined.append(f"{name}.{node.name}")
    assert [d for d in defined if not d.startswith("volreg.errors.")] == []


#: The stages of the package in the order they may import one another: a module imports only
#: modules of its own stage or an earlier one (the first prefix that matches names the stage).
#: Infrastructure (threads, the compiled loops' cache and its helper processes, signals, memory,
#: progress callbacks) comes first, with the
#: errors and settings; ``evaluation.metrics`` is a leaf of pure functions on arrays (Dice,
#: folded fractions) beside the grid, so that every later stage may use it.
STAGES = (
    ("volreg.errors", "volreg.settings", "volreg._memory", "volreg._jit", "volreg._cache_folder", "volreg._lazy",
     "volreg._signals", "volreg._threads", "volreg.progress", "volreg.precompile"),
    ("volreg.grid", "volreg.linear_map", "volreg.evaluation.metrics"),
    ("volreg.io",),
    ("volreg.kernels",),
    ("volreg.features",),
    ("volreg.warp", "volreg.synthetic"),
    ("volreg.pipeline", "volreg.morph", "volreg.demo"),
    ("volreg.evaluation",),
    ("volreg.outputs", "volreg.cohort", "volreg.template", "volreg.shape_models"),
    ("volreg.cli", "volreg.__main__"),
)


def _stage_of(module: str) -> int | None:
    for rank, prefixes in enumerate(STAGES):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return rank
    return None


def _module_files() -> dict[str, Path]:
    files = {}
    for name in MODULES:
        rel = name.split(".")[1:]
        path = PACKAGE.joinpath(*rel)
        files[name] = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    return files


def test_every_module_has_a_stage():
    assert [m for m in MODULES if m != "volreg" and _stage_of(m) is None] == []


def test_no_module_imports_a_later_stage():
    upward = []
    for name, path in _module_files().items():
        if name == "volreg":
            continue  # the public API: lazy names of every stage
        for target in _imports(path, name):
            if target == "volreg" or target == name:
                continue
            if _stage_of(target) > _stage_of(name):
                upward.append(f"{name} -> {target}")
    assert sorted(set(upward)) == []


def _package_of(module: str, path: Path) -> str:
    return module if path.name == "__init__.py" else module.rpartition(".")[0]


def test_no_private_name_is_imported_from_another_package():
    """``from volreg.x.y import _name`` only within the package ``volreg.x`` (and ``from volreg
    import _module`` only within ``volreg`` itself)."""
    files = _module_files()
    crossing = []
    for name, path in files.items():
        here = _package_of(name, path)
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.ImportFrom) or node.level or not (node.module or "").startswith("volreg"):
                continue
            source = node.module
            source_package = source if source in files and files[source].name == "__init__.py" else source.rpartition(".")[0]
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__") and source_package != here:
                    crossing.append(f"{name}: from {source} import {alias.name}")
    assert crossing == []

"""volreg on a locked-down install: package directory and home both unwritable.

Running as root, permissions cannot make a folder unwritable, so the test makes numba's
cache locations impossible instead: the package is a copy whose ``__pycache__`` entries
are regular files, and HOME / XDG_CACHE_HOME lie under a regular file.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import volreg

pytestmark = pytest.mark.skipif(os.name != "posix", reason="POSIX paths")

# imports every module that compiles loops, then calls one small compiled loop (compiled or from the cache)
_SNIPPET = """
import sys, tempfile
if len(sys.argv) > 1:
    tempfile.tempdir = sys.argv[1]  # the system's temporary directory unusable too
import volreg._jit, volreg.outputs.registration, volreg.cli
print(volreg._jit.cache_location())
import numpy as np
from volreg.kernels._compiled import take_rows
print(int(take_rows(np.arange(10.0)[:, None], np.arange(10)[::-1].copy()).sum()))
"""


@pytest.fixture(scope="module")
def locked(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("locked")
    package = root / "site" / "volreg"
    shutil.copytree(Path(volreg.__file__).parent, package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(Path(volreg.__file__).parent.parent / "protocols", package / "protocols")  # as installed
    for folder in [package, *[p for p in package.rglob("*") if p.is_dir()]]:
        (folder / "__pycache__").write_bytes(b"")  # numba (and Python) cannot cache here
    blocker = root / "blocker"
    blocker.write_bytes(b"")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(HOME=str(blocker / "home"), XDG_CACHE_HOME=str(blocker / "cache"),
               PYTHONPATH=str(root / "site"), TMPDIR=str(root / "tmp"))
    (root / "tmp").mkdir()
    return root, env


def _run(args, env, cwd):
    return subprocess.run([sys.executable, *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=600)


def test_the_copy_is_the_package_imported(locked):
    root, env = locked
    run = _run(["-c", "import volreg; print(volreg.__file__)"], env, root)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip().startswith(str(root / "site"))


def test_version_and_protocols_work_without_a_writable_cache(locked):
    root, env = locked
    version = _run(["-m", "volreg", "--version"], env, root)
    assert version.returncode == 0, version.stderr
    assert "cannot cache" not in version.stderr
    protocols = _run(["-m", "volreg", "protocols"], env, root)
    assert protocols.returncode == 0, protocols.stderr
    assert "default" in protocols.stdout


def test_cache_falls_back_to_the_temporary_directory(locked):
    root, env = locked
    first = _run(["-c", _SNIPPET], env, root)
    assert first.returncode == 0, first.stderr
    location, value = first.stdout.split("\n")[:2]
    assert Path(location).parent == root / "tmp"
    assert any(Path(location).rglob("*.nbi")), "nothing cached in the fallback folder"
    again = _run(["-c", _SNIPPET], env, root)  # loads from the fallback cache
    assert again.returncode == 0, again.stderr
    assert again.stdout.split("\n")[:2] == [location, value]
    assert value == str(sum(range(10)))


def test_no_cache_at_all_still_computes(locked):
    root, env = locked
    blocked_tmp = str(root / "blocker" / "tmp")
    none = _run(["-c", _SNIPPET, blocked_tmp], env, root)
    assert none.returncode == 0, none.stderr
    location, value = none.stdout.split("\n")[:2]
    assert location == "None"
    assert value == str(sum(range(10)))

"""Small text records (JSON run summaries, CSV tables, TOML protocols), written atomically."""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from volreg import __version__
from volreg.errors import VolregIOError
from volreg.io._atomic import atomic_output

__all__ = ["json_safe", "package_versions", "write_json", "write_text"]

#: The packages whose versions a run summary records, besides volreg and Python.
_RECORDED_PACKAGES = ("numpy", "scipy", "SimpleITK", "nibabel", "scikit-image", "pyvista", "numba")


def json_safe(value: Any) -> Any:
    """``value`` with NaN and Inf as ``None`` (JSON null) and numpy scalars as Python numbers, recursively.

    Dict keys become strings and tuples lists, as JSON has them.
    """
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def package_versions() -> dict[str, str]:
    """Versions of volreg, Python and the numerical and I/O packages, for a run summary."""
    out = {"volreg": __version__, "python": sys.version.split()[0]}
    for name in _RECORDED_PACKAGES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:  # pragma: no cover
            out[name] = "unknown"
    return out


def write_json(record: Any, path: str | os.PathLike[str], *, force: bool = False) -> None:
    """Write a JSON document (UTF-8, indented, trailing newline), atomically.

    Parameters
    ----------
    record : JSON-serialisable object
        Plain ``dict``/``list``/``str``/``int``/``float``/``bool``/``None``;
        NaN and Inf are refused (they are not JSON).
    path : path-like
        Output file, conventionally ``.json``.
    force : bool, default False
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        If ``record`` cannot be serialised, ``path`` exists and ``force`` is
        false, or the write fails; nothing is left behind on failure.
    """
    p = Path(path)
    try:
        text = json.dumps(record, indent=2, allow_nan=False) + "\n"
    except (TypeError, ValueError) as exc:
        raise VolregIOError(f"Summary `{p}` could not be written: {exc}.") from exc
    write_text(text, p, force=force)


def write_text(text: str, path: str | os.PathLike[str], *, force: bool = False) -> None:
    """Write a UTF-8 text file (a CSV table, a TOML protocol) atomically.

    Raises
    ------
    VolregIOError
        If ``path`` exists and ``force`` is false, or the write fails; nothing
        is left behind on failure.
    """
    p = Path(path)
    with atomic_output(p, force=force) as tmp:
        try:
            tmp.write_text(text, encoding="utf-8")
        except OSError as exc:
            raise VolregIOError(f"File `{p}` could not be written: {exc.strerror}.") from exc


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The SHA-256 checksum (hex) of a file, as the reports record their inputs."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()

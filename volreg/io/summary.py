"""Small text records (JSON run summaries, CSV tables, TOML protocols), written atomically."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from volreg.errors import VolregIOError
from volreg.io._atomic import atomic_output

__all__ = ["write_json", "write_text"]


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

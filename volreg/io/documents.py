"""JSON and TOML documents read from users' files, with their nesting bounded.

Python's JSON and TOML readers descend one stack frame per level of lists or tables within one
another: a file nested some thousands of levels deep (a few kilobytes of brackets) ends their
descent in a :class:`RecursionError`, and a document just under that depth still breaks every
recursive step taken on it afterwards (copying it, writing it back).  :func:`parse_json` and
:func:`parse_toml` turn both into one line naming the file: a document may nest its data at most
:data:`MAX_NESTING` levels deep, far beyond what any volreg file holds (a Slicer markups file
nests about six levels, a protocol two), and the depth is checked before anything reads the
document's values.  Errors of syntax are left to the caller, which words them as it always has.
"""

from __future__ import annotations

import json
import sys
from typing import Any, Callable

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

from volreg.errors import ProtocolError, VolregIOError

__all__ = ["MAX_NESTING", "nesting_depth", "parse_json", "parse_toml"]

#: The deepest nesting of lists and objects (tables) a document read from a user's file may have.
MAX_NESTING = 64

ErrorFactory = Callable[[str], Exception]


def nesting_depth(value: Any, limit: int | None = None) -> int:
    """How many levels of lists (or tuples) and mappings ``value`` nests: 0 for a scalar, 1 for a
    flat list or object, 2 for a list of lists, ...

    Walked without recursion, so any depth is measured; with ``limit``, the walk stops at the first
    container deeper than ``limit`` and returns that depth (``limit + 1``).
    """
    deepest = 0
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, dict):
            children = item.values()
        elif isinstance(item, (list, tuple)):
            children = item
        else:
            continue
        deepest = max(deepest, depth)
        if limit is not None and deepest > limit:
            return deepest
        stack.extend((child, depth + 1) for child in children if isinstance(child, (dict, list, tuple)))
    return deepest


def _too_deep(what: str, language: str) -> str:
    return (f"{what} nests its {language} data more than {MAX_NESTING} levels deep (lists or "
            f"{'tables' if language == 'TOML' else 'objects'} within one another); expected at most "
            f"{MAX_NESTING} levels.")


def _checked(data: Any, what: str, language: str, error: ErrorFactory) -> Any:
    if nesting_depth(data, MAX_NESTING) > MAX_NESTING:
        raise error(_too_deep(what, language))
    return data


def parse_json(text: str, what: str, *, error: ErrorFactory = VolregIOError) -> Any:
    """``json.loads(text)``, refusing a document nested more than :data:`MAX_NESTING` levels deep.

    Parameters
    ----------
    text : str
        The document.
    what : str
        How the message names the document, e.g. ``"Landmark file `a.mrk.json`"``.
    error : callable, default VolregIOError
        Makes the exception raised from the one-line message.

    Returns
    -------
    object
        The document's value.

    Raises
    ------
    VolregIOError (or what ``error`` makes)
        Nesting deeper than :data:`MAX_NESTING` levels, also where the reader itself ran out of stack.
    json.JSONDecodeError
        Text that is not JSON (a ``ValueError``), as ``json.loads`` raises it.
    """
    try:
        data = json.loads(text)
    except RecursionError:
        raise error(_too_deep(what, "JSON")) from None
    return _checked(data, what, "JSON", error)


def parse_toml(text: str, what: str, *, error: ErrorFactory = ProtocolError) -> dict[str, Any]:
    """``tomllib.loads(text)``, refusing a document nested more than :data:`MAX_NESTING` levels deep.

    Parameters
    ----------
    text : str
        The document.
    what : str
        How the message names the document, e.g. ``"Protocol `p.toml`"``.
    error : callable, default ProtocolError
        Makes the exception raised from the one-line message.

    Returns
    -------
    dict
        The document's tables.

    Raises
    ------
    ProtocolError (or what ``error`` makes)
        Nesting deeper than :data:`MAX_NESTING` levels (inline arrays or tables, dotted keys,
        table headers), also where the reader itself ran out of stack.
    tomllib.TOMLDecodeError
        Text that is not TOML (a ``ValueError``), as ``tomllib.loads`` raises it.
    """
    try:
        data = tomllib.loads(text)
    except RecursionError:
        raise error(_too_deep(what, "TOML")) from None
    return _checked(data, what, "TOML", error)

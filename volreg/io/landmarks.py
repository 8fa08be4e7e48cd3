"""Landmark point files: CSV (LPS mm), 3D Slicer ``.fcsv`` and ``.mrk.json``.

CSV: a header row naming ``x,y,z`` (optionally a first ``label``/``name``
column, ignored) then one point per row, in LPS millimetres (ITK physical
space).  Slicer files say their frame: ``.fcsv`` in its ``# CoordinateSystem``
line (``LPS``/``RAS`` or 0 = RAS, 1 = LPS; RAS when absent, as older Slicer),
``.mrk.json`` in each markup's ``coordinateSystem`` (default LPS, as Slicer
writes it since 4.11); RAS points are converted to LPS by negating x and y.
A ``.mrk.json`` markup's ``coordinateUnits`` (default ``mm``) is honoured:
``um``, ``cm`` and ``m`` are converted to mm, other units refused.
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from volreg.errors import VolregIOError, exception_text, excerpt
from volreg.io.documents import parse_json

__all__ = ["csv_rows", "fcsv_records", "read_landmarks"]

_FLIP = np.array([-1.0, -1.0, 1.0])


def _frame(value: str, path: Path) -> bool:
    """True for RAS, False for LPS."""
    v = str(value).strip().upper()
    if v in ("RAS", "0"):
        return True
    if v in ("LPS", "1"):
        return False
    raise VolregIOError(f"Landmark file `{path}` has coordinate system {excerpt(value)}; expected LPS or RAS.")


def _fcsv_frame(line: str, path: Path) -> bool:
    """True for RAS, False for LPS, from a ``.fcsv`` ``# CoordinateSystem`` line: ``= RAS`` as
    Slicer writes it, a colon read alike."""
    value = line.split("=", 1)[1] if "=" in line else line.split("CoordinateSystem", 1)[1].lstrip(" :")
    return _frame(value, path)


def csv_rows(text: str) -> list[list[str]]:
    """The rows of CSV text, a quoted field's line breaks kept inside it (the csv module splits the
    lines itself: ``str.splitlines`` would cut a quoted field in two, and split at form feeds,
    U+2028 and other separators inside a value)."""
    return list(csv.reader(io.StringIO(text)))


def fcsv_records(text: str) -> Iterator[tuple[int, str, list[str] | None]]:
    """The records of a Slicer ``.fcsv`` file: ``(line, text, row)`` for each, in order.

    A comment (``#`` first) or blank line gives its text (without the line break) and ``row``
    ``None``; a point gives its fields as ``row``, read as CSV over as many lines as its quoted
    fields span (``text`` is then the first of them); ``line`` counts from 1.
    """
    lines = io.StringIO(text)  # splits at "\n" alone, as the csv module expects
    read = 0

    def counted() -> Iterator[str]:
        nonlocal read
        for line in lines:
            read += 1
            yield line

    source = counted()
    for line in source:
        number, body = read, line.rstrip("\n")
        if body.startswith("#") or not body.strip():
            yield number, body, None
        else:  # the reader takes the lines after this one only while a quoted field goes on
            yield number, body, next(csv.reader(itertools.chain([line], source)))


def _read_fcsv(path: Path, text: str) -> np.ndarray:
    ras = True
    points = []
    for number, line, r in fcsv_records(text):
        if r is None:
            if line.startswith("#") and "CoordinateSystem" in line:
                ras = _fcsv_frame(line, path)
            continue
        if len(r) < 4:
            raise VolregIOError(f"Landmark file `{path}` line {number} has {len(r)} fields; expected Slicer's "
                                "id,x,y,z,... columns.")
        points.append([_number(v, path, f"line {number}") for v in r[1:4]])
    points = np.array(points, dtype=float).reshape(-1, 3)
    return points * _FLIP if ras else points


#: Slicer's ``positionStatus`` of a control point that was never placed (its position means nothing).
_UNPLACED = ("undefined",)


#: Millimetres per unit of a ``.mrk.json`` markup's ``coordinateUnits``.
_UNITS_MM = {"mm": 1.0, "um": 1e-3, "\u00b5m": 1e-3, "cm": 10.0, "m": 1000.0}


def _units_mm(value: object, path: Path) -> float:
    """Millimetres per unit of a markup's ``coordinateUnits``."""
    key = str(value).strip().lower()
    if key not in _UNITS_MM:
        raise VolregIOError(f"Landmark file `{path}` has coordinateUnits {excerpt(value)}; expected one of mm, um, cm, m.")
    return _UNITS_MM[key]


def _read_mrk_json(path: Path, text: str) -> np.ndarray:
    """The control points, with a row of NaN for each one not placed (``positionStatus``
    ``"undefined"``): their order pairs them with another file's."""
    data = parse_json(text, f"Landmark file `{path}`")
    expected = "expected a Slicer markups file: an object whose `markups` list holds objects with `controlPoints`"
    if not isinstance(data, dict):
        raise VolregIOError(f"Landmark file `{path}` holds {type(data).__name__} data at the top; {expected}.")
    if not isinstance(data.get("markups", []), list):
        raise VolregIOError(f"Landmark file `{path}` has a `markups` {type(data['markups']).__name__}, not a list; "
                            f"{expected}.")
    points = []
    for number, markup in enumerate(data.get("markups", []), start=1):
        if not isinstance(markup, dict) or not isinstance(markup.get("controlPoints", []), list):
            raise VolregIOError(f"Landmark file `{path}` markup {number} is not an object with a `controlPoints` list; "
                                f"{expected}.")
        ras = _frame(markup.get("coordinateSystem", "LPS"), path)
        scale = _units_mm(markup.get("coordinateUnits", "mm"), path)
        for cp in markup.get("controlPoints", []):
            unplaced = isinstance(cp, dict) and str(cp.get("positionStatus", "defined")).lower() in _UNPLACED
            if unplaced:
                points.append(np.full(3, np.nan))
                continue
            if not isinstance(cp, dict) or "position" not in cp:
                raise VolregIOError(f"Landmark file `{path}` control point {len(points) + 1} is not an object with a "
                                    f"`position`; {expected}.")
            _check_coordinates(cp["position"], path, len(points) + 1)
            try:
                p = np.asarray(cp["position"], dtype=float) * scale
            except (TypeError, ValueError):  # words or nested lists: numpy's message would quote them whole
                p = np.zeros(0)
            if p.shape != (3,):
                raise VolregIOError(f"Landmark file `{path}` control point {len(points) + 1} has position "
                                    f"{excerpt(cp['position'])}; expected three coordinates.")
            if not np.all(np.isfinite(p)):  # a row of NaN would read as never placed
                raise VolregIOError(f"Landmark file `{path}` control point {len(points) + 1} is placed (positionStatus "
                                    f"{excerpt(cp.get('positionStatus', 'defined'))}) but has position "
                                    f"{excerpt(cp['position'])}; "
                                    "expected finite coordinates, or positionStatus \"undefined\" for a point not placed.")
            points.append(p * _FLIP if ras else p)
    return np.array(points).reshape(-1, 3)


def _check_coordinates(position: object, path: Path, number: int) -> None:
    """Refuse a control point's ``position`` holding true/false or text, which numpy would read as
    numbers (true as 1 mm, ``"5"`` as 5 mm)."""
    if isinstance(position, list) and any(isinstance(v, (bool, str)) for v in position):
        what = "true or false" if any(isinstance(v, bool) for v in position) else "text"
        raise VolregIOError(f"Landmark file `{path}` control point {number} has position {excerpt(json.dumps(position), quote=False)}; "
                            f"expected three numbers (in the markup's coordinateUnits), not {what}.")


def _read_csv(path: Path, text: str) -> np.ndarray:
    rows = [r for r in csv_rows(text) if r and any(c.strip() for c in r)]
    if not rows:
        return np.zeros((0, 3))
    header = [c.strip().lower() for c in rows[0]]
    if not {"x", "y", "z"} <= set(header):
        raise VolregIOError(f"Landmark file `{path}` has header {excerpt(rows[0])}; expected a header row naming x,y,z (LPS mm).")
    cols = [header.index(c) for c in ("x", "y", "z")]
    points = []
    for number, r in enumerate(rows[1:], start=2):
        if len(r) <= max(cols):
            raise VolregIOError(f"Landmark file `{path}` row {number} has {len(r)} fields; expected x, y and z in "
                                f"columns {', '.join(str(c + 1) for c in cols)}, as the header names them.")
        points.append([_number(r[c], path, f"row {number}") for c in cols])
    return np.array(points, dtype=float).reshape(-1, 3)


def _number(text: str, path: Path, where: str) -> float:
    """``float(text)``, or a one-line error naming the file and ``where`` in it."""
    try:
        return float(text)
    except ValueError:
        raise VolregIOError(f"Landmark file `{path}` {where} holds {excerpt(text.strip())}; expected a number (mm).") from None


def read_landmarks(path: str | os.PathLike[str], *, keep_unplaced: bool = False) -> np.ndarray:
    """Read landmark points as an (L, 3) float array in LPS mm.

    Slicer ``.mrk.json`` control points that were never placed (``positionStatus``
    ``"undefined"``) are left out, or with ``keep_unplaced`` kept as rows of NaN so
    that the order still pairs the points with another file's (drop a pair where
    either side is NaN).

    Raises
    ------
    VolregIOError
        Missing or unreadable file, unknown suffix, bad numbers, a non-finite
        value, or no placed point at all -- one line naming the file.
    """
    p = Path(path)
    if not p.is_file():
        raise VolregIOError(f"Landmark file `{p}` does not exist or is not a file.")
    name = p.name.lower()
    try:
        text = p.read_text(encoding="utf-8-sig")  # a byte-order mark (Excel) is not part of the header
    except OSError as exc:
        raise VolregIOError(f"Landmark file `{p}` could not be read: {exc.strerror or exc}.") from None
    except UnicodeDecodeError:
        raise VolregIOError(f"Landmark file `{p}` is not UTF-8 text; expected .csv, .fcsv or .mrk.json text.") from None
    try:
        if name.endswith(".fcsv"):
            points = _read_fcsv(p, text)
        elif name.endswith(".mrk.json") or name.endswith(".json"):
            points = _read_mrk_json(p, text)
        elif name.endswith(".csv"):
            points = _read_csv(p, text)
        else:
            raise VolregIOError(f"Landmark file `{p}` has an unknown suffix; expected .csv (x,y,z LPS mm), .fcsv or .mrk.json.")
    except (ValueError, IndexError, KeyError, TypeError, UnicodeDecodeError) as exc:
        if isinstance(exc, VolregIOError):
            raise
        raise VolregIOError(f"Landmark file `{p}` could not be parsed: {exception_text(exc)}.") from None
    unplaced = np.zeros(len(points), dtype=bool)
    if name.endswith(".json"):
        unplaced = np.all(np.isnan(points), axis=1)
    if not np.any(~unplaced):
        more = f" ({int(unplaced.sum())} not placed)" if unplaced.any() else ""
        raise VolregIOError(f"Landmark file `{p}` holds no placed points{more}; expected at least one.")
    if not np.all(np.isfinite(points[~unplaced])):
        raise VolregIOError(f"Landmark file `{p}` holds NaN or Inf coordinates; expected finite mm.")
    return points if keep_unplaced else points[~unplaced]

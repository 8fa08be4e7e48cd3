"""Point files and meshes read for their positions and written back with new ones, all else kept.

``volreg apply`` carries landmarks and mesh vertices through a warp and writes them in
the format they came in.  :func:`read_point_set` reads the positions (LPS mm, as
everywhere in volreg) together with what the file holds besides;
:func:`write_point_set` writes that back with the positions replaced:

- CSV (``x,y,z`` header, LPS mm): every row and column kept as text, only the
  ``x``, ``y`` and ``z`` cells rewritten (so an ANTs point file keeps its ``t``,
  ``label`` and ``comment`` columns);
- Slicer ``.fcsv``: comment lines and every other column kept; positions written in
  the file's own coordinate system (RAS or LPS, as its ``# CoordinateSystem`` line says);
- Slicer ``.mrk.json`` (or ``.json``): the JSON kept, each placed control point's
  ``position`` rewritten in its markup's ``coordinateSystem``; control points never
  placed (``positionStatus`` ``"undefined"``) are read as rows of NaN and left as they are;
- ``.vtk``, ``.vtp``, ``.ply``, ``.stl``, ``.obj`` (pyvista): the dataset kept -- cells,
  point and cell data, field data -- with its points replaced; the point normals
  (the active normals, or an array named ``Normals``) are offered for updating, and
  cell-data normals, which would no longer hold, are removed (see :attr:`PointSetFile.dropped`).
  A PLY file holds normals, texture coordinates and one colour array (8-bit RGB or RGBA,
  over the vertices, the faces or both under one name); those are written back, and any
  other array is named in :attr:`PointSetFile.unwritable`;
- GIFTI ``.gii``: every data array and all metadata kept, the ``POINTSET`` array
  replaced (read and written as RAS, like :func:`volreg.io.meshes.read_surface`).

Positions are written at full double precision as text (shortest repr), float32
where the format stores that (GIFTI, most VTK files as read).
"""

from __future__ import annotations

import csv
import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from volreg.errors import VolregIOError, exception_text
from volreg.io._atomic import atomic_output
from volreg.io.documents import parse_json
from volreg.io.gifti import check_gifti_name, load_gifti
from volreg.io.landmarks import _fcsv_frame, _frame, _units_mm, csv_rows, fcsv_records, read_landmarks
from volreg.io.meshes import quiet_vtk, read_pyvista

__all__ = ["POINT_SUFFIXES", "MESH_FORMATS", "PointSetFile", "check_same_format", "point_set_kind", "read_point_set",
           "write_point_set"]

#: Landmark files :func:`read_point_set` reads (lower case; ``.json`` is a Slicer markups file).
POINT_SUFFIXES = (".csv", ".fcsv", ".mrk.json", ".json")
#: Mesh files :func:`read_point_set` reads (lower case).
MESH_FORMATS = (".vtk", ".vtp", ".ply", ".stl", ".obj", ".gii")

_FLIP = np.array([-1.0, -1.0, 1.0])


def point_set_kind(path: str | os.PathLike[str]) -> str | None:
    """The format of ``path`` by its suffix: ``"csv"``, ``"fcsv"``, ``"mrk.json"``, ``"mesh"``, ``"gifti"``, or None."""
    name = Path(path).name.lower()
    if name.endswith(".fcsv"):
        return "fcsv"
    if name.endswith(".json"):
        return "mrk.json"
    if name.endswith(".csv"):
        return "csv"
    if name.endswith(".gii"):
        return "gifti"
    if name.endswith(MESH_FORMATS):
        return "mesh"
    return None


def _suffix(path: Path) -> str:
    """The suffix that names the format (``.mrk.json`` whole)."""
    name = path.name.lower()
    return ".mrk.json" if name.endswith(".mrk.json") else path.suffix.lower()


@dataclass
class PointSetFile:
    """A point file or mesh as read, to be written back with new positions.

    Attributes
    ----------
    path : pathlib.Path
        The file read.
    kind : {"csv", "fcsv", "mrk.json", "mesh", "gifti"}
    points : (N, 3) float ndarray, LPS mm
        The positions (rows of NaN for Slicer control points never placed).
    normals : (N, 3) float ndarray or None
        The point normals of a mesh (LPS), if it has them.
    dropped : list of str
        What :func:`write_point_set` leaves out because it would no longer hold
        (cell-data normals of a mesh), one phrase each.
    unwritable : list of str
        What :func:`write_point_set` leaves out because the file's format cannot
        hold it (arrays of a PLY mesh besides its normals, texture coordinates and
        one colour array), one phrase each.
    """

    path: Path
    kind: str
    points: np.ndarray
    normals: np.ndarray | None = None
    dropped: list = field(default_factory=list)
    unwritable: list = field(default_factory=list)
    _content: Any = None
    _normal_names: tuple = ()
    _colours: str | None = None


def _read_pyvista(p: Path) -> PointSetFile:
    import pyvista as pv

    mesh = read_pyvista(p, "Mesh")
    if not isinstance(mesh, (pv.PolyData, pv.UnstructuredGrid, pv.StructuredGrid)):
        raise VolregIOError(f"Mesh `{p}` holds {type(mesh).__name__}; expected a mesh or point cloud with explicit points.")
    if mesh.n_points == 0:
        raise VolregIOError(f"Mesh `{p}` is empty (no vertices).")
    points = np.array(mesh.points, dtype=float)
    names = []
    active = mesh.point_data.active_normals_name if hasattr(mesh.point_data, "active_normals_name") else None
    for name in (active, "Normals"):
        if name and name in mesh.point_data and name not in names and np.shape(mesh.point_data[name]) == points.shape:
            names.append(name)
    normals = np.array(mesh.point_data[names[0]], dtype=float) if names else None
    if normals is not None and not np.all(np.isfinite(normals)):
        normals = None
        names = []
    dropped = []
    cell_active = mesh.cell_data.active_normals_name if hasattr(mesh.cell_data, "active_normals_name") else None
    cell_normals = {n for n in (cell_active, "Normals") if n and n in mesh.cell_data}
    for name in sorted(cell_normals):
        dropped.append(f"cell normals `{name}`")
    colours, unwritable = None, []
    if p.suffix.lower() == ".ply":
        colours, unwritable = _ply_contents(mesh, names[:1], cell_normals)
    return PointSetFile(p, "mesh", points, normals, dropped, unwritable, _content=mesh, _normal_names=tuple(names),
                        _colours=colours)


def _is_colour(values) -> bool:
    """Whether ``values`` can be a PLY colour array: 8-bit unsigned, 3 (RGB) or 4 (RGBA) components."""
    a = np.asarray(values)
    return a.dtype == np.uint8 and a.ndim == 2 and a.shape[1] in (3, 4)


def _ply_contents(mesh, normals: list, cell_normals: set) -> tuple[str | None, list]:
    """The colour array a PLY writer is to write (by name), and the arrays of ``mesh`` it cannot hold.

    VTK's PLY writer holds the active point normals, the active texture coordinates and one
    colour array, named when writing: written as vertex colours if it is a point array and as
    face colours if it is a cell array (or both, under one name).  ``RGB`` / ``RGBA``, the
    names VTK's PLY reader gives colours, come first.
    """
    point = [n for n in mesh.point_data.keys() if _is_colour(mesh.point_data[n])]
    cell = [n for n in mesh.cell_data.keys() if _is_colour(mesh.cell_data[n])]
    order = sorted(set(point + cell), key=lambda n: (n not in ("RGB", "RGBA"), n not in point, n))
    colours = order[0] if order else None
    tcoords = getattr(mesh.point_data, "active_texture_coordinates_name", None)
    held = {colours, tcoords, *normals}
    unwritable = [f"point array `{n}`" for n in mesh.point_data.keys() if n not in held]
    unwritable += [f"cell array `{n}`" for n in mesh.cell_data.keys() if n != colours and n not in cell_normals]
    unwritable += [f"field array `{n}`" for n in mesh.field_data.keys()]
    return colours, unwritable


def _read_gifti(p: Path) -> PointSetFile:
    import nibabel as nib

    img = load_gifti(p, "Mesh")
    try:
        arrays = [a for a in img.darrays if a.intent == nib.nifti1.intent_codes["NIFTI_INTENT_POINTSET"]]
    except Exception as exc:  # nibabel raises assorted types for bad files
        raise VolregIOError(f"Mesh `{p}` is not a readable GIFTI surface: {exception_text(exc)}.") from exc
    if len(arrays) != 1:
        raise VolregIOError(f"Mesh `{p}` has {len(arrays)} POINTSET data arrays; expected one (a GIFTI surface, .surf.gii).")
    data = np.asarray(arrays[0].data, dtype=float)
    if data.ndim != 2 or data.shape[1] != 3 or len(data) == 0:
        raise VolregIOError(f"Mesh `{p}` has a POINTSET of shape {data.shape}; expected (N, 3) vertices.")
    return PointSetFile(p, "gifti", data * _FLIP, None, [], _content=(img, arrays[0]))


def check_same_format(source: str | os.PathLike[str], output: str | os.PathLike[str]) -> None:
    """Refuse an ``output`` name whose format is not that of ``source`` (``.mrk.json`` and ``.json`` are one),
    and a GIFTI surface's output named as a data file (:func:`~volreg.io.gifti.check_gifti_name`).

    Raises
    ------
    VolregIOError
        One line naming both files and the suffix expected.
    """
    source, output = Path(source), Path(output)
    kind = point_set_kind(source)
    same = point_set_kind(output) == kind and (kind != "mesh" or _suffix(output) == _suffix(source))
    if not same:
        raise VolregIOError(f"Output `{output}` must have the suffix of `{source.name}` ({_suffix(source)}); "
                            "points and meshes are written in the format they were read in.")
    if kind == "gifti":  # a GIFTI surface is carried, and written back as one
        check_gifti_name(output, surface=True)


def read_point_set(path: str | os.PathLike[str]) -> PointSetFile:
    """Read the positions of a landmark file or mesh, keeping the rest for :func:`write_point_set`.

    Parameters
    ----------
    path : path-like
        ``.csv`` (``x,y,z`` header, LPS mm), ``.fcsv``, ``.mrk.json`` (or ``.json``),
        ``.vtk``, ``.vtp``, ``.ply``, ``.stl``, ``.obj`` or ``.gii``.

    Returns
    -------
    PointSetFile

    Raises
    ------
    VolregIOError
        One line naming the file: missing, unknown suffix, unreadable, no points,
        non-finite coordinates (see :func:`volreg.io.landmarks.read_landmarks` for
        the landmark formats).
    """
    p = Path(path)
    kind = point_set_kind(p)
    if kind is None:
        raise VolregIOError(f"`{p}` has an unsupported suffix; expected points ({', '.join(POINT_SUFFIXES)}) "
                            f"or a mesh ({', '.join(MESH_FORMATS)}).")
    if not p.is_file():
        raise VolregIOError(f"`{p}` does not exist or is not a file.")
    if kind in ("csv", "fcsv", "mrk.json"):
        points = read_landmarks(p, keep_unplaced=True)
        text = p.read_text(encoding="utf-8-sig")  # a byte-order mark, as read_landmarks allows
        content = parse_json(text, f"Landmark file `{p}`") if kind == "mrk.json" else text
        return PointSetFile(p, kind, points, None, [], _content=content)
    out = _read_gifti(p) if kind == "gifti" else _read_pyvista(p)
    if not np.all(np.isfinite(out.points)):
        bad = int((~np.isfinite(out.points)).any(axis=1).sum())
        raise VolregIOError(f"Mesh `{p}` has {bad} vertices with NaN/Inf coordinates; expected finite points.")
    return out


def _number(value: float) -> str:
    """A float as the shortest text that reads back as the same double."""
    text = repr(float(value))
    return "0" if text in ("0.0", "-0.0") else text


def _write_lines(rows: list[list[str]]) -> str:
    buffer = io.StringIO()
    csv.writer(buffer, lineterminator="\n").writerows(rows)
    return buffer.getvalue()


def _csv_text(text: str, points: np.ndarray) -> str:
    rows = csv_rows(text)
    data = [i for i, r in enumerate(rows) if r and any(c.strip() for c in r)]
    header = [c.strip().lower() for c in rows[data[0]]]
    cols = [header.index(c) for c in ("x", "y", "z")]
    for k, i in enumerate(data[1:]):
        for c, v in zip(cols, points[k]):
            rows[i][c] = _number(v)
    return _write_lines(rows)


def _fcsv_text(text: str, points: np.ndarray, path: Path) -> str:
    ras = True
    out, k = [], 0
    for _, line, row in fcsv_records(text):
        if row is None:  # a comment or blank line, kept as it is
            if line.startswith("#") and "CoordinateSystem" in line:
                ras = _fcsv_frame(line, path)
            out.append(line + "\n")
            continue
        q = points[k] * _FLIP if ras else points[k]
        row[1:4] = [_number(v) for v in q]
        out.append(_write_lines([row]))
        k += 1
    return "".join(out)


def _mrk_json_text(data: dict, points: np.ndarray, path: Path) -> str:
    k = 0
    for markup in data.get("markups", []):
        ras = _frame(markup.get("coordinateSystem", "LPS"), path)
        per_unit = _units_mm(markup.get("coordinateUnits", "mm"), path)  # back in the markup's own unit
        for cp in markup.get("controlPoints", []):
            q = points[k]
            k += 1
            if np.all(np.isnan(q)):  # never placed: left as it was
                continue
            cp["position"] = [float(v) / per_unit for v in (q * _FLIP if ras else q)]
    return json.dumps(data, indent=4) + "\n"


def write_point_set(data: PointSetFile, points: np.ndarray, path: str | os.PathLike[str], *,
                    normals: np.ndarray | None = None, force: bool = False) -> None:
    """Write ``data`` back with new positions, in its own format, atomically.

    Parameters
    ----------
    data : PointSetFile
        As :func:`read_point_set` returned it.
    points : (N, 3) float ndarray, LPS mm
        The new positions, one per row of ``data.points`` (rows of NaN stay unplaced
        control points; elsewhere finite).
    path : path-like
        The output; it must have the suffix of ``data.path`` (the same format).
    normals : (N, 3) float ndarray, optional
        New point normals (LPS) for a mesh that has them (``data.normals``); without
        them the point normals are written unchanged.
    force : bool
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        A suffix other than the input's, positions of the wrong shape or not finite,
        an existing ``path`` without ``force``, or a failed write.
    """
    p = Path(path)
    check_same_format(data.path, p)
    q = np.asarray(points, dtype=float)
    if q.shape != data.points.shape:
        raise VolregIOError(f"Expected `points` of shape {data.points.shape} (one per input point), got {q.shape}.")
    placed = ~np.all(np.isnan(data.points), axis=1)
    if not np.all(np.isfinite(q[placed])):
        raise VolregIOError(f"Expected finite `points` for `{p}`; they hold NaN or Inf.")
    if data.kind in ("csv", "fcsv", "mrk.json"):
        if data.kind == "csv":
            text = _csv_text(data._content, q)
        elif data.kind == "fcsv":
            text = _fcsv_text(data._content, q, data.path)
        else:
            text = _mrk_json_text(json.loads(json.dumps(data._content)), q, data.path)
        with atomic_output(p, force=force) as tmp:
            with open(tmp, "w", encoding="utf-8", newline="") as fh:
                fh.write(text)
        return
    if data.kind == "gifti":
        _write_gifti(data, q, p, force)
        return
    import pyvista as pv

    mesh = data._content.copy(deep=True)
    mesh.points = q.astype(np.asarray(data._content.points).dtype, copy=False)
    if normals is not None and data._normal_names:
        nv = np.asarray(normals, dtype=float)
        if nv.shape != q.shape or not np.all(np.isfinite(nv)):
            raise VolregIOError(f"Expected finite `normals` of shape {q.shape}, got {nv.shape}.")
        for name in data._normal_names:
            mesh.point_data[name] = nv.astype(np.asarray(data._content.point_data[name]).dtype, copy=False)
    for name in ("Normals", mesh.cell_data.active_normals_name if hasattr(mesh.cell_data, "active_normals_name") else None):
        if name and name in mesh.cell_data:
            del mesh.cell_data[name]
    if data._normal_names:
        mesh.point_data.active_normals_name = data._normal_names[0]
    with atomic_output(p, force=force) as tmp:
        try:
            with quiet_vtk():
                if isinstance(mesh, pv.PolyData):  # the normals as given, not recomputed (PLY, STL)
                    colours = {"texture": data._colours} if data._colours else {}  # PLY only
                    mesh.save(tmp, binary=True, recompute_normals=False, **colours)
                else:
                    mesh.save(tmp, binary=True)
        except Exception as exc:  # VTK writers raise assorted types
            raise VolregIOError(f"Mesh `{p}` could not be written: {exc}".splitlines()[0]) from exc


def _write_gifti(data: PointSetFile, points: np.ndarray, p: Path, force: bool) -> None:
    import copy

    import nibabel as nib

    img, array = data._content
    new = copy.deepcopy(img)
    index = img.darrays.index(array)
    target = new.darrays[index]
    values = (points * _FLIP).astype(np.asarray(array.data).dtype, copy=False)
    target.data = values
    with atomic_output(p, force=force) as tmp:
        try:
            nib.save(new, str(tmp))
        except Exception as exc:  # nibabel raises assorted types
            raise VolregIOError(f"Mesh `{p}` could not be written: {exc}".splitlines()[0]) from exc

"""Surface meshes and 2-D outlines: VTK, VTP, PLY, STL and OBJ via pyvista; GIFTI via :mod:`volreg.io.gifti`.

Vertices are world points in ITK physical space (LPS, mm), like everything
else in volreg; the pyvista formats carry no frame of their own and are taken
as LPS.  GIFTI files are RAS and converted (:mod:`volreg.io.gifti`).
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Mapping
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from volreg._lazy import LazyModule
from volreg.errors import VolregIOError, VolregWarning, exception_text
from volreg.io._atomic import atomic_output
from volreg.io._guards import check_mesh_sizes
from volreg.io.gifti import GiftiSurfaceMeta, is_gifti, read_gifti_data, read_gifti_surface, write_gifti

pv = LazyModule("pyvista")

__all__ = ["write_mesh", "read_mesh", "read_surface", "write_gifti", "add_vertex_data", "SurfaceData"]

#: Suffixes the mesh reader and writer accept (lower case).
MESH_SUFFIXES = (".vtk", ".vtp", ".ply", ".stl", ".obj")
# Which formats can hold what (as written by VTK's writers through pyvista).
_LINE_SUFFIXES = (".vtk", ".vtp", ".obj")
_NORMAL_SUFFIXES = (".vtk", ".vtp", ".ply", ".obj")
_POINT_DATA_SUFFIXES = (".vtk", ".vtp")


@contextmanager
def _no_vtk_logging():
    """Silence VTK reader errors that pyvista forwards to Python logging (volreg reports one line itself)."""
    previous = logging.root.manager.disable
    logging.disable(logging.CRITICAL)
    try:
        yield
    finally:
        logging.disable(previous)


@contextmanager
def quiet_vtk():
    """No VTK messages on the console or in Python logging (volreg reports one line itself)."""
    quiet = pv.vtk_verbosity("off") if hasattr(pv, "vtk_verbosity") else nullcontext()
    with quiet, _no_vtk_logging():
        yield


def read_pyvista(p: Path, what: str):
    """``pyvista.read(p)`` after the size guards, with VTK's messages turned into one-line errors.

    Parameters
    ----------
    p : Path
        A ``.vtk``, ``.vtp``, ``.ply``, ``.stl`` or ``.obj`` file.
    what : str
        How the error messages name the file ("Mesh", "Surface").

    Returns
    -------
    pyvista.DataSet (or whatever ``pyvista.read`` returns; the caller checks the type)

    Raises
    ------
    VolregIOError
        A header declaring more data than the file holds or memory allows, or a file
        that VTK cannot read or reads with a warning.
    """
    check_mesh_sizes(p, what)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with quiet_vtk():
                mesh = pv.read(p)
        except Exception as exc:  # pyvista/VTK raise assorted types for bad files
            raise VolregIOError(f"{what} `{p}` could not be read: {exception_text(exc)}") from exc
    problems = [w for w in caught if not issubclass(w.category, (DeprecationWarning, PendingDeprecationWarning))]
    if problems:
        raise VolregIOError(f"{what} `{p}` could not be read: {exception_text(problems[0].message)}")
    return mesh

def _mesh_suffix(path: Path, what: str) -> str:
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise VolregIOError(
            f"{what} `{path}` has unsupported suffix {suffix!r}; expected one of {', '.join(MESH_SUFFIXES)}."
        )
    return suffix


def _points3(values: object, n: int | None, name: str) -> np.ndarray:
    """Validate an (N, 2) or (N, 3) finite float array; pad 2-D with z = 0."""
    a = np.asarray(values, dtype=float)
    if a.ndim != 2 or a.shape[1] not in (2, 3) or (n is not None and a.shape[0] != n):
        rows = "N" if n is None else str(n)
        raise VolregIOError(f"Expected `{name}` of shape ({rows}, 3) or ({rows}, 2), got {a.shape}.")
    if not np.all(np.isfinite(a)):
        bad = int((~np.isfinite(a)).any(axis=1).sum())
        raise VolregIOError(f"Expected finite `{name}`, got {bad} rows with NaN/Inf.")
    if a.shape[1] == 2:
        a = np.column_stack([a, np.zeros(len(a))])
    return a


def write_mesh(
    vertices: np.ndarray,
    cells: np.ndarray,
    path: str | os.PathLike[str],
    *,
    normals: np.ndarray | None = None,
    point_data: Mapping[str, np.ndarray] | None = None,
    force: bool = False,
    allow_points: bool = False,
) -> None:
    """Write a triangle mesh or a set of line segments (or, with ``allow_points``, a point cloud), atomically.

    Parameters
    ----------
    vertices : (N, 3) or (N, 2) float ndarray, mm
        Vertex positions (LPS).  2-D points are written with ``z = 0``.
    cells : (F, 3) or (F, 2) int ndarray
        Triangles (vertex indices) or line segments (2-D outlines).
    path : path-like
        ``.vtk`` (legacy), ``.vtp``, ``.ply``, ``.stl`` or ``.obj``, chosen by
        suffix.  Segments can be written to ``.vtk``, ``.vtp`` and ``.obj``
        only; normals to all but ``.stl``; ``point_data`` to ``.vtk`` and
        ``.vtp`` only.
    normals : (N, 3) or (N, 2) float ndarray, optional
        Per-vertex normals, stored as the point array ``"Normals"`` and made
        the active normals.
    point_data : mapping of str to (N, ...) ndarray, optional
        Extra per-vertex arrays, stored under their names.
    force : bool, default False
        Overwrite an existing ``path``.
    allow_points : bool, default False
        Accept ``cells`` of shape (0, 3) and write the vertices alone (a point cloud).

    Raises
    ------
    VolregIOError
        On malformed inputs (shapes, NaN, out-of-range indices, no cells), a
        format that cannot hold what was given, an existing ``path`` without
        ``force``, or a failed write.
    """
    p = Path(path)
    suffix = _mesh_suffix(p, "Mesh")
    points = _points3(vertices, None, "vertices")
    n = len(points)
    c = np.asarray(cells)
    if c.ndim != 2 or c.shape[1] not in (2, 3) or not (np.issubdtype(c.dtype, np.integer) or c.size == 0):
        raise VolregIOError(f"Expected integer `cells` of shape (F, 3) or (F, 2), got {c.shape} {c.dtype}.")
    if c.shape[0] == 0 and not allow_points:
        raise VolregIOError(f"Expected at least one cell in `cells`; refusing to write an empty mesh to `{p}`.")
    if c.size and (c.min() < 0 or c.max() >= n):
        raise VolregIOError(f"Expected `cells` to index vertices in [0, {n}), got values in [{c.min()}, {c.max()}].")
    c = c.astype(np.int64)
    is_lines = c.shape[1] == 2
    if is_lines and suffix not in _LINE_SUFFIXES:
        raise VolregIOError(
            f"Mesh `{p}`: {suffix} cannot hold line segments; expected one of {', '.join(_LINE_SUFFIXES)}."
        )
    if normals is not None and suffix not in _NORMAL_SUFFIXES:
        raise VolregIOError(
            f"Mesh `{p}`: {suffix} cannot hold vertex normals; expected one of {', '.join(_NORMAL_SUFFIXES)}."
        )
    if point_data and suffix not in _POINT_DATA_SUFFIXES:
        raise VolregIOError(
            f"Mesh `{p}`: {suffix} cannot hold `point_data`; expected one of {', '.join(_POINT_DATA_SUFFIXES)}."
        )

    connectivity = np.column_stack([np.full(len(c), c.shape[1], dtype=np.int64), c]).ravel()
    if c.shape[0] == 0:
        mesh = pv.PolyData(points)  # a point cloud: one vertex cell per point
    else:
        mesh = pv.PolyData(points, lines=connectivity) if is_lines else pv.PolyData(points, faces=connectivity)
    for name, values in (point_data or {}).items():
        values = np.asarray(values)
        if name == "Normals":
            raise VolregIOError("Expected `point_data` not to contain 'Normals'; pass `normals=` instead.")
        if values.ndim == 0 or values.shape[0] != n:
            raise VolregIOError(f"Expected `point_data[{name!r}]` with first axis of length {n}, got {values.shape}.")
        mesh.point_data[name] = values
    if normals is not None:
        # float32: VTK's PLY writer drops normals of any other type.
        mesh.point_data["Normals"] = _points3(normals, n, "normals").astype(np.float32)
        mesh.GetPointData().SetActiveNormals("Normals")

    with atomic_output(p, force=force) as tmp:
        try:
            mesh.save(tmp, binary=True, recompute_normals=False)
        except Exception as exc:  # VTK writers raise assorted types
            raise VolregIOError(f"Mesh `{p}` could not be written: {exc}".splitlines()[0]) from exc


def read_mesh(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a triangle mesh.

    Parameters
    ----------
    path : path-like
        ``.vtk``, ``.vtp``, ``.ply``, ``.stl`` or ``.obj``.  Polygons and
        triangle strips are triangulated; non-PolyData datasets (e.g. an
        unstructured grid in a legacy ``.vtk``) are reduced to their surface.
        A GIFTI surface ``.gii`` is read as RAS and converted to LPS.

    Returns
    -------
    vertices : (N, 3) float ndarray, mm
        As stored (STL readers merge duplicate corners, so order may differ
        from what was written).
    triangles : (F, 3) int ndarray
        Vertex indices.
    normals : (N, 3) float ndarray or None
        The active point normals, or the point array ``"Normals"``, if present.

    Raises
    ------
    VolregIOError
        If the file is missing, unreadable, empty, has no triangles, or has
        NaN/Inf vertices.
    """
    p = Path(path)
    if not p.exists():
        raise VolregIOError(f"Mesh `{p}` does not exist.")
    if not p.is_file():
        raise VolregIOError(f"Mesh `{p}` is not a regular file.")
    if p.suffix.lower() == ".gii":
        vertices, triangles, _ = read_gifti_surface(p)
        if len(triangles) == 0:
            raise VolregIOError(f"Mesh `{p}` has no triangles (a POINTSET alone); expected a surface.")
        if not np.all(np.isfinite(vertices)):
            raise VolregIOError(f"Mesh `{p}` has vertices with NaN/Inf coordinates; expected finite points.")
        if triangles.min() < 0 or triangles.max() >= len(vertices):
            raise VolregIOError(f"Mesh `{p}` has triangles indexing missing vertices; expected indices below "
                                f"{len(vertices)}.")
        return vertices, triangles, None
    _mesh_suffix(p, "Mesh")
    mesh = read_pyvista(p, "Mesh")
    if mesh is None or not isinstance(mesh, pv.DataSet):
        raise VolregIOError(f"Mesh `{p}` holds {type(mesh).__name__}; expected a single surface mesh.")
    if not isinstance(mesh, pv.PolyData):
        mesh = mesh.extract_surface()
    if mesh.n_points == 0:
        raise VolregIOError(f"Mesh `{p}` is empty (no vertices).")
    vertices = np.array(mesh.points, dtype=float)
    if not np.all(np.isfinite(vertices)):
        bad = int((~np.isfinite(vertices)).any(axis=1).sum())
        raise VolregIOError(f"Mesh `{p}` has {bad} vertices with NaN/Inf coordinates; expected finite points.")

    tri = mesh.triangulate()
    faces = np.asarray(tri.faces, dtype=np.int64)
    if faces.size == 0:
        raise VolregIOError(f"Mesh `{p}` has no triangles (only {mesh.n_cells} vertex/line cells); expected a surface.")
    faces = faces.reshape(-1, 4)
    if not np.all(faces[:, 0] == 3) or tri.n_points != mesh.n_points:
        raise VolregIOError(f"Mesh `{p}` could not be triangulated; expected polygonal faces.")
    triangles = faces[:, 1:].copy()

    normals = tri.point_data.active_normals
    if normals is None and "Normals" in tri.point_data:
        normals = tri.point_data["Normals"]
    if normals is not None:
        normals = np.array(normals, dtype=float)
        if normals.shape != vertices.shape:
            normals = None
    return vertices, triangles, normals


# ----------------------------------------------------------------------------- surfaces with data

#: Suffixes :func:`read_surface` accepts: pyvista's formats and GIFTI surfaces.
SURFACE_SUFFIXES = MESH_SUFFIXES + (".gii",)


@dataclass
class SurfaceData:
    """A surface read from a file: a triangle mesh or a bare point cloud, with its per-vertex arrays.

    Attributes
    ----------
    vertices : (N, 3) float ndarray, mm (LPS)
    triangles : (F, 3) int ndarray
        Empty (F = 0) for a point cloud.
    normals : (N, 3) float ndarray or None
        Stored vertex normals, if any, as stored: rows may be zero or not finite
        (:func:`volreg.morph.checked_normals` computes those again).
    arrays : dict of str to (N, ...) ndarray
        Other per-vertex arrays (scalars, colours, labels), by name.
    gifti : GiftiSurfaceMeta or None
        For a GIFTI surface, its metadata and coordinate system (to write back).
    array_meta : dict of str to GiftiArrayMeta
        For arrays read from GIFTI data files, their metadata, intents and label tables.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray | None
    arrays: dict = field(default_factory=dict)
    gifti: GiftiSurfaceMeta | None = None
    array_meta: dict = field(default_factory=dict)


def add_vertex_data(surface: SurfaceData, paths, role: str) -> None:
    """Read per-vertex GIFTI data files onto ``surface``, in place.

    Parameters
    ----------
    surface : SurfaceData
        The surface the data lies on (its vertex count is checked).
    paths : iterable of path-like
        ``.shape.gii``, ``.func.gii`` or ``.label.gii`` files; each becomes the
        array :func:`volreg.io.gifti.data_name` (``lh.thickness`` for
        ``lh.thickness.shape.gii``), with its metadata in ``surface.array_meta``.
    role : str
        The surface as errors name it, e.g. ``"SOURCE `lh.white.surf.gii`"``.

    Raises
    ------
    VolregIOError
        A file that is not GIFTI data, has not one value per vertex, or whose
        name is already an array of ``surface``.
    """
    for path in paths:
        p = Path(path)
        if not is_gifti(p):
            raise VolregIOError(f"Data file `{p}` has suffix {p.suffix!r}; expected a GIFTI data file "
                                "(.shape.gii, .func.gii, .label.gii).")
        name, values, meta = read_gifti_data(p, len(surface.vertices), role)
        if name in surface.arrays:
            raise VolregIOError(f"Data file `{p}` gives the array `{name}`, which {role} already has; "
                                "expected one file per array name.")
        surface.arrays[name] = values
        surface.array_meta[name] = meta


def read_surface(path: str | os.PathLike[str]) -> SurfaceData:
    """Read a surface mesh or point cloud with its per-vertex arrays.

    Parameters
    ----------
    path : path-like
        ``.vtk``, ``.vtp``, ``.ply``, ``.stl``, ``.obj`` (through pyvista; a
        file with vertices only is a point cloud) or a GIFTI surface ``.gii``
        (its coordinates are taken as RAS and converted to LPS).

    Returns
    -------
    SurfaceData

    Raises
    ------
    VolregIOError
        Missing, unreadable or empty file, NaN/Inf vertices, faces that are
        not polygons, or triangle indices out of range.
    """
    p = Path(path)
    if not p.exists():
        raise VolregIOError(f"Surface `{p}` does not exist.")
    if not p.is_file():
        raise VolregIOError(f"Surface `{p}` is not a regular file.")
    suffix = p.suffix.lower()
    if suffix not in SURFACE_SUFFIXES:
        raise VolregIOError(f"Surface `{p}` has unsupported suffix {suffix!r}; expected one of {', '.join(SURFACE_SUFFIXES)}.")
    if suffix == ".gii":
        vertices, triangles, meta = read_gifti_surface(p)
        out = SurfaceData(vertices, triangles, None, {}, gifti=meta)
    else:
        mesh = read_pyvista(p, "Surface")
        if mesh is None or not isinstance(mesh, pv.DataSet):
            raise VolregIOError(f"Surface `{p}` holds {type(mesh).__name__}; expected a single surface mesh.")
        if not isinstance(mesh, pv.PolyData):
            mesh = mesh.extract_surface()
        triangles = np.zeros((0, 3), np.int64)
        if mesh.faces.size:  # polygons (a point cloud has none)
            tri = mesh.triangulate()
            faces = np.asarray(tri.faces, dtype=np.int64).reshape(-1, 4)
            if tri.n_points != mesh.n_points or not np.all(faces[:, 0] == 3):
                raise VolregIOError(f"Surface `{p}` could not be triangulated; expected polygonal faces.")
            triangles = faces[:, 1:].copy()
            mesh = tri
        normals = mesh.point_data.active_normals
        if normals is None and "Normals" in mesh.point_data:
            normals = mesh.point_data["Normals"]
        normals = None if normals is None else np.array(normals, dtype=float)
        arrays = {name: np.array(mesh.point_data[name]) for name in mesh.point_data.keys()
                  if name != "Normals" and len(mesh.point_data[name]) == mesh.n_points}
        out = SurfaceData(np.array(mesh.points, dtype=float), triangles, normals, arrays)
    if len(out.vertices) == 0:
        raise VolregIOError(f"Surface `{p}` is empty (no vertices).")
    if not np.all(np.isfinite(out.vertices)):
        bad = int((~np.isfinite(out.vertices)).any(axis=1).sum())
        raise VolregIOError(f"Surface `{p}` has {bad} vertices with NaN/Inf coordinates; expected finite points.")
    if out.triangles.size and (out.triangles.min() < 0 or out.triangles.max() >= len(out.vertices)):
        raise VolregIOError(f"Surface `{p}` has triangles indexing missing vertices; expected indices below {len(out.vertices)}.")
    if out.normals is not None and out.normals.shape != out.vertices.shape:
        out.normals = None  # unusable normals are estimated again (rows of zero or NaN: by the surface's users)
    t = out.triangles
    # triangles that repeat a vertex (zero area by their indices) have no edges of their own
    proper = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 2] != t[:, 0])] if len(t) else t
    if len(proper):
        edges = np.sort(proper[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        bad = int(np.count_nonzero(counts > 2))
        if bad:
            warnings.warn(
                f"Surface `{p}` has {bad} non-manifold edges (shared by more than two triangles); its normals and "
                "implicit surface may be unreliable there (repair the mesh, e.g. with pymeshfix or MeshLab).",
                VolregWarning,
                stacklevel=2,
            )
    return out

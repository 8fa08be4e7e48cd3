"""GIFTI surfaces (``.surf.gii``) and per-vertex data files (``.shape.gii``, ``.func.gii``, ``.label.gii``).

GIFTI coordinates are RAS millimetres (FreeSurfer's surface RAS or scanner RAS,
whichever space the file's POINTSET is in; its coordinate-system transform is
kept as written, not applied).  volreg works in LPS millimetres: this module is
the one place where GIFTI points change frame, by negating x and y on reading
and on writing.

What a file carries besides coordinates is kept so that it can be written back:
the file's and the data arrays' metadata (``AnatomicalStructurePrimary``,
``AnatomicalStructureSecondary``, ``GeometricType``, ``Name``, FreeSurfer's
volume geometry ...), the POINTSET's coordinate system, the data arrays'
intents and the label table of a ``.label.gii``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from volreg.errors import VolregIOError, exception_text
from volreg.io._atomic import atomic_output
from volreg.io._guards import check_gifti_sizes

__all__ = [
    "DATA_KINDS",
    "GiftiArrayMeta",
    "GiftiSurfaceMeta",
    "check_gifti_name",
    "data_name",
    "is_gifti",
    "read_gifti_data",
    "read_gifti_surface",
    "write_gifti",
    "write_gifti_data",
]

#: ``LPS = RAS * _FLIP`` and ``RAS = LPS * _FLIP``, per point.
_FLIP = np.array([-1.0, -1.0, 1.0])
#: The kinds of per-vertex data file, by the suffix before ``.gii``.
DATA_KINDS = ("shape", "func", "label")
#: Metadata keys that describe the surface a data file lies on (taken from the surface when data is carried over).
STRUCTURE_KEYS = ("AnatomicalStructurePrimary", "AnatomicalStructureSecondary")
_POINTSET = "NIFTI_INTENT_POINTSET"
_TRIANGLE = "NIFTI_INTENT_TRIANGLE"


def is_gifti(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` names a GIFTI file (suffix ``.gii``, any case)."""
    return Path(path).suffix.lower() == ".gii"


def _kind_of(path: Path) -> str | None:
    """``"shape"``, ``"func"`` or ``"label"`` from a name like ``lh.thickness.shape.gii``; None otherwise."""
    parts = path.name.lower().split(".")
    return parts[-2] if len(parts) >= 3 and parts[-2] in DATA_KINDS else None


def check_gifti_name(path: str | os.PathLike[str], *, surface: bool) -> None:
    """Refuse a GIFTI output named as the other kind of GIFTI file.

    A surface (``POINTSET`` and ``TRIANGLE``) written as ``x.shape.gii`` (or ``.func.gii``,
    ``.label.gii``) is taken for per-vertex values by the tools that go by the name (Connectome
    Workbench, FreeSurfer, volreg's own ``--source-data``), and values written as ``x.surf.gii``
    for a surface.

    Parameters
    ----------
    path : path-like
        The output's name.
    surface : bool
        Whether a surface is to be written there (else a data file).

    Raises
    ------
    VolregIOError
        One line naming the output and the suffix expected.
    """
    p = Path(path)
    kind = _kind_of(p)
    if surface and kind is not None:
        raise VolregIOError(f"Output `{p}` has the suffix of a GIFTI data file (.{kind}.gii) but would hold a surface; "
                            f"expected a surface name such as `{data_name(p)}.surf.gii` (data files hold per-vertex "
                            "values).")
    if not surface and p.name.lower().endswith(".surf.gii"):
        raise VolregIOError(f"Output `{p}` has the suffix of a GIFTI surface (.surf.gii) but would hold per-vertex "
                            "values; expected a GIFTI data file (.shape.gii, .func.gii, .label.gii).")


def data_name(path: str | os.PathLike[str]) -> str:
    """The array name of a data file: its file name without ``.gii`` and ``.shape``/``.func``/``.label``.

    ``lh.thickness.shape.gii`` gives ``lh.thickness``.
    """
    p = Path(path)
    stem = p.name[: -len(".gii")] if p.name.lower().endswith(".gii") else p.name
    if _kind_of(p) is not None:
        stem = stem[: stem.rfind(".")]
    return stem


@dataclass
class GiftiSurfaceMeta:
    """What a GIFTI surface carries besides its coordinates and triangles.

    Attributes
    ----------
    file_meta : dict of str to str
        The file's metadata.
    pointset_meta, triangle_meta : dict of str to str
        The metadata of the POINTSET and TRIANGLE data arrays (Workbench puts
        ``AnatomicalStructurePrimary`` and ``GeometricType`` on the POINTSET).
    dataspace, xformspace : int
        The POINTSET's coordinate system codes (NIFTI_XFORM_*), as written.
    xform : (4, 4) float ndarray
        The POINTSET's transform from ``dataspace`` to ``xformspace``, as written (not applied).
    """

    file_meta: dict = field(default_factory=dict)
    pointset_meta: dict = field(default_factory=dict)
    triangle_meta: dict = field(default_factory=dict)
    dataspace: int = 0
    xformspace: int = 0
    xform: np.ndarray = field(default_factory=lambda: np.eye(4))

    def structure(self) -> dict:
        """The ``AnatomicalStructure*`` entries of the surface (file metadata first, then the POINTSET's)."""
        out = {k: v for k, v in self.pointset_meta.items() if k in STRUCTURE_KEYS}
        out.update({k: v for k, v in self.file_meta.items() if k in STRUCTURE_KEYS})
        return out


@dataclass
class GiftiArrayMeta:
    """What a GIFTI data file carries besides its values.

    Attributes
    ----------
    kind : {"shape", "func", "label"}
        The kind of file (from its suffix, else from its label table).
    file_meta : dict of str to str
        The file's metadata.
    array_meta : list of dict
        Each data array's metadata (one per column of the values).
    intents : list of str
        Each data array's intent (``NIFTI_INTENT_SHAPE``, ``NIFTI_INTENT_LABEL``, ...).
    label_table : dict of int to (str, (4,) tuple of float) or None
        Key -> (name, RGBA in [0, 1]) of a label file; None for other data.
    """

    kind: str = "shape"
    file_meta: dict = field(default_factory=dict)
    array_meta: list = field(default_factory=list)
    intents: list = field(default_factory=list)
    label_table: dict | None = None

    @property
    def is_label(self) -> bool:
        """Whether the values are label keys (a label file or a label table)."""
        return self.kind == "label" or bool(self.label_table)


def load_gifti(p: Path, what: str):
    """The nibabel GiftiImage at ``p``; one-line errors for a missing or unreadable file."""
    import nibabel as nib

    if not p.exists():
        raise VolregIOError(f"{what} `{p}` does not exist.")
    if not p.is_file():
        raise VolregIOError(f"{what} `{p}` is not a regular file.")
    check_gifti_sizes(p, what)
    try:
        img = nib.load(str(p))
    except Exception as exc:  # nibabel raises assorted types for bad files
        raise VolregIOError(f"{what} `{p}` is not a readable GIFTI file: {exception_text(exc)}.") from exc
    if not isinstance(img, nib.gifti.GiftiImage):
        raise VolregIOError(f"{what} `{p}` is a {type(img).__name__}; expected a GIFTI file.")
    return img


def _intent(darray) -> str:
    from nibabel.nifti1 import intent_codes

    return str(intent_codes.niistring[darray.intent])


def read_gifti_surface(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, GiftiSurfaceMeta]:
    """Read a GIFTI surface: its POINTSET (RAS mm, converted to LPS), TRIANGLE array and metadata.

    Parameters
    ----------
    path : path-like
        A ``.gii`` file with one POINTSET data array and at most one TRIANGLE
        data array (none: a point cloud).

    Returns
    -------
    vertices : (N, 3) float ndarray, mm (LPS)
    triangles : (F, 3) int ndarray
        F = 0 for a point cloud.
    meta : GiftiSurfaceMeta

    Raises
    ------
    VolregIOError
        A missing or unreadable file, no POINTSET (e.g. a data file given as a
        surface), a POINTSET not of shape (N, 3), or faces that are not
        triangles.
    """
    p = Path(path)
    img = load_gifti(p, "Surface")
    points = [d for d in img.darrays if _intent(d) == _POINTSET]
    triangles = [d for d in img.darrays if _intent(d) == _TRIANGLE]
    if not points:
        raise VolregIOError(f"Surface `{p}` has no POINTSET data array; expected a GIFTI surface (.surf.gii), "
                            "not a data file (.shape.gii, .func.gii, .label.gii: pass those with --source-data "
                            "or --target-data).")
    if len(points) > 1 or len(triangles) > 1:
        raise VolregIOError(f"Surface `{p}` has {len(points)} POINTSET and {len(triangles)} TRIANGLE data arrays; "
                            "expected one of each.")
    pointset = points[0]
    xyz = np.asarray(pointset.data, dtype=float)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0:
        raise VolregIOError(f"Surface `{p}` has a POINTSET of shape {xyz.shape}; expected (N, 3) coordinates.")
    if triangles:
        tri = np.asarray(triangles[0].data)
        if tri.ndim == 2 and tri.shape[1] == 4 and np.issubdtype(tri.dtype, np.integer):
            tri = np.concatenate([tri[:, [0, 1, 2]], tri[:, [0, 2, 3]]])  # quads: (a, b, c) and (a, c, d)
        if tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer):
            faces = f"faces of {tri.shape[1]} vertices" if tri.ndim == 2 else f"a TRIANGLE array of shape {tri.shape}"
            raise VolregIOError(f"Surface `{p}` has {faces}; expected triangles or quads (an (F, 3) or (F, 4) integer array).")
        tri = tri.astype(np.int64)
    else:
        tri = np.zeros((0, 3), np.int64)
    coordsys = pointset.coordsys
    meta = GiftiSurfaceMeta(
        file_meta=dict(img.meta),
        pointset_meta=dict(pointset.meta),
        triangle_meta=dict(triangles[0].meta) if triangles else {},
        dataspace=int(coordsys.dataspace) if coordsys is not None else 0,
        xformspace=int(coordsys.xformspace) if coordsys is not None else 0,
        xform=np.array(coordsys.xform, dtype=float) if coordsys is not None else np.eye(4),
    )
    return xyz * _FLIP, tri, meta


def read_gifti_data(path: str | os.PathLike[str], n_vertices: int, surface: str) -> tuple[str, np.ndarray, GiftiArrayMeta]:
    """Read a per-vertex GIFTI data file (``.shape.gii``, ``.func.gii``, ``.label.gii``).

    Parameters
    ----------
    path : path-like
        The data file: one or more data arrays of ``n_vertices`` values each.
    n_vertices : int
        The number of vertices of the surface the data lies on.
    surface : str
        That surface, as errors name it (e.g. ``"SOURCE `lh.white.surf.gii`"``).

    Returns
    -------
    name : str
        :func:`data_name` of the file (``lh.thickness`` for ``lh.thickness.shape.gii``).
    values : (N,) or (N, K) ndarray
        One column per data array (K > 1 for a time series or several maps),
        in the file's dtype; label keys for a label file.
    meta : GiftiArrayMeta

    Raises
    ------
    VolregIOError
        A missing or unreadable file, a surface given as data, no data array,
        or a data array without exactly one value per vertex.
    """
    p = Path(path)
    img = load_gifti(p, "Data file")
    if not img.darrays:
        raise VolregIOError(f"Data file `{p}` has no data arrays; expected per-vertex values.")
    intents = [_intent(d) for d in img.darrays]
    if _POINTSET in intents or _TRIANGLE in intents:
        raise VolregIOError(f"Data file `{p}` is a GIFTI surface (POINTSET/TRIANGLE); expected per-vertex data "
                            "(.shape.gii, .func.gii, .label.gii).")
    columns = []
    for d in img.darrays:
        a = np.asarray(d.data)
        if a.ndim == 2 and 1 in a.shape:
            a = a.reshape(-1)
        if a.ndim != 1 or len(a) != n_vertices:
            raise VolregIOError(f"Data file `{p}` has a data array of shape {a.shape}; expected {n_vertices} values, "
                                f"one per vertex of {surface}.")
        columns.append(a)
    values = columns[0] if len(columns) == 1 else np.column_stack(columns)
    if not np.issubdtype(values.dtype, np.integer) and not np.all(np.isfinite(values.astype(float))):
        raise VolregIOError(f"Data file `{p}` holds NaN/Inf values; expected finite per-vertex values.")
    table = None
    if img.labeltable is not None and img.labeltable.labels:
        table = {}
        for lab in img.labeltable.labels:
            rgba = tuple(float(c) if c is not None else 0.0 for c in (lab.red, lab.green, lab.blue, lab.alpha))
            table[int(lab.key)] = (str(lab.label or ""), rgba)
    kind = _kind_of(p) or ("label" if table or "NIFTI_INTENT_LABEL" in intents else "shape")
    meta = GiftiArrayMeta(kind=kind, file_meta=dict(img.meta), array_meta=[dict(d.meta) for d in img.darrays],
                          intents=intents, label_table=table)
    return data_name(p), values, meta


def _save(img, p: Path, force: bool) -> None:
    import nibabel as nib

    with atomic_output(p, force=force) as tmp:
        try:
            nib.save(img, str(tmp))
        except Exception as exc:
            raise VolregIOError(f"GIFTI file `{p}` could not be written: {exc}".splitlines()[0]) from exc


def write_gifti(vertices: np.ndarray, triangles: np.ndarray, path: str | os.PathLike[str], *,
                meta: GiftiSurfaceMeta | None = None, force: bool = False) -> None:
    """Write a GIFTI surface (POINTSET in RAS mm, float32; TRIANGLE int32), atomically.

    Parameters
    ----------
    vertices : (N, 3) float ndarray, mm (LPS)
        Stored as RAS (x and y negated), the frame FreeSurfer and Connectome
        Workbench expect.
    triangles : (F, 3) int ndarray
        Vertex indices; F = 0 writes the POINTSET alone (a point cloud).
    path : path-like
        The output, conventionally ``*.surf.gii``.
    meta : GiftiSurfaceMeta, optional
        Metadata and coordinate system to write (those of the surface the
        vertices came from); none by default.
    force : bool, default False
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        Malformed vertices or triangles, a ``path`` named as a data file
        (:func:`check_gifti_name`), an existing ``path`` without ``force``, or a
        failed write.
    """
    from nibabel.gifti import GiftiCoordSystem, GiftiDataArray, GiftiImage, GiftiMetaData

    p = Path(path)
    check_gifti_name(p, surface=True)
    pts = np.asarray(vertices, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or not np.all(np.isfinite(pts)):
        raise VolregIOError(f"Expected finite `vertices` of shape (N, 3), got {pts.shape}.")
    tri = np.asarray(triangles)
    if tri.size == 0:
        tri = np.zeros((0, 3), np.int64)
    if (tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer)
            or (len(tri) and (tri.min() < 0 or tri.max() >= len(pts)))):
        raise VolregIOError(f"Expected integer `triangles` of shape (F, 3) indexing {len(pts)} vertices, got {tri.shape}.")
    meta = meta or GiftiSurfaceMeta()
    coordsys = GiftiCoordSystem(meta.dataspace, meta.xformspace, np.asarray(meta.xform, float))
    darrays = [GiftiDataArray((pts * _FLIP).astype(np.float32), intent=_POINTSET, datatype="NIFTI_TYPE_FLOAT32",
                              coordsys=coordsys, meta=GiftiMetaData(meta.pointset_meta))]
    if len(tri):
        darrays.append(GiftiDataArray(tri.astype(np.int32), intent=_TRIANGLE, datatype="NIFTI_TYPE_INT32",
                                      meta=GiftiMetaData(meta.triangle_meta)))
    _save(GiftiImage(meta=GiftiMetaData(meta.file_meta), darrays=darrays), p, force)


def write_gifti_data(values: np.ndarray, path: str | os.PathLike[str], *, meta: GiftiArrayMeta | None = None,
                     structure: dict | None = None, force: bool = False) -> None:
    """Write per-vertex values as a GIFTI data file, atomically.

    Parameters
    ----------
    values : (N,) or (N, K) ndarray
        One data array per column.  Integers are written as int32, anything
        else as float32.
    path : path-like
        The output, conventionally ``*.shape.gii``, ``*.func.gii`` or ``*.label.gii``.
    meta : GiftiArrayMeta, optional
        Metadata, intents and label table to write (those of the file the values
        came from).  Without it: intent ``NIFTI_INTENT_SHAPE`` for floats,
        ``NIFTI_INTENT_NONE`` for integers, no metadata.
    structure : dict of str to str, optional
        ``AnatomicalStructurePrimary``/``Secondary`` of the surface the values
        now lie on; they replace those of ``meta`` in the file's metadata.
    force : bool, default False
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        Values that are not 1-D or 2-D, a ``path`` named as a surface
        (:func:`check_gifti_name`), an existing ``path`` without ``force``, or
        a failed write.
    """
    from nibabel.gifti import GiftiDataArray, GiftiImage, GiftiLabel, GiftiLabelTable, GiftiMetaData

    p = Path(path)
    check_gifti_name(p, surface=False)
    a = np.asarray(values)
    if a.ndim not in (1, 2) or len(a) == 0:
        raise VolregIOError(f"Expected `values` of shape (N,) or (N, K), got {a.shape}.")
    columns = [a] if a.ndim == 1 else [a[:, k] for k in range(a.shape[1])]
    meta = meta or GiftiArrayMeta()
    integer = a.dtype.kind in "iub"
    if meta.is_label and not integer:
        raise VolregIOError(f"Expected integer label keys for label file `{p}`, got {a.dtype}.")
    dtype, datatype = (np.int32, "NIFTI_TYPE_INT32") if integer else (np.float32, "NIFTI_TYPE_FLOAT32")
    default_intent = "NIFTI_INTENT_LABEL" if meta.is_label else ("NIFTI_INTENT_NONE" if integer else "NIFTI_INTENT_SHAPE")
    darrays = []
    for k, column in enumerate(columns):
        intent = meta.intents[k] if k < len(meta.intents) else default_intent
        darray_meta = meta.array_meta[k] if k < len(meta.array_meta) else {}
        darrays.append(GiftiDataArray(column.astype(dtype), intent=intent, datatype=datatype,
                                      meta=GiftiMetaData(darray_meta)))
    file_meta = {k: v for k, v in meta.file_meta.items() if not (structure and k in STRUCTURE_KEYS)}
    file_meta.update(structure or {})
    table = None
    if meta.label_table:
        table = GiftiLabelTable()
        for key, (name, rgba) in sorted(meta.label_table.items()):
            label = GiftiLabel(int(key), *rgba)
            label.label = name
            table.labels.append(label)
    _save(GiftiImage(meta=GiftiMetaData(file_meta), labeltable=table, darrays=darrays), p, force)

"""What ``volreg register-surfaces``, ``morph`` and ``transfer`` share: reading surfaces, registering them,
writing them (VTK in LPS, GIFTI in RAS), saved models and plausibility warnings."""

from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

from volreg.cli._common import _warn
from volreg.errors import UsageError, VolregWarning

if TYPE_CHECKING:  # imported where used, so that the parsers load without numpy and the pipeline
    import numpy as np

    from volreg.evaluation.review import Finding
    from volreg.io.gifti import GiftiArrayMeta
    from volreg.io.meshes import SurfaceData
    from volreg.warp.model import KernelWarp

#: The frame of each kind of surface output, as the reports state it.
FRAMES = {".vtk": "LPS mm", ".gii": "RAS mm", ".csv": "LPS mm"}

#: Fewest vertices a surface is fitted to.
MIN_VERTICES = 10


def _add_data_options(parser, *roles: str) -> None:
    """``--source-data`` / ``--target-data FILE ...``: GIFTI per-vertex data files of SOURCE / TARGET."""
    for role in roles:
        parser.add_argument(f"--{role}-data", metavar="FILE", nargs="+", action="extend", type=Path, default=[],
                            help=f"GIFTI data files (.shape.gii .func.gii .label.gii) over the vertices of {role.upper()}; "
                            "each is an array named after its file (lh.thickness for lh.thickness.shape.gii)")


def _read(path: Path, role: str, data=()) -> SurfaceData:
    """The surface (mesh or point cloud) at ``path`` with the arrays of the GIFTI ``data`` files, with at
    least 10 vertices; ``role`` names it in errors."""
    from volreg.io.meshes import add_vertex_data, read_surface

    surface = read_surface(path)
    if len(surface.vertices) < MIN_VERTICES:
        raise UsageError(f"{role} `{path}` has {len(surface.vertices)} vertices; expected at least {MIN_VERTICES} to "
                         "fit a surface.")
    add_vertex_data(surface, data, f"{role} `{path}`")
    return surface


def _wants_gifti(args, source_path: Path) -> bool:
    """Whether to write GIFTI outputs: SOURCE is GIFTI, or ``--gifti`` was given."""
    from volreg.io.gifti import is_gifti

    return bool(getattr(args, "gifti", False)) or is_gifti(source_path)


#: Relative size (of the largest) below which a principal extent of a surface's vertices counts as none.
_FLAT = 1e-6

#: Largest ratio of the two surfaces' sizes taken as one unit (mm); beyond it they are refused.
MAX_SIZE_RATIO = 5.0


def _warn_normals(name: object, check, n: int, cloud: bool) -> None:
    """One warning line for each thing :func:`volreg.morph.checked_normals` mended in the normals of ``name``."""
    source = "neighbouring points (local PCA)" if cloud else "the triangles"
    if check.absent == n:
        warnings.warn(f"{name} has vertex normals of zero length or not finite only; they are ignored and computed "
                      f"from {source}.", VolregWarning, stacklevel=3)
    elif check.absent:
        warnings.warn(f"{name} has {check.absent} of {n} vertex normals of zero length or not finite; those are "
                      f"computed from {source}.", VolregWarning, stacklevel=3)
    if check.flipped:
        warnings.warn(f"{name} has vertex normals that point inward ({check.inward} of {check.compared} against the "
                      "outward side of the volume its triangles enclose); they are flipped.", VolregWarning, stacklevel=3)
    if check.replaced:
        warnings.warn(f"{name} has {check.replaced} vertex normals that point with and against its triangles at random; "
                      "they are replaced by normals computed from the triangles.", VolregWarning, stacklevel=3)


def _fitting_points(data: SurfaceData, name: object) -> tuple[np.ndarray, np.ndarray]:
    """The vertices of ``data`` that can train an implicit surface, with their outward unit normals.

    Normals read with the surface are checked (:func:`volreg.morph.checked_normals`: zero or
    non-finite ones computed again, inward ones flipped, ones at random replaced), with a
    warning for each.  Vertices on no triangle (or on degenerate ones only) without a normal
    of their own are warped like every vertex but not fitted (with a warning).  Refuses fewer
    than :data:`MIN_VERTICES` vertices to fit, and vertices that span no volume a surface
    could bound: all at one point, on a line, or a point cloud in a plane.
    """
    import numpy as np

    from volreg.morph import checked_normals

    normals, check = checked_normals(data.vertices, data.triangles, data.normals)
    _warn_normals(name, check, len(data.vertices), not len(data.triangles))
    ok = np.linalg.norm(normals, axis=1) > 0.5
    if len(data.triangles) and not ok.all():
        if not ok.any():
            raise UsageError(f"{name} has no triangle of non-zero area; expected a surface mesh.")
        warnings.warn(f"{name} has {int((~ok).sum())} of {len(ok)} vertices on no triangle of non-zero area "
                      "(unreferenced or duplicated); they are warped but not used to fit.", VolregWarning, stacklevel=3)
    if ok.sum() < MIN_VERTICES:
        raise UsageError(f"{name} has {int(ok.sum())} of {len(ok)} vertices on triangles of non-zero area (or with "
                         f"normals of their own); expected at least {MIN_VERTICES} to fit a surface.")
    points, normals = data.vertices[ok], normals[ok]
    sizes = np.linalg.svd(points - points.mean(axis=0), compute_uv=False) if len(points) > 1 else np.zeros(3)
    sizes = np.concatenate([sizes, np.zeros(3 - len(sizes))])
    if sizes[0] == 0:
        raise UsageError(f"{name} has all its {len(points)} vertices at one point; expected a surface.")
    if sizes[1] <= _FLAT * sizes[0]:
        raise UsageError(f"{name} has all its vertices on a line; expected a surface.")
    if sizes[2] <= _FLAT * sizes[0] and not len(data.triangles):
        raise UsageError(f"{name} is a point cloud lying in a plane: its inside and outside are undefined; "
                         "expected points around a closed surface, or a mesh with triangles.")
    return points, normals


def _register(source: SurfaceData, target: SurfaceData, protocol, landmarks, progress,
              names: tuple[object, object] = ("SOURCE", "TARGET")) -> KernelWarp:
    """The kernel warp of ``source`` onto ``target`` (:func:`volreg.pipeline.surfaces.register_surfaces`).

    ``names`` name the two surfaces in errors (e.g. ``SOURCE `a.vtk```).  Surfaces whose
    sizes differ by more than :data:`MAX_SIZE_RATIO` are refused: one is most likely in
    other units (metres, centimetres) and the fit would end far off.
    """
    import numpy as np

    from volreg.pipeline.surfaces import register_surfaces

    src = _fitting_points(source, names[0])
    tgt = _fitting_points(target, names[1])
    size = [float(np.linalg.norm(np.ptp(p, axis=0))) for p in (src[0], tgt[0])]
    ratio = max(size) / min(size)
    if ratio > MAX_SIZE_RATIO:
        raise UsageError(
            f"{names[0]} is {size[0]:.4g} mm across and {names[1]} {size[1]:.4g} mm ({ratio:.3g} times the size); "
            f"expected two surfaces in one unit, millimetres, within {MAX_SIZE_RATIO:g} times each other's size "
            "(check whether one is in metres or centimetres)."
        )
    return register_surfaces(src, tgt, landmarks=landmarks, settings=protocol.warp, progress=progress).warp


def _write_surface(path: Path, data: SurfaceData, vertices: np.ndarray, arrays: dict, force: bool) -> None:
    """``data``'s faces with moved ``vertices`` (LPS mm) and per-vertex ``arrays``: VTK/VTP in LPS."""
    from volreg.io import write_mesh

    write_mesh(vertices, data.triangles, path, point_data=arrays or None, force=force, allow_points=True)


def _write_gifti_surface(path: Path, data: SurfaceData, vertices: np.ndarray, force: bool) -> None:
    """``data``'s faces with moved ``vertices`` (LPS mm) as a GIFTI surface in RAS, with ``data``'s metadata."""
    from volreg.io.gifti import write_gifti

    write_gifti(vertices, data.triangles, path, meta=data.gifti, force=force)


def _is_label(surface: SurfaceData, name: str) -> bool:
    """Whether ``surface``'s array ``name`` holds labels: integers, or a GIFTI label array."""
    import numpy as np

    meta = surface.array_meta.get(name)
    return np.asarray(surface.arrays[name]).dtype.kind in "iub" or (meta is not None and meta.is_label)


def _data_meta(surface: SurfaceData, name: str) -> GiftiArrayMeta:
    """The GIFTI metadata of ``surface``'s array ``name`` (a bare one for arrays not read from GIFTI)."""
    from volreg.io.gifti import GiftiArrayMeta

    meta = surface.array_meta.get(name)
    if meta is not None:
        return meta
    return GiftiArrayMeta(kind="label" if _is_label(surface, name) else "shape")


def _data_file_name(stem: str, name: str, meta: GiftiArrayMeta) -> str:
    """``<stem>.<name>.<kind>.gii``, with characters unsafe in file names replaced by ``_``."""
    safe = re.sub(r"[^A-Za-z0-9._+-]", "_", name) or "array"
    return f"{stem}.{safe}.{meta.kind}.gii"


def _warn_findings(command: str, findings: list[Finding]) -> None:
    """One warning line on stderr per finding."""
    for finding in findings:
        _warn(command, finding.message)


def _load_model(result: Path) -> KernelWarp:
    """The 3-D warp saved in a ``volreg register-surfaces`` OUTDIR."""
    from volreg.warp.model import KernelWarp

    model = result / "model.npz"
    if not model.is_file():
        raise UsageError(f"`{result}` has no model.npz; expected an OUTDIR written by `volreg register-surfaces`.")
    warp = KernelWarp.load(model)
    if warp.dim != 3:
        raise UsageError(f"`{model}` is a {warp.dim}-D warp; expected a 3-D surface registration.")
    return warp

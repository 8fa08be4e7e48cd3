"""Surfaces checked before they are fitted: normals against their triangles, degenerate shapes, units.

A surface that cannot bound a volume (all its vertices at one point or on a line, a point cloud
in a plane), normals that point inward or at random, and two surfaces whose sizes differ as
millimetres and metres do are found here, before any fit: the mended normals with a warning
(:class:`~volreg.errors.VolregWarning`), the rest refused with a one-line
:class:`~volreg.errors.SurfaceError` naming the surface
(:func:`volreg.pipeline.surfaces.register_surfaces` and
:func:`~volreg.pipeline.surfaces.register_surface_pair` run these checks).
"""

from __future__ import annotations

import warnings

import numpy as np

from volreg.errors import SurfaceError, VolregWarning
from volreg.grid import box_diameter
from volreg.io.meshes import SurfaceData
from volreg.morph import checked_normals

__all__ = ["MAX_SIZE_RATIO", "MIN_VERTICES", "check_point_extent", "check_size_ratio", "fitting_points"]

#: Fewest vertices a surface is fitted to.
MIN_VERTICES = 10

#: Relative size (of the largest) below which a principal extent of a surface's vertices counts as none.
_FLAT = 1e-6

#: Largest ratio of the two surfaces' sizes taken as one unit (mm); beyond it they are refused.
MAX_SIZE_RATIO = 5.0


def _warn_normals(name: object, check, n: int, cloud: bool) -> None:
    """One warning for each thing :func:`volreg.morph.checked_normals` mended in the normals of ``name``."""
    source = "neighbouring points (local PCA)" if cloud else "the triangles"
    if check.absent == n:
        warnings.warn(f"{name} has vertex normals of zero length or not finite only; they are ignored and computed "
                      f"from {source}.", VolregWarning, stacklevel=4)
    elif check.absent:
        warnings.warn(f"{name} has {check.absent} of {n} vertex normals of zero length or not finite; those are "
                      f"computed from {source}.", VolregWarning, stacklevel=4)
    if check.flipped:
        warnings.warn(f"{name} has vertex normals that point inward ({check.inward} of {check.compared} against the "
                      "outward side of the volume its triangles enclose); they are flipped.", VolregWarning, stacklevel=4)
    if check.replaced:
        warnings.warn(f"{name} has {check.replaced} vertex normals that point with and against its triangles at random; "
                      "they are replaced by normals computed from the triangles.", VolregWarning, stacklevel=4)


def check_point_extent(points: np.ndarray, name: object, *, cloud: bool) -> None:
    """Refuse points that span no volume a surface could bound.

    Parameters
    ----------
    points : (N, D) float ndarray, mm
    name : str
        How the message names the surface (e.g. ``SOURCE `a.vtk```).
    cloud : bool
        Whether the points are a point cloud (no triangles): in 3-D one lying in a plane has
        no inside either.

    Raises
    ------
    SurfaceError
        All points at one point, on a line, or (a 3-D point cloud) in a plane.
    """
    points = np.asarray(points, float)
    sizes = np.linalg.svd(points - points.mean(axis=0), compute_uv=False) if len(points) > 1 else np.zeros(3)
    sizes = np.concatenate([sizes, np.zeros(3 - len(sizes))]) if len(sizes) < 3 else sizes
    if sizes[0] == 0:
        raise SurfaceError(f"{name} has all its {len(points)} vertices at one point; expected a surface.")
    if points.shape[1] < 3:
        return  # a curve in the plane: its line case is a closed curve of no area, left to the fit
    if sizes[1] <= _FLAT * sizes[0]:
        raise SurfaceError(f"{name} has all its vertices on a line; expected a surface.")
    if sizes[2] <= _FLAT * sizes[0] and cloud:
        raise SurfaceError(f"{name} is a point cloud lying in a plane: its inside and outside are undefined; "
                           "expected points around a closed surface, or a mesh with triangles.")


def check_size_ratio(source: np.ndarray, target: np.ndarray, names: tuple[object, object] = ("SOURCE", "TARGET")) -> None:
    """Refuse two surfaces whose sizes differ by more than :data:`MAX_SIZE_RATIO`: one is most
    likely in other units (metres, centimetres) and the fit would end far off.

    Parameters
    ----------
    source, target : (N, D) and (M, D) float ndarrays, mm
        The points of the two surfaces.
    names : pair of str
        How the message names them.

    Raises
    ------
    SurfaceError
    """
    size = [box_diameter(np.asarray(p, float)) for p in (source, target)]
    ratio = max(size) / min(size) if min(size) > 0 else np.inf
    if ratio > MAX_SIZE_RATIO:
        raise SurfaceError(
            f"{names[0]} is {size[0]:.4g} mm across and {names[1]} {size[1]:.4g} mm ({ratio:.3g} times the size); "
            f"expected two surfaces in one unit, millimetres, within {MAX_SIZE_RATIO:g} times each other's size "
            "(check whether one is in metres or centimetres)."
        )


def fitting_points(data: SurfaceData, name: object) -> tuple[np.ndarray, np.ndarray]:
    """The vertices of ``data`` that can train an implicit surface, with their outward unit normals.

    Normals read with the surface are checked (:func:`volreg.morph.checked_normals`: zero or
    non-finite ones computed again, inward ones flipped, ones at random replaced), with a
    warning for each.  Vertices on no triangle (or on degenerate ones only) without a normal
    of their own are warped like every vertex but not fitted (with a warning).

    Parameters
    ----------
    data : SurfaceData
        A surface as read (:func:`volreg.io.meshes.read_surface`).
    name : str
        How messages name it.

    Returns
    -------
    points, normals : (K, 3) float ndarrays
        LPS mm, and unit normals.

    Raises
    ------
    SurfaceError
        Fewer than :data:`MIN_VERTICES` vertices to fit, no triangle of non-zero area, or
        vertices that span no volume (:func:`check_point_extent`).
    """
    normals, check = checked_normals(data.vertices, data.triangles, data.normals)
    _warn_normals(name, check, len(data.vertices), not len(data.triangles))
    ok = np.linalg.norm(normals, axis=1) > 0.5
    if len(data.triangles) and not ok.all():
        if not ok.any():
            raise SurfaceError(f"{name} has no triangle of non-zero area; expected a surface mesh.")
        warnings.warn(f"{name} has {int((~ok).sum())} of {len(ok)} vertices on no triangle of non-zero area "
                      "(unreferenced or duplicated); they are warped but not used to fit.", VolregWarning, stacklevel=2)
    if ok.sum() < MIN_VERTICES:
        raise SurfaceError(f"{name} has {int(ok.sum())} of {len(ok)} vertices on triangles of non-zero area (or with "
                           f"normals of their own); expected at least {MIN_VERTICES} to fit a surface.")
    points, normals = data.vertices[ok], normals[ok]
    check_point_extent(points, name, cloud=not len(data.triangles))
    return points, normals

"""The surface front end: meshes or point clouds in, a fitted kernel warp out.

:func:`register_surfaces` fits each object as a multi-scale kernel implicit surface (paper
Section 4, :class:`~volreg.features.implicit.ImplicitSurface`), takes out the translation between
the two objects' area-weighted centroids where that brings them nearer (:func:`centroid_shift`),
and fits the warp (9) between the feature pairs (6) with :func:`~volreg.warp.fit.fit_warp`.
"""

from __future__ import annotations

import os
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from volreg._threads import single_blas, thread_map
from volreg.features.implicit import ImplicitSurface, default_min_width
from volreg.features.mapped import LinearlyMapped
from volreg.grid import box_diameter
from volreg.errors import ArgumentTypeError
from volreg.io.meshes import SurfaceData
from volreg.pipeline.arguments import bool_argument, callable_argument, landmarks_argument, warp_settings_argument
from volreg.pipeline.surface_inputs import check_point_extent, check_size_ratio, fitting_points
from volreg.settings import Protocol
from volreg.settings import WarpSettings
from volreg.warp.model import KernelWarp
from volreg.warp.fit import RegistrationResult, fit_warp
from volreg.linear_map import LinearMap
from volreg.warp.objective import FeaturePair

__all__ = ["centroid_shift", "mesh_min_width", "register_surface_pair", "register_surfaces"]


def _pyvista():
    """The pyvista module, or ``None`` where it cannot be imported."""
    try:
        import pyvista as pv
    except ImportError:  # pragma: no cover - pyvista is a dependency
        return None
    return pv


def _surface_points(surface) -> ImplicitSurface | tuple[np.ndarray, np.ndarray]:
    """An ImplicitSurface as given, or the (points, normals) of a pyvista mesh or a (points, normals) pair."""
    if isinstance(surface, ImplicitSurface):
        return surface
    if isinstance(surface, tuple):
        if len(surface) != 2:
            raise ArgumentTypeError(f"Expected `source`/`target` tuples as (points, normals), got {len(surface)} items.")
        try:
            return tuple(np.asarray(a, float) for a in surface)
        except (TypeError, ValueError):  # ragged lists, text, objects
            raise ArgumentTypeError("Expected `source`/`target` tuples of two (N, D) arrays of numbers (points, "
                                    "normals).") from None
    pv = _pyvista()
    if pv is not None and isinstance(surface, pv.PolyData):
        mesh = surface.triangulate().compute_normals(point_normals=True, cell_normals=False,
                                                     auto_orient_normals=True, consistent_normals=True)
        return np.asarray(mesh.points, float), np.asarray(mesh.point_data["Normals"], float)
    hint = " (read a mesh file with pyvista.read(path))" if isinstance(surface, (str, os.PathLike)) else ""
    raise ArgumentTypeError(
        f"Expected `source`/`target` as pyvista PolyData, ImplicitSurface or (points, normals), got "
        f"{type(surface).__name__}{hint}."
    )


def _check_objects(objects: list, data: list, names: tuple[object, object], n_source: int) -> None:
    """Refuse objects that span no volume (:func:`~volreg.pipeline.surface_inputs.check_point_extent`)
    and a source and target of sizes as far apart as two units
    (:func:`~volreg.pipeline.surface_inputs.check_size_ratio`); fitted implicit surfaces are taken as they are."""
    pv = _pyvista()
    points = [None if isinstance(d, ImplicitSurface) else d[0] for d in data]
    for k, (obj, p) in enumerate(zip(objects, points)):
        if p is not None and len(p) >= 2:
            cloud = not (pv is not None and isinstance(obj, pv.PolyData) and len(obj.faces) > 0)
            check_point_extent(p, names[0] if k < n_source else names[1], cloud=cloud)
    src = [p for p in points[:n_source] if p is not None and len(p)]
    tgt = [p for p in points[n_source:] if p is not None and len(p)]
    if src and tgt:
        check_size_ratio(np.concatenate(src), np.concatenate(tgt), names)


@single_blas
def register_surfaces(
    source,
    target,
    *,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    settings: WarpSettings = WarpSettings(),
    progress: Callable[[str, int, int], None] | None = None,
    align_centroids: bool = True,
    check_names: tuple[object, object] = ("`source`", "`target`"),
) -> RegistrationResult:
    """Register ``source`` onto ``target``: ``result.warp`` maps source points to target points.

    Parameters
    ----------
    source, target : pyvista.PolyData, ImplicitSurface, (points, normals), or lists of them
        One object or several (one per label: several feature functions, (6)),
        in the same order for both.  Meshes and points are fitted as
        :class:`~volreg.features.implicit.ImplicitSurface` (in parallel, one surface per thread),
        down to the finer of its default width (8 vertex spacings) and the warp's finest
        width / sqrt(2), but not below 3 vertex spacings.
    landmarks : pair of (L, D) float ndarrays, optional
        Source landmark points and their target positions, mm.
    settings : WarpSettings, Protocol or str, optional
        The warp settings, or a protocol (or its preset name or file) whose ``warp`` section to take.
    progress : callable, optional
    align_centroids : bool
        First move the source by the translation between the two point sets' centroids, where
        that brings its points nearer the target's (:func:`centroid_shift`); the warp then holds
        that translation as its linear part.  A kernel warp moves a surface little further than
        its own kernels reach: a bumpy sphere 108 mm across shifted 15 mm ended with its points
        6 % of the diameter from their partners, 25 mm 11 % (the warped source on the target).
        Rotations and scales are not found: the two must be in one frame and turned alike.

    check_names : pair of str
        How errors name the source and the target.  Objects that span no volume (all points at
        one point or on a line, a point cloud in a plane) and a source and target whose sizes
        differ more than millimetres and centimetres could are refused
        (:mod:`volreg.pipeline.surface_inputs`), as the surface commands refuse them.

    Returns
    -------
    RegistrationResult
        ``.warp`` (:class:`~volreg.warp.KernelWarp`) and ``.log`` (per level:
        width, samples, iterations, objective terms, seconds).

    Raises
    ------
    ArgumentTypeError
        An argument of the wrong kind (a path for a surface, a number for a callable), named.
    ValueError
        Source and target lists of different lengths, landmarks of the wrong shape
        (:class:`~volreg.errors.RegistrationInputError`), surfaces that bound no volume.
    """
    settings = warp_settings_argument(settings)
    progress = callable_argument(progress, "progress", "progress(stage, done, total)")
    align_centroids = bool_argument(align_centroids, "align_centroids")
    sources = source if isinstance(source, list) else [source]
    targets = target if isinstance(target, list) else [target]
    if len(sources) != len(targets):
        raise ValueError(f"Expected as many `target` objects as `source` objects, got {len(targets)} and {len(sources)}.")
    if not sources:
        raise ArgumentTypeError("Expected at least one `source` and one `target` object, got empty lists.")
    data = [_surface_points(x) for x in sources + targets]
    _check_objects(sources + targets, data, check_names, len(sources))

    def points_of(objects) -> np.ndarray:
        return np.concatenate([d.points if isinstance(d, ImplicitSurface) else d[0] for d in objects])

    points = points_of(data[:len(sources)])
    if landmarks is not None and points.ndim == 2:
        landmarks = landmarks_argument(landmarks, points.shape[1])
    # Surfaces given as points are fitted about as finely as the warp's finest level at least
    # (features coarser than a level cannot pin it): down to its width / sqrt(2), so that the
    # halving widths of a target of another size also reach it, but not below 3 vertex spacings
    # (sparser training points than that leave holes between the kernels).  ImplicitSurface's own
    # default (8 vertex spacings) is coarser than the warp on decimated meshes.
    diameter = box_diameter(points) if len(points) else 0.0
    finest = settings.resolved(diameter).min_width / np.sqrt(2.0) if diameter > 0 else np.inf

    def fit(d) -> ImplicitSurface:
        if isinstance(d, ImplicitSurface):
            return d
        if len(d[0]) < 2:  # ImplicitSurface says what it expects
            return ImplicitSurface(*d)
        return ImplicitSurface(*d, min_width=mesh_min_width(d[0], finest))

    fits = list(thread_map(fit, data))  # independent fits: numba releases the GIL
    shift = None
    if align_centroids and len(points):
        shift = centroid_shift(points, points_of(data[len(sources):]))
    if shift is None:
        pairs = [FeaturePair(f1, f2) for f1, f2 in zip(fits[:len(sources)], fits[len(sources):])]
        return fit_warp(pairs, points, landmarks=landmarks, settings=settings, progress=progress)
    # tau = L o phi: phi is fitted between the source's features and the target's seen through L
    linear = LinearMap(np.eye(points.shape[1]), shift)
    pairs = [FeaturePair(f1, LinearlyMapped(f2, linear)) for f1, f2 in zip(fits[:len(sources)], fits[len(sources):])]
    if landmarks is not None:
        landmarks = (landmarks[0], np.asarray(landmarks[1], float) - shift)
    result = fit_warp(pairs, points, landmarks=landmarks, settings=settings, progress=progress)
    return RegistrationResult(result.warp.then(linear), result.log)


def centroid_shift(source: np.ndarray, target: np.ndarray) -> np.ndarray | None:
    """The translation (D,) mm between the centroids of ``source`` and ``target`` (points (N, D),
    (M, D) mm; each point weighted by the surface it stands for, :func:`_area_centroid`), where it
    brings the source nearer: the median distance of the moved source points to their nearest
    target points below that of the points as they lie; ``None`` where it does not (one surface
    is part of the other, pre-aligned) or is under 1 % of the source's diameter.
    """
    shift = _area_centroid(target) - _area_centroid(source)
    if np.linalg.norm(shift) <= 0.01 * box_diameter(source):
        return None
    tree = cKDTree(target)
    before = np.median(tree.query(source)[0])
    after = np.median(tree.query(source + shift)[0])
    return shift if after < before else None


def _area_centroid(points: np.ndarray, k: int = 6) -> np.ndarray:
    """The centroid (D,) mm of surface points (N, D) mm, each weighted by the surface it stands
    for: its distance to its ``k``-th nearest neighbour to the power D - 1.

    A mean over the vertices follows the meshing (a target meshed densely on one half, or a
    little debris far away, would pull it off).  Repeated points count once, and no point's spacing counts above twice the
    median (else a few stray points, far from their neighbours, would weigh as much as a
    surface).  Where all points coincide, the plain mean.
    """
    points = np.unique(np.asarray(points, float), axis=0)  # a repeated point stands for no more surface
    if len(points) <= k:
        return points.mean(axis=0)
    spacing = cKDTree(points).query(points, k=k + 1)[0][:, -1]
    # A few stray points (a one-voxel speck's octahedron) are far from their sixth neighbour: capped
    # at two typical spacings, they weigh little more than the surface they stand for.
    spacing = np.minimum(spacing, 2.0 * float(np.median(spacing)))
    weight = spacing ** (points.shape[1] - 1)
    total = float(weight.sum())
    return points.mean(axis=0) if not total > 0 else weight @ points / total


def mesh_min_width(points: np.ndarray, finest: float) -> float:
    """The finest implicit-surface width (mm) :func:`register_surfaces` fits a mesh's ``points``
    (N, D) mm down to: ``finest`` (the warp's finest width / sqrt(2)), clipped to 3-8 vertex
    spacings (8 is :class:`~volreg.features.implicit.ImplicitSurface`'s default)."""
    default = default_min_width(points)  # 8 vertex spacings
    return min(default, max(finest, 3.0 * default / 8.0))


def register_surface_pair(source: SurfaceData, target: SurfaceData, protocol: Protocol, landmarks=None,
                          progress: Callable[[str, int, int], None] | None = None,
                          names: tuple[object, object] = ("SOURCE", "TARGET")) -> KernelWarp:
    """The kernel warp of ``source`` onto ``target`` (:func:`~volreg.pipeline.surfaces.register_surfaces`),
    both checked first (:func:`fitting_points`, :func:`check_size_ratio`).

    Parameters
    ----------
    source, target : SurfaceData
    protocol : Protocol
        Its ``warp`` settings.
    landmarks : pair of (L, 3) float ndarrays, optional
        Source points and their target partners, LPS mm.
    progress : callable, optional
    names : pair of str
        How errors name the two surfaces (e.g. ``SOURCE `a.vtk```).

    Returns
    -------
    KernelWarp
        Source points -> target points, LPS mm.
    """
    src = fitting_points(source, names[0])
    tgt = fitting_points(target, names[1])
    check_size_ratio(src[0], tgt[0], names)
    return register_surfaces(src, tgt, landmarks=landmarks, settings=protocol.warp, progress=progress,
                             check_names=names).warp

"""Surface-to-surface registration helpers: normals, correspondence, morphs and transfer (paper Section 5).

Pure functions on arrays (vertices in LPS mm).  A registration of SOURCE to
TARGET gives ``tau`` (:class:`~volreg.warp.KernelWarp`) mapping each source
point to its target partner; the correspondence of a source vertex ``v`` is
the target-surface point nearest to ``tau(v)``.  A warp with a linear part
``L(x) = A x + b`` morphs along ``L_t(v) + t (tau(v) - L(v))``, with ``L_t``
turning and stretching from the identity to ``L`` (:func:`morph_vertices`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyvista as pv
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from volreg.features.implicit import estimate_normals
from volreg.linear_map import LinearMap

__all__ = ["surface_normals", "checked_normals", "NormalsCheck", "closest_points", "surface_gaps", "morph_vertices", "transfer_values", "linear_path"]


def _polydata(vertices: np.ndarray, triangles: np.ndarray) -> pv.PolyData:
    faces = np.column_stack([np.full(len(triangles), 3), triangles]).ravel()
    return pv.PolyData(np.asarray(vertices, float), faces=faces)


def surface_normals(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
    """Outward unit normals, (N, 3): the given ones (checked), else from the triangles, else from neighbours.

    Triangle normals are made consistent and outward (VTK's
    ``auto_orient_normals``); a point cloud gets normals by local PCA with
    orientation propagated along a spanning tree (paper Section 4,
    :func:`volreg.features.implicit.estimate_normals`).  Given normals are
    checked as :func:`checked_normals` does.
    """
    return checked_normals(vertices, triangles, normals)[0]


@dataclass(frozen=True)
class NormalsCheck:
    """What :func:`checked_normals` did to given vertex normals (counts of vertices).

    Attributes
    ----------
    absent : int
        Normals of zero length or not finite, computed again (from the triangles, or
        from neighbouring points for a point cloud).
    compared : int
        Normals compared with the triangles' orientation on closed pieces of the mesh
        (pieces where they point at random left out).
    inward : int
        Of those, the ones that pointed inward as given (before flipping).
    flipped : bool
        All normals were flipped: on the closed pieces they bounded a negative volume.
    replaced : int
        Normals on pieces where they point with and against the triangles at random,
        replaced by the triangles' normals.
    """

    absent: int = 0
    compared: int = 0
    inward: int = 0
    flipped: bool = False
    replaced: int = 0


#: Fraction of a piece's normals that must point one way relative to its triangles for the normals'
#: orientation to be taken as consistent (either way); between it and 1 minus it, they point at random.
_CONSISTENT = 0.9


def _triangle_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals from the triangles, consistent and outward on each closed piece (zero off the triangles)."""
    mesh = _polydata(vertices, triangles).compute_normals(
        point_normals=True, cell_normals=False, auto_orient_normals=True, consistent_normals=True, split_vertices=False
    )
    return np.array(mesh.point_data["Normals"], float)


def checked_normals(vertices: np.ndarray, triangles: np.ndarray,
                    normals: np.ndarray | None = None) -> tuple[np.ndarray, NormalsCheck]:
    """Outward unit normals (N, 3) from given normals checked against the triangles, and what was done.

    Without ``normals``, the triangles' normals (consistent, outward on each
    closed piece) or, for a point cloud, local PCA (:func:`estimate_normals`).
    With them:

    - rows of zero length or not finite are computed again as without normals
      (oriented as the given normals of their piece);
    - on each connected piece of triangles, the given normals are compared with
      the triangles' normals: if at least 90 % point one way (with them or
      against, e.g. the inner wall of a hollow shell), the given orientation is
      taken; otherwise they point at random and are replaced by the triangles';
    - the closed pieces (every edge on two triangles) then bound a volume with
      the given orientation, Σ ± V_piece; if it is negative, the normals point
      inward and all are flipped.  A mesh of open pieces only bounds nothing and
      keeps the given orientation.

    Parameters
    ----------
    vertices : (N, 3) float ndarray, mm
    triangles : (F, 3) int ndarray
        Empty (F = 0) for a point cloud.
    normals : (N, 3) float ndarray, optional
        Normals read with the vertices, any length.

    Returns
    -------
    normals : (N, 3) float ndarray
        Unit length, or zero at vertices on no triangle of non-zero area that had no
        usable given normal.
    check : NormalsCheck
    """
    vertices = np.asarray(vertices, float)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if normals is None:
        if len(triangles):
            return _triangle_normals(vertices, triangles), NormalsCheck()
        return estimate_normals(vertices), NormalsCheck()
    given = np.array(normals, float)
    length = np.linalg.norm(np.where(np.isfinite(given), given, 0.0), axis=1)
    usable = np.all(np.isfinite(given), axis=1) & (length > 0)
    out = np.zeros_like(given)
    out[usable] = given[usable] / length[usable, None]
    absent = int(np.count_nonzero(~usable))
    if not len(triangles):
        if absent:
            estimated = estimate_normals(vertices)
            if usable.any() and np.einsum("nd,nd->n", estimated[usable], out[usable]).sum() < 0:
                estimated = -estimated  # as the given normals point
            out[~usable] = estimated[~usable]
        return out, NormalsCheck(absent=absent)

    own = _triangle_normals(vertices, triangles)  # outward on each closed piece
    on = np.linalg.norm(own, axis=1) > 0.5
    n = len(vertices)
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, piece = connected_components(graph, directed=False)
    pieces = piece.max() + 1
    agree = np.einsum("nd,nd->n", out, own)
    compare = usable & on
    with_ = np.bincount(piece[compare & (agree > 0)], minlength=pieces)
    total = np.bincount(piece[compare], minlength=pieces)
    fraction = np.divide(with_, total, out=np.ones(pieces), where=total > 0)
    random = (fraction < _CONSISTENT) & (fraction > 1 - _CONSISTENT)
    sign = np.where(fraction <= 1 - _CONSISTENT, -1.0, 1.0)  # the given orientation, relative to ``own``
    sign[random] = 1.0
    replace = random[piece] & on
    out[replace] = own[replace]
    fill = ~usable & on
    out[fill] = own[fill] * sign[piece[fill], None]

    # closed pieces: every edge (of triangles with three distinct corners) on exactly two triangles
    proper = (triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2]) & (triangles[:, 2] != triangles[:, 0])
    keys, counts = np.unique(edges.reshape(-1, 3, 2)[proper].reshape(-1, 2) @ np.array([n, 1]), return_counts=True)
    closed = np.zeros(pieces, bool)
    closed[np.unique(piece[triangles[proper, 0]])] = True
    closed[piece[keys[counts != 2] // n]] = False
    # each piece's volume with ``own``'s orientation: triangles turned to agree with it, summed v0 . (v1 x v2) / 6
    a, b, c = (vertices[triangles[proper, k]] for k in range(3))
    det = np.einsum("nd,nd->n", a, np.cross(b, c))
    facing = np.einsum("nd,nd->n", np.cross(b - a, c - a), own[triangles[proper]].sum(axis=1))
    volume = np.bincount(piece[triangles[proper, 0]], weights=np.sign(facing) * det / 6.0, minlength=pieces)
    flip = float(np.sum((sign * volume)[closed])) < 0
    if flip:
        out = -out
        out[replace] = own[replace]
    counted = compare & closed[piece] & ~random[piece]
    against = sign[piece] * agree < 0 if not flip else sign[piece] * agree > 0  # against the final outward side
    return out, NormalsCheck(absent=absent, compared=int(np.count_nonzero(counted)),
                             inward=int(np.count_nonzero(counted & against)), flipped=bool(flip),
                             replaced=int(np.count_nonzero(replace & usable)))


def closest_points(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray):
    """Nearest points of a surface (or point cloud) to ``points``.

    Returns
    -------
    closest : (M, 3) float ndarray, mm
        On the triangles (exact point-to-triangle distance) or, for a point
        cloud, the nearest vertex.
    distance : (M,) float ndarray, mm
    cell : (M,) int ndarray
        Index of the triangle (or vertex, for a cloud) holding ``closest``.
    """
    points = np.asarray(points, float)
    if len(triangles):
        mesh = _polydata(vertices, triangles)
        cell, closest = mesh.find_closest_cell(points, return_closest_point=True)
        closest = np.asarray(closest, float).reshape(-1, 3)
        cell = np.asarray(cell).reshape(-1)
    else:
        _, cell = cKDTree(vertices).query(points)
        closest = np.asarray(vertices, float)[cell]
    return closest, np.linalg.norm(closest - points, axis=1), cell


def surface_gaps(warped: np.ndarray, target_vertices: np.ndarray, target_triangles: np.ndarray) -> tuple[np.ndarray, str]:
    """Distance of each warped source vertex to the target, a surface or a sample of one.

    To the target's triangles; to a point cloud's nearest point, less half the cloud's median
    spacing (clipped at 0).  A point cloud is a sample of its surface: a vertex that lies on the
    surface is still up to about half the samples' spacing from the nearest one (40 points over
    a sphere 40 mm across: the vertices of a correct result lie a median 4.5 mm from the nearest,
    6.7 % of the points' bounding-box diagonal), which read as surfaces in different frames.
    Less that allowance, a correct result lies a median 0 mm off, and a source with no
    counterpart in part of the cloud stays far from it.

    Parameters
    ----------
    warped : (N, 3) float ndarray, mm
        The source vertices carried by the warp.
    target_vertices : (M, 3) float ndarray, mm
    target_triangles : (U, 3) int ndarray
        Empty for a point cloud.

    Returns
    -------
    distance : (N,) float ndarray, mm
    measured : str
        ``"source_to_target"`` (to the triangles) or ``"source_to_target_points"``: a key of
        :data:`volreg.evaluation.surface_review.GAPS_MEASURED`.
    """
    if len(target_triangles):
        return closest_points(warped, target_vertices, target_triangles)[1], "source_to_target"
    points = np.unique(np.asarray(target_vertices, float), axis=0)  # repeated points are no closer sampling
    spacing = float(np.median(cKDTree(points).query(points, k=2)[0][:, 1])) if len(points) > 1 else 0.0
    distance = cKDTree(points).query(np.asarray(warped, float))[0]
    return np.maximum(distance - 0.5 * spacing, 0.0), "source_to_target_points"


def _rotation_power(rot: np.ndarray, t: float) -> np.ndarray:
    """``rot^t``: the rotation about the same axis by ``t`` times the angle (angle in [0, pi])."""
    if rot.shape == (2, 2):
        angle = t * np.arctan2(rot[1, 0], rot[0, 0])
        return np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(t * Rotation.from_matrix(rot).as_rotvec()).as_matrix()


def linear_path(linear: LinearMap, t: float) -> LinearMap:
    """The linear map a fraction ``t`` of the way from the identity to ``linear``.

    With the polar decomposition ``A = R S`` (``R`` a rotation, ``S`` symmetric
    positive definite): ``A_t = R^t ((1 - t) I + t S)`` and ``b_t = t b``, so a
    rotation turns at a constant rate and keeps its size on the way (the straight
    path ``(1 - t) x + t A x`` of a 30 degree turn shrinks the object by 3.4 % half
    way), and ``t = 0`` and ``t = 1`` give the identity and ``linear``.

    Parameters
    ----------
    linear : LinearMap
    t : float
        In [0, 1].

    Returns
    -------
    LinearMap
    """
    t = float(t)
    if not 0.0 <= t <= 1.0:
        raise ValueError(f"Expected `t` in [0, 1], got {t!r}.")
    if t == 1.0:
        return linear
    dim = linear.dim
    u, s, vt = np.linalg.svd(linear.matrix)
    rot = u @ vt  # det(A) > 0 gives a proper rotation
    stretch = (vt.T * s) @ vt
    a_t = _rotation_power(rot, t) @ ((1.0 - t) * np.eye(dim) + t * stretch)
    return LinearMap(a_t, t * linear.translation)


def morph_vertices(
    vertices: np.ndarray, warped: np.ndarray, frames: int, *, linear: LinearMap | None = None
) -> list[np.ndarray]:
    """Vertices along the paths from ``v`` to ``tau(v)``, at ``t = 0, 1/(frames-1), ..., 1``.

    Without a linear part the straight paths ``v + t (tau(v) - v)`` (paper
    Section 5).  With one, ``L_t(v) + t (tau(v) - L(v))``: the linear part
    follows :func:`linear_path` (turning, not cutting across), the kernel
    displacement grows linearly.

    Parameters
    ----------
    vertices : (N, D) float ndarray, mm
    warped : (N, D) float ndarray, mm
        ``tau(vertices)``.
    frames : int
        Number of frames, ``>= 2``; the first is ``vertices``, the last ``warped``.
    linear : LinearMap, optional
        The warp's linear part (``warp.linear``); ``None`` or the identity give
        the straight paths.

    Returns
    -------
    list of (N, D) float ndarrays, mm
    """
    if frames < 2:
        raise ValueError(f"Expected `frames` >= 2, got {frames}.")
    if linear is None or linear.is_identity:
        return [vertices + t * (warped - vertices) for t in np.linspace(0.0, 1.0, frames)]
    vertices = np.asarray(vertices, float)
    rest = np.asarray(warped, float) - linear(vertices)  # the kernel part: tau(v) - L(v)
    out = [linear_path(linear, t)(vertices) + t * rest for t in np.linspace(0.0, 1.0, frames)]
    out[0], out[-1] = vertices.copy(), np.array(warped, dtype=float)  # exact end points
    return out


def _barycentric(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric weights (M, 3) of points ``p`` in triangles ``(a, b, c)`` (clipped to the triangle)."""
    v0, v1, v2 = b - a, c - a, p - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-30, den, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    weights = np.clip(np.column_stack([1.0 - v - w, v, w]), 0.0, 1.0)
    return weights / np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)


def transfer_values(
    warped: np.ndarray,
    target_vertices: np.ndarray,
    target_triangles: np.ndarray,
    values: np.ndarray,
    *,
    method: str = "barycentric",
) -> np.ndarray:
    """Carry per-vertex ``values`` of the target onto warped source vertices (paper Figure 5).

    Parameters
    ----------
    warped : (M, 3) float ndarray, mm
        ``tau(v)`` for the source vertices.
    target_vertices, target_triangles
        The target surface ((N, 3) mm, (F, 3) indices; F = 0 for a cloud).
    values : (N, ...) ndarray
        Per-vertex array of the target (scalars, colours, labels).
    method : {"nearest", "barycentric"}
        ``nearest``: the value of the target vertex nearest to ``tau(v)``.
        ``barycentric``: interpolated in the closest triangle; integer arrays
        (labels) take the value of that triangle's vertex with the largest
        weight, so only input values come out.

    Returns
    -------
    (M, ...) ndarray, the dtype of ``values``
    """
    values = np.asarray(values)
    if method not in ("nearest", "barycentric"):
        raise ValueError(f"Expected `method` 'nearest' or 'barycentric', got {method!r}.")
    if method == "nearest" or len(target_triangles) == 0:
        _, idx = cKDTree(target_vertices).query(warped)
        return values[idx]
    closest, _, cell = closest_points(warped, target_vertices, target_triangles)
    tri = np.asarray(target_triangles)[cell]
    tv = np.asarray(target_vertices, float)
    weights = _barycentric(closest, tv[tri[:, 0]], tv[tri[:, 1]], tv[tri[:, 2]])
    if values.dtype.kind in "iub":
        return values[tri[np.arange(len(tri)), np.argmax(weights, axis=1)]]
    a, b, c = (values[tri[:, i]].astype(float) for i in range(3))
    shape = (-1,) + (1,) * (a.ndim - 1)
    # a + w_b (b - a) + w_c (c - a): exact where the three values agree (a constant comes back as itself)
    out = a + weights[:, 1].reshape(shape) * (b - a) + weights[:, 2].reshape(shape) * (c - a)
    return out.astype(values.dtype, copy=False)

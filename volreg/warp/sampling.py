"""Octree sampling of the warp volume (paper Section 3.5).

The warp is trained on points spread over a volume X around the source
surfaces.  Section 3.5 of Schölkopf, Steinke & Blanz (ICML 2005) samples X by
"recursively subdividing an initial bounding box until the boxes reach a
resolution smaller than a chosen fraction of the kernel width (in our case
1/2).  We then take the center point of those boxes to be a training point.
Boxes are just subdivided if they lie within the volume X."

Here X is the neighbourhood of the source surfaces padded by ``pad`` mm,
``X = {x : dist(x, surface) <= pad}``, with the distance to the surface
approximated by the distance to its mesh vertices (see :func:`octree_sample`).

The subdivision runs level by level, vectorised over all boxes of a level, and
prunes every box that cannot meet X; the work therefore grows with the volume
of X (dilated by one box), not with the bounding box.  The samples lie on a
regular lattice of spacing equal to the final box edge and are returned in
Morton (Z-order) so that neighbours in space are mostly neighbours in memory,
which speeds up the sparse kernel products built on them.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from volreg._threads import query_workers
from volreg.kernels.grid import column_bounds
from volreg.settings import WarpSettings

__all__ = ["octree_sample", "morton_order"]

# Morton codes are held in 63 bits of an int64/uint64: 63 // D bits per axis.
_CODE_BITS = 63


def _positive(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"Expected a positive finite number for `{name}`, got {value!r}.") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"Expected a positive finite number for `{name}`, got {value!r}.")
    return v


def _morton_codes(cells: np.ndarray) -> np.ndarray:
    """Interleave the bits of non-negative integer cell coordinates.

    Parameters
    ----------
    cells : (N, D) int ndarray
        Non-negative cell indices; each must fit in ``63 // D`` bits.

    Returns
    -------
    codes : (N,) uint64 ndarray
        Bit ``b`` of axis ``d`` goes to bit ``b * D + d`` of the code (axis 0
        is the fastest-varying one).
    """
    n, dim = cells.shape
    codes = np.zeros(n, dtype=np.uint64)
    if n == 0:
        return codes
    c = cells.astype(np.uint64)
    nbits = int(cells.max()).bit_length()
    one = np.uint64(1)
    for b in range(nbits):
        for d in range(dim):
            codes |= ((c[:, d] >> np.uint64(b)) & one) << np.uint64(b * dim + d)
    return codes


def morton_order(points: np.ndarray, cell: float | np.ndarray) -> np.ndarray:
    """Permutation sorting points along a Morton (Z-order) curve.

    Points are binned into cells of edge ``cell`` anchored at the points'
    minimum corner, ``q = floor((points - points.min(0)) / cell)``, and sorted
    by the code that interleaves the bits of ``q`` (axis 0 in the lowest bit).
    Consecutive points in this order are mostly spatial neighbours, which
    keeps sparse kernel matrices banded-like and their products cache
    friendly.  Points in the same cell keep their input order.

    Parameters
    ----------
    points : (N, D) float ndarray, mm
        Points to order; N may be 0.
    cell : float or (D,) float ndarray, mm
        Cell edge, positive.  For lattice points use the lattice spacing.

    Returns
    -------
    order : (N,) intp ndarray
        A permutation of ``range(N)``; ``points[order]`` is Z-ordered.

    Raises
    ------
    ValueError
        If `points` is not a finite (N, D) array, `cell` is not positive, or
        the cell grid needs more than ``63 // D`` bits per axis.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] < 1:
        raise ValueError(f"Expected `points` of shape (N, D), got {pts.shape}.")
    if not np.all(np.isfinite(pts)):
        raise ValueError("Expected finite values in `points`, found NaN or Inf.")
    dim = pts.shape[1]
    cell_arr = np.asarray(cell, dtype=float)
    if cell_arr.ndim == 0:
        cell_arr = np.full(dim, float(cell_arr))
    if cell_arr.shape != (dim,) or not np.all(np.isfinite(cell_arr) & (cell_arr > 0)):
        raise ValueError(f"Expected a positive `cell` (scalar or shape ({dim},)), got {cell!r}.")
    if pts.shape[0] == 0:
        return np.zeros(0, dtype=np.intp)
    qf = np.floor((pts - column_bounds(pts)[0]) / cell_arr)
    bits = _CODE_BITS // dim
    if not qf.max() < 2.0**bits:
        raise ValueError(
            f"`cell` = {cell!r} is too small for the extent of `points`: the grid "
            f"needs more than {bits} bits per axis."
        )
    q = qf.astype(np.int64)
    return np.argsort(_morton_codes(q), kind="stable").astype(np.intp, copy=False)


def octree_sample(
    surface_points: np.ndarray,
    pad: float,
    width: float,
    *,
    fraction: float = WarpSettings.fraction,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """Training points of one kernel level: centres of octree boxes in X.

    Implements the sampling of the paper's Section 3.5.  The root box is the
    cube bounding the surface points padded by ``pad`` (or bounding
    ``bounds``), centred on that box.  It is halved along every axis, level
    by level, until the box edge ``e`` is smaller than ``fraction * width``
    (strictly), i.e. ``fraction * width / 2 <= e < fraction * width``.  A
    box of centre ``c`` and half-diagonal ``h = e sqrt(D) / 2`` is subdivided
    only if it can meet X, that is if ``dist(c, surface_points) <= pad + h``
    (a conservative test, by the triangle inequality).  At the last level the
    centres with ``dist(c, surface_points) <= pad`` are returned.

    All boxes of a level are processed at once (numpy over the level, one
    k-d tree query), so the cost is proportional to the number of boxes that
    meet X dilated by ``h``, i.e. to the sampled volume, not to the bounding
    box.

    Parameters
    ----------
    surface_points : (M, D) float ndarray, mm
        Vertices of one or several source surfaces, D = 2 (quadtree) or
        3 (octree).  The distance to the surface is approximated by the
        distance to this vertex set, so the vertices must be dense: with
        ``s`` the largest distance from a surface point to its nearest vertex
        (about the circumradius of the largest mesh triangle), the vertex
        distance overestimates the true distance by at most ``s``.  Hence
        every sample is within ``pad`` of the surface (when the vertices lie
        on it) and X is under-covered by at most ``s`` near its outer
        boundary.  Use ``s`` well below the box edge.
    pad : float, mm
        Half-thickness of the warp volume X around the surfaces, positive.
    width : float, mm
        Kernel width (support radius ``sigma`` of the Wu kernel, eq. 13) of
        the level being sampled, positive.
    fraction : float, optional
        Boxes are subdivided until their edge is below ``fraction * width``;
        default ``WarpSettings.fraction``, the paper's 1/2.  Positive.
    bounds : (lo, hi) pair of (D,) float ndarrays, mm, optional
        Axis-aligned box to sample instead of the padded bounding box of the
        surface points (e.g. the image's field of view).  The root cube
        covers it; samples outside ``[lo, hi]`` are dropped.
    tree : scipy.spatial.cKDTree, optional
        A k-d tree of ``surface_points`` (the same array), to share between the levels of
        one fit: on a large surface building it takes about as long as sampling a coarse
        level.

    Returns
    -------
    samples : (N, D) float ndarray, mm
        Box centres inside X (and inside `bounds`).  They lie on a regular
        lattice of spacing ``e`` (the final box edge), so the nearest-sample
        distance is ``e`` and, when ``pad >= h``, every point of X has a
        sample within ``2 h``.  Rows are sorted along a Morton (Z-order)
        curve of the boxes' integer indices, which keeps spatial neighbours
        close in memory and makes the sparse kernel products faster.  N may
        be 0 if `bounds` misses X.

    Raises
    ------
    ValueError
        For non-positive or non-finite `pad`, `width` or `fraction`; empty,
        non-finite or wrongly shaped `surface_points` (D must be 2 or 3);
        malformed `bounds`; or a `width` so small that the tree would need
        more levels than the Morton code holds.

    References
    ----------
    B. Schölkopf, F. Steinke, V. Blanz, "Object correspondence as a machine
    learning problem", ICML 2005, Section 3.5.
    """
    pts = _check_surface_points(surface_points)
    pad = _positive("pad", pad)
    width = _positive("width", width)
    fraction = _positive("fraction", fraction)
    dim = pts.shape[1]
    box_lo, box_hi, clip = _sampled_box(pts, pad, bounds)
    root = float(np.max(box_hi - box_lo))
    origin = 0.5 * (box_lo + box_hi) - 0.5 * root  # root cube centred on the box
    levels = _level_count(root, fraction * width, dim)
    if tree is None:
        tree = cKDTree(pts)
    elif tree.n != len(pts) or tree.m != dim:
        raise ValueError(f"Expected `tree` built on `surface_points` ({len(pts)} points in {dim}-D), "
                         f"got one of {tree.n} points in {tree.m}-D.")
    idx, centres = _subdivide(tree, origin, root, levels, pad, clip, dim)
    order = np.argsort(_morton_codes(idx), kind="stable")
    return np.ascontiguousarray(centres[order])


def _check_surface_points(surface_points: np.ndarray) -> np.ndarray:
    """``surface_points`` as a float (M, D) array, D = 2 or 3, M > 0, finite; errors name it."""
    pts = np.asarray(surface_points, dtype=float)
    if pts.ndim != 2:
        raise ValueError(f"Expected `surface_points` of shape (M, D), got {pts.shape}.")
    if pts.shape[1] not in (2, 3):
        raise ValueError(
            f"Expected `surface_points` of shape (M, 2) or (M, 3) (D = 2 or 3), got {pts.shape}."
        )
    if pts.shape[0] == 0:
        raise ValueError("Expected at least one point in `surface_points`, got none.")
    if not np.all(np.isfinite(pts)):
        raise ValueError("Expected finite values in `surface_points`, found NaN or Inf.")
    return pts


def _sampled_box(pts: np.ndarray, pad: float, bounds) -> tuple[np.ndarray, np.ndarray, tuple | None]:
    """The box the root cube covers, ``(lo, hi)`` (D,) mm each, and the box the samples are
    clipped to (``bounds`` checked, or None): the points' bounding box padded by ``pad`` without
    ``bounds``, ``bounds`` itself with it."""
    dim = pts.shape[1]
    if bounds is None:
        box_lo, box_hi = column_bounds(pts)
        return box_lo - pad, box_hi + pad, None
    try:
        box_lo, box_hi = (np.asarray(b, dtype=float) for b in bounds)
    except (TypeError, ValueError):
        raise ValueError(f"Expected `bounds` as a pair (lo, hi) of shape ({dim},) arrays.") from None
    if box_lo.shape != (dim,) or box_hi.shape != (dim,):
        raise ValueError(
            f"Expected `bounds` as a pair (lo, hi) of shape ({dim},) arrays, "
            f"got shapes {box_lo.shape} and {box_hi.shape}."
        )
    if not (np.all(np.isfinite(box_lo)) and np.all(np.isfinite(box_hi)) and np.all(box_hi >= box_lo)):
        raise ValueError(f"Expected finite `bounds` with hi >= lo, got lo={box_lo}, hi={box_hi}.")
    if not np.any(box_hi > box_lo):
        raise ValueError(f"Expected `bounds` of positive extent, got lo={box_lo}, hi={box_hi}.")
    return box_lo, box_hi, (box_lo, box_hi)


def _level_count(root: float, target: float, dim: int) -> int:
    """The halvings of a root cube of edge ``root`` (mm) until its boxes' edge is below ``target`` (mm);
    an error where the Morton code cannot hold that many."""
    levels = 0
    while root / 2.0**levels >= target:
        levels += 1
    max_levels = _CODE_BITS // dim
    if levels > max_levels:
        raise ValueError(
            f"`width` * `fraction` = {target:g} mm is too small for a sampled extent of "
            f"{root:g} mm: {levels} octree levels needed, at most {max_levels} supported."
        )
    return levels


def _subdivide(tree: cKDTree, origin: np.ndarray, root: float, levels: int, pad: float, clip: tuple | None,
               dim: int) -> tuple[np.ndarray, np.ndarray]:
    """The octree subdivision, level by level: the last level's boxes within ``pad`` of the surface.

    Parameters
    ----------
    tree : cKDTree
        Of the surface points.
    origin : (D,) float ndarray, mm
        The root cube's lowest corner.
    root : float, mm
        The root cube's edge.
    levels : int
        Halvings (:func:`_level_count`).
    pad : float, mm
    clip : (lo, hi) or None
        The box the boxes must meet (the last level's centres lie in).
    dim : int

    Returns
    -------
    idx : (N, D) int64 ndarray
        The kept boxes' integer indices at the last level.
    centres : (N, D) float ndarray, mm
        Their centres.
    """
    workers = query_workers()
    offsets = np.indices((2,) * dim).reshape(dim, -1).T.astype(np.int64)  # (2^D, D)
    idx = np.zeros((1, dim), dtype=np.int64)
    # Boxes wholly within `pad` of the surface points (dist(c) + h <= pad): every point of
    # them is in X, so all their descendants are kept without another query.  The result is
    # the same; only the boxes near the boundary of X are queried.
    inside = np.zeros(1, dtype=bool)
    for level in range(levels + 1):
        edge = root / 2.0**level
        centres = origin + (idx + 0.5) * edge
        last = level == levels
        half_diagonal = 0.5 * edge * math.sqrt(dim)
        reach = pad if last else pad + half_diagonal
        keep = inside.copy()
        ask = np.flatnonzero(~inside)
        # Any neighbour within `reach` decides; the bound prunes the search.
        dist, _ = tree.query(centres[ask], k=1, distance_upper_bound=reach * (1 + 1e-12) + 1e-12,
                             workers=workers)
        keep[ask] = dist <= reach
        if not last:
            inside[ask] = dist < pad - half_diagonal - 1e-9 * pad
        if clip is not None:
            half = 0.0 if last else 0.5 * edge
            keep &= np.all((centres + half >= clip[0]) & (centres - half <= clip[1]), axis=1)
        idx = idx[keep]
        if last:
            centres = centres[keep]
        else:
            idx = (2 * idx[:, None, :] + offsets[None, :, :]).reshape(-1, dim)
            inside = np.repeat(inside[keep], len(offsets))
    return idx, centres

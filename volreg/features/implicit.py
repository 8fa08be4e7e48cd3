"""Kernel implicit surfaces: signed-distance approximations fitted by SV regression.

Paper Section 4 (after Steinke, Schölkopf & Blanz 2005): the surface is the zero
set of ``f(x) = sum_i alpha_i k(x, x_i) + b`` (eqs. 14-15) with the Wu kernel
(13).  Training points are surface points (target 0) and off-surface points
displaced along the normals by ``+-delta`` (targets ``+-delta``, Carr et al.
2001); ``f`` is positive outside and negative inside.

The regression is epsilon-insensitive SV regression with the offset ``b``
fixed, so its dual has no equality constraint::

    minimise_beta   1/2 beta^T K beta - beta^T (y - b) + eps |beta|_1
    subject to      -C <= beta_i <= C

a box-constrained convex QP with the sparse kernel matrix ``K``, solved by
cyclic coordinate descent (each coordinate minimised exactly: soft threshold,
then clip).  Multi-scale: the first level uses a width of half the object
diameter; each further level halves the width and fits the residual of the
levels before it, down to ``min_width``.  Each level's training points are the
surface points thinned to a spacing of ``width / density`` and their validated
off-surface points, so every level's kernel matrix has a bounded number of
non-zeros per row and the fit costs time linear in the number of points.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.spatial import cKDTree
import scipy.sparse as sp

from volreg._jit import njit
from volreg._threads import query_workers
from volreg.kernels import CellGrid, _check_points, kernel_matrix, kernel_sum, put_rows, spatial_order, take_rows
from volreg.kernels.grid import column_bounds
from volreg.kernels.wu import wu

__all__ = ["ImplicitSurface", "ImplicitLevel", "default_min_width", "estimate_normals", "thin_points"]

ProgressCallback = Callable[[str, int, int], None]


# --------------------------------------------------------------------------------------
# Point-set utilities


#: :func:`_median_spacing` takes the median over every k-th point of larger sets, k chosen to
#: leave at least this many.
SPACING_SAMPLE = 20000


def _median_spacing(tree: cKDTree) -> float:
    """Median distance from each of the tree's points to its nearest other point, mm.

    Over every k-th point where there are more than twice :data:`SPACING_SAMPLE` (the
    median of such a sample is close to that of all the points, at a fraction of the search).
    """
    data = tree.data
    step = max(len(data) // SPACING_SAMPLE, 1) if len(data) > 2 * SPACING_SAMPLE else 1
    return float(np.median(tree.query(data[::step], 2, workers=query_workers())[0][:, 1]))


def default_min_width(points: np.ndarray) -> float:
    """:class:`ImplicitSurface`'s default finest width for ``points`` (N, D) mm: 8 times the
    median distance between neighbouring points, mm."""
    return 8.0 * _median_spacing(cKDTree(_check_points("points", points)))


def thin_points(points: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of a subset of ``points`` with about one point per cube of edge ``spacing``.

    Parameters
    ----------
    points : (N, D) float ndarray, mm
    spacing : float, mm

    Returns
    -------
    (K,) int ndarray
        Sorted indices into ``points``; in each occupied cell the point
        nearest the cell centre is kept.
    """
    points = np.asarray(points, dtype=float)
    lo = column_bounds(points)[0]
    rel = (points - lo) / spacing
    cell = np.floor(rel).astype(np.int64)
    dist = np.einsum("nd,nd->n", rel - cell - 0.5, rel - cell - 0.5)
    dims = column_bounds(cell)[1] + 1
    if np.prod(dims.astype(float)) < 2**62:
        key = np.ravel_multi_index(cell.T, dims)
    else:
        key = np.unique(cell, axis=0, return_inverse=True)[1].ravel()
    # Per cell, the nearest point (the lowest index among equals), as ``np.lexsort((dist, key))``
    # would choose it, without sorting the distances: a stable sort of the integer keys, then
    # each cell's least distance.
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    new_cell = np.ones(len(order), dtype=bool)
    new_cell[1:] = sorted_key[1:] != sorted_key[:-1]
    cell_of = np.cumsum(new_cell) - 1  # the cell number of each sorted point
    d_sorted = dist[order]
    rows = np.flatnonzero(d_sorted == np.minimum.reduceat(d_sorted, np.flatnonzero(new_cell))[cell_of])
    first = np.ones(len(rows), dtype=bool)
    first[1:] = cell_of[rows[1:]] != cell_of[rows[:-1]]
    return np.sort(order[rows[first]])


def estimate_normals(points: np.ndarray, *, k: int = 12) -> np.ndarray:
    """Unit normals of a point cloud from its nearest neighbours (paper Section 4).

    Each normal is the direction of least variance of the point's ``k`` nearest
    neighbours (local PCA).  Orientation is made consistent by propagating it
    along a minimum spanning tree of the neighbour graph weighted by
    ``1 - |n_i . n_j|`` (Hoppe et al. 1992), starting from the point of largest
    first coordinate whose normal is made to point in ``+x``; the result is then
    flipped if needed so that normals point away from the centroid on average
    (outward for a closed surface).

    Parameters
    ----------
    points : (N, D) float ndarray, mm
        A sufficiently dense sample of the surface (N > k).
    k : int
        Neighbours per point.

    Returns
    -------
    (N, D) float ndarray
        Unit normals.
    """
    points = _check_points("points", points)
    n, dim = points.shape
    if n <= dim:
        raise ValueError(f"Expected more than {dim} points to estimate normals, got {n}.")
    k = int(min(k, n - 1))
    tree = cKDTree(points)
    _, nbr = tree.query(points, k + 1, workers=query_workers())
    local = points[nbr] - points[nbr].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", local, local)
    _, vecs = np.linalg.eigh(cov)
    normals = vecs[:, :, 0]
    # Consistent orientation along a minimum spanning tree of the kNN graph.
    rows = np.repeat(np.arange(n), k)
    cols = nbr[:, 1:].ravel()
    weight = 1.0 - np.abs(np.einsum("nd,nd->n", normals[rows], normals[cols])) + 1e-9
    graph = sp.coo_matrix((weight, (rows, cols)), shape=(n, n)).tocsr()
    graph = graph.maximum(graph.T)
    tree_graph = minimum_spanning_tree(graph)
    tree_graph = tree_graph + tree_graph.T
    seed = int(np.argmax(points[:, 0]))
    if normals[seed, 0] < 0:
        normals[seed] = -normals[seed]
    visited = np.zeros(n, dtype=bool)
    for start in [seed] + list(range(n)):
        if visited[start]:
            continue
        order, pred = breadth_first_order(tree_graph, start, directed=False, return_predecessors=True)
        for node in order[1:]:
            if np.dot(normals[node], normals[pred[node]]) < 0:
                normals[node] = -normals[node]
        visited[order] = True
    if np.einsum("nd,nd->", normals, points - points.mean(axis=0)) < 0:
        normals = -normals
    return normals


def _unit_normals(normals: np.ndarray, n: int, dim: int) -> np.ndarray:
    normals = _check_points("normals", normals, dim)
    if normals.shape[0] != n:
        raise ValueError(f"Expected `normals` of shape ({n}, {dim}), got {normals.shape}.")
    length = np.linalg.norm(normals, axis=1)
    if np.any(length < 1e-12):
        raise ValueError("Expected non-zero `normals`; found zero-length normals.")
    return normals / length[:, None]


def _offsurface(points, normals, delta, tree) -> tuple[np.ndarray, np.ndarray]:
    """Carr-style off-surface points ``x +- delta n``, validated.

    A displaced point is kept only if no surface point lies closer to it than
    ``0.9 delta`` (otherwise the displacement crossed another part of the
    surface, and ``+-delta`` would be a wrong signed distance).
    """
    pts, vals = [], []
    for sign in (1.0, -1.0):
        p = points + sign * delta * normals
        # Only whether a surface point lies within 0.9 delta matters: the bounded search stops
        # there (inf where none does), sooner than the nearest point's exact distance.
        dist, _ = tree.query(p, 1, distance_upper_bound=0.9 * delta, workers=query_workers())
        ok = dist >= 0.9 * delta
        pts.append(p[ok])
        vals.append(np.full(int(ok.sum()), sign * delta))
    return np.concatenate(pts), np.concatenate(vals)


@njit(nogil=True)  # nogil: labels are fitted on parallel threads
def _svr_coordinate_descent(indptr, indices, data, diag, y, eps, box, beta, kbeta, max_sweeps, tol):
    """Cyclic coordinate descent on the fixed-offset SVR dual (in place).

    Minimises ``1/2 b^T K b - b^T y + eps |b|_1`` over ``|b_i| <= box``;
    ``kbeta`` holds ``K beta`` and is kept current; ``diag`` is the diagonal of
    ``K`` (positive).  Stops after the first sweep in which the fitted values
    ``K beta`` change by less than ``tol`` on average (each point's own change).

    Returns
    -------
    sweeps : int
    mean_change, max_change : float, mm
        Of the last sweep.
    """
    n = y.shape[0]
    change = np.inf
    total = np.inf
    sweeps = 0
    for sweep in range(max_sweeps):
        change = 0.0
        total = 0.0
        for i in range(n):
            kii = diag[i]
            z = beta[i] - (kbeta[i] - y[i]) / kii
            thr = eps / kii
            if z > thr:
                nb = z - thr
            elif z < -thr:
                nb = z + thr
            else:
                nb = 0.0
            if nb > box:
                nb = box
            elif nb < -box:
                nb = -box
            d = nb - beta[i]
            if d != 0.0:
                beta[i] = nb
                for p in range(indptr[i], indptr[i + 1]):
                    kbeta[indices[p]] += d * data[p]
                total += abs(d) * kii
                if abs(d) * kii > change:
                    change = abs(d) * kii
        sweeps = sweep + 1
        if total < tol * n:
            break
    return sweeps, total / max(n, 1), change


@dataclass(frozen=True)
class ImplicitLevel:
    """One scale of an implicit surface: ``sum_i alpha_i k(|x - c_i| / width)``.

    Attributes
    ----------
    centres : (M, D) float ndarray, mm
    alpha : (M,) float ndarray, mm
    width : float, mm
        Kernel width (support radius).
    """

    centres: np.ndarray
    alpha: np.ndarray
    width: float
    grid: CellGrid = field(repr=False, compare=False, default=None)

    def __post_init__(self) -> None:
        if self.grid is None:
            object.__setattr__(self, "grid", CellGrid.build(self.centres, self.width))


class ImplicitSurface:
    """Multi-scale kernel signed-distance function fitted to points and normals.

    Fitting happens in the constructor; calling the object evaluates ``f``.

    Parameters
    ----------
    points : (N, D) float ndarray, mm
        Surface points (D = 2 for outlines, 3 for surfaces).
    normals : (N, D) float ndarray, optional
        Outward normals at ``points``.  If omitted they are estimated from
        nearest neighbours (:func:`estimate_normals`).
    min_width : float, mm, optional
        Smallest kernel width.  Default: 8 times the median distance between
        neighbouring points.  Tie it to the voxel size when the points come from
        a label volume (:func:`volreg.features.label_surfaces.implicit_surfaces` uses 4 voxels).
    max_width : float, mm, optional
        Largest kernel width; default half the diameter (bounding-box diagonal).
    density : float
        Training points per kernel width along the surface (spacing ``width / density``).
    epsilon : float, mm, optional
        Half-width of the insensitive tube; default ``0.025 * min_width``
        (0.1 voxel when ``min_width`` is 4 voxels: about the noise of a
        marching-cubes mesh, so the fit regresses through it instead of
        interpolating it, and fewer centres are needed).
    box : float
        Box constraint ``C`` on the dual coefficients (mm); ``inf`` (default)
        gives epsilon-insensitive interpolation.
    offset : float, mm, optional
        The fixed offset ``b``: the value of ``f`` farther than the kernel
        widths from every centre.  Default ``max_width`` (positive: far points
        count as outside, as their true signed distance is at least about that).
    tol : float, mm, optional
        Coordinate descent stops after a sweep that changes the fitted values by
        less than this on average; default ``1e-4 * min_width``.  (On a 1 mm
        brain-size surface of 480k vertices the finest level then stops after
        48 sweeps instead of running to ``max_sweeps`` = 200; ``f`` moved by
        0.001 mm on average, at most 0.04 mm: well within the tube ``epsilon``.)
    max_sweeps : int
        Limit on coordinate-descent sweeps per level.
    progress : callable, optional
        ``progress(stage, done, total)``, called after each level.

    Attributes
    ----------
    points : (N, D) float ndarray, mm
        The surface points the surface was fitted to.
    levels : list of ImplicitLevel
    diameter : float, mm
    log : list of dict
        Per level: width, training points, non-zeros, sweeps, seconds,
        max and 99th-percentile residual at the training points (mm).
    """

    def __init__(
        self,
        points: np.ndarray,
        normals: np.ndarray | None = None,
        *,
        min_width: float | None = None,
        max_width: float | None = None,
        density: float = 3.0,
        epsilon: float | None = None,
        box: float = np.inf,
        offset: float | None = None,
        tol: float | None = None,
        max_sweeps: int = 200,
        progress: ProgressCallback | None = None,
    ) -> None:
        points = _check_points("points", points)
        n, dim = points.shape
        if dim not in (2, 3):
            raise ValueError(f"Expected `points` in 2 or 3 dimensions, got D={dim}.")
        if n < 2 * dim + 1:
            raise ValueError(f"Expected at least {2 * dim + 1} `points`, got {n}.")
        normals = estimate_normals(points) if normals is None else _unit_normals(normals, n, dim)
        tree = cKDTree(points)
        spacing = _median_spacing(tree)
        lo, hi = column_bounds(points)
        self.diameter = float(np.linalg.norm(hi - lo))
        if self.diameter <= 0:
            raise ValueError("Expected `points` spanning a non-zero extent, got coincident points.")
        if min_width is None:
            min_width = 8.0 * spacing
        if max_width is None:
            max_width = self.diameter / 2.0
        if not (min_width > 0 and max_width > 0):
            raise ValueError(f"Expected positive widths, got min_width={min_width}, max_width={max_width}.")
        if not density > 0:
            raise ValueError(f"Expected a positive `density`, got {density}.")
        widths = [float(max_width)]
        while widths[-1] / 2.0 >= min_width * (1 - 1e-9):
            widths.append(widths[-1] / 2.0)
        eps = 0.025 * min_width if epsilon is None else float(epsilon)
        tol = 1e-4 * min_width if tol is None else float(tol)
        self.offset = float(max_width if offset is None else offset)
        self.dim = dim
        self.points = points
        self.levels: list[ImplicitLevel] = []
        self.log: list[dict] = []
        for li, width in enumerate(widths):
            t0 = time.perf_counter()
            step = width / density
            keep = thin_points(points, step) if step > spacing else np.arange(n)
            sp_pts, sp_nrm = points[keep], normals[keep]
            off_pts, off_val = _offsurface(sp_pts, sp_nrm, step, tree)
            x = np.concatenate([sp_pts, off_pts])
            y = np.concatenate([np.zeros(len(sp_pts)), off_val])
            # The training points cell by cell: coordinate descent then updates the fitted values
            # of near neighbours one after the other, in cache.
            perm = spatial_order(x, width)
            if perm is not None:
                x, y = x[perm], y[perm]
            grid = CellGrid.build(x, width)
            residual = y - self.evaluate(x, order=0)[0]
            # Coordinate descent only walks the rows, and reads the kernel values in single precision:
            # the sweeps read half the bytes (the sums stay double, so the fit stays that of doubles).
            kmat = kernel_matrix(x, grid, width, sort=False, dtype=np.float32)
            beta = np.zeros(len(x))
            kbeta = np.zeros(len(x))
            sweeps, mean_change, max_change = _svr_coordinate_descent(
                kmat.indptr, kmat.indices, kmat.data, np.full(len(x), float(wu(np.zeros(1))[0])),  # K_ii = k(0)
                residual, eps, float(box), beta, kbeta,
                int(max_sweeps), tol,
            )
            used = beta != 0
            if used.any():
                self.levels.append(ImplicitLevel(x[used], beta[used], width))
            self.log.append(
                dict(
                    level=li,
                    width=width,
                    training_points=int(len(x)),
                    centres=int(used.sum()),
                    nnz_per_row=float(kmat.nnz / len(x)),
                    sweeps=int(sweeps),
                    converged=bool(mean_change < tol),
                    max_change=float(max_change),
                    max_residual=float(np.abs(kbeta - residual).max()),
                    p99_residual=float(np.percentile(np.abs(kbeta - residual), 99)),
                    seconds=time.perf_counter() - t0,
                )
            )
            if progress is not None:
                progress("fit implicit surface", li + 1, len(widths))

    @property
    def widths(self) -> list[float]:
        """Kernel widths of the levels, coarse to fine, mm."""
        return [lev.width for lev in self.levels]

    def evaluate(self, x: np.ndarray, *, order: int = 1) -> tuple[np.ndarray, ...]:
        """``f`` and its derivatives at ``x``.

        Parameters
        ----------
        x : (N, D) float ndarray, mm
        order : {0, 1, 2}

        Returns
        -------
        f : (N,) float ndarray, mm
            Approximate signed distance, positive outside.
        gradient : (N, D) float ndarray (if ``order >= 1``)
        hessian : (N, D, D) float ndarray, 1/mm (if ``order >= 2``)
        """
        x = _check_points("x", x, self.dim)
        n = len(x)
        perm = spatial_order(x, 0.5 * self.levels[-1].width) if self.levels else None
        xs = x if perm is None else take_rows(x, perm)
        outs = tuple(
            np.zeros(s) for s in [(n, 1), (n, 1, self.dim), (n, 1, self.dim, self.dim)][: order + 1]
        )
        for lev in self.levels:
            kernel_sum(xs, lev.grid, lev.alpha[:, None], lev.width, order=order, out=outs)
        outs[0][:] += self.offset
        result = []
        for o in outs:
            shape = (n,) + o.shape[2:]
            if perm is not None:
                o = put_rows(o.reshape(n, -1), perm)
            result.append(o.reshape(shape))
        return tuple(result)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Approximate signed distance ``f(x)``, (N,) mm."""
        return self.evaluate(x, order=0)[0]

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """``grad f(x)``, (N, D)."""
        return self.evaluate(x, order=1)[1]

    def hessian(self, x: np.ndarray) -> np.ndarray:
        """Hessian of ``f`` at ``x``, (N, D, D), 1/mm."""
        return self.evaluate(x, order=2)[2]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Corners ``(lo, hi)``, each (D,) mm, of the box outside which ``f`` equals the offset
        (an empty box at the origin if no level has a centre)."""
        if not self.levels:
            return np.zeros(self.dim), np.zeros(self.dim)
        lo = np.min([lev.centres.min(axis=0) - lev.width for lev in self.levels], axis=0)
        hi = np.max([lev.centres.max(axis=0) + lev.width for lev in self.levels], axis=0)
        return lo, hi

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays describing the model (for ``np.savez``; no pickle needed)."""
        out = {
            "dim": np.array(self.dim),
            "offset": np.array(self.offset),
            "diameter": np.array(self.diameter),
            "widths": np.array(self.widths),
            "points": self.points,
        }
        for i, lev in enumerate(self.levels):
            out[f"centres_{i}"] = lev.centres
            out[f"alpha_{i}"] = lev.alpha
        return out

    @classmethod
    def from_arrays(cls, arrays) -> "ImplicitSurface":
        """Rebuild a fitted surface from :meth:`to_arrays` output."""
        self = cls.__new__(cls)
        self.dim = int(arrays["dim"])
        self.offset = float(arrays["offset"])
        self.diameter = float(arrays["diameter"])
        self.points = np.asarray(arrays["points"], float)
        self.levels = [
            ImplicitLevel(np.asarray(arrays[f"centres_{i}"], float), np.asarray(arrays[f"alpha_{i}"], float), float(w))
            for i, w in enumerate(np.asarray(arrays["widths"]))
        ]
        self.log = []
        return self

"""The Wu kernel (paper eq. 13) and sparse neighbour sums over it.

``k(r) = (1 - r)_+^4 (4 + 16 r + 12 r^2 + 3 r^3)`` with ``r = |x - y| / sigma``:
compactly supported on ``|x - y| < sigma`` and C^2 in up to three dimensions,
so every kernel sum is a neighbour query and its gradient and Hessian exist in
closed form.  Writing ``d = x - y``::

    k'(r) / r          = g(r) = -7 (1 - r)^3 (8 + 9 r + 3 r^2)
    grad_x k           = g(r) d / sigma^2
    hess_x k           = [g(r) I + h(r) d d^T / sigma^2] / sigma^2,
    h(r) = g'(r) / r   = 105 (1 - r)^2 (1 + r)^2 / r

(``h(r) d d^T / sigma^2 = 105 (1-r)^2 (1+r)^2 r u u^T`` vanishes as r -> 0.)

Two implementations of the neighbour sums exist side by side:

* :func:`kernel_sum` -- the fast path: points are binned on a uniform grid of
  cells and a compiled (numba) loop visits, for each query, only the cells
  whose box is closer than ``sigma`` (one contiguous run of points per row of
  cells), in parallel over queries, writing into preallocated outputs.
* :func:`kernel_sum_reference` -- plain scipy (``cKDTree.sparse_distance_matrix``)
  processed in chunks under a memory budget; slower, used as the test oracle
  and as the benchmark baseline that justifies the JIT (``BENCHMARKS.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

__all__ = [
    "wu",
    "wu_derivatives",
    "CellGrid",
    "kernel_sum",
    "kernel_sum_reference",
    "kernel_matrix",
    "kernel_gradient_matrices",
    "spatial_order",
]


# Queries per parallel work item (per-item scratch arrays are allocated once).
_BLOCK = 512

# Cap on the number of grid cells of a CellGrid (int32 start offsets: 64 MiB).
_MAX_CELLS = 1 << 24


def wu(r: np.ndarray) -> np.ndarray:
    """Wu kernel profile (13), ``k(r)``, zero for ``r >= 1``.

    Parameters
    ----------
    r : ndarray
        Distances divided by the kernel width (dimensionless, >= 0).

    Returns
    -------
    ndarray, same shape as ``r``
    """
    r = np.asarray(r, dtype=float)
    t = np.clip(1.0 - r, 0.0, None)
    return t**4 * (4.0 + r * (16.0 + r * (12.0 + 3.0 * r)))


def wu_derivatives(d: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Value, gradient and Hessian of ``k(|d| / sigma)`` with respect to ``x``.

    Parameters
    ----------
    d : (N, D) float ndarray, mm
        Differences ``x - y``.
    sigma : float, mm
        Kernel width (support radius).

    Returns
    -------
    value : (N,) float ndarray
    gradient : (N, D) float ndarray, 1/mm
    hessian : (N, D, D) float ndarray, 1/mm^2
    """
    d = np.asarray(d, dtype=float)
    dim = d.shape[1]
    r = np.sqrt(np.einsum("nd,nd->n", d, d)) / sigma
    inside = r < 1.0
    t = np.where(inside, 1.0 - r, 0.0)
    value = t**4 * (4.0 + r * (16.0 + r * (12.0 + 3.0 * r)))
    g = -7.0 * t**3 * (8.0 + r * (9.0 + 3.0 * r))
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(r > 0, 105.0 * t**2 * (1.0 + r) ** 2 / np.where(r > 0, r, 1.0), 0.0)
    gradient = g[:, None] * d / sigma**2
    hessian = (
        g[:, None, None] * np.eye(dim)[None] + h[:, None, None] * d[:, :, None] * d[:, None, :] / sigma**2
    ) / sigma**2
    return value, gradient, hessian


# --------------------------------------------------------------------------------------
# Uniform cell grid over a point set


@dataclass(frozen=True, eq=False)
class CellGrid:
    """Points binned on a uniform grid of cubic cells, for radius queries.

    Attributes
    ----------
    points : (M, D) float ndarray, mm
        The points, reordered cell by cell.
    order : (M,) int ndarray
        ``points == original_points[order]``.
    start : (n_cells + 1,) int32 ndarray
        Points of cell ``c`` are ``points[start[c]:start[c + 1]]``.
    lo : (D,) float ndarray, mm
        Corner of cell ``(0, ..., 0)``.
    cell : float, mm
        Cell edge length.
    dims : (D,) int64 ndarray
        Number of cells per axis.
    radius : float, mm
        The query radius the grid was built for; a query visits the cells
        whose box is closer than ``radius``.
    """

    points: np.ndarray
    order: np.ndarray
    start: np.ndarray
    lo: np.ndarray
    cell: float
    dims: np.ndarray
    radius: float

    @cached_property
    def columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Coordinates as three contiguous (M,) arrays (z zeros in 2-D), for SIMD loops."""
        cols = [np.ascontiguousarray(self.points[:, a]) for a in range(self.points.shape[1])]
        while len(cols) < 3:
            cols.append(np.zeros(len(self.points)))
        return tuple(cols)

    @classmethod
    def build(cls, points: np.ndarray, radius: float, *, subdivisions: int = 1) -> "CellGrid":
        """Bin ``points`` (M, D) for queries of radius ``radius`` (mm).

        Cells have edge ``radius / subdivisions`` (larger if the grid would
        exceed 2^24 cells): smaller cells mean fewer candidate points per query
        but more runs to look up; 1 was fastest on surface-like point sets
        (1M queries against the frog body's 6 levels: 2.7 s for 1, 3.1 s for 2,
        3.3 s for 3 subdivisions).
        """
        points = np.ascontiguousarray(points, dtype=float)
        if points.ndim != 2 or points.shape[0] == 0:
            raise ValueError(f"Expected `points` of shape (M, D) with M > 0, got {points.shape}.")
        if not radius > 0:
            raise ValueError(f"Expected a positive `radius`, got {radius}.")
        lo = points.min(axis=0)
        extent = points.max(axis=0) - lo
        cell = float(radius) / max(1, int(subdivisions))
        while True:
            dims = np.floor(extent / cell).astype(np.int64) + 1
            if np.prod(dims.astype(float)) <= _MAX_CELLS:  # float: no int64 overflow
                break
            cell *= 1.25
        key = _cell_keys(points, lo, cell, dims)
        order = np.argsort(key, kind="stable")
        start = np.searchsorted(key[order], np.arange(np.prod(dims) + 1)).astype(np.int32)
        return cls(points[order], order, start, lo, cell, dims, float(radius))


def _cell_keys(points: np.ndarray, lo: np.ndarray, cell: float, dims: np.ndarray) -> np.ndarray:
    idx = np.clip(np.floor((points - lo) / cell).astype(np.int64), 0, dims - 1)
    key = np.zeros(len(points), dtype=np.int64)
    for a in range(points.shape[1]):
        key = key * dims[a] + idx[:, a]
    return key


@numba.njit(cache=True, inline="always")
def _gap2(x, lo_c, cell):
    """Squared distance from coordinate x to the interval [lo_c, lo_c + cell]."""
    if x < lo_c:
        return (lo_c - x) * (lo_c - x)
    if x > lo_c + cell:
        return (x - lo_c - cell) * (x - lo_c - cell)
    return 0.0


@numba.njit(cache=True, inline="always")
def _axis_range(x, radius, lo, cell, n):
    """Cells ``[first, last]`` of one axis that can hold points within ``radius`` of x."""
    first = np.floor((x - radius - lo) / cell)
    last = np.floor((x + radius - lo) / cell)
    first = max(first, 0.0)
    last = min(last, n - 1.0)
    return np.int64(first), np.int64(last)


@numba.njit(cache=True, inline="always")
def _candidate_ranges(x, lo, cell, dims, radius, start, ranges):
    """Fill ``ranges`` with ``[begin, end)`` runs of grid points that may lie within
    ``radius`` of ``x``: cells whose box is closer than ``radius``; along the last
    axis consecutive cells are contiguous, so each row of cells is one run.
    Returns the number of runs (D = 2 or 3)."""
    dim = x.shape[0]
    r2 = radius * radius
    nr = 0
    i0, i1 = _axis_range(x[0], radius, lo[0], cell, dims[0])
    for i in range(i0, i1 + 1):
        gi = _gap2(x[0], lo[0] + i * cell, cell)
        if gi >= r2:
            continue
        if dim == 2:
            rem = np.sqrt(r2 - gi)
            k0, k1 = _axis_range(x[1], rem, lo[1], cell, dims[1])
            if k0 > k1:
                continue
            base = i * dims[1]
            b, e = start[base + k0], start[base + k1 + 1]
            if e > b:
                ranges[nr, 0] = b
                ranges[nr, 1] = e
                nr += 1
            continue
        j0, j1 = _axis_range(x[1], np.sqrt(r2 - gi), lo[1], cell, dims[1])
        for j in range(j0, j1 + 1):
            gj = gi + _gap2(x[1], lo[1] + j * cell, cell)
            if gj >= r2:
                continue
            rem = np.sqrt(r2 - gj)
            k0, k1 = _axis_range(x[2], rem, lo[2], cell, dims[2])
            if k0 > k1:
                continue
            base = (i * dims[1] + j) * dims[2]
            b, e = start[base + k0], start[base + k1 + 1]
            if e > b:
                ranges[nr, 0] = b
                ranges[nr, 1] = e
                nr += 1
    return nr


def _max_runs(grid: "CellGrid") -> int:
    """Upper bound on the runs :func:`_candidate_ranges` returns for this grid."""
    per_axis = int(np.ceil(grid.radius / grid.cell)) * 2 + 2
    return per_axis ** (grid.points.shape[1] - 1)


@numba.njit(parallel=True, cache=True)
def _grid_sum(queries, gpts, gcoef, start, lo, cell, dims, max_runs, sigma, order, val, grad, hess):
    n, dim = queries.shape
    m = gcoef.shape[1]
    inv_s2 = 1.0 / (sigma * sigma)
    n_blocks = (n + _BLOCK - 1) // _BLOCK
    for blk in numba.prange(n_blocks):
        ranges = np.empty((max_runs, 2), dtype=np.int64)
        d = np.empty(dim)
        for q in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            x = queries[q]
            nr = _candidate_ranges(x, lo, cell, dims, sigma, start, ranges)
            for rr in range(nr):
                for p in range(ranges[rr, 0], ranges[rr, 1]):
                    r2 = 0.0
                    for a in range(dim):
                        d[a] = x[a] - gpts[p, a]
                        r2 += d[a] * d[a]
                    r2 *= inv_s2
                    if r2 >= 1.0:
                        continue
                    r = np.sqrt(r2)
                    t = 1.0 - r
                    t2 = t * t
                    k = t2 * t2 * (4.0 + r * (16.0 + r * (12.0 + 3.0 * r)))
                    for j in range(m):
                        val[q, j] += gcoef[p, j] * k
                    if order >= 1:
                        g = -7.0 * t2 * t * (8.0 + r * (9.0 + 3.0 * r)) * inv_s2
                        for j in range(m):
                            cg = gcoef[p, j] * g
                            for a in range(dim):
                                grad[q, j, a] += cg * d[a]
                        if order >= 2:
                            h = 0.0
                            if r > 0.0:
                                h = 105.0 * t2 * (1.0 + r) * (1.0 + r) / r * inv_s2 * inv_s2
                            for j in range(m):
                                cj = gcoef[p, j]
                                for a in range(dim):
                                    hess[q, j, a, a] += cj * g
                                    for b in range(dim):
                                        hess[q, j, a, b] += cj * h * d[a] * d[b]


@numba.njit(cache=True, fastmath=True, inline="always")
def _run_value(x0, x1, x2, px, py, pz, gcoef, begin, end, inv_s2):
    """sum_p a_p k(|x - p| / sigma) over one run of points: branch-free so that it
    compiles to SIMD code (t = 0 outside the support zeroes the term)."""
    v = 0.0
    for p in range(begin, end):
        d0 = x0 - px[p]
        d1 = x1 - py[p]
        d2 = x2 - pz[p]
        r = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2) * inv_s2)
        t = max(1.0 - r, 0.0)
        t2 = t * t
        v += gcoef[p] * t2 * t2 * (4.0 + r * (16.0 + r * (12.0 + 3.0 * r)))
    return v


@numba.njit(cache=True, fastmath=True, inline="always")
def _run_value_grad(x0, x1, x2, px, py, pz, gcoef, begin, end, inv_s2):
    """Value and gradient of the sum over one run of points (branch-free, SIMD)."""
    v = 0.0
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    for p in range(begin, end):
        d0 = x0 - px[p]
        d1 = x1 - py[p]
        d2 = x2 - pz[p]
        r = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2) * inv_s2)
        t = max(1.0 - r, 0.0)
        t2 = t * t
        a = gcoef[p]
        v += a * t2 * t2 * (4.0 + r * (16.0 + r * (12.0 + 3.0 * r)))
        g = a * -7.0 * t2 * t * (8.0 + r * (9.0 + 3.0 * r)) * inv_s2
        g0 += g * d0
        g1 += g * d1
        g2 += g * d2
    return v, g0, g1, g2


@numba.njit(parallel=True, cache=True)
def _grid_sum_scalar(queries, px, py, pz, gcoef, start, lo, cell, dims, max_runs, sigma, val, grad):
    """Hot path of :func:`_grid_sum` for scalar coefficients, order <= 1, D <= 3;
    point coordinates as separate arrays (``pz`` zeros in 2-D) for SIMD loads."""
    n, dim = queries.shape
    inv_s2 = 1.0 / (sigma * sigma)
    want_grad = grad.shape[0] == n
    dim3 = dim == 3
    n_blocks = (n + _BLOCK - 1) // _BLOCK
    for blk in numba.prange(n_blocks):
        ranges = np.empty((max_runs, 2), dtype=np.int64)
        for q in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            x = queries[q]
            nr = _candidate_ranges(x, lo, cell, dims, sigma, start, ranges)
            x0 = x[0]
            x1 = x[1]
            x2 = x[2] if dim3 else 0.0
            if want_grad:
                v = 0.0
                g0 = 0.0
                g1 = 0.0
                g2 = 0.0
                for rr in range(nr):
                    dv, d0, d1, d2 = _run_value_grad(x0, x1, x2, px, py, pz, gcoef, ranges[rr, 0], ranges[rr, 1],
                                                     inv_s2)
                    v += dv
                    g0 += d0
                    g1 += d1
                    g2 += d2
                val[q, 0] += v
                grad[q, 0, 0] += g0
                grad[q, 0, 1] += g1
                if dim3:
                    grad[q, 0, 2] += g2
            else:
                v = 0.0
                for rr in range(nr):
                    v += _run_value(x0, x1, x2, px, py, pz, gcoef, ranges[rr, 0], ranges[rr, 1], inv_s2)
                val[q, 0] += v


#: Evaluations of more points than this visit them in spatial order first.
SORT_ABOVE = 50_000


def spatial_order(points: np.ndarray, cell: float) -> np.ndarray | None:
    """A permutation visiting ``points`` (N, D) cell by cell (cells of ``cell`` mm),
    or None when there are too few points for it to pay.

    Neighbouring queries share kernel centres, which then stay in cache: 1.5x
    faster on 1e6 scattered points near the frog's surface.
    """
    if len(points) <= SORT_ABOVE or not cell > 0:
        return None
    return CellGrid.build(points, cell).order


def _as_coefficients(coeffs: np.ndarray, m_centres: int) -> tuple[np.ndarray, bool]:
    coeffs = np.asarray(coeffs, dtype=float)
    if coeffs.ndim not in (1, 2) or coeffs.shape[0] != m_centres:
        raise ValueError(
            f"Expected `coeffs` of shape ({m_centres},) or ({m_centres}, m), got {coeffs.shape}."
        )
    vector = coeffs.ndim == 2
    return (coeffs if vector else coeffs[:, None]), vector


def _check_points(name: str, x: np.ndarray, dim: int | None = None) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim != 2 or (dim is not None and x.shape[1] != dim):
        want = f"(N, {dim})" if dim is not None else "(N, D)"
        raise ValueError(f"Expected `{name}` of shape {want}, got {x.shape}.")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"Expected finite values in `{name}`, found NaN or Inf.")
    return np.ascontiguousarray(x)


def kernel_sum(
    queries: np.ndarray,
    centres: np.ndarray | CellGrid,
    coeffs: np.ndarray,
    sigma: float,
    *,
    order: int = 0,
    out: tuple[np.ndarray, ...] | None = None,
) -> tuple[np.ndarray, ...]:
    """Evaluate ``s(x) = sum_i a_i k(|x - x_i| / sigma)`` and its derivatives.

    Parameters
    ----------
    queries : (N, D) float ndarray, mm
        Evaluation points.
    centres : (M, D) float ndarray, mm, or CellGrid
        Kernel centres ``x_i`` (a prebuilt :class:`CellGrid` for radius >= sigma
        avoids re-binning when the same centres are queried repeatedly; its
        ``order`` is applied to ``coeffs``).
    coeffs : (M,) or (M, m) float ndarray
        Coefficients ``a_i`` (scalar or m-vector valued).
    sigma : float, mm
        Kernel width (support radius).
    order : {0, 1, 2}
        Highest derivative to return.
    out : tuple of arrays, optional
        Arrays ``(value, gradient, hessian)`` (as many as ``order + 1``) shaped
        as below, to accumulate into (added to, not overwritten).

    Returns
    -------
    value : (N,) or (N, m) float ndarray
    gradient : (N, D) or (N, m, D) float ndarray, 1/mm (if ``order >= 1``)
    hessian : (N, D, D) or (N, m, D, D) float ndarray, 1/mm^2 (if ``order >= 2``)
    """
    if order not in (0, 1, 2):
        raise ValueError(f"Expected `order` in (0, 1, 2), got {order}.")
    if not sigma > 0:
        raise ValueError(f"Expected a positive kernel width `sigma`, got {sigma}.")
    grid = centres if isinstance(centres, CellGrid) else CellGrid.build(_check_points("centres", centres), sigma)
    if grid.radius < sigma:
        raise ValueError(f"Expected a CellGrid built for radius >= sigma={sigma}, got {grid.radius}.")
    dim = grid.points.shape[1]
    queries = _check_points("queries", queries, dim)
    coef, vector = _as_coefficients(coeffs, grid.points.shape[0])
    coef = np.ascontiguousarray(coef[grid.order])
    n, m = queries.shape[0], coef.shape[1]
    shapes = [(n, m), (n, m, dim), (n, m, dim, dim)]
    if out is None:
        bufs = [np.zeros(s) for s in shapes[: order + 1]]
    else:
        if len(out) < order + 1:
            raise ValueError(f"Expected {order + 1} arrays in `out`, got {len(out)}.")
        bufs = [b.reshape(s) for b, s in zip(out, shapes)]
    val = bufs[0]
    grad = bufs[1] if order >= 1 else np.zeros((0, 1, dim))
    hess = bufs[2] if order >= 2 else np.zeros((1, 1, 1, 1))
    runs = _max_runs(grid)
    if m == 1 and order <= 1:
        px, py, pz = grid.columns
        _grid_sum_scalar(queries, px, py, pz, np.ascontiguousarray(coef[:, 0]), grid.start, grid.lo,
                         grid.cell, grid.dims, runs, float(sigma), val, grad)
    else:
        _grid_sum(queries, grid.points, coef, grid.start, grid.lo, grid.cell, grid.dims,
                  runs, float(sigma), order, val, grad, hess)
    result = [val, grad, hess][: order + 1]
    if not vector:
        result = [a.reshape((n,) + a.shape[2:]) for a in result]
    return tuple(result)


def kernel_sum_reference(
    queries: np.ndarray,
    centres: np.ndarray,
    coeffs: np.ndarray,
    sigma: float,
    *,
    order: int = 0,
    memory_budget: float = 256e6,
) -> tuple[np.ndarray, ...]:
    """Same as :func:`kernel_sum` with scipy only (KD-tree, chunked).

    Queries are processed in chunks so that the neighbour pairs of one chunk
    take about ``memory_budget`` bytes.  Kept as the oracle for tests and the
    baseline for benchmarks.
    """
    centres = _check_points("centres", centres)
    dim = centres.shape[1]
    queries = _check_points("queries", queries, dim)
    coef, vector = _as_coefficients(coeffs, centres.shape[0])
    n, m = queries.shape[0], coef.shape[1]
    tree = cKDTree(centres)
    # Estimate pairs per query from a small sample to size the chunks.
    sample = queries[:: max(1, n // 256)]
    per_query = max(1.0, tree.query_ball_point(sample, sigma, return_length=True).mean())
    bytes_per_pair = 8 * (4 + dim + dim * dim + m * (1 + dim + dim * dim))
    chunk = int(max(1, memory_budget // (per_query * bytes_per_pair)))
    outs = [np.zeros((n, m)), np.zeros((n, m, dim)), np.zeros((n, m, dim, dim))][: order + 1]
    for s in range(0, n, chunk):
        q = queries[s : s + chunk]
        pairs = cKDTree(q).sparse_distance_matrix(tree, sigma, output_type="ndarray")
        i, j = pairs["i"], pairs["j"]
        value, gradient, hessian = wu_derivatives(q[i] - centres[j], sigma)
        c = coef[j]
        nq = len(q)
        for col in range(m):
            outs[0][s : s + nq, col] = np.bincount(i, c[:, col] * value, minlength=nq)
            if order >= 1:
                for a in range(dim):
                    outs[1][s : s + nq, col, a] = np.bincount(i, c[:, col] * gradient[:, a], minlength=nq)
            if order >= 2:
                for a in range(dim):
                    for b in range(dim):
                        outs[2][s : s + nq, col, a, b] = np.bincount(
                            i, c[:, col] * hessian[:, a, b], minlength=nq
                        )
    if not vector:
        outs = [a.reshape((n,) + a.shape[2:]) for a in outs]
    return tuple(outs)


@numba.njit(parallel=True, cache=True)
def _grid_pairs(queries, gpts, gorder, start, lo, cell, dims, max_runs, sigma, indptr, indices, data, fill):
    """Count (``fill`` False: into ``indptr[1:]``) or write the kernel matrix rows."""
    n, dim = queries.shape
    sigma2 = sigma * sigma
    n_blocks = (n + _BLOCK - 1) // _BLOCK
    for blk in numba.prange(n_blocks):
        ranges = np.empty((max_runs, 2), dtype=np.int64)
        for q in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            x = queries[q]
            nr = _candidate_ranges(x, lo, cell, dims, sigma, start, ranges)
            w = indptr[q] if fill else 0
            for rr in range(nr):
                for p in range(ranges[rr, 0], ranges[rr, 1]):
                    r2 = 0.0
                    for a in range(dim):
                        da = x[a] - gpts[p, a]
                        r2 += da * da
                    if r2 < sigma2:
                        if fill:
                            r = np.sqrt(r2) / sigma
                            t = 1.0 - r
                            t2 = t * t
                            indices[w] = gorder[p]
                            data[w] = t2 * t2 * (4.0 + r * (16.0 + r * (12.0 + 3.0 * r)))
                        w += 1
            if not fill:
                indptr[q + 1] = w


def kernel_matrix(rows: np.ndarray, cols: np.ndarray | CellGrid, sigma: float) -> sp.csr_matrix:
    """Sparse kernel matrix ``K[i, j] = k(|rows_i - cols_j| / sigma)``.

    Parameters
    ----------
    rows : (N, D) float ndarray, mm
    cols : (M, D) float ndarray, mm, or a CellGrid of them (radius >= sigma)
    sigma : float, mm

    Returns
    -------
    (N, M) scipy.sparse.csr_matrix
        Column indices refer to the original order of ``cols``; sorted per row.
    """
    grid = cols if isinstance(cols, CellGrid) else CellGrid.build(_check_points("cols", cols), sigma)
    dim = grid.points.shape[1]
    rows = _check_points("rows", rows, dim)
    if grid.radius < sigma:
        raise ValueError(f"Expected a CellGrid built for radius >= sigma={sigma}, got {grid.radius}.")
    indptr = np.zeros(len(rows) + 1, dtype=np.int64)
    gorder = grid.order.astype(np.int64)
    args = (rows, grid.points, gorder, grid.start, grid.lo, grid.cell, grid.dims, _max_runs(grid), float(sigma))
    _grid_pairs(*args, indptr, np.zeros(0, np.int64), np.zeros(0), False)
    np.cumsum(indptr, out=indptr)
    nnz = int(indptr[-1])
    indices = np.empty(nnz, dtype=np.int64)
    data = np.empty(nnz)
    _grid_pairs(*args, indptr, indices, data, True)
    index_dtype = np.int32 if max(nnz, len(grid.points)) < 2**31 - 1 else np.int64
    indptr, indices = indptr.astype(index_dtype), indices.astype(index_dtype)
    mat = sp.csr_matrix((data, indices, indptr), shape=(len(rows), len(grid.points)))
    mat.sort_indices()
    return mat


def kernel_gradient_matrices(rows: np.ndarray, cols: np.ndarray, sigma: float) -> list[sp.csr_matrix]:
    """Sparse matrices ``G_b[i, j] = d k(|x - c_j| / sigma) / d x_b`` at ``x = rows_i``.

    Parameters
    ----------
    rows : (N, D) float ndarray, mm
    cols : (M, D) float ndarray, mm
    sigma : float, mm

    Returns
    -------
    list of D (N, M) scipy.sparse.csr_matrix, 1/mm
        ``sum_b``-wise, ``J(x_i) = I + sum_j c_j (G[:, i, j])^T`` is the Jacobian
        of ``x + sum_j c_j k(x, c_j)``.
    """
    rows = _check_points("rows", rows)
    cols = _check_points("cols", cols, rows.shape[1])
    k = kernel_matrix(rows, cols, sigma)
    i = np.repeat(np.arange(k.shape[0]), np.diff(k.indptr))
    d = rows[i] - cols[k.indices]
    r = np.sqrt(np.einsum("nd,nd->n", d, d)) / sigma
    t = np.clip(1.0 - r, 0.0, None)
    g = -7.0 * t**3 * (8.0 + r * (9.0 + 3.0 * r)) / sigma**2
    return [sp.csr_matrix((g * d[:, b], k.indices, k.indptr), shape=k.shape) for b in range(rows.shape[1])]

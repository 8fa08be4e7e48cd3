"""Sums of the Wu kernel (13) over point sets, and the sparse kernel and gradient matrices.

:func:`kernel_sum` is the fast path: it bins the centres on a
:class:`~volreg.kernels.grid.CellGrid` and runs a compiled loop (chosen from
:data:`_BLOCKED`) that visits only the centres within ``sigma`` of each query.
:func:`kernel_sum_reference` computes the same with scipy only and is the test
oracle and benchmark baseline.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from volreg.kernels._compiled import (
    _MIN_MEAN_BLOCK,
    _BLOCK,
    _QBLOCK,
    _SUPER,
    _blocked_sum,
    _blocked_sum_hessian,
    _blocked_sum_vector,
    _grid_pairs,
    _query_blocks,
    _strict_sum,
)
from volreg._threads import run_parts
from volreg.kernels.grid import CellGrid, max_runs, put_rows, spatial_order, take_rows
from volreg.kernels.wu import wu_derivatives, wu_slope

__all__ = ["check_points", "kernel_gradient_matrices", "kernel_matrix", "kernel_sum", "kernel_sum_reference"]


def check_points(name: str, x: np.ndarray, dim: int | None = None) -> np.ndarray:
    """``x`` as a C-contiguous (N, D) float array of finite values, checked.

    Parameters
    ----------
    name : str
        The argument's name, for the error messages.
    x : (N, D) array_like
        Points (mm, in the callers).
    dim : int, optional
        The D that ``x`` must have; any when None.

    Returns
    -------
    (N, D) float64 ndarray, C-contiguous
        ``x`` itself where it already is one.

    Raises
    ------
    ValueError
        ``x`` is not two-dimensional, has another D than ``dim``, or holds NaN or Inf.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 2 or (dim is not None and x.shape[1] != dim):
        want = f"(N, {dim})" if dim is not None else "(N, D)"
        raise ValueError(f"Expected `{name}` of shape {want}, got {x.shape}.")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"Expected finite values in `{name}`, found NaN or Inf.")
    return np.ascontiguousarray(x)


def _as_coefficients(coeffs: np.ndarray, m_centres: int) -> tuple[np.ndarray, bool]:
    """``coeffs`` (M,) or (M, m) as an (M, m) float array, and whether it was vector valued."""
    coeffs = np.asarray(coeffs, dtype=float)
    if coeffs.ndim not in (1, 2) or coeffs.shape[0] != m_centres:
        raise ValueError(
            f"Expected `coeffs` of shape ({m_centres},) or ({m_centres}, m), got {coeffs.shape}."
        )
    vector = coeffs.ndim == 2
    return (coeffs if vector else coeffs[:, None]), vector


def _super_blocks(blocks: np.ndarray) -> int:
    """The work items of the blocked loops: ``_SUPER`` query blocks each."""
    return (len(blocks) - 1 + _SUPER - 1) // _SUPER


def _query_parts(queries: np.ndarray) -> int:
    """The work items of the loops with one neighbour search per query: ``_BLOCK`` queries each."""
    return (len(queries) + _BLOCK - 1) // _BLOCK


# --------------------------------------------------------------------------------------
# The compiled loops, called with one convention: (queries (N, D), grid, coef (M, m) in grid
# order, sigma, order, blocks from _coherent_blocks or None, val, grad, hess)


def _blocked(queries, grid, coef, sigma, order, blocks, val, grad, hess):
    px, py, pz = grid.columns
    run_parts(_blocked_sum, _super_blocks(blocks), queries, blocks, px, py, pz, coef, grid.start, grid.lo,
              grid.cell, grid.dims, sigma, val, grad)


def _blocked_vector(queries, grid, coef, sigma, order, blocks, val, grad, hess):
    px, py, pz = grid.columns
    run_parts(_blocked_sum_vector, _super_blocks(blocks), queries, blocks, px, py, pz, coef, grid.start, grid.lo,
              grid.cell, grid.dims, sigma, val, grad)


def _blocked_hessian(queries, grid, coef, sigma, order, blocks, val, grad, hess):
    px, py, pz = grid.columns
    run_parts(_blocked_sum_hessian, _super_blocks(blocks), queries, blocks, px, py, pz, coef, grid.start, grid.lo,
              grid.cell, grid.dims, sigma, val, grad, hess)


def _strict(queries, grid, coef, sigma, order, blocks, val, grad, hess):
    run_parts(_strict_sum, _query_parts(queries), queries, grid.points, coef, grid.start, grid.lo, grid.cell,
              grid.dims, max_runs(grid), sigma, order, val, grad, hess)


#: The blocked loop serving each case of :func:`kernel_sum` that has one: (coefficients, order)
#: -> loop.  Coefficients are "scalar" (m = 1, implicit surfaces), "vector" (m = 2 or 3, warps)
#: or "wide" (m > 3).  The blocked loops are branch-free SIMD code (fastmath) over the centres
#: gathered once per block of nearby queries; queries that do not come in such blocks are sorted
#: cell by cell first.  The strict loop (one neighbour search per query) serves every other case.
_BLOCKED = {
    ("scalar", 0): _blocked,
    ("scalar", 1): _blocked,
    ("scalar", 2): _blocked_hessian,
    ("vector", 0): _blocked_vector,
    ("vector", 1): _blocked_vector,
}


def _coefficient_kind(m: int) -> str:
    return "scalar" if m == 1 else "vector" if m <= 3 else "wide"


def _coherent_blocks(queries: np.ndarray, sigma: float) -> np.ndarray | None:
    """Blocks of nearby consecutive queries (:func:`~volreg.kernels._compiled._query_blocks`,
    at most ``sigma / 2`` wide), or None when there are few queries or they are not in
    spatial order (too few queries per block for the shared search to pay; they are then
    sorted first, :func:`_blocked_in_order`)."""
    n = queries.shape[0]
    if n < _QBLOCK:
        return None
    blocks = _query_blocks(queries, 0.5 * sigma, _QBLOCK)
    if n < _MIN_MEAN_BLOCK * (len(blocks) - 1):
        return None
    return blocks


def _blocked_in_order(blocked, queries, grid, coef, sigma, order, val, grad, hess):
    """Run a blocked loop on queries that do not come in blocks of nearby ones: sorted cell by
    cell first (:func:`~volreg.kernels.grid.spatial_order`), the sums added back in the
    callers' order.  Sorting costs less than a neighbour search per query, and the
    registration's compiled loops then need no per-query variant."""
    n = queries.shape[0]
    perm = spatial_order(queries, 0.5 * sigma, above=0)
    sorted_queries = take_rows(queries, perm)
    blocks = _query_blocks(sorted_queries, 0.5 * sigma, _QBLOCK)
    outs = [val, grad, hess][: order + 1]
    sums = [np.zeros(o.shape) for o in outs]
    blocked(sorted_queries, grid, coef, sigma, order, blocks, *(sums + [grad, hess][order:]))
    for o, s in zip(outs, sums):
        o += put_rows(s.reshape(n, -1), perm).reshape(o.shape)


def kernel_sum(
    queries: np.ndarray,
    centres: np.ndarray | CellGrid,
    coeffs: np.ndarray,
    sigma: float,
    *,
    order: int = 0,
    out: tuple[np.ndarray, ...] | None = None,
) -> tuple[np.ndarray, ...]:
    """Evaluate ``s(x) = sum_i a_i k(|x - x_i| / sigma)`` (Wu kernel (13)) and its derivatives.

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

    Notes
    -----
    Queries are evaluated in blocks of nearby queries that share one neighbour search:
    as given where they come in spatial order (for instance by
    :func:`~volreg.kernels.grid.spatial_order`), else sorted cell by cell first and the
    sums put back in their order; see :data:`_BLOCKED` for which compiled loop serves
    which case.
    """
    if order not in (0, 1, 2):
        raise ValueError(f"Expected `order` in (0, 1, 2), got {order}.")
    if not sigma > 0:
        raise ValueError(f"Expected a positive kernel width `sigma`, got {sigma}.")
    grid = centres if isinstance(centres, CellGrid) else CellGrid.build(check_points("centres", centres), sigma)
    if grid.radius < sigma:
        raise ValueError(f"Expected a CellGrid built for radius >= sigma={sigma}, got {grid.radius}.")
    dim = grid.points.shape[1]
    queries = check_points("queries", queries, dim)
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
    blocked = _BLOCKED.get((_coefficient_kind(m), order))
    if blocked is None:
        _strict(queries, grid, coef, float(sigma), order, None, val, grad, hess)
    elif n > 0:
        blocks = _coherent_blocks(queries, sigma)
        if blocks is not None:
            blocked(queries, grid, coef, float(sigma), order, blocks, val, grad, hess)
        else:
            _blocked_in_order(blocked, queries, grid, coef, float(sigma), order, val, grad, hess)
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
    """Same as :func:`kernel_sum` with scipy only (KD-tree, chunked); the test oracle.

    Parameters
    ----------
    queries, centres, coeffs, sigma, order
        As :func:`kernel_sum` (``centres`` an array).
    memory_budget : float, bytes
        Queries are processed in chunks whose neighbour pairs take about this much.

    Returns
    -------
    tuple of float ndarray
        As :func:`kernel_sum`.
    """
    centres = check_points("centres", centres)
    dim = centres.shape[1]
    queries = check_points("queries", queries, dim)
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


def kernel_matrix(rows: np.ndarray, cols: np.ndarray | CellGrid, sigma: float, *,
                  sort: bool = True, dtype=np.float64) -> sp.csr_matrix:
    """Sparse kernel matrix ``K[i, j] = k(|rows_i - cols_j| / sigma)`` (Wu kernel (13)).

    Parameters
    ----------
    rows : (N, D) float ndarray, mm
    cols : (M, D) float ndarray, mm, or a CellGrid of them (radius >= sigma)
    sigma : float, mm
    sort : bool
        Sort the column indices of each row (scipy's canonical form); a caller that
        only walks the rows (coordinate descent) may skip it.
    dtype : numpy.float64 or numpy.float32
        Type of the values.  They are computed in double precision and stored rounded to
        single precision either way (relative error below 6e-8), then widened for float64.

    Returns
    -------
    (N, M) scipy.sparse.csr_matrix
        Column indices refer to the original order of ``cols``; sorted per row if ``sort``.
    """
    if np.dtype(dtype) not in (np.float32, np.float64):
        raise ValueError(f"Expected `dtype` float32 or float64, got {np.dtype(dtype)}.")
    grid = cols if isinstance(cols, CellGrid) else CellGrid.build(check_points("cols", cols), sigma)
    dim = grid.points.shape[1]
    rows = check_points("rows", rows, dim)
    if grid.radius < sigma:
        raise ValueError(f"Expected a CellGrid built for radius >= sigma={sigma}, got {grid.radius}.")
    indptr = np.zeros(len(rows) + 1, dtype=np.int64)
    gorder = grid.order.astype(np.int64)
    args = (rows, grid.points, gorder, grid.start, grid.lo, grid.cell, grid.dims, max_runs(grid), float(sigma))
    run_parts(_grid_pairs, _query_parts(rows), *args, indptr, np.zeros(0, np.int32), np.zeros(0, np.float32), False)
    np.cumsum(indptr, out=indptr)
    nnz = int(indptr[-1])
    # Column indices written in their final type: no second copy of the largest array (tens of
    # millions of entries at a 1 mm surface's finest level), whose fresh pages cost more than the fill.
    index_dtype = np.int32 if max(nnz, len(grid.points)) < 2**31 - 1 else np.int64
    indices = np.empty(nnz, dtype=index_dtype)
    # The values written in single precision: one compiled loop for both types, and for the
    # implicit surfaces' coordinate descent (float32) half the fresh pages and no copy.
    data = np.empty(nnz, dtype=np.float32)
    run_parts(_grid_pairs, _query_parts(rows), *args, indptr, indices, data, True)
    if np.dtype(dtype) == np.float64:
        data = data.astype(np.float64)
    indptr = indptr.astype(index_dtype)
    mat = sp.csr_matrix((data, indices, indptr), shape=(len(rows), len(grid.points)))
    if sort:
        mat.sort_indices()
    else:
        mat.has_sorted_indices = False  # scipy sorts (or checks) before any operation that needs it
    return mat


def kernel_gradient_matrices(rows: np.ndarray, cols: np.ndarray, sigma: float) -> list[sp.csr_matrix]:
    """Sparse matrices ``G_b[i, j] = d k(|x - c_j| / sigma) / d x_b`` at ``x = rows_i`` (Wu kernel (13)).

    Parameters
    ----------
    rows : (N, D) float ndarray, mm
    cols : (M, D) float ndarray, mm
    sigma : float, mm

    Returns
    -------
    list of D (N, M) scipy.sparse.csr_matrix, 1/mm
        ``J(x_i) = I + sum_j c_j (G[:, i, j])^T`` is the Jacobian of
        ``x + sum_j c_j k(x, c_j)``; the pattern is that of :func:`kernel_matrix`.
    """
    rows = check_points("rows", rows)
    cols = check_points("cols", cols, rows.shape[1])
    k = kernel_matrix(rows, cols, sigma)
    i = np.repeat(np.arange(k.shape[0]), np.diff(k.indptr))
    d = rows[i] - cols[k.indices]
    r = np.sqrt(np.einsum("nd,nd->n", d, d)) / sigma
    g = wu_slope(r) / sigma**2
    return [sp.csr_matrix((g * d[:, b], k.indices, k.indptr), shape=k.shape) for b in range(rows.shape[1])]

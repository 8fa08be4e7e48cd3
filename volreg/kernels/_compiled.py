"""Compiled (numba) loops of the kernel sums; private, called through ``grid``, ``sums`` and ``sparse``,
but :func:`segmented_sums` (exported by :mod:`volreg.kernels` for :mod:`volreg.features.batch`).

Every loop evaluates the Wu kernel (13) through :func:`volreg.kernels.wu.wu_terms`,
inlined.  Loops marked ``fastmath`` are branch-free over the candidate points
(``t = max(1 - r, 0)`` zeroes terms outside the support) so that they compile to
SIMD code; their sums are reassociated by the compiler and may differ from the
strict loops in the last bits.

Loops whose first two arguments are ``part, parts`` cover part ``part`` of ``parts`` of their
work items (the blocks, queries, rows or segments said "in parallel" below), as
:func:`volreg._threads.run_parts` calls them, one part per call on its threads.

Layout of the point sets: a :class:`~volreg.kernels.grid.CellGrid` sorts the
centres cell by cell (row-major, last axis fastest), so the points of one row of
cells along the last axis are one contiguous run ``[start[c0], start[c1 + 1])``.
"""

from __future__ import annotations

import numpy as np

from volreg._jit import njit
from volreg._threads import part_range, run_parts
from volreg.kernels.wu import wu_terms

#: Queries per parallel work item of the loops with one neighbour search per query (scratch
#: arrays are allocated per item).
_BLOCK = 512

#: Most queries of one block of the blocked loop (queries sharing one gathered candidate list).
_QBLOCK = 256

#: Blocks per parallel work item of the blocked loop (one gather buffer per work item).
_SUPER = 32

#: The blocked loop is used when query blocks hold at least this many queries on average.
_MIN_MEAN_BLOCK = 8.0


# --------------------------------------------------------------------------------------
# Cells and neighbour ranges


@njit
def _cell_sort(points, lo, cell, dims):
    """Stable counting sort of points by row-major cell index, O(M + n_cells).

    Parameters
    ----------
    points : (M, D) float ndarray, mm
    lo : (D,) float ndarray, mm
        Corner of cell ``(0, ..., 0)``.
    cell : float, mm
        Cell edge.
    dims : (D,) int64 ndarray
        Cells per axis; points outside are clamped into the border cells.

    Returns
    -------
    order : (M,) int64 ndarray
        The permutation that sorts the points.
    start : (n_cells + 1,) int64 ndarray
        Cell ``c`` holds sorted points ``start[c]:start[c + 1]``.
    """
    n, dim = points.shape
    n_cells = 1
    for a in range(dim):
        n_cells *= dims[a]
    keys = np.empty(n, dtype=np.int64)
    start = np.zeros(n_cells + 1, dtype=np.int64)
    for i in range(n):
        k = 0
        for a in range(dim):
            c = np.int64(np.floor((points[i, a] - lo[a]) / cell))
            k = k * dims[a] + min(max(c, 0), dims[a] - 1)
        keys[i] = k
        start[k + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        order[fill[keys[i]]] = i
        fill[keys[i]] += 1
    return order, start


@njit
def _gap2(x, lo_c, cell):
    """Squared distance (mm^2) from coordinate ``x`` to the interval ``[lo_c, lo_c + cell]``."""
    if x < lo_c:
        return (lo_c - x) * (lo_c - x)
    if x > lo_c + cell:
        return (x - lo_c - cell) * (x - lo_c - cell)
    return 0.0


@njit
def _axis_range(x, radius, lo, cell, n):
    """Cells ``(first, last)`` of one axis (``n`` cells from ``lo``) that can hold points
    within ``radius`` of ``x``; empty when ``first > last``."""
    first = np.floor((x - radius - lo) / cell)
    last = np.floor((x + radius - lo) / cell)
    first = max(first, 0.0)
    last = min(last, n - 1.0)
    return np.int64(first), np.int64(last)


@njit
def _candidate_ranges(x, lo, cell, dims, radius, start, ranges):
    """Runs of grid points that may lie within ``radius`` of ``x`` (D = 2 or 3).

    Visits the cells whose box is closer than ``radius``; along the last axis
    consecutive cells are contiguous, so each row of cells is one run.  Fills
    ``ranges`` (max_runs, 2) with ``[begin, end)`` pairs and returns their count.
    """
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


# --------------------------------------------------------------------------------------
# Blocks of nearby queries and the centres they share


@njit
def _query_blocks(queries, width, max_size):
    """Split consecutive queries into blocks of nearby ones.

    Parameters
    ----------
    queries : (N, D) float ndarray, mm
    width : float, mm
        Largest extent of a block's bounding box along any axis.
    max_size : int
        Most queries per block.

    Returns
    -------
    (n_blocks + 1,) int64 ndarray
        Block ``b`` holds queries ``starts[b]:starts[b + 1]``.
    """
    n, dim = queries.shape
    starts = np.empty(n + 1, dtype=np.int64)
    lo = np.empty(dim)
    hi = np.empty(dim)
    nb = 0
    i = 0
    while i < n:
        starts[nb] = i
        nb += 1
        for a in range(dim):
            lo[a] = queries[i, a]
            hi[a] = queries[i, a]
        j = i + 1
        while j < n and j - i < max_size:
            fits = True
            for a in range(dim):
                v = queries[j, a]
                if max(hi[a], v) - min(lo[a], v) > width:
                    fits = False
                    break
            if not fits:
                break
            for a in range(dim):
                v = queries[j, a]
                lo[a] = min(lo[a], v)
                hi[a] = max(hi[a], v)
            j += 1
        i = j
    starts[nb] = n
    return starts[: nb + 1]


@njit
def _block_box(queries, q0, q1, dim3):
    """Bounding box ``(l0, h0, l1, h1, l2, h2)`` (mm) of ``queries[q0:q1]`` (z = 0 in 2-D)."""
    l0 = queries[q0, 0]
    h0 = l0
    l1 = queries[q0, 1]
    h1 = l1
    l2 = queries[q0, 2] if dim3 else 0.0
    h2 = l2
    for q in range(q0 + 1, q1):
        l0 = min(l0, queries[q, 0])
        h0 = max(h0, queries[q, 0])
        l1 = min(l1, queries[q, 1])
        h1 = max(h1, queries[q, 1])
        if dim3:
            l2 = min(l2, queries[q, 2])
            h2 = max(h2, queries[q, 2])
    return l0, h0, l1, h1, l2, h2


@njit
def _box_cells(l0, h0, l1, h1, l2, h2, sigma, lo, cell, dims, dim3):
    """Cell ranges ``(i0, i1, j0, j1, k0, k1)`` of the box dilated by ``sigma``.

    In 2-D the contiguous axis is axis 1 and ``(j0, j1) = (0, 0)``.  Empty when a
    first index exceeds its last.
    """
    i0 = _axis_range(l0, sigma, lo[0], cell, dims[0])[0]
    i1 = _axis_range(h0, sigma, lo[0], cell, dims[0])[1]
    j0 = _axis_range(l1, sigma, lo[1], cell, dims[1])[0]
    j1 = _axis_range(h1, sigma, lo[1], cell, dims[1])[1]
    if dim3:
        k0 = _axis_range(l2, sigma, lo[2], cell, dims[2])[0]
        k1 = _axis_range(h2, sigma, lo[2], cell, dims[2])[1]
        return i0, i1, j0, j1, k0, k1
    return i0, i1, np.int64(0), np.int64(0), j0, j1


@njit
def _gather_block(queries, q0, q1, dim3, px, py, pz, coef, start, lo, cell, dims, sigma, buf):
    """Copy the centres within ``sigma`` of the bounding box of ``queries[q0:q1]`` into ``buf``.

    Parameters
    ----------
    buf : (6, capacity) float ndarray
        Rows 0-2 receive the coordinates (mm), rows 3-5 the (up to 3) coefficient
        columns of ``coef`` (M, m), zeros past ``m``.

    Returns
    -------
    buf : (6, capacity') float ndarray
        ``buf``, or a larger array when the candidates do not fit.
    count : int
        Number of centres gathered.
    """
    l0, h0, l1, h1, l2, h2 = _block_box(queries, q0, q1, dim3)
    i0, i1, j0, j1, k0, k1 = _box_cells(l0, h0, l1, h1, l2, h2, sigma, lo, cell, dims, dim3)
    if i0 > i1 or j0 > j1 or k0 > k1:
        return buf, 0
    nz = dims[2] if dim3 else dims[1]
    ny = dims[1] if dim3 else 1
    count = 0
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            base = (i * ny + j) * nz
            count += start[base + k1 + 1] - start[base + k0]
    if count > buf.shape[1]:
        buf = np.empty((6, 2 * count))
    m = coef.shape[1]
    s2 = sigma * sigma
    c = 0
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            base = (i * ny + j) * nz
            for p in range(start[base + k0], start[base + k1 + 1]):
                if _gap2(px[p], l0, h0 - l0) + _gap2(py[p], l1, h1 - l1) + _gap2(pz[p], l2, h2 - l2) < s2:
                    buf[0, c] = px[p]
                    buf[1, c] = py[p]
                    buf[2, c] = pz[p]
                    for a in range(3):
                        buf[3 + a, c] = coef[p, a] if a < m else 0.0
                    c += 1
    return buf, c


# --------------------------------------------------------------------------------------
# Sums over one run of candidate points and writing them out.  The run sums are
# branch-free (t = max(1 - r, 0) zeroes the terms outside the support) so that they
# compile to SIMD code; one helper per order, because a single helper with the order
# as a constant argument compiled to slower loops.


@njit(fastmath=True, inline="always")
def _run_value(x0, x1, x2, px, py, pz, coef, begin, end, inv_s2):
    """``sum_p a_p k(|x - p| / sigma)`` over points ``begin:end``.

    Parameters
    ----------
    x0, x1, x2 : float, mm
        The query (``x2 = 0`` in 2-D).
    px, py, pz : (M,) float ndarray, mm
        Point coordinates (``pz`` zeros in 2-D).
    coef : (M,) float ndarray
        Coefficients ``a_p``.
    begin, end : int
    inv_s2 : float, 1/mm^2
        ``1 / sigma^2``.

    Returns
    -------
    float
    """
    v = 0.0
    for p in range(begin, end):
        d0 = x0 - px[p]
        d1 = x1 - py[p]
        d2 = x2 - pz[p]
        r = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2) * inv_s2)
        v += wu_terms(coef[p], r, max(1.0 - r, 0.0))[0]
    return v


@njit(fastmath=True, inline="always")
def _run_value_grad(x0, x1, x2, px, py, pz, coef, begin, end, inv_s2):
    """:func:`_run_value` and the gradient: ``v, g0, g1, g2`` (gradient in 1/mm)."""
    v = 0.0
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    for p in range(begin, end):
        d0 = x0 - px[p]
        d1 = x1 - py[p]
        d2 = x2 - pz[p]
        r = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2) * inv_s2)
        value, slope, _ = wu_terms(coef[p], r, max(1.0 - r, 0.0))
        v += value
        g = slope * inv_s2
        g0 += g * d0
        g1 += g * d1
        g2 += g * d2
    return v, g0, g1, g2


@njit(fastmath=True, inline="always")
def _run_value_grad_hess(x0, x1, x2, px, py, pz, coef, begin, end, inv_s2):
    """:func:`_run_value_grad` and the Hessian.

    Returns
    -------
    tuple of 11 floats
        ``v, g0, g1, g2, gs, h00, h01, h02, h11, h12, h22``: value, gradient
        (1/mm) and the Hessian ``gs I + h`` (1/mm^2, ``h`` symmetric).
    """
    inv_s4 = inv_s2 * inv_s2
    v = 0.0
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    gs = 0.0
    a00 = 0.0
    a01 = 0.0
    a02 = 0.0
    a11 = 0.0
    a12 = 0.0
    a22 = 0.0
    for p in range(begin, end):
        d0 = x0 - px[p]
        d1 = x1 - py[p]
        d2 = x2 - pz[p]
        r = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2) * inv_s2)
        value, slope, curvature = wu_terms(coef[p], r, max(1.0 - r, 0.0))
        v += value
        g = slope * inv_s2
        # r = 0 only where d = 0, which zeroes h's terms: the floor only avoids 0/0.
        h = curvature / max(r, 1e-12) * inv_s4
        gs += g
        g0 += g * d0
        g1 += g * d1
        g2 += g * d2
        a00 += h * d0 * d0
        a01 += h * d0 * d1
        a02 += h * d0 * d2
        a11 += h * d1 * d1
        a12 += h * d1 * d2
        a22 += h * d2 * d2
    return v, g0, g1, g2, gs, a00, a01, a02, a11, a12, a22


@njit(inline="always")
def _add_value_grad(q, dim3, val, grad, v, g0, g1, g2):
    """Add one query's value and gradient sums to ``val`` (N, 1) and ``grad`` (N, 1, D)."""
    val[q, 0] += v
    grad[q, 0, 0] += g0
    grad[q, 0, 1] += g1
    if dim3:
        grad[q, 0, 2] += g2


@njit(inline="always")
def _add_value_grad_hess(q, dim3, val, grad, hess, v, g0, g1, g2, gs, a00, a01, a02, a11, a12, a22):
    """Add one query's sums (as :func:`_run_value_grad_hess` returns them) to ``val``
    (N, 1), ``grad`` (N, 1, D) and ``hess`` (N, 1, D, D)."""
    val[q, 0] += v
    grad[q, 0, 0] += g0
    grad[q, 0, 1] += g1
    hess[q, 0, 0, 0] += gs + a00
    hess[q, 0, 0, 1] += a01
    hess[q, 0, 1, 0] += a01
    hess[q, 0, 1, 1] += gs + a11
    if dim3:
        grad[q, 0, 2] += g2
        hess[q, 0, 0, 2] += a02
        hess[q, 0, 2, 0] += a02
        hess[q, 0, 1, 2] += a12
        hess[q, 0, 2, 1] += a12
        hess[q, 0, 2, 2] += gs + a22


@njit(fastmath=True, inline="always")
def _ranges_value(x0, x1, x2, px, py, pz, coef, ranges, nr, inv_s2):
    """Value of the kernel sum at one query over its ``nr`` candidate runs of centres."""
    v = 0.0
    for rr in range(nr):
        v += _run_value(x0, x1, x2, px, py, pz, coef, ranges[rr, 0], ranges[rr, 1], inv_s2)
    return v


@njit(fastmath=True, inline="always")
def _ranges_value_grad(q, dim3, val, grad, x0, x1, x2, px, py, pz, coef, ranges, nr, inv_s2):
    """Value and gradient of the kernel sum at one query over its ``nr`` candidate runs of
    centres (:func:`_run_value_grad`), added into row ``q`` of the outputs."""
    v = g0 = g1 = g2 = 0.0
    for rr in range(nr):
        dv, d0, d1, d2 = _run_value_grad(x0, x1, x2, px, py, pz, coef, ranges[rr, 0], ranges[rr, 1], inv_s2)
        v += dv
        g0 += d0
        g1 += d1
        g2 += d2
    _add_value_grad(q, dim3, val, grad, v, g0, g1, g2)


@njit(fastmath=True, inline="always")
def _ranges_value_grad_hess(q, dim3, val, grad, hess, x0, x1, x2, px, py, pz, coef, ranges, nr, inv_s2):
    """Value, gradient and Hessian of the kernel sum at one query over its ``nr`` candidate
    runs of centres (:func:`_run_value_grad_hess`), added into row ``q`` of the outputs."""
    v = g0 = g1 = g2 = gs = a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    for rr in range(nr):
        r = _run_value_grad_hess(x0, x1, x2, px, py, pz, coef, ranges[rr, 0], ranges[rr, 1], inv_s2)
        v += r[0]
        g0 += r[1]
        g1 += r[2]
        g2 += r[3]
        gs += r[4]
        a00 += r[5]
        a01 += r[6]
        a02 += r[7]
        a11 += r[8]
        a12 += r[9]
        a22 += r[10]
    _add_value_grad_hess(q, dim3, val, grad, hess, v, g0, g1, g2, gs, a00, a01, a02, a11, a12, a22)


# --------------------------------------------------------------------------------------
# The kernel-sum loops (which serves which case: ``volreg.kernels.sums._BLOCKED``)


@njit(nogil=True, fastmath=True)
def _blocked_sum(part, parts, queries, bstarts, px, py, pz, coef, start, lo, cell, dims, sigma, val, grad):
    """Kernel sums up to order 1 for scalar coefficients, one neighbour search per block of queries.

    The centres within ``sigma`` of a block's bounding box are gathered once into
    contiguous arrays (:func:`_gather_block`), then every query of the block runs
    one branch-free SIMD loop over them.  Blocks in parallel, ``_SUPER`` per work item.

    Parameters
    ----------
    queries : (N, D) float ndarray, mm
    bstarts : (n_blocks + 1,) int64 ndarray
        Blocks from :func:`_query_blocks`.
    px, py, pz : (M,) float ndarray, mm
        Centre coordinates in grid order (``pz`` zeros in 2-D).
    coef : (M, 1) float ndarray
        Coefficients in grid order.
    start, lo, cell, dims
        The :class:`~volreg.kernels.grid.CellGrid` (radius >= sigma).
    sigma : float, mm
    val, grad : (N, 1), (N, 1, D) float ndarray
        Added to; the gradient is computed when ``grad`` has N rows.
    """
    n, dim = queries.shape
    dim3 = dim == 3
    inv_s2 = 1.0 / (sigma * sigma)
    want_grad = grad.shape[0] == n
    n_blocks = bstarts.shape[0] - 1
    first, stop = part_range((n_blocks + _SUPER - 1) // _SUPER, part, parts)
    for sb in range(first, stop):
        buf = np.empty((6, 256))  # gathered candidates, grown as needed
        for b in range(sb * _SUPER, min(n_blocks, (sb + 1) * _SUPER)):
            q0 = bstarts[b]
            q1 = bstarts[b + 1]
            buf, c = _gather_block(queries, q0, q1, dim3, px, py, pz, coef, start, lo, cell, dims, sigma, buf)
            if c == 0:
                continue
            cx = buf[0]
            cy = buf[1]
            cz = buf[2]
            ca = buf[3]
            for q in range(q0, q1):
                x0 = queries[q, 0]
                x1 = queries[q, 1]
                x2 = queries[q, 2] if dim3 else 0.0
                if want_grad:
                    v, g0, g1, g2 = _run_value_grad(x0, x1, x2, cx, cy, cz, ca, 0, c, inv_s2)
                    _add_value_grad(q, dim3, val, grad, v, g0, g1, g2)
                else:
                    val[q, 0] += _run_value(x0, x1, x2, cx, cy, cz, ca, 0, c, inv_s2)


@njit(nogil=True, fastmath=True)
def _blocked_sum_hessian(part, parts, queries, bstarts, px, py, pz, coef, start, lo, cell, dims, sigma, val, grad, hess):
    """:func:`_blocked_sum` at order 2: adds to ``val`` (N, 1), ``grad`` (N, 1, D) and
    ``hess`` (N, 1, D, D).

    A loop of its own rather than an order-2 branch of :func:`_blocked_sum`: with the
    branch, a process that compiles the loop (rather than loading it from numba's
    on-disk cache) rounds the Hessian sums differently in the last bits.
    """
    dim = queries.shape[1]
    dim3 = dim == 3
    inv_s2 = 1.0 / (sigma * sigma)
    n_blocks = bstarts.shape[0] - 1
    first, stop = part_range((n_blocks + _SUPER - 1) // _SUPER, part, parts)
    for sb in range(first, stop):
        buf = np.empty((6, 256))  # gathered candidates, grown as needed
        for b in range(sb * _SUPER, min(n_blocks, (sb + 1) * _SUPER)):
            q0 = bstarts[b]
            q1 = bstarts[b + 1]
            buf, c = _gather_block(queries, q0, q1, dim3, px, py, pz, coef, start, lo, cell, dims, sigma, buf)
            if c == 0:
                continue
            cx = buf[0]
            cy = buf[1]
            cz = buf[2]
            ca = buf[3]
            for q in range(q0, q1):
                x2 = queries[q, 2] if dim3 else 0.0
                r = _run_value_grad_hess(queries[q, 0], queries[q, 1], x2, cx, cy, cz, ca, 0, c, inv_s2)
                _add_value_grad_hess(q, dim3, val, grad, hess, r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7],
                                     r[8], r[9], r[10])


@njit(nogil=True, fastmath=True)
def _blocked_sum_vector(part, parts, queries, bstarts, px, py, pz, coef, start, lo, cell, dims, sigma, val, grad):
    """:func:`_blocked_sum` for 2- or 3-vector coefficients (warps), order 0 or 1.

    Parameters as :func:`_blocked_sum`, with ``coef`` (M, m), ``val`` (N, m) and
    ``grad`` (N, m, D); the gradient is computed when ``grad`` has N rows.  The
    twelve sums over the candidates are written out here rather than returned by
    an inlined helper like :func:`_run_value_grad`: with the helper the loop ran a few
    per cent slower.
    """
    n, dim = queries.shape
    m = coef.shape[1]
    dim3 = dim == 3
    inv_s2 = 1.0 / (sigma * sigma)
    want_grad = grad.shape[0] == n
    n_blocks = bstarts.shape[0] - 1
    first, stop = part_range((n_blocks + _SUPER - 1) // _SUPER, part, parts)
    for sb in range(first, stop):
        buf = np.empty((6, 256))  # gathered candidates, grown as needed
        for b in range(sb * _SUPER, min(n_blocks, (sb + 1) * _SUPER)):
            q0 = bstarts[b]
            q1 = bstarts[b + 1]
            buf, c = _gather_block(queries, q0, q1, dim3, px, py, pz, coef, start, lo, cell, dims, sigma, buf)
            if c == 0:
                continue
            cx = buf[0]
            cy = buf[1]
            cz = buf[2]
            c0 = buf[3]
            c1 = buf[4]
            c2 = buf[5]
            for q in range(q0, q1):
                x0 = queries[q, 0]
                x1 = queries[q, 1]
                x2 = queries[q, 2] if dim3 else 0.0
                v0 = 0.0
                v1 = 0.0
                v2 = 0.0
                g00 = 0.0
                g01 = 0.0
                g02 = 0.0
                g10 = 0.0
                g11 = 0.0
                g12 = 0.0
                g20 = 0.0
                g21 = 0.0
                g22 = 0.0
                if want_grad:
                    for p in range(c):
                        d0 = x0 - cx[p]
                        d1 = x1 - cy[p]
                        d2 = x2 - cz[p]
                        r = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2) * inv_s2)
                        k, slope, _ = wu_terms(1.0, r, max(1.0 - r, 0.0))
                        g = slope * inv_s2
                        a0 = c0[p]
                        a1 = c1[p]
                        a2 = c2[p]
                        v0 += a0 * k
                        v1 += a1 * k
                        v2 += a2 * k
                        e0 = g * d0
                        e1 = g * d1
                        e2 = g * d2
                        g00 += a0 * e0
                        g01 += a0 * e1
                        g02 += a0 * e2
                        g10 += a1 * e0
                        g11 += a1 * e1
                        g12 += a1 * e2
                        g20 += a2 * e0
                        g21 += a2 * e1
                        g22 += a2 * e2
                else:
                    for p in range(c):
                        d0 = x0 - cx[p]
                        d1 = x1 - cy[p]
                        d2 = x2 - cz[p]
                        r = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2) * inv_s2)
                        k = wu_terms(1.0, r, max(1.0 - r, 0.0))[0]
                        v0 += c0[p] * k
                        v1 += c1[p] * k
                        v2 += c2[p] * k
                val[q, 0] += v0
                val[q, 1] += v1
                if m == 3:
                    val[q, 2] += v2
                if want_grad:
                    grad[q, 0, 0] += g00
                    grad[q, 0, 1] += g01
                    grad[q, 1, 0] += g10
                    grad[q, 1, 1] += g11
                    if dim3:
                        grad[q, 0, 2] += g02
                        grad[q, 1, 2] += g12
                    if m == 3:
                        grad[q, 2, 0] += g20
                        grad[q, 2, 1] += g21
                        if dim3:
                            grad[q, 2, 2] += g22


@njit(nogil=True)
def _strict_sum(part, parts, queries, gpts, gcoef, start, lo, cell, dims, max_runs, sigma, order, val, grad, hess):
    """Kernel sums for any number of coefficient columns and any order (strict arithmetic).

    Parameters
    ----------
    queries : (N, D) float ndarray, mm
    gpts : (M, D) float ndarray, mm
        Centres in grid order.
    gcoef : (M, m) float ndarray
        Coefficients in grid order.
    start, lo, cell, dims
        The :class:`~volreg.kernels.grid.CellGrid` (radius >= sigma).
    max_runs : int
        :func:`volreg.kernels.grid.max_runs`.
    sigma : float, mm
    order : {0, 1, 2}
    val, grad, hess : (N, m), (N, m, D), (N, m, D, D) float ndarray
        Added to, up to ``order`` (unused ones may be dummies).
    """
    n, dim = queries.shape
    m = gcoef.shape[1]
    inv_s2 = 1.0 / (sigma * sigma)
    n_blocks = (n + _BLOCK - 1) // _BLOCK
    first, stop = part_range(n_blocks, part, parts)
    for blk in range(first, stop):
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
                    k, slope, curvature = wu_terms(1.0, r, 1.0 - r)
                    for j in range(m):
                        val[q, j] += gcoef[p, j] * k
                    if order >= 1:
                        g = slope * inv_s2
                        for j in range(m):
                            cg = gcoef[p, j] * g
                            for a in range(dim):
                                grad[q, j, a] += cg * d[a]
                        if order >= 2:
                            h = 0.0
                            if r > 0.0:
                                h = curvature / r * inv_s2 * inv_s2
                            for j in range(m):
                                cj = gcoef[p, j]
                                for a in range(dim):
                                    hess[q, j, a, a] += cj * g
                                    for b in range(dim):
                                        hess[q, j, a, b] += cj * h * d[a] * d[b]


# --------------------------------------------------------------------------------------
# Kernel matrices and products with matrices sharing one sparsity pattern


@njit(nogil=True)
def _grid_pairs(part, parts, queries, gpts, gorder, start, lo, cell, dims, max_runs, sigma, indptr, indices, data, fill):
    """Count or write the rows of the sparse kernel matrix ``k(|queries_i - gpts_j| / sigma)``.

    With ``fill`` False, writes each row's entry count into ``indptr[1:]``; with
    ``fill`` True, writes the column (``gorder[p]``, the original index) and value
    (``data`` float32: computed in double precision, stored rounded) of every entry at
    ``indptr[row]`` onwards.
    """
    n, dim = queries.shape
    sigma2 = sigma * sigma
    n_blocks = (n + _BLOCK - 1) // _BLOCK
    first, stop = part_range(n_blocks, part, parts)
    for blk in range(first, stop):
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
                            indices[w] = gorder[p]
                            data[w] = wu_terms(1.0, r, 1.0 - r)[0]
                        w += 1
            if not fill:
                indptr[q + 1] = w


@njit(nogil=True)
def _csr_matmul_shared(part, parts, indptr, indices, data, x, out):
    """``out[i, a, b] = sum_e data[e, b] x[indices[e], a]`` over row i's entries.

    B <= 3 sparse matrices sharing one CSR pattern (``data`` (nnz, B)) times ``x``
    (M, k <= 3), into ``out`` (N, k, B): rows ``part_range(N, part, parts)``, nine scalar
    accumulators per row.
    """
    n = indptr.shape[0] - 1
    nb = data.shape[1]
    k = x.shape[1]
    first, stop = part_range(n, part, parts)
    for i in range(first, stop):
        s00 = s01 = s02 = s10 = s11 = s12 = s20 = s21 = s22 = 0.0
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            x0 = x[j, 0]
            x1 = x[j, 1] if k > 1 else 0.0
            x2 = x[j, 2] if k > 2 else 0.0
            d0 = data[e, 0]
            s00 += d0 * x0
            s10 += d0 * x1
            s20 += d0 * x2
            if nb > 1:
                d1 = data[e, 1]
                s01 += d1 * x0
                s11 += d1 * x1
                s21 += d1 * x2
            if nb > 2:
                d2 = data[e, 2]
                s02 += d2 * x0
                s12 += d2 * x1
                s22 += d2 * x2
        acc = ((s00, s01, s02), (s10, s11, s12), (s20, s21, s22))
        for a in range(k):
            for b in range(nb):
                out[i, a, b] = acc[a][b]


@njit(nogil=True)
def _csr_matmul_shared_sum(part, parts, indptr, indices, data, y, out):
    """``out[i, a] = sum_e sum_b data[e, b] y[indices[e], a, b]``, i.e. ``sum_b A_b @ y[:, :, b]``.

    B <= 3 matrices sharing one CSR pattern (``data`` (nnz, B)), ``y`` (M, k <= 3, B), into
    ``out`` (N, k): rows ``part_range(N, part, parts)``.
    """
    n = indptr.shape[0] - 1
    nb = data.shape[1]
    k = y.shape[1]
    first, stop = part_range(n, part, parts)
    for i in range(first, stop):
        s0 = s1 = s2 = 0.0
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            for b in range(nb):
                d = data[e, b]
                s0 += d * y[j, 0, b]
                if k > 1:
                    s1 += d * y[j, 1, b]
                if k > 2:
                    s2 += d * y[j, 2, b]
        out[i, 0] = s0
        if k > 1:
            out[i, 1] = s1
        if k > 2:
            out[i, 2] = s2


# --------------------------------------------------------------------------------------
# Row permutations


@njit(nogil=True)
def _take_rows(part, parts, x, perm, out):
    """Part ``part`` of ``parts`` of ``out[:] = x[perm]`` (:func:`take_rows`)."""
    first, stop = part_range(perm.shape[0], part, parts)
    for i in range(first, stop):
        for a in range(x.shape[1]):
            out[i, a] = x[perm[i], a]


@njit(nogil=True)
def _put_rows(part, parts, src, perm, out):
    """Part ``part`` of ``parts`` of ``out[perm] = src`` (:func:`put_rows`)."""
    first, stop = part_range(perm.shape[0], part, parts)
    for i in range(first, stop):
        for a in range(src.shape[1]):
            out[perm[i], a] = src[i, a]


def take_rows(x: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """``x[perm]`` for a 2-D array, on volreg's threads.

    Parameters
    ----------
    x : (M, k) ndarray
    perm : (N,) int ndarray

    Returns
    -------
    (N, k) ndarray, dtype of ``x``
    """
    out = np.empty((perm.shape[0], x.shape[1]), dtype=x.dtype)
    run_parts(_take_rows, perm.shape[0], x, perm, out, grain=4096)
    return out


def put_rows(src: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """The inverse of :func:`take_rows`: ``out[perm] = src``, on volreg's threads.

    Parameters
    ----------
    src : (N, k) ndarray
    perm : (N,) int ndarray
        A permutation of ``range(N)``.

    Returns
    -------
    (N, k) ndarray, dtype of ``src``
    """
    out = np.empty_like(src)
    run_parts(_put_rows, perm.shape[0], src, perm, out, grain=4096)
    return out


# --------------------------------------------------------------------------------------
# Many scalar kernel sums, each at its own few queries, in one parallel loop


@njit(nogil=True, fastmath=True)
def segmented_sums(part, parts, queries, rstart, jstart, poff, soff, px, py, pz, coef, sstart, lo, cell, dims, sigma,
                   max_runs, order, val, grad, hess):
    """Add kernel sums of several point sets, each at its own segment of the queries.

    Segment ``f`` (queries ``rstart[f]:rstart[f + 1]``) gets the sums of the jobs
    ``jstart[f]:jstart[f + 1]`` in turn; job ``j`` is one CellGrid's points
    ``poff[j]:poff[j + 1]`` of ``px``, ``py``, ``pz`` with coefficients ``coef`` (in
    grid order), cell starts ``sstart[soff[j]:soff[j + 1]]`` (relative to ``poff[j]``),
    corner ``lo[j]``, cell edge ``cell[j]``, cells ``dims[j]`` and width ``sigma[j]``.
    Per query the sums are those of :func:`_blocked_sum` and
    :func:`_blocked_sum_hessian`, with one neighbour search per query and job.  The
    queries in parallel, ``part_range(N, part, parts)`` of them per part, whichever
    segments they fall in (one segment may hold most of them: a large label among small
    ones); ``val`` (N, 1), ``grad`` (N, 1, D) and ``hess`` (N, 1, D, D) as there
    (``order`` 0, 1 or 2 says which are filled).
    """
    dim = queries.shape[1]
    dim3 = dim == 3
    first, stop = part_range(rstart[rstart.shape[0] - 1], part, parts)
    ranges = np.empty((max_runs, 2), dtype=np.int64)
    nf = rstart.shape[0] - 1
    f = 0
    while f < nf and rstart[f + 1] <= first:  # the segment holding the part's first query
        f += 1
    for f in range(f, nf):
        q0, q1 = max(rstart[f], first), min(rstart[f + 1], stop)
        if q0 >= stop:
            break
        for j in range(jstart[f], jstart[f + 1]):
            p0, p1 = poff[j], poff[j + 1]
            gx = px[p0:p1]
            gy = py[p0:p1]
            gz = pz[p0:p1]
            gc = coef[p0:p1]
            start = sstart[soff[j]:soff[j + 1]]
            width = sigma[j]
            inv_s2 = 1.0 / (width * width)
            for q in range(q0, q1):
                x = queries[q]
                nr = _candidate_ranges(x, lo[j], cell[j], dims[j], width, start, ranges)
                x0 = x[0]
                x1 = x[1]
                x2 = x[2] if dim3 else 0.0
                if order == 2:
                    _ranges_value_grad_hess(q, dim3, val, grad, hess, x0, x1, x2, gx, gy, gz, gc, ranges, nr, inv_s2)
                elif order == 1:
                    _ranges_value_grad(q, dim3, val, grad, x0, x1, x2, gx, gy, gz, gc, ranges, nr, inv_s2)
                else:
                    val[q, 0] += _ranges_value(x0, x1, x2, gx, gy, gz, gc, ranges, nr, inv_s2)

"""Wu kernel (13): closed forms, neighbour sums against a KD-tree oracle, sparse matrices."""

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from volreg.kernels import (
    CellGrid,
    SharedPatternCSR,
    kernel_gradient_matrices,
    kernel_matrix,
    kernel_sum,
    kernel_sum_reference,
    wu,
    wu_derivatives,
)
from volreg.kernels._compiled import _MIN_MEAN_BLOCK, _QBLOCK, _query_blocks
from volreg.kernels.sums import _BLOCKED
from volreg.kernels.wu import wu_slope


def test_wu_profile_values():
    assert wu(0.0) == pytest.approx(4.0)
    assert wu(1.0) == 0.0
    assert np.all(wu(np.array([1.0, 1.5, 10.0])) == 0.0)
    # Strictly decreasing on [0, 1).
    r = np.linspace(0, 1, 101)
    assert np.all(np.diff(wu(r)) < 0)


def test_wu_is_c2_at_the_support_boundary():
    # k, k' and k'' vanish at r = 1 (C^2), checked by one-sided finite differences.
    h = 1e-4
    r = 1.0 - np.array([0.0, h, 2 * h])
    k = wu(r)
    assert abs(k[0]) < 1e-12
    assert abs((k[0] - k[1]) / h) < 1e-6
    assert abs((k[0] - 2 * k[1] + k[2]) / h**2) < 1e-3


def test_wu_slope_is_the_derivative_over_r():
    # g(r) = k'(r) / r, by central differences; g(0) = -56, g = 0 outside the support.
    r = np.linspace(0.05, 0.95, 19)
    h = 1e-6
    np.testing.assert_allclose(wu_slope(r) * r, (wu(r + h) - wu(r - h)) / (2 * h), rtol=0, atol=1e-7)
    assert wu_slope(0.0) == -56.0
    assert np.all(wu_slope(np.array([1.0, 2.0])) == 0.0)


def test_the_blocked_loops_serve_scalars_to_order_2_and_vectors_to_order_1():
    assert set(_BLOCKED) == {("scalar", 0), ("scalar", 1), ("scalar", 2), ("vector", 0), ("vector", 1)}


@pytest.mark.parametrize("n", [0, 1, 37, 3000])
@pytest.mark.parametrize("order", [0, 1, 2])
@pytest.mark.parametrize("m", [None, 3])
def test_unsorted_queries_are_summed_in_their_own_order(n, order, m):
    # Queries in random order (no blocks of nearby ones) are sorted for the blocked loops and
    # their sums added back row by row, into what `out` already holds.
    rng = np.random.default_rng(7)
    centres = rng.uniform(0, 10, (700, 3))
    coeffs = rng.normal(size=700 if m is None else (700, m))
    queries = rng.uniform(-2, 12, (n, 3))
    slow = [a[:n] for a in kernel_sum_reference(queries if n else np.zeros((1, 3)), centres, coeffs, 2.3, order=order)]
    out = tuple(np.ones(a.shape) for a in slow)
    fast = kernel_sum(queries, centres, coeffs, 2.3, order=order, out=out)
    for a, b in zip(fast, slow):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b + 1.0, rtol=0, atol=1e-11)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("m", [None, 1, 3, 4])
def test_kernel_sum_matches_kdtree_reference(dim, m):
    rng = np.random.default_rng(1)
    centres = rng.uniform(0, 10, (800, dim))
    coeffs = rng.normal(size=800 if m is None else (800, m))
    queries = rng.uniform(-3, 13, (1500, dim))
    fast = kernel_sum(queries, centres, coeffs, 1.7, order=2)
    slow = kernel_sum_reference(queries, centres, coeffs, 1.7, order=2, memory_budget=2e5)
    for a, b in zip(fast, slow):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-11)


@pytest.mark.parametrize("dim", [2, 3])
def test_gradient_and_hessian_match_finite_differences(dim):
    rng = np.random.default_rng(2)
    centres = rng.uniform(0, 10, (600, dim))
    coeffs = rng.normal(size=600)
    x = rng.uniform(3, 7, (20, dim))
    sigma, h = 2.5, 1e-5
    _, grad, hess = kernel_sum(x, centres, coeffs, sigma, order=2)
    for a in range(dim):
        e = np.zeros(dim)
        e[a] = h
        fp, gp = kernel_sum(x + e, centres, coeffs, sigma, order=1)
        fm, gm = kernel_sum(x - e, centres, coeffs, sigma, order=1)
        np.testing.assert_allclose((fp - fm) / (2 * h), grad[:, a], rtol=0, atol=1e-5 * np.abs(grad).max())
        np.testing.assert_allclose((gp - gm) / (2 * h), hess[:, :, a], rtol=0, atol=1e-5 * np.abs(hess).max())


def test_hessian_is_symmetric_and_finite_at_a_centre():
    centres = np.array([[0.0, 0.0, 0.0], [0.5, 0.2, 0.1]])
    _, _, hess = kernel_sum(centres, centres, np.array([1.0, -2.0]), 1.0, order=2)
    assert np.all(np.isfinite(hess))
    np.testing.assert_allclose(hess, np.swapaxes(hess, 1, 2), atol=1e-12)
    # At r = 0 the kernel's Hessian is g(0) I / sigma^2 = -56 I.
    value, _, h0 = wu_derivatives(np.zeros((1, 3)), 1.0)
    assert value[0] == pytest.approx(4.0)
    np.testing.assert_allclose(h0[0], -56.0 * np.eye(3))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("order", [0, 1, 2])
@pytest.mark.parametrize("grid_radius", [1.7, 3.0])
@pytest.mark.parametrize("m", [None, 2, 3])
def test_blocked_sum_of_spatially_sorted_queries_matches_reference(dim, order, grid_radius, m):
    # Many queries visited cell by cell take the blocked path (one gathered candidate
    # list per block of nearby queries); some blocks lie partly or wholly off the grid.
    # Scalar coefficients (implicit surfaces) and 2-/3-vectors (warps).
    rng = np.random.default_rng(4)
    centres = rng.uniform(0, 10, (900, dim))
    coeffs = rng.normal(size=900 if m is None else (900, m))
    queries = rng.uniform(-2, 12, (6000 if dim == 2 else 40000, dim))
    queries = np.concatenate([queries, centres[:50]])  # r = 0 in the Hessian's h / r
    queries = queries[CellGrid.build(queries, 0.5 * 1.7).order]  # cell by cell, as spatial_order
    blocks = _query_blocks(queries, 0.5 * 1.7, _QBLOCK)
    assert len(queries) >= _MIN_MEAN_BLOCK * (len(blocks) - 1)  # the blocked path is taken
    fast = kernel_sum(queries, CellGrid.build(centres, grid_radius), coeffs, 1.7, order=order)
    slow = kernel_sum_reference(queries, centres, coeffs, 1.7, order=order)
    assert np.any(fast[0] == 0) and np.any(fast[0] != 0)
    for a, b in zip(fast, slow):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-11)
    # The same values whatever the query order (within rounding).
    shuffled = rng.permutation(len(queries))
    np.testing.assert_allclose(kernel_sum(queries[shuffled], centres, coeffs, 1.7)[0], fast[0][shuffled],
                               rtol=0, atol=1e-11)


def test_queries_beyond_the_support_get_zero():
    centres = np.zeros((1, 3))
    far = np.array([[2.0, 0, 0], [0, -1.0, 0], [100.0, 100.0, 100.0]])
    value, grad = kernel_sum(far, centres, np.ones(1), 1.0, order=1)
    assert np.all(value == 0) and np.all(grad == 0)


def test_prebuilt_grid_reorders_coefficients():
    rng = np.random.default_rng(3)
    centres = rng.uniform(0, 5, (300, 3))
    coeffs = rng.normal(size=300)
    q = rng.uniform(0, 5, (100, 3))
    grid = CellGrid.build(centres, 1.2)
    np.testing.assert_allclose(kernel_sum(q, grid, coeffs, 1.2)[0], kernel_sum(q, centres, coeffs, 1.2)[0])
    with pytest.raises(ValueError, match="radius >= sigma"):
        kernel_sum(q, grid, coeffs, 2.0)


@settings(max_examples=25, deadline=None)
@given(
    shift=st.tuples(*[st.floats(-1e3, 1e3)] * 3),
    sigma=st.floats(0.5, 5.0),
)
def test_kernel_sum_is_translation_invariant(shift, sigma):
    rng = np.random.default_rng(4)
    centres = rng.uniform(0, 6, (200, 3))
    coeffs = rng.normal(size=200)
    q = rng.uniform(0, 6, (50, 3))
    t = np.array(shift)
    a = kernel_sum(q, centres, coeffs, sigma, order=1)
    b = kernel_sum(q + t, centres + t, coeffs, sigma, order=1)
    scale = 1 + np.abs(t).max() / sigma
    for u, v in zip(a, b):
        np.testing.assert_allclose(u, v, atol=1e-9 * scale * np.abs(coeffs).sum())


@pytest.mark.parametrize("dim", [2, 3])
def test_kernel_matrix_matches_dense(dim):
    rng = np.random.default_rng(5)
    a = rng.uniform(0, 8, (300, dim))
    b = rng.uniform(0, 8, (250, dim))
    k = kernel_matrix(a, b, 1.9)
    dense = wu(np.linalg.norm(a[:, None] - b[None], axis=2) / 1.9)
    # The values are stored rounded to single precision: within half a float32 ulp (2**-24 relative).
    np.testing.assert_allclose(k.toarray(), dense, rtol=2.0**-24, atol=1e-14)
    k32 = kernel_matrix(a, b, 1.9, dtype=np.float32)
    assert k32.dtype == np.float32 and k.dtype == np.float64
    assert np.array_equal(k32.indptr, k.indptr) and np.array_equal(k32.indices, k.indices)
    assert np.array_equal(k32.data.astype(np.float64), k.data)
    with pytest.raises(ValueError, match="dtype"):
        kernel_matrix(a, b, 1.9, dtype=np.float16)
    sym = kernel_matrix(a, a, 1.9)
    assert abs(sym - sym.T).max() == 0
    np.testing.assert_allclose(sym.diagonal(), 4.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_kernel_gradient_matrices_match_the_kernel_sum_gradient(dim):
    rng = np.random.default_rng(6)
    rows = rng.uniform(0, 8, (200, dim))
    cols = rng.uniform(0, 8, (250, dim))
    coeffs = rng.normal(size=250)
    mats = kernel_gradient_matrices(rows, cols, 1.9)
    assert len(mats) == dim
    assert all((g.indptr == mats[0].indptr).all() and (g.indices == mats[0].indices).all() for g in mats)
    _, grad = kernel_sum(rows, cols, coeffs, 1.9, order=1)
    np.testing.assert_allclose(np.stack([g @ coeffs for g in mats], axis=1), grad, rtol=0, atol=1e-12)


def test_bad_arguments_are_named():
    c = np.zeros((5, 3))
    with pytest.raises(ValueError, match="`queries` of shape"):
        kernel_sum(np.zeros((4, 2)), c, np.ones(5), 1.0)
    with pytest.raises(ValueError, match="`coeffs`"):
        kernel_sum(np.zeros((4, 3)), c, np.ones(4), 1.0)
    with pytest.raises(ValueError, match="`sigma`"):
        kernel_sum(np.zeros((4, 3)), c, np.ones(5), 0.0)
    with pytest.raises(ValueError, match="`order`"):
        kernel_sum(np.zeros((4, 3)), c, np.ones(5), 1.0, order=3)
    with pytest.raises(ValueError, match="finite values in `queries`"):
        kernel_sum(np.full((1, 3), np.nan), c, np.ones(5), 1.0)


def test_shared_pattern_products_match_scipy():
    rng = np.random.default_rng(7)
    pattern = sp.random(300, 200, density=0.05, random_state=8, format="csr")
    mats = [sp.csr_matrix((rng.normal(size=pattern.nnz), pattern.indices, pattern.indptr), shape=pattern.shape)
            for _ in range(3)]
    shared = SharedPatternCSR(mats)
    for k in (1, 2, 3):
        x = rng.normal(size=(200, k))
        y = rng.normal(size=(300, k, 3))
        np.testing.assert_allclose(shared.matmul(x), np.stack([a @ x for a in mats], axis=2), rtol=0, atol=1e-12)
        np.testing.assert_allclose(shared.rmatmul_sum(y), sum(a.T @ y[:, :, b] for b, a in enumerate(mats)),
                                   rtol=0, atol=1e-12)
    one = SharedPatternCSR(mats[:1])
    np.testing.assert_allclose(one.matmul(x)[:, :, 0], mats[0] @ x, rtol=0, atol=1e-12)
    other = sp.random(300, 200, density=0.05, random_state=9, format="csr")
    with pytest.raises(ValueError, match="share one sparsity pattern"):
        SharedPatternCSR([mats[0], other])


@pytest.mark.parametrize("dim", [2, 3])
def test_column_bounds_and_rows_within_equal_numpy_reductions(dim):
    from volreg.kernels.grid import column_bounds, rows_within

    rng = np.random.default_rng(dim)
    points = rng.normal(size=(1000, dim))
    lo, hi = column_bounds(points)
    np.testing.assert_array_equal(lo, points.min(axis=0))
    np.testing.assert_array_equal(hi, points.max(axis=0))
    box_lo, box_hi = np.full(dim, -0.5), np.full(dim, 0.7)
    points[:5] = box_lo  # on the box's faces: inside
    expected = np.all((points >= box_lo) & (points <= box_hi), axis=1)
    assert expected.any() and not expected.all()
    np.testing.assert_array_equal(rows_within(points, box_lo, box_hi), expected)
    open_box = np.all((points > box_lo) & (points < box_hi), axis=1)
    assert not open_box[:5].any()  # the faces are outside the open box
    np.testing.assert_array_equal(rows_within(points, box_lo, box_hi, closed=False), open_box)
    points[7, 0] = np.nan
    assert np.isnan(column_bounds(points)[0][0]) and not rows_within(points, box_lo, box_hi)[7]


def test_spatial_order_threshold_is_a_parameter():
    from volreg.kernels.grid import SORT_ABOVE, spatial_order

    points = np.random.default_rng(0).uniform(0, 50, (500, 3))
    assert 500 <= SORT_ABOVE and spatial_order(points, 5.0) is None
    perm = spatial_order(points, 5.0, above=100)
    assert sorted(perm.tolist()) == list(range(500))
    cells = np.floor((points[perm] - points.min(axis=0)) / 5.0).astype(int)
    # Visited cell by cell: each cell's points are consecutive.
    keys = [tuple(c) for c in cells]
    runs = sum(1 for a, b in zip(keys, keys[1:]) if a != b) + 1
    assert runs == len(set(keys))

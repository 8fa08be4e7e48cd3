"""Voxel grids (volreg.grid.Grid): index <-> world, chunked traversal, and LabelVolume's grid."""

from __future__ import annotations

import numpy as np
import pytest
from shapes import rotation

from volreg.errors import GeometryError
from volreg.features.implicit import ImplicitSurface
from volreg.features.label_surfaces import implicit_on_grid
from volreg.grid import Grid, LabelVolume, apply_affine, as_grid
from volreg.warp.field import (
    displacement_on_grid,
    fields_on_grid,
    jacobian_determinant_on_grid,
)
from volreg.warp.model import KernelWarp, WarpLevel
from volreg.warp.resample import resample_image

# Orientations of the index axes in the LPS world frame (columns of `direction`):
# "RAS" means index i runs to the patient's right (-x in LPS), j anterior (-y), k superior (+z).
ORIENTATIONS = {
    "LPS": np.eye(3),
    "RAS": np.diag([-1.0, -1.0, 1.0]),
    "LAS": np.diag([1.0, -1.0, 1.0]),
    "oblique": rotation(25.0),
}
# World direction (LPS) of one step along each index axis, for the axis-aligned orientations.
STEP_SIGNS = {"LPS": (1, 1, 1), "RAS": (-1, -1, 1), "LAS": (1, -1, 1)}
SHAPE = (6, 5, 4)
SPACING = np.array([0.8, 1.1, 2.5])  # mm, anisotropic so that a swapped axis shows
ORIGIN = np.array([-31.0, 12.5, 7.25])  # mm

# Index -> world -> index is a product with an orthonormal matrix and back: a few ulps of
# the world coordinates (tens of mm), far below this (in voxels).
ROUND_TRIP_TOL_VOXELS = 1e-9


def _grid(orientation: str) -> Grid:
    return Grid(SHAPE, ORIGIN, SPACING, ORIENTATIONS[orientation])


@pytest.mark.parametrize("orientation", list(ORIENTATIONS))
def test_index_world_round_trip(orientation):
    grid = _grid(orientation)
    rng = np.random.default_rng(0)
    index = rng.uniform(-2.0, 8.0, (500, 3))  # continuous, some outside the grid
    world = grid.index_to_world(index)
    np.testing.assert_allclose(grid.world_to_index(world), index, rtol=0, atol=ROUND_TRIP_TOL_VOXELS)
    # the affine says the same as index_to_world
    homogeneous = np.column_stack([index, np.ones(len(index))]) @ grid.affine.T
    np.testing.assert_allclose(homogeneous[:, :3], world, atol=1e-9)
    np.testing.assert_allclose(homogeneous[:, 3], 1.0)
    # one step along index axis d moves spacing[d] mm along column d of the direction
    for d in range(3):
        step = grid.index_to_world(np.eye(3)[d][None]) - grid.index_to_world(np.zeros((1, 3)))
        np.testing.assert_allclose(step[0], SPACING[d] * ORIENTATIONS[orientation][:, d], atol=1e-12)
        if orientation in STEP_SIGNS:
            expected = np.zeros(3)
            expected[d] = STEP_SIGNS[orientation][d] * SPACING[d]
            np.testing.assert_allclose(step[0], expected, atol=1e-12)
    # and the grid comes back from its (shape, affine) pair
    again = Grid.from_affine(grid.shape, grid.affine)
    assert again.same_geometry(grid, atol=1e-12)


@pytest.mark.parametrize("orientation", list(ORIENTATIONS))
def test_grid_points_and_index_window(orientation):
    grid = _grid(orientation)
    points = grid.grid_points()
    assert points.shape == (*SHAPE, 3)
    np.testing.assert_allclose(points[2, 3, 1], grid.index_to_world(np.array([[2, 3, 1]]))[0], atol=1e-12)
    # every voxel centre is index_to_world of its index, to the last bit
    every = np.stack(np.meshgrid(*map(np.arange, SHAPE), indexing="ij"), axis=-1).reshape(-1, 3)
    np.testing.assert_array_equal(points.reshape(-1, 3), grid.index_to_world(every))
    # the window of the world box spanned by two voxel centres holds both
    a, b = points[1, 1, 1], points[3, 2, 2]
    window = grid.index_window(np.minimum(a, b), np.maximum(a, b))
    assert all(s.start <= i < s.stop for s, i in zip(window, (1, 1, 1)))
    assert all(s.start <= i < s.stop for s, i in zip(window, (3, 2, 2)))
    far = ORIGIN + 1e4
    assert grid.index_window(far, far + 1.0) is None


def test_round_trip_2d_flipped():
    swapped = np.array([[0.0, -1.0], [-1.0, 0.0]])  # index axes along -y and -x: a mirror (det -1)
    for d in (swapped, np.diag([1.0, -1.0]), rotation(0.0)[:2, :2]):
        grid = Grid((7, 3), (4.0, -2.0), (0.5, 1.5), d)
        index = np.random.default_rng(1).uniform(0, 7, (50, 2))
        np.testing.assert_allclose(grid.world_to_index(grid.index_to_world(index)), index, atol=1e-12)
        assert grid.ndim == 2 and grid.affine.shape == (3, 3)
        every = np.stack(np.meshgrid(np.arange(7), np.arange(3), indexing="ij"), axis=-1).reshape(-1, 2)
        np.testing.assert_array_equal(grid.grid_points().reshape(-1, 2), grid.index_to_world(every))


# ----------------------------------------------------------------------------- chunks


@pytest.mark.parametrize("n", [1, 7, 60, 10**6])
@pytest.mark.parametrize("window", [None, (slice(1, 5), slice(0, 5), slice(2, 3))], ids=["whole", "window"])
def test_chunks_cover_every_voxel_exactly_once(n, window):
    grid = _grid("oblique")
    count = np.zeros(SHAPE, dtype=int)
    indices, done = [], []
    for part in grid.chunks(n, window):
        assert 1 <= len(part.index) <= n
        assert part.index.shape == (len(part.index), 3) and part.points.shape == part.index.shape
        np.add.at(count.reshape(-1), part.flat, 1)
        np.testing.assert_array_equal(part.flat, np.ravel_multi_index(tuple(part.index.T), SHAPE))
        np.testing.assert_allclose(part.points, grid.grid_points()[tuple(part.index.T)], atol=1e-12)
        indices.append(part.index)
        done.append((part.done, part.total))
        alone = grid.chunk(part.done - len(part.index), part.done, window)  # the same chunk, made on its own
        for name in ("index", "flat", "points", "done", "total"):
            np.testing.assert_array_equal(getattr(alone, name), getattr(part, name))
    inside = np.zeros(SHAPE, dtype=bool)
    inside[window if window is not None else ...] = True
    np.testing.assert_array_equal(count, inside.astype(int))  # each voxel of the window once, nothing else
    np.testing.assert_array_equal(np.concatenate(indices), np.argwhere(inside))  # in C order
    total = int(inside.sum())
    assert [t for _, t in done] == [total] * len(done)
    assert [d for d, _ in done] == [min(k * n, total) for k in range(1, len(done) + 1)]


def test_chunks_of_an_empty_grid_and_bad_arguments():
    assert list(Grid((0, 4, 3), ORIGIN, SPACING, np.eye(3)).chunks(10)) == []
    grid = _grid("LPS")
    for bad in (0, -3, 2.5, True):
        with pytest.raises(GeometryError, match="Expected `n` to be a positive number of voxels"):
            next(grid.chunks(bad))
    for window in ((slice(0, 7), slice(0, 5), slice(0, 4)), (slice(0, 6), slice(0, 5)), (slice(0, 6, 2),) * 3):
        with pytest.raises(GeometryError, match="Expected `window` of 3 slices within the grid"):
            next(grid.chunks(10, window))
    for first, stop in ((-1, 3), (4, 2), (0, grid.shape[0] * grid.shape[1] * grid.shape[2] + 1)):
        with pytest.raises(GeometryError, match="Expected 0 <= `first` <= `stop`"):
            grid.chunk(first, stop)


# ----------------------------------------------------------------------------- LabelVolume and its grid


def test_label_volume_grid_same_geometry():
    array = np.random.default_rng(2).integers(0, 4, SHAPE).astype(np.uint16)
    vol = LabelVolume(array, ORIGIN, SPACING, ORIENTATIONS["oblique"])
    grid = vol.grid
    assert isinstance(grid, Grid) and grid.shape == vol.shape and grid.ndim == vol.ndim
    assert grid.same_geometry(vol) and vol.same_geometry(grid) and grid.same_geometry(_grid("oblique"))
    np.testing.assert_array_equal(grid.affine, vol.affine)
    shifted = Grid(SHAPE, ORIGIN + 1e-3, SPACING, ORIENTATIONS["oblique"])
    assert not vol.grid.same_geometry(shifted)
    assert vol.grid.same_geometry(shifted, atol=2e-3)
    assert not vol.grid.same_geometry(Grid((6, 5, 5), ORIGIN, SPACING, ORIENTATIONS["oblique"]))
    assert not vol.grid.same_geometry(_grid("RAS"))
    # a grid plus an array is a volume again
    back = grid.with_array(array)
    assert isinstance(back, LabelVolume) and back.same_geometry(vol) and back.array is array
    with pytest.raises(GeometryError, match=r"Expected `array` of shape \(6, 5, 4\), got \(6, 5\)"):
        grid.with_array(array[:, :, 0])
    # the volume's geometric methods are the grid's
    idx = np.array([[0.5, 1.0, 3.0]])
    np.testing.assert_array_equal(vol.index_to_world(idx), grid.index_to_world(idx))
    np.testing.assert_array_equal(vol.grid_points(), grid.grid_points())
    lo, hi = ORIGIN - 2.0, ORIGIN + 3.0
    assert vol.index_window(lo, hi) == grid.index_window(lo, hi)


BAD_GEOMETRY = {
    "origin length": ((1.0, 2.0), SPACING, np.eye(3), "Expected `origin` of length 3"),
    "negative spacing": (ORIGIN, (1.0, -1.0, 1.0), np.eye(3), "Expected `spacing` of 3 positive finite values"),
    "infinite origin": ((0.0, np.inf, 0.0), SPACING, np.eye(3), "Expected a finite `origin`"),
    "sheared direction": (ORIGIN, SPACING, [[1, 0.3, 0], [0, 1, 0], [0, 0, 1]], "Expected `direction` to be an orthonormal"),
}


@pytest.mark.parametrize("case", list(BAD_GEOMETRY))
def test_grid_and_volume_refuse_bad_geometry_with_one_message(case):
    origin, spacing, direction, match = BAD_GEOMETRY[case]
    with pytest.raises(GeometryError, match=match) as from_grid:
        Grid(SHAPE, origin, spacing, direction)
    with pytest.raises(GeometryError, match=match) as from_volume:
        LabelVolume(np.zeros(SHAPE, np.uint8), origin, spacing, direction)
    assert str(from_grid.value) == str(from_volume.value)


def test_shape_and_array_checks():
    for shape in ((4,), (2, 3, 4, 5), (3, -1, 2), (3.5, 2, 2), "abc", 7):
        with pytest.raises(GeometryError, match="Expected `shape` to be 2 or 3 non-negative integers"):
            Grid(shape, ORIGIN[: len(shape)] if isinstance(shape, tuple) else ORIGIN, SPACING, np.eye(3))
    assert Grid(np.array([6, 5, 4]), ORIGIN, SPACING, np.eye(3)).shape == SHAPE
    with pytest.raises(GeometryError, match="Expected `array` to be 2-D or 3-D, got 4-D"):
        LabelVolume(np.zeros((2, 2, 2, 2), np.uint8), ORIGIN, SPACING, np.eye(3))
    with pytest.raises(GeometryError, match="Expected `array` to hold integer labels, got dtype float32"):
        LabelVolume(np.zeros(SHAPE, np.float32), ORIGIN, SPACING, np.eye(3))


def test_as_grid_takes_a_grid_a_volume_or_shape_and_affine():
    grid = _grid("RAS")
    vol = grid.with_array(np.zeros(SHAPE, np.uint8))
    assert as_grid(grid) is grid
    assert as_grid(vol) is vol.grid
    assert as_grid((SHAPE, grid.affine)).same_geometry(grid, atol=1e-12)
    with pytest.raises(GeometryError, match=r"Expected `reference` to be a Grid, a LabelVolume or a \(shape, affine\)"):
        as_grid(np.zeros(SHAPE), "reference")
    with pytest.raises(GeometryError, match="Expected `affine` to be a homogeneous 4x4 matrix"):
        Grid.from_affine(SHAPE, np.eye(3))
    sheared = grid.affine.copy()
    sheared[0, 1] = 0.5
    with pytest.raises(GeometryError, match="Expected `direction` to be an orthonormal"):
        Grid.from_affine(SHAPE, sheared)


# ----------------------------------------------------------------------------- functions that take a grid


def _warp() -> KernelWarp:
    rng = np.random.default_rng(3)
    centres = ORIGIN + rng.uniform(0, 8, (12, 3))
    return KernelWarp([WarpLevel(centres, rng.normal(0, 0.2, (12, 3)), width=6.0)], dim=3)


def test_warp_fields_on_a_grid_equal_those_on_the_volume():
    vol = LabelVolume(np.zeros(SHAPE, np.uint8), ORIGIN, SPACING, ORIENTATIONS["oblique"])
    warp = _warp()
    u = displacement_on_grid(warp, vol)
    assert np.abs(u).max() > 0.01  # the warp moves some voxels
    for target in (vol.grid, (SHAPE, vol.affine)):
        np.testing.assert_allclose(displacement_on_grid(warp, target), u, atol=1e-12)
        np.testing.assert_allclose(jacobian_determinant_on_grid(warp, target), jacobian_determinant_on_grid(warp, vol),
                                   atol=1e-12)
    # Chunks group the points into other blocks for the kernel sums: equal to rounding.
    np.testing.assert_allclose(displacement_on_grid(warp, vol.grid, chunk=7), u, rtol=0, atol=1e-12)
    u2, det = fields_on_grid(warp, vol.grid, chunk=11)
    np.testing.assert_allclose(u2, u, atol=1e-12)
    assert det.shape == SHAPE and np.all(det > 0)


def test_grid_chunks_on_threads_give_what_one_thread_gives():
    """The chunks of a grid are evaluated side by side on the threads: the same fields as on one
    thread, and an inverse's tallies (largest residual, unconverged points) count every chunk."""
    import numba

    from volreg.warp.inverse import InverseWarp

    vol = LabelVolume(np.zeros(SHAPE, np.uint8), ORIGIN, SPACING, ORIENTATIONS["oblique"])
    warp = _warp()
    results = {}
    for threads in (1, 2):
        previous = numba.get_num_threads()
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        try:
            inverse = InverseWarp(warp, tol=1e-9)
            results[threads] = (fields_on_grid(warp, vol.grid, chunk=5), displacement_on_grid(inverse, vol.grid, chunk=3),
                                inverse.max_residual, inverse.unconverged)
        finally:
            numba.set_num_threads(previous)
    (u1, det1), inv1, res1, bad1 = results[1]
    (u2, det2), inv2, res2, bad2 = results[2]
    np.testing.assert_array_equal(u1, u2)
    np.testing.assert_array_equal(det1, det2)
    np.testing.assert_array_equal(inv1, inv2)
    assert res1 == res2 and 0 < res1 <= 1e-9 and bad1 == bad2 == 0


def test_resample_image_and_implicit_surface_on_a_grid():
    vol = LabelVolume(np.zeros(SHAPE, np.uint8), ORIGIN, SPACING, ORIENTATIONS["LAS"])
    values = np.random.default_rng(4).normal(size=SHAPE)
    points = vol.grid_points() + 0.3
    expected = resample_image(values, vol, points, order=1)
    np.testing.assert_array_equal(resample_image(values, vol.grid, points, order=1), expected)
    np.testing.assert_array_equal(resample_image(values, (SHAPE, vol.affine), points, order=1), expected)

    rng = np.random.default_rng(5)
    normals = rng.normal(size=(200, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    centre = vol.grid_points()[3, 2, 2]
    surface = ImplicitSurface(centre + 3.0 * normals, normals, min_width=4.0)
    on_volume = implicit_on_grid(surface, vol, chunk=13)
    np.testing.assert_array_equal(implicit_on_grid(surface, vol.grid, chunk=13), on_volume)
    np.testing.assert_allclose(on_volume, surface(vol.grid_points().reshape(-1, 3)).reshape(SHAPE), rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("shape", [(0, 3), (1, 3), (1000, 3), (40000, 3), (500, 2)])  # 40000: blocks and a remainder
def test_apply_affine_is_the_product_plus_the_offset(shape):
    rng = np.random.default_rng(3)
    p = rng.uniform(-200, 200, shape)
    d = shape[1]
    for e in (d, 2):
        m, b = rng.normal(size=(e, d)), rng.normal(size=e) * 50
        out = apply_affine(p, m, b)
        assert out.shape == (shape[0], e) and out.flags.c_contiguous
        # offset first, then each column's term in order: the same bits over whole columns
        expected = np.stack([sum((m[a, c] * p[:, c] for c in range(d)), np.full(shape[0], b[a]))
                             for a in range(e)], axis=1).reshape(shape[0], e)
        np.testing.assert_array_equal(out, expected)
    # A strided (non-contiguous) view gives the same as its copy.
    q = rng.uniform(-5, 5, (2 * shape[0], d))[::2]
    m, b = rng.normal(size=(d, d)), rng.normal(size=d)
    np.testing.assert_array_equal(apply_affine(q, m, b), apply_affine(q.copy(), m, b))

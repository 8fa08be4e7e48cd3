"""Kernel warps with a linear part, ``tau(x) = A x + b + sum_l sum_j c_j k(x, x_j)``, through every consumer.

Evaluation and Jacobian, ``then``, the saved model (format version 2, version 1 still read), the Newton
inverse, the fields on a grid, compositions, the consistency error, resampling against SimpleITK, ITK
transform files and morphs.
"""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
import SimpleITK as sitk

from volreg import LabelVolume
from volreg.evaluation.consistency import error_on_grid, round_trip_error
from volreg.io import VolregIOError, read_labels, write_labels
from volreg.io.fields import read_itk_linear, write_itk_linear
from volreg.linear_map import LinearMap
from volreg.morph import linear_path, morph_vertices
from volreg.warp.field import (
    displacement_on_grid,
    fields_on_grid,
    indices_through,
    jacobian_determinant_on_grid,
    linear_displacement_on_grid,
    support_slices,
)
from volreg.warp.inverse import InverseWarp, invert_points
from volreg.warp.model import (
    ComposedWarp,
    KernelWarp,
    WarpLevel,
    jacobian_det,
    linear_outside,
)
from volreg.warp.resample import resample_labels, resample_labels_at

from shapes import rotation
from helpers import blob_volume, run
from test_warp import assert_jacobian_close, fd_jacobian


def oblique_linear(dim: int) -> LinearMap:
    """A 30 degree turn, scales 0.8 to 1.25 and a 40 mm shift: a pose change no kernel warp can make."""
    if dim == 3:
        rot = rotation(30.0)
        scales = np.diag([0.8, 1.1, 1.25])
    else:
        t = np.deg2rad(30.0)
        rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        scales = np.diag([0.8, 1.25])
    shift = np.array([40.0, -12.0, 5.0])[:dim]
    return LinearMap(rot @ scales, shift)


def kernel_levels(dim: int, seed: int = 0) -> list[WarpLevel]:
    """Three levels on [0, 100]^dim mm moving points by a few mm (as test_inverse's smooth warp)."""
    rng = np.random.default_rng(seed)
    n = 60 if dim == 2 else 200
    return [WarpLevel(rng.uniform(0, 100, (n, dim)), rng.normal(0, amp, (n, dim)), width=width)
            for width, amp in ((40.0, 0.25), (20.0, 0.12), (10.0, 0.05))]


def linear_warp(dim: int, seed: int = 0) -> KernelWarp:
    return KernelWarp(kernel_levels(dim, seed), dim=dim, linear=oblique_linear(dim))


# ------------------------------------------------------------------------------------------
# Evaluation


@pytest.mark.parametrize("dim", [2, 3])
def test_linear_only_warp(dim):
    linear = oblique_linear(dim)
    warp = KernelWarp(dim=dim, linear=linear)
    x = np.random.default_rng(1).uniform(-200, 200, (300, dim))
    tau, jac = warp.evaluate(x, order=1)
    np.testing.assert_allclose(tau, x @ linear.matrix.T + linear.translation, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(jac, np.broadcast_to(linear.matrix, (300, dim, dim)))
    np.testing.assert_allclose(jacobian_det(jac), np.linalg.det(linear.matrix), rtol=1e-14)
    np.testing.assert_allclose(warp.displacement(x), linear(x) - x, rtol=0, atol=1e-12)
    assert not warp.is_identity and warp.bounds() is None and warp.linear is linear
    assert "linear" in repr(warp)
    plain = KernelWarp(dim=dim)
    assert plain.is_identity and plain.linear.is_identity and "linear" not in repr(plain)
    # zero levels on top keep it linear
    zero = warp.with_level(WarpLevel(np.zeros((2, dim)), np.zeros((2, dim)), 5.0))
    assert zero.linear is linear and not zero.is_identity
    np.testing.assert_array_equal(zero(x), warp(x))


@pytest.mark.parametrize("dim", [2, 3])
def test_identity_linear_part_changes_nothing_bit_for_bit(dim):
    levels = kernel_levels(dim, seed=2)
    plain = KernelWarp(levels, dim=dim)
    ident = KernelWarp(levels, dim=dim, linear=LinearMap.identity(dim))
    x = np.random.default_rng(3).uniform(-10, 110, (4000, dim))
    for a, b in zip(plain.evaluate(x, order=1), ident.evaluate(x, order=1)):
        np.testing.assert_array_equal(a, b)
    grid = LabelVolume(np.zeros((30, 28, 26)[:dim], np.uint8), (-20.0, -5.0, 0.0)[:dim], (5.0, 4.0, 4.5)[:dim],
                       np.eye(dim))
    for a, b in zip(fields_on_grid(plain, grid), fields_on_grid(ident, grid)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(displacement_on_grid(InverseWarp(plain), grid),
                                  displacement_on_grid(InverseWarp(ident), grid))


@pytest.mark.parametrize("dim", [2, 3])
def test_kernel_sums_are_taken_at_x_beside_the_linear_part(dim):
    """tau(x) = A x + b + (kernel warp without linear part)(x) - x; Jacobian A + kernel gradients."""
    warp = linear_warp(dim, seed=4)
    plain = KernelWarp(warp.levels, dim=dim)
    x = np.random.default_rng(5).uniform(-10, 110, (200, dim))
    tau, jac = warp.evaluate(x, order=1)
    np.testing.assert_allclose(tau, warp.linear(x) + plain.displacement(x), rtol=0, atol=1e-12)
    np.testing.assert_allclose(jac, warp.linear.matrix + plain.jacobian(x) - np.eye(dim), rtol=0, atol=1e-13)
    assert np.abs(plain.displacement(x)).max() > 1.0  # the kernel part moves points by millimetres
    assert_jacobian_close(jac, fd_jacobian(warp, x))


@pytest.mark.parametrize("dim", [2, 3])
def test_then_is_composition_with_a_linear_map(dim):
    rng = np.random.default_rng(6)
    warp = linear_warp(dim, seed=6)
    after = LinearMap(rotation(-50.0, axis=(1.0, -0.2, 0.4))[:dim, :dim] * 1.1, rng.normal(0, 30, dim))
    moved = warp.then(after)
    x = rng.uniform(-50, 150, (500, dim))
    # only rounding of the matrix products separates the two (coordinates of a few hundred mm)
    np.testing.assert_allclose(moved(x), after(warp(x)), rtol=0, atol=1e-9)
    np.testing.assert_allclose(moved.jacobian(x), after.matrix @ warp.jacobian(x), rtol=0, atol=1e-12)
    assert [lev.width for lev in moved.levels] == warp.widths
    assert all(np.array_equal(a.centres, b.centres) for a, b in zip(moved.levels, warp.levels))
    np.testing.assert_allclose(moved.linear.matrix, after.matrix @ warp.linear.matrix, rtol=0, atol=1e-15)
    assert warp.then(LinearMap.identity(dim)) is warp
    # with_level keeps the linear part
    extra = WarpLevel(rng.uniform(0, 100, (5, dim)), rng.normal(0, 0.1, (5, dim)), 8.0)
    assert warp.with_level(extra).linear is warp.linear
    with pytest.raises(ValueError, match="`linear`"):
        warp.then(LinearMap.identity(5 - dim))
    with pytest.raises(ValueError, match="`linear`"):
        KernelWarp(dim=dim, linear=np.eye(dim))


# ------------------------------------------------------------------------------------------
# The saved model


def _write_npz(path, arrays):
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


@pytest.mark.parametrize("dim", [2, 3])
def test_save_load_round_trip_with_linear_part(tmp_path, dim):
    warp = KernelWarp(kernel_levels(dim, seed=7), dim=dim, settings={"pad": 5.0}, linear=oblique_linear(dim))
    warp.save(tmp_path / "model.npz")
    loaded = KernelWarp.load(tmp_path / "model.npz")
    x = np.random.default_rng(8).uniform(-20, 120, (300, dim))
    for a, b in zip(loaded.evaluate(x), warp.evaluate(x)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(loaded.linear.matrix, warp.linear.matrix)
    np.testing.assert_array_equal(loaded.linear.translation, warp.linear.translation)
    with np.load(tmp_path / "model.npz", allow_pickle=False) as data:
        assert int(data["format_version"]) == 2
        assert data["linear_matrix"].shape == (dim, dim) and data["linear_translation"].shape == (dim,)
    again = KernelWarp.from_arrays(warp.to_arrays())
    np.testing.assert_array_equal(again(x), warp(x))


def test_version_1_file_loads_with_identity_linear_part(tmp_path):
    warp = KernelWarp(kernel_levels(3, seed=9), dim=3, settings={"pad": 4.0})
    arrays = {k: v for k, v in warp.to_arrays().items() if not k.startswith("linear_")}
    arrays["format_version"] = np.array(1)
    _write_npz(tmp_path / "old.npz", arrays)
    loaded = KernelWarp.load(tmp_path / "old.npz")
    assert loaded.linear.is_identity and loaded.settings == {"pad": 4.0}
    x = np.random.default_rng(10).uniform(0, 100, (100, 3))
    np.testing.assert_array_equal(loaded(x), warp(x))


def test_load_rejects_bad_linear_entries(tmp_path):
    good = linear_warp(2, seed=11).to_arrays()

    def check(name, arrays, match):
        _write_npz(tmp_path / name, arrays)
        with pytest.raises(VolregIOError, match=match) as info:
            KernelWarp.load(tmp_path / name)
        assert name in str(info.value) and "\n" not in str(info.value)

    check("no_matrix.npz", {k: v for k, v in good.items() if k != "linear_matrix"}, "linear_matrix")
    check("no_shift.npz", {k: v for k, v in good.items() if k != "linear_translation"}, "linear_translation")
    check("matrix_shape.npz", {**good, "linear_matrix": np.eye(3)}, r"linear_matrix.*\(2, 2\)")
    check("shift_shape.npz", {**good, "linear_translation": np.zeros((2, 1))}, "linear_translation")
    check("matrix_nan.npz", {**good, "linear_matrix": np.array([[1.0, np.nan], [0.0, 1.0]])}, "linear_matrix.*NaN")
    check("shift_inf.npz", {**good, "linear_translation": np.array([np.inf, 0.0])}, "linear_translation.*Inf")
    check("reflection.npz", {**good, "linear_matrix": np.diag([-1.0, 1.0])}, "positive determinant")
    check("collapse.npz", {**good, "linear_matrix": np.zeros((2, 2))}, "positive determinant")
    check("text_matrix.npz", {**good, "linear_matrix": np.array([["a", "b"], ["c", "d"]])}, "linear_matrix")
    check("object_matrix.npz", {**good, "linear_matrix": np.array([None, 1], dtype=object)}, "linear_matrix")
    check("v1_with_linear.npz", {**good, "format_version": np.array(1)}, "format_version 1 has no linear part")
    check("newer.npz", {**good, "format_version": np.array(3)}, "format_version 3")
    assert zipfile.is_zipfile(tmp_path / "newer.npz")


# ------------------------------------------------------------------------------------------
# The inverse


@pytest.mark.parametrize("dim", [2, 3])
def test_inverse_with_linear_part(dim):
    """tau(inv(y)) = y to 1e-4 mm (the solver stops at 1e-6 mm), inside the support and far outside it."""
    warp = linear_warp(dim, seed=12)
    rng = np.random.default_rng(13)
    x = rng.uniform(-10, 110, (20000, dim))
    assert np.linalg.det(warp.jacobian(x)).min() > 0.2  # invertible here
    assert np.abs(warp(x) - warp.linear(x)).max() > 2.0  # and the kernel part moves points by millimetres
    y = warp(x)
    sol = invert_points(warp, y)
    assert sol.converged.all() and sol.residual.max() <= 1e-6 and sol.iterations <= 10
    assert np.abs(warp(sol.points) - y).max() <= 1e-4
    assert np.abs(sol.points - x).max() <= 1e-4  # the Jacobian is well conditioned: x comes back too
    far = rng.uniform(-2000, 2000, (2000, dim))
    far = far[np.abs(far).max(axis=1) > 500]
    inv = InverseWarp(warp)
    back = inv(far)
    assert np.abs(warp(back) - far).max() <= 1e-4
    np.testing.assert_array_equal(back, warp.linear.inverse()(far))  # exactly A^-1 (y - b), not iterated
    assert inv.max_residual <= 1e-6 and inv.unconverged == 0
    _, jinv = inv.evaluate(y[:50], order=1)
    assert np.allclose(jinv @ warp.jacobian(sol.points[:50]), np.eye(dim), atol=1e-10)


@pytest.mark.parametrize("dim", [2, 3])
def test_inverse_bounds_are_in_moving_space(dim):
    """The image of the support box lies in InverseWarp.bounds(); outside it the inverse is A^-1 (y - b)."""
    warp = linear_warp(dim, seed=14)
    inv = InverseWarp(warp)
    lo, hi = warp.bounds()
    ilo, ihi = inv.bounds()
    assert np.abs(ilo - lo).max() > 20.0  # a different box than the fixed-space one
    rng = np.random.default_rng(15)
    x = rng.uniform(lo, hi, (20000, dim))
    y = warp(x)
    assert np.all((y >= ilo) & (y <= ihi))
    np.testing.assert_allclose(inv.linear.matrix @ warp.linear.matrix, np.eye(dim), rtol=0, atol=1e-12)
    # targets just outside the moving box: the inverse is exactly linear there
    out = rng.uniform(ilo - 30.0, ihi + 30.0, (20000, dim))
    out = out[~np.all((out >= ilo) & (out <= ihi), axis=1)]
    np.testing.assert_array_equal(inv(out), inv.linear(out))
    assert np.abs(warp(inv(out)) - out).max() <= 1e-9
    assert inv.bounds() is not None and InverseWarp(KernelWarp(dim=dim, linear=warp.linear)).bounds() is None


# ------------------------------------------------------------------------------------------
# Fields on a grid, compositions, consistency


def oblique_grid(shape=(30, 28, 26), spacing=(14.0, 14.5, 15.0)) -> LabelVolume:
    """A grid of about [-200, 250] mm in an oblique orientation, reaching far beyond the boxes of the
    kernels' supports (about [-40, 140] mm in fixed space, [-85, 210] mm in moving space)."""
    direction = rotation(20.0, axis=(0.2, 1.0, 0.3))
    return LabelVolume(np.zeros(shape, np.uint8), (-180.0, -200.0, -190.0), spacing, direction)


def test_indices_through_a_displacement_are_those_of_the_displaced_world_points():
    """The moving grid's indices of x + u(x) at every fixed voxel centre, summed axis by axis,
    equal ``world_to_index`` of the world points (oblique grids of other spacings), and the
    labels there equal those of :func:`resample_labels` at the world points."""
    warp = linear_warp(3, seed=17)
    fixed = oblique_grid()
    moving = blob_volume(direction=rotation(25, (0.2, -0.5, 0.8)), origin=(-33.0, -29.0, -35.0),
                         spacing=np.array([1.3, 0.9, 1.6]))
    u = fields_on_grid(warp, fixed, chunk=4000)[0]
    points = fixed.grid_points() + u
    index = indices_through(fixed, u, moving)
    assert index.shape == (fixed.grid_points().size // 3, 3)
    np.testing.assert_allclose(index, moving.world_to_index(points.reshape(-1, 3)), rtol=0, atol=1e-10)
    np.testing.assert_allclose(indices_through(fixed, None, moving),
                               moving.world_to_index(fixed.grid_points().reshape(-1, 3)), rtol=0, atol=1e-10)
    for method in ("label", "nearest", "gaussian"):
        at_points = resample_labels(moving, points, method=method)
        assert np.array_equal(resample_labels_at(moving, index, method=method).reshape(fixed.shape), at_points)
        assert len(np.unique(at_points)) >= 2  # a label and the background are met
    with pytest.raises(ValueError, match="displacement"):
        indices_through(fixed, u[:-1], moving)


def test_indices_through_a_linear_map_are_those_of_the_mapped_world_points():
    """With a linear map L (an affine with a shear and scales), the moving grid's indices of
    L(x + u(x)) and of L(x) equal ``world_to_index`` of the mapped world points."""
    from volreg.linear_map import LinearMap

    warp = linear_warp(3, seed=5)
    fixed = oblique_grid()
    moving = blob_volume(direction=rotation(25, (0.2, -0.5, 0.8)), origin=(-33.0, -29.0, -35.0),
                         spacing=np.array([1.3, 0.9, 1.6]))
    lin = LinearMap(rotation(17, (1.0, 0.3, -0.2)) @ np.array([[1.1, 0.1, 0.0], [0.0, 0.9, 0.05], [0.0, 0.0, 1.2]]),
                    [4.0, -7.0, 2.5])
    u = fields_on_grid(warp, fixed, chunk=4000)[0]
    points = (fixed.grid_points() + u).reshape(-1, 3)
    np.testing.assert_allclose(indices_through(fixed, u, moving, lin), moving.world_to_index(lin(points)),
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(indices_through(fixed, None, moving, lin),
                               moving.world_to_index(lin(fixed.grid_points().reshape(-1, 3))), rtol=0, atol=1e-9)


def test_grid_fields_outside_the_support_are_linear():
    warp = linear_warp(3, seed=16)
    grid = oblique_grid()
    x = grid.grid_points().reshape(-1, 3)
    window = support_slices(warp, grid)
    outside = np.ones(grid.shape, bool)
    outside[window] = False
    assert 0.2 < outside.mean() < 0.9  # both parts are there
    u, det = fields_on_grid(warp, grid, chunk=4000)
    u, det = u.reshape(-1, 3), det.ravel()
    lin = warp.linear(x) - x
    # outside: (A - I) x + b (closed form; rounding of coordinates of a few hundred mm only)
    np.testing.assert_allclose(u[outside.ravel()], lin[outside.ravel()], rtol=0, atol=1e-9)
    np.testing.assert_allclose(det[outside.ravel()], np.linalg.det(warp.linear.matrix), rtol=1e-13)
    # everywhere: what the warp gives at the voxel centres
    np.testing.assert_allclose(u, warp.displacement(x), rtol=0, atol=1e-9)
    np.testing.assert_allclose(det, jacobian_det(warp.jacobian(x)), rtol=1e-12)
    # Other chunks (blocks of the kernel sums) and the value without the Jacobian: to rounding.
    np.testing.assert_allclose(displacement_on_grid(warp, grid).reshape(-1, 3), u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(jacobian_determinant_on_grid(warp, grid).ravel(), det, rtol=1e-13)
    np.testing.assert_allclose(linear_displacement_on_grid(warp.linear, grid).reshape(-1, 3), lin, rtol=0, atol=1e-9)
    assert not linear_displacement_on_grid(None, grid).any()
    # a warp that is linear everywhere: no voxel evaluated, every field closed form
    only = KernelWarp(dim=3, linear=warp.linear)
    assert support_slices(only, grid) is None
    np.testing.assert_allclose(displacement_on_grid(only, grid).reshape(-1, 3), lin, rtol=0, atol=1e-9)


def test_inverse_field_on_the_moving_grid_reaches_beyond_the_support():
    """y + v(y) = tau^-1(y) on every voxel of an oblique grid, inside and outside the moving-space box."""
    warp = linear_warp(3, seed=17)
    grid = LabelVolume(np.zeros((32, 30, 28), np.uint8), (-200.0, -180.0, -190.0), (14.0, 14.0, 15.0),
                       rotation(-15.0))
    v = displacement_on_grid(InverseWarp(warp), grid).reshape(-1, 3)
    y = grid.grid_points().reshape(-1, 3)
    assert np.abs(warp(y + v) - y).max() <= 1e-4
    window = support_slices(InverseWarp(warp), grid)
    assert window is not None and np.prod([s.stop - s.start for s in window]) < 0.9 * len(y)


def test_composed_warps_with_linear_parts():
    rng = np.random.default_rng(18)
    a = linear_warp(3, seed=18)
    b = KernelWarp(kernel_levels(3, seed=19), dim=3, linear=LinearMap(rotation(-20.0), [-10.0, 5.0, 30.0]))
    ab = a.compose(b)
    assert isinstance(ab, ComposedWarp)
    x = rng.uniform(-150, 250, (3000, 3))
    np.testing.assert_array_equal(ab(x), b(a(x)))
    np.testing.assert_allclose(ab.jacobian(x), b.jacobian(a(x)) @ a.jacobian(x), rtol=0, atol=1e-13)
    np.testing.assert_allclose(ab.linear.matrix, b.linear.matrix @ a.linear.matrix, rtol=0, atol=1e-15)
    lo, hi = ab.bounds()
    out = ~np.all((x >= lo) & (x <= hi), axis=1)
    assert out.sum() > 500
    np.testing.assert_allclose(ab(x[out]), ab.linear(x[out]), rtol=0, atol=1e-9)  # linear outside its box
    # the box holds a's support and the preimage of b's under a's linear part
    box, linear = linear_outside([a, b])
    np.testing.assert_array_equal(box[0], lo)
    np.testing.assert_array_equal(linear.matrix, ab.linear.matrix)
    assert np.all(lo <= a.bounds()[0]) and np.all(hi >= a.bounds()[1])
    grid = oblique_grid((24, 22, 20), (19.0, 19.0, 19.0))
    pts = grid.grid_points().reshape(-1, 3)
    np.testing.assert_allclose(displacement_on_grid(ab, grid).reshape(-1, 3), ab(pts) - pts, rtol=0, atol=1e-9)


def test_consistency_error_with_linear_parts():
    """A warp and its inverse are consistent everywhere; a warp twice over is not, outside its support too."""
    warp = linear_warp(3, seed=20)
    grid = oblique_grid((30, 28, 26), (17.0, 17.0, 17.0))
    error = error_on_grid(warp, InverseWarp(warp), grid, chunk=5000)
    assert error.max() <= 1e-5
    brute = round_trip_error(warp, warp, grid.grid_points().reshape(-1, 3)).reshape(grid.shape)
    outside = np.ones(grid.shape, bool)
    outside[support_slices((warp, warp), grid)] = False
    assert outside.any() and brute[outside].min() > 1.0  # the linear part moves points everywhere
    np.testing.assert_allclose(error_on_grid(warp, warp, grid, chunk=5000), brute, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------
# Resampling and ITK transform files against SimpleITK


def _sitk_image(volume: LabelVolume) -> sitk.Image:
    img = sitk.GetImageFromArray(np.ascontiguousarray(volume.array.transpose(2, 1, 0)))
    img.SetOrigin(tuple(map(float, volume.origin)))
    img.SetSpacing(tuple(map(float, volume.spacing)))
    img.SetDirection(tuple(map(float, volume.direction.ravel())))
    return img


def _sitk_affine(linear: LinearMap) -> sitk.AffineTransform:
    t = sitk.AffineTransform(linear.dim)
    t.SetMatrix(tuple(map(float, linear.matrix.ravel())))
    t.SetTranslation(tuple(map(float, linear.translation)))
    return t


def test_resample_through_a_rigid_warp_matches_simpleitk():
    """Nearest-neighbour labels through rotation + translation: volreg and ITK agree on >= 99 % of voxels
    (they may differ only where a point falls within rounding of a half-voxel boundary)."""
    moving = blob_volume(direction=rotation(10.0, axis=(1.0, 0.0, 0.2)))
    fixed = LabelVolume(np.zeros((44, 40, 38), np.uint8), (-28.0, -35.0, -20.0), (1.4, 1.6, 1.5), rotation(-25.0))
    centre = moving.index_to_world((np.array(moving.shape)[None] - 1) / 2.0)[0]
    rot = rotation(30.0, axis=(0.1, 0.3, 1.0))
    linear = LinearMap(rot, centre - rot @ (centre + [3.0, -4.0, 2.0]))  # turn about the blob, 5 mm shift
    warp = KernelWarp(dim=3, linear=linear)
    points = fixed.grid_points() + displacement_on_grid(warp, fixed)
    ours = resample_labels(moving, points, method="nearest")
    ref = sitk.Resample(_sitk_image(moving), _sitk_image(fixed), _sitk_affine(linear), sitk.sitkNearestNeighbor, 0)
    theirs = sitk.GetArrayFromImage(ref).transpose(2, 1, 0)
    assert (theirs > 0).sum() > 5000 and set(np.unique(theirs)) == {0, 1, 2}  # the blob landed on the grid
    assert (ours == theirs).mean() >= 0.99
    objects = (ours > 0) | (theirs > 0)  # also where it counts (measured: every voxel agrees)
    assert (ours == theirs)[objects].mean() >= 0.98
    # the label-preserving interpolation stays close to it
    assert (resample_labels(moving, points, method="label") == theirs).mean() >= 0.97


@pytest.mark.parametrize("dim", [2, 3])
def test_written_tfm_is_read_by_simpleitk(tmp_path, dim):
    linear = oblique_linear(dim)
    path = tmp_path / "linear.tfm"
    write_itk_linear(path, linear)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["linear.tfm"]  # no temporary left
    text = path.read_text()
    assert text.startswith("#Insight Transform File V1.0\n") and f"AffineTransform_double_{dim}_{dim}" in text
    transform = sitk.ReadTransform(str(path))
    x = np.random.default_rng(21).uniform(-300, 300, (200, dim))
    theirs = np.array([transform.TransformPoint(tuple(map(float, p))) for p in x])
    np.testing.assert_allclose(theirs, linear(x), rtol=0, atol=1e-9)  # the same map, in full precision
    back = read_itk_linear(path, dim=dim)
    np.testing.assert_array_equal(back.matrix, linear.matrix)
    np.testing.assert_array_equal(back.translation, linear.translation)
    with pytest.raises(VolregIOError, match="exists"):
        write_itk_linear(path, LinearMap.identity(dim))
    write_itk_linear(path, LinearMap.identity(dim), force=True)
    assert read_itk_linear(path).is_identity
    with pytest.raises(VolregIOError, match=r"\.tfm or \.txt"):
        write_itk_linear(tmp_path / "linear.nii.gz", linear)


def _simpleitk_linears():
    affine = sitk.AffineTransform(3)
    affine.SetMatrix(tuple(map(float, (rotation(25.0) @ np.diag([0.9, 1.2, 1.05])).ravel())))
    affine.SetTranslation((12.0, -7.5, 30.0))
    affine.SetCenter((40.0, -20.0, 65.0))
    euler = sitk.Euler3DTransform((10.0, 20.0, -5.0), 0.2, -0.4, 0.7, (3.0, -8.0, 1.5))
    similarity = sitk.Similarity3DTransform(1.3, (0.1, 0.5, 0.2), 0.6, (4.0, 5.0, 6.0), (-10.0, 3.0, 8.0))
    versor = sitk.VersorRigid3DTransform((0.0, 0.0, 1.0), 0.9, (1.0, 2.0, 3.0), (30.0, 30.0, 0.0))
    euler2 = sitk.Euler2DTransform((5.0, -3.0), 0.4, (2.0, 9.0))
    return {"affine": affine, "euler": euler, "similarity": similarity, "versor": versor, "euler2d": euler2}


@pytest.mark.parametrize("name", ["affine", "euler", "similarity", "versor", "euler2d"])
@pytest.mark.parametrize("suffix", [".tfm", ".mat"])
def test_read_transforms_that_simpleitk_writes(tmp_path, name, suffix):
    """A centred transform written by SimpleITK reads back as x -> A x + b with b = t + c - A c."""
    transform = _simpleitk_linears()[name]
    path = tmp_path / f"t{suffix}"
    sitk.WriteTransform(transform, str(path))
    linear = read_itk_linear(path)
    dim = transform.GetDimension()
    assert linear.dim == dim
    x = np.random.default_rng(22).uniform(-200, 200, (100, dim))
    theirs = np.array([transform.TransformPoint(tuple(map(float, p))) for p in x])
    np.testing.assert_allclose(linear(x), theirs, rtol=0, atol=1e-9)


def test_read_itk_linear_rejects_what_is_not_one_linear_transform(tmp_path):
    def check(path, match, **kwargs):
        with pytest.raises(VolregIOError, match=match) as info:
            read_itk_linear(path, **kwargs)
        assert path.name in str(info.value) and "\n" not in str(info.value)

    header = "#Insight Transform File V1.0\n#Transform 0\n"
    composite = tmp_path / "composite.tfm"
    sitk.WriteTransform(sitk.CompositeTransform([sitk.Euler3DTransform(), sitk.AffineTransform(3)]), str(composite))
    check(composite, "2 transforms")
    bspline = tmp_path / "bspline.tfm"
    sitk.WriteTransform(sitk.BSplineTransform(3), str(bspline))
    check(bspline, "BSplineTransform")
    reflection = tmp_path / "reflection.tfm"
    reflection.write_text(header + "Transform: AffineTransform_double_2_2\nParameters: -1 0 0 1 0 0\n"
                          "FixedParameters: 0 0\n")
    check(reflection, "determinant")
    count = tmp_path / "count.tfm"
    count.write_text(header + "Transform: AffineTransform_double_3_3\nParameters: 1 0 0 1\nFixedParameters: 0 0 0\n")
    check(count, "expected 12 and 3")
    nan = tmp_path / "nan.tfm"
    nan.write_text(header + "Transform: AffineTransform_double_2_2\nParameters: 1 0 0 nan 0 0\n"
                   "FixedParameters: 0 0\n")
    check(nan, "NaN")
    words = tmp_path / "words.tfm"
    words.write_text(header + "Transform: AffineTransform_double_2_2\nParameters: one 0 0 1 0 0\n"
                     "FixedParameters: 0 0\n")
    check(words, "not numbers")
    good = tmp_path / "good.tfm"
    write_itk_linear(good, oblique_linear(3))
    check(good, "expected a 2-D transform", dim=2)
    garbage = tmp_path / "garbage.txt"
    garbage.write_text("not a transform\n")
    check(garbage, "could not be read")
    check(tmp_path / "absent.tfm", "does not exist")


# ------------------------------------------------------------------------------------------
# volreg apply with a transform file, and morphs


def test_apply_an_itk_linear_transform(tmp_path):
    moving = blob_volume()
    write_labels(moving, tmp_path / "moving.nii.gz")
    linear = LinearMap(rotation(12.0), [2.0, -3.0, 1.5])
    write_itk_linear(tmp_path / "linear.tfm", linear)
    assert run(["apply", tmp_path / "linear.tfm", tmp_path / "moving.nii.gz", "--reference",
                tmp_path / "moving.nii.gz", "-o", tmp_path / "out.nii.gz", "--quiet"]) == 0
    out = read_labels(tmp_path / "out.nii.gz").array
    warp = KernelWarp(dim=3, linear=linear)
    expect = resample_labels(moving, moving.grid_points() + displacement_on_grid(warp, moving))
    np.testing.assert_array_equal(out, expect)
    assert (out != moving.array).mean() > 0.01  # it moved


def test_morph_turns_instead_of_cutting_across():
    """A pure 60 degree turn: the frames keep every vertex's distance from the axis point (a straight path
    shrinks it in the plane of the turn by 1 - cos 30 deg = 13 % half way); the end frames are v and tau(v)."""
    rng = np.random.default_rng(23)
    v = rng.normal(0, 20, (500, 3))
    linear = LinearMap(rotation(60.0, axis=(0.0, 0.0, 1.0)), np.zeros(3))
    frames = morph_vertices(v, linear(v), 5, linear=linear)
    np.testing.assert_array_equal(frames[0], v)
    np.testing.assert_array_equal(frames[-1], linear(v))
    for f in frames:
        np.testing.assert_allclose(np.linalg.norm(f, axis=1), np.linalg.norm(v, axis=1), rtol=1e-12)
    flat = v * [1.0, 1.0, 0.0]  # in the plane of the turn
    straight = morph_vertices(flat, linear(flat), 3)[1]
    np.testing.assert_allclose(np.linalg.norm(straight, axis=1), np.cos(np.pi / 6) * np.linalg.norm(flat, axis=1))
    half = linear_path(linear, 0.5)
    np.testing.assert_allclose(half.matrix @ half.matrix, linear.matrix, atol=1e-12)
    # with a kernel part on top, it is added in proportion to t
    warped = linear(v) + 1.0
    mid = morph_vertices(v, warped, 3, linear=linear)[1]
    np.testing.assert_allclose(mid, half(v) + 0.5, rtol=0, atol=1e-12)

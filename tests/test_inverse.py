"""The Newton inverse of kernel warps (volreg.inverse) on points and on grids."""

from __future__ import annotations

import numpy as np
import pytest

from volreg import LabelVolume
from volreg.warp.field import displacement_on_grid
from volreg.warp.inverse import CHORD_STEPS, InverseWarp, _newton_steps, invert_points
from volreg.warp.model import KernelWarp, WarpLevel


def smooth_warp(dim: int, seed: int = 0, strength: float = 1.0) -> KernelWarp:
    """A random three-level kernel warp on [0, 100]^dim mm (max displacement a few mm, det J > 0.5)."""
    rng = np.random.default_rng(seed)
    levels = []
    for width, amp in ((40.0, 0.25), (20.0, 0.12), (10.0, 0.05)):
        n = 60 if dim == 2 else 200
        levels.append(WarpLevel(rng.uniform(0, 100, (n, dim)), strength * rng.normal(0, amp, (n, dim)), width=width))
    return KernelWarp(levels, dim=dim)


@pytest.mark.parametrize("dim", [2, 3])
def test_newton_inverse_round_trips(dim):
    """tau(tau^-1(y)) = y and tau^-1(tau(x)) = x to <= 1e-3 voxel (1 mm voxels) on the support."""
    warp = smooth_warp(dim)
    rng = np.random.default_rng(1)
    y = rng.uniform(0, 100, (20000, dim))
    assert np.linalg.det(warp.jacobian(y)).min() > 0.3  # the warp is invertible here
    assert np.linalg.norm(warp.displacement(y), axis=1).max() > 2.0  # and moves points by millimetres
    sol = invert_points(warp, y)
    assert sol.converged.all() and sol.residual.max() <= 1e-6
    assert np.abs(warp(sol.points) - y).max() <= 1e-3
    x = rng.uniform(0, 100, (20000, dim))
    assert np.abs(invert_points(warp, warp(x)).points - x).max() <= 1e-3
    assert sol.iterations <= 10  # Newton converges in a few steps


def test_outside_support_and_identity_are_exact():
    warp = smooth_warp(3)
    lo, hi = warp.bounds()
    far = np.array([hi + 1.0, lo - 5.0, [hi[0] + 2.0, 50.0, 50.0]])
    sol = invert_points(warp, far)
    assert np.array_equal(sol.points, far) and np.all(sol.residual == 0.0)
    pts = np.random.default_rng(2).uniform(0, 100, (100, 3))
    assert np.array_equal(invert_points(KernelWarp.identity(3), pts).points, pts)


def test_inverse_jacobian_is_inverse_matrix_and_matches_differences():
    warp = smooth_warp(3)
    inv = InverseWarp(warp)
    y = np.random.default_rng(3).uniform(20, 80, (50, 3))
    x, jinv = inv.evaluate(y, order=1)
    assert np.allclose(jinv @ warp.jacobian(x), np.eye(3), atol=1e-10)
    h = 1e-4
    fd = np.stack([(inv(y + h * e) - inv(y - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)
    assert np.abs(fd - jinv).max() < 1e-5
    assert inv.max_residual <= 1e-6 and inv.unconverged == 0


def test_inverse_on_grid_composes_to_identity():
    """displacement_on_grid(InverseWarp) is the ANTs InverseWarp field: y + v(y) = tau^-1(y)."""
    warp = smooth_warp(3, seed=4)
    grid = LabelVolume(np.zeros((26, 24, 22), np.uint8), origin=(-5.0, 0.0, 3.0),
                       spacing=(4.0, 4.5, 5.0), direction=np.eye(3))
    v = displacement_on_grid(InverseWarp(warp), grid)
    y = grid.grid_points().reshape(-1, 3)
    assert np.abs(warp(y + v.reshape(-1, 3)) - y).max() <= 1e-3 * 4.0
    assert np.abs(v).max() > 1.0


def test_folding_warp_reports_residual():
    """A warp that folds has no inverse everywhere: the solver stops, and says so per point."""
    warp = smooth_warp(3, strength=12.0)
    y = np.random.default_rng(5).uniform(0, 100, (5000, 3))
    assert np.linalg.det(warp.jacobian(y)).min() < 0  # folds
    sol = invert_points(warp, y, max_iter=20)
    assert np.array_equal(sol.converged, sol.residual <= 1e-6)
    assert np.allclose(sol.residual, np.linalg.norm(warp(sol.points) - y, axis=1))
    assert sol.converged.mean() > 0.5  # most points still have a preimage


@pytest.mark.parametrize("kwargs, match", [({"tol": 0.0}, "tol"), ({"max_iter": 0}, "max_iter")])
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        invert_points(smooth_warp(2), np.zeros((1, 2)), **kwargs)


@pytest.mark.parametrize("dim", [2, 3])
def test_grid_start_from_the_sampled_forward_field(dim):
    """Starts interpolated from the forward field on a 1 mm grid lie within 0.05 mm of the exact
    preimages (a linear part included), NaN where the preimage is off the grid; Newton from them
    gives the plain inverse's answer to its 1e-6 mm."""
    from volreg.warp.inverse import GridStart
    from volreg.linear_map import LinearMap

    angle = np.deg2rad(8.0)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    matrix = np.eye(dim)
    matrix[:2, :2] = 1.05 * rot
    base = smooth_warp(dim)
    warp = KernelWarp(base.levels, dim=dim, linear=LinearMap(matrix, np.full(dim, 3.0)))
    grid = LabelVolume(np.zeros((101,) * dim, dtype=np.int16), np.zeros(dim), np.ones(dim), np.eye(dim))
    start = GridStart(displacement_on_grid(warp, grid), grid, warp.linear)
    rng = np.random.default_rng(4)
    x_true = rng.uniform(5, 95, (3000, dim))
    y = warp(x_true)
    x0 = start(y)
    assert np.isfinite(x0).all()
    assert np.abs(x0 - x_true).max() <= 0.05
    off_grid = warp(np.full((1, dim), -10.0))  # its preimage lies outside the grid
    assert np.isnan(start(off_grid)).all()
    plain = invert_points(warp, y)
    started = invert_points(warp, y, start=start)
    assert started.converged.all() and started.residual.max() <= 1e-6
    assert np.abs(started.points - plain.points).max() <= 2e-6
    assert started.iterations <= plain.iterations


def test_a_start_within_tol_is_kept_without_the_jacobian():
    """Starts already within ``tol`` of their targets are checked by one evaluation of tau alone
    (no Jacobian) and kept as they are; starts a little off are polished by chord steps (tau
    alone, the linear part for the Jacobian); starts further off go on with Newton to ``tol``."""
    warp = smooth_warp(3)
    y = np.random.default_rng(5).uniform(20, 80, (4000, 3))
    exact = invert_points(warp, y).points
    orders = []

    class Counting:
        dim = 3

        def bounds(self):
            return warp.bounds()

        def evaluate(self, points, order=1):
            orders.append(order)
            return warp.evaluate(points, order=order)

    shift = np.zeros_like(exact)
    shift[::2] = 1e-5  # 1.7e-5 mm off: within tol
    kept = invert_points(Counting(), y, tol=1e-4, start=lambda _: exact + shift)
    assert orders == [0] and np.array_equal(kept.points, exact + shift)
    assert kept.converged.all() and kept.residual.max() <= 1e-4
    orders.clear()
    shift[1::2] = 2e-4  # 3.5e-4 mm off: chord steps (|du/dx| up to 0.4 here: each shrinks it 3-4 times)
    chord = invert_points(Counting(), y, tol=1e-4, start=lambda _: exact + shift)
    assert 1 not in orders and len(orders) <= 1 + CHORD_STEPS
    assert chord.converged.all() and chord.residual.max() <= 1e-4
    assert np.array_equal(chord.points[::2], exact[::2] + shift[::2])
    orders.clear()
    shift[1::2] = 0.5  # 0.9 mm off: chord steps, then Newton
    polished = invert_points(Counting(), y, tol=1e-4, start=lambda _: exact + shift)
    assert orders[: 1 + CHORD_STEPS] == [0] * (1 + CHORD_STEPS) and 1 in orders
    assert polished.converged.all() and polished.residual.max() <= 1e-4
    assert np.array_equal(polished.points[::2], exact[::2] + shift[::2])


@pytest.mark.parametrize("dim", [2, 3])
def test_newton_steps_solve_where_the_jacobian_is_sound_and_damp_elsewhere(dim):
    rng = np.random.default_rng(8)
    jac = np.eye(dim) + 0.3 * rng.normal(size=(200, dim, dim))
    jac[:20] = -jac[:20]  # orientation flipped in 3-D (and some 2-D rows): det below the floor
    jac[20:30] = 0.0  # singular
    r = rng.normal(size=(200, dim))
    a_inv = np.linalg.inv(np.eye(dim) * 1.2 + 0.1 * rng.normal(size=(dim, dim)))
    step = _newton_steps(jac, r, 0.05, a_inv)
    sound = np.linalg.det(jac) > 0.05
    assert sound.sum() > 100 and (~sound).sum() >= 10
    np.testing.assert_allclose(step[sound], -np.linalg.solve(jac[sound], r[sound][..., None])[..., 0],
                               rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(step[~sound], -0.5 * r[~sound] @ a_inv.T, rtol=1e-12, atol=1e-12)

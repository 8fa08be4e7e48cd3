"""Implicit surfaces fitted to label-volume surfaces: the foundation issue's acceptance.

Tolerances are in voxels, with "voxel" the largest spacing of the grid (2 mm on
the anisotropic 0.8 x 0.8 x 2 mm grid: its staircase along the coarse axis
limits what any mesh of it can resolve).
"""

import numpy as np
import pytest

from shapes import Disc2D, Ellipsoid, Torus, label_volume, rotation
from volreg.features.implicit import ImplicitSurface, estimate_normals, thin_points
from volreg.features.label_surfaces import implicit_surfaces, label_surfaces, voxel_size

ELLIPSOID = Ellipsoid((20, 15, 11), (0.37, -0.21, 0.13))
TORUS = Torus(16, 6, (0.37, -0.21, 0.13))


def _volume(shape, kind):
    if kind == "iso":
        return label_volume((56,) * 3, (1, 1, 1), np.eye(3), (-27.5,) * 3, shape.signed_distance)
    rot = rotation(25)
    return label_volume((70, 70, 28), (0.8, 0.8, 2.0), rot, -rot @ np.array([27.6, 27.6, 27.0]), shape.signed_distance)


CASES = [(s, k) for s in ("ellipsoid", "torus") for k in ("iso", "aniso-oblique")]


@pytest.fixture(scope="module")
def fitted():
    out = {}
    for name, kind in CASES:
        shape = ELLIPSOID if name == "ellipsoid" else TORUS
        vol = _volume(shape, kind)
        surf = label_surfaces(vol)
        out[name, kind] = (shape, vol, implicit_surfaces(vol, surf)[1])
    return out


@pytest.mark.parametrize("case", CASES, ids=["-".join(c) for c in CASES])
def test_signed_distance_accuracy(fitted, case):
    shape, vol, f = fitted[case]
    vox = voxel_size(vol)
    rng = np.random.default_rng(7)
    # |f| on the true surface: mean <= 0.1 voxel.
    pts, normals = shape.surface_points(3000, rng)
    value, grad = f.evaluate(pts, order=1)
    assert np.abs(value).mean() <= 0.1 * vox
    # Angle between grad f and the true normal: mean <= 5 degrees.
    cos = np.einsum("nd,nd->n", grad, normals) / np.linalg.norm(grad, axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).mean() <= 5.0
    # Within +-3 voxels of the surface, |f - sd| has mean <= 0.25 voxel.
    grid = vol.grid_points().reshape(-1, 3)
    sd = shape.signed_distance(grid)
    band = np.abs(sd) <= 3 * vox
    assert np.abs(f(grid[band]) - sd[band]).mean() <= 0.25 * vox
    # Sign right at every grid point farther than one voxel from the surface.
    far = np.abs(sd) > vox
    assert np.array_equal(np.sign(f(grid[far])), np.sign(sd[far]))


def test_derivatives_match_finite_differences(fitted):
    _, _, f = fitted["torus", "iso"]
    rng = np.random.default_rng(8)
    x = TORUS.surface_points(50, rng)[0] + rng.normal(0, 1.0, (50, 3))
    _, grad, hess = f.evaluate(x, order=2)
    h = 1e-5
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        fp, gp = f.evaluate(x + e, order=1)
        fm, gm = f.evaluate(x - e, order=1)
        np.testing.assert_allclose((fp - fm) / (2 * h), grad[:, a], rtol=0, atol=1e-5 * np.abs(grad).max())
        np.testing.assert_allclose((gp - gm) / (2 * h), hess[:, :, a], rtol=0, atol=1e-5 * np.abs(hess).max())


def test_levels_halve_from_half_the_diameter_to_the_minimum_width(fitted):
    _, vol, f = fitted["ellipsoid", "iso"]
    widths = np.array(f.widths)
    assert widths[0] == pytest.approx(f.diameter / 2)
    np.testing.assert_allclose(widths[1:] / widths[:-1], 0.5)
    assert widths[-1] >= 4 * voxel_size(vol) > widths[-1] / 2
    # The finest level's coordinate descent converges: its fitted values lie within the tube
    # (epsilon = 0.1 voxel) widened by 5 % at 99 % of the training points, and nowhere far outside it.
    assert f.log[-1]["converged"]
    assert f.log[-1]["p99_residual"] <= 0.105 * voxel_size(vol)
    assert f.log[-1]["max_residual"] <= 0.15 * voxel_size(vol)


def test_far_from_the_object_f_is_the_positive_offset(fitted):
    _, _, f = fitted["ellipsoid", "iso"]
    lo, hi = f.bounds()
    far = np.array([hi + 1.0, lo - 1.0])
    np.testing.assert_array_equal(f(far), [f.offset, f.offset])
    assert f.offset > 0


def test_to_arrays_round_trip_is_exact(fitted, tmp_path):
    _, _, f = fitted["torus", "iso"]
    path = tmp_path / "f.npz"
    np.savez(path, **f.to_arrays())
    with np.load(path, allow_pickle=False) as data:
        g = ImplicitSurface.from_arrays(data)
    x = np.random.default_rng(9).uniform(-25, 25, (500, 3))
    for a, b in zip(f.evaluate(x, order=1), g.evaluate(x, order=1)):
        np.testing.assert_array_equal(a, b)
    assert (g.offset, g.diameter, g.widths) == (f.offset, f.diameter, f.widths)
    np.testing.assert_array_equal(g.points, f.points)


def test_two_dimensional_outline():
    disc = Disc2D((18, 11), (0.3, -0.2))
    vol = label_volume((60, 60), (1.0, 1.0), np.eye(2), (-29.5, -29.5), disc.signed_distance)
    surf = label_surfaces(vol)[1]
    assert surf.cells.shape[1] == 2
    f = implicit_surfaces(vol, {1: surf})[1]
    rng = np.random.default_rng(10)
    pts, normals = disc.surface_points(500, rng)
    value, grad = f.evaluate(pts, order=1)
    # The 3-D thresholds are 0.1 voxel; an outline has far fewer vertices per
    # kernel width than a surface, so less of the pixel staircase averages out
    # (measured 0.116 pixel here).
    assert np.abs(value).mean() <= 0.15
    cos = np.einsum("nd,nd->n", grad, normals) / np.linalg.norm(grad, axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).mean() <= 5.0
    grid = vol.grid_points().reshape(-1, 2)
    sd = disc.signed_distance(grid)
    far = np.abs(sd) > 1.0
    assert np.array_equal(np.sign(f(grid[far])), np.sign(sd[far]))


def test_normals_estimated_from_neighbours():
    rng = np.random.default_rng(11)
    pts, true = ELLIPSOID.surface_points(4000, rng)
    est = estimate_normals(pts)
    cos = np.einsum("nd,nd->n", est, true)
    assert np.all(cos > 0)  # every one oriented outward
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).mean() < 3.0


def test_fit_from_a_point_cloud_without_normals():
    rng = np.random.default_rng(12)
    pts, _ = ELLIPSOID.surface_points(6000, rng)
    f = ImplicitSurface(pts, min_width=6.0)
    probe, _ = ELLIPSOID.surface_points(500, rng)
    assert np.abs(f(probe)).mean() < 0.1
    inside = ELLIPSOID.centre + np.array([[0, 0, 0], [10, 0, 0], [0, 8, 0]])
    outside = ELLIPSOID.centre + np.array([[25, 0, 0], [0, 19, 0], [0, 0, 15]])
    assert np.all(f(inside) < 0) and np.all(f(outside) > 0)


def test_bad_arguments():
    pts = np.random.default_rng(13).normal(size=(50, 3))
    with pytest.raises(ValueError, match="`normals` of shape"):
        ImplicitSurface(pts, np.ones((49, 3)))
    with pytest.raises(ValueError, match="at least 7 `points`"):
        ImplicitSurface(pts[:3], np.ones((3, 3)))
    with pytest.raises(ValueError, match="finite values in `points`"):
        ImplicitSurface(np.full((50, 3), np.nan), np.ones((50, 3)))
    with pytest.raises(ValueError, match="non-zero `normals`"):
        ImplicitSurface(pts, np.zeros((50, 3)))


@pytest.mark.parametrize("seed, dim, spacing", [(0, 3, 1.0), (1, 3, 0.37), (2, 2, 0.5), (3, 3, 50.0)])
def test_thinning_keeps_the_point_nearest_each_cell_centre(seed, dim, spacing):
    rng = np.random.default_rng(seed)
    # Half the points on a lattice (equal distances in many cells: the lowest index wins), half random.
    points = np.concatenate([rng.integers(0, 6, (400, dim)) * 0.5, rng.uniform(0, 3, (400, dim))])
    kept = thin_points(points, spacing)
    lo = points.min(axis=0)
    cell = np.floor((points - lo) / spacing).astype(np.int64)
    dist = np.sum(((points - lo) / spacing - cell - 0.5) ** 2, axis=1)
    expected = {}
    for i, (c, d) in enumerate(zip(map(tuple, cell), dist)):
        if c not in expected or d < dist[expected[c]]:
            expected[c] = i
    assert kept.tolist() == sorted(expected.values())


def test_median_spacing_of_a_large_set_from_a_sample():
    """Above twice SPACING_SAMPLE points the median neighbour distance is taken over every k-th
    point: exact on a regular grid, and within 2 % of the full median on a random surface."""
    from scipy.spatial import cKDTree

    from volreg.features.implicit import SPACING_SAMPLE, _median_spacing

    g = np.stack(np.meshgrid(np.arange(300) * 0.5, np.arange(300) * 0.5, indexing="ij"), -1).reshape(-1, 2)
    plane = np.column_stack([g, np.zeros(len(g))])
    assert len(plane) > 2 * SPACING_SAMPLE
    assert _median_spacing(cKDTree(plane)) == pytest.approx(0.5, abs=1e-12)
    rng = np.random.default_rng(2)
    u = rng.normal(size=(120_000, 3))
    sphere = 40.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    tree = cKDTree(sphere)
    full = float(np.median(tree.query(sphere, 2)[0][:, 1]))
    assert _median_spacing(tree) == pytest.approx(full, rel=0.02)
    small = sphere[: 2 * SPACING_SAMPLE]  # not sampled: every point counts
    assert _median_spacing(cKDTree(small)) == float(np.median(cKDTree(small).query(small, 2)[0][:, 1]))


def test_off_surface_points_that_cross_another_sheet_are_dropped():
    """Carr's off-surface points x +- delta n are kept only where no surface point lies within
    0.9 delta: across a slab 1 mm thick, the inward points (0.6 mm) land near the other face
    and are dropped; the outward ones are kept, at signed distance +delta."""
    from scipy.spatial import cKDTree

    from volreg.features.implicit import _offsurface

    g = np.stack(np.meshgrid(np.arange(-10, 10.01, 0.25), np.arange(-10, 10.01, 0.25), indexing="ij"), -1)
    g = g.reshape(-1, 2)
    top = np.column_stack([g, np.full(len(g), 0.5)])
    bottom = np.column_stack([g, np.full(len(g), -0.5)])
    points = np.concatenate([top, bottom])
    normals = np.concatenate([np.tile([0, 0, 1.0], (len(g), 1)), np.tile([0, 0, -1.0], (len(g), 1))])
    pts, vals = _offsurface(points, normals, 0.6, cKDTree(points))
    assert np.all(vals == 0.6)  # every inward point (-0.6) lay 0.4 mm from the other face
    assert len(pts) == len(points)
    np.testing.assert_allclose(np.abs(pts[:, 2]), 1.1)
    pts, vals = _offsurface(points, normals, 0.4, cKDTree(points))  # 0.6 mm from the other face: kept
    assert len(pts) == 2 * len(points) and np.sum(vals < 0) == len(points)

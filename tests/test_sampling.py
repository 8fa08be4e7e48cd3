"""Octree sampling of the warp volume (paper Section 3.5), on analytic oracles.

The source surface is a sphere (3-D) or circle (2-D) of radius R = 20 mm given
by dense vertices; X is the shell R - pad <= |x| <= R + pad.  The vertices lie
on the surface, so their distance overestimates the surface distance by at
most the vertex covering radius s (checked below): samples must lie in the
exact shell, and X may be under-covered by at most s.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from volreg.warp.sampling import morton_order, octree_sample

R, PAD, WIDTH = 20.0, 5.0, 8.0
ROUND = 1e-9  # mm, float round-off on coordinates of order 50 mm


def fibonacci_sphere(n: int, radius: float) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0**0.5) * i
    rho = np.sqrt(1.0 - z * z)
    return radius * np.c_[rho * np.cos(phi), rho * np.sin(phi), z]


def circle(n: int, radius: float) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return radius * np.c_[np.cos(t), np.sin(t)]


def lattice_edge(points: np.ndarray) -> np.ndarray:
    """Nearest-neighbour distance of every sample (mm)."""
    d, _ = cKDTree(points).query(points, k=2)
    return d[:, 1]


def uniform_shell(rng: np.random.Generator, n: int, dim: int, r0: float, r1: float) -> np.ndarray:
    """``n`` points uniform in the shell r0 <= |x| <= r1 (inverse CDF in r^D)."""
    u = rng.normal(size=(n, dim))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = (r0**dim + rng.random(n) * (r1**dim - r0**dim)) ** (1.0 / dim)
    return u * r[:, None]


@pytest.fixture(scope="module")
def sphere():
    return fibonacci_sphere(20_000, R)


@pytest.fixture(scope="module")
def sphere_samples(sphere):
    return octree_sample(sphere, PAD, WIDTH)


def covering_radius(surface: np.ndarray, rng: np.random.Generator) -> float:
    """Largest distance from a random surface point to its nearest vertex (mm)."""
    dim = surface.shape[1]
    u = rng.normal(size=(50_000, dim))
    u = R * u / np.linalg.norm(u, axis=1, keepdims=True)
    return float(cKDTree(surface).query(u)[0].max())


def test_sphere_samples_in_shell_on_lattice(sphere, sphere_samples):
    s = sphere_samples
    assert s.ndim == 2 and s.shape[1] == 3 and s.dtype == float
    r = np.linalg.norm(s, axis=1)
    # Vertex distance >= surface distance, so samples lie in the exact shell.
    assert r.min() >= R - PAD - ROUND and r.max() <= R + PAD + ROUND
    edge = lattice_edge(s)
    # Stopping rule: fraction*width/2 <= edge < fraction*width, and the edge is
    # the root cube (padded bounding box) halved an integer number of times.
    e = edge.min()
    np.testing.assert_allclose(edge, e, rtol=1e-9)
    assert 0.5 * 0.5 * WIDTH <= e < 0.5 * WIDTH
    root = np.max(np.ptp(sphere, axis=0)) + 2 * PAD
    assert np.isclose(np.log2(root / e), round(np.log2(root / e)))
    # Regular lattice: coordinates are offset + integer * edge.
    k = (s - s.min(axis=0)) / e
    np.testing.assert_allclose(k, np.round(k), atol=1e-7)
    assert len(np.unique(np.round(k), axis=0)) == len(s)


def test_sphere_covers_shell_without_holes(sphere, sphere_samples):
    rng = np.random.default_rng(1)
    sv = covering_radius(sphere, rng)
    assert sv < 0.5  # mm: 20k vertices on 5,000 mm^2, spacing ~0.5 mm
    e = lattice_edge(sphere_samples).min()
    h = 0.5 * e * np.sqrt(3)  # box half-diagonal
    tree = cKDTree(sphere_samples)
    # Away from the shell's boundary by h + s, the point's own box centre is in X.
    inner = uniform_shell(rng, 5_000, 3, R - PAD + h + sv, R + PAD - h - sv)
    assert tree.query(inner)[0].max() <= h + ROUND
    # Anywhere in the shell a sample is within 2h + s (needs pad >= h).
    assert PAD >= h
    shell = uniform_shell(rng, 5_000, 3, R - PAD, R + PAD)
    assert tree.query(shell)[0].max() <= 2 * h + sv


def test_sphere_count_matches_shell_volume(sphere_samples):
    e = lattice_edge(sphere_samples).min()
    volume = 4.0 / 3.0 * np.pi * ((R + PAD) ** 3 - (R - PAD) ** 3)
    assert len(sphere_samples) == pytest.approx(volume / e**3, rel=0.15)


def test_halving_width_multiplies_count_by_eight(sphere, sphere_samples):
    fine = octree_sample(sphere, PAD, WIDTH / 2)
    np.testing.assert_allclose(lattice_edge(fine).min(), lattice_edge(sphere_samples).min() / 2)
    assert len(fine) / len(sphere_samples) == pytest.approx(8.0, rel=0.1)


@pytest.mark.parametrize("pad, width", [(15.0, 4.0), (PAD, WIDTH), (0.3, 4.0)])
def test_samples_are_exactly_the_lattice_centres_within_pad(sphere, pad, width):
    """The octree keeps exactly the final-lattice centres within ``pad`` of a vertex, also
    where whole boxes are taken without a query (a wide pad: most of X is deep inside)."""
    s = octree_sample(sphere, pad, width)
    lo, hi = sphere.min(axis=0) - pad, sphere.max(axis=0) + pad
    root = float(np.max(hi - lo))
    origin = 0.5 * (lo + hi) - 0.5 * root
    levels = 0
    while root / 2.0**levels >= 0.5 * width:
        levels += 1
    n, edge = 2**levels, root / 2**levels
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    centres = origin + (idx + 0.5) * edge
    brute = centres[cKDTree(sphere).query(centres, distance_upper_bound=pad * 1.01)[0] <= pad]
    assert len(s) == len(brute) > 0
    np.testing.assert_array_equal(np.unique(s, axis=0), np.unique(brute, axis=0))


def test_circle_2d():
    rng = np.random.default_rng(2)
    c = circle(4_000, R)
    samples = octree_sample(c, PAD, WIDTH)
    assert samples.shape[1] == 2
    r = np.linalg.norm(samples, axis=1)
    assert r.min() >= R - PAD - ROUND and r.max() <= R + PAD + ROUND
    edge = lattice_edge(samples)
    e = edge.min()
    np.testing.assert_allclose(edge, e, rtol=1e-9)
    assert 0.25 * WIDTH <= e < 0.5 * WIDTH
    area = np.pi * ((R + PAD) ** 2 - (R - PAD) ** 2)
    assert len(samples) == pytest.approx(area / e**2, rel=0.15)
    h = 0.5 * e * np.sqrt(2)
    sv = covering_radius(c, rng)
    inner = uniform_shell(rng, 2_000, 2, R - PAD + h + sv, R + PAD - h - sv)
    assert cKDTree(samples).query(inner)[0].max() <= h + ROUND
    fine = octree_sample(c, PAD, WIDTH / 2)
    assert len(fine) / len(samples) == pytest.approx(4.0, rel=0.1)


def test_fraction_and_width_enter_as_product():
    c = circle(2_000, R)
    np.testing.assert_array_equal(
        octree_sample(c, PAD, WIDTH, fraction=0.25), octree_sample(c, PAD, WIDTH / 2)
    )


def test_translation_equivariance():
    c = circle(2_000, R)
    shift = np.array([-123.25, 47.5])
    np.testing.assert_allclose(
        octree_sample(c + shift, PAD, WIDTH), octree_sample(c, PAD, WIDTH) + shift, atol=1e-9
    )


def test_bounds_clip_and_large_bounds(sphere, sphere_samples):
    lo, hi = np.array([-30.0, -30.0, -30.0]), np.array([0.0, 30.0, 30.0])
    half = octree_sample(sphere, PAD, WIDTH, bounds=(lo, hi))
    assert np.all(half >= lo) and np.all(half <= hi)
    assert np.all(np.abs(np.linalg.norm(half, axis=1) - R) <= PAD + ROUND)
    e = lattice_edge(half).min()  # a different root cube, hence lattice
    volume = 4.0 / 3.0 * np.pi * ((R + PAD) ** 3 - (R - PAD) ** 3)
    assert len(half) == pytest.approx(volume / 2 / e**3, rel=0.15)
    # A field of view 40x wider only adds levels: the work and the result
    # still follow the shell volume.
    big = octree_sample(sphere, PAD, WIDTH, bounds=(np.full(3, -1000.0), np.full(3, 1000.0)))
    e = lattice_edge(big).min()
    assert 2.0 <= e < 4.0
    assert len(big) == pytest.approx(volume / e**3, rel=0.15)
    # Bounds that miss X give no samples.
    empty = octree_sample(sphere, PAD, WIDTH, bounds=(np.full(3, 100.0), np.full(3, 110.0)))
    assert empty.shape == (0, 3)


def test_several_surfaces():
    a = fibonacci_sphere(2_000, 5.0)
    b = a + np.array([40.0, 0.0, 0.0])
    samples = octree_sample(np.vstack([a, b]), 2.0, 2.0)
    d = np.minimum(np.linalg.norm(samples, axis=1), np.linalg.norm(samples - [40.0, 0, 0], axis=1))
    assert np.all(np.abs(d - 5.0) <= 2.0 + ROUND)
    near_a = np.linalg.norm(samples, axis=1) < 10
    assert 0.4 < near_a.mean() < 0.6


def test_samples_are_morton_ordered(sphere_samples):
    rng = np.random.default_rng(3)
    step = np.linalg.norm(np.diff(sphere_samples, axis=0), axis=1).mean()
    shuffled = sphere_samples[rng.permutation(len(sphere_samples))]
    random_step = np.linalg.norm(np.diff(shuffled, axis=0), axis=1).mean()
    assert step < 0.25 * random_step
    e = lattice_edge(sphere_samples).min()
    assert step < 2 * e


def test_morton_order_is_z_curve():
    # 4x4 grid, axis 0 in the lowest bit: the classic Z pattern.
    ij = np.array([(i, j) for j in range(4) for i in range(4)], dtype=float)
    order = morton_order(ij * 2.5 + 7.0, 2.5)
    expected = [(0, 0), (1, 0), (0, 1), (1, 1), (2, 0), (3, 0), (2, 1), (3, 1),
                (0, 2), (1, 2), (0, 3), (1, 3), (2, 2), (3, 2), (2, 3), (3, 3)]  # fmt: skip
    assert [tuple(map(int, p)) for p in ij[order]] == expected


def test_morton_order_permutation_and_locality():
    rng = np.random.default_rng(4)
    pts = rng.random((5_000, 3)) * 100.0
    order = morton_order(pts, 2.0)
    assert order.shape == (5_000,) and np.issubdtype(order.dtype, np.integer)
    np.testing.assert_array_equal(np.sort(order), np.arange(5_000))
    step = np.linalg.norm(np.diff(pts[order], axis=0), axis=1).mean()
    random_step = np.linalg.norm(np.diff(pts, axis=0), axis=1).mean()
    assert step < 0.25 * random_step
    assert morton_order(np.zeros((0, 2)), 1.0).shape == (0,)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"pad": 0.0}, "pad"),
        ({"pad": -1.0}, "pad"),
        ({"pad": np.nan}, "pad"),
        ({"width": 0.0}, "width"),
        ({"width": -2.0}, "width"),
        ({"fraction": 0.0}, "fraction"),
        ({"surface_points": np.zeros((0, 3))}, "surface_points"),
        ({"surface_points": np.array([[0.0, np.nan, 1.0]])}, "surface_points"),
        ({"surface_points": np.zeros((5, 4))}, "surface_points"),
        ({"surface_points": np.zeros((5, 1))}, "surface_points"),
        ({"surface_points": np.zeros(3)}, "surface_points"),
        ({"bounds": (np.zeros(2), np.ones(2))}, "bounds"),
        ({"bounds": (np.ones(3), np.zeros(3))}, "bounds"),
        ({"width": 1e-9}, "width"),
    ],
)
def test_bad_inputs_raise(kwargs, name):
    args = {"surface_points": circle(8, 1.0) @ np.eye(2, 3), "pad": 1.0, "width": 1.0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=f"`{name}`"):
        octree_sample(**args)


@pytest.mark.parametrize(
    ("points", "cell", "name"),
    [
        (np.zeros(3), 1.0, "points"),
        (np.array([[0.0, np.nan]]), 1.0, "points"),
        (np.zeros((3, 2)), 0.0, "cell"),
        (np.zeros((3, 2)), np.ones(3), "cell"),
        (np.array([[0.0, 0.0], [1e12, 0.0]]), 1e-9, "cell"),
    ],
)
def test_morton_bad_inputs_raise(points, cell, name):
    with pytest.raises(ValueError, match=f"`{name}`"):
        morton_order(points, cell)


def test_a_shared_tree_gives_the_same_samples(sphere):
    tree = cKDTree(sphere)
    for width in (40.0, 10.0, 4.0):
        np.testing.assert_array_equal(octree_sample(sphere, 3.0, width, tree=tree), octree_sample(sphere, 3.0, width))
    with pytest.raises(ValueError, match="`tree`"):
        octree_sample(sphere[:-1], 3.0, 10.0, tree=tree)

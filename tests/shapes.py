"""Analytic shapes with known signed distance, for tests (world mm, LPS)."""

from __future__ import annotations

import numpy as np

from volreg.grid import LabelVolume


class Ellipsoid:
    """Solid ellipsoid with semi-axes ``axes`` (mm) centred at ``centre``."""

    def __init__(self, axes, centre):
        self.axes = np.asarray(axes, float)
        self.centre = np.asarray(centre, float)

    def signed_distance(self, x: np.ndarray) -> np.ndarray:
        """Exact signed distance (mm, positive outside), by bisection on the
        Lagrange multiplier of the nearest-point problem (Eberly's method)."""
        p = np.abs(np.asarray(x, float) - self.centre)
        a2 = self.axes**2
        lo = np.full(len(p), -a2.min())
        hi = np.full(len(p), np.linalg.norm(p, axis=1) * self.axes.max() + 1.0)
        for _ in range(200):
            t = 0.5 * (lo + hi)
            with np.errstate(divide="ignore", invalid="ignore"):  # t = -a_min^2 on an axis
                f = np.sum((self.axes * p / (t[:, None] + a2)) ** 2, axis=1) - 1.0
            f = np.where(np.isnan(f), np.inf, f)
            pos = f > 0
            lo = np.where(pos, t, lo)
            hi = np.where(pos, hi, t)
        t = 0.5 * (lo + hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            nearest = np.where(p == 0, 0.0, a2 * p / (t[:, None] + a2))
        dist = np.linalg.norm(p - nearest, axis=1)
        inside = np.sum((p / self.axes) ** 2, axis=1) < 1.0
        return np.where(inside, -dist, dist)

    def surface_points(self, n: int, rng: np.random.Generator):
        """``n`` points on the surface and their outward unit normals."""
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        pts = u * self.axes
        nrm = pts / self.axes**2
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        return pts + self.centre, nrm


class Torus:
    """Solid torus about the axis ``z`` (major radius R, minor radius r, mm)."""

    def __init__(self, major, minor, centre):
        self.major, self.minor = float(major), float(minor)
        self.centre = np.asarray(centre, float)

    def signed_distance(self, x):
        p = np.asarray(x, float) - self.centre
        q = np.hypot(p[:, 0], p[:, 1]) - self.major
        return np.hypot(q, p[:, 2]) - self.minor

    def surface_points(self, n, rng):
        u, v = rng.uniform(0, 2 * np.pi, (2, n))
        nrm = np.stack([np.cos(u) * np.cos(v), np.sin(u) * np.cos(v), np.sin(v)], axis=1)
        ring = np.stack([np.cos(u), np.sin(u), np.zeros(n)], axis=1) * self.major
        return ring + self.minor * nrm + self.centre, nrm


class Disc2D:
    """2-D ellipse (semi-axes ``axes``) for outline tests."""

    def __init__(self, axes, centre):
        self.axes = np.asarray(axes, float)
        self.centre = np.asarray(centre, float)

    signed_distance = Ellipsoid.signed_distance

    def surface_points(self, n, rng):
        t = rng.uniform(0, 2 * np.pi, n)
        u = np.stack([np.cos(t), np.sin(t)], axis=1)
        pts = u * self.axes
        nrm = pts / self.axes**2
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        return pts + self.centre, nrm



def bumpy_ellipsoid_parts(bumps: int = 8) -> list:
    """The ellipsoids of :func:`bumpy_ellipsoid`: the body (semi-axes 20 / 14 / 10 mm), then
    the first ``bumps`` (0-8) of the eight small ones."""
    body = Ellipsoid((20, 14, 10), (0.37, -0.21, 0.13))
    extra = [Ellipsoid((6, 6, 6), (14.0, 8.0, 3.0)), Ellipsoid((5, 5, 5), (-6.0, -9.0, 7.0)),
             Ellipsoid((7, 5, 5), (-15.0, 4.0, -4.0)), Ellipsoid((5, 5, 6), (3.0, 6.0, -9.0)),
             Ellipsoid((5, 6, 5), (10.0, -8.0, -5.0)), Ellipsoid((6, 5, 5), (-10.0, 10.0, 6.0)),
             Ellipsoid((5, 5, 5), (18.0, -3.0, 4.0)), Ellipsoid((5, 5, 5), (-3.0, -2.0, 11.0))][:bumps]
    return [body] + extra


def bumpy_ellipsoid(bumps: int = 8):
    """Signed distance bound of an ellipsoid (semi-axes 20 / 14 / 10 mm) with the first
    ``bumps`` (0-8) of eight small ellipsoids attached: the union (min) of their distances.

    The known-deformation shapes (`tests/test_known_deformation.py`,
    `benchmarks/bench_register.py`); the bumps are the features that pin sliding.
    """
    parts = bumpy_ellipsoid_parts(bumps)

    def sdf(p):
        return np.min([e.signed_distance(p) for e in parts], axis=0)

    return sdf


def folded_blob_inside(points: np.ndarray, axes=(30.0, 36.0, 30.0), depth: float = 8.0,
                       wavelength: float = 14.0, seed: int = 7) -> np.ndarray:
    """Inside test of a folded, cortex-like blob at ``points`` (N, 3) mm.

    A point x at ellipsoidal radius rho = |x / axes| projects to q = x / rho on the envelope; it
    is inside where |x| < |q| - depth exp(-(s(q) / 0.4)^2), s a random sum of 10 plane waves of
    ``wavelength`` mm with unit variance: sulci ``depth`` mm deep along its zero set, about half a
    wavelength apart.
    """
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(10, 3))
    k *= (2 * np.pi / wavelength) / np.linalg.norm(k, axis=1, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, 10)
    rho = np.maximum(np.linalg.norm(points / np.asarray(axes), axis=1), 1e-9)
    q = points / rho[:, None]
    fold = np.cos(q @ k.T + phase) @ np.full(10, np.sqrt(2.0 / 10))
    dent = depth * np.exp(-((fold / 0.4) ** 2))
    return (np.linalg.norm(points, axis=1) < np.linalg.norm(q, axis=1) - dent) | (rho < 0.5)


def decimated_surface(surface, size: int):
    """A marching-cubes ``surface`` (its ``vertices`` and triangles ``cells``) decimated by VTK to
    about ``size`` vertices: ``.vertices`` (M, 3) mm and outward unit ``.normals`` (M, 3)."""
    from types import SimpleNamespace

    import pyvista as pv

    from volreg.morph import surface_normals

    cells = np.asarray(surface.cells)
    mesh = pv.PolyData(surface.vertices, np.c_[np.full(len(cells), 3), cells].ravel())
    if size < mesh.n_points:
        mesh = mesh.decimate(1.0 - size / mesh.n_points)
    mesh = mesh.triangulate().clean()
    pts = np.asarray(mesh.points, float)
    return SimpleNamespace(vertices=pts, normals=surface_normals(pts, np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]))


def rotation(angle_deg: float, axis=(0.3, 0.5, 0.8)) -> np.ndarray:
    """Rotation matrix about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, float)
    a /= np.linalg.norm(a)
    t = np.deg2rad(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


def label_volume(shape, spacing, direction, origin, sdf, label=1, dtype=np.uint8) -> LabelVolume:
    """A label volume holding ``label`` where ``sdf < 0`` at voxel centres."""
    geom = LabelVolume(np.zeros(shape, dtype=dtype), origin, spacing, direction)
    pts = geom.grid_points().reshape(-1, len(shape))
    inside = sdf(pts) < 0
    return geom.with_array((inside.reshape(shape) * label).astype(dtype))


def _inside_shape(shape, points):
    """Inside test of an Ellipsoid or Disc2D (fast; the labels only need the sign)."""
    return np.sum(((points - shape.centre) / shape.axes) ** 2, axis=1) < 1.0


def _shape_labels(shapes, points):
    """Label of every point: the index + 1 of the last shape holding it, 0 outside all."""
    out = np.zeros(len(points), dtype=np.uint8)
    for i, shape in enumerate(shapes):
        out[_inside_shape(shape, points)] = i + 1
    return out


def posed_volume(shapes, shape, spacing, origin, direction=None, matrix=None, translation=None) -> LabelVolume:
    """The labels of ``shapes`` posed by ``T: x -> matrix x + translation`` on a grid:
    ``volume(y) = labels(T^-1 y)`` at the voxel centres (identity when no map is given)."""
    d = len(shape)
    direction = np.eye(d) if direction is None else direction
    grid = LabelVolume(np.zeros(shape, np.uint8), origin, spacing, direction)
    points = grid.grid_points().reshape(-1, d)
    if matrix is not None:
        points = (points - translation) @ np.linalg.inv(matrix).T
    return grid.with_array(_shape_labels(shapes, points).reshape(shape))


def grid_around(centre, shape, spacing, direction=None):
    """Origin of a grid of ``shape`` x ``spacing`` whose middle is at ``centre`` (mm)."""
    d = len(shape)
    direction = np.eye(d) if direction is None else direction
    half = (np.array(shape) - 1) / 2.0 * np.asarray(spacing, float)
    return np.asarray(centre, float) - direction @ half


# Six blobs placed without symmetry (label i + 1 is BLOBS[i]); semi-axes and centres, mm.
BLOBS = [
    Ellipsoid((9, 7, 6), (-12, -8, 3)),
    Ellipsoid((7, 6, 8), (10, -10, -6)),
    Ellipsoid((6, 8, 5), (4, 12, 8)),
    Ellipsoid((8, 5, 6), (-9, 10, -8)),
    Ellipsoid((5, 6, 7), (16, 6, 4)),
    Ellipsoid((6, 5, 5), (-3, -2, -14)),
]


def ball_and_shifted_cube(whole_cube: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Label arrays (40^3, uint8) of a ball (label 1, radius 7 voxels) and a cube of 2^3 voxels
    (label 2) 10 voxels beside it, the cube shifted by 2 voxels along axis 0 in the second
    array; without ``whole_cube`` the cube lacks one voxel (7 voxels: too few for a surface)."""
    shape = (40, 40, 40)
    index = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    fixed = np.zeros(shape, np.uint8)
    fixed[np.linalg.norm(index - 14, axis=-1) < 7] = 1
    moving = fixed.copy()
    fixed[31:33, 13:15, 13:15] = 2
    moving[33:35, 13:15, 13:15] = 2
    if not whole_cube:
        fixed[32, 14, 14] = moving[34, 14, 14] = 0
    return fixed, moving


def thick_slice_pair():
    """One ellipsoid (semi-axes 6 / 5 / 12 mm) on 64 x 64 x 8 voxels of 0.3 x 0.3 x 5 mm, about
    five slices through it, and the same grid holding it stretched to 6.5 mm along x and moved
    0.6 mm: the pull-back map is x -> A (x - c) + c + t."""
    grid = LabelVolume(np.zeros((64, 64, 8), np.uint8), (0.0, 0.0, 0.0), (0.3, 0.3, 5.0), np.eye(3))
    centre, axes = np.array([9.6, 9.6, 20.0]), np.array([6.0, 5.0, 12.0])
    a, t = np.diag([6.5 / 6.0, 1.0, 1.0]), np.array([0.6, 0.0, 0.0])
    p = grid.grid_points().reshape(-1, 3)
    fixed = grid.with_array((np.sum(((p - centre) / axes) ** 2, axis=1) <= 1).astype(np.uint8).reshape(grid.shape))
    back = (p - centre - t) @ np.linalg.inv(a).T + centre  # the moving voxels' fixed-space positions
    moving = grid.with_array((np.sum(((back - centre) / axes) ** 2, axis=1) <= 1).astype(np.uint8).reshape(grid.shape))
    return fixed, moving, lambda x: (x - centre) @ a.T + centre + t

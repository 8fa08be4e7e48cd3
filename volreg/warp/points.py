"""Carrying points (landmarks, mesh vertices) through a warp, in either direction.

A registration ``volreg register FIXED MOVING`` gives the pull-back map ``tau``: a
fixed-space point ``x`` corresponds to ``tau(x)`` in moving space.  Points given in
fixed space are carried to moving space by ``tau`` itself, points given in moving
space to fixed space by ``tau^-1``.  :func:`transform_points` does either for the
three forms a saved result takes:

- a kernel warp (:class:`~volreg.warp.model.KernelWarp`): ``tau`` exactly, and
  ``tau^-1`` by Newton's method (:func:`~volreg.warp.inverse.invert_points`);
- a linear map (:class:`~volreg.linear_map.LinearMap`, e.g. ``linear.tfm``):
  ``A x + b`` and its exact inverse ``A^-1 (y - b)``;
- a displacement field on a grid (:class:`DisplacementField`): ``p + u(p)`` with
  ``u`` interpolated linearly at ``p``, as ITK's ``DisplacementFieldTransform``
  does.  A field holds one direction only: ``warp.nii.gz`` (on the fixed grid)
  carries fixed points to moving space, ``inverse_warp.nii.gz`` (on the moving
  grid) moving points to fixed space; a field is never inverted here.

Normals of a surface follow the map's Jacobian ``J``: ``n' = J^-T n``, rescaled to
the length ``n`` had (:func:`transform_normals`).

Pure functions on arrays: no files, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from volreg.grid import Grid, as_grid
from volreg.linear_map import LinearMap
from volreg.warp.inverse import InverseWarp, invert_points

__all__ = ["DisplacementField", "MappedPoints", "transform_points", "transform_normals"]


@dataclass(frozen=True, eq=False)
class DisplacementField:
    """A displacement field on a voxel grid, as the point map ``p -> p + u(p)``.

    ``u`` is interpolated linearly between voxel centres; within half a voxel of
    the grid's edge it takes the value of the edge voxel, and outside the grid
    (continuous index below ``-1/2`` or at or above ``n - 1/2`` on an axis) it is
    zero -- as ITK's ``DisplacementFieldTransform`` with its default linear
    interpolator, and so ANTs' ``antsApplyTransformsToPoints``.

    Parameters
    ----------
    displacement : (*grid.shape, D) float array_like, LPS mm
        ``u`` at the voxel centres (as :func:`volreg.io.fields.read_displacement` gives it).
    grid : Grid
        The field's grid (D = 2 or 3).
    """

    displacement: np.ndarray
    grid: Grid

    def __post_init__(self) -> None:
        grid = as_grid(self.grid, "grid")
        u = np.array(self.displacement, dtype=float)
        if u.shape != (*grid.shape, grid.ndim):
            raise ValueError(f"Expected `displacement` of shape {(*grid.shape, grid.ndim)} (grid, then D), got {u.shape}.")
        if not np.all(np.isfinite(u)):
            raise ValueError("Expected a finite `displacement`; it holds NaN or Inf.")
        u.flags.writeable = False
        object.__setattr__(self, "displacement", u)
        object.__setattr__(self, "grid", grid)

    @property
    def dim(self) -> int:
        """Number of spatial dimensions D."""
        return self.grid.ndim

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Whether each of ``points`` (N, D) mm lies on the field's grid, (N,) bool (see the class notes)."""
        index = self.grid.world_to_index(_as_points(points, self.dim))
        size = np.array(self.grid.shape, dtype=float)
        return np.all((index >= -0.5) & (index < size - 0.5), axis=1)

    def displacement_at(self, points: np.ndarray) -> np.ndarray:
        """``u`` at ``points`` (N, D) mm: linear interpolation, zero outside the grid; (N, D) LPS mm."""
        points = _as_points(points, self.dim)
        index = self.grid.world_to_index(points)
        size = np.array(self.grid.shape, dtype=float)
        inside = np.all((index >= -0.5) & (index < size - 0.5), axis=1)
        out = np.zeros_like(points)
        if inside.any():
            at = index[inside].T
            for d in range(self.dim):
                out[inside, d] = ndimage.map_coordinates(self.displacement[..., d], at, order=1, mode="nearest")
        return out

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """``p + u(p)`` at ``points``, (N, D) mm."""
        points = _as_points(points, self.dim)
        return points + self.displacement_at(points)

    def jacobian(self, points: np.ndarray) -> np.ndarray:
        """``d(p + u(p)) / dp`` at ``points`` by central differences of half the finest spacing, (N, D, D)."""
        points = _as_points(points, self.dim)
        h = 0.5 * float(np.min(self.grid.spacing))
        jac = np.empty((len(points), self.dim, self.dim))
        for b in range(self.dim):
            step = np.zeros(self.dim)
            step[b] = h
            jac[:, :, b] = (self(points + step) - self(points - step)) / (2.0 * h)
        return jac


@dataclass(frozen=True)
class MappedPoints:
    """Points carried through a map, with what the caller should know about them.

    Attributes
    ----------
    points : (N, D) float ndarray, LPS mm
        The carried points.
    outside : (N,) bool ndarray
        Points that lie outside a displacement field's grid, where its displacement
        is taken as zero (the point stays where it is); all False for other maps.
    residual : (N,) float ndarray, mm
        ``|tau(x) - y|`` of each point solved by the inverse of a kernel warp; zero otherwise.
    converged : (N,) bool ndarray
        ``residual <= tol``; all True unless an inverse solve stopped short.
    """

    points: np.ndarray
    outside: np.ndarray
    residual: np.ndarray
    converged: np.ndarray


def _as_points(points, dim: int) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != dim:
        raise ValueError(f"Expected `points` of shape (N, {dim}), got {p.shape}.")
    if not np.all(np.isfinite(p)):
        raise ValueError("Expected finite `points`; they hold NaN or Inf.")
    return p


def transform_points(warp, points: np.ndarray, *, inverse: bool = False, tol: float = 1e-6,
                     max_iter: int = 50) -> MappedPoints:
    """Carry points through a warp (``inverse=False``) or through its inverse.

    Parameters
    ----------
    warp : KernelWarp, ComposedWarp, LinearMap or DisplacementField
        The pull-back map ``tau`` (fixed point -> moving point) of a registration,
        or a displacement field (which maps in the one direction it was sampled for).
    points : (N, D) float array_like, LPS mm
        For ``inverse=False`` points ``x`` in the warp's source (fixed) space; for
        ``inverse=True`` points ``y`` in its target (moving) space.
    inverse : bool
        False: ``tau(x)``.  True: ``tau^-1(y)`` -- Newton's method for a kernel warp
        (:func:`~volreg.warp.inverse.invert_points`), ``A^-1 (y - b)`` for a linear
        map.  A displacement field cannot be inverted here: pass the field sampled
        for the other direction (``inverse_warp.nii.gz``) with ``inverse=False``.
    tol : float, mm
        Residual at which the inverse solve stops (kernel warps).
    max_iter : int
        Newton iterations at most (kernel warps).

    Returns
    -------
    MappedPoints

    Raises
    ------
    ValueError
        Points of the wrong shape or not finite, ``inverse=True`` with a
        displacement field, or a ``warp`` of another kind.
    """
    dim = getattr(warp, "dim", None)
    if dim is None:
        raise ValueError(f"Expected a KernelWarp, LinearMap or DisplacementField as `warp`, got {type(warp).__name__}.")
    p = _as_points(points, dim)
    n = len(p)
    outside = np.zeros(n, dtype=bool)
    residual = np.zeros(n)
    converged = np.ones(n, dtype=bool)
    if isinstance(warp, DisplacementField):
        if inverse:
            raise ValueError("A displacement field maps in one direction only; for the other, pass the field "
                             "sampled for it (inverse_warp.nii.gz) with inverse=False.")
        outside = ~warp.inside(p)
        out = warp(p)
    elif isinstance(warp, LinearMap):
        out = (warp.inverse() if inverse else warp)(p)
    elif hasattr(warp, "evaluate"):
        if inverse:
            sol = invert_points(warp, p, tol=tol, max_iter=max_iter)
            out, residual, converged = sol.points, sol.residual, sol.converged
        else:
            out = warp(p)
    else:
        raise ValueError(f"Expected a KernelWarp, LinearMap or DisplacementField as `warp`, got {type(warp).__name__}.")
    return MappedPoints(points=np.asarray(out, dtype=float), outside=outside, residual=residual, converged=converged)


def _jacobian(warp, points: np.ndarray, inverse: bool, mapped: np.ndarray | None) -> np.ndarray:
    """``d map / dp`` at the (source) ``points``, (N, D, D)."""
    n, dim = points.shape
    if isinstance(warp, DisplacementField):
        if inverse:
            raise ValueError("A displacement field maps in one direction only; for the other, pass the field "
                             "sampled for it (inverse_warp.nii.gz) with inverse=False.")
        return warp.jacobian(points)
    if isinstance(warp, LinearMap):
        a = np.linalg.inv(warp.matrix) if inverse else warp.matrix
        return np.broadcast_to(a, (n, dim, dim)).copy()
    if inverse:
        if mapped is None:
            return InverseWarp(warp).evaluate(points, order=1)[1]
        return np.linalg.inv(warp.evaluate(_as_points(mapped, dim), order=1)[1])  # J(x)^-1 at x = tau^-1(y)
    return warp.evaluate(points, order=1)[1]


def transform_normals(warp, points: np.ndarray, normals: np.ndarray, *, inverse: bool = False,
                      mapped: np.ndarray | None = None, keep_length: bool = True) -> np.ndarray:
    """Carry surface normals at ``points`` through the map of :func:`transform_points`.

    A normal is a covector: under a map with Jacobian ``J`` it becomes ``J^-T n``
    (the cofactor rule), which stays perpendicular to the carried surface.  Each
    result is rescaled to the length of its input (unit normals stay unit) unless
    ``keep_length`` is false.

    Parameters
    ----------
    warp : KernelWarp, ComposedWarp, LinearMap or DisplacementField
        As for :func:`transform_points`.
    points : (N, D) float array_like, LPS mm
        Where the normals sit, in the map's source space (before the map).
    normals : (N, D) float array_like
        The normals (any length; zero rows stay zero).
    inverse : bool
        As for :func:`transform_points`.
    mapped : (N, D) float array_like, mm, optional
        The carried points (``transform_points(...).points``): for the inverse of a
        kernel warp its Jacobian is then taken there instead of solving again.
    keep_length : bool
        Rescale each result to the length of its input (default); False gives ``J^-T n`` as it is.

    Returns
    -------
    (N, D) float ndarray
        The carried normals, LPS.
    """
    dim = getattr(warp, "dim", None)
    if dim is None:
        raise ValueError(f"Expected a KernelWarp, LinearMap or DisplacementField as `warp`, got {type(warp).__name__}.")
    p = _as_points(points, dim)
    nv = np.asarray(normals, dtype=float)
    if nv.shape != p.shape:
        raise ValueError(f"Expected `normals` of shape {p.shape} (one per point), got {nv.shape}.")
    jac = _jacobian(warp, p, inverse, mapped)
    out = np.linalg.solve(np.swapaxes(jac, 1, 2), nv[..., None])[..., 0]  # J^-T n
    if not keep_length:
        return out
    length = np.linalg.norm(nv, axis=1)
    new = np.linalg.norm(out, axis=1)
    scale = np.divide(length, new, out=np.zeros_like(length), where=new > 0)
    return out * scale[:, None]

"""The inverse of a kernel warp by Newton iteration with the analytic Jacobian.

A kernel warp ``tau(x) = L(x) + u(x)`` (:class:`~volreg.warp.KernelWarp`, with
linear part ``L(x) = A x + b``, the identity unless the warp has one) is smooth,
with an analytic Jacobian ``J = d tau / d x``; where it does not fold
(``det J > 0``) it is invertible, and ``tau^-1(y)`` is the root of
``r(x) = tau(x) - y``.  Newton's method solves it::

    z = L^-1(y),   x_0 = z - A^-1 u(z),   x_{n+1} = x_n - J(x_n)^-1 (tau(x_n) - y)

(``x_0 = y - u(y)`` without a linear part), converging quadratically once close.
Where ``det J`` is small (below ``min_det det A``, near a fold) the Newton step
is unreliable, so a damped fixed-point step ``x_{n+1} = x_n - A^-1 (tau(x_n) - y) / 2``
is taken instead; any step that does not reduce ``|r|`` is halved (up to a few
times).  The residual ``|tau(x) - y|`` of every point is returned, so callers
can state how exact the inverse is.

Outside the warp's support box ``B`` (fixed space) ``tau = L`` exactly.  So a
target ``y`` whose linear preimage ``L^-1(y)`` lies outside ``B`` -- a target
outside ``L(B)`` -- has that preimage (``tau(L^-1 y) = y``), the only one for a
warp without folds: it is not iterated.  The inverse is therefore exactly
``L^-1`` outside the bounding box of ``L(B)`` in moving space
(:meth:`InverseWarp.bounds`).

Not in the paper (Section 3 fits the forward warp only); used for the
consistency test (Section 5) and to carry points and images the other way.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from volreg._jit import njit
from volreg._threads import part_range, run_parts
from volreg.grid import apply_affine
from volreg.kernels import check_points
from volreg.kernels.grid import rows_within
from volreg.linear_map import LinearMap
from volreg.warp.model import _box_through, _PointMap, linear_outside
from volreg.warp.objective import _det_cofactor

__all__ = ["InverseSolution", "invert_points", "InverseWarp", "GridStart", "linear_part"]

ProgressCallback = Callable[[str, int, int], None]


@dataclass(frozen=True)
class InverseSolution:
    """Preimages of target points under a warp.

    Attributes
    ----------
    points : (N, D) float ndarray, mm
        ``x`` with ``tau(x) ~= y`` (LPS).
    residual : (N,) float ndarray, mm
        ``|tau(x) - y|``.
    iterations : int
        Newton iterations taken by the slowest point.
    converged : (N,) bool ndarray
        ``residual <= tol``.
    """

    points: np.ndarray
    residual: np.ndarray
    iterations: int
    converged: np.ndarray


def _in_box(points: np.ndarray, bounds) -> np.ndarray:
    if bounds is None:
        return np.zeros(len(points), dtype=bool)
    lo, hi = bounds
    return rows_within(points, lo, hi)


def linear_part(warp) -> LinearMap:
    """The linear part of a map, the identity for one without.

    Parameters
    ----------
    warp : KernelWarp, ComposedWarp, InverseWarp or any map with ``dim``
        A map with a ``linear`` attribute (a :class:`~volreg.linear_map.LinearMap` or None),
        or without one.

    Returns
    -------
    LinearMap
        ``warp.linear``, or ``LinearMap.identity(warp.dim)`` where that is missing or None.
    """
    linear = getattr(warp, "linear", None)
    return LinearMap.identity(warp.dim) if linear is None else linear


def invert_points(
    warp,
    targets: np.ndarray,
    *,
    tol: float = 1e-6,
    max_iter: int = 50,
    min_det: float = 0.05,
    chunk: int = 1 << 17,
    start: Callable[[np.ndarray], np.ndarray] | None = None,
    progress: ProgressCallback | None = None,
) -> InverseSolution:
    """Solve ``tau(x) = y`` for every target ``y`` (Newton, analytic Jacobian).

    Parameters
    ----------
    warp : KernelWarp or ComposedWarp
        Anything with ``evaluate(points, order=1) -> (tau, jacobian)``; a
        ``bounds()`` method (the box outside which the map equals its
        ``linear`` part, or the identity for a map without one) lets targets
        whose linear preimage lies outside it skip the iteration: their
        preimage is ``A^-1 (y - b)``.
    targets : (N, D) float array_like, mm
        Points ``y`` in the warp's target space (LPS).
    tol : float, mm
        Stop a point once ``|tau(x) - y| <= tol``.
    max_iter : int
        Iteration limit; points still above ``tol`` keep their best estimate
        and ``converged`` is False for them.
    min_det : float
        Below ``min_det * det A`` (``det A = 1`` without a linear part) the
        damped fixed-point step replaces Newton's.
    chunk : int
        Points solved at once (bounds temporary memory; the result does not
        depend on it).
    start : callable, optional
        ``start(y) -> x0``, (N, D) mm: starting points for Newton's method, NaN
        rows where it has none (e.g. :class:`GridStart`); those rows, and every
        row without ``start``, start from ``L^-1(y) - A^-1 u(L^-1(y))``.  A good
        start saves evaluations; the answer is the same to within ``tol``.  The
        starts are checked first without the Jacobian: a start within ``tol`` of
        its target costs one evaluation of ``tau`` alone (so a start pays where
        it is mostly within ``tol``, as :class:`GridStart`'s are).
        A start further off then takes up to :data:`CHORD_STEPS` chord steps
        (:func:`_chord_steps`: one evaluation of ``tau`` each, the linear part's
        matrix for the Jacobian), and the Jacobian and Newton's steps only where
        those do not reach ``tol``.
    progress : callable, optional
        ``progress("invert warp", done, total)`` after each chunk.

    Returns
    -------
    InverseSolution
    """
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"Expected `tol` > 0, got {tol!r}.")
    if int(max_iter) < 1:
        raise ValueError(f"Expected `max_iter` >= 1, got {max_iter!r}.")
    y_all = check_points("targets", targets, warp.dim)
    affine, x_all, res_all, inside = _linear_preimages(warp, y_all)
    if affine is None:
        a_inv, det_floor = np.eye(warp.dim), min_det
    else:
        a_inv, det_floor = np.linalg.inv(affine.matrix), min_det * float(np.linalg.det(affine.matrix))
    worst_iter = 0
    for s in range(0, len(inside), chunk):
        idx = inside[s : s + chunk]
        y = y_all[idx]
        x = _starting_points(warp, y, x_all[idx], affine, a_inv, start)
        rn, it = _solve(warp, x, y, tol, max_iter, det_floor, a_inv, started=start is not None)
        worst_iter = max(worst_iter, it)
        x_all[idx] = x
        res_all[idx] = rn
        if progress is not None:
            progress("invert warp", min(s + chunk, len(inside)), len(inside))
    return InverseSolution(points=x_all, residual=res_all, iterations=worst_iter, converged=res_all <= tol)


def _linear_preimages(warp, y_all: np.ndarray) -> tuple[LinearMap | None, np.ndarray, np.ndarray, np.ndarray]:
    """The preimages of the targets that lie beyond the warp's box, and the targets left to solve.

    Outside its box (``bounds()``) the warp is its linear part ``L``: a target whose linear
    preimage ``L^-1(y)`` lies outside the box has that preimage, exactly (the target itself
    for a warp without a linear part).

    Returns
    -------
    affine : LinearMap or None
        The linear part, None where it is the identity.
    x_all : (N, D) float ndarray, mm
        ``L^-1(y)`` for every target (``y`` without a linear part): the answer outside the box.
    res_all : (N,) float ndarray, mm
        ``|L(x) - y|`` there (rounding only), 0 elsewhere.
    inside : (K,) int ndarray
        The targets to solve by Newton's method.
    """
    n = len(y_all)
    bounds, linear = linear_outside([warp])
    if linear.is_identity:
        # tau = identity outside the box: targets there are their own preimages, exactly
        x_all = y_all.copy()
        res_all = np.zeros(n)
        return None, x_all, res_all, np.flatnonzero(_in_box(y_all, bounds))
    x_all = linear.inverse()(y_all)  # the preimage wherever it lies outside the box
    inside = _in_box(x_all, bounds)
    res_all = np.zeros(n)
    res_all[~inside] = np.linalg.norm(linear(x_all[~inside]) - y_all[~inside], axis=1)  # rounding only
    return linear, x_all, res_all, np.flatnonzero(inside)


def _starting_points(warp, y: np.ndarray, z: np.ndarray, affine: LinearMap | None, a_inv: np.ndarray,
                     start: Callable[[np.ndarray], np.ndarray] | None) -> np.ndarray:
    """Newton's starting points (N, D) mm for targets ``y`` (N, D) mm with linear preimages ``z``.

    ``start(y)`` where given, and where it has none (NaN or Inf rows), or without it,
    ``x0 = z - A^-1 u(z)`` (``x0 = y - u(y)`` without a linear part).
    """
    x = np.full_like(y, np.nan) if start is None else np.asarray(start(y), dtype=float).reshape(y.shape)
    fresh = np.flatnonzero(~np.isfinite(x @ np.ones(x.shape[1])))  # rows holding NaN or Inf
    if fresh.size:
        yf = y[fresh]
        if affine is None:
            tau_y, = warp.evaluate(yf, order=0)
            x[fresh] = 2.0 * yf - tau_y  # x0 = y - u(y)
        else:
            zf = z[fresh]  # L^-1(y)
            tau_z, = warp.evaluate(zf, order=0)
            x[fresh] = zf - (tau_z - yf) @ a_inv.T  # x0 = z - A^-1 u(z), as tau(z) - y = u(z) up to rounding
    return x


def _solve(warp, x: np.ndarray, y: np.ndarray, tol: float, max_iter: int, det_floor: float, a_inv: np.ndarray,
           *, started: bool) -> tuple[np.ndarray, int]:
    """Solve ``tau(x) = y`` from ``x`` (in place), with chord steps first where ``started``.

    Returns
    -------
    rn : (N,) float ndarray, mm
        ``|tau(x) - y|`` at the points found.
    iterations : int
        Newton iterations taken.
    """
    if not started:
        tau_x, jac = warp.evaluate(x, order=1)
    else:  # the Jacobian only where the start is not within tol already
        tau_x, = warp.evaluate(x, order=0)
        jac = np.empty((len(y), warp.dim, warp.dim))
    r = tau_x - y
    rn = np.linalg.norm(r, axis=1)
    active = np.flatnonzero(rn > tol)
    if started and active.size:
        active = _chord_steps(warp, x, r, rn, y, active, tol, a_inv)
    if started and active.size:
        _, jac[active] = warp.evaluate(x[active], order=1)
    return rn, _newton_iterations(warp, x, r, rn, jac, y, active, tol, max_iter, det_floor, a_inv)


def _newton_iterations(warp, x: np.ndarray, r: np.ndarray, rn: np.ndarray, jac: np.ndarray, y: np.ndarray,
                       active: np.ndarray, tol: float, max_iter: int, det_floor: float, a_inv: np.ndarray) -> int:
    """Newton's steps (:func:`_newton_steps`) at the rows ``active`` until each is within ``tol``
    or stuck, at most ``max_iter``; ``x``, the residuals ``r``, their norms ``rn`` and the
    Jacobians ``jac`` are updated in place.  Returns the iterations taken."""
    it = 0
    while active.size and it < max_iter:
        it += 1
        xa, ra, ja, rna = x[active], r[active], jac[active], rn[active]
        step = _newton_steps(ja, ra, det_floor, a_inv)
        scale = np.ones(len(active))
        for _ in range(6):  # halve steps that do not reduce the residual
            xn = xa + scale[:, None] * step
            tn, = warp.evaluate(xn, order=0)
            rnew = tn - y[active]
            rnn = np.linalg.norm(rnew, axis=1)
            worse = rnn >= rna
            if not worse.any():
                break
            scale[worse] *= 0.5
        better = rnn < rna
        upd = active[better]
        x[upd], r[upd], rn[upd] = xn[better], rnew[better], rnn[better]
        # points that could not improve are stuck: drop them (their residual says so)
        active = upd[rn[upd] > tol]
        if active.size and it < max_iter:  # the Jacobian only where another step follows
            _, jac[active] = warp.evaluate(x[active], order=1)
    return it


#: Chord steps (:func:`_chord_steps`) tried from a start before Newton's method.
CHORD_STEPS = 2


def _chord_steps(warp, x: np.ndarray, r: np.ndarray, rn: np.ndarray, y: np.ndarray, active: np.ndarray,
                 tol: float, a_inv: np.ndarray) -> np.ndarray:
    """Up to :data:`CHORD_STEPS` steps ``x <- x - A^-1 (tau(x) - y)`` at the rows ``active`` (in
    place in ``x``, the residuals ``r`` and their norms ``rn``); the rows Newton's method must
    still take on.

    The linear part's matrix ``A`` stands in for the Jacobian ``J = A (I + du/dx)``: each step
    costs one evaluation of ``tau`` without the Jacobian (about half the cost of one with it) and
    shrinks the error by about ``|du/dx|``, so from a start a few micrometres off (as
    :class:`GridStart`'s are where they miss the tolerance) one or two steps reach it.  A row a
    step does not improve (near a fold, where ``du/dx`` is large) keeps its value and is left to
    Newton's method.
    """
    newton = []
    for _ in range(CHORD_STEPS):
        if not active.size:
            break
        xa = x[active] - r[active] @ a_inv.T
        ta, = warp.evaluate(xa, order=0)
        ra = ta - y[active]
        rna = np.linalg.norm(ra, axis=1)
        better = rna < rn[active]
        newton.append(active[~better])
        upd = active[better]
        x[upd], r[upd], rn[upd] = xa[better], ra[better], rna[better]
        active = upd[rn[upd] > tol]
    return np.sort(np.concatenate(newton + [active]))


def _newton_steps(jac: np.ndarray, r: np.ndarray, det_floor: float, a_inv: np.ndarray) -> np.ndarray:
    """Per row, the Newton step ``-J^-1 r`` where ``det J > det_floor``, else the damped
    fixed-point step ``-A^-1 r / 2``.

    ``J^-1 = cof(J)^T / det J`` from the objective's cofactors, row-wise in NumPy (no per-row
    LAPACK call, and no compiled loop for a first run to compile: the rows are the few voxels
    whose start was not within the tolerance).

    Parameters
    ----------
    jac : (N, D, D) float ndarray
    r : (N, D) float ndarray, mm
    det_floor : float
    a_inv : (D, D) float ndarray

    Returns
    -------
    (N, D) float ndarray, mm
    """
    det, cof = _det_cofactor(jac)
    newton = det > det_floor
    step = -0.5 * apply_affine(r, a_inv, np.zeros(r.shape[1]))
    step[newton] = -np.einsum("nba,nb->na", cof[newton], r[newton]) / det[newton, None]
    return step


class InverseWarp(_PointMap):
    """``tau^-1`` of a kernel warp as a point map (evaluated by :func:`invert_points`).

    ``InverseWarp(warp)(y)`` gives the preimages (also ``displacement`` and
    ``jacobian``, as for a warp); ``evaluate(y, order=1)``
    also gives the Jacobian of the inverse, ``J(x)^-1`` at ``x = tau^-1(y)``.
    Its box (:meth:`bounds`, moving space) and :attr:`linear` part follow from
    the warp's, so the grid functions of :mod:`volreg.warp.field` sample it like
    a warp.  ``max_residual`` holds the largest ``|tau(x) - y|`` (mm) seen by the
    evaluations so far.

    Parameters
    ----------
    warp : KernelWarp or ComposedWarp
    tol, max_iter, min_det, start : see :func:`invert_points`
    """

    def __init__(self, warp, *, tol: float = 1e-6, max_iter: int = 50, min_det: float = 0.05,
                 start: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        self.warp = warp
        self.dim = warp.dim
        self.tol, self.max_iter, self.min_det = tol, max_iter, min_det
        self.start = start
        self.max_residual = 0.0
        self.unconverged = 0
        self._tally = threading.Lock()  # evaluations may run on several threads (volreg.warp.field)

    @property
    def linear(self) -> LinearMap:
        """``L^-1``, the inverse of the warp's linear part: the inverse map outside :meth:`bounds`."""
        linear = linear_part(self.warp)
        return linear if linear.is_identity else linear.inverse()

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Corners ``(lo, hi)``, each (D,) mm in MOVING space, of a box outside which the inverse is linear.

        The bounding box of ``L(B)``, the warp's box ``B`` (fixed space) under its
        linear part ``L`` (``B`` itself without one): a target outside it has its
        preimage ``L^-1(y)`` outside ``B``, where ``tau = L``.  ``None`` when the
        warp is linear everywhere; an infinite box when the warp has no
        ``bounds`` (nothing is known: every point is evaluated).
        """
        if not hasattr(self.warp, "bounds"):
            return np.full(self.dim, -np.inf), np.full(self.dim, np.inf)
        box = self.warp.bounds()
        linear = linear_part(self.warp)
        if box is None or linear.is_identity:
            return box
        return _box_through(box, linear)

    def evaluate(self, points: np.ndarray, *, order: int = 1, chunk: int | None = None, progress=None):
        """``tau^-1(points)`` and (``order == 1``) its Jacobian, (N, D) and (N, D, D)."""
        sol = invert_points(
            self.warp, points, tol=self.tol, max_iter=self.max_iter, min_det=self.min_det, start=self.start,
            progress=progress,
            **({} if chunk is None else {"chunk": chunk}),
        )
        worst = float(sol.residual.max()) if len(sol.residual) else 0.0
        missed = int(np.count_nonzero(~sol.converged))
        with self._tally:
            self.max_residual = max(self.max_residual, worst)
            self.unconverged += missed
        if order == 0:
            return (sol.points,)
        _, jac = self.warp.evaluate(sol.points, order=1)
        return sol.points, np.linalg.inv(jac)


@njit(nogil=True)
def _grid_fixed_point(part, parts, u, w2i, w2i_offset, a_inv, b, y, max_iter, settle, out):
    """Fixed-point solve of ``x + U(x) = y`` with ``U`` the trilinear interpolation of ``u`` (in place).

    ``u`` (X, Y, Z, 3) mm on a grid whose continuous index is ``w2i @ x + w2i_offset``;
    ``x_0 = a_inv (y - b)``, ``x_{k+1} = x_k - a_inv (x_k + U(x_k) - y)``.  ``out[p]`` is the
    iterate once a step moves it less than ``settle``, NaN if it leaves the grid or does
    not settle within ``max_iter`` steps.
    """
    nx, ny, nz = u.shape[0], u.shape[1], u.shape[2]
    first, stop = part_range(y.shape[0], part, parts)
    for p in range(first, stop):
        x = np.empty(3)
        r = np.empty(3)
        for a in range(3):
            x[a] = a_inv[a, 0] * (y[p, 0] - b[0]) + a_inv[a, 1] * (y[p, 1] - b[1]) + a_inv[a, 2] * (y[p, 2] - b[2])
        done = False
        for _ in range(max_iter):
            fi = w2i[0, 0] * x[0] + w2i[0, 1] * x[1] + w2i[0, 2] * x[2] + w2i_offset[0]
            fj = w2i[1, 0] * x[0] + w2i[1, 1] * x[1] + w2i[1, 2] * x[2] + w2i_offset[1]
            fk = w2i[2, 0] * x[0] + w2i[2, 1] * x[1] + w2i[2, 2] * x[2] + w2i_offset[2]
            if not (0.0 <= fi <= nx - 1 and 0.0 <= fj <= ny - 1 and 0.0 <= fk <= nz - 1):
                break
            i0 = min(int(fi), max(nx - 2, 0))
            j0 = min(int(fj), max(ny - 2, 0))
            k0 = min(int(fk), max(nz - 2, 0))
            ti, tj, tk = fi - i0, fj - j0, fk - k0
            i1, j1, k1 = min(i0 + 1, nx - 1), min(j0 + 1, ny - 1), min(k0 + 1, nz - 1)
            for a in range(3):
                c00 = u[i0, j0, k0, a] * (1 - ti) + u[i1, j0, k0, a] * ti
                c10 = u[i0, j1, k0, a] * (1 - ti) + u[i1, j1, k0, a] * ti
                c01 = u[i0, j0, k1, a] * (1 - ti) + u[i1, j0, k1, a] * ti
                c11 = u[i0, j1, k1, a] * (1 - ti) + u[i1, j1, k1, a] * ti
                c0 = c00 * (1 - tj) + c10 * tj
                c1 = c01 * (1 - tj) + c11 * tj
                r[a] = x[a] + c0 * (1 - tk) + c1 * tk - y[p, a]
            moved = 0.0
            for a in range(3):
                step = -(a_inv[a, 0] * r[0] + a_inv[a, 1] * r[1] + a_inv[a, 2] * r[2])
                x[a] += step
                moved += step * step
            if moved < settle * settle:
                done = True
                break
        for a in range(3):
            out[p, a] = x[a] if done else np.nan


class GridStart:
    """Starting points for :func:`invert_points` from the forward warp sampled on a grid.

    Solves ``tau(x) = y`` approximately by the fixed-point iteration
    ``x_{k+1} = x_k - A^-1 (x_k + U(x_k) - y)`` on ``U``, the trilinear
    interpolation of the displacement ``u = tau - id`` on ``grid`` (which the
    outputs compute anyway), from ``x_0 = L^-1(y)``.  Each step costs one
    interpolation instead of kernel sums; Newton's method then needs about one
    exact step from the result (the interpolated displacement is close to the
    warp's between voxel centres).  Rows whose iterates leave the grid, or have
    not settled to ``settle`` mm within ``iterations`` steps (near a fold), are
    NaN: no start.

    Parameters
    ----------
    displacement : (*grid.shape, D) float ndarray, mm
        ``u(x) = tau(x) - x`` at the voxel centres of ``grid`` (LPS), D = 2 or 3.
    grid : Grid or LabelVolume
        Where ``displacement`` was sampled (fixed space).
    linear : LinearMap
        The warp's linear part ``L(x) = A x + b`` (the identity for a warp without).
    iterations : int
        Fixed-point steps at most.
    settle : float, mm
        A row is done once a step moves it less than this.
    """

    def __init__(self, displacement: np.ndarray, grid, linear: LinearMap, *, iterations: int = 20,
                 settle: float = 1e-4) -> None:
        dim = grid.ndim
        if displacement.shape != tuple(grid.shape) + (dim,):
            raise ValueError(f"Expected `displacement` of shape {tuple(grid.shape) + (dim,)}, got {displacement.shape}.")
        # a 2-D grid is the slice z = 0 of a 3-D one, with no displacement along z
        m = np.eye(3)
        m[:dim, :dim] = (np.asarray(grid.direction) * np.asarray(grid.spacing)[None, :])  # index -> world
        origin = np.zeros(3)
        origin[:dim] = grid.origin
        a = np.eye(3)
        a[:dim, :dim] = linear.matrix
        b = np.zeros(3)
        b[:dim] = linear.translation
        u = displacement
        if dim == 2:
            u = np.zeros(tuple(grid.shape) + (1, 3))
            u[:, :, 0, :2] = displacement
        self._u = np.ascontiguousarray(u, dtype=float)
        self._w2i = np.linalg.inv(m)
        self._w2i_offset = -self._w2i @ origin
        self._a_inv = np.linalg.inv(a)
        self._b = b
        self.dim = dim
        self.iterations, self.settle = int(iterations), float(settle)

    def __call__(self, y: np.ndarray) -> np.ndarray:
        """Starting points ``x0`` (N, D) mm for targets ``y`` (N, D) mm; NaN rows where there is none."""
        y = np.asarray(y, dtype=float)
        y3 = np.zeros((len(y), 3))
        y3[:, : self.dim] = y
        out = np.empty_like(y3)
        run_parts(_grid_fixed_point, len(y3), self._u, self._w2i, self._w2i_offset, self._a_inv, self._b, y3,
                  self.iterations, self.settle, out, grain=256)
        return out[:, : self.dim].copy()

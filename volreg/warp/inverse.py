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

from dataclasses import dataclass
from typing import Callable

import numpy as np

from volreg.kernels import _check_points
from volreg.warp.linear import LinearMap
from volreg.warp.model import _box_through, _PointMap, linear_outside

__all__ = ["InverseSolution", "invert_points", "InverseWarp"]

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
    return np.all((points >= lo) & (points <= hi), axis=1)


def _linear_of(warp) -> LinearMap:
    """The linear part of a map (the identity for one without)."""
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
    y_all = _check_points("targets", targets, warp.dim)
    n = len(y_all)
    bounds, linear = linear_outside([warp])
    if linear.is_identity:
        # tau = identity outside the box: targets there are their own preimages, exactly
        affine = None
        x_all = y_all.copy()
        res_all = np.zeros(n)
        inside = np.flatnonzero(_in_box(y_all, bounds))
        det_floor = min_det
    else:
        affine = linear
        a_inv = np.linalg.inv(linear.matrix)
        x_all = linear.inverse()(y_all)  # the preimage wherever it lies outside the box
        inside = _in_box(x_all, bounds)
        res_all = np.zeros(n)
        res_all[~inside] = np.linalg.norm(linear(x_all[~inside]) - y_all[~inside], axis=1)  # rounding only
        inside = np.flatnonzero(inside)
        det_floor = min_det * float(np.linalg.det(linear.matrix))
    worst_iter = 0
    for s in range(0, len(inside), chunk):
        idx = inside[s : s + chunk]
        y = y_all[idx]
        if affine is None:
            tau_y, = warp.evaluate(y, order=0)
            x = 2.0 * y - tau_y  # x0 = y - u(y)
        else:
            z = x_all[idx]  # L^-1(y)
            tau_z, = warp.evaluate(z, order=0)
            x = z - (tau_z - y) @ a_inv.T  # x0 = z - A^-1 u(z), as tau(z) - y = u(z) up to rounding
        tau_x, jac = warp.evaluate(x, order=1)
        r = tau_x - y
        rn = np.linalg.norm(r, axis=1)
        active = np.flatnonzero(rn > tol)
        it = 0
        while active.size and it < max_iter:
            it += 1
            xa, ra, ja, rna = x[active], r[active], jac[active], rn[active]
            det = np.linalg.det(ja)
            step = -0.5 * ra if affine is None else -0.5 * ra @ a_inv.T
            good = det > det_floor
            if good.any():
                step[good] = -np.linalg.solve(ja[good], ra[good][..., None])[..., 0]
            scale = np.ones(len(active))
            for _ in range(6):  # halve steps that do not reduce the residual
                xn = xa + scale[:, None] * step
                tn, jn = warp.evaluate(xn, order=1)
                rnew = tn - y[active]
                rnn = np.linalg.norm(rnew, axis=1)
                worse = rnn >= rna
                if not worse.any():
                    break
                scale[worse] *= 0.5
            better = rnn < rna
            upd = active[better]
            x[upd], r[upd], jac[upd], rn[upd] = xn[better], rnew[better], jn[better], rnn[better]
            # points that could not improve are stuck: drop them (their residual says so)
            active = upd[rn[upd] > tol]
        worst_iter = max(worst_iter, it)
        x_all[idx] = x
        res_all[idx] = rn
        if progress is not None:
            progress("invert warp", min(s + chunk, len(inside)), len(inside))
    return InverseSolution(points=x_all, residual=res_all, iterations=worst_iter, converged=res_all <= tol)


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
    tol, max_iter, min_det : see :func:`invert_points`
    """

    def __init__(self, warp, *, tol: float = 1e-6, max_iter: int = 50, min_det: float = 0.05) -> None:
        self.warp = warp
        self.dim = warp.dim
        self.tol, self.max_iter, self.min_det = tol, max_iter, min_det
        self.max_residual = 0.0
        self.unconverged = 0

    @property
    def linear(self) -> LinearMap:
        """``L^-1``, the inverse of the warp's linear part: the inverse map outside :meth:`bounds`."""
        linear = _linear_of(self.warp)
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
        linear = _linear_of(self.warp)
        if box is None or linear.is_identity:
            return box
        return _box_through(box, linear)

    def evaluate(self, points: np.ndarray, *, order: int = 1, chunk: int | None = None, progress=None):
        """``tau^-1(points)`` and (``order == 1``) its Jacobian, (N, D) and (N, D, D)."""
        sol = invert_points(
            self.warp, points, tol=self.tol, max_iter=self.max_iter, min_det=self.min_det, progress=progress,
            **({} if chunk is None else {"chunk": chunk}),
        )
        if len(sol.residual):
            self.max_residual = max(self.max_residual, float(sol.residual.max()))
        self.unconverged += int(np.count_nonzero(~sol.converged))
        if order == 0:
            return (sol.points,)
        _, jac = self.warp.evaluate(sol.points, order=1)
        return sol.points, np.linalg.inv(jac)

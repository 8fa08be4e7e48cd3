"""A moving object's feature seen through the linear part of the map.

With the map ``tau(x) = L(phi(x))``, ``L(y) = A y + b`` the linear stage and ``phi`` the
kernel warp (paper eq. 9), the locational cost (3)-(4) compares ``f1(x)`` with
``f2(tau(x)) = f2(L(phi(x)))``.  :class:`LinearlyMapped` is ``f2 o L``, divided by the
linear part's mean scale ``s = det(A)^(1/D)`` so that it stays a signed distance in the
fixed object's millimetres: for a similarity ``L`` and a moving object that is exactly
``L`` of the fixed one, ``f2(L(x)) / s = f1(x)`` and ``grad (f2 o L) / s = A^T grad f2 / s``
is the fixed object's normal -- the gradient term (4) compares normals *after* undoing the
rotation, and the kernel warp is left only the local deformation.
"""

from __future__ import annotations

import numpy as np

__all__ = ["LinearlyMapped"]


def congruence(h: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``A^T H_n A`` for every (D, D) matrix ``H_n`` of ``h`` (N, D, D): the Hessian of ``f o L``
    from that of ``f``.  As a stacked matrix product (numpy's einsum of the three operands is
    slower)."""
    return np.matmul(np.matmul(a.T, h), a)


class LinearlyMapped:
    """``g(y) = f(A y + b) / s``, with ``s = det(A)^(1/D)``, and its derivatives.

    Parameters
    ----------
    feature : object
        A feature with ``evaluate(points, order=...) -> (f, grad f[, hess f])`` in mm
        (e.g. :class:`~volreg.features.implicit.ImplicitSurface`,
        :class:`~volreg.features.distance_maps.VoxelDistance`).
    linear : LinearMap
        ``y -> A y + b`` (fixed space to the feature's space), ``det A > 0``.
    """

    def __init__(self, feature, linear) -> None:
        self.feature = feature
        self.linear = linear
        self._matrix = np.asarray(linear.matrix, dtype=float)
        self._scale = float(np.linalg.det(self._matrix)) ** (1.0 / self._matrix.shape[0])

    def evaluate(self, points: np.ndarray, order: int = 1) -> tuple[np.ndarray, ...]:
        """``g``, and up to ``order`` (0, 1 or 2) of its gradient (N, D) and Hessian (N, D, D).

        Parameters
        ----------
        points : (N, D) float ndarray, mm (fixed space)
        order : {0, 1, 2}
        """
        a, s = self._matrix, self._scale
        out = self.feature.evaluate(self.linear(points), order=order)
        res = [np.asarray(out[0]) / s]
        if order >= 1:
            res.append(np.asarray(out[1]) @ a / s)  # rows: A^T grad f
        if order >= 2:
            res.append(congruence(np.asarray(out[2]), a) / s)
        return tuple(res)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """``g(points)``, (N,) mm."""
        return self.evaluate(points, order=0)[0]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """A box (lo, hi) in fixed space holding the preimage of the feature's ``bounds()``."""
        lo, hi = (np.asarray(v, float) for v in self.feature.bounds())
        dim = len(lo)
        corners = np.array(np.meshgrid(*[[0, 1]] * dim, indexing="ij")).reshape(dim, -1).T
        pts = self.linear.inverse()(lo + corners * (hi - lo))
        return pts.min(axis=0), pts.max(axis=0)

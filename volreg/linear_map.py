"""The linear map ``x -> A x + b`` in world millimetres (LPS), ``det A > 0``.

The linear part of a registration's map ``tau(x) = A x + b + sum_j c_j k(x, x_j)``
(:func:`~volreg.warp.linear.fit_linear` finds it), and a linear transform as ITK's
transform files hold it (:mod:`volreg.io.fields`).  It lives beside the grid, below
the readers and the warp, so that both can use it.  Points are ``(N, D)`` arrays,
D = 2 or 3; the map is a pull-back (fixed point -> moving point), as ITK's transforms are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from volreg.grid import apply_affine

__all__ = ["LinearMap"]


def _as_matrix(matrix) -> np.ndarray:
    a = np.array(matrix, dtype=float)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or a.shape[0] not in (2, 3):
        raise ValueError(f"Expected `matrix` of shape (D, D) with D = 2 or 3, got {a.shape}.")
    if not np.all(np.isfinite(a)):
        raise ValueError("Expected finite values in `matrix`, found NaN or Inf.")
    det = float(np.linalg.det(a))
    if not det > 0:
        raise ValueError(f"Expected `matrix` with a positive determinant (no reflection, no collapse), got {det:.3g}.")
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class LinearMap:
    """The map ``x -> matrix @ x + translation`` in world mm (LPS).

    Parameters
    ----------
    matrix : (D, D) float array_like
        ``A``; its determinant must be positive (orientation kept).
    translation : (D,) float array_like, mm
        ``b``.
    """

    matrix: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        a = _as_matrix(self.matrix)
        b = np.array(self.translation, dtype=float).reshape(-1)
        if b.shape != (a.shape[0],) or not np.all(np.isfinite(b)):
            raise ValueError(f"Expected a finite `translation` of shape ({a.shape[0]},), got {np.shape(self.translation)}.")
        b.flags.writeable = False
        object.__setattr__(self, "matrix", a)
        object.__setattr__(self, "translation", b)

    @classmethod
    def identity(cls, dim: int) -> "LinearMap":
        """``x -> x`` in ``dim`` dimensions."""
        return cls(np.eye(dim), np.zeros(dim))

    @property
    def dim(self) -> int:
        """Number of spatial dimensions D."""
        return int(self.matrix.shape[0])

    @property
    def is_identity(self) -> bool:
        """Whether the map is ``x -> x`` exactly."""
        return bool(np.array_equal(self.matrix, np.eye(self.dim)) and not np.any(self.translation))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """``A x + b`` at ``points``, (N, D) mm."""
        return apply_affine(points, self.matrix, self.translation)

    def inverse(self) -> "LinearMap":
        """``y -> A^-1 (y - b)``."""
        inv = np.linalg.inv(self.matrix)
        return LinearMap(inv, -inv @ self.translation)

    def then(self, other: "LinearMap") -> "LinearMap":
        """The map ``x -> other(self(x))``."""
        return LinearMap(other.matrix @ self.matrix, other.matrix @ self.translation + other.translation)

    def describe(self) -> dict:
        """What a reviewer reads off the map (JSON-ready).

        Returns
        -------
        dict
            ``matrix`` (D x D), ``translation`` (mm), ``rotation_deg`` (angle of the
            rotation ``R`` of the polar decomposition ``A = R S``), ``scales`` (the
            eigenvalues of the symmetric stretch ``S``, largest first) and ``determinant``
            (the volume ratio, moving to fixed).
        """
        a = self.matrix
        u, s, vt = np.linalg.svd(a)
        rot = u @ vt  # det(A) > 0 gives det(rot) = +1
        cos = (np.trace(rot) - (self.dim - 2)) / 2 if self.dim == 3 else rot[0, 0]
        angle = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        return dict(
            matrix=a.tolist(),
            translation=self.translation.tolist(),
            rotation_deg=angle,
            scales=[float(v) for v in s],
            determinant=float(np.linalg.det(a)),
        )

"""Known smooth deformations, for tests, the demo and benchmarks (ground truth).

:class:`GaussianBumps` is ``tau(x) = x + sum_k a_k exp(-|x - p_k|^2 / (2 s^2))``:
smooth, invertible when ``max |grad u| < 1`` (checked), with an exact
Jacobian and an inverse by fixed-point iteration.  :func:`deform_labels`
makes the moving volume of a pair whose true pull-back warp is ``tau``:
``moving(y) = fixed(tau^-1(y))``, so that registering (fixed, moving) should
recover ``tau``.  :class:`KnownModes` makes a cohort of such warps from a few known modes of
deformation and known per-subject coefficients (ground truth for shape models).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from volreg.warp.resample import resample_labels
from volreg.grid import LabelVolume

__all__ = ["GaussianBumps", "KnownModes", "deform_labels"]


@dataclass(frozen=True)
class GaussianBumps:
    """A smooth displacement ``u(x) = sum_k a_k exp(-|x - p_k|^2 / (2 s^2))``.

    Attributes
    ----------
    centres : (K, D) float ndarray, mm
    amplitudes : (K, D) float ndarray, mm
    scale : float, mm
        ``s``.
    """

    centres: np.ndarray
    amplitudes: np.ndarray
    scale: float

    @classmethod
    def random(cls, lo, hi, *, max_displacement: float, scale: float, count: int = 6,
               rng: np.random.Generator) -> "GaussianBumps":
        """Bumps at random centres in the box ``[lo, hi]`` (mm), rescaled so that
        ``max |u| = max_displacement`` (mm) over the box.

        Raises
        ------
        ValueError
            If the result would not be invertible (``max |grad u| >= 0.8``).
        """
        lo = np.asarray(lo, float)
        hi = np.asarray(hi, float)
        centres = lo + rng.random((count, len(lo))) * (hi - lo)
        amplitudes = rng.normal(size=(count, len(lo)))
        bumps = cls(centres, amplitudes, float(scale))
        probe = lo + rng.random((20000, len(lo))) * (hi - lo)
        probe = np.concatenate([probe, centres])
        peak = np.linalg.norm(bumps.displacement(probe), axis=1).max()
        bumps = cls(centres, amplitudes * (max_displacement / peak), float(scale))
        jac = bumps.jacobian(probe) - np.eye(len(lo))
        if np.linalg.norm(jac, ord=2, axis=(1, 2)).max() >= 0.8:
            raise ValueError(
                f"Expected an invertible deformation: `max_displacement` {max_displacement} mm is too large for "
                f"`scale` {scale} mm (max |grad u| >= 0.8)."
            )
        return bumps

    def displacement(self, points: np.ndarray) -> np.ndarray:
        """``u(points)``, (N, D) mm."""
        points = np.asarray(points, float)
        # |x - p_k|^2 axis by axis: the sum in the order of ``(diff ** 2).sum(-1)``, without the
        # (N, K, D) temporaries (faster, and the same bits)
        d2 = np.zeros((points.shape[0], self.centres.shape[0]))
        for a in range(points.shape[1]):
            d = points[:, a, None] - self.centres[None, :, a]
            d *= d
            d2 += d
        np.divide(d2, -(2 * self.scale**2), out=d2)
        return np.exp(d2, out=d2) @ self.amplitudes

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """``tau(points) = points + u(points)``, (N, D) mm."""
        points = np.asarray(points, float)
        return points + self.displacement(points)

    def jacobian(self, points: np.ndarray) -> np.ndarray:
        """``d tau / dx``, (N, D, D)."""
        points = np.asarray(points, float)
        diff = points[:, None, :] - self.centres[None]  # (N, K, D)
        g = np.exp(-(diff**2).sum(-1) / (2 * self.scale**2))  # (N, K)
        # d u_a / d x_b = sum_k a_ka g_k (-(x_b - p_kb) / s^2)
        ju = -np.einsum("nk,ka,nkb->nab", g, self.amplitudes, diff) / self.scale**2
        return ju + np.eye(points.shape[1])

    def inverse(self, points: np.ndarray, *, iterations: int = 100, tol: float = 1e-9) -> np.ndarray:
        """``tau^-1(points)`` by the fixed-point iteration ``x <- y - u(x)`` (a contraction here)."""
        y = np.asarray(points, float)
        x = y.copy()
        for _ in range(iterations):
            new = y - self.displacement(x)
            done = np.abs(new - x).max() < tol
            x = new
            if done:
                break
        return x


def deform_labels(fixed: LabelVolume, tau: GaussianBumps, *, chunk: int = 1 << 18) -> LabelVolume:
    """The moving volume whose pull-back warp to ``fixed`` is ``tau``: ``fixed(tau^-1(y))``
    on the grid of ``fixed``, resampled label-preservingly."""
    points = fixed.grid_points().reshape(-1, fixed.ndim)
    pre = np.empty_like(points)
    for s in range(0, len(points), chunk):
        pre[s : s + chunk] = tau.inverse(points[s : s + chunk])
    return fixed.with_array(resample_labels(fixed, pre).reshape(fixed.shape))


@dataclass(frozen=True)
class KnownModes:
    """Modes of deformation ``e_m(x) = sigma_m a_m (g(x - p_m) - g(x - p'_m))`` and a cohort of them.

    ``g(r) = exp(-|r|^2 / (2 s^2))`` and ``p'_m`` is the mirror image of ``p_m`` in the plane
    through the origin normal to ``a_m``: a pair of opposite bumps, so that a mode neither moves
    nor turns a shape symmetric about that plane (rigid alignment leaves it alone).  Subject
    ``i``'s warp is ``x + sum_m b_im e_m(x)``; :meth:`coefficients` draws the ``b`` whitened (each
    mode's coefficients have mean 0 and variance exactly 1 over the cohort, and are
    uncorrelated), so that the cohort's covariance is exactly ``sum_m e_m e_m^T`` and, where the
    directions ``a_m`` are the coordinate axes, the modes are exactly orthogonal.

    Attributes
    ----------
    centres : (M, D) float ndarray, mm
        ``p_m``, off the plane through the origin normal to ``a_m``.
    directions : (M, D) float ndarray
        Unit vectors ``a_m``.
    sd : (M,) float ndarray, mm
        ``sigma_m``: each bump's peak displacement at one standard deviation.
    scale : float, mm
        ``s``.
    """

    centres: np.ndarray
    directions: np.ndarray
    sd: np.ndarray
    scale: float

    def coefficients(self, subjects: int, seed: int = 0) -> np.ndarray:
        """Whitened coefficients ``(subjects, M)``: column means 0, ``b^T b = (subjects - 1) I``."""
        m = len(self.sd)
        if subjects <= m:
            raise ValueError(f"Expected more subjects than modes ({m}), got {subjects}.")
        b = np.random.default_rng(seed).standard_normal((subjects, m))
        b -= b.mean(0)
        q, r = np.linalg.qr(b)
        q *= np.sign(np.diag(r))  # keep the draws' signs
        return q * np.sqrt(subjects - 1)

    def warp(self, b: np.ndarray) -> GaussianBumps:
        """The warp of coefficients ``b`` (M,)."""
        p = np.asarray(self.centres, float)
        a = np.asarray(self.directions, float)
        mirror = p - 2 * (p * a).sum(1, keepdims=True) * a
        amplitudes = np.asarray(b, float)[:, None] * np.asarray(self.sd, float)[:, None] * a
        return GaussianBumps(np.concatenate([p, mirror]), np.concatenate([amplitudes, -amplitudes]), float(self.scale))

    def fields(self, points: np.ndarray) -> np.ndarray:
        """Each mode at one standard deviation at ``points`` (N, D): ``(M, N, D)`` mm."""
        return np.stack([self.warp(np.eye(len(self.sd))[k]).displacement(points) for k in range(len(self.sd))])

"""The Wu kernel (paper eq. 13): numpy reference and the compiled helper every loop inlines.

With ``r = |x - y| / sigma`` and ``t = (1 - r)_+``, equation (13) is::

    k(r) = t^4 (4 + 16 r + 12 r^2 + 3 r^3)

compactly supported on ``r < 1`` and C^2 in up to three dimensions.  Writing
``d = x - y`` (mm), its derivatives with respect to ``x`` are::

    g(r)    = k'(r) / r = -7 t^3 (8 + 9 r + 3 r^2)
    grad_x k            = g(r) d / sigma^2
    h(r)    = g'(r) / r = 105 t^2 (1 + r)^2 / r
    hess_x k            = [g(r) I + h(r) d d^T / sigma^2] / sigma^2

(``h(r) d d^T / sigma^2 = 105 t^2 (1 + r)^2 r u u^T`` with ``u = d / |d|``
vanishes as ``r -> 0``, so the Hessian is ``g(0) I / sigma^2 = -56 I / sigma^2``
at a centre.)

Kernel properties, as a table:

==================  ==========================================
support             ``|x - y| < sigma`` (``r < 1``)
smoothness          C^2, for points in up to three dimensions
``k(0)``            4
``g(0)``            -56
``r h(r)`` at 0     105
==================  ==========================================
"""

from __future__ import annotations

import numpy as np

from volreg._jit import njit

__all__ = ["wu", "wu_derivatives", "wu_slope", "wu_terms"]


def wu(r: np.ndarray) -> np.ndarray:
    """Wu kernel profile (13), ``k(r)``, zero for ``r >= 1``.

    Parameters
    ----------
    r : float ndarray, dimensionless
        Distances divided by the kernel width (>= 0).

    Returns
    -------
    float ndarray, same shape as ``r``
    """
    r = np.asarray(r, dtype=float)
    t = np.clip(1.0 - r, 0.0, None)
    return t**4 * (4.0 + r * (16.0 + r * (12.0 + 3.0 * r)))


def wu_slope(r: np.ndarray) -> np.ndarray:
    """``g(r) = k'(r) / r = -7 (1 - r)_+^3 (8 + 9 r + 3 r^2)`` of the Wu kernel (13).

    The gradient of ``k(|x - y| / sigma)`` with respect to ``x`` is
    ``g(r) (x - y) / sigma^2``.

    Parameters
    ----------
    r : float ndarray, dimensionless
        Distances divided by the kernel width (>= 0).

    Returns
    -------
    float ndarray, same shape as ``r``
    """
    r = np.asarray(r, dtype=float)
    t = np.clip(1.0 - r, 0.0, None)
    return -7.0 * t**3 * (8.0 + r * (9.0 + 3.0 * r))


def wu_derivatives(d: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Value, gradient and Hessian of ``k(|d| / sigma)`` (13) with respect to ``x``.

    Parameters
    ----------
    d : (N, D) float ndarray, mm
        Differences ``x - y``.
    sigma : float, mm
        Kernel width (support radius).

    Returns
    -------
    value : (N,) float ndarray
    gradient : (N, D) float ndarray, 1/mm
    hessian : (N, D, D) float ndarray, 1/mm^2
    """
    d = np.asarray(d, dtype=float)
    dim = d.shape[1]
    r = np.sqrt(np.einsum("nd,nd->n", d, d)) / sigma
    t = np.clip(1.0 - r, 0.0, None)
    value = wu(r)
    g = wu_slope(r)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(r > 0, 105.0 * t**2 * (1.0 + r) ** 2 / np.where(r > 0, r, 1.0), 0.0)
    gradient = g[:, None] * d / sigma**2
    hessian = (
        g[:, None, None] * np.eye(dim)[None] + h[:, None, None] * d[:, :, None] * d[:, None, :] / sigma**2
    ) / sigma**2
    return value, gradient, hessian


@njit(inline="always")
def wu_terms(a, r, t):
    """The Wu kernel (13) and its derivative profiles, scaled by a coefficient; for compiled loops.

    Inlined into every compiled kernel sum (it compiles with the caller's
    floating-point flags); the caller computes ``r`` and ``t`` (how depends on
    the loop: branch-free loops clamp ``t`` at 0) and applies the powers of
    ``1 / sigma``, so each loop keeps its own evaluation order.

    Parameters
    ----------
    a : float
        Coefficient (1.0 for the bare kernel).
    r : float, dimensionless
        ``|x - y| / sigma``.
    t : float
        ``1 - r``, or 0 outside the support.

    Returns
    -------
    value : float
        ``a k(r) = a t^4 (4 + 16 r + 12 r^2 + 3 r^3)``.
    slope : float
        ``a g(r) = a k'(r) / r = -7 a t^3 (8 + 9 r + 3 r^2)``; the gradient is
        ``slope d / sigma^2``.
    curvature : float
        ``a r h(r) = 105 a t^2 (1 + r)^2``; the Hessian is
        ``(slope I + curvature / r d d^T / sigma^2) / sigma^2``.
    """
    t2 = t * t
    value = a * t2 * t2 * (4.0 + r * (16.0 + r * (12.0 + 3.0 * r)))
    slope = a * -7.0 * t2 * t * (8.0 + r * (9.0 + 3.0 * r))
    curvature = a * 105.0 * t2 * (1.0 + r) * (1.0 + r)
    return value, slope, curvature

"""The linear stage's cost and one least-squares solve of it.

The symmetric locational distance cost (paper eq. 3, with the labels' exact signed distances
as the feature functions): fixed boundary samples ``x`` count ``d_m(T x)^2``, moving ones ``y``
count ``d_f(T^-1 y)^2``, with ``T = start o G(p)`` and ``G`` the local map of a parameter vector
about the fixed labels' centre (:class:`_Local`).  :func:`_run` solves it with
``scipy.optimize.least_squares`` and the analytic Jacobian (:class:`_Cost`).
"""

from __future__ import annotations

import numpy as np

from volreg.linear_map import LinearMap
from volreg.warp.linear_labels import _MapBank, _Samples


def _right_jacobian(v: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3) at rotation vector ``v``: ``R(v + e) ~ R(v) exp([J_r e]x)``."""
    theta = float(np.linalg.norm(v))
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    if theta < 1e-6:
        return np.eye(3) - 0.5 * k + k @ k / 6.0
    return np.eye(3) - (1 - np.cos(theta)) / theta**2 * k + (theta - np.sin(theta)) / theta**3 * k @ k


class _Local:
    """The local map ``G(x) = c + M (x - c) + t`` of a parameter vector, about the centre ``c``.

    rigid: ``t`` (D), rotation vector (3) or angle (1); similarity adds the log-scale;
    affine: ``t`` and ``M - I`` (D x D, row-major).
    """

    def __init__(self, kind: str, dim: int):
        self.kind, self.dim = kind, dim
        n_rot = 3 if dim == 3 else 1
        self.size = dim + (dim * dim if kind == "affine" else n_rot + (kind == "similarity"))

    def x_scale(self, radius: float) -> np.ndarray:
        """Characteristic size of each parameter: mm for translations, 1 / radius otherwise."""
        out = np.full(self.size, 1.0 / radius)
        out[: self.dim] = 1.0
        return out

    def matrix(self, p: np.ndarray):
        """``M`` and what its derivatives need: the rotation, scale and right Jacobian."""
        d = self.dim
        if self.kind == "affine":
            return np.eye(d) + p[d:].reshape(d, d), None, 1.0, None
        if d == 3:
            v = p[3:6]
            theta = float(np.linalg.norm(v))
            if theta < 1e-12:
                rot = np.eye(3)
            else:
                k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / theta
                rot = np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * k @ k
            jr = _right_jacobian(v)
        else:
            c, s = np.cos(p[2]), np.sin(p[2])
            rot, jr = np.array([[c, -s], [s, c]]), None
        scale = float(np.exp(p[-1])) if self.kind == "similarity" else 1.0
        return scale * rot, rot, scale, jr

    def derivative_rows(self, h: np.ndarray, u: np.ndarray, parts) -> np.ndarray:
        """Rows ``h^T d(M u)/dp`` for the non-translation parameters, (N, size - D)."""
        m, rot, scale, jr = parts
        d = self.dim
        if self.kind == "affine":
            return (h[:, :, None] * u[:, None, :]).reshape(len(h), d * d)
        cols = []
        if d == 3:
            q = h @ rot  # rows R^T h
            cols.append(scale * np.cross(u, q) @ jr)
        else:
            ju = np.stack([-u[:, 1], u[:, 0]], axis=1)
            cols.append((scale * np.sum(h * (ju @ rot.T), axis=1))[:, None])
        if self.kind == "similarity":
            cols.append(np.sum(h * (u @ m.T), axis=1)[:, None])
        return np.hstack(cols)

    def compose(self, start: LinearMap, p: np.ndarray, centre: np.ndarray) -> LinearMap:
        """The map ``start o G``."""
        m = self.matrix(p)[0]
        a0, b0 = start.matrix, start.translation
        return LinearMap(a0 @ m, a0 @ (centre - m @ centre + p[: self.dim]) + b0)


class _Cost:
    """The symmetric locational distance cost (paper eq. 3 with exact signed distances).

    Fixed boundary points ``x`` count ``d_m(T x)^2``, moving boundary points ``y``
    count ``d_f(T^-1 y)^2``, with ``T = start o G(p)``; residuals are ``sqrt(w) d``
    and their Jacobian is analytic (chain rule through the interpolated gradients).
    """

    def __init__(self, local: _Local, start: LinearMap, centre: np.ndarray, bank_f: _MapBank, bank_m: _MapBank,
                 fwd: _Samples, back: _Samples):
        self.local, self.start, self.centre = local, start, centre
        self.bank_f, self.bank_m = bank_f, bank_m
        self.fwd, self.back = fwd, back
        self.look_f, self.look_b = bank_m.lookup(fwd.which), bank_f.lookup(back.which)
        self.u = fwd.points - centre
        self.v = start.inverse()(back.points) - centre
        self.sw_f, self.sw_b = np.sqrt(fwd.weights), np.sqrt(back.weights)
        self._key = None

    def evaluate(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = p.tobytes()
        if key == self._key:
            return self._r, self._jac
        d = self.local.dim
        parts = self.local.matrix(p)
        m = parts[0]
        a0, b0 = self.start.matrix, self.start.translation
        t = p[:d]
        res, rows = [], []
        if len(self.fwd):
            y = self.u @ (a0 @ m).T + (a0 @ (self.centre + t) + b0)
            dist, g = self.bank_m.sample(self.look_f, y)
            h = g @ a0
            res.append(self.sw_f * dist)
            rows.append(self.sw_f[:, None] * np.hstack([h, self.local.derivative_rows(h, self.u, parts)]))
        if len(self.back):
            det = np.linalg.det(m)
            if not det > 1e-6:
                r = np.full(len(self.fwd) + len(self.back), 1e6)
                self._key, self._r, self._jac = key, r, np.zeros((len(r), self.local.size))
                return self._r, self._jac
            minv = np.linalg.inv(m)
            w = (self.v - t) @ minv.T
            dist, g = self.bank_f.sample(self.look_b, self.centre + w)
            h = g @ minv
            res.append(self.sw_b * dist)
            rows.append(-self.sw_b[:, None] * np.hstack([h, self.local.derivative_rows(h, w, parts)]))
        self._key, self._r, self._jac = key, np.concatenate(res), np.vstack(rows)
        return self._r, self._jac


def _finite(value: float) -> float | None:
    """``value`` as a float, or None when it is NaN or infinite (JSON has neither)."""
    return float(value) if np.isfinite(value) else None


def _run(local, start, centre, bank_f, bank_m, fwd, back, f_scale, radius, max_nfev, tol):
    """One least-squares solve from ``start``; the field-of-view masks are those of ``start``."""
    from scipy.optimize import least_squares

    keep_f = fwd.kept(bank_m.volume, start(fwd.points))
    keep_b = back.kept(bank_f.volume, start.inverse()(back.points))
    fwd_k, back_k = fwd.subset(keep_f), back.subset(keep_b)
    n_valid, n_total = len(fwd_k) + len(back_k), len(fwd) + len(back)
    if n_valid < local.size:
        return start, dict(cost=float("inf"), score=float("inf"), iterations=0, valid=n_valid, total=n_total,
                           mean_abs_distance_mm=float("nan")), (keep_f, keep_b)
    cost = _Cost(local, start, centre, bank_f, bank_m, fwd_k, back_k)
    result = least_squares(
        lambda p: cost.evaluate(p)[0], np.zeros(local.size), jac=lambda p: cost.evaluate(p)[1],
        method="trf", tr_solver="lsmr", loss="soft_l1", f_scale=f_scale, x_scale=local.x_scale(radius),
        max_nfev=max_nfev, xtol=tol, ftol=tol, gtol=tol,
    )
    found = local.compose(start, result.x, centre)
    r = cost.evaluate(result.x)[0]
    weights = np.concatenate([fwd_k.weights, back_k.weights])
    info = dict(
        cost=float(result.cost),
        # Mean robust cost per sample, raised where samples left the field of view (a
        # start cannot win by pushing the labels out of the image).
        score=float(result.cost / n_valid * (n_total / n_valid) ** 2),
        iterations=int(result.nfev),
        valid=int(n_valid),
        total=int(n_total),
        mean_abs_distance_mm=float(np.sum(np.abs(r) * np.sqrt(weights)) / np.sum(weights)),
    )
    return found, info, (keep_f, keep_b)

"""How good a shape model is, as the field measures it (Davies 2002; Styner et al. 2003).

For ``M = 1 .. K`` modes of a :class:`~volreg.pipeline.shape_model.ShapeModel`:

- **compactness** ``C(M)``: the share of the training shapes' variance in the leading ``M``
  modes (``sum_{m<=M} variance_m / total``), with Styner's standard error ``sqrt(2 / N) C(M)``;
- **generalization** ``G(M)``: leave-one-out: the model of the other ``N - 1`` shapes
  reconstructs the one left out with ``M`` modes; the mean over points of the distance (mm)
  between it and its reconstruction, averaged over the ``N`` shapes (standard error: their
  standard deviation over ``sqrt(N)``);
- **specificity** ``S(M)``: shapes drawn from the model (coefficients standard normal, seeded),
  each one's mean point distance (mm) to its nearest training shape, averaged over the draws
  (standard error likewise).

Distances are Euclidean per point, averaged over the points; where the shapes have more than
``points`` points (default 5,000), over a seeded random subset of that many (an unbiased estimate of the mean;
the fits use every point).  The leave-one-out models are read off the ``N x N`` Gram matrix of
the whole set (double-centred on the ``N - 1``), so the ``N`` refits cost ``N`` small
eigenproblems, not ``N`` passes over the data.
"""

from __future__ import annotations

import numpy as np

from volreg.pipeline.shape_model import ShapeModel, gram_matrix

__all__ = ["model_quality", "point_distance"]


def point_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean over points of ``|a - b|`` (mm) along the last two axes: (..., P, D) -> (...)."""
    return np.sqrt(((a - b) ** 2).sum(-1)).mean(-1)


def _loo_errors(data: np.ndarray, sub: np.ndarray, modes: int) -> np.ndarray:
    """Leave-one-out reconstruction errors (N, modes), mm: row ``i``, column ``M - 1``.

    ``data`` (N, P, D) aligned shapes; ``sub`` the points the errors are measured at.
    """
    n, p, d = data.shape
    flat = data.reshape(n, p * d)
    mean = flat.mean(0, dtype=float)
    gram = gram_matrix(flat, mean)  # inner products of x - mean: any constant offset works below
    at = data[:, sub].astype(float)  # (N, S, D)
    out = np.full((n, modes), np.nan)
    for i in range(n):
        rest = np.delete(np.arange(n), i)
        g = gram[np.ix_(rest, rest)]
        row = g.mean(0)
        centred = g - row[:, None] - row[None, :] + row.mean()  # Gram of x_j - mean of the rest
        q = gram[rest, i] - row - gram[rest, i].mean() + row.mean()  # (x_j - that mean) . (x_i - that mean)
        w, v = np.linalg.eigh(centred)
        order = np.argsort(w)[::-1][:modes]
        w, v = w[order], v[:, order]
        good = w > max(float(w[0]), 0.0) * 1e-10
        w, v = w[good], v[:, good]
        base = at[rest].mean(0)
        offsets = (at[rest] - base).reshape(n - 1, -1)  # (N-1, S D)
        steps = ((v.T @ q) / w)[:, None] * (v.T @ offsets)  # each mode's part of the reconstruction, (k, S D)
        recon = base.reshape(-1) + np.cumsum(steps, axis=0)  # with 1 .. k modes
        errors = point_distance(recon.reshape(len(w), -1, d), at[i])
        out[i, :len(w)] = errors
        out[i, len(w):] = errors[-1] if len(w) else point_distance(base, at[i])
    return out


def model_quality(model: ShapeModel, shapes: np.ndarray, *, samples: int = 100, points: int = 5000,
                  seed: int = 0) -> dict:
    """Compactness, generalization and specificity of ``model`` for 1 .. K modes (module notes).

    Parameters
    ----------
    model : ShapeModel
        Fitted to ``shapes`` (aligned as the model aligned them).
    shapes : (N, P, D) float array, mm
        The training shapes in the model's frame.
    samples : int
        Shapes drawn for the specificity.
    points : int
        At most this many points measured (a seeded random subset beyond).
    seed : int

    Returns
    -------
    dict
        ``modes`` ([1 .. K]), ``compactness`` and ``compactness_se`` (fractions),
        ``compactness_mm2`` (cumulative variance), ``generalization_mm`` and
        ``generalization_se_mm``, ``specificity_mm`` and ``specificity_se_mm`` (lists over M),
        ``samples``, ``points_measured``, ``seed``.
    """
    rng = np.random.default_rng(seed)
    n, p, _ = shapes.shape
    k = model.n_modes
    sub = np.sort(rng.choice(p, points, replace=False)) if p > points else np.arange(p)
    cumulative = np.cumsum(model.variances)
    fraction = cumulative / model.total_variance if model.total_variance > 0 else np.zeros(k)
    loo = _loo_errors(shapes, sub, k) if k else np.zeros((n, 0))
    draws = rng.standard_normal((samples, k))
    at = shapes[:, sub].astype(float)
    mean, modes = model.mean[sub], model.modes[:, sub]
    spec = np.zeros((samples, k))
    for m in range(k):
        scale = draws[:, :m + 1] * np.sqrt(model.variances[:m + 1])
        drawn = mean + np.tensordot(scale, modes[:m + 1], axes=1)  # (samples, S, D)
        nearest = np.stack([point_distance(drawn, at[j]) for j in range(n)], axis=1).min(1)
        spec[:, m] = nearest
    root = np.sqrt(max(samples, 1))
    return {
        "modes": list(range(1, k + 1)),
        "compactness": fraction.tolist(),
        "compactness_se": (np.sqrt(2.0 / n) * fraction).tolist(),
        "compactness_mm2": cumulative.tolist(),
        "generalization_mm": loo.mean(0).tolist(),
        "generalization_se_mm": (loo.std(0, ddof=1) / np.sqrt(n) if n > 1 else np.zeros(k)).tolist(),
        "specificity_mm": spec.mean(0).tolist(),
        "specificity_se_mm": (spec.std(0, ddof=1) / root if samples > 1 else np.zeros(k)).tolist(),
        "samples": int(samples),
        "points_measured": int(len(sub)),
        "seed": int(seed),
    }

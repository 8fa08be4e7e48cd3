"""The linear stage's starts: closed-form candidate maps from the labels' moments, and their scoring.

When at least D + 1 labels uncut by the image edge have centroids that span the space, the
weighted Procrustes fit of the centroid pairs (:func:`_procrustes`) and the centroids'
translation; otherwise the principal axes of the labels' union for every sign choice
(:func:`_axis_candidates`) and the centroids' translation.  The identity is always a candidate.
Each runs a few iterations at the coarsest level (:func:`_score_starts`); of those that fit
about as well as the best, the least rotated wins.
"""

from __future__ import annotations

import numpy as np

from volreg.linear_map import LinearMap
from volreg.warp.linear_cost import _finite, _Local, _run
from volreg.warp.linear_labels import _LabelPair, _LabelShape, _union_moments

#: A start whose score is within this factor of the best one's competes on rotation: the
#: least rotated of them wins.
_NEAR_BEST = 1.5
#: Least-squares evaluations per start candidate at the coarsest level, and their tolerance.
_CANDIDATE_EVALUATIONS = 8
_CANDIDATE_TOLERANCE = 1e-5


def _procrustes(p: np.ndarray, q: np.ndarray, w: np.ndarray, kind: str) -> tuple[LinearMap, str]:
    """Weighted fit of ``q ~ A p + b`` to point pairs (Kabsch, Umeyama or least squares).

    Parameters
    ----------
    p, q : (n, D) float ndarray, mm
        Fixed and moving points (label centroids).
    w : (n,) float ndarray
        Non-negative weights.
    kind : {"rigid", "similarity", "affine"}
        An affine fit is kept only when it is well conditioned (at least 2 D pairs,
        a moderate condition number and no reflection); otherwise the similarity.

    Returns
    -------
    LinearMap, str
        The map and the model actually fitted.
    """
    d = p.shape[1]
    w = w / w.sum()
    mp, mq = w @ p, w @ q
    x, y = p - mp, q - mq
    cross = (y * w[:, None]).T @ x
    u, sv, vt = np.linalg.svd(cross)
    flip = np.ones(d)
    flip[-1] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag(flip) @ vt
    scale = 1.0
    if kind != "rigid":
        scale = float(sv @ flip / (w @ np.sum(x * x, axis=1)))
    a = scale * rot
    used = "rigid" if kind == "rigid" else "similarity"
    if kind == "affine" and len(p) >= 2 * d:
        xh = np.hstack([x, np.ones((len(x), 1))]) * np.sqrt(w)[:, None]
        sol, *_ = np.linalg.lstsq(xh, y * np.sqrt(w)[:, None], rcond=None)
        cand = sol[:d].T
        s_cand = np.linalg.svd(cand, compute_uv=False)
        if np.linalg.det(cand) > 0 and s_cand[0] / s_cand[-1] < 3.0:
            a, used = cand, "affine"
    return LinearMap(a, mq - a @ mp), used


def _spans(points: np.ndarray, weights: np.ndarray) -> bool:
    """Whether weighted points span their space: D + 1 of them, not nearly on a plane (line)."""
    n, d = points.shape
    if n < d + 1:
        return False
    w = weights / weights.sum()
    x = (points - w @ points) * np.sqrt(w)[:, None]
    s = np.linalg.svd(x, compute_uv=False)
    return bool(s[-1] > 0.15 * s[0])


def _axis_candidates(fixed: list[_LabelShape], moving: list[_LabelShape], kind: str) -> list[tuple[str, LinearMap]]:
    """Principal-axes starts: ``R = E_m diag(s) E_f^T`` for every sign choice with det +1,
    the centroids' translation, and the volume ratio's scale (similarity); for an affine map,
    the scales along the axes that carry one union's second moments onto the other's,
    ``A = E_m diag(s sqrt(l_m / l_f)) E_f^T`` (``l``: the moments' eigenvalues, mm^2)."""
    vf, cf, covf = _union_moments(fixed)
    vm, cm, covm = _union_moments(moving)
    d = len(cf)
    scale = 1.0 if kind == "rigid" else (vm / vf) ** (1.0 / d)
    lf, ef = np.linalg.eigh(covf)
    lm, em = np.linalg.eigh(covm)
    ef, em, lf, lm = ef[:, ::-1], em[:, ::-1], lf[::-1], lm[::-1]
    tiny = 1e-12 * max(float(lf.max()), float(lm.max()), 1e-300)
    axes = np.sqrt(np.maximum(lm, tiny) / np.maximum(lf, tiny)) if kind == "affine" else np.full(d, scale)
    out = []
    for signs in np.ndindex(*([2] * d)):
        s = 1.0 - 2.0 * np.array(signs, dtype=float)
        if np.linalg.det(em @ np.diag(s) @ ef.T) < 0:
            continue
        a = em @ np.diag(s * axes) @ ef.T
        label = "".join("+" if v > 0 else "-" for v in s)
        out.append((f"principal axes {label}", LinearMap(a, cm - a @ cf)))
    out.append(("centroid translation", LinearMap(scale * np.eye(d), cm - scale * cf)))
    return out


def _start_candidates(pair: _LabelPair, kind: str) -> list[tuple[str, str, LinearMap]]:
    """The candidate starts of a fit, as ``(family, name, map)``.

    ``family`` is ``"centroids"`` (the centroids' Procrustes fit or translation),
    ``"principal axes"`` or ``"identity"`` (always the last candidate).  The centroid fit
    needs the labels uncut by either image's edge, at least D + 1 of them, spanning the
    space in both volumes; otherwise the principal axes of the uncut labels' union (of all
    labels where every one is cut).
    """
    shapes_f, shapes_m = pair.fixed.shapes, pair.moving.shapes
    dim = pair.fixed.volume.ndim
    uncut = [v for v in pair.labels if v not in pair.cut]
    weights = np.array([np.sqrt(shapes_f[v].volume_mm3 * shapes_m[v].volume_mm3) for v in uncut])
    candidates: list[tuple[str, str, LinearMap]] = []
    if uncut and _spans(np.array([shapes_f[v].centroid for v in uncut]), weights) and \
            _spans(np.array([shapes_m[v].centroid for v in uncut]), weights):
        pf = np.array([shapes_f[v].centroid for v in uncut])
        pm = np.array([shapes_m[v].centroid for v in uncut])
        fitted, model = _procrustes(pf, pm, weights, kind)
        candidates.append(("centroids", f"centroids ({model})", fitted))
        _, cf, _ = _union_moments([shapes_f[v] for v in uncut])
        _, cm, _ = _union_moments([shapes_m[v] for v in uncut])
        candidates.append(("centroids", "centroid translation", LinearMap(np.eye(dim), cm - cf)))
    else:
        basis = uncut if uncut else pair.labels
        for name, cand in _axis_candidates([shapes_f[v] for v in basis], [shapes_m[v] for v in basis], kind):
            family = "centroids" if name == "centroid translation" else "principal axes"
            candidates.append((family, name, cand))
    candidates.append(("identity", "identity", LinearMap.identity(dim)))
    return candidates


def _score_starts(pair: _LabelPair, candidates: list[tuple[str, str, LinearMap]], local: _Local,
                  spacing_mm: float, count: int, progress=None) -> tuple[list[dict], int, LinearMap]:
    """Run each candidate start a few iterations at the coarsest level and pick one.

    Parameters
    ----------
    pair : _LabelPair
    candidates : list of (family, name, LinearMap)
        From :func:`_start_candidates`.
    local : _Local
        The parameters the candidates' iterations fit.
    spacing_mm : float
        The coarsest level's map spacing, mm.
    count : int
        Boundary samples per label and volume at that level.
    progress : callable, optional
        ``progress("linear start", done, total)`` per candidate.

    Returns
    -------
    tried : list of dict
        Per candidate, JSON-ready: ``name``, ``family``, ``start`` (its
        :meth:`~volreg.linear_map.LinearMap.describe`), ``cost`` (the score) and ``iterations``.
    index : int
        The chosen candidate's position in ``candidates``.
    found : LinearMap
        The chosen candidate after its iterations: where the refinement starts.
    """
    bank_f, bank_m, fwd, back = pair.level(spacing_mm, count)
    f_scale = 2.0 * spacing_mm
    tried = []
    scored = []
    for i, (family, name, cand) in enumerate(candidates):
        found, info, _ = _run(local, cand, pair.centre, bank_f, bank_m, fwd, back, f_scale, pair.radius,
                              _CANDIDATE_EVALUATIONS, _CANDIDATE_TOLERANCE)
        described = cand.describe()
        tried.append(dict(name=name, family=family, start=described, cost=_finite(info["score"]),
                          iterations=info["iterations"]))
        scored.append((info["score"], round(described["rotation_deg"]), i, found))
        if progress is not None:
            progress("linear start", i + 1, len(candidates))
    # Of the starts that fit about as well as the best, the least rotated (whole degrees, then
    # the order of the candidates): near-symmetric anatomy fits turned upside down almost as
    # well, and scans are rarely upside down.  The start's rotation, not that of its few
    # iterations: on grids too coarse for the object the coarse cost turns even the right start.
    lowest = min(row[0] for row in scored)
    near = [row for row in scored if row[0] <= _NEAR_BEST * lowest]
    _, _, index, found = min(near or scored, key=lambda row: (row[1], row[2]))
    return tried, index, found

"""The linear stage's refinement: coarse-to-fine least squares from the chosen start.

The levels' map spacings are the object's diameter over 16, 32 and 64, never finer than the
coarser volume's voxel (:func:`_level_plan`); each level solves the cost of
:mod:`volreg.warp.linear_cost` on its maps and samples (:func:`_solve_level`).  Where the labels'
second moments are nearly symmetric about an axis, the finest level's cost is first searched
over turns about it (:func:`_turn_search`).
"""

from __future__ import annotations

import time

import numpy as np

from volreg.linear_map import LinearMap
from volreg.warp.linear_cost import _finite, _Local, _run
from volreg.warp.linear_labels import _LabelPair, _LabelShape, _level_factors, _union_moments

#: Object diameter over grid spacing, coarse to fine (each level's distance-map spacing).
_LEVEL_DIVISORS = (16.0, 32.0, 64.0)
#: Boundary samples per label and volume at each level (coarse to fine), and in all
#: (per volume): many labels share the second budget.
_LEVEL_SAMPLES = (600, 1200, 2500)
_LEVEL_TOTAL = (4000, 8000, 16000)
#: Least-squares evaluations per level.
_LEVEL_EVALUATIONS = 40
#: least_squares' xtol, ftol and gtol at every level (the finest too: a tighter tolerance there
#: costs more evaluations and moves the map far less than the kernel warp then corrects).
_LEVEL_TOLERANCE = 1e-5
#: Solves per level at most: a level is solved again while the field-of-view masks change.
_LEVEL_SOLVES = 3
#: Where two of the labels' second moments differ by less than this fraction, their turn about
#: the third axis is searched at the finest level (:func:`_free_axis`), in steps of
#: ``_TURN_STEP_DEG``; of the turns whose score is within ``_TURN_TIE`` of the best, the smallest.
_TURN_AXIS_TOL = 0.1
_TURN_STEP_DEG = 5.0
_TURN_TIE = 0.02


def _voxel_size(volume) -> float:
    """Geometric mean of the voxel sides, mm."""
    return float(np.prod(volume.spacing) ** (1.0 / volume.ndim))


def _level_plan(fixed, moving, diameter: float, n_labels: int) -> tuple[list[float], list[int], float]:
    """The levels of a fit: map spacings (coarse to fine, mm), boundary samples per label and
    volume at each, and the finest spacing allowed (the coarser volume's voxel, mm).

    A level whose spacing gives both volumes the same grid coarsening as the coarser one
    replaces it (one level, at the finer spacing's sample count).
    """
    floor_mm = max(_voxel_size(fixed), _voxel_size(moving))
    levels: list[tuple[float, int, tuple]] = []
    for i, div in enumerate(_LEVEL_DIVISORS):
        h = max(floor_mm, diameter / div)
        grids = (tuple(_level_factors(fixed, h)), tuple(_level_factors(moving, h)))
        if levels and levels[-1][2] == grids:
            levels[-1] = (h, i, grids)  # the same grids as the coarser level: one level
        else:
            levels.append((h, i, grids))
    spacings = [h for h, _, _ in levels]
    counts = [min(_LEVEL_SAMPLES[i], _LEVEL_TOTAL[i] // n_labels) for _, i, _ in levels]
    return spacings, counts, floor_mm


def _solve_level(local: _Local, current: LinearMap, pair: _LabelPair, bank_f, bank_m, fwd, back,
                 f_scale: float) -> tuple[LinearMap, dict, int]:
    """Solve one level from ``current``, again (up to :data:`_LEVEL_SOLVES` times) while the
    field-of-view masks of the samples change under the map found.

    Returns
    -------
    LinearMap
        The map found (``current`` where the cost was not finite).
    dict
        The last solve's information (:func:`~volreg.warp.linear_cost._run`).
    int
        Cost evaluations over the solves.
    """
    iterations = 0
    for _ in range(_LEVEL_SOLVES):
        found, info, used = _run(local, current, pair.centre, bank_f, bank_m, fwd, back, f_scale, pair.radius,
                                 _LEVEL_EVALUATIONS, _LEVEL_TOLERANCE)
        iterations += info["iterations"]
        if not np.isfinite(info["cost"]):
            break
        current = found
        after = (fwd.kept(pair.moving.volume, current(fwd.points)),
                 back.kept(pair.fixed.volume, current.inverse()(back.points)))
        if all(np.array_equal(a, b) for a, b in zip(used, after)):
            break
    return current, info, iterations


def _refine(pair: _LabelPair, start: LinearMap, local: _Local, coarse_local: _Local, spacings: list[float],
            counts: list[int], turn_axis: np.ndarray | None,
            progress=None) -> tuple[LinearMap, list[dict], dict | None]:
    """Coarse-to-fine least squares from ``start``.

    Parameters
    ----------
    pair : _LabelPair
    start : LinearMap
        The chosen start after its iterations (:func:`~volreg.warp.linear_starts._score_starts`).
    local, coarse_local : _Local
        The parameters of the finest level, and of the coarser ones and the turn search.
    spacings, counts : list
        From :func:`_level_plan`.
    turn_axis : (3,) float ndarray or None
        The axis whose turn the finest level's cost is searched over (:func:`_free_axis`).
    progress : callable, optional
        ``progress("fit linear", done, total)`` per level.

    Returns
    -------
    LinearMap
        The refined map.
    list of dict
        Per level, JSON-ready: ``spacing_mm``, ``f_scale_mm``, ``samples``, ``samples_outside_view``,
        ``cost``, ``iterations``, ``mean_abs_distance_mm``.
    dict or None
        The turn search's log (:func:`_turn_search`), None where there was none.
    """
    current = start
    turn_log = None
    level_log = []
    for level, (h, count) in enumerate(zip(spacings, counts)):
        bank_f, bank_m, fwd, back = pair.level(h, count)
        f_scale = 2.0 * h
        finest = level == len(spacings) - 1
        if turn_axis is not None and finest and len(spacings) > 1:
            current, turn_log = _turn_search(current, turn_axis, pair.centre, lambda m: _run(
                coarse_local, m, pair.centre, bank_f, bank_m, fwd, back, f_scale, pair.radius, 1,
                _LEVEL_TOLERANCE)[1]["score"])
        current, info, iterations = _solve_level(local if finest else coarse_local, current, pair,
                                                 bank_f, bank_m, fwd, back, f_scale)
        level_log.append(dict(spacing_mm=float(h), f_scale_mm=float(f_scale), samples=int(info["valid"]),
                              samples_outside_view=int(info["total"] - info["valid"]), cost=_finite(info["cost"]),
                              iterations=int(iterations),
                              mean_abs_distance_mm=_finite(info["mean_abs_distance_mm"])))
        if progress is not None:
            progress("fit linear", level + 1, len(spacings))
    return current, level_log, turn_log


def _free_axis(shapes: list[_LabelShape]) -> np.ndarray | None:
    """The axis (3,) about which the union's second moments are nearly symmetric (two of them
    within :data:`_TURN_AXIS_TOL` of each other), or None."""
    _, _, cov = _union_moments(shapes)
    lam, vec = np.linalg.eigh(cov)  # ascending
    if lam[2] <= 0:
        return None
    if (lam[2] - lam[1]) / lam[2] < _TURN_AXIS_TOL:
        return vec[:, 0]
    if (lam[1] - lam[0]) / max(lam[1], 1e-300) < _TURN_AXIS_TOL:
        return vec[:, 2]
    return None


def _turned(linear: LinearMap, axis: np.ndarray, centre: np.ndarray, angle: float) -> LinearMap:
    """``x -> L(R (x - c) + c)``: ``linear`` after a turn by ``angle`` (rad) about ``axis``
    (unit, (3,)) through ``centre`` (mm)."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_rotvec(angle * np.asarray(axis, float)).as_matrix()
    return LinearMap(linear.matrix @ rot, linear.matrix @ (centre - rot @ centre) + linear.translation)


def _turn_search(current: LinearMap, axis: np.ndarray, centre: np.ndarray, score) -> tuple[LinearMap, dict]:
    """``current`` turned about ``axis`` through ``centre`` by the multiple of :data:`_TURN_STEP_DEG`
    whose ``score(map)`` is lowest (of those within :data:`_TURN_TIE` of it, the smallest turn),
    and a JSON-ready log: the axis, the turn (degrees), its score and the lowest score more than
    three steps from it (the runner-up: close to the best where the labels do not show the turn)."""
    t0 = time.perf_counter()
    angles = np.arange(0.0, 360.0, _TURN_STEP_DEG)
    maps = [_turned(current, axis, centre, np.radians(a)) for a in angles]
    scores = np.array([score(m) for m in maps])
    signed = (angles + 180.0) % 360.0 - 180.0  # the turn in (-180, 180], degrees
    size = np.abs(signed)
    finite = np.isfinite(scores)
    if not finite.any():
        return current, dict(axis=[float(v) for v in axis], degrees=0.0, score=None, runner_up=None,
                             seconds=time.perf_counter() - t0)
    best = float(scores[finite].min())
    near = np.flatnonzero(finite & (scores <= best * (1.0 + _TURN_TIE)))
    pick = int(near[np.argmin(size[near])])
    apart = np.abs((angles - angles[pick] + 180.0) % 360.0 - 180.0) > 3 * _TURN_STEP_DEG
    others = scores[apart & finite]
    return maps[pick], dict(axis=[float(v) for v in axis], degrees=float(signed[pick]), score=float(scores[pick]),
                            runner_up=float(others.min()) if others.size else None, seconds=time.perf_counter() - t0)

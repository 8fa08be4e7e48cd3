"""The linear stage's refinement: coarse-to-fine least squares from the chosen start.

The levels' map spacings are the object's diameter over 16, 32 and 64, never finer than the
coarser volume's voxel (:func:`_level_plan`); each level solves the cost of
:mod:`volreg.warp.linear_cost` on its maps and samples (:func:`_solve_level`).  Where the labels'
second moments are nearly symmetric about an axis, the finest level's cost is first searched
over turns about it (:func:`_turn_search`).  Where the map found turns more than 45 degrees, the
turns of the fixed labels' symmetries are tried after it (:func:`_least_rotated`): of the maps that
fit as well, the least rotated is kept.
"""

from __future__ import annotations

import itertools
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
#: A refined map that turns more than this (degrees) is compared with itself after each turn of
#: :func:`symmetry_turns` (:func:`_least_rotated`).  Those turns are of 90 degrees or more, and a
#: map turned by ``t`` after one of ``s`` turns by at least ``s - t``: below half of 90 degrees no
#: such map turns less, and nothing is tried.
_SYMMETRY_CHECK_DEG = 45.0
#: Of the maps whose score is within this fraction of the lowest, the least rotated is kept (the
#: labels' boundary samples are thinned at random, so a symmetry's two maps score alike, not equal).
_SYMMETRY_TIE = 0.02


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
            counts: list[int], turn_axis: np.ndarray | None, frames: list[np.ndarray] = (),
            progress=None) -> tuple[LinearMap, list[dict], dict]:
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
    frames : list of (D, D) float ndarray
        Orthonormal frames of the fixed labels (their principal axes, the image's axes) whose
        symmetry turns the refined map is compared after (:func:`_least_rotated`).
    progress : callable, optional
        ``progress("fit linear", done, total)`` per level.

    Returns
    -------
    LinearMap
        The refined map.
    list of dict
        Per level, JSON-ready: ``spacing_mm``, ``f_scale_mm``, ``samples``, ``samples_outside_view``,
        ``cost``, ``iterations``, ``mean_abs_distance_mm``.
    dict
        The searches' logs, by name, where they ran: ``turn_search`` (:func:`_turn_search`) and
        ``least_rotation`` (:func:`_least_rotated`).
    """
    current = start
    searches = {}
    level_log = []
    for level, (h, count) in enumerate(zip(spacings, counts)):
        bank_f, bank_m, fwd, back = pair.level(h, count)
        f_scale = 2.0 * h
        finest = level == len(spacings) - 1
        if turn_axis is not None and finest and len(spacings) > 1:
            current, searches["turn_search"] = _turn_search(current, turn_axis, pair.centre, lambda m: _run(
                coarse_local, m, pair.centre, bank_f, bank_m, fwd, back, f_scale, pair.radius, 1,
                _LEVEL_TOLERANCE)[1]["score"])
        current, info, iterations = _solve_level(local if finest else coarse_local, current, pair,
                                                 bank_f, bank_m, fwd, back, f_scale)
        if finest and frames and current.describe()["rotation_deg"] > _SYMMETRY_CHECK_DEG:
            current, searches["least_rotation"] = _least_rotated(current, frames, pair.centre, lambda m: _run(
                local, m, pair.centre, bank_f, bank_m, fwd, back, f_scale, pair.radius, 1,
                _LEVEL_TOLERANCE)[1]["score"])
        level_log.append(dict(spacing_mm=float(h), f_scale_mm=float(f_scale), samples=int(info["valid"]),
                              samples_outside_view=int(info["total"] - info["valid"]), cost=_finite(info["cost"]),
                              iterations=int(iterations),
                              mean_abs_distance_mm=_finite(info["mean_abs_distance_mm"])))
        if progress is not None:
            progress("fit linear", level + 1, len(spacings))
    return current, level_log, searches


def symmetry_turns(frames: list[np.ndarray]) -> list[np.ndarray]:
    """The turns that would carry an object symmetric in one of ``frames`` onto itself: per frame
    ``F`` (orthonormal (D, D), its columns the axes), ``F P F^T`` for each signed permutation ``P``
    of the axes with determinant +1 other than the identity (a cube's 23 turns in 3-D, 3 in 2-D),
    each turn once.

    Returns
    -------
    list of (D, D) float ndarray
        Rotation matrices.
    """
    turns: list[np.ndarray] = []
    for frame in frames:
        f = np.asarray(frame, float)
        dim = len(f)
        for order in itertools.permutations(range(dim)):
            for signs in itertools.product((1.0, -1.0), repeat=dim):
                p = np.zeros((dim, dim))
                p[range(dim), order] = signs
                if np.linalg.det(p) < 0 or np.array_equal(p, np.eye(dim)):
                    continue
                turn = f @ p @ f.T
                if not any(np.allclose(turn, t, atol=1e-9) for t in turns):
                    turns.append(turn)
    return turns


def _least_rotated(current: LinearMap, frames: list[np.ndarray], centre: np.ndarray, score) -> tuple[LinearMap, dict]:
    """Of ``current`` and ``current`` after each turn of :func:`symmetry_turns` about ``centre``
    (``x -> L(S (x - c) + c)``), the least rotated of those whose ``score(map)`` is within
    :data:`_SYMMETRY_TIE` of the lowest, and a JSON-ready log.

    An object with symmetries (a cube, a box) fits as well turned by any of them: the refinement
    ends at whichever its start led to, a cube turned 45 degrees at a turn of 98.  The least
    rotated of the equals is the pose the images most likely differ by, and the one the review of
    a registration judges (a turn above its limit reads as a wrong orientation header).
    """
    t0 = time.perf_counter()
    maps = [current] + [LinearMap(current.matrix @ s, current.matrix @ (centre - s @ centre) + current.translation)
                        for s in symmetry_turns(frames)]
    scores = np.array([score(m) for m in maps])
    angles = np.array([m.describe()["rotation_deg"] for m in maps])
    finite = np.isfinite(scores)
    log = dict(rotation_deg=float(angles[0]), tried=len(maps) - 1, kept_rotation_deg=float(angles[0]),
               score=float(scores[0]) if finite[0] else None, seconds=0.0)
    if finite.any():
        best = float(scores[finite].min())
        near = np.flatnonzero(finite & (scores <= best * (1.0 + _SYMMETRY_TIE)))
        pick = int(near[np.argmin(np.round(angles[near], 6))])  # the first of equal angles: current before its turns
        current = maps[pick]
        log.update(kept_rotation_deg=float(angles[pick]), score=float(scores[pick]))
    log["seconds"] = time.perf_counter() - t0
    return current, log


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

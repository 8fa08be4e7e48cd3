"""The numerics of a cohort template of label maps: pure functions on arrays.

A template is built by :func:`volreg.template.build_template`; this module holds its steps:

- the subjects' mean linear pose (:func:`mean_linear_map`, a log-Euclidean mean of their affine
  maps from a provisional reference), so that the template's position and size are the cohort's
  own, not the reference's;
- the template grid that holds every aligned subject (:func:`template_grid`);
- per-label vote counts, the template labels as their arg max with the background
  (:func:`vote`) or with each label's mean volume kept (:func:`vote_volumes`), and each label's
  probability sharpness (:func:`sharpness`);
- the first template's subject: the medoid of the linearly aligned label maps (:func:`medoid`);
- the shape update: the mean of the subjects' pull-back displacements ``u_bar`` over the
  template grid says where, on average, the subjects' points lie relative to the template's; the
  template is moved by ``phi(x) = x + u_bar(x)``: each subject is read once, from its own labels,
  at ``phi^-1(y) + u_i(phi^-1(y))`` (:func:`invert_displacement`, :func:`pull_back_points`);
- the subjects' distances to the template and the outliers among them (:func:`rank_subjects`).
"""

from __future__ import annotations

import numpy as np
from scipy import linalg, ndimage

from volreg.grid import Grid
from volreg.linear_map import LinearMap

__all__ = [
    "invert_displacement",
    "mean_linear_map",
    "medoid",
    "pull_back_points",
    "rank_subjects",
    "sharpness",
    "template_grid",
    "vote",
    "vote_volumes",
]


def _homogeneous(m: LinearMap) -> np.ndarray:
    d = m.dim
    h = np.eye(d + 1)
    h[:d, :d] = m.matrix
    h[:d, d] = m.translation
    return h


def mean_linear_map(maps: list[LinearMap]) -> LinearMap:
    """The log-Euclidean mean ``exp(mean_i log H_i)`` of affine maps in homogeneous form.

    Parameters
    ----------
    maps : list of LinearMap
        Maps of one dimension D (x -> A x + b, LPS mm), each with a positive determinant.

    Returns
    -------
    LinearMap
        The mean map; the identity for maps that are all the identity, and ``exp(log H)`` = H
        for one map.

    Raises
    ------
    ValueError
        No map, or a map that mirrors (non-positive determinant: no real logarithm).
    """
    if not maps:
        raise ValueError("Expected at least one linear map, got none.")
    logs = []
    for m in maps:
        if np.linalg.det(m.matrix) <= 0:
            raise ValueError(f"Expected maps with a positive determinant, got {np.linalg.det(m.matrix):.3g}.")
        logs.append(np.real(linalg.logm(_homogeneous(m))))
    h = np.real(linalg.expm(np.mean(logs, axis=0)))
    d = maps[0].dim
    return LinearMap(h[:d, :d], h[:d, d])


def template_grid(boxes: list[tuple[np.ndarray, np.ndarray]], spacing: float, margin: float) -> Grid:
    """An axis-aligned grid of isotropic ``spacing`` holding every box plus ``margin``.

    Parameters
    ----------
    boxes : list of ((D,), (D,)) float arrays, mm
        Lower and upper corners in template coordinates (LPS).
    spacing : float, mm
        Positive.
    margin : float, mm
        Added on every side.

    Returns
    -------
    Grid
        Identity direction; voxel centres from the union's lower corner minus ``margin``.
    """
    lo = np.min([b[0] for b in boxes], axis=0) - margin
    hi = np.max([b[1] for b in boxes], axis=0) + margin
    shape = tuple(int(n) for n in np.ceil((hi - lo) / spacing) + 1)
    return Grid(shape, lo, np.full(len(lo), float(spacing)), np.eye(len(lo)))


def vote(counts: np.ndarray, subjects: int, labels: np.ndarray) -> np.ndarray:
    """The template labels: at each voxel the label with most votes, the background's votes being
    the subjects that gave no label there; ties go to the background, then to the lower label.

    Parameters
    ----------
    counts : (L, *shape) array
        Votes (or probabilities times ``subjects``) per label of ``labels``.
    subjects : int
        The number of subjects.
    labels : (L,) int array
        The label values.

    Returns
    -------
    (*shape) array of the labels' dtype (at least uint8)
    """
    counts = np.asarray(counts, float)
    background = subjects - counts.sum(axis=0)
    best = counts.argmax(axis=0)
    top = np.take_along_axis(counts, best[None], axis=0)[0]
    dtype = np.result_type(np.min_scalar_type(int(np.max(labels, initial=0))), np.uint8)
    out = np.asarray(labels, dtype)[best]
    out[top <= background] = 0
    return out


def _tie_break(counts: np.ndarray, subjects: int) -> np.ndarray:
    """A label's votes plus, below one, their mean over the voxel's 3^D neighbourhood: the order of
    the voxels by their votes, ties broken towards the voxels among more votes."""
    c = np.asarray(counts, np.float32)
    return c + 0.99 * ndimage.uniform_filter(c, size=3, mode="nearest") / max(subjects, 1)


def _largest(score: np.ndarray, allowed: np.ndarray, n: int) -> np.ndarray:
    """The mask of the ``n`` largest ``score`` values among the ``allowed`` voxels (equal scores
    in C order of the voxels)."""
    where = np.flatnonzero(allowed)
    out = np.zeros(score.shape, bool)
    if n > 0 and where.size:
        order = np.argsort(-score.ravel()[where], kind="stable")[:n]
        out.ravel()[where[order]] = True
    return out


def vote_volumes(counts: np.ndarray, subjects: int, labels: np.ndarray) -> np.ndarray:
    """Template labels that keep each label's mean volume: a vote with a threshold per label.

    Label ``l`` takes the ``V_l = round(sum(counts_l) / subjects)`` voxels where it has most votes
    (the subjects' mean volume of it; ties broken towards the voxels among more votes, then in C
    order); a voxel that two labels take goes to the one with more votes there (then the lower
    label), and a label that lost voxels so takes as many more among those no label took.  The
    majority vote (:func:`vote`) thins a structure thinner than the subjects' disagreement on its
    place: at its edges no label has the majority, and the background wins; here its volume is kept.

    Parameters
    ----------
    counts : (L, *shape) int array
        Votes per label of ``labels`` (subjects with the label at the voxel).
    subjects : int
        The number of subjects.
    labels : (L,) int array
        The label values.

    Returns
    -------
    (*shape) array of the labels' dtype (at least uint8)
        Only voxels with at least one vote hold a label.
    """
    dtype = np.result_type(np.min_scalar_type(int(np.max(labels, initial=0))), np.uint8)
    shape = counts.shape[1:]
    out = np.zeros(shape, dtype)
    held = np.zeros(shape, np.int64)  # the votes of the label each voxel holds
    wanted = []
    for k, v in enumerate(labels):
        c = np.asarray(counts[k])
        n = round(float(c.sum(dtype=np.int64)) / max(subjects, 1))
        wanted.append(n)
        take = _largest(_tie_break(c, subjects), c > 0, n) & (c > held)
        out[take] = v
        held[take] = c[take]
    for k, v in enumerate(labels):  # the voxels lost to other labels, from those no label took
        c = np.asarray(counts[k])
        missing = wanted[k] - int(np.count_nonzero(out == v))
        if missing > 0:
            take = _largest(_tie_break(c, subjects), (c > 0) & (out == 0), missing)
            out[take] = v
    return out


def sharpness(counts: np.ndarray, subjects: int, template: np.ndarray, labels: np.ndarray) -> dict[int, float]:
    """Each label's mean probability over the template voxels it holds (1: every subject agrees).

    Parameters
    ----------
    counts : (L, *shape) array
    subjects : int
    template : (*shape) int array
        :func:`vote` of ``counts``.
    labels : (L,) int array

    Returns
    -------
    dict of int to float
        Labels absent from ``template`` are left out.
    """
    out = {}
    for k, v in enumerate(labels):
        inside = template == v
        if inside.any():
            out[int(v)] = float(np.asarray(counts[k], float)[inside].mean() / subjects)
    return out


def _sample_field(field: np.ndarray, grid: Grid, points: np.ndarray) -> np.ndarray:
    """Trilinear (bilinear) samples of a (*shape, C) field at world points (N, D); the nearest
    edge value outside."""
    index = grid.world_to_index(points).T
    return np.stack([ndimage.map_coordinates(field[..., c], index, order=1, mode="nearest")
                     for c in range(field.shape[-1])], axis=-1)


def invert_displacement(u: np.ndarray, grid: Grid, *, iterations: int = 30, tol: float = 1e-3) -> np.ndarray:
    """The displacement ``v`` of the inverse map: ``y + v(y) = phi^-1(y)`` for ``phi(x) = x + u(x)``.

    Fixed-point iteration ``v <- -u(y + v)`` (converges where ``|grad u| < 1``, as for an
    average of invertible warps).

    Parameters
    ----------
    u : (*shape, D) float array, mm
        On ``grid``.
    grid : Grid
    iterations : int
        At most this many steps.
    tol : float, mm
        Stop once no voxel's ``v`` moves by more than this.

    Returns
    -------
    (*shape, D) float array, mm
    """
    y = grid.grid_points().reshape(-1, grid.ndim)
    flat_u = u.reshape(-1, grid.ndim)
    v = -flat_u.copy()
    for _ in range(iterations):
        new = -_sample_field(u, grid, y + v)
        step = np.abs(new - v).max(initial=0.0)
        v = new
        if step < tol:
            break
    return v.reshape(u.shape)


def pull_back_points(grid: Grid, inverse: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Where a subject is read for the moved template: ``phi^-1(y) + u(phi^-1(y))`` at each voxel
    centre ``y`` of ``grid``, the subject's registration composed with the inverse shape update.

    Parameters
    ----------
    grid : Grid
        The template grid.
    inverse : (*shape, D) float array, mm
        :func:`invert_displacement` of the mean displacement: ``phi^-1(y) = y + inverse(y)``.
    u : (*shape, D) float array, mm
        The subject's pull-back field on ``grid`` (template point ``x`` is subject point
        ``x + u(x)``), read trilinearly between the voxel centres (the edge value beyond them).

    Returns
    -------
    (N, D) float array, mm
        Subject points, one per voxel of ``grid`` in C order.
    """
    points = grid.grid_points().reshape(-1, grid.ndim) + inverse.reshape(-1, grid.ndim)
    return points + _sample_field(u, grid, points)


def medoid(arrays: list[np.ndarray], labels: np.ndarray) -> tuple[int, np.ndarray]:
    """The label map closest to the others: the largest mean Dice to them.

    The Dice of two maps is the mean, over the labels either holds, of ``2 |A & B| / (|A| + |B|)``.

    Parameters
    ----------
    arrays : list of (*shape) int arrays
        Label maps on one grid (e.g. the subjects read through their linear maps), at least one.
    labels : (L,) int array
        The label values (sorted, without 0); other values count as background.

    Returns
    -------
    index : int
        Of the medoid in ``arrays`` (the first on a tie).
    mean_dice : (S,) float array
        Each map's mean Dice to the others (1.0 for a single map).
    """
    labels = np.asarray(labels)
    n = len(labels) + 1
    small = np.min_scalar_type(n)
    codes = []  # 0 for the background, k + 1 for labels[k]
    for a in arrays:
        a = np.asarray(a).ravel()
        k = np.searchsorted(labels, a).clip(0, max(len(labels) - 1, 0))
        known = (a != 0) & (labels[k] == a) if len(labels) else np.zeros(a.shape, bool)
        codes.append(np.where(known, k + 1, 0).astype(small))
        del k, known
    total = np.zeros((len(arrays), len(arrays)))
    for i in range(len(arrays)):
        for j in range(i + 1, len(arrays)):
            table = np.bincount(codes[i].astype(np.intp) * n + codes[j], minlength=n * n).reshape(n, n)
            sizes = (table.sum(1) + table.sum(0))[1:]
            held = sizes > 0
            d = float(np.mean(2.0 * np.diag(table)[1:][held] / sizes[held])) if held.any() else 1.0
            total[i, j] = total[j, i] = d
    mean = total.sum(1) / (len(arrays) - 1) if len(arrays) > 1 else np.ones(1)
    return int(np.argmax(mean)), mean


def rank_subjects(distances: dict[str, float], *, spread: float = 3.0) -> tuple[list[str], list[str]]:
    """Subjects ordered by their distance to the template (nearest first), and the outliers: those
    farther than the median by more than ``spread`` robust standard deviations (1.4826 x the
    median absolute deviation, at least 1 % of the median).

    Parameters
    ----------
    distances : dict of str to float, mm
        Each subject's mean distance to the template.
    spread : float

    Returns
    -------
    ranked, outliers : list of str
    """
    ranked = sorted(distances, key=lambda s: (distances[s], s))
    if not ranked:
        return [], []
    values = np.array([distances[s] for s in ranked])
    median = float(np.median(values))
    scale = max(1.4826 * float(np.median(np.abs(values - median))), 0.01 * median, 1e-9)
    return ranked, [s for s in ranked if distances[s] > median + spread * scale]

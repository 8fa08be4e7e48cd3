"""The linear stage of a registration: the map ``x -> A x + b`` found before the kernel warp.

A registration's map is ``tau(x) = A x + b + sum_j c_j k(x, x_j)``: the linear part
brings the moving object into the pose and size of the fixed one (a kernel warp of
compact support cannot rotate an object by 20 degrees), the kernel expansion (paper
eq. 9) does the rest.  Points are ``(N, D)`` arrays in world millimetres (LPS), D = 2
or 3; the map is a pull-back (fixed point -> moving point), as ITK's transforms are.

:func:`fit_linear` runs the stage: the labels' moments, boundary samples and distance
maps (:mod:`volreg.warp.linear_labels`), the candidate starts and their scoring
(:mod:`volreg.warp.linear_starts`), the coarse-to-fine refinement of the cost
(:mod:`volreg.warp.linear_refine`, :mod:`volreg.warp.linear_cost`), and the overlap check
(:func:`mean_dice_through`).  The map itself is :class:`~volreg.linear_map.LinearMap`.

The stage
---------
A closed-form start from the labels' moments, tested by the cost below, then a
coarse-to-fine least-squares fit of the symmetric locational distance cost
(paper eq. 3, with the labels' exact signed distances as the feature functions).

1. **Start.** Per label: volume, centroid and second moments in world mm.  When
   at least D + 1 labels, uncut by the image edge in both volumes, have centroids
   that span the space, a weighted Procrustes fit of the centroid pairs (Kabsch
   for rigid, Umeyama for similarity, least squares for affine when well
   conditioned).  Otherwise the principal axes of the labels' union,
   ``R = E_m diag(s) E_f^T`` for each sign choice with det +1, with the centroids'
   translation and the volume ratio's scale (for an affine map, the scales along
   the axes that carry one union's second moments onto the other's:
   ``E_m diag(s sqrt(l_m / l_f)) E_f^T``); and the centroid translation alone.
   The identity is always a candidate.  Each candidate runs a few iterations at
   the coarsest level; of those whose cost is within 1.5 times the lowest, the
   least rotated start wins (a near-symmetric object also fits upside down).
2. **Refinement.** Per label and volume, signed distance maps (mm, positive
   outside) on the volume's grid coarsened towards the level's spacing
   (object diameter / 16, / 32, / 64, never finer than the coarser volume's
   voxel, nor coarser than half a label's thickness) over the label's box plus a
   margin.  Samples are each label's boundary (voxel-face centres), thinned to a
   bounded number per label: fixed ones cost ``d_m(A x + b)^2``, moving ones
   ``d_f(A^-1 (y - b))^2`` (the symmetric cost keeps an affine map from
   shrinking), under a soft-L1 loss of scale twice the level's spacing, each
   label weighted by its boundary area.  ``scipy.optimize.least_squares`` with
   the analytic Jacobian; the parameters are about the fixed centroid
   (translation, rotation vector or angle, log-scale, or the full matrix).  For an
   affine map the starts' iterations and every level but the finest fit a
   similarity about the start's matrix, the finest level the full matrix: a smooth
   object turned is matched by a stretch along oblique axes as well as by the
   turn, and a coarse affine fit takes the stretch and stops short of the turn.
   Where the principal axes started the fit and two of the union's second moments
   are within 10 % of each other, the turn about the third axis is not shown at the
   coarse levels (a spheroidal brain shows it only by its folds): before the finest
   level is solved, its cost is evaluated at turns about that axis in steps of 5
   degrees and the lowest kept (of those within 2 % of it, the smallest turn),
   logged as ``turn_search``.  A symmetric object fits as well turned by any of its
   symmetries: where the refined map turns more than 45 degrees, the finest level's
   cost is evaluated after each turn that carries a cube onto itself in the fixed
   labels' principal axes and in the fixed image's axes, and of the maps within 2 %
   of the lowest the least rotated kept, logged as ``least_rotation``.
3. **Partial fields of view.** Samples of a label cut by the edge of either image
   (:func:`cut_labels`) whose image falls outside the other volume's field of view
   less two of its voxels carry no cost, and cut labels are left out of the
   centroid start.  Samples of uncut labels always count (beyond a map's box its
   distance keeps growing), so no map wins by pushing a label out of view.
4. **Overlap check.** The labels' mean Dice through the identity, the chosen start and
   the fitted map (nearest neighbour, at most about 2^18 fixed voxels); the first of
   them, in that order, whose Dice is the highest is kept.  Where the labels do not
   determine the map (one smooth organ: every ``A = L R L^-1`` maps an ellipsoid of
   semi-axes ``L`` onto itself) the fit drifts with the grids' differences without
   overlapping better, and on grids too coarse for the object (one organ over a few
   5 mm slices) it can run into a degenerate map that the coarse samples favour.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from volreg.errors import RegistrationInputError
from volreg.linear_map import LinearMap
from volreg.settings import LINEAR_KINDS
from volreg.warp.linear_labels import _label_shape, _LabelPair, _Side, _union_moments
from volreg.warp.linear_cost import _Local
from volreg.warp.linear_refine import _LEVEL_SAMPLES, _free_axis, _level_plan, _refine
from volreg.warp.linear_starts import _score_starts, _start_candidates

__all__ = ["KEEP_MARGIN", "LINEAR_KINDS", "LinearFit", "MAX_LINEAR_LABELS", "cut_labels",
           "fit_linear", "mean_dice_through"]

#: Labels that drive the linear fit at most (the largest by volume in the fixed volume).
MAX_LINEAR_LABELS = 30
#: The linear stage keeps the identity (or its start) over the fitted map unless the fitted map's
#: mean Dice is higher by more than this. Read by nearest neighbour between grids of different
#: resolutions, the same labels with no motion overlap a little better through an affine map
#: fitted to thick slices' staircase than through the identity, which is the better map; a real
#: change of pose gains several times this margin.
KEEP_MARGIN = 0.005


@dataclass(frozen=True, eq=False)
class LinearFit:
    """The result of :func:`fit_linear`.

    Attributes
    ----------
    map : LinearMap
        The pull-back ``x -> A x + b`` (fixed point -> moving point, LPS mm).
    log : dict
        JSON-ready record of the fit: ``kind``; ``start`` (``"centroids"``: the
        Procrustes fit of the label centroids or the centroids' translation alone;
        ``"principal axes"``; or ``"identity"``: the family of the start kept) and
        ``start_candidate`` (its name); ``candidates`` (name, closed-form map and the
        cost after a few iterations at the coarsest level); ``levels`` (per level:
        ``spacing_mm``, ``f_scale_mm``, ``samples``, ``cost``, ``iterations``,
        ``mean_abs_distance_mm``); ``labels`` (the labels that drove the fit);
        ``cut_labels`` (``fixed`` / ``moving``: labels touching the image edge);
        ``overlap`` (mean Dice through the ``identity``, the ``start`` and the ``refined``
        map, compared two at a time: the start against the refined map, then the identity
        against the one kept, each pair over the voxels both send into the moving image) and
        ``kept_instead`` (``None``, or which of the first two was kept);
        ``map`` (:meth:`LinearMap.describe`); ``seconds``.
    """

    map: LinearMap
    log: dict


def cut_labels(volume) -> list[int]:
    """The labels of ``volume`` with a voxel on the outermost layer of an axis.

    Such a label is cut by the edge of the image (a partial field of view): its
    centroid and moments are those of the visible part only.  Axes of length 1 do
    not count (a single slice is not a cut along its normal).

    Parameters
    ----------
    volume : LabelVolume

    Returns
    -------
    list of int
        Sorted non-zero label values.
    """
    array = np.asarray(volume.array)
    found: set[int] = set()
    for axis, n in enumerate(array.shape):
        if n <= 1:
            continue
        for index in (0, n - 1):
            found.update(int(v) for v in np.unique(np.take(array, index, axis=axis)))
    found.discard(0)
    return sorted(found)


def mean_dice_through(fixed, moving, maps, labels, fixed_boxes: dict, pooled: bool = False) -> np.ndarray:
    """Mean Dice of the fixed labels and the moving labels read through each of ``maps``.

    The moving labels are read by nearest neighbour at ``map(x)`` for fixed voxel centres
    ``x``: at most about 2^18 of them, every ``step``-th voxel of the labels' box widened by
    half its size on each side.

    Only voxels sent into the moving image count: beyond its field of view the moving image
    says nothing (read as background there, a map that squeezed the fixed labels into a moving
    image cut through them would overlap "better" than the right one).  A map under which no
    label lies on either side of the voxels it sends inside scores 0 (nothing it aligns was
    seen, as for the identity of two images apart); the others are compared on the voxels that
    all of them send inside, each over the labels on either side there (a map with none there
    scores 0).

    Parameters
    ----------
    fixed, moving : LabelVolume
        The two volumes, of one dimension D.
    maps : sequence of callable
        Pull-backs taking fixed points (N, D) mm to moving points (N, D) mm: a
        :class:`~volreg.linear_map.LinearMap`, a :class:`~volreg.warp.model.KernelWarp`, ...
    labels : sequence of int
        The non-zero labels to compare, each with a box in ``fixed_boxes``.
    fixed_boxes : dict of int to tuple of slice
        ``fixed.label_boxes()``: each label's index box in ``fixed``.
    pooled : bool
        Sum the labels' overlaps and sizes before the ratio
        (``sum 2 |A_v & B_v| / sum (|A_v| + |B_v|)``), so that each label weighs by its
        size and a label of a few voxels cannot outweigh the rest; otherwise the mean of
        the labels' Dice (:func:`volreg.evaluation.metrics.dice`).

    Returns
    -------
    (len(maps),) float ndarray
        Per map, in ``[0, 1]``.
    """
    from volreg.evaluation.metrics import dice
    from volreg.kernels.grid import rows_within
    from volreg.warp.resample import resample_labels_at

    lo = np.min([[b.start for b in fixed_boxes[v]] for v in labels], axis=0)
    hi = np.max([[b.stop for b in fixed_boxes[v]] for v in labels], axis=0)
    reach = (hi - lo) // 2
    lo, hi = np.maximum(lo - reach, 0), np.minimum(hi + reach, fixed.shape)
    step = max(1, int(np.ceil((np.prod(hi - lo, dtype=float) / 2**18) ** (1.0 / fixed.ndim))))
    axes = [np.arange(a, b, step) for a, b in zip(lo, hi)]
    index = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, fixed.ndim)
    points = fixed.index_to_world(index)
    label_f = fixed.array[tuple(index.T)]
    size_m = np.array(moving.shape)
    wanted = np.isin(label_f, labels)

    def seen(where: np.ndarray, label_m: np.ndarray) -> list:
        present = set(np.unique(label_f[where & wanted]).tolist())
        present |= set(np.unique(label_m[where]).tolist())
        return [v for v in labels if v in present]

    insides, reads = [], []
    for linear in maps:
        at = moving.world_to_index(linear(points))
        insides.append(rows_within(at, np.full(moving.ndim, -0.5), size_m - 0.5))
        reads.append(resample_labels_at(moving, at, method="nearest"))  # background outside
    active = [k for k in range(len(maps)) if seen(insides[k], reads[k])]
    common = np.logical_and.reduce([insides[k] for k in active]) if active else np.zeros(len(points), bool)
    out = []
    for k in range(len(maps)):
        compared = seen(common, reads[k]) if k in active else []
        if not compared:
            out.append(0.0)
            continue
        f, m = label_f[common], reads[k][common]
        if pooled:
            both = sum(2 * np.count_nonzero((f == v) & (m == v)) for v in compared)
            size = sum(np.count_nonzero(f == v) + np.count_nonzero(m == v) for v in compared)
            out.append(both / size)
        else:
            out.append(float(np.mean([dice(f == v, m == v) for v in compared])))
    return np.array(out)


def fit_linear(fixed, moving, *, kind: str = "affine", labels=None, progress=None) -> LinearFit:
    """Find the linear pull-back ``x -> A x + b`` (fixed -> moving, LPS mm) that aligns two label volumes.

    A closed-form start from the labels' moments, then a coarse-to-fine least-squares fit of
    the symmetric locational distance cost, then an overlap check (the steps of the module
    notes).  The :data:`MAX_LINEAR_LABELS` largest labels (by volume in ``fixed``) drive the fit.

    Parameters
    ----------
    fixed, moving : LabelVolume
        The two volumes, of one dimension (2 or 3).
    kind : {"none", "rigid", "similarity", "affine"}
        The family of maps; ``"none"`` returns the identity at once.
    labels : sequence of int, optional
        Labels to align (non-zero, present in both volumes).  Default: every non-zero
        label present in both.
    progress : callable, optional
        ``progress(stage, done, total)``: ``"linear start"`` per candidate, then
        ``"fit linear"`` per level.

    Returns
    -------
    LinearFit
        The map and a JSON-ready log.

    Raises
    ------
    ValueError
        An unknown ``kind``; volumes of different dimensions; a requested label absent
        from a volume; no label in common (:class:`~volreg.errors.RegistrationInputError`).
    """
    t_begin = time.perf_counter()
    if kind not in LINEAR_KINDS:
        raise ValueError(f"Expected `kind` in {LINEAR_KINDS}, got {kind!r}.")
    if moving.ndim != fixed.ndim:
        raise ValueError(f"Expected `moving` of the same dimension as `fixed` ({fixed.ndim}-D), got {moving.ndim}-D.")
    dim = fixed.ndim
    if kind == "none":
        return _identity_fit("none", dim, "identity", [], cut_labels(fixed), cut_labels(moving), t_begin)

    boxes_f, boxes_m = fixed.label_boxes(), moving.label_boxes()
    drive = _driving_labels(fixed, boxes_f, _chosen_labels(boxes_f, boxes_m, labels))
    cap = _LEVEL_SAMPLES[-1]
    shapes_f = {v: _label_shape(fixed, v, boxes_f[v], cap, np.random.default_rng(abs(v))) for v in drive}
    shapes_m = {v: _label_shape(moving, v, boxes_m[v], cap, np.random.default_rng(abs(v))) for v in drive}
    cut_f, cut_m = cut_labels(fixed), cut_labels(moving)

    if not any(len(s.points) for s in shapes_f.values()) or not any(len(s.points) for s in shapes_m.values()):
        # No label has a boundary inside an image (a volume filled by one label): nothing to align.
        return _identity_fit(kind, dim, "identity (no label boundary in an image)", [int(v) for v in drive],
                             cut_f, cut_m, t_begin)

    centre, diameter = _centre_and_diameter(list(shapes_f.values()))
    spacings, counts, floor_mm = _level_plan(fixed, moving, diameter, len(drive))
    pair = _LabelPair(_Side(fixed, shapes_f), _Side(moving, shapes_m), drive, set(cut_f) | set(cut_m), floor_mm,
                      centre, 0.5 * diameter)
    local = _Local(kind, dim)
    # For an affine map the starts and every level but the finest fit a similarity about the
    # start's matrix (which keeps the start's own stretch), the finest the whole affine map: a
    # smooth object turned can be matched by a stretch along oblique axes as well (every
    # ``A = L R L^-1`` maps an ellipsoid of semi-axes ``L`` onto itself), and a coarse affine fit
    # stopped there, short of the turn that the finer levels' detail then needed.
    coarse_local = _Local("similarity", dim) if kind == "affine" and len(spacings) > 1 else local

    candidates = _start_candidates(pair, kind)
    tried, index, current = _score_starts(pair, candidates, coarse_local, spacings[0], counts[0], progress)
    start_family, start_name, chosen_start = candidates[index]
    # Where the labels' moments are (nearly) symmetric about an axis and no spread of label
    # centroids shows the turn about it, only finer detail does (a spheroidal brain's folds):
    # the coarse levels cannot tell, and the finest level's cost is searched over that turn.
    by_centroids = any(family == "centroids" and name != "centroid translation" for family, name, _ in candidates)
    uncut = [v for v in drive if v not in pair.cut]
    turn_axis = None if by_centroids or dim != 3 else _free_axis([shapes_f[v] for v in (uncut or drive)])

    # The frames in which the fixed labels may be symmetric: their principal axes, and the image's
    # own axes (a cube's moments are the same about every axis, its principal axes any three).
    _, _, cov_f = _union_moments(list(shapes_f.values()))
    frames = [np.linalg.eigh(cov_f)[1], np.asarray(fixed.direction, float)]
    current, level_log, searches = _refine(pair, current, local, coarse_local, spacings, counts, turn_axis, frames,
                                           progress)
    current, overlap, kept = _overlap_check(fixed, moving, chosen_start, current, drive, boxes_f)
    log = dict(
        kind=kind,
        overlap=overlap,
        kept_instead=kept,
        start=start_family,
        start_candidate=start_name,
        candidates=tried,
        levels=level_log,
        labels=[int(v) for v in drive],
        cut_labels=dict(fixed=cut_f, moving=cut_m),
        diameter_mm=diameter,
        map=current.describe(),
        seconds=time.perf_counter() - t_begin,
    )
    log.update(searches)  # turn_search, least_rotation: where they ran
    return LinearFit(current, log)


def _identity_fit(kind: str, dim: int, why: str, labels: list[int], cut_f: list[int], cut_m: list[int],
                  t_begin: float) -> LinearFit:
    """The identity as the fit of ``kind``: no candidates, no levels; ``why`` names its start candidate."""
    ident = LinearMap.identity(dim)
    return LinearFit(ident, dict(kind=kind, start="identity", start_candidate=why, candidates=[], levels=[],
                                 labels=labels, cut_labels=dict(fixed=cut_f, moving=cut_m), map=ident.describe(),
                                 seconds=time.perf_counter() - t_begin))


def _chosen_labels(boxes_f: dict, boxes_m: dict, labels) -> list[int]:
    """The labels to align, sorted: ``labels`` checked, or every non-zero label both volumes hold."""
    if labels is None:
        chosen = sorted(set(boxes_f) & set(boxes_m))
        if not chosen:
            raise RegistrationInputError("Expected `fixed` and `moving` to share a non-zero label, found none.")
        return chosen
    chosen = sorted({int(v) for v in labels})
    absent = [v for v in chosen if v == 0 or v not in boxes_f or v not in boxes_m]
    if absent or not chosen:
        raise RegistrationInputError(
            f"Expected `labels` to be non-zero labels present in both volumes, got {absent[:10] or 'none'}.")
    return chosen


def _driving_labels(fixed, boxes_f: dict, chosen: list[int]) -> list[int]:
    """The :data:`MAX_LINEAR_LABELS` largest of ``chosen`` by volume in ``fixed``, sorted: they drive the fit."""
    voxel_f = float(np.prod(fixed.spacing))
    sizes = {v: int(np.count_nonzero(fixed.array[boxes_f[v]] == v)) * voxel_f for v in chosen}
    return sorted(sorted(chosen, key=lambda v: -sizes[v])[:MAX_LINEAR_LABELS])


def _centre_and_diameter(shapes: list) -> tuple[np.ndarray, float]:
    """The labels' joint centroid (D,) mm and the diagonal of their boundary samples' bounding box, mm."""
    _, centre, _ = _union_moments(shapes)
    lo = np.min([s.points.min(axis=0) for s in shapes if len(s.points)], axis=0)
    hi = np.max([s.points.max(axis=0) for s in shapes if len(s.points)], axis=0)
    return centre, max(float(np.linalg.norm(hi - lo)), 1e-6)


def _overlap_check(fixed, moving, start: LinearMap, refined: LinearMap, labels: list[int],
                   boxes_f: dict) -> tuple[LinearMap, dict, str | None]:
    """The map kept of the identity, the chosen start and the refined map, by the labels' overlap.

    The fit minimises boundary distances on maps coarsened to each level.  Where the labels do
    not determine the map it drifts with the grids' differences (one smooth organ: every
    ``A = L R L^-1`` maps an ellipsoid of semi-axes ``L`` onto itself), and on grids too coarse
    for the object (a few thick slices) it can run into a degenerate map the coarse samples
    favour.  The labels' overlap checks it: the start is kept instead of the refined map where
    its mean Dice is as high, to :data:`KEEP_MARGIN` (and above 0: on voxels where neither
    overlaps a label the two are not told apart), then the identity instead of that likewise.
    Two maps at a time, each pair on the voxels both send into the moving image: all three at
    once would be compared on the voxels every one of them sends inside, which for images far
    apart is a corner far from the labels, where a map that missed the turn or the shift could
    beat the one that found it.

    Returns
    -------
    LinearMap
        The map kept.
    dict
        Mean Dice (:func:`mean_dice_through`) through ``identity``, ``start`` and ``refined``.
    str or None
        ``"identity"`` or ``"start"`` where one was kept instead of the refined map.
    """
    maps = [("identity", LinearMap.identity(fixed.ndim)), ("start", start), ("refined", refined)]
    overlap = {}
    pick = len(maps) - 1
    for k in range(len(maps) - 2, -1, -1):
        pair = mean_dice_through(fixed, moving, [maps[k][1], maps[pick][1]], labels, boxes_f)
        overlap.setdefault(maps[pick][0], float(pair[1]))
        overlap[maps[k][0]] = float(pair[0])
        if pair[0] >= pair[1] - KEEP_MARGIN and pair[0] > 0:
            pick = k
    kept = None if pick == len(maps) - 1 else maps[pick][0]
    return maps[pick][1], {name: overlap[name] for name, _ in maps}, kept



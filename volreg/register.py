"""Registration as users call it: label volumes or surfaces in, a fitted kernel warp out.

:func:`register_labels` (the main job) turns two label volumes into feature pairs --
one kernel implicit surface per driving label and side (paper Section 4, eq. 6), plus
voxel signed-distance maps (not in the paper) -- and fits the warp with
:func:`volreg.warp.fit.fit_warp`.  :func:`register_surfaces` does the same for meshes
or point clouds with normals.

:func:`write_registration` registers two label volumes and writes every output
(displacement fields, warped labels, the model, the Jacobian map, a report) into a
folder, all or nothing; :func:`register_both_ways` registers A to B and B to A, as the
consistency test (paper Section 5) needs; :func:`check_pair` refuses, before any work,
a pair that cannot be registered (different dimensions, grids apart, too large).
"""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, NamedTuple, Sequence
import numpy as np
from volreg import __version__
from volreg._memory import available_bytes
from volreg._threads import JobQueue, single_blas, thread_map
from volreg.features.implicit import ImplicitSurface, default_min_width
from volreg.grid import LabelVolume
from volreg.kernels.grid import column_bounds
from volreg.warp.objective import FeaturePair
from volreg.errors import RegistrationInputError
from volreg.settings import Protocol, SurfaceSettings, WarpSettings
from volreg.warp.fit import RegistrationResult, check_folding, fit_warp

__all__ = [
    "LabelRegistration",
    "ITK_H5_OUTPUTS",
    "REGISTRATION_OUTPUTS",
    "TwoWayRegistration",
    "check_pair",
    "despeckle",
    "estimated_peak_gb",
    "feature_unit",
    "mesh_min_width",
    "register_both_ways",
    "register_labels",
    "register_surfaces",
    "world_box",
    "registration_outputs",
    "write_registration",
]

ProgressCallback = Callable[[str, int, int], None]


def _surface_points(surface) -> ImplicitSurface | tuple[np.ndarray, np.ndarray]:
    """An ImplicitSurface as given, or the (points, normals) of a pyvista mesh or a (points, normals) pair."""
    if isinstance(surface, ImplicitSurface):
        return surface
    if isinstance(surface, tuple):
        if len(surface) != 2:
            raise TypeError(f"Expected `source`/`target` tuples as (points, normals), got {len(surface)} items.")
        return tuple(np.asarray(a, float) for a in surface)
    try:
        import pyvista as pv
    except ImportError:  # pragma: no cover - pyvista is a dependency
        pv = None
    if pv is not None and isinstance(surface, pv.PolyData):
        mesh = surface.triangulate().compute_normals(point_normals=True, cell_normals=False,
                                                     auto_orient_normals=True, consistent_normals=True)
        return np.asarray(mesh.points, float), np.asarray(mesh.point_data["Normals"], float)
    raise TypeError(
        f"Expected `source`/`target` as pyvista PolyData, ImplicitSurface or (points, normals), got {type(surface).__name__}."
    )


@single_blas
def register_surfaces(
    source,
    target,
    *,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    settings: WarpSettings = WarpSettings(),
    progress: Callable[[str, int, int], None] | None = None,
    align_centroids: bool = True,
) -> RegistrationResult:
    """Register ``source`` onto ``target``: ``result.warp`` maps source points to target points.

    Parameters
    ----------
    source, target : pyvista.PolyData, ImplicitSurface, (points, normals), or lists of them
        One object or several (one per label: several feature functions, (6)),
        in the same order for both.  Meshes and points are fitted as
        :class:`~volreg.features.implicit.ImplicitSurface` (in parallel, one surface per thread),
        down to the finer of its default width (8 vertex spacings) and the warp's finest
        width / sqrt(2), but not below 3 vertex spacings.
    landmarks : pair of (L, D) float ndarrays, optional
        Source landmark points and their target positions, mm.
    settings : WarpSettings
    progress : callable, optional
    align_centroids : bool
        First move the source by the translation between the two point sets' centroids, where
        that brings its points nearer the target's (:func:`centroid_shift`); the warp then holds
        that translation as its linear part.  A kernel warp moves a surface little further than
        its own kernels reach: a bumpy sphere 108 mm across shifted 15 mm ended with its points
        6 % of the diameter from their partners, 25 mm 11 % (the warped source on the target).
        Rotations and scales are not found: the two must be in one frame and turned alike.

    Returns
    -------
    RegistrationResult
        ``.warp`` (:class:`~volreg.warp.KernelWarp`) and ``.log`` (per level:
        width, samples, iterations, objective terms, seconds).
    """
    sources = source if isinstance(source, list) else [source]
    targets = target if isinstance(target, list) else [target]
    if len(sources) != len(targets):
        raise ValueError(f"Expected as many `target` objects as `source` objects, got {len(targets)} and {len(sources)}.")
    data = [_surface_points(x) for x in sources + targets]

    def points_of(objects) -> np.ndarray:
        return np.concatenate([d.points if isinstance(d, ImplicitSurface) else d[0] for d in objects])

    points = points_of(data[:len(sources)])
    # Surfaces given as points are fitted about as finely as the warp's finest level at least
    # (features coarser than a level cannot pin it): down to its width / sqrt(2), so that the
    # halving widths of a target of another size also reach it, but not below 3 vertex spacings
    # (sparser training points than that leave holes between the kernels).  ImplicitSurface's own
    # default (8 vertex spacings) is coarser than the warp on decimated meshes: on a folded,
    # cortex-like surface of 10k vertices (110 mm across, sulci 7 mm apart) it stopped at 13.8 mm
    # where the warp's finest level is 6.9 mm, and left the warped vertices 0.78-0.99 % of the
    # diameter from their partners instead of 0.22-0.24 % (`bench_sliding.py --shapes cortex`).
    diameter = _diameter(points) if len(points) else 0.0
    finest = settings.resolved(diameter).min_width / np.sqrt(2.0) if diameter > 0 else np.inf

    def fit(d) -> ImplicitSurface:
        if isinstance(d, ImplicitSurface):
            return d
        if len(d[0]) < 2:  # ImplicitSurface says what it expects
            return ImplicitSurface(*d)
        return ImplicitSurface(*d, min_width=mesh_min_width(d[0], finest))

    fits = list(thread_map(fit, data))  # independent fits: numba releases the GIL
    shift = None
    if align_centroids and len(points):
        shift = centroid_shift(points, points_of(data[len(sources):]))
    if shift is None:
        pairs = [FeaturePair(f1, f2) for f1, f2 in zip(fits[:len(sources)], fits[len(sources):])]
        return fit_warp(pairs, points, landmarks=landmarks, settings=settings, progress=progress)
    # tau = L o phi: phi is fitted between the source's features and the target's seen through L
    from volreg.features.mapped import LinearlyMapped
    from volreg.warp.linear import LinearMap

    linear = LinearMap(np.eye(points.shape[1]), shift)
    pairs = [FeaturePair(f1, LinearlyMapped(f2, linear)) for f1, f2 in zip(fits[:len(sources)], fits[len(sources):])]
    if landmarks is not None:
        landmarks = (landmarks[0], np.asarray(landmarks[1], float) - shift)
    result = fit_warp(pairs, points, landmarks=landmarks, settings=settings, progress=progress)
    return RegistrationResult(result.warp.then(linear), result.log)


def centroid_shift(source: np.ndarray, target: np.ndarray) -> np.ndarray | None:
    """The translation (D,) mm between the centroids of ``source`` and ``target`` (points (N, D),
    (M, D) mm; each point weighted by the surface it stands for, :func:`_area_centroid`), where it
    brings the source nearer: the median distance of the moved source points to their nearest
    target points below that of the points as they lie; ``None`` where it does not (one surface
    is part of the other, pre-aligned) or is under 1 % of the source's diameter.
    """
    from scipy.spatial import cKDTree

    shift = _area_centroid(target) - _area_centroid(source)
    if np.linalg.norm(shift) <= 0.01 * _diameter(source):
        return None
    tree = cKDTree(target)
    before = np.median(tree.query(source)[0])
    after = np.median(tree.query(source + shift)[0])
    return shift if after < before else None


def _area_centroid(points: np.ndarray, k: int = 6) -> np.ndarray:
    """The centroid (D,) mm of surface points (N, D) mm, each weighted by the surface it stands
    for: its distance to its ``k``-th nearest neighbour to the power D - 1.

    A mean over the vertices follows the meshing: a target meshed four times as densely on one
    half put a plain mean 10 mm off on a body 115 mm across, and 50 vertices of debris 400 mm
    away 6 mm.  Repeated points count once, and no point's spacing counts above twice the
    median (else a few stray points, far from their neighbours, would weigh as much as a
    surface).  Where all points coincide, the plain mean.
    """
    from scipy.spatial import cKDTree

    points = np.unique(np.asarray(points, float), axis=0)  # a repeated point stands for no more surface
    if len(points) <= k:
        return points.mean(axis=0)
    spacing = cKDTree(points).query(points, k=k + 1)[0][:, -1]
    # A few stray points (a one-voxel speck's octahedron) are far from their sixth neighbour: capped
    # at two typical spacings, they weigh little more than the surface they stand for.
    spacing = np.minimum(spacing, 2.0 * float(np.median(spacing)))
    weight = spacing ** (points.shape[1] - 1)
    total = float(weight.sum())
    return points.mean(axis=0) if not total > 0 else weight @ points / total


def mesh_min_width(points: np.ndarray, finest: float) -> float:
    """The finest implicit-surface width (mm) :func:`register_surfaces` fits a mesh's ``points``
    (N, D) mm down to: ``finest`` (the warp's finest width / sqrt(2)), clipped to 3-8 vertex
    spacings (8 is :class:`~volreg.features.implicit.ImplicitSurface`'s default)."""
    default = default_min_width(points)  # 8 vertex spacings
    return min(default, max(finest, 3.0 * default / 8.0))


def _diameter(points: np.ndarray) -> float:
    """Diagonal of the bounding box of ``points``, mm."""
    lo, hi = column_bounds(points)
    return float(np.linalg.norm(hi - lo))


#: A label drives the warp by default when at least this fraction of its voxels lies in
#: pieces holding >= 5 % of the label each (in both volumes).  On the frog demo (3 mm), with
#: the robust distance term, its labels at 0.87 (13), 0.73 (12) and 0.54 (1) gave endpoint
#: errors of 0.70 mm driving 13 and 0.75 driving all three (``fast`` with a 24 mm finest width
#: and 48 mm sample spacing), and 0.96 driving 13 against 1.28 driving none (``fast`` as
#: shipped); with the squared cost (3), driving 13 had made it worse.
COMPACT_FRACTION = 0.8


#: Pieces of a driving label smaller than this fraction of its voxels are removed before its
#: surface is made.  On the frog at 3 mm: 0.05 -> endpoint error
#: 0.611 / 1.468 mm (mean / p95), Dice 0.887; 0.01 -> 0.521 / 1.175, Dice 0.888 (the small bones
#: of the skeleton, label 13, then drive the warp); at full resolution no change (0.296 -> 0.295 mm).
SPECK_FRACTION = 0.01


def despeckle(volume, labels, *, piece: float = 0.05, judge: float | None = None):
    """Remove each label's specks: connected pieces (face connectivity) smaller than
    ``piece`` times the label's voxel count (they are set to 0).

    ``judge`` (default ``piece``) is the piece fraction by which ``kept`` is measured.

    Returns
    -------
    cleaned : LabelVolume
    kept : dict of int to float
        Per label, the fraction of its voxels that lies in pieces of at least ``judge``
        times the label's voxel count.
    """
    from scipy import ndimage

    array = volume.array.copy()
    kept = {}
    boxes = volume.label_boxes()
    for v in labels:
        box = boxes.get(v, tuple(slice(0, n) for n in volume.shape))
        mask = volume.array[box] == v
        pieces, n = ndimage.label(mask)
        sizes = np.bincount(pieces.ravel())[1:]
        total = int(sizes.sum())
        if total == 0:
            kept[v] = 0.0
            continue
        small = np.flatnonzero(sizes < piece * total) + 1
        kept[v] = float(sizes[sizes >= (piece if judge is None else judge) * total].sum() / total)
        if len(small):
            sub = array[box]
            sub[np.isin(pieces, small)] = 0
    return volume.with_array(array), kept


@dataclass
class LabelRegistration(RegistrationResult):
    """A label-volume registration: the warp (fixed -> moving), its log, and what drove it.

    Attributes
    ----------
    labels : list of int
        The labels whose implicit surfaces drove the warp (protocol ``surface.implicit_weight``
        > 0; none by default).
    skipped : list of str
        Labels whose implicit surfaces were left out (too small in one of the volumes, or
        speckled), with the reason.
    distance_labels : list of int
        The labels whose voxel signed-distance maps drove the warp (protocol
        ``surface.distance_weight`` > 0).
    stages : list of dict
        Per stage: ``{"stage", "seconds"}``.
    linear : LinearFit
        The linear stage (:func:`~volreg.warp.linear.fit_linear`): its map, also the
        linear part of ``warp``, and its log.
    cut_labels : dict
        ``{"fixed": [...], "moving": [...]}``: labels cut by the edge of each image (partial
        field of view); near the edges the locational cost is not counted.
    kernel_warp : dict
        The overlap check of the kernel warp (:func:`kernel_warp_overlap`): ``dice_linear``,
        ``dice_warp``, ``margin`` and ``kept`` (``"warp"``, or ``"linear"`` where the kernel
        warp lowered the labels' pooled Dice by more than :data:`KERNEL_DICE_MARGIN` and
        ``warp`` is the linear part alone), and ``levels_fitted``: the kernel warp's levels
        fitted (the same check after the first level ends the fit there when it fails).
    """

    labels: list = field(default_factory=list)
    skipped: list = field(default_factory=list)
    stages: list = field(default_factory=list)
    distance_labels: list = field(default_factory=list)
    linear: object = None
    cut_labels: dict = field(default_factory=dict)
    kernel_warp: dict = field(default_factory=dict)


#: How far the kernel warp may lower the labels' pooled Dice below the linear part's alone before
#: the linear part alone is kept (:func:`kernel_warp_overlap`).
KERNEL_DICE_MARGIN = 0.02


@single_blas
def register_labels(
    fixed,
    moving,
    *,
    drive_labels: Sequence[int] | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    protocol=None,
    prior: Callable[[np.ndarray], np.ndarray] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> LabelRegistration:
    """Register two label volumes: ``result.warp`` maps fixed points to moving points (pull-back).

    Each label present in both volumes (or each drive label) gives a feature pair (paper (6)):
    its signed distance function (3)-(4) in the fixed volume (``f1``, O1) and in the moving
    volume (``f2``, O2), read from the label's voxels
    (:class:`~volreg.distance_maps.VoxelDistance`, weight ``surface.distance_weight``), so that
    labels too small or too fragmented for a surface drive the warp as well.  With the
    protocol's ``surface.implicit_weight`` > 0 each label with a surface in both volumes also
    gives the pair of kernel implicit surfaces (Section 4) of its boundary meshes.  The warp
    is fitted in the padded neighbourhood of the fixed boundary meshes (:func:`fit_warp`).

    Parameters
    ----------
    fixed, moving : LabelVolume
    drive_labels : sequence of int, optional
        Labels whose distance maps (and implicit surfaces) drive the warp; default every label
        present in both volumes, whose meshes and implicit surfaces leave out speckled ones
        (less than :data:`COMPACT_FRACTION` of the voxels in pieces of at least 5 % of the
        label, see :func:`despeckle`).
        Specks (pieces under :data:`SPECK_FRACTION` of the label) are removed
        before the surfaces are made.  Labels too small to give a surface in
        either volume are skipped (their distance maps still count).
        ``result.skipped`` says which and why.
    landmarks : pair of (L, D) float ndarrays, optional
        Fixed-space points and their moving-space partners, LPS mm.
    protocol : Protocol, optional
        Default :func:`volreg.protocol.load_protocol` ``("default")``.
    prior : callable, optional
        Target positions for the symmetric option (see :func:`fit_warp`), e.g. the
        inverse of a registration of ``moving`` to ``fixed``.
    progress : callable, optional
        ``progress(stage, done, total)``.

    Returns
    -------
    LabelRegistration

    Raises
    ------
    RegistrationInputError
        No label in common, a requested label absent from a volume, or, with
        the protocol's ``distance_weight`` 0 (implicit surfaces alone), no label with a surface
        in both volumes (with distance maps every common label drives, surface or not).
    """
    from volreg.io.protocol import load_protocol
    from volreg.warp.linear import fit_linear

    protocol = load_protocol("default") if protocol is None else protocol
    common, labels = _candidate_labels(fixed, moving, drive_labels)
    unit = feature_unit(fixed, moving)
    stages = []

    t0 = time.perf_counter()
    linear_fit = fit_linear(fixed, moving, kind=protocol.linear.kind, labels=labels, progress=progress)
    linear = linear_fit.map
    cut = {side: [int(v) for v in linear_fit.log["cut_labels"][side]] for side in ("fixed", "moving")}
    stages.append(dict(stage="linear", seconds=time.perf_counter() - t0))

    t0 = time.perf_counter()
    implicit = protocol.surface.implicit_weight > 0
    clean_fixed, clean_moving, labels, skipped = _despeckled(fixed, moving, labels, drive_labels is None,
                                                             protocol.surface)
    # The fixed meshes delimit the warp volume X; the moving ones are needed only for implicit surfaces.
    s_fixed, s_moving, notes = _surface_pairs(clean_fixed, clean_moving if implicit else None, labels,
                                              protocol.surface, unit, progress)
    meshed = [v for v in labels if v in s_fixed]
    used = [v for v in meshed if v in s_moving]  # none without implicit surfaces (no moving meshes)
    if implicit:
        skipped += notes
    else:
        skipped = []  # no surface drives: nothing is left out
    if not used and protocol.surface.distance_weight <= 0:
        # With distance maps (distance_weight > 0) every label drives, with a surface or not.
        raise RegistrationInputError(
            f"No label of {labels[:30]} gives a surface in both volumes and the protocol's distance_weight is 0; "
            "nothing drives the warp (set distance_weight > 0 to drive by the labels' voxel distance maps)."
        )
    stages.append(dict(stage="surfaces", seconds=time.perf_counter() - t0))

    pairs = []
    if implicit:
        t0 = time.perf_counter()
        pairs = _implicit_pairs(s_fixed, s_moving, used, protocol.surface, unit, linear, progress)
        stages.append(dict(stage="implicit surfaces", seconds=time.perf_counter() - t0))

    distance_labels = []
    boxes_f = {}
    if protocol.surface.distance_weight > 0:
        # Voxel signed-distance features: every label in both volumes (or the chosen
        # drive labels), also those too small or too fragmented for a surface.
        t0 = time.perf_counter()
        distance_labels = common if drive_labels is None else labels
        boxes_f, boxes_m = fixed.label_boxes(), moving.label_boxes()
        coarse = _finer_on_coarser(fixed, moving, linear) if protocol.surface.resample_finer else None
        pairs += _distance_pairs(fixed, moving, distance_labels, boxes_f, boxes_m, protocol.surface, unit, linear,
                                 progress, coarse)
        stages.append(dict(stage="voxel distance maps", seconds=time.perf_counter() - t0))

    t0 = time.perf_counter()
    points = _warp_volume_points(fixed, s_fixed, meshed, distance_labels, boxes_f)
    if len(points) < 2:
        raise RegistrationInputError(
            f"The labels that drive the warp ({(distance_labels or used)[:30]}) give {len(points)} point to fit it at "
            "(a label of a single voxel); expected labels of a few voxels at least."
        )
    # The kernel warp phi is fitted between the fixed features and the moving ones seen through
    # the linear part (tau = L o phi), so landmarks and the prior are taken back through L^-1.
    back = None if linear.is_identity else linear.inverse()
    if back is not None and landmarks is not None:
        landmarks = (landmarks[0], back(np.asarray(landmarks[1], float)))
    if back is not None and prior is not None:
        prior = _then(prior, back)
    valid = None
    if cut["fixed"] or cut["moving"]:
        margin = protocol.surface.min_width_voxels * unit + protocol.surface.clip_mm(unit)
        # A cut label's box in the image that cuts it ends at the cut; the other image's box of
        # the same label (through L) reaches where the first image has nothing.
        either = sorted(set(cut["fixed"]) | set(cut["moving"]))
        boxes = _world_boxes(fixed, either) + _world_boxes(moving, either, back)
        valid = _field_of_view_test(fixed, moving, linear, margin, boxes)
    checked = labels if landmarks is None else []  # landmarks may ask for what the labels do not show
    boxes = (boxes_f or fixed.label_boxes()) if checked else {}  # for both overlap checks

    def whole(phi):
        return phi if linear.is_identity else phi.then(linear)

    def stop(phi) -> bool:
        # The overlap check after the coarsest level too: where that level already lowers the
        # labels' overlap beyond the margin, the finer ones are not fitted (the check below
        # then drops the warp).  Only the first: finer levels seldom turn what it started.
        first = len(phi.levels) == 1
        return first and kernel_warp_overlap(fixed, moving, whole(phi), linear, checked, boxes)[1]["kept"] == "linear"

    result = fit_warp(pairs, points, landmarks=landmarks, settings=protocol.warp, prior=prior, valid=valid,
                      progress=progress, stop=stop if checked else None)
    warp = whole(result.warp)
    warp, kernel_warp = kernel_warp_overlap(fixed, moving, warp, linear, checked, boxes)
    kernel_warp["levels_fitted"] = len(result.log)
    stages.append(dict(stage="fit warp", seconds=time.perf_counter() - t0))
    return LabelRegistration(warp, result.log, labels=used, skipped=skipped, stages=stages,
                             distance_labels=[int(v) for v in distance_labels], linear=linear_fit,
                             cut_labels=cut, kernel_warp=kernel_warp)


def kernel_warp_overlap(fixed, moving, warp, linear, labels: list[int], boxes: dict | None = None):
    """Keep the kernel warp only where it does not lower the labels' overlap.

    The pooled Dice over ``labels`` (``sum 2 |A_v & B_v| / sum (|A_v| + |B_v|)``: each label
    weighs by its size) of the fixed labels and the moving ones read through the linear part
    alone and through the whole warp (nearest neighbour, at most about 2^18 fixed voxel
    centres, as the linear stage's check).  Where the kernel warp lowers it by more than
    :data:`KERNEL_DICE_MARGIN`, its features misled it (a label only a few voxels across on the
    coarser grid, whose features are read at that grid's largest spacing: one organ over five
    5 mm slices ended at Dice 0.90 where the linear part alone gave 0.99), and the linear part
    alone is returned.

    Parameters
    ----------
    fixed, moving : LabelVolume
    warp : KernelWarp
        The whole map ``x -> L(phi(x))``.
    linear : LinearMap
        Its linear part ``L``.
    labels : list of int
        The labels compared; none: nothing is checked.
    boxes : dict, optional
        ``fixed.label_boxes()``, where the caller has them already.

    Returns
    -------
    warp : KernelWarp
        ``warp``, or the linear part alone (no levels).
    log : dict
        ``dice_linear``, ``dice_warp`` (``None`` when nothing was checked), ``margin``
        (:data:`KERNEL_DICE_MARGIN`), ``kept``.
    """
    from volreg.warp.linear import _mean_dice
    from volreg.warp.model import KernelWarp

    if not labels or not warp.levels:
        return warp, dict(dice_linear=None, dice_warp=None, margin=KERNEL_DICE_MARGIN, kept="warp")
    boxes = fixed.label_boxes() if boxes is None else boxes
    by_linear, by_warp = _mean_dice(fixed, moving, [linear, warp], labels, boxes, pooled=True)
    log = dict(dice_linear=float(by_linear), dice_warp=float(by_warp), margin=KERNEL_DICE_MARGIN,
               kept="warp")
    if by_warp < by_linear - KERNEL_DICE_MARGIN:
        log["kept"] = "linear"
        warp = KernelWarp((), dim=warp.dim, settings=warp.settings, linear=linear)
    return warp, log


def landmark_errors(warp, landmarks: tuple[np.ndarray, np.ndarray], fixed) -> dict:
    """How far the warp carries each fixed landmark from its moving partner (the report's
    ``landmarks`` block).

    Parameters
    ----------
    warp : callable
        The pull-back map, fixed (N, D) mm -> moving (N, D) mm.
    landmarks : pair of (L, D) float ndarrays
        Fixed landmarks and their moving partners, mm.
    fixed : LabelVolume
        The fixed volume; the diameter of the box of its label voxels (mm) is the scale of
        the percentages.

    Returns
    -------
    dict
        ``count``; ``error_mm`` per landmark |tau(p) - q|; ``mean_mm``, ``max_mm``;
        ``mean_percent_of_diameter`` (of the fixed labels' diameter, ``diameter_mm``); and
        ``identity_mean_mm``, the mean |p - q| before registering.
    """
    p, q = (np.asarray(v, float) for v in landmarks)
    err = np.linalg.norm(np.asarray(warp(p)) - q, axis=1)
    boxes = _world_boxes(fixed, [int(v) for v in fixed.labels() if v != 0]) or [world_box(fixed)]
    lo, hi = np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)
    diameter = float(np.linalg.norm(hi - lo))
    return {
        "count": int(len(p)),
        "error_mm": [float(v) for v in err],
        "mean_mm": float(err.mean()),
        "max_mm": float(err.max()),
        "diameter_mm": diameter,
        "mean_percent_of_diameter": float(100.0 * err.mean() / diameter) if diameter > 0 else None,
        "identity_mean_mm": float(np.linalg.norm(p - q, axis=1).mean()),
    }


def feature_unit(fixed, moving) -> float:
    """The length (mm) in which the protocol's voxel-counted surface settings are given: the
    largest voxel spacing of the two volumes.

    Smoothing, the finest implicit width and the distance clip and blur are set in this one
    unit for both volumes, so that the same object at two resolutions gives the same features
    (the coarser grid sets the scale: finer detail is not in both).
    """
    return float(max(np.max(fixed.spacing), np.max(moving.spacing)))


def _then(first: Callable[[np.ndarray], np.ndarray], second: Callable[[np.ndarray], np.ndarray]):
    """``x -> second(first(x))``."""
    def composed(points: np.ndarray) -> np.ndarray:
        return second(np.asarray(first(points), float))
    return composed


def _inside_field_of_view(volume, points: np.ndarray, margin: float) -> np.ndarray:
    """Whether each point (N, D), mm, lies inside ``volume``'s voxel domain by at least ``margin`` mm
    (axes of a single voxel do not count)."""
    index = volume.world_to_index(points)
    keep = np.ones(len(points), dtype=bool)
    for axis, (n, step) in enumerate(zip(volume.shape, volume.spacing)):
        if n <= 1:
            continue
        m = margin / step
        keep &= (index[:, axis] >= -0.5 + m) & (index[:, axis] <= n - 0.5 - m)
    return keep


def _world_boxes(volume, labels: list[int], to_fixed=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The world (mm) bounding boxes ``(lo, hi)`` of ``labels``' voxels in ``volume`` (those it
    holds), their corners taken through ``to_fixed`` (a point map) when given."""
    if not labels:
        return []
    all_boxes = volume.label_boxes()
    out = []
    for label in labels:
        if label not in all_boxes:
            continue
        box = all_boxes[label]
        corners = np.array([[s.start - 0.5 if c == 0 else s.stop - 0.5 for s, c in zip(box, bits)]
                            for bits in np.ndindex(*([2] * len(box)))], float)
        world = volume.index_to_world(corners)
        if to_fixed is not None:
            world = to_fixed(world)
        out.append((world.min(axis=0), world.max(axis=0)))
    return out


def _field_of_view_test(fixed, moving, linear, margin: float, boxes) -> Callable[[np.ndarray], np.ndarray]:
    """Which locational-cost samples count: all but those near a cut label (within ``margin`` mm
    of one of ``boxes``, the cut labels' world boxes in fixed space) that are also within
    ``margin`` mm of the fixed image's edge or, mapped by the linear part, of the moving one's.

    Where a label is cut by the edge of an image, marching cubes closes it along the edge;
    that face is not a boundary of the object and must not pull the warp, so the samples it
    reaches carry no locational cost (:func:`~volreg.warp.fit.fit_warp` ``valid``).  Samples
    near an edge but away from cut labels keep theirs.
    """
    def valid(points: np.ndarray) -> np.ndarray:
        seen = _inside_field_of_view(fixed, points, margin) & _inside_field_of_view(moving, linear(points), margin)
        near_cut = np.zeros(len(points), dtype=bool)
        for lo, hi in boxes:
            near_cut |= np.all((points >= lo - margin) & (points <= hi + margin), axis=1)
        return seen | ~near_cut
    return valid


def _candidate_labels(fixed, moving, drive_labels: Sequence[int] | None) -> tuple[list[int], list[int]]:
    """The labels of both volumes and the candidate driving labels (``drive_labels``, checked, or all common).

    Raises
    ------
    RegistrationInputError
        Volumes of different dimensions, no label in common, an empty ``drive_labels``
        or one naming a label absent from either volume.
    """
    if fixed.ndim != moving.ndim:
        raise RegistrationInputError(f"Expected `fixed` and `moving` of the same dimension, got {fixed.ndim}-D and {moving.ndim}-D.")
    common = sorted(set(fixed.labels().tolist()) & set(moving.labels().tolist()))
    if not common:
        raise RegistrationInputError(
            f"The fixed and moving volumes have no label in common (fixed: {fixed.labels().tolist()[:20]}, "
            f"moving: {moving.labels().tolist()[:20]}); expected the same label values for the same structures."
        )
    if drive_labels is None:
        return common, common
    labels = [int(v) for v in drive_labels]
    if not labels:
        raise RegistrationInputError("Expected at least one label in `drive_labels`, got none.")
    absent = [v for v in labels if v not in common]
    if absent:
        raise RegistrationInputError(
            f"Drive label {absent[0]} is not present in both volumes (labels in both: {common[:30]})."
        )
    return common, labels


def _despeckled(fixed, moving, labels: list[int], choose: bool, settings: SurfaceSettings):
    """Both volumes without the specks of ``labels``, and (``choose``: labels chosen by default) the compact ones.

    Specks (pieces under :data:`SPECK_FRACTION` of a label) are removed before the surfaces
    are made; whether a label is speckled is judged on pieces of at least 5 %.

    Returns
    -------
    clean_fixed, clean_moving : LabelVolume
    labels : list of int
        ``labels``, without the speckled ones when ``choose``.
    skipped : list of str
        Why each speckled label does not drive by its surface.
    """
    clean_fixed, speckled_f = despeckle(fixed, labels, piece=SPECK_FRACTION, judge=0.05)
    clean_moving, speckled_m = despeckle(moving, labels, piece=SPECK_FRACTION, judge=0.05)
    skipped = []
    if choose:
        # Speckled labels (a sheet broken into many pieces by the voxel grid) give pieces in
        # one volume that have no partner in the other; their implicit surfaces then differ by
        # tens of mm near the surfaces and mislead the warp.  They are warped, not driving.
        for v in labels:
            frac = min(speckled_f[v], speckled_m[v])
            if frac < COMPACT_FRACTION:
                how = ("only its voxel distance map does" if settings.distance_weight > 0
                       else "name it in drive_labels to use it anyway")
                skipped.append(f"Label {v}'s surface does not drive the warp: only {100 * frac:.0f} % of its voxels lie in "
                               f"pieces of at least 5 % of the label (speckled); {how}.")
        labels = [v for v in labels if min(speckled_f[v], speckled_m[v]) >= COMPACT_FRACTION]
        if not labels and settings.distance_weight <= 0:
            raise RegistrationInputError(
                "Every common label is speckled (many small pieces) and the protocol's distance_weight is 0; "
                "choose drive_labels explicitly, or set distance_weight > 0 so that the labels' distance maps drive."
            )
    return clean_fixed, clean_moving, labels, skipped


def _surface_pairs(clean_fixed, clean_moving, labels: list[int], settings: SurfaceSettings, unit: float, progress):
    """The boundary meshes of ``labels`` in both volumes (in the fixed one only when ``clean_moving``
    is None); labels too small for one are noted, not fatal.

    Both are blurred by ``settings.smoothing * unit`` mm (:func:`feature_unit`), whatever their grids.
    The fixed meshes alone (no implicit surfaces: they only delimit the warp volume X) are made
    on every second voxel.

    Returns
    -------
    s_fixed, s_moving : dict of int to Surface
        ``s_moving`` is empty when ``clean_moving`` is None.
    skipped : list of str
        One note per label and volume without a surface.
    """
    from volreg.features.label_surfaces import surfaces_of_volumes, voxel_size

    volumes = (clean_fixed,) if clean_moving is None else (clean_fixed, clean_moving)
    # label_surface counts the blur in each volume's own largest spacing
    smoothing = [settings.smoothing * unit / voxel_size(volume) for volume in volumes]
    # Both volumes' meshes on the threads at once (one volume after the other, the 1 mm phantom's
    # grey shell left a thread idle for most of each: 2.3 s in all).
    # Without implicit surfaces the meshes only delimit the warp volume X (within pad, 10 % of the
    # diameter, of their vertices): marching cubes on every second voxel is enough for that.
    step = 1 if clean_moving is not None else 2
    found = surfaces_of_volumes(volumes, labels, smoothing=smoothing, step=step, progress=progress)
    skipped = []
    for name, (_, errors) in zip(("fixed", "moving"), found):
        for lab, err in errors.items():
            message = f"Skipping label {lab}: {err}"
            if settings.distance_weight > 0:
                skipped.append(f"{name} volume: {message.rstrip('.')}; its voxel distance map drives instead.")
            else:
                skipped.append(f"{name} volume: {message}")
    return found[0][0], found[1][0] if len(found) > 1 else {}, skipped


def _implicit_pairs(s_fixed, s_moving, used: list[int], settings: SurfaceSettings, unit: float, linear,
                    progress) -> list[FeaturePair]:
    """One pair of kernel implicit surfaces (paper Section 4) per label in ``used``: fixed (f1), moving (f2).

    Both with the finest width ``settings.min_width_voxels * unit`` mm (:func:`feature_unit`); the
    moving one seen through ``linear`` (:class:`~volreg.features.mapped.LinearlyMapped`) unless
    that is the identity.
    """
    from volreg.features.mapped import LinearlyMapped

    pairs = []
    w_fixed = w_moving = settings.min_width_voxels * unit
    jobs = []
    for v in used:
        # One coarsest width and one offset for both objects of a label: far from the
        # surfaces f1 and f2 then agree (f = b), instead of differing by a constant that
        # the locational cost would try to explain by moving points.
        top = max(_diameter(s_fixed[v].vertices), _diameter(s_moving[v].vertices)) / 2
        top = max(top, w_fixed, w_moving)
        jobs += [(s_fixed[v], w_fixed, top), (s_moving[v], w_moving, top)]

    def fit(job) -> ImplicitSurface:
        surface, min_width, top = job
        # Coordinate descent stops once a sweep changes the fitted values by 1e-3 of the finest
        # width on average (1/25 of the tube epsilon), not ImplicitSurface's 1e-4: the 1 mm
        # phantom's grey shell then takes 19 sweeps at its finest level instead of 47, its 99th
        # percentile residual is 0.117 mm instead of 0.102 (tube 0.1 mm), and the endpoint error of
        # the whole-command cases moved by at most 0.0012 mm (phantom 0.2335 / 0.5380 -> 0.2335 /
        # 0.5368 mm, frog 0.5424 / 0.8724 -> 0.5426 / 0.8726, parcels 0.3492 / 0.6674 -> 0.3496 /
        # 0.6669) with their implicit surfaces fitted in 20-28 % less time.
        return ImplicitSurface(surface.vertices, surface.normals, min_width=min_width, max_width=top, offset=top,
                               tol=1e-3 * min_width)

    # The fits are independent: on two threads (numba releases the GIL) the frog's took 1.3 s
    # instead of 2.3 s at 3 mm, with identical results.
    fits = thread_map(fit, jobs)
    try:
        for i, (f1, f2) in enumerate(zip(fits, fits)):
            pairs.append(FeaturePair(f1, f2 if linear.is_identity else LinearlyMapped(f2, linear),
                                     settings.implicit_weight))
            if progress is not None:
                progress("fit implicit surfaces", i + 1, len(used))
    finally:
        fits.close()  # joins the threads, also when progress raises (an interrupt)
    return pairs


class _OnCoarser(NamedTuple):
    """The finer volume's labels resampled onto the coarser volume's grid (:func:`_finer_on_coarser`)."""

    side: str  # "fixed" or "moving": the finer volume
    volume: LabelVolume  # on the coarser grid
    boxes: dict  # its label boxes


def _finer_on_coarser(fixed, moving, linear) -> _OnCoarser | None:
    """The finer volume's labels on the coarser grid, where every spacing of one grid is larger
    than every spacing of the other.

    Both volumes' distance maps then come from the same staircase: the moving labels at ``L(x)``
    for the fixed voxel centres ``x``, or the fixed labels at ``L^-1(y)`` for the moving ones ``y``
    (:func:`~volreg.warp.resample.resample_labels_at`, ``"gaussian"``: Gaussian-smoothed indicators,
    which tell best which side of a boundary a point between voxel centres lies on; ties to the
    coarser volume's label there).  ``None``
    otherwise (the same spacing, a grid finer along some axes and coarser along others, or
    spacings that interleave, such as 0.5 x 0.5 x 2 mm against 1 x 1 x 3 mm).
    """
    from volreg.evaluation.review import _counts
    from volreg.warp.field import indices_through
    from volreg.warp.resample import resample_labels_at

    if np.min(fixed.spacing) > np.max(moving.spacing) * (1 + 1e-6):
        side, fine, coarse, through = "moving", moving, fixed, linear
    elif np.min(moving.spacing) > np.max(fixed.spacing) * (1 + 1e-6):
        side, fine, coarse, through = "fixed", fixed, moving, linear.inverse()
    else:
        return None
    index = indices_through(coarse, None, fine, None if through.is_identity else through)
    # On a tie (the finer labels put a boundary through a coarse voxel centre) the coarser
    # volume's own label: the finer labels do not tell the two apart.
    labels = resample_labels_at(fine, index, method="gaussian", prefer=coarse.array.reshape(-1))
    volume = coarse.with_array(labels.reshape(coarse.shape))
    # A label one or two finer voxels thick has a blurred indicator below the background's in
    # places and is eroded or lost on the coarser grid: such a label (under 3/4 of the coarse
    # voxels its volume fills, through L; other labels keep 0.92-1.02 of them) keeps its own
    # grid's map. A sheet 1.2 mm thick at 1 mm kept 51 % on a 2 mm grid, one 1.5 mm thick 69 %.
    per_voxel = np.prod(fine.spacing) / (abs(float(np.linalg.det(through.matrix))) * np.prod(coarse.spacing))
    fine_counts, coarse_counts = _counts(fine.array), _counts(labels)
    kept = {v: box for v, box in volume.label_boxes().items()
            if coarse_counts.get(v, 0) >= 0.75 * per_voxel * fine_counts.get(v, 0)}
    return _OnCoarser(side, volume, kept)


def _distance_pairs(fixed, moving, labels: list[int], boxes_f: dict, boxes_m: dict, settings: SurfaceSettings,
                    unit: float, linear, progress, coarse: _OnCoarser | None = None) -> list[FeaturePair]:
    """One pair of voxel signed-distance maps per label (fixed, moving), weighted by ``settings.distance_weight``.

    ``boxes_f``, ``boxes_m`` are the volumes' label boxes (:meth:`LabelVolume.label_boxes`); clip and
    blur are counted in ``unit`` mm for both (:func:`feature_unit`); the moving map is seen through
    ``linear`` unless that is the identity.  With ``coarse`` (:func:`_finer_on_coarser`) the finer
    volume's map of each label is read from its labels on the coarser grid (where the label is
    left there): the fixed ones on the moving grid, seen through ``linear``; the moving ones on the
    fixed grid, already through it.
    """
    from volreg.features.mapped import LinearlyMapped

    def source(side: str, v: int) -> tuple:
        volume, boxes = (fixed, boxes_f) if side == "fixed" else (moving, boxes_m)
        if coarse is not None and coarse.side == side and v in coarse.boxes:
            # Seen through L where it lies on the moving grid (the fixed labels at L^-1 of it).
            return coarse.volume, v, coarse.boxes, side == "fixed"
        return volume, v, boxes, side == "moving"

    # The maps are independent, and their filters and loops release the GIL: made side by side
    # on the threads (one after another, the 100-label parcellation's 200 maps took 1.0 s at
    # 1.2 cores; side by side 0.7 s).
    jobs = [source(side, v) for v in labels for side in ("fixed", "moving")]
    maps = []
    for f in thread_map(lambda job: _voxel_distance(*job[:3], settings, unit), jobs):
        maps.append(f)
        if progress is not None and len(maps) % 2 == 0:
            progress("voxel distance maps", len(maps) // 2, len(labels))
    maps = [LinearlyMapped(f, linear) if job[3] and not linear.is_identity else f for f, job in zip(maps, jobs)]
    return [FeaturePair(f1, f2, settings.distance_weight) for f1, f2 in zip(maps[0::2], maps[1::2])]


def _warp_volume_points(fixed, s_fixed, used: list[int], distance_labels: list[int], boxes_f: dict) -> np.ndarray:
    """The fixed points whose padded neighbourhood is the warp volume X, (N, D) mm.

    The vertices of the driving surfaces, and the boundary voxels of the labels that
    drive only through their distance maps.
    """
    points = [s_fixed[v].vertices for v in used]
    points += [_boundary_points(fixed, v, boxes_f[v]) for v in distance_labels if v not in used]
    return np.concatenate(points)


def _boundary_points(volume, value: int, box) -> np.ndarray:
    """World points (LPS mm, (N, D)) of the voxels of label ``value`` on its boundary
    (with a face neighbour of another value), within its bounding box ``box``."""
    from scipy import ndimage

    window = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
    mask = volume.array[window] == value
    edge = mask & ~ndimage.binary_erosion(mask, border_value=0)  # never empty: the box holds the label
    return volume.index_to_world(np.argwhere(edge) + np.array([w.start for w in window]))


def _voxel_distance(volume, value: int, boxes: dict, settings, unit: float):
    """The :class:`~volreg.distance_maps.VoxelDistance` of label ``value`` of ``volume`` (its
    bounding box in ``boxes``), with the clip and blur of ``settings`` (a SurfaceSettings;
    counted in ``unit`` mm)."""
    from volreg.features.distance_maps import VoxelDistance

    clip, smoothing, scale = settings.clip_mm(unit), settings.distance_smoothing * unit, settings.distance_scale * unit
    # Only the label's box, padded beyond VoxelDistance's own crop, is compared with the value.
    pad = np.ceil((clip + 3 * smoothing + 4 * scale) / volume.spacing).astype(int) + 3
    lo = np.array([max(b.start - p, 0) for b, p in zip(boxes[value], pad)])
    window = tuple(slice(a, min(b.stop + p, n)) for a, b, p, n in zip(lo, boxes[value], pad, volume.shape))
    origin = volume.origin + volume.direction @ (volume.spacing * lo)
    return VoxelDistance(volume.array[window] == value, volume.spacing, origin, volume.direction,
                         clip=clip, smoothing=smoothing, scale=scale)


# ----------------------------------------------------------------------------- a pair of volumes


def world_box(volume) -> tuple[np.ndarray, np.ndarray]:
    """The LPS bounding box of the voxel domain of ``volume`` (voxel corners, not centres).

    Returns
    -------
    lo, hi : (D,) float ndarrays, mm
    """
    corners = np.array(list(np.ndindex(*([2] * volume.ndim))), dtype=float)
    pts = volume.index_to_world(corners * (np.array(volume.shape) - 1)[None] + (corners - 0.5))
    return pts.min(axis=0), pts.max(axis=0)


#: Peak memory of a registration, estimated before it starts: a base plus bytes per voxel of the
#: two grids. Measured peaks: the 3 mm frog demo 1.71 GB for 3.5 M voxels, a 1 mm brain-size
#: phantom 2.30 GB for 11.4 M, the frog at 1 x 1 x 1.5 mm 9.06 GB for 63.9 M (estimates 1.73,
#: 2.79 and 10.1 GB).
_BASE_GB = 1.2

_BYTES_PER_VOXEL = 150


def estimated_peak_gb(fixed, moving) -> float:
    """Rough peak memory of registering ``moving`` to ``fixed`` (:func:`write_registration`), GB."""
    voxels = int(np.prod(fixed.shape)) + int(np.prod(moving.shape))
    return _BASE_GB + _BYTES_PER_VOXEL * voxels / 1024**3


def _check_memory(fixed, moving, fixed_name, moving_name) -> None:
    """Refuse a job that would not fit in the memory available now, before it starts."""
    need = estimated_peak_gb(fixed, moving)
    available = available_bytes()
    if available is not None and need * 1024**3 > available:
        raise RegistrationInputError(
            f"Registering `{moving_name}` ({moving.shape}) to `{fixed_name}` ({fixed.shape}) would need about "
            f"{need:.1f} GB of memory and {available / 1024**3:.1f} GB is available; expected smaller grids "
            "(downsample the label volumes) or more free memory."
        )


def check_pair(fixed, moving, fixed_name: object = "fixed", moving_name: object = "moving", *,
               linear: str = "none") -> None:
    """Refuse, before any work, a pair of label volumes that cannot be registered.

    Parameters
    ----------
    fixed, moving : LabelVolume
    fixed_name, moving_name : str or path-like
        How the messages name the volumes (e.g. their files).
    linear : {"none", "rigid", "similarity", "affine"}
        The protocol's linear stage.  With one, grids far apart in world space are
        fine (the stage brings the labels together, as scans from two scanners need);
        without, they cannot be registered.

    Raises
    ------
    RegistrationInputError
        Volumes of different dimensions, grids that do not overlap in world (LPS)
        space when ``linear`` is ``"none"``, or a registration whose estimated peak
        memory (:func:`estimated_peak_gb`) exceeds the memory available now.
    """
    if fixed.ndim != moving.ndim:
        raise RegistrationInputError(
            f"`{fixed_name}` is {fixed.ndim}-D and `{moving_name}` {moving.ndim}-D; expected two volumes of one dimension."
        )
    lo1, hi1 = world_box(fixed)
    lo2, hi2 = world_box(moving)
    if linear == "none" and (np.any(hi1 < lo2) or np.any(hi2 < lo1)):
        raise RegistrationInputError(
            f"The grids of `{fixed_name}` and `{moving_name}` do not overlap in world (LPS) space "
            f"(fixed {np.round(lo1, 1).tolist()}..{np.round(hi1, 1).tolist()} mm, moving "
            f"{np.round(lo2, 1).tolist()}..{np.round(hi2, 1).tolist()} mm) and the protocol has no linear stage; "
            "check their origins and orientations, or use a linear stage ([linear] kind)."
        )
    _check_memory(fixed, moving, fixed_name, moving_name)


# ----------------------------------------------------------------------------- every output of a registration


#: The files :func:`write_registration` writes into its output folder with the default protocol.
REGISTRATION_OUTPUTS = (
    "warp.nii.gz", "inverse_warp.nii.gz", "warped.nii.gz", "model.npz", "jacobian.nii.gz", "linear.tfm", "report.json",
    "report.png", "warp.h5", "inverse_warp.h5",
)

#: The outputs left out when the protocol's ``[outputs] itk_h5`` is false.
ITK_H5_OUTPUTS = ("warp.h5", "inverse_warp.h5")


def registration_outputs(protocol: Protocol | None = None) -> tuple[str, ...]:
    """The files :func:`write_registration` writes with ``protocol`` (default: the default protocol's).

    Returns
    -------
    tuple of str
        :data:`REGISTRATION_OUTPUTS`, less :data:`ITK_H5_OUTPUTS` when ``protocol.outputs.itk_h5`` is false.
    """
    if protocol is None or protocol.outputs.itk_h5:
        return REGISTRATION_OUTPUTS
    return tuple(name for name in REGISTRATION_OUTPUTS if name not in ITK_H5_OUTPUTS)


def _peak_rss_gb() -> float:
    """Peak resident memory of this process so far, GB (Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def _stage(name: str, t0: float) -> dict:
    """A stage record: its name, seconds since ``t0`` and the peak memory so far (GB)."""
    return dict(stage=name, seconds=time.perf_counter() - t0, peak_rss_gb=round(_peak_rss_gb(), 3))


class _FixedGridFields(NamedTuple):
    """The warp sampled at the voxel centres of the fixed grid, (X, Y, Z[, 3]) arrays."""

    displacement: np.ndarray  # u(x) = tau(x) - x, mm
    jacobian: np.ndarray  # det d tau / dx
    warped: np.ndarray  # the moving labels at tau(x)


def _sample_on_fixed_grid(warp, fixed, moving, max_folded_fraction: float, progress) -> _FixedGridFields:
    """The warp's displacement and Jacobian determinant on the fixed grid, checked for folding
    (:func:`~volreg.warp.fit.check_folding`), and the moving labels resampled through it
    (label-preserving)."""
    from volreg.warp.field import fields_on_grid, indices_through
    from volreg.warp.resample import resample_labels_at

    u, jac = fields_on_grid(warp, fixed, progress=progress)
    check_folding(warp, fixed, jac, max_folded_fraction)  # before more work
    # The moving labels at tau(x), from their indices there: no world points of the grid
    index = indices_through(fixed, u, moving)
    warped = resample_labels_at(moving, index, method="label", progress=progress).reshape(fixed.shape)
    return _FixedGridFields(u, jac, warped)


#: The inverse written on the moving grid holds to this fraction of the grid's smallest spacing
#: (1 micrometre at 1 mm), checked exactly at every voxel.
INVERSE_GRID_TOL = 1e-3


def _inverse_on_moving_grid(warp, moving, progress, fixed=None, displacement=None):
    """The warp's inverse (:class:`~volreg.warp.inverse.InverseWarp`) and its displacement on the moving grid, mm.

    To :data:`INVERSE_GRID_TOL` of the moving grid's smallest spacing.  Given the warp's
    ``displacement`` on the ``fixed`` grid, each voxel starts from its interpolated inverse
    (:class:`~volreg.warp.inverse.GridStart`), which one exact evaluation of the warp checks;
    chord steps, then Newton's method, go on only where that is not within the tolerance.
    """
    from volreg.warp.field import displacement_on_grid
    from volreg.warp.inverse import GridStart, InverseWarp, _linear_of

    start = None if displacement is None else GridStart(displacement, fixed, _linear_of(warp))
    # The starts are within 1e-3 voxel at 96 % of the 1 mm phantom's voxels and 99 % of the 3 mm
    # frog's (at most 0.004 and 0.007 mm): checking them costs one evaluation of tau, where
    # polishing every voxel to 1e-6 mm took its Jacobian too and a second evaluation.
    inverse = InverseWarp(warp, start=start, tol=INVERSE_GRID_TOL * float(np.min(moving.spacing)))
    return inverse, displacement_on_grid(inverse, moving, progress=progress, stage="invert warp")


def _scores_before(fixed, moving) -> dict:
    """Dice and surface distances per label (every label of either volume) of the moving labels
    at the fixed voxel centres before any registration (nearest neighbour), against the fixed ones."""
    from volreg.evaluation.metrics import label_scores
    from volreg.warp.field import indices_through
    from volreg.warp.resample import resample_labels_at

    # On one grid, nearest neighbour at the fixed voxel centres is the moving array itself.
    before = (moving.array if moving.same_geometry(fixed) else
              resample_labels_at(moving, indices_through(fixed, None, moving), method="nearest").reshape(fixed.shape))
    labels = sorted(set(fixed.labels().tolist()) | set(moving.labels().tolist()))
    return label_scores(fixed.array, before, labels, fixed.spacing)


def _interpolated_dice_before(fixed, moving, labels) -> dict[int, float]:
    """Dice of each of ``labels`` between the fixed labels and the moving ones read at the fixed
    voxel centres as they lie (no registration) by per-label interpolation, as the warped labels
    are read (:func:`_scores_before` reads by nearest neighbour); over the label's boxes in both
    grids, beyond which neither reading holds it."""
    from volreg.warp.resample import resample_labels

    out = {}
    if not labels:
        return out
    boxes_f, boxes_m = fixed.label_boxes(), moving.label_boxes()
    shape = np.array(fixed.shape)
    for v in labels:
        if v not in boxes_f or v not in boxes_m:
            continue
        corners = np.array([[s.start - 3.5 if c == 0 else s.stop + 2.5 for s, c in zip(boxes_m[v], bits)]
                            for bits in np.ndindex(*([2] * moving.ndim))], float)
        index = fixed.world_to_index(moving.index_to_world(corners))
        lo = np.minimum(np.floor(index.min(axis=0)).astype(int), [s.start - 1 for s in boxes_f[v]])
        hi = np.maximum(np.ceil(index.max(axis=0)).astype(int) + 1, [s.stop + 1 for s in boxes_f[v]])
        region = tuple(slice(int(a), int(b)) for a, b in zip(np.maximum(lo, 0), np.minimum(hi, shape)))
        grid = np.stack(np.meshgrid(*[np.arange(r.start, r.stop) for r in region], indexing="ij"), axis=-1)
        # The moving labels near the label only (the reading passes over the whole image it is given).
        start = [max(b.start - 4, 0) for b in boxes_m[v]]
        crop = tuple(slice(a, min(b.stop + 4, n)) for a, b, n in zip(start, boxes_m[v], moving.shape))
        near = LabelVolume(moving.array[crop], moving.index_to_world(np.array([start], float))[0], moving.spacing,
                           moving.direction)
        read = resample_labels(near, fixed.index_to_world(grid.reshape(-1, fixed.ndim).astype(float)), method="label")
        a, b = fixed.array[region].reshape(-1) == v, read == v
        total = int(np.count_nonzero(a)) + int(np.count_nonzero(b))
        if total:
            out[int(v)] = 2.0 * np.count_nonzero(a & b) / total
    return out


def _registration_report(fixed, moving, result: LabelRegistration, fields: _FixedGridFields, inverse,
                         protocol: Protocol, inputs, truth, scores_before: dict) -> dict:
    """The report of a registration: Dice per label before and after, Jacobian and displacement
    figures, the inverse's residual, the fit's levels, and (given ``truth``, the true warp) the
    endpoint error; without stages and timings.  ``scores_before``: :func:`_scores_before`, computed
    in the background while the registration runs."""
    from volreg.evaluation.metrics import folded_fraction, label_scores
    from volreg.evaluation.review import (
        ReviewLimits,
        findings_summary,
        judged_labels,
        label_voxel_counts,
        review_registration,
    )
    from volreg.io.summary import package_versions

    u, jac, warped_array = fields
    in_fixed, in_moving = set(fixed.labels().tolist()), set(moving.labels().tolist())  # one pass over each
    labels = sorted(in_fixed | in_moving)
    scores_after = label_scores(fixed.array, warped_array, labels, fixed.spacing)
    inside = fixed.array != 0
    u_in = u[inside]
    linear = result.linear.map.describe() if result.linear is not None else None
    voxels, interior = label_voxel_counts(fixed.array)
    # Not judged: labels cut by an image edge, and labels absent from the moving volume (a
    # structure one subject lacks, or a field of view that misses it: nothing to align).
    shared = sorted(in_fixed & in_moving) or labels
    cut = sorted(set(result.cut_labels.get("fixed", [])) | set(result.cut_labels.get("moving", []))
                 | (in_fixed - in_moving))
    # Where a label's Dice fell by more than the review allows, "before" is read again as "after"
    # is (per-label interpolation): between grids of other resolutions the two readings of the
    # same labels differ by more than that on small labels.
    drop = ReviewLimits().max_dice_drop
    judged = judged_labels(scores_after, label_voxels=voxels, label_interior=interior, cut_labels=cut)
    fell = [v for v in judged if v in scores_before and scores_before[v]["dice"] - scores_after[v]["dice"] > drop]
    findings = review_registration(
        scores_before, scores_after, voxel_mm=feature_unit(fixed, moving), label_voxels=voxels,
        label_interior=interior, linear=linear, cut_labels=cut, folded_fraction=folded_fraction(jac, inside),
        kernel_warp=result.kernel_warp, dice_before_interpolated=_interpolated_dice_before(fixed, moving, fell))
    report = {
        "volreg_version": __version__,
        "command": "register",
        "inputs": {} if inputs is None else inputs,
        "direction": "pull-back: fixed point x corresponds to moving point x + u(x) (LPS mm)",
        "drive_labels": sorted(set(result.labels) | set(result.distance_labels)),
        "distance_map_labels": result.distance_labels,
        "implicit_surface_labels": result.labels,
        "skipped_labels": result.skipped,
        # A structure one subject lacks, a field of view that misses it, or another numbering.
        "labels_in_one_volume": {"fixed": sorted(in_fixed - in_moving), "moving": sorted(in_moving - in_fixed)},
        "labels": {
            str(v): {"before": scores_before[v], "after": scores_after[v]} for v in labels
        },
        # Over the labels both volumes hold: one that only one holds has Dice 0 whatever the
        # warp (a one-voxel speck took a good registration's mean from 0.99 to 0.66).
        "mean_dice": {
            "before": float(np.mean([scores_before[v]["dice"] for v in shared])),
            "after": float(np.mean([scores_after[v]["dice"] for v in shared])),
            "labels": shared,
        },
        "jacobian": {
            "min": float(jac.min()),
            "max": float(jac.max()),
            "folded_fraction": folded_fraction(jac),
            "folded_fraction_in_labels": folded_fraction(jac, inside),
        },
        "displacement_mm": {  # |u| by einsum: on 32 M voxels 0.6 s instead of np.linalg.norm's 1.0 s
            "max": float(np.sqrt(np.einsum("...i,...i->...", u, u).max())),
            "mean_in_labels": float(np.sqrt(np.einsum("ni,ni->n", u_in, u_in)).mean()) if inside.any() else 0.0,
        },
        "inverse": {
            "method": "start from a fixed point on the sampled forward field (else from the linear part's "
                      "inverse), checked exactly at every voxel of the moving grid; where above the "
                      "tolerance, chord steps (the linear part's matrix for the Jacobian), then Newton "
                      "iteration with the analytic Jacobian",
            "tolerance_mm": inverse.tol,
            "max_residual_mm": inverse.max_residual,
            "unconverged_voxels": inverse.unconverged,
        },
        "linear": None if linear is None else {"kind": protocol.linear.kind, **linear, "fit": result.linear.log},
        "cut_labels": result.cut_labels,
        "kernel_warp": result.kernel_warp,
        "review": findings_summary(findings, judged=judged),
        "levels": result.log,
        "protocol": protocol.to_dict(),
        "versions": package_versions(),
    }
    if truth is not None:
        gp = fixed.grid_points()[inside]
        err = np.linalg.norm(gp + u[inside] - truth(gp), axis=1)
        err0 = np.linalg.norm(truth(gp) - gp, axis=1)
        report["endpoint_error_mm"] = {
            "mean": float(err.mean()), "p95": float(np.percentile(err, 95)), "max": float(err.max()),
            "identity_mean": float(err0.mean()), "identity_p95": float(np.percentile(err0, 95)),
        }
    return report


class _OutputWrites:
    """The registration's files, each written in the background (a :class:`~volreg._threads.JobQueue`)
    as soon as its array exists, into ``folder`` (an :class:`~volreg.io._atomic.OutputFolder`),
    and recorded there once complete.

    The fields on the fixed grid, the model and the linear part are written while the inverse
    and the metrics are computed (compressing and writing release the GIL, and those stages
    leave part of the second core idle); the inverse's field once it exists; the report figure
    once the metrics give its title.
    """

    def __init__(self, jobs, folder, fixed, moving, force: bool, itk_h5: bool) -> None:
        self.jobs, self.folder, self.fixed, self.moving = jobs, folder, fixed, moving
        self.force, self.itk_h5 = force, itk_h5

    def _submit(self, *outputs: tuple[str, Callable[[Path], None]]) -> None:
        """Write the named outputs one after the other, as one background job."""
        def job() -> None:
            for name, writer in outputs:
                path = self.folder.path / name
                writer(path)
                self.folder.record(path)  # once complete: a failed run removes it
        self.jobs.submit(job)

    def fields(self, warp, fields: _FixedGridFields) -> None:
        """The fixed grid's displacement, Jacobian map and warped labels, the model and the linear part."""
        from volreg.io import write_labels, write_scalar
        from volreg.io.fields import write_displacement, write_itk_linear

        fixed, moving, force = self.fixed, self.moving, self.force
        warped = fields.warped.astype(moving.array.dtype, copy=False)
        # Largest first; the files are independent (on two threads the 1 mm phantom's outputs took
        # 4.0 s instead of 7.5 s one after the other).
        self._submit(("warp.nii.gz", lambda p: write_displacement(fields.displacement, fixed, p, force=force)))
        self._submit(("jacobian.nii.gz", lambda p: write_scalar(fields.jacobian, fixed, p, force=force)))
        self._submit(("warped.nii.gz", lambda p: write_labels(fixed.with_array(warped), p, force=force)),
                     ("model.npz", lambda p: warp.save(p, force=force)),
                     ("linear.tfm", lambda p: write_itk_linear(p, warp.linear, force=force)))

    def inverse(self, u_fixed: np.ndarray, u_inverse: np.ndarray) -> None:
        """The inverse's displacement on the moving grid (and both fields as ITK composite transforms
        when asked for); ``u_fixed`` is the forward displacement on the fixed grid."""
        from volreg.io.fields import write_displacement, write_itk_composite

        fixed, moving, force = self.fixed, self.moving, self.force
        self._submit(("inverse_warp.nii.gz", lambda p: write_displacement(u_inverse, moving, p, force=force)))
        if self.itk_h5:
            # The two HDF5 files in one job, one after the other: ITK's HDF5 library may not be thread-safe.
            self._submit(("warp.h5", lambda p: write_itk_composite(u_fixed, fixed, p, force=force)),
                         ("inverse_warp.h5", lambda p: write_itk_composite(u_inverse, moving, p, force=force)))

    def figure(self, fields: _FixedGridFields, report: dict) -> None:
        """The report figure, titled with the report's mean Dice before and after."""
        from volreg.io.report_figure import write_report_figure

        fixed, moving = self.fixed, self.moving
        title = (f"volreg register: mean Dice {report['mean_dice']['before']:.3f} -> "
                 f"{report['mean_dice']['after']:.3f}")
        # The displacement in LPS mm, turned into the fixed grid's voxels on the drawn slices only
        self._submit(("report.png", lambda p: write_report_figure(
            p, fixed.array, moving.array, fields.warped, fields.displacement, fixed_spacing=fixed.spacing,
            moving_spacing=moving.spacing, force=self.force, title=title, to_voxels=fixed.direction / fixed.spacing)))


def _register_and_write(fixed, moving, outdir, *, protocol, drive_labels, landmarks, force, inputs, truth, prior,
                        progress, on_fit) -> tuple[LabelRegistration, dict]:
    """:func:`write_registration`, also returning the registration itself."""
    from volreg.io import write_json
    from volreg.io._atomic import output_folder
    from volreg.io.protocol import load_protocol
    from volreg.io.summary import json_safe

    protocol = load_protocol("default") if protocol is None else protocol
    with output_folder(outdir, force) as folder, JobQueue() as jobs:  # the jobs end before the folder closes
        folder.check_writable(registration_outputs(protocol), force=force)
        t_all = time.perf_counter()
        # The scores before registration need only the inputs: computed in the background while
        # the linear stage and the fit leave a core partly idle, not in the metrics stage.
        before = jobs.submit(_scores_before, fixed, moving)
        result = register_labels(fixed, moving, drive_labels=drive_labels, landmarks=landmarks,
                                 protocol=protocol, prior=prior, progress=progress)
        stages = [dict(st, peak_rss_gb=round(_peak_rss_gb(), 3)) for st in result.stages]
        if on_fit is not None:
            on_fit(result)

        t0 = time.perf_counter()
        fields = _sample_on_fixed_grid(result.warp, fixed, moving, protocol.warp.max_folded_fraction, progress)
        stages.append(_stage("resample", t0))
        # From here on the outputs are written in the background as their arrays come; the
        # inverse and metrics stages below share the cores with those writes, and the write
        # stage is what is left of them at the end.
        writes = _OutputWrites(jobs, folder, fixed, moving, force, protocol.outputs.itk_h5)
        writes.fields(result.warp, fields)

        t0 = time.perf_counter()
        inverse, u_inverse = _inverse_on_moving_grid(result.warp, moving, progress, fixed, fields.displacement)
        writes.inverse(fields.displacement, u_inverse)
        stages.append(_stage("inverse", t0))

        t0 = time.perf_counter()
        report = _registration_report(fixed, moving, result, fields, inverse, protocol, inputs, truth,
                                      scores_before=before.result())
        if landmarks is not None:
            report["landmarks"] = landmark_errors(result.warp, landmarks, fixed)
        writes.figure(fields, report)
        stages.append(_stage("metrics", t0))

        t0 = time.perf_counter()
        jobs.wait()
        stages.append(_stage("write", t0))
        report["stages"] = stages
        report["seconds"] = time.perf_counter() - t_all
        report["peak_rss_gb"] = round(_peak_rss_gb(), 3)
        report = json_safe(report)
        write_json(report, folder.path / "report.json", force=force)
        folder.record(folder.path / "report.json")
    return result, report


def write_registration(
    fixed,
    moving,
    outdir: str | os.PathLike[str],
    *,
    protocol: Protocol | None = None,
    drive_labels: Sequence[int] | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    force: bool = False,
    inputs: Mapping | None = None,
    truth: Callable[[np.ndarray], np.ndarray] | None = None,
    prior: Callable[[np.ndarray], np.ndarray] | None = None,
    progress: ProgressCallback | None = None,
    on_fit: Callable[[LabelRegistration], None] | None = None,
) -> dict:
    """Register ``moving`` to ``fixed`` (:func:`register_labels`) and write every output into ``outdir``.

    The outputs (:func:`registration_outputs`): ``warp.nii.gz`` (the displacement
    u(x) = tau(x) - x on the fixed grid, LPS mm, as ANTs/ITK read it),
    ``inverse_warp.nii.gz`` (the inverse's displacement on the moving grid),
    ``warp.h5`` and ``inverse_warp.h5`` (the same two fields as ITK composite
    transforms, unless the protocol's ``outputs.itk_h5`` is false),
    ``warped.nii.gz`` (the moving labels on the fixed grid), ``model.npz`` (the
    warp, paper eq. 9 with its linear part), ``linear.tfm`` (the linear part alone,
    an ITK transform), ``jacobian.nii.gz`` (det d tau / dx on the fixed grid),
    ``report.png`` and ``report.json`` (the report returned).

    Parameters
    ----------
    fixed, moving : LabelVolume
    outdir : path-like
        The output folder; created with missing parents.  A warp folding more than
        ``protocol.warp.max_folded_fraction`` of the fixed grid is refused before
        anything is written.
    protocol : Protocol, optional
        Default :func:`volreg.io.protocol.load_protocol` ``("default")``.
    drive_labels, landmarks, prior
        As :func:`register_labels`.
    force : bool, default False
        Write into a non-empty ``outdir``, replacing outputs.
    inputs : dict, optional
        What the report records as the inputs (e.g. paths and checksums).
    truth : callable, optional
        The true warp, ``truth(points (N, D) mm) -> (N, D) mm``: the report then gives the
        endpoint error ``|tau(x) - truth(x)|`` over the fixed labels' voxels, mm.
    progress : callable, optional
        ``progress(stage, done, total)``.
    on_fit : callable, optional
        Called with the :class:`LabelRegistration` once the warp is fitted, before the
        outputs are computed (e.g. to log its stages and levels).

    Returns
    -------
    dict
        The report, as written to ``report.json`` (NaN as ``None``): Dice per label before
        and after, the Jacobian determinant's range and folded fractions, displacement
        figures in mm, the inverse's residual, the fit's ``levels`` and ``stages`` (seconds
        and peak memory, GB), ``seconds`` and ``peak_rss_gb``.

    Raises
    ------
    VolregError
        Inputs that cannot be registered, a non-empty ``outdir`` without ``force``, an output
        that cannot be written, a warp that diverges or folds.  On any error (and on an
        interrupt) the files written so far and the folders created are removed.
    """
    return _register_and_write(fixed, moving, outdir, protocol=protocol, drive_labels=drive_labels,
                               landmarks=landmarks, force=force, inputs=inputs, truth=truth, prior=prior,
                               progress=progress, on_fit=on_fit)[1]


# ----------------------------------------------------------------------------- both ways


@dataclass
class TwoWayRegistration:
    """Registrations of A to B and of B to A.

    Attributes
    ----------
    forward : LabelRegistration
        ``forward.warp`` maps A points to their B partners (the pull-back of registering B to A's grid).
    backward : LabelRegistration
        ``backward.warp`` maps B points to their A partners.
    reports : dict of str to dict
        ``{"forward": report, "backward": report}`` of :func:`write_registration` when the
        registrations were written; empty otherwise.
    """

    forward: LabelRegistration
    backward: LabelRegistration
    reports: dict = field(default_factory=dict)


def register_both_ways(
    a,
    b,
    *,
    protocol: Protocol | None = None,
    drive_labels: Sequence[int] | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    outdir: str | os.PathLike[str] | None = None,
    force: bool = False,
    inputs: Mapping | None = None,
    progress: ProgressCallback | None = None,
    on_fit: Callable[[LabelRegistration], None] | None = None,
) -> TwoWayRegistration:
    """Register A to B, then B to A, as the consistency test (paper Section 5) needs.

    With the protocol's ``warp.lambda_consistency`` > 0 (the symmetric option) the
    backward fit is pulled towards the inverse of the forward warp
    (:class:`~volreg.warp.inverse.InverseWarp`, the ``prior`` of :func:`register_labels`);
    otherwise the two registrations are independent.

    Parameters
    ----------
    a, b : LabelVolume
    protocol : Protocol, optional
        For both registrations; default :func:`volreg.io.protocol.load_protocol` ``("default")``.
    drive_labels : sequence of int, optional
        As :func:`register_labels`, for both.
    landmarks : pair of (L, D) float ndarrays, optional
        A's points and their B partners, LPS mm (swapped for the backward registration).
    outdir : path-like, optional
        Write each registration's outputs (:func:`write_registration`) into
        ``outdir/forward`` and ``outdir/backward``; default: write nothing.
    force : bool, default False
        With ``outdir``: write into non-empty folders, replacing outputs.
    inputs : dict, optional
        With ``outdir``: ``{"A": ..., "B": ...}``, what the reports record as A and B.
    progress, on_fit : callable, optional
        As :func:`write_registration` (``on_fit`` is called for each direction).

    Returns
    -------
    TwoWayRegistration
    """
    from volreg.io.protocol import load_protocol
    from volreg.warp.inverse import InverseWarp

    protocol = load_protocol("default") if protocol is None else protocol
    reverse = None if landmarks is None else (landmarks[1], landmarks[0])
    reports = {}

    def register(name, fixed, moving, fixed_key, moving_key, points, prior) -> LabelRegistration:
        if outdir is None:
            result = register_labels(fixed, moving, protocol=protocol, drive_labels=drive_labels, landmarks=points,
                                     prior=prior, progress=progress)
            if on_fit is not None:
                on_fit(result)
            return result
        records = None if inputs is None else {"fixed": inputs[fixed_key], "moving": inputs[moving_key]}
        result, reports[name] = _register_and_write(
            fixed, moving, Path(outdir) / name, protocol=protocol, drive_labels=drive_labels, landmarks=points,
            force=force, inputs=records, truth=None, prior=prior, progress=progress, on_fit=on_fit,
        )
        return result

    forward = register("forward", a, b, "A", "B", landmarks, None)
    # the symmetric option: the backward fit is pulled towards the forward warp's inverse
    prior = InverseWarp(forward.warp) if protocol.warp.lambda_consistency > 0 else None
    backward = register("backward", b, a, "B", "A", reverse, prior)
    return TwoWayRegistration(forward, backward, reports)

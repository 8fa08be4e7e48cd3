"""Registration as users call it: label volumes or surfaces in, a fitted kernel warp out.

:func:`register_labels` (the main job) turns two label volumes into feature pairs --
one kernel implicit surface per driving label and side (paper Section 4, eq. 6), plus
voxel signed-distance maps (not in the paper) -- and fits the warp with
:func:`volreg.warp.fit.fit_warp`.  :func:`register_surfaces` does the same for meshes
or point clouds with normals.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, Sequence
import numpy as np
from volreg._threads import single_blas, thread_map
from volreg.features.implicit import ImplicitSurface
from volreg.warp.objective import FeaturePair
from volreg.errors import RegistrationInputError
from volreg.settings import WarpSettings
from volreg.warp.fit import RegistrationResult, fit_warp

__all__ = ["LabelRegistration", "despeckle", "register_labels", "register_surfaces"]


def _as_implicit(surface, **kwargs) -> tuple[ImplicitSurface, np.ndarray]:
    """An ImplicitSurface and its points from a pyvista mesh, an ImplicitSurface, or (points, normals)."""
    if isinstance(surface, ImplicitSurface):
        return surface, surface.points
    if isinstance(surface, tuple):
        pts, normals = (np.asarray(a, float) for a in surface)
        return ImplicitSurface(pts, normals, **kwargs), pts
    try:
        import pyvista as pv
    except ImportError:  # pragma: no cover - pyvista is a dependency
        pv = None
    if pv is not None and isinstance(surface, pv.PolyData):
        mesh = surface.triangulate().compute_normals(point_normals=True, cell_normals=False,
                                                     auto_orient_normals=True, consistent_normals=True)
        pts = np.asarray(mesh.points, float)
        return ImplicitSurface(pts, np.asarray(mesh.point_data["Normals"], float), **kwargs), pts
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
) -> RegistrationResult:
    """Register ``source`` onto ``target``: ``result.warp`` maps source points to target points.

    Parameters
    ----------
    source, target : pyvista.PolyData, ImplicitSurface, (points, normals), or lists of them
        One object or several (one per label: several feature functions, (6)),
        in the same order for both.
    landmarks : pair of (L, D) float ndarrays, optional
        Source landmark points and their target positions, mm.
    settings : WarpSettings
    progress : callable, optional

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
    pairs, points = [], []
    for s, t in zip(sources, targets):
        f1, p1 = _as_implicit(s)
        f2, _ = _as_implicit(t)
        pairs.append(FeaturePair(f1, f2))
        points.append(p1)
    return fit_warp(pairs, np.concatenate(points), landmarks=landmarks, settings=settings, progress=progress)


def _diameter(points: np.ndarray) -> float:
    """Diagonal of the bounding box of ``points``, mm."""
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


#: A label drives the warp by default when at least this fraction of its voxels lies in
#: pieces holding >= 5 % of the label each (in both volumes).  On the frog demo (3 mm), with
#: the robust distance term, its labels at 0.87 (13), 0.73 (12) and 0.54 (1) gave endpoint
#: errors of 0.70 mm driving 13 and 0.75 driving all three (``fast`` with a 24 mm finest width
#: and 48 mm sample spacing), and 0.96 driving 13 against 1.28 driving none (``fast`` as
#: shipped); with the squared cost (3), driving 13 had made it worse.
COMPACT_FRACTION = 0.8


#: Pieces of a driving label smaller than this fraction of its voxels are removed before its
#: surface is made.  Measured on the frog at 3 mm (2026-12-02): 0.05 -> endpoint error
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
        The labels whose surfaces drove the warp.
    skipped : list of str
        Labels left out (too small in one of the volumes), with the reason.
    distance_labels : list of int
        The labels whose voxel signed-distance maps drove the warp (protocol
        ``surface.distance_weight`` > 0).
    stages : list of dict
        Per stage: ``{"stage", "seconds"}``.
    """

    labels: list = field(default_factory=list)
    skipped: list = field(default_factory=list)
    stages: list = field(default_factory=list)
    distance_labels: list = field(default_factory=list)


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

    Each driving label gives one feature pair (paper (6)): the kernel implicit
    surface (Section 4) of its boundary in the fixed volume (``f1``, O1) and in
    the moving volume (``f2``, O2).  With the protocol's
    ``surface.distance_weight`` > 0 (the presets) every label present in both
    volumes (or every drive label) also gives a pair of voxel signed-distance
    maps (:class:`~volreg.distance_maps.VoxelDistance`, not in the paper), so that
    labels too small or too fragmented for a surface drive the warp as well
    (frog demo at 3 mm: endpoint error 0.52 / 1.18 -> 0.51 / 0.84 mm, mean / p95;
    at 1 x 1 x 1.5 mm 0.29 / 1.08 -> 0.21 / 0.40).  The warp is fitted in the
    padded neighbourhood of the fixed surfaces (:func:`fit_warp`).

    Parameters
    ----------
    fixed, moving : LabelVolume
    drive_labels : sequence of int, optional
        Labels whose surfaces (and distance maps) drive the warp; default every label present in
        both volumes except speckled ones (less than :data:`COMPACT_FRACTION` of
        the voxels in pieces of at least 5 % of the label, see :func:`despeckle`).
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
        the protocol's ``distance_weight`` 0, no label with a surface in both
        volumes (with distance maps every common label drives, surface or not).
    """
    from volreg.io.protocol import load_protocol
    from volreg.features.label_surfaces import label_surfaces, voxel_size

    protocol = load_protocol("default") if protocol is None else protocol
    if fixed.ndim != moving.ndim:
        raise RegistrationInputError(f"Expected `fixed` and `moving` of the same dimension, got {fixed.ndim}-D and {moving.ndim}-D.")
    common = sorted(set(fixed.labels().tolist()) & set(moving.labels().tolist()))
    if not common:
        raise RegistrationInputError(
            f"The fixed and moving volumes have no label in common (fixed: {fixed.labels().tolist()[:20]}, "
            f"moving: {moving.labels().tolist()[:20]}); expected the same label values for the same structures."
        )
    if drive_labels is None:
        labels = common
    else:
        labels = [int(v) for v in drive_labels]
        if not labels:
            raise RegistrationInputError("Expected at least one label in `drive_labels`, got none.")
        absent = [v for v in labels if v not in common]
        if absent:
            raise RegistrationInputError(
                f"Drive label {absent[0]} is not present in both volumes (labels in both: {common[:30]})."
            )
    stages = []
    t0 = time.perf_counter()
    skipped = []
    # Specks (pieces under SPECK_FRACTION of a label) are removed before the surfaces are
    # made; whether a label is speckled is judged on pieces of at least 5 %.
    clean_fixed, speckled_f = despeckle(fixed, labels, piece=SPECK_FRACTION, judge=0.05)
    clean_moving, speckled_m = despeckle(moving, labels, piece=SPECK_FRACTION, judge=0.05)
    if drive_labels is None:
        # Speckled labels (a sheet broken into many pieces by the voxel grid) give pieces in
        # one volume that have no partner in the other; their implicit surfaces then differ by
        # tens of mm near the surfaces and mislead the warp.  They are warped, not driving.
        for v in labels:
            frac = min(speckled_f[v], speckled_m[v])
            if frac < COMPACT_FRACTION:
                how = ("only its voxel distance map does" if protocol.surface.distance_weight > 0
                       else "name it in drive_labels to use it anyway")
                skipped.append(f"Label {v}'s surface does not drive the warp: only {100 * frac:.0f} % of its voxels lie in "
                               f"pieces of at least 5 % of the label (speckled); {how}.")
        labels = [v for v in labels if min(speckled_f[v], speckled_m[v]) >= COMPACT_FRACTION]
        if not labels and protocol.surface.distance_weight <= 0:
            raise RegistrationInputError(
                "Every common label is speckled (many small pieces) and the protocol's distance_weight is 0; "
                "choose drive_labels explicitly, or set distance_weight > 0 so that the labels' distance maps drive."
            )
    surfaces = {}
    for name, volume in (("fixed", clean_fixed), ("moving", clean_moving)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            surfaces[name] = label_surfaces(volume, labels, on_small="warn", smoothing=protocol.surface.smoothing,
                                            progress=progress)
        if protocol.surface.distance_weight > 0:
            skipped += [f"{name} volume: {str(w.message).rstrip('.')}; its voxel distance map drives instead." for w in caught]
        else:
            skipped += [f"{name} volume: {w.message}" for w in caught]
    s_fixed, s_moving = surfaces["fixed"], surfaces["moving"]
    used = [v for v in labels if v in s_fixed and v in s_moving]
    if not used and protocol.surface.distance_weight <= 0:
        # With distance maps (distance_weight > 0) every label drives, with a surface or not.
        raise RegistrationInputError(
            f"No label of {labels[:30]} gives a surface in both volumes and the protocol's distance_weight is 0; "
            "nothing drives the warp (set distance_weight > 0 to drive by the labels' voxel distance maps)."
        )
    stages.append(dict(stage="surfaces", seconds=time.perf_counter() - t0))

    t0 = time.perf_counter()
    pairs = []
    w_fixed = protocol.surface.min_width_voxels * voxel_size(fixed)
    w_moving = protocol.surface.min_width_voxels * voxel_size(moving)
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
        return ImplicitSurface(surface.vertices, surface.normals, min_width=min_width, max_width=top, offset=top)

    # The fits are independent: on two threads (numba releases the GIL) the frog's took 1.3 s
    # instead of 2.3 s at 3 mm, with identical results.
    fits = thread_map(fit, jobs)
    try:
        for i, (f1, f2) in enumerate(zip(fits, fits)):
            pairs.append(FeaturePair(f1, f2))
            if progress is not None:
                progress("fit implicit surfaces", i + 1, len(used))
    finally:
        fits.close()  # joins the threads, also when progress raises (an interrupt)
    stages.append(dict(stage="implicit surfaces", seconds=time.perf_counter() - t0))

    weight = protocol.surface.distance_weight
    distance_labels = []
    if weight > 0:
        # Voxel signed-distance features: every label in both volumes (or the chosen
        # drive labels), also those too small or too fragmented for a surface.
        t0 = time.perf_counter()
        distance_labels = common if drive_labels is None else labels
        boxes_f, boxes_m = fixed.label_boxes(), moving.label_boxes()
        for i, v in enumerate(distance_labels):
            pairs.append(FeaturePair(_voxel_distance(fixed, v, boxes_f, protocol.surface),
                                     _voxel_distance(moving, v, boxes_m, protocol.surface), weight))
            if progress is not None:
                progress("voxel distance maps", i + 1, len(distance_labels))
        stages.append(dict(stage="voxel distance maps", seconds=time.perf_counter() - t0))

    t0 = time.perf_counter()
    points = [s_fixed[v].vertices for v in used]
    # Labels that drive only through their distance maps: their boundary voxels join the
    # points whose padded neighbourhood is the warp volume X.
    points += [_boundary_points(fixed, v, boxes_f[v]) for v in distance_labels if v not in used]
    points = np.concatenate(points)
    result = fit_warp(pairs, points, landmarks=landmarks, settings=protocol.warp, prior=prior, progress=progress)
    stages.append(dict(stage="fit warp", seconds=time.perf_counter() - t0))
    return LabelRegistration(result.warp, result.log, labels=used, skipped=skipped, stages=stages,
                             distance_labels=[int(v) for v in distance_labels])


def _boundary_points(volume, value: int, box) -> np.ndarray:
    """World points (LPS mm, (N, D)) of the voxels of label ``value`` on its boundary
    (with a face neighbour of another value), within its bounding box ``box``."""
    from scipy import ndimage

    window = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
    mask = volume.array[window] == value
    edge = mask & ~ndimage.binary_erosion(mask, border_value=0)  # never empty: the box holds the label
    return volume.index_to_world(np.argwhere(edge) + np.array([w.start for w in window]))


def _voxel_distance(volume, value: int, boxes: dict, settings):
    """The :class:`~volreg.distance_maps.VoxelDistance` of label ``value`` of ``volume`` (its
    bounding box in ``boxes``), with the clip and blur of ``settings`` (a SurfaceSettings;
    voxels of the largest spacing)."""
    from volreg.features.distance_maps import VoxelDistance

    unit = float(np.max(volume.spacing))
    clip, smoothing = settings.distance_clip * unit, settings.distance_smoothing * unit
    # Only the label's box, padded beyond VoxelDistance's own crop, is compared with the value.
    pad = np.ceil((clip + 3 * smoothing) / volume.spacing).astype(int) + 3
    lo = np.array([max(b.start - p, 0) for b, p in zip(boxes[value], pad)])
    window = tuple(slice(a, min(b.stop + p, n)) for a, b, p, n in zip(lo, boxes[value], pad, volume.shape))
    origin = volume.origin + volume.direction @ (volume.spacing * lo)
    return VoxelDistance(volume.array[window] == value, volume.spacing, origin, volume.direction,
                         clip=clip, smoothing=smoothing)

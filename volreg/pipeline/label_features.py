"""Label features: each driving label of a pair of volumes becomes feature pairs of the locational cost.

A label present in both volumes gives, per side, the signed distance function of its
boundary (paper (3)-(6)): the label's voxel signed distance, read through a Gaussian
(:class:`~volreg.features.distance_maps.VoxelDistance`, not in the paper), and, where the
protocol asks for them (``surface.implicit_weight`` > 0), the kernel implicit surface of its
marching-cubes mesh (Section 4, :class:`~volreg.features.implicit.ImplicitSurface`).  The
moving side is seen through the linear part (``tau = L o phi``).  :func:`label_features` runs
the stage and returns a :class:`LabelFeatures`; its parts are the functions below.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Sequence

import numpy as np
from scipy import ndimage

from volreg._threads import thread_map
from volreg.errors import RegistrationInputError
from volreg.features.distance_maps import VoxelDistance
from volreg.features.implicit import ImplicitSurface
from volreg.features.label_surfaces import surfaces_of_volumes, voxel_size
from volreg.features.mapped import LinearlyMapped
from volreg.grid import LabelVolume, box_diameter, inside_field_of_view, label_counts
from volreg.settings import Protocol, SurfaceSettings
from volreg.warp.field import indices_through
from volreg.linear_map import LinearMap
from volreg.warp.objective import FeaturePair
from volreg.warp.resample import resample_labels_at

__all__ = [
    "COMPACT_FRACTION", "SPECK_FRACTION", "DrivingLabels", "LabelFeatures", "candidate_labels", "despeckle",
    "feature_unit", "field_of_view_test", "label_features",
]

ProgressCallback = Callable[[str, int, int], None]


#: A label's surface drives the warp by default when at least this fraction of its voxels lies in
#: pieces holding >= 5 % of the label each (in both volumes): a speckled label's pieces have no
#: partners in the other volume and mislead the warp.
COMPACT_FRACTION = 0.8


#: Pieces of a driving label smaller than this fraction of its voxels are removed before its
#: surface is made (small enough that thin, many-piece structures such as bones still drive).
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



def feature_unit(fixed, moving) -> float:
    """The length (mm) in which the protocol's voxel-counted surface settings are given: the
    largest voxel spacing of the two volumes.

    Smoothing, the finest implicit width and the distance clip and blur are set in this one
    unit for both volumes, so that the same object at two resolutions gives the same features
    (the coarser grid sets the scale: finer detail is not in both).
    """
    return float(max(np.max(fixed.spacing), np.max(moving.spacing)))



def field_of_view_test(fixed, moving, linear, margin: float, boxes) -> Callable[[np.ndarray], np.ndarray]:
    """Which locational-cost samples count: all but those near a cut label (within ``margin`` mm
    of one of ``boxes``, the cut labels' world boxes in fixed space) that are also within
    ``margin`` mm of the fixed image's edge or, mapped by the linear part, of the moving one's.

    Where a label is cut by the edge of an image, marching cubes closes it along the edge;
    that face is not a boundary of the object and must not pull the warp, so the samples it
    reaches carry no locational cost (:func:`~volreg.warp.fit.fit_warp` ``valid``).  Samples
    near an edge but away from cut labels keep theirs.
    """
    def valid(points: np.ndarray) -> np.ndarray:
        seen = inside_field_of_view(fixed, points, margin) & inside_field_of_view(moving, linear(points), margin)
        near_cut = np.zeros(len(points), dtype=bool)
        for lo, hi in boxes:
            near_cut |= np.all((points >= lo - margin) & (points <= hi + margin), axis=1)
        return seen | ~near_cut
    return valid



def candidate_labels(fixed, moving, drive_labels: Sequence[int] | None) -> DrivingLabels:
    """The labels of both volumes and the candidate driving labels (``drive_labels``, checked, or all common).

    Returns
    -------
    DrivingLabels

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
        return DrivingLabels(common, common, True)
    labels = [int(v) for v in drive_labels]
    if not labels:
        raise RegistrationInputError("Expected at least one label in `drive_labels`, got none.")
    absent = [v for v in labels if v not in common]
    if absent:
        raise RegistrationInputError(
            f"Drive label {absent[0]} is not present in both volumes (labels in both: {common[:30]})."
        )
    return DrivingLabels(common, labels, False)


def despeckled(fixed, moving, labels: list[int], choose: bool, settings: SurfaceSettings):
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


def surface_pairs(clean_fixed, clean_moving, labels: list[int], settings: SurfaceSettings, unit: float, progress):
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

    volumes = (clean_fixed,) if clean_moving is None else (clean_fixed, clean_moving)
    # label_surface counts the blur in each volume's own largest spacing
    smoothing = [settings.smoothing * unit / voxel_size(volume) for volume in volumes]
    # Both volumes' meshes on the threads at once: one volume after the other leaves a thread idle.
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


def implicit_pairs(s_fixed, s_moving, used: list[int], settings: SurfaceSettings, unit: float, linear,
                    progress) -> list[FeaturePair]:
    """One pair of kernel implicit surfaces (paper Section 4) per label in ``used``: fixed (f1), moving (f2).

    Both with the finest width ``settings.min_width_voxels * unit`` mm (:func:`feature_unit`); the
    moving one seen through ``linear`` (:class:`~volreg.features.mapped.LinearlyMapped`) unless
    that is the identity.
    """

    pairs = []
    w_fixed = w_moving = settings.min_width_voxels * unit
    jobs = []
    for v in used:
        # One coarsest width and one offset for both objects of a label: far from the
        # surfaces f1 and f2 then agree (f = b), instead of differing by a constant that
        # the locational cost would try to explain by moving points.
        top = max(box_diameter(s_fixed[v].vertices), box_diameter(s_moving[v].vertices)) / 2
        top = max(top, w_fixed, w_moving)
        jobs += [(s_fixed[v], w_fixed, top), (s_moving[v], w_moving, top)]

    def fit(job) -> ImplicitSurface:
        surface, min_width, top = job
        # Coordinate descent stops once a sweep changes the fitted values by 1e-3 of the finest
        # width on average (1/25 of the tube epsilon), not ImplicitSurface's 1e-4: far fewer
        # sweeps at the finest level, for residuals still within the tube and the same warp to
        # about a micrometre.
        return ImplicitSurface(surface.vertices, surface.normals, min_width=min_width, max_width=top, offset=top,
                               tol=1e-3 * min_width)

    # The fits are independent and numba releases the GIL: on the threads, with identical results.
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


class OnCoarser(NamedTuple):
    """The finer volume's labels resampled onto the coarser volume's grid (:func:`finer_on_coarser`)."""

    side: str  # "fixed" or "moving": the finer volume
    volume: LabelVolume  # on the coarser grid
    boxes: dict  # its label boxes


def finer_on_coarser(fixed, moving, linear) -> OnCoarser | None:
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
    # voxels its volume fills, through L; other labels keep about all of them) keeps its own
    # grid's map.
    per_voxel = np.prod(fine.spacing) / (abs(float(np.linalg.det(through.matrix))) * np.prod(coarse.spacing))
    fine_counts, coarse_counts = label_counts(fine.array), label_counts(labels)
    kept = {v: box for v, box in volume.label_boxes().items()
            if coarse_counts.get(v, 0) >= 0.75 * per_voxel * fine_counts.get(v, 0)}
    return OnCoarser(side, volume, kept)


def distance_pairs(fixed, moving, labels: list[int], boxes_f: dict, boxes_m: dict, settings: SurfaceSettings,
                    unit: float, linear, progress, coarse: OnCoarser | None = None) -> list[FeaturePair]:
    """One pair of voxel signed-distance maps per label (fixed, moving), weighted by ``settings.distance_weight``.

    ``boxes_f``, ``boxes_m`` are the volumes' label boxes (:meth:`LabelVolume.label_boxes`); clip and
    blur are counted in ``unit`` mm for both (:func:`feature_unit`); the moving map is seen through
    ``linear`` unless that is the identity.  With ``coarse`` (:func:`finer_on_coarser`) the finer
    volume's map of each label is read from its labels on the coarser grid (where the label is
    left there): the fixed ones on the moving grid, seen through ``linear``; the moving ones on the
    fixed grid, already through it.
    """

    def source(side: str, v: int) -> tuple:
        volume, boxes = (fixed, boxes_f) if side == "fixed" else (moving, boxes_m)
        if coarse is not None and coarse.side == side and v in coarse.boxes:
            # Seen through L where it lies on the moving grid (the fixed labels at L^-1 of it).
            return coarse.volume, v, coarse.boxes, side == "fixed"
        return volume, v, boxes, side == "moving"

    # The maps are independent, and their filters and loops release the GIL: made side by side
    # on the threads.
    jobs = [source(side, v) for v in labels for side in ("fixed", "moving")]
    maps = []
    for f in thread_map(lambda job: voxel_distance(*job[:3], settings, unit), jobs):
        maps.append(f)
        if progress is not None and len(maps) % 2 == 0:
            progress("voxel distance maps", len(maps) // 2, len(labels))
    maps = [LinearlyMapped(f, linear) if job[3] and not linear.is_identity else f for f, job in zip(maps, jobs)]
    return [FeaturePair(f1, f2, settings.distance_weight) for f1, f2 in zip(maps[0::2], maps[1::2])]


def warp_volume_points(fixed, s_fixed, used: list[int], distance_labels: list[int], boxes_f: dict) -> np.ndarray:
    """The fixed points whose padded neighbourhood is the warp volume X, (N, D) mm.

    The vertices of the driving surfaces, and the boundary voxels of the labels that
    drive only through their distance maps.
    """
    points = [s_fixed[v].vertices for v in used]
    points += [boundary_points(fixed, v, boxes_f[v]) for v in distance_labels if v not in used]
    return np.concatenate(points)


def boundary_points(volume, value: int, box) -> np.ndarray:
    """World points (LPS mm, (N, D)) of the voxels of label ``value`` on its boundary
    (with a face neighbour of another value), within its bounding box ``box``."""

    window = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
    mask = volume.array[window] == value
    edge = mask & ~ndimage.binary_erosion(mask, border_value=0)  # never empty: the box holds the label
    return volume.index_to_world(np.argwhere(edge) + np.array([w.start for w in window]))


def voxel_distance(volume, value: int, boxes: dict, settings, unit: float):
    """The :class:`~volreg.distance_maps.VoxelDistance` of label ``value`` of ``volume`` (its
    bounding box in ``boxes``), with the clip and blur of ``settings`` (a SurfaceSettings;
    counted in ``unit`` mm)."""

    clip, smoothing, scale = settings.clip_mm(unit), settings.distance_smoothing * unit, settings.distance_scale * unit
    # Only the label's box, padded beyond VoxelDistance's own crop, is compared with the value.
    pad = np.ceil((clip + 3 * smoothing + 4 * scale) / volume.spacing).astype(int) + 3
    lo = np.array([max(b.start - p, 0) for b, p in zip(boxes[value], pad)])
    window = tuple(slice(a, min(b.stop + p, n)) for a, b, p, n in zip(lo, boxes[value], pad, volume.shape))
    origin = volume.origin + volume.direction @ (volume.spacing * lo)
    return VoxelDistance(volume.array[window] == value, volume.spacing, origin, volume.direction,
                         clip=clip, smoothing=smoothing, scale=scale)


@dataclass(frozen=True)
class DrivingLabels:
    """The labels a registration may be driven by (:func:`candidate_labels`).

    Attributes
    ----------
    common : list of int
        Every non-zero label present in both volumes.
    labels : list of int
        The candidate driving labels: ``drive_labels`` as given (checked), or ``common``.
    by_default : bool
        Whether ``labels`` were chosen by default (then speckled labels' surfaces are left out).
    """

    common: list[int]
    labels: list[int]
    by_default: bool


@dataclass
class LabelFeatures:
    """The feature stage of a label registration (:func:`label_features`).

    Attributes
    ----------
    pairs : list of FeaturePair
        The locational cost's feature pairs (paper (6)): implicit surfaces first, then voxel
        distance maps; the moving side seen through the linear part.
    points : (N, D) float ndarray, mm
        The fixed points whose padded neighbourhood is the warp volume X.
    labels : list of int
        The candidate driving labels, less the speckled ones when chosen by default.
    implicit_labels : list of int
        The labels whose implicit surfaces drive (a surface in both volumes).
    distance_labels : list of int
        The labels whose voxel distance maps drive.
    skipped : list of str
        Why each label's surface does not drive (only where surfaces drive).
    fixed_boxes : dict of int to tuple of slice
        The fixed volume's label boxes (:meth:`LabelVolume.label_boxes`), where computed.
    stages : list of (str, float)
        The stage's parts and their seconds.
    """

    pairs: list[FeaturePair]
    points: np.ndarray
    labels: list[int]
    implicit_labels: list[int]
    distance_labels: list[int]
    skipped: list[str]
    fixed_boxes: dict[int, tuple[slice, ...]] = field(default_factory=dict)
    stages: list[tuple[str, float]] = field(default_factory=list)


def label_features(fixed: LabelVolume, moving: LabelVolume, driving: DrivingLabels, linear: LinearMap,
                   protocol: Protocol, progress: ProgressCallback | None = None, *,
                   clock: Callable[[], float]) -> LabelFeatures:
    """The feature pairs and warp-volume points of a label registration, given its linear part.

    Specks are removed, each driving label's fixed boundary mesh is made (it delimits the warp
    volume X), and, where the protocol asks, the labels' implicit surfaces are fitted in both
    volumes; every driving label's voxel signed-distance maps are made (also labels too small
    or fragmented for a surface).

    Parameters
    ----------
    fixed, moving : LabelVolume
    driving : DrivingLabels
    linear : LinearMap
        The linear part ``L`` (fixed -> moving, LPS mm): the moving features are seen through it.
    protocol : Protocol
        Its ``surface`` settings.
    progress : callable, optional
        ``progress(stage, done, total)``.
    clock : callable
        Seconds (e.g. :func:`time.perf_counter`), to time the stage's parts.

    Returns
    -------
    LabelFeatures

    Raises
    ------
    RegistrationInputError
        Nothing to drive the warp: no label with a surface in both volumes while the protocol's
        ``distance_weight`` is 0, or driving labels giving fewer than two points.
    """
    settings = protocol.surface
    unit = feature_unit(fixed, moving)
    stages = []
    t0 = clock()
    implicit = settings.implicit_weight > 0
    clean_fixed, clean_moving, labels, skipped = despeckled(fixed, moving, driving.labels, driving.by_default,
                                                            settings)
    # The fixed meshes delimit the warp volume X; the moving ones are needed only for implicit surfaces.
    s_fixed, s_moving, notes = surface_pairs(clean_fixed, clean_moving if implicit else None, labels,
                                             settings, unit, progress)
    meshed = [v for v in labels if v in s_fixed]
    used = [v for v in meshed if v in s_moving]  # none without implicit surfaces (no moving meshes)
    if implicit:
        skipped += notes
    else:
        skipped = []  # no surface drives: nothing is left out
    if not used and settings.distance_weight <= 0:
        # With distance maps (distance_weight > 0) every label drives, with a surface or not.
        raise RegistrationInputError(
            f"No label of {labels[:30]} gives a surface in both volumes and the protocol's distance_weight is 0; "
            "nothing drives the warp (set distance_weight > 0 to drive by the labels' voxel distance maps)."
        )
    stages.append(("surfaces", clock() - t0))

    pairs = []
    if implicit:
        t0 = clock()
        pairs = implicit_pairs(s_fixed, s_moving, used, settings, unit, linear, progress)
        stages.append(("implicit surfaces", clock() - t0))

    distance_labels = []
    boxes_f = {}
    if settings.distance_weight > 0:
        # Every label in both volumes (or the chosen drive labels), also those too small or
        # too fragmented for a surface.
        t0 = clock()
        distance_labels = driving.common if driving.by_default else labels
        boxes_f, boxes_m = fixed.label_boxes(), moving.label_boxes()
        coarse = finer_on_coarser(fixed, moving, linear) if settings.resample_finer else None
        pairs += distance_pairs(fixed, moving, distance_labels, boxes_f, boxes_m, settings, unit, linear,
                                progress, coarse)
        stages.append(("voxel distance maps", clock() - t0))

    points = warp_volume_points(fixed, s_fixed, meshed, distance_labels, boxes_f)
    if len(points) < 2:
        raise RegistrationInputError(
            f"The labels that drive the warp ({(distance_labels or used)[:30]}) give {len(points)} point to fit it at "
            "(a label of a single voxel); expected labels of a few voxels at least."
        )
    return LabelFeatures(pairs, points, labels, used, [int(v) for v in distance_labels], skipped, boxes_f, stages)

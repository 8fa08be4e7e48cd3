"""The label front end: two label volumes in, a fitted kernel warp out.

:func:`register_labels` runs the stages of a label registration one after the other, each
handing the next a typed result: the candidate labels (:func:`~volreg.pipeline.label_features.candidate_labels`),
the linear stage (:func:`~volreg.warp.linear.fit_linear`), the label features
(:func:`~volreg.pipeline.label_features.label_features`), and the kernel warp fitted coarse to
fine (:func:`~volreg.warp.fit.fit_warp`), kept only where it does not lower the labels' overlap
(:func:`kernel_warp_overlap`).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Sequence

import numpy as np

from volreg._threads import single_blas
from volreg.grid import LabelVolume, label_world_boxes
from volreg.pipeline.arguments import (
    callable_argument,
    drive_labels_argument,
    label_volume_argument,
    landmarks_argument,
    protocol_argument,
)
from volreg.pipeline.label_features import (
    LabelFeatures,
    candidate_labels,
    feature_unit,
    field_of_view_test,
    label_features,
)
from volreg.settings import Protocol
from volreg.warp.fit import RegistrationResult, fit_warp
from volreg.linear_map import LinearMap
from volreg.warp.linear import LinearFit, fit_linear, mean_dice_through
from volreg.warp.model import KernelWarp

__all__ = ["KERNEL_DICE_MARGIN", "KernelWarpCheck", "LabelRegistration", "StageTime", "kernel_warp_overlap",
           "register_labels"]

ProgressCallback = Callable[[str, int, int], None]
PointMap = Callable[[np.ndarray], np.ndarray]

#: How far the kernel warp may lower the labels' pooled Dice below the linear part's alone before
#: the linear part alone is kept (:func:`kernel_warp_overlap`).
KERNEL_DICE_MARGIN = 0.02


class StageTime(NamedTuple):
    """One stage of a registration and its wall time."""

    stage: str
    seconds: float


@dataclass(frozen=True)
class KernelWarpCheck:
    """The overlap check of the kernel warp (:func:`kernel_warp_overlap`).

    Attributes
    ----------
    dice_linear, dice_warp : float or None
        The labels' pooled Dice through the linear part alone and through the whole warp
        (``None`` when nothing was checked).
    margin : float
        :data:`KERNEL_DICE_MARGIN`.
    kept : {"warp", "linear"}
        ``"linear"`` where the kernel warp lowered the pooled Dice by more than ``margin``
        and the warp is the linear part alone.
    levels_fitted : int
        The kernel warp's levels fitted (the check after the first level ends the fit there
        when it fails).
    """

    dice_linear: float | None
    dice_warp: float | None
    margin: float
    kept: str
    levels_fitted: int = 0

    def to_json(self) -> dict:
        """The check as the report records it."""
        return dict(dice_linear=self.dice_linear, dice_warp=self.dice_warp, margin=self.margin, kept=self.kept,
                    levels_fitted=self.levels_fitted)


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
    stages : list of StageTime
        The stages and their seconds.
    distance_labels : list of int
        The labels whose voxel signed-distance maps drove the warp (protocol
        ``surface.distance_weight`` > 0).
    linear : LinearFit or None
        The linear stage (:func:`~volreg.warp.linear.fit_linear`): its map, also the
        linear part of ``warp``, and its log.
    cut_labels : dict of str to list of int
        ``{"fixed": [...], "moving": [...]}``: labels cut by the edge of each image (partial
        field of view); near the edges the locational cost is not counted.
    kernel_warp : KernelWarpCheck or None
        The overlap check of the kernel warp.
    """

    labels: list[int] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    stages: list[StageTime] = field(default_factory=list)
    distance_labels: list[int] = field(default_factory=list)
    linear: LinearFit | None = None
    cut_labels: dict[str, list[int]] = field(default_factory=dict)
    kernel_warp: KernelWarpCheck | None = None


@single_blas
def register_labels(
    fixed: LabelVolume | str | os.PathLike[str],
    moving: LabelVolume | str | os.PathLike[str],
    *,
    drive_labels: Sequence[int] | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    protocol: Protocol | str | os.PathLike[str] | None = None,
    prior: PointMap | None = None,
    progress: ProgressCallback | None = None,
) -> LabelRegistration:
    """Register two label volumes: ``result.warp`` maps fixed points to moving points (pull-back).

    Each label present in both volumes (or each drive label) gives a feature pair (paper (6)):
    its signed distance function (3)-(4) in the fixed volume (``f1``, O1) and in the moving
    volume (``f2``, O2), read from the label's voxels
    (:class:`~volreg.features.distance_maps.VoxelDistance`, weight ``surface.distance_weight``), so that
    labels too small or too fragmented for a surface drive the warp as well.  With the
    protocol's ``surface.implicit_weight`` > 0 each label with a surface in both volumes also
    gives the pair of kernel implicit surfaces (Section 4) of its boundary meshes.  The warp
    is fitted in the padded neighbourhood of the fixed boundary meshes (:func:`fit_warp`).

    Parameters
    ----------
    fixed, moving : LabelVolume or path-like
        The volumes, or the paths of label images (read with :func:`volreg.io.read_labels`).
    drive_labels : sequence of int, optional
        Labels whose distance maps (and implicit surfaces) drive the warp; default every label
        present in both volumes, whose meshes and implicit surfaces leave out speckled ones
        (less than :data:`~volreg.pipeline.label_features.COMPACT_FRACTION` of the voxels in
        pieces of at least 5 % of the label, see :func:`~volreg.pipeline.label_features.despeckle`).
        Specks (pieces under :data:`~volreg.pipeline.label_features.SPECK_FRACTION` of the label) are removed
        before the surfaces are made.  Labels too small to give a surface in
        either volume are skipped (their distance maps still count).
        ``result.skipped`` says which and why.
    landmarks : pair of (L, D) float ndarrays, optional
        Fixed-space points and their moving-space partners, LPS mm.
    protocol : Protocol, str or path-like, optional
        A protocol, or a preset name or protocol file (:func:`volreg.io.protocol.load_protocol`);
        default ``load_protocol("default")``.
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
    ArgumentTypeError
        An argument of the wrong kind (a list or an array for a volume, a number for a callable,
        a label that is not a number), named, before any work.
    RegistrationInputError
        A label that is not a whole number, landmarks of the wrong shape or not finite, no label
        in common, a requested label absent from a volume, or, with
        the protocol's ``distance_weight`` 0 (implicit surfaces alone), no label with a surface
        in both volumes (with distance maps every common label drives, surface or not).
    """
    fixed = label_volume_argument(fixed, "fixed")
    moving = label_volume_argument(moving, "moving")
    drive_labels = drive_labels_argument(drive_labels)
    landmarks = landmarks_argument(landmarks, fixed.ndim)
    protocol = protocol_argument(protocol)
    prior = callable_argument(prior, "prior", "of (N, D) fixed points, mm")
    progress = callable_argument(progress, "progress", "progress(stage, done, total)")
    driving = candidate_labels(fixed, moving, drive_labels)
    stages = []

    t0 = time.perf_counter()
    linear_fit = fit_linear(fixed, moving, kind=protocol.linear.kind, labels=driving.labels, progress=progress)
    cut = {side: [int(v) for v in linear_fit.log["cut_labels"][side]] for side in ("fixed", "moving")}
    stages.append(StageTime("linear", time.perf_counter() - t0))

    features = label_features(fixed, moving, driving, linear_fit.map, protocol, progress, clock=time.perf_counter)
    stages += [StageTime(name, seconds) for name, seconds in features.stages]

    t0 = time.perf_counter()
    warp, log, check = _fit_kernel_warp(fixed, moving, features, linear_fit.map, cut, protocol,
                                        landmarks=landmarks, prior=prior, progress=progress)
    stages.append(StageTime("fit warp", time.perf_counter() - t0))
    return LabelRegistration(warp, log, labels=features.implicit_labels, skipped=features.skipped, stages=stages,
                             distance_labels=features.distance_labels, linear=linear_fit, cut_labels=cut,
                             kernel_warp=check)


def _fit_kernel_warp(fixed: LabelVolume, moving: LabelVolume, features: LabelFeatures, linear: LinearMap,
                     cut: dict[str, list[int]], protocol: Protocol, *, landmarks, prior, progress
                     ) -> tuple[KernelWarp, list[dict], KernelWarpCheck]:
    """The kernel warp ``phi`` fitted between the fixed features and the moving ones seen through
    the linear part, as the whole map ``tau = L o phi``, its levels' log and its overlap check.

    Landmarks and the prior are taken back through ``L^-1``; with labels cut by an image edge,
    samples near the cut carry no locational cost (:func:`field_of_view_test`).
    """
    back = None if linear.is_identity else linear.inverse()
    if back is not None and landmarks is not None:
        landmarks = (landmarks[0], back(np.asarray(landmarks[1], float)))
    if back is not None and prior is not None:
        prior = _then(prior, back)
    valid = None
    if cut["fixed"] or cut["moving"]:
        unit = feature_unit(fixed, moving)
        margin = protocol.surface.min_width_voxels * unit + protocol.surface.clip_mm(unit)
        # A cut label's box in the image that cuts it ends at the cut; the other image's box of
        # the same label (through L) reaches where the first image has nothing.
        either = sorted(set(cut["fixed"]) | set(cut["moving"]))
        boxes = label_world_boxes(fixed, either) + label_world_boxes(moving, either, back)
        valid = field_of_view_test(fixed, moving, linear, margin, boxes)
    checked = features.labels if landmarks is None else []  # landmarks may ask for what the labels do not show
    boxes = (features.fixed_boxes or fixed.label_boxes()) if checked else {}  # for both overlap checks

    def whole(phi):
        return phi if linear.is_identity else phi.then(linear)

    def stop(phi) -> bool:
        # The overlap check after the coarsest level too: where that level already lowers the
        # labels' overlap beyond the margin, the finer ones are not fitted (the check below
        # then drops the warp).  Only the first: finer levels seldom turn what it started.
        first = len(phi.levels) == 1
        return first and kernel_warp_overlap(fixed, moving, whole(phi), linear, checked, boxes)[1].kept == "linear"

    result = fit_warp(features.pairs, features.points, landmarks=landmarks, settings=protocol.warp, prior=prior,
                      valid=valid, progress=progress, stop=stop if checked else None)
    warp, check = kernel_warp_overlap(fixed, moving, whole(result.warp), linear, checked, boxes)
    return warp, result.log, KernelWarpCheck(check.dice_linear, check.dice_warp, check.margin, check.kept,
                                             len(result.log))


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
    check : KernelWarpCheck
        ``levels_fitted`` left 0 (the caller knows how many levels were fitted).
    """
    if not labels or not warp.levels:
        return warp, KernelWarpCheck(None, None, KERNEL_DICE_MARGIN, "warp")
    boxes = fixed.label_boxes() if boxes is None else boxes
    by_linear, by_warp = mean_dice_through(fixed, moving, [linear, warp], labels, boxes, pooled=True)
    kept = "warp"
    if by_warp < by_linear - KERNEL_DICE_MARGIN:
        kept = "linear"
        warp = KernelWarp((), dim=warp.dim, settings=warp.settings, linear=linear)
    return warp, KernelWarpCheck(float(by_linear), float(by_warp), KERNEL_DICE_MARGIN, kept)


def _then(first: Callable[[np.ndarray], np.ndarray], second: Callable[[np.ndarray], np.ndarray]):
    """``x -> second(first(x))``."""
    def composed(points: np.ndarray) -> np.ndarray:
        return second(np.asarray(first(points), float))
    return composed

"""The report of a label registration: what drove it, how well the labels meet, and the warp's figures.

:func:`registration_report` judges a finished registration on the grids (Dice and surface
distances per label before and after, the Jacobian determinant, displacements, the inverse's
residual, the plausibility review) and returns a :class:`RegistrationReport`, whose
:meth:`~RegistrationReport.to_json` is what ``report.json`` holds.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from volreg import __version__
from volreg.evaluation.metrics import folded_fraction, label_scores
from volreg.evaluation.review import (
    ReviewLimits,
    findings_summary,
    judged_labels,
    label_voxel_counts,
    review_registration,
)
from volreg.grid import LabelVolume, label_world_boxes, world_box
from volreg.io.summary import json_safe, package_versions
from volreg.pipeline.grid_fields import FixedGridFields
from volreg.pipeline.label_features import feature_unit
from volreg.pipeline.labels import LabelRegistration
from volreg.settings import Protocol
from volreg.warp.field import indices_through
from volreg.warp.resample import resample_labels, resample_labels_at

__all__ = ["DIRECTION", "RegistrationReport", "interpolated_dice_before", "landmark_errors", "registration_report",
           "scores_before"]

#: How the report states the direction of the written fields.
DIRECTION = "pull-back: fixed point x corresponds to moving point x + u(x) (LPS mm)"

#: How the report describes the inverse written on the moving grid.
INVERSE_METHOD = ("start from a fixed point on the sampled forward field (else from the linear part's "
                  "inverse), checked exactly at every voxel of the moving grid; where above the "
                  "tolerance, chord steps (the linear part's matrix for the Jacobian), then Newton "
                  "iteration with the analytic Jacobian")

#: The report's optional entries, left out of the JSON when not measured.
_OPTIONAL = ("endpoint_error_mm", "landmarks")


@dataclass(kw_only=True)
class RegistrationReport:
    """The report of a label registration, as ``report.json`` holds it (:meth:`to_json`).

    Attributes
    ----------
    inputs : dict
        What the caller recorded as the inputs (paths, checksums).
    drive_labels, distance_map_labels, implicit_surface_labels : list of int
        The labels that drove the warp: all, by their voxel distance maps, by their implicit surfaces.
    skipped_labels : list of str
        Why labels' surfaces did not drive.
    labels_in_one_volume : dict
        ``{"fixed": [...], "moving": [...]}``: labels only one volume holds.
    labels : dict
        Per label (a string key): ``{"before": scores, "after": scores}`` (Dice, surface distances, mm).
    mean_dice : dict
        ``before``, ``after`` (over the labels both volumes hold) and those ``labels``.
    jacobian : dict
        ``min``, ``max``, ``folded_fraction``, ``folded_fraction_in_labels``.
    displacement_mm : dict
        ``max`` and ``mean_in_labels`` of |u|, mm.
    inverse : dict
        ``method``, ``tolerance_mm``, ``max_residual_mm``, ``unconverged_voxels``.
    linear : dict or None
        The linear part (``kind``, its description, ``fit``: the linear stage's log).
    cut_labels : dict
        ``{"fixed": [...], "moving": [...]}``: labels cut by an image edge.
    kernel_warp : dict
        The kernel warp's overlap check.
    review : dict
        The plausibility review's findings.
    levels : list of dict
        The fit's levels.
    protocol, versions : dict
    endpoint_error_mm : dict, optional
        Against a known true warp: ``mean``, ``p95``, ``max``, ``identity_mean``, ``identity_p95``, mm.
    landmarks : dict, optional
        :func:`landmark_errors`.
    stages : list of dict
        Per stage: ``stage``, ``seconds``, ``peak_rss_gb``.
    seconds : float or None
        The whole registration and its outputs, s.
    peak_rss_gb : float or None
    """

    volreg_version: str = __version__
    command: str = "register"
    inputs: dict = field(default_factory=dict)
    direction: str = DIRECTION
    drive_labels: list[int]
    distance_map_labels: list[int]
    implicit_surface_labels: list[int]
    skipped_labels: list[str]
    labels_in_one_volume: dict[str, list[int]]
    labels: dict[str, dict[str, dict[str, Any]]]
    mean_dice: dict[str, Any]
    jacobian: dict[str, float]
    displacement_mm: dict[str, float]
    inverse: dict[str, Any]
    linear: dict[str, Any] | None
    cut_labels: dict[str, list[int]]
    kernel_warp: dict[str, Any]
    review: dict[str, Any]
    levels: list[dict[str, Any]]
    protocol: dict[str, Any]
    versions: dict[str, str]
    endpoint_error_mm: dict[str, float] | None = None
    landmarks: dict[str, Any] | None = None
    stages: list[dict[str, Any]] = field(default_factory=list)
    seconds: float | None = None
    peak_rss_gb: float | None = None

    def to_json(self) -> dict[str, Any]:
        """The report as ``report.json`` holds it: its entries in order, NaN as ``None``, the
        optional entries only where measured."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
               if not (f.name in _OPTIONAL and getattr(self, f.name) is None)}
        return json_safe(out)


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
    boxes = label_world_boxes(fixed, [int(v) for v in fixed.labels() if v != 0]) or [world_box(fixed)]
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



def scores_before(fixed, moving) -> dict:
    """Dice and surface distances per label (every label of either volume) of the moving labels
    at the fixed voxel centres before any registration (nearest neighbour), against the fixed ones."""
    # On one grid, nearest neighbour at the fixed voxel centres is the moving array itself.
    before = (moving.array if moving.same_geometry(fixed) else
              resample_labels_at(moving, indices_through(fixed, None, moving), method="nearest").reshape(fixed.shape))
    labels = sorted(set(fixed.labels().tolist()) | set(moving.labels().tolist()))
    return label_scores(fixed.array, before, labels, fixed.spacing)


def interpolated_dice_before(fixed, moving, labels) -> dict[int, float]:
    """Dice of each of ``labels`` between the fixed labels and the moving ones read at the fixed
    voxel centres as they lie (no registration) by per-label interpolation, as the warped labels
    are read (:func:`scores_before` reads by nearest neighbour); over the label's boxes in both
    grids, beyond which neither reading holds it."""
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


def _review(fixed: LabelVolume, moving: LabelVolume, result: LabelRegistration, scores: tuple[dict, dict],
            jac: np.ndarray, linear: dict | None) -> dict:
    """The plausibility review's summary (:func:`~volreg.evaluation.review.review_registration`).

    Not judged: labels cut by an image edge, and labels absent from the moving volume (a
    structure one subject lacks, or a field of view that misses it: nothing to align).  Where a
    label's Dice fell by more than the review allows, "before" is read again as "after" is (per-label
    interpolation): between grids of other resolutions the two readings of the same labels differ
    by more than that on small labels.
    """
    before, after = scores
    inside = fixed.array != 0
    in_fixed, in_moving = set(fixed.labels().tolist()), set(moving.labels().tolist())
    voxels, interior = label_voxel_counts(fixed.array)
    cut = sorted(set(result.cut_labels.get("fixed", [])) | set(result.cut_labels.get("moving", []))
                 | (in_fixed - in_moving))
    drop = ReviewLimits().max_dice_drop
    judged = judged_labels(after, label_voxels=voxels, label_interior=interior, cut_labels=cut)
    fell = [v for v in judged if v in before and before[v]["dice"] - after[v]["dice"] > drop]
    kernel_warp = None if result.kernel_warp is None else result.kernel_warp.to_json()
    findings = review_registration(
        before, after, voxel_mm=feature_unit(fixed, moving), label_voxels=voxels,
        label_interior=interior, linear=linear, cut_labels=cut, folded_fraction=folded_fraction(jac, inside),
        kernel_warp=kernel_warp, dice_before_interpolated=interpolated_dice_before(fixed, moving, fell),
        linear_kind=None if result.linear is None else result.linear.log.get("kind"))
    return findings_summary(findings, judged=judged)


def _endpoint_error(fixed: LabelVolume, u: np.ndarray, truth: Callable[[np.ndarray], np.ndarray]) -> dict:
    """``|tau(x) - truth(x)|`` over the fixed labels' voxel centres, and ``|truth(x) - x|``, mm."""
    inside = fixed.array != 0
    gp = fixed.grid_points()[inside]
    err = np.linalg.norm(gp + u[inside] - truth(gp), axis=1)
    err0 = np.linalg.norm(truth(gp) - gp, axis=1)
    return {
        "mean": float(err.mean()), "p95": float(np.percentile(err, 95)), "max": float(err.max()),
        "identity_mean": float(err0.mean()), "identity_p95": float(np.percentile(err0, 95)),
    }


def registration_report(fixed: LabelVolume, moving: LabelVolume, result: LabelRegistration, fields: FixedGridFields,
                        inverse, protocol: Protocol, *, inputs: dict | None = None,
                        truth: Callable[[np.ndarray], np.ndarray] | None = None,
                        before: dict | None = None) -> RegistrationReport:
    """The report of a registration, without its stages and timings.

    Parameters
    ----------
    fixed, moving : LabelVolume
    result : LabelRegistration
    fields : FixedGridFields
        The warp on the fixed grid (:func:`~volreg.pipeline.grid_fields.sample_on_fixed_grid`).
    inverse : InverseWarp
        The inverse as the moving grid's field was computed (its tolerance and residual).
    protocol : Protocol
    inputs : dict, optional
        What the report records as the inputs.
    truth : callable, optional
        The true warp, ``(N, D) mm -> (N, D) mm``: the report then gives the endpoint error.
    before : dict, optional
        :func:`scores_before`, where the caller computed it already (e.g. in the background).

    Returns
    -------
    RegistrationReport
    """
    u, jac, warped_array = fields
    before = scores_before(fixed, moving) if before is None else before
    in_fixed, in_moving = set(fixed.labels().tolist()), set(moving.labels().tolist())  # one pass over each
    labels = sorted(in_fixed | in_moving)
    after = label_scores(fixed.array, warped_array, labels, fixed.spacing)
    inside = fixed.array != 0
    u_in = u[inside]
    linear = result.linear.map.describe() if result.linear is not None else None
    # Over the labels both volumes hold: one that only one holds has Dice 0 whatever the warp.
    shared = sorted(in_fixed & in_moving) or labels
    return RegistrationReport(
        inputs={} if inputs is None else inputs,
        drive_labels=sorted(set(result.labels) | set(result.distance_labels)),
        distance_map_labels=result.distance_labels,
        implicit_surface_labels=result.labels,
        skipped_labels=result.skipped,
        # A structure one subject lacks, a field of view that misses it, or another numbering.
        labels_in_one_volume={"fixed": sorted(in_fixed - in_moving), "moving": sorted(in_moving - in_fixed)},
        labels={str(v): {"before": before[v], "after": after[v]} for v in labels},
        mean_dice={
            "before": float(np.mean([before[v]["dice"] for v in shared])),
            "after": float(np.mean([after[v]["dice"] for v in shared])),
            "labels": shared,
        },
        jacobian={
            "min": float(jac.min()),
            "max": float(jac.max()),
            "folded_fraction": folded_fraction(jac),
            "folded_fraction_in_labels": folded_fraction(jac, inside),
        },
        displacement_mm={  # |u| by einsum: cheaper than np.linalg.norm on large grids
            "max": float(np.sqrt(np.einsum("...i,...i->...", u, u).max())),
            "mean_in_labels": float(np.sqrt(np.einsum("ni,ni->n", u_in, u_in)).mean()) if inside.any() else 0.0,
        },
        inverse={
            "method": INVERSE_METHOD,
            "tolerance_mm": inverse.tol,
            "max_residual_mm": inverse.max_residual,
            "unconverged_voxels": inverse.unconverged,
        },
        linear=None if linear is None else {"kind": protocol.linear.kind, **linear, "fit": result.linear.log},
        cut_labels=result.cut_labels,
        kernel_warp={} if result.kernel_warp is None else result.kernel_warp.to_json(),
        review=_review(fixed, moving, result, (before, after), jac, linear),
        levels=result.log,
        protocol=protocol.to_dict(),
        versions=package_versions(),
        endpoint_error_mm=None if truth is None else _endpoint_error(fixed, u, truth),
    )

"""A plausibility review of a label registration: what a reviewer would check, as findings.

A registration can finish without error and still be wrong: a header with a flipped
axis makes the linear part rotate by 180 degrees, a wrong voxel spacing makes it
scale by 2, a label that means another structure in the other image is pulled onto
the wrong partner.  :func:`review_registration` checks the figures a reviewer reads
off a report -- per-label Dice and mean surface distance before and after, the
linear part's rotation and scales, the folded fraction -- against the limits of
:class:`ReviewLimits`, and returns one :class:`Finding` per broken rule, each with a
one-line message that names the label, the figure with its unit, the limit and one
thing to try.  :func:`findings_summary` gives the JSON block of a report.

Labels cut by the edge of either image, labels of fewer than
``ReviewLimits.min_voxels`` voxels in the fixed volume, and (given their interior
counts, :func:`label_voxel_counts`) labels with almost no interior voxel are not
judged on overlap or distance (:func:`judged_labels`): their figures measure the
field of view or the voxel grid, not the registration.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from volreg.grid import label_counts

__all__ = ["Finding", "ReviewLimits", "findings_summary", "judged_labels", "label_voxel_counts",
           "review_registration"]


def _is_real(value) -> bool:
    """Whether ``value`` is a real number (not a bool)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


@dataclass(frozen=True)
class ReviewLimits:
    """The limits of :func:`review_registration`, with the reason for each default.

    Attributes
    ----------
    min_voxels : int, default 100
        Labels with fewer voxels in the fixed volume are not judged on Dice or distance.
        A ball of 100 voxels has a radius of 2.9 voxels; shifting it by one voxel lowers
        its Dice to 0.74, and most of its voxels are boundary voxels, so the figures of
        smaller labels measure the grid more than the registration (the benchmarks'
        "labels >= 100 voxels" column uses the same cut).
    min_interior_fraction : float, default 0.02
        Given interior counts, labels with fewer interior voxels (all face neighbours in
        the label) than this fraction of their voxels are not judged either: they are
        sheets at most two voxels thick or scatters of specks, whose Dice and surface
        distance a half-voxel resampling shift decides: resampled through the true warp,
        labels without an interior voxel can break the Dice and distance limits, while
        labels with a few percent of interior voxels stay within them.
    max_distance_voxels : float, default 2.0
    max_distance_mm : float, default 2.0
        A judged label's mean surface distance after the warp may be at most the larger
        of ``max_distance_voxels`` voxels (of the coarser grid) and ``max_distance_mm``.
        Resampling labels alone moves a boundary by up to half a voxel, and the distances
        are measured between boundary voxels, so a correct result is within about one
        voxel; two voxels is clearly beyond the grid.  The floor in mm keeps sub-millimetre
        images from being judged on differences as small as the variability of drawn
        labels (about a millimetre).
    min_dice : float, default 0.5
        A judged label's Dice after the warp.  Two equal balls have Dice 0.5 when their
        centres are 0.69 radii apart: half the label lies off its partner.
    max_dice_drop : float, default 0.05
        How far a judged label's Dice may fall below its Dice before registration (the
        moving labels resampled onto the fixed grid unchanged).  A registration should
        not leave a label worse than doing nothing; 0.05 leaves room for the difference
        between nearest-neighbour resampling (before) and per-label interpolation (after).
        On small labels between grids of other resolutions the two readings differ by more,
        so where a label's drop exceeds the limit its Dice before is read again by per-label
        interpolation and the lower reading counts.
    min_mean_dice : float, default 0.6
        The mean Dice after the warp over the judged labels.  Registrations of the demo
        pair score far above it, and even the pair unregistered scores above it: a mean
        below 0.6 means the images were not brought together at all.
    max_rotation_deg : float, default 60.0
        The linear part's rotation angle.  Scans of one anatomy differ in pose by up to
        about 45 degrees; a larger angle (often 90 or 180) usually comes from an
        orientation header that flips or permutes axes, or from a wrong pairing.
    min_scale, max_scale : float, default 0.6 and 1.67
        The range of the linear part's scales (the stretches of its polar decomposition).
        Subjects differ in size by about 0.8-1.25; 1.67 = 1 / 0.6 keeps the range symmetric
        on a log scale.  Beyond it a header's voxel spacing is the likelier cause (a
        resampled image with its old spacing, mm against cm).
    max_folded_fraction : float, default 0.0
        Fraction of voxels where ``det d tau / dx <= 0``.  Where the warp folds, two fixed
        points map to one moving point; the fold barrier and guard aim for none, so any
        fold is worth a look (the registration itself stops above the protocol's
        ``max_folded_fraction``).
    max_listed : int, default 5
        When more labels than this fail one rule, they give one finding (their count and
        the worst ``worst_listed``) instead of one each: a user reads a few lines.
    worst_listed : int, default 3
        How many of the worst labels such a finding names.
    """

    min_voxels: int = 100
    min_interior_fraction: float = 0.02
    max_distance_voxels: float = 2.0
    max_distance_mm: float = 2.0
    min_dice: float = 0.5
    max_dice_drop: float = 0.05
    min_mean_dice: float = 0.6
    max_rotation_deg: float = 60.0
    min_scale: float = 0.6
    max_scale: float = 1.67
    max_folded_fraction: float = 0.0
    max_listed: int = 5
    worst_listed: int = 3

    def __post_init__(self) -> None:
        for name in ("min_voxels", "max_listed", "worst_listed"):
            value = getattr(self, name)
            least = 0 if name == "min_voxels" else 1
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < least:
                raise ValueError(f"Expected `{name}` as a {'non-negative' if name == 'min_voxels' else 'positive'} "
                                 f"integer, got {value!r}.")
        for name in ("max_distance_voxels", "max_distance_mm", "max_dice_drop", "max_rotation_deg",
                     "max_folded_fraction"):
            value = getattr(self, name)
            if not (_is_real(value) and math.isfinite(value) and value >= 0):
                raise ValueError(f"Expected `{name}` as a finite number >= 0, got {value!r}.")
        for name in ("min_dice", "min_mean_dice", "min_interior_fraction"):
            value = getattr(self, name)
            if not (_is_real(value) and 0 <= value <= 1):
                raise ValueError(f"Expected `{name}` in [0, 1], got {value!r}.")
        if not (_is_real(self.min_scale) and _is_real(self.max_scale)
                and 0 < self.min_scale <= 1 <= self.max_scale < math.inf):
            raise ValueError(f"Expected 0 < `min_scale` <= 1 <= `max_scale` (finite), "
                             f"got {self.min_scale!r} and {self.max_scale!r}.")

    def max_distance(self, voxel_mm: float) -> float:
        """The largest acceptable mean surface distance, mm, for a coarser grid of ``voxel_mm``."""
        return max(self.max_distance_voxels * voxel_mm, self.max_distance_mm)


@dataclass(frozen=True)
class Finding:
    """One implausible figure of a registration.

    Attributes
    ----------
    label : int or None
        The label judged; ``None`` for a finding about the whole registration, or about
        several labels at once (then ``labels`` names them).
    figure : str
        What was judged: ``"mean_surface_distance_mm"``, ``"dice"``, ``"dice_drop"`` (Dice
        before minus Dice after), ``"mean_dice"``, ``"rotation_deg"``, ``"scale"``,
        ``"folded_fraction"``, or ``"judged_labels"`` (the count of labels judged, when none
        could be: the result was not checked).
    value : float
        The figure's value (for several labels: the worst of them).
    limit : float
        The limit it crossed.
    message : str
        One line for a user: which label, the figure with its unit, the limit, one thing to try.
    labels : tuple of int
        Every label the finding is about (one, several, or none).
    """

    label: int | None
    figure: str
    value: float
    limit: float
    message: str
    labels: tuple[int, ...] = ()

    def to_dict(self) -> dict:
        """Plain JSON data: ``label``, ``labels`` (a list), ``figure``, ``value``, ``limit``, ``message``."""
        return dict(label=self.label, labels=list(self.labels), figure=self.figure, value=float(self.value),
                    limit=float(self.limit), message=self.message)


def _number(value: float, limit: float, decimals: int) -> str:
    """``value`` with ``decimals`` decimals, or more (up to 4) when it would print as ``limit``."""
    for d in range(decimals, 5):
        text = f"{value:.{d}f}"
        if text != f"{limit:.{d}f}":
            return text
    return f"{value:.4f}"


@dataclass(frozen=True)
class _Rule:
    """A per-label rule: the words of its messages and which way is worse."""

    figure: str
    higher_is_worse: bool
    unit: str
    decimals: int
    single: str  # a sentence about one label, formatted with label, value, limit
    several: str  # a sentence about several labels, formatted with count, limit
    hint: str  # one thing to try, about one label (formatted with label)
    hint_several: str  # the same, about several labels


_DISTANCE = _Rule(
    "mean_surface_distance_mm", True, " mm", 1,
    "the warped boundary of label {label} lies {value} mm from the fixed one on average "
    "(mean surface distance, limit {limit} mm)",
    "the warped boundaries of {count} labels lie farther from the fixed ones than {limit} mm on average "
    "(mean surface distance)",
    "check that label {label} marks the same structure in both images, or try a finer warp (a smaller "
    "`[warp] min_width`)",
    "check that these labels mark the same structures in both images, or try a finer warp (a smaller "
    "`[warp] min_width`)")
_DICE = _Rule(
    "dice", False, "", 2,
    "label {label} overlaps its fixed counterpart with Dice {value} after registration (limit {limit})",
    "{count} labels overlap their fixed counterparts with a Dice below {limit} after registration",
    "check that label {label} marks the same structure in both images{linear}",
    "check that these labels mark the same structures in both images{linear}")
_DROP = _Rule(
    "dice_drop", True, "", 2,
    "the Dice of label {label} fell by {value} during registration (from {before} to {after}; limit {limit})",
    "the Dice of {count} labels fell by more than {limit} during registration",
    "check whether label {label} drove the warp (report.json `drive_labels`, `skipped_labels`); if not, "
    "name it in `--drive-labels`",
    "check whether these labels drove the warp (report.json `drive_labels`, `skipped_labels`); if not, "
    "name them in `--drive-labels`")


def _linear_hint(kind: str | None) -> str:
    """What a finding of poor overlap suggests about the linear stage, after a comma: a rigid stage
    (a similarity or affine one can meet the labels by a wrong scale or stretch, and without one
    the poses are not brought together), except where it was rigid already; then the one thing a
    rigid map cannot undo, a mirrored image.  ``kind`` is the stage's kind (the
    protocol's ``[linear] kind``), None where it is not known."""
    if kind == "rigid":
        return (", and whether one image is mirrored (a flipped axis in one header: a rigid map turns "
                "but cannot mirror)")
    return ', or try `[linear] kind = "rigid"`'


def _check_scores(name: str, scores, label: int, keys: Sequence[str]) -> dict:
    entry = scores.get(label)
    if not isinstance(entry, Mapping) or any(k not in entry for k in keys):
        raise ValueError(f"Expected `{name}[{label}]` as a dict with {', '.join(repr(k) for k in keys)} "
                         f"(label_scores output), got {entry!r}.")
    return entry


def _per_label(rule: _Rule, failures: list[tuple[int, float, float, dict]], limits: ReviewLimits,
               linear_kind: str | None = None) -> list[Finding]:
    """Findings of one per-label rule: one per label, or one summary for more than ``max_listed``.

    ``failures`` holds ``(label, value, limit, extra)``, with ``extra`` more fields of the message.
    """
    if not failures:
        return []
    failures = sorted(failures, key=lambda f: (-f[1] if rule.higher_is_worse else f[1], f[0]))
    if len(failures) <= limits.max_listed:
        out = []
        for label, value, limit, extra in failures:
            text = rule.single.format(label=label, value=_number(value, limit, rule.decimals),
                                      limit=f"{limit:.{rule.decimals}f}", **extra)
            hint = rule.hint.format(label=label, linear=_linear_hint(linear_kind))
            out.append(Finding(label, rule.figure, value, limit, f"{text}; {hint}.", (label,)))
        return out
    limit = failures[0][2]  # one limit per rule
    worst = ", ".join(f"label {label} {_number(value, lim, rule.decimals)}{rule.unit}"
                      for label, value, lim, _ in failures[: limits.worst_listed])
    text = rule.several.format(count=len(failures), limit=f"{limit:.{rule.decimals}f}")
    label_list = tuple(sorted(f[0] for f in failures))
    message = f"{text}; worst: {worst}; {rule.hint_several.format(linear=_linear_hint(linear_kind))}."
    return [Finding(None, rule.figure, failures[0][1], limit, message, label_list)]


def label_voxel_counts(array: np.ndarray) -> tuple[dict[int, int], dict[int, int]]:
    """Voxels and interior voxels of every non-zero label of a label array.

    Parameters
    ----------
    array : (n_i, n_j[, n_k]) int ndarray
        A label volume's array (e.g. the fixed one).

    Returns
    -------
    voxels : dict of int to int
        Voxel count of each non-zero label present.
    interior : dict of int to int
        Of those, the voxels whose face neighbours all hold the same label (a voxel on the
        image edge is not interior: the edge counts as outside, as for the surface
        distances of :mod:`volreg.evaluation.metrics`; axes of length 1 have no neighbours
        and do not count).
    """
    a = np.asarray(array)
    if a.ndim < 1 or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"Expected `array` as an integer label array, got {a.dtype} of shape {a.shape}.")
    # Axes of one voxel (a single slice stored as a volume) have no neighbours to compare.
    axes = [k for k in range(a.ndim) if a.shape[k] > 1]
    inner = tuple(slice(1, -1) if k in axes else slice(None) for k in range(a.ndim))
    core = a[inner]
    interior_core = np.ones(core.shape, dtype=bool)
    for axis in axes:
        for lo, hi in ((0, -2), (2, None)):
            shifted = tuple(slice(lo, hi) if k == axis else inner[k] for k in range(a.ndim))
            interior_core &= core == a[shifted]
    voxels = label_counts(a)
    inside = label_counts(core[interior_core])
    return voxels, {v: inside.get(v, 0) for v in voxels}


def judged_labels(labels: Iterable[int], *, label_voxels: Mapping[int, int],
                  label_interior: Mapping[int, int] | None = None, cut_labels: Iterable[int] = (),
                  limits: ReviewLimits = ReviewLimits()) -> list[int]:
    """The labels :func:`review_registration` judges on Dice and distance, sorted.

    Parameters
    ----------
    labels : iterable of int
        Candidate labels (e.g. the keys of the scores); 0 (background) is never judged.
    label_voxels : dict of int to int
        Voxel count of each label in the fixed volume (labels not given count 0); with
        fewer than ``limits.min_voxels`` a label is not judged.
    label_interior : dict of int to int, optional
        Interior voxel count of each label in the fixed volume (:func:`label_voxel_counts`);
        with fewer than ``limits.min_interior_fraction`` of its voxels a label is not judged.
        ``None``: no such rule.
    cut_labels : iterable of int
        Labels cut by the edge of either image: not judged.
    limits : ReviewLimits

    Returns
    -------
    list of int
    """
    cut = {int(v) for v in cut_labels}
    out = []
    for v in sorted({int(v) for v in labels}):
        n = int(label_voxels.get(v, 0))
        if v == 0 or v in cut or n == 0 or n < limits.min_voxels:
            continue
        if label_interior is not None and int(label_interior.get(v, 0)) < limits.min_interior_fraction * n:
            continue
        out.append(v)
    return out


def review_registration(
    scores_before: Mapping[int, Mapping],
    scores_after: Mapping[int, Mapping],
    *,
    voxel_mm: float,
    label_voxels: Mapping[int, int],
    label_interior: Mapping[int, int] | None = None,
    linear: Mapping | None = None,
    cut_labels: Iterable[int] = (),
    folded_fraction: float = 0.0,
    kernel_warp: Mapping | None = None,
    limits: ReviewLimits = ReviewLimits(),
    dice_before_interpolated: Mapping[int, float] | None = None,
    linear_kind: str | None = None,
) -> list[Finding]:
    """Check a registration's figures against ``limits``; one finding per broken rule.

    The rules (defaults and their reasons in :class:`ReviewLimits`):

    * the linear part's rotation above ``max_rotation_deg``, or a scale outside
      ``[min_scale, max_scale]`` (a wrong orientation or spacing header, or a wrong pairing);
    * the kernel warp left out because it lowered the labels' overlap (``kernel_warp``);
    * a folded fraction above ``max_folded_fraction``;
    * the mean Dice after over the judged labels below ``min_mean_dice``;
    * a judged label's mean surface distance after above
      ``max(max_distance_voxels * voxel_mm, max_distance_mm)`` (labels whose distance is
      undefined, being absent after the warp, are left to the Dice rules);
    * a judged label's Dice after below ``min_dice``;
    * a judged label's Dice after more than ``max_dice_drop`` below its Dice before;
    * no label judged at all (the result could not be checked).

    Judged labels (:func:`judged_labels`): non-zero labels of ``scores_after`` with at least
    ``min_voxels`` voxels in the fixed volume, not in ``cut_labels`` and, given
    ``label_interior``, with at least ``min_interior_fraction`` of their voxels interior.
    When more than ``max_listed`` labels break one per-label rule, they give one finding
    (count and the worst ``worst_listed``).

    Parameters
    ----------
    scores_before, scores_after : dict of int to dict
        :func:`~volreg.evaluation.metrics.label_scores` of the moving labels on the fixed
        grid against the fixed labels: before (the moving volume resampled unchanged) and
        after the registration.  ``"dice"`` and ``"mean_surface_distance_mm"`` (mm, NaN
        when a label is absent from either volume) are read.
    voxel_mm : float, mm
        The largest voxel spacing of the coarser of the two grids.
    label_voxels : dict of int to int
        Voxel count of each label in the fixed volume (labels not given count 0).
    label_interior : dict of int to int, optional
        Interior voxel count of each label in the fixed volume (:func:`label_voxel_counts`).
    linear : dict, optional
        :meth:`~volreg.linear_map.LinearMap.describe` of the linear part (``rotation_deg``,
        ``scales`` are read), or ``None`` without a linear stage.
    cut_labels : iterable of int
        Labels cut by the edge of either image: not judged on Dice or distance.
    folded_fraction : float
        Fraction of the fixed labels' voxels where ``det d tau / dx <= 0``.
    kernel_warp : dict, optional
        The kernel warp's overlap check (:func:`volreg.pipeline.labels.kernel_warp_overlap`:
        ``dice_linear``, ``dice_warp``, ``margin``, ``kept``); with ``kept`` ``"linear"`` the
        result is the linear part alone, which is reported.
    limits : ReviewLimits
    dice_before_interpolated : mapping of int to float, optional
        Per label, its Dice before registration with the moving labels read as the warped ones
        are (per-label interpolation) rather than by nearest neighbour; where given, the Dice
        drop is measured from the lower of the two readings (on small labels between grids of
        other resolutions they differ by more than ``max_dice_drop``).
    linear_kind : {"none", "rigid", "similarity", "affine"}, optional
        The kind of linear stage that ran (the protocol's ``[linear] kind``): the findings suggest
        no kind that is already set (after a rigid stage, a mirrored image rather than a rigid
        stage).  Not known: the suggestions name a rigid stage.

    Returns
    -------
    list of Finding
        Empty for a plausible registration.  Whole-registration findings come first (the
        linear part, folding, mean Dice), then the per-label rules in the order above,
        each worst first.

    Raises
    ------
    ValueError
        ``voxel_mm`` not positive, ``folded_fraction`` outside [0, 1], a judged label
        without Dice or distance in ``scores_after``, or ``linear`` without
        ``rotation_deg`` and ``scales``.
    """
    if not (_is_real(voxel_mm) and math.isfinite(voxel_mm) and voxel_mm > 0):
        raise ValueError(f"Expected `voxel_mm` as a positive voxel spacing in mm, got {voxel_mm!r}.")
    if not (_is_real(folded_fraction) and 0 <= folded_fraction <= 1):
        raise ValueError(f"Expected `folded_fraction` in [0, 1], got {folded_fraction!r}.")
    cut_labels = sorted({int(v) for v in cut_labels})
    judged = judged_labels(scores_after, label_voxels=label_voxels, label_interior=label_interior,
                           cut_labels=cut_labels, limits=limits)
    findings: list[Finding] = []
    if linear is not None:
        findings += _linear_findings(linear, limits, linear_kind)
    if kernel_warp is not None and kernel_warp.get("kept") == "linear":
        findings.append(_kernel_warp_left_out(kernel_warp, float(voxel_mm), cut_labels))
    if folded_fraction > limits.max_folded_fraction:
        findings.append(Finding(
            None, "folded_fraction", float(folded_fraction), limits.max_folded_fraction,
            f"the warp folds (det d tau/dx <= 0) at {100 * folded_fraction:.2g} % of the fixed labels' voxels "
            f"(limit {100 * limits.max_folded_fraction:.2g} %); try a larger `[warp] lambda_fold` or `min_width`."))
    after = {v: _check_scores("scores_after", scores_after, v, ("dice", "mean_surface_distance_mm")) for v in judged}
    findings += _overall_findings(judged, after, scores_after, limits, linear_kind)
    findings += _label_findings(judged, after, scores_before, dice_before_interpolated,
                                limits.max_distance(float(voxel_mm)), limits, linear_kind)
    return findings


def _linear_findings(linear: Mapping, limits: ReviewLimits, kind: str | None = None) -> list[Finding]:
    """Findings on the linear part (:meth:`~volreg.warp.linear.LinearMap.describe`): its rotation
    angle, then its smallest and largest scales; ``kind`` the stage's kind, as
    :func:`review_registration` takes it."""
    if not isinstance(linear, Mapping) or "rotation_deg" not in linear or "scales" not in linear:
        raise ValueError("Expected `linear` as LinearMap.describe() output (with 'rotation_deg' and 'scales') "
                         f"or None, got {linear!r}.")
    findings = []
    angle = float(linear["rotation_deg"])
    if angle > limits.max_rotation_deg:
        try_kind = ('`[linear] kind = "none"` for images already aligned' if kind == "rigid" else
                    '`[linear] kind = "rigid"` (or "none" for images already aligned)')
        findings.append(Finding(
            None, "rotation_deg", angle, limits.max_rotation_deg,
            f"the linear part rotates the images by {_number(angle, limits.max_rotation_deg, 1)} deg "
            f"(limit {limits.max_rotation_deg:.1f} deg), likely a wrong orientation header or a wrong pairing "
            f"of images; check both images' headers, or try {try_kind}."))
    scales = [float(s) for s in linear["scales"]]
    low, high = min(scales), max(scales)
    for value, limit, side in ((low, limits.min_scale, "below"), (high, limits.max_scale, "above")):
        if (value < limit) if side == "below" else (value > limit):
            findings.append(Finding(
                None, "scale", value, limit,
                f"the linear part scales the images by {_number(value, limit, 2)} along one axis "
                f"({side} the limit {limit:.2f}), likely a wrong voxel spacing in a header or a wrong pairing "
                "of images; check both images' spacings, or try `[linear] kind = \"rigid\"`."))
    return findings


def _kernel_warp_left_out(kernel_warp: Mapping, voxel_mm: float, cut_labels: list[int]) -> Finding:
    """The finding that the kernel warp was left out because it lowered the labels' pooled Dice."""
    by_linear, by_warp = float(kernel_warp["dice_linear"]), float(kernel_warp["dice_warp"])
    return Finding(
        None, "kernel_warp_dice_drop", by_linear - by_warp, float(kernel_warp.get("margin", 0.0)),
        f"the kernel warp lowered the labels' pooled Dice from {by_linear:.3f} (the linear part alone) to "
        f"{by_warp:.3f}, so the result is the linear part alone; labels only a few voxels across at the "
        f"largest voxel spacing of the two grids ({voxel_mm:.3g} mm, which sets the features' scale) cannot "
        "drive a warp" + (f", and labels {cut_labels[:10]} are cut by an image edge or absent from one "
                          "volume" if cut_labels else "")
        + ": check the labels' size against that spacing and what each image covers, or use the result as a "
        "linear one.")


def _overall_findings(judged: list[int], after: Mapping[int, Mapping], scores_after: Mapping[int, Mapping],
                      limits: ReviewLimits, linear_kind: str | None = None) -> list[Finding]:
    """Findings on the judged labels as a whole: none could be judged, or their mean Dice is too low."""
    if not judged:
        if any(int(v) != 0 for v in scores_after):
            return [Finding(
                None, "judged_labels", 0.0, 1.0,
                f"no label could be judged on Dice or boundary distance (each is under {limits.min_voxels} voxels "
                "in the fixed volume, a thin sheet, cut by an image edge, or absent from the moving volume), so "
                "the result was not checked; look at report.png.")]
        return []
    mean_dice = sum(float(after[v]["dice"]) for v in judged) / len(judged)
    if mean_dice < limits.min_mean_dice:
        return [Finding(
            None, "mean_dice", mean_dice, limits.min_mean_dice,
            f"the mean Dice after registration is {_number(mean_dice, limits.min_mean_dice, 2)} over "
            f"{len(judged)} judged labels (limit {limits.min_mean_dice:.2f}): the images were not brought "
            f"together; check that they show the same anatomy with the same label values"
            f"{_linear_hint(linear_kind)}.", tuple(judged))]
    return []


def _label_findings(judged: list[int], after: Mapping[int, Mapping], scores_before: Mapping[int, Mapping],
                    dice_before_interpolated: Mapping[int, float] | None, max_distance: float,
                    limits: ReviewLimits, linear_kind: str | None = None) -> list[Finding]:
    """Findings of the per-label rules, in order: mean surface distance above ``max_distance`` (mm),
    Dice below ``limits.min_dice``, Dice drop above ``limits.max_dice_drop``."""
    distance, low_dice, drop = [], [], []
    for v in judged:
        d = float(after[v]["mean_surface_distance_mm"])
        if math.isfinite(d) and d > max_distance:
            distance.append((v, d, max_distance, {}))
        dice_after = float(after[v]["dice"])
        if dice_after < limits.min_dice:
            low_dice.append((v, dice_after, limits.min_dice, {}))
        if v in scores_before:
            dice_before = float(_check_scores("scores_before", scores_before, v, ("dice",))["dice"])
            if dice_before_interpolated and v in dice_before_interpolated:
                dice_before = min(dice_before, float(dice_before_interpolated[v]))
            if dice_before - dice_after > limits.max_dice_drop:
                drop.append((v, dice_before - dice_after, limits.max_dice_drop,
                             dict(before=f"{dice_before:.2f}", after=f"{dice_after:.2f}")))
    findings: list[Finding] = []
    for rule, failures in ((_DISTANCE, distance), (_DICE, low_dice), (_DROP, drop)):
        findings += _per_label(rule, failures, limits, linear_kind)
    return findings


def findings_summary(findings: Sequence[Finding], *, limits: ReviewLimits = ReviewLimits(),
                     judged: Sequence[int] | None = None) -> dict:
    """The review's block of ``report.json`` (JSON-ready, no NaN).

    Parameters
    ----------
    findings : sequence of Finding
        :func:`review_registration` output.
    limits : ReviewLimits
        The limits the review used (recorded in the block).
    judged : sequence of int, optional
        The labels judged on Dice and distance (:func:`judged_labels`), to record.

    Returns
    -------
    dict
        ``plausible`` (bool: no finding), ``findings`` (a list of :meth:`Finding.to_dict`),
        ``limits`` (every field of ``limits``) and, given ``judged``, ``judged_labels``.
    """
    out = {"plausible": not findings, "findings": [f.to_dict() for f in findings], "limits": asdict(limits)}
    if judged is not None:
        out["judged_labels"] = [int(v) for v in judged]
    return out

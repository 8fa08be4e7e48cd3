"""Plausibility checks of a surface pair and its correspondence: frames and units that do not match.

A surface written in RAS and read as LPS is mirrored in x and y; one in metres
beside one in millimetres is a thousand times smaller.  Neither stops a
registration or a transfer, which then finish with meaningless values.  These
checks catch both from figures the commands compute anyway, as
:class:`~volreg.evaluation.review.Finding` s with one-line messages.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from volreg.evaluation.review import Finding

__all__ = ["GAPS_MEASURED", "SurfaceReviewLimits", "diameter", "review_surface_distance", "review_surface_extents",
           "review_surface_translation", "review_landmarks"]


@dataclass(frozen=True)
class SurfaceReviewLimits:
    """The limits of the surface checks, with the reason for each default.

    Attributes
    ----------
    max_median_distance_fraction : float, default 0.05
        The median distance from the warped source vertices to the target
        surface, as a fraction of the target's diameter (bounding-box
        diagonal).  On the GIFTI test pair (an ellipsoid of diameter 67 mm
        centred 32 mm from the midline) the registered source lies a median
        0.05 mm (0.08 %) from the target; read mirrored (its RAS coordinates
        taken as LPS) 49 mm (73 %).  A structure off the midline, such as a
        hemisphere, moves by twice its distance from the midline when mirrored
        in x and y.  5 % leaves room for a poor but honest registration.
        The same fraction holds for the 90th percentile of the distances: a
        tenth of the source farther off is a part of it with no counterpart in
        the target, squeezed towards the cut while the median over all vertices
        stays small (a sphere against the 60 % of it above a cut: 16 % of its
        vertices beyond 5 % of the target's diameter, the median 0.2 %; half an
        ellipsoid against the whole: its unmatched half a median 9 % off).
    max_extent_ratio : float, default 10.0
        The ratio of the larger diameter to the smaller one of the two
        surfaces.  The same structure in two subjects differs by tens of per
        cent; metres against millimetres gives 1000, centimetres 10.
    max_translation_fraction : float, default 0.5
        The centroids' translation the warp starts from (``register_surfaces``
        ``align_centroids``), as a fraction of the source's diameter.  The
        GIFTI test pair read mirrored needs 98 % (the structure 32 mm off the
        midline moves 64 mm), after which the mirrored surface lies on the
        target and no distance shows it; a subject's surface shifted by a
        quarter of its size within one frame is an honest pair.
    max_landmark_fraction : float, default 0.05
        The mean distance between the warped source landmarks and the target
        ones, as a fraction of the target's diameter.  Exact landmarks are met
        to 0.04 mm; landmarks in another order or frame (RAS values in an LPS
        file) were left 23-26 % off, with the warp 6-7 mm from the truth.
    """

    max_median_distance_fraction: float = 0.05
    max_extent_ratio: float = 10.0
    max_translation_fraction: float = 0.5
    max_landmark_fraction: float = 0.05

    def __post_init__(self) -> None:
        for name in ("max_translation_fraction", "max_landmark_fraction"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"Expected `{name}` > 0, got {value!r}.")
        if not (math.isfinite(self.max_median_distance_fraction) and self.max_median_distance_fraction > 0):
            raise ValueError(f"Expected `max_median_distance_fraction` > 0, got {self.max_median_distance_fraction!r}.")
        if not (math.isfinite(self.max_extent_ratio) and self.max_extent_ratio > 1):
            raise ValueError(f"Expected `max_extent_ratio` > 1, got {self.max_extent_ratio!r}.")


def diameter(points: np.ndarray) -> float:
    """The diagonal of the bounding box of ``points`` ((N, 3), mm), mm."""
    p = np.asarray(points, float)
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))


def review_surface_extents(source: np.ndarray, target: np.ndarray,
                           limits: SurfaceReviewLimits = SurfaceReviewLimits()) -> list[Finding]:
    """A finding when the two surfaces differ in size by more than ``limits.max_extent_ratio``.

    Parameters
    ----------
    source, target : (N, 3) and (M, 3) float ndarray, mm
        The vertices of the two surfaces.
    limits : SurfaceReviewLimits

    Returns
    -------
    list of Finding
        Empty, or one finding with figure ``"extent_ratio"`` (larger diameter over smaller).
    """
    ds, dt = diameter(source), diameter(target)
    small, large = min(ds, dt), max(ds, dt)
    ratio = math.inf if small <= 0 else large / small
    if ratio <= limits.max_extent_ratio:
        return []
    message = (f"SOURCE spans {ds:.4g} mm and TARGET {dt:.4g} mm, a ratio of {ratio:.3g} (limit "
               f"{limits.max_extent_ratio:g}); check that both are in millimetres (metres against millimetres gives "
               "about 1000).")
    return [Finding(None, "extent_ratio", ratio, limits.max_extent_ratio, message)]


#: How :func:`volreg.morph.surface_gaps` measured, by the key it returns (``report.json``
#: ``measured``), in words after a distance ("a median 0.2 mm from TARGET").
GAPS_MEASURED = {
    "source_to_target": "from TARGET",
    "source_to_target_points": "from TARGET's points (beyond half their spacing)",
}


def review_surface_distance(distance: np.ndarray, target_diameter: float,
                            limits: SurfaceReviewLimits = SurfaceReviewLimits(), *, hint: str = "",
                            measured: str = "source_to_target") -> list[Finding]:
    """A finding when the warped source lies far from the target surface.

    Parameters
    ----------
    distance : (N,) float ndarray, mm
        Distance of each warped source vertex to the target surface, or as ``measured`` says
        (:func:`volreg.morph.surface_gaps`).
    target_diameter : float, mm
        The target's bounding-box diagonal (:func:`diameter`).
    limits : SurfaceReviewLimits
    hint : str, optional
        A sentence to append (what to check, in the words of the command).
    measured : str, default "source_to_target"
        How ``distance`` was measured: a key of :data:`GAPS_MEASURED`
        (``"source_to_target_points"``: to a point cloud's points, beyond half their spacing).

    Returns
    -------
    list of Finding
        Empty, or one finding with figure ``"median_distance_fraction"`` (median distance
        over the target's diameter) or, where the median is within the limit,
        ``"p90_distance_fraction"`` (the 90th percentile's, a partial surface).
    """
    from_what = GAPS_MEASURED[measured]
    d = np.asarray(distance, float)
    median = float(np.median(d))
    fraction = median / target_diameter if target_diameter > 0 else math.inf
    if fraction <= limits.max_median_distance_fraction:
        p90 = float(np.percentile(d, 90))
        tenth = p90 / target_diameter if target_diameter > 0 else math.inf
        if tenth <= limits.max_median_distance_fraction:
            return []
        message = (f"a tenth of the warped SOURCE vertices lie more than {p90:.3g} mm {from_what}, "
                   f"{100 * tenth:.1f} % of TARGET's diameter (limit {100 * limits.max_median_distance_fraction:g} %), "
                   f"while the median is {median:.3g} mm: part of SOURCE has no counterpart in TARGET (a partial "
                   "surface), and the warp squeezes it towards what TARGET holds; register surfaces that cover the "
                   "same part of the structure.")
        if hint:
            message += " " + hint
        return [Finding(None, "p90_distance_fraction", tenth, limits.max_median_distance_fraction, message)]
    message = (f"the warped SOURCE vertices lie a median {median:.3g} mm {from_what}, {100 * fraction:.1f} % of "
               f"TARGET's diameter (limit {100 * limits.max_median_distance_fraction:g} %): the surfaces are probably in "
               "different frames (RAS against LPS: a GIFTI converted to another format keeps RAS) or units.")
    if hint:
        message += " " + hint
    return [Finding(None, "median_distance_fraction", fraction, limits.max_median_distance_fraction, message)]


def review_surface_translation(translation: np.ndarray, source_diameter: float,
                               limits: SurfaceReviewLimits = SurfaceReviewLimits()) -> list[Finding]:
    """A finding when the centroids' translation the warp starts from exceeds
    ``limits.max_translation_fraction`` of the source's diameter.

    Parameters
    ----------
    translation : (D,) float ndarray, mm
        The warp's linear part's translation (``register_surfaces`` ``align_centroids``).
    source_diameter : float, mm
    limits : SurfaceReviewLimits

    Returns
    -------
    list of Finding
        Empty, or one with figure ``"translation_fraction"``.
    """
    length = float(np.linalg.norm(np.asarray(translation, float)))
    fraction = length / source_diameter if source_diameter > 0 else math.inf
    if not length or fraction <= limits.max_translation_fraction:
        return []
    message = (f"SOURCE was moved {length:.3g} mm by the centroids' translation to meet TARGET, "
               f"{100 * fraction:.0f} % of its diameter (limit {100 * limits.max_translation_fraction:g} %): "
               "surfaces from one frame are probably in different ones (RAS against LPS: a GIFTI converted to "
               "another format keeps RAS, mirrored in x and y as LPS), and the warp then pairs mirrored points; "
               "check both files' frames.")
    return [Finding(None, "translation_fraction", fraction, limits.max_translation_fraction, message)]


def review_landmarks(error: np.ndarray, target_diameter: float,
                     limits: SurfaceReviewLimits = SurfaceReviewLimits(), *,
                     off_surface: np.ndarray | None = None) -> list[Finding]:
    """Findings when the warped source landmarks end a mean of more than
    ``limits.max_landmark_fraction`` of the target's diameter from the target landmarks, or
    when the landmarks lie that far from their surfaces on average.

    Parameters
    ----------
    error : (L,) float ndarray, mm
        ``|tau(p_i) - q_i|`` per landmark pair.
    target_diameter : float, mm
    limits : SurfaceReviewLimits
    off_surface : (L,) float ndarray, mm, optional
        Per pair, the larger of the source landmark's distance to the source surface and
        the target landmark's to the target surface.

    Returns
    -------
    list of Finding
        Empty, or with figures ``"landmark_fraction"`` and ``"landmark_off_surface_fraction"``.
    """
    findings = []
    limit = limits.max_landmark_fraction
    mean = float(np.mean(np.asarray(error, float))) if len(error) else 0.0
    fraction = mean / target_diameter if target_diameter > 0 else math.inf
    if fraction > limit:
        findings.append(Finding(None, "landmark_fraction", fraction, limit, (
            f"the warped SOURCE landmarks end a mean {mean:.3g} mm from the TARGET ones, {100 * fraction:.1f} % of "
            f"its diameter (limit {100 * limit:g} %): the two landmark files probably list their points in another "
            "order, or in another frame than the surfaces; check that row i of each names the same point, in LPS "
            "mm.")))
    if off_surface is not None and len(off_surface):
        off = float(np.mean(np.asarray(off_surface, float)))
        fraction = off / target_diameter if target_diameter > 0 else math.inf
        if fraction > limit:
            findings.append(Finding(None, "landmark_off_surface_fraction", fraction, limit, (
                f"the landmarks lie a mean {off:.3g} mm from their surfaces, {100 * fraction:.1f} % of TARGET's "
                f"diameter (limit {100 * limit:g} %), and the warp bends to carry them: landmarks belong on the "
                "surfaces they mark; check their frame (LPS mm) and that each file goes with its surface.")))
    return findings

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

__all__ = ["SurfaceReviewLimits", "diameter", "review_surface_distance", "review_surface_extents"]


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
    max_extent_ratio : float, default 10.0
        The ratio of the larger diameter to the smaller one of the two
        surfaces.  The same structure in two subjects differs by tens of per
        cent; metres against millimetres gives 1000, centimetres 10.
    """

    max_median_distance_fraction: float = 0.05
    max_extent_ratio: float = 10.0

    def __post_init__(self) -> None:
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


def review_surface_distance(distance: np.ndarray, target_diameter: float,
                            limits: SurfaceReviewLimits = SurfaceReviewLimits(), *, hint: str = "") -> list[Finding]:
    """A finding when the warped source lies far from the target surface.

    Parameters
    ----------
    distance : (N,) float ndarray, mm
        Distance of each warped source vertex to the target surface.
    target_diameter : float, mm
        The target's bounding-box diagonal (:func:`diameter`).
    limits : SurfaceReviewLimits
    hint : str, optional
        A sentence to append (what to check, in the words of the command).

    Returns
    -------
    list of Finding
        Empty, or one finding with figure ``"median_distance_fraction"`` (median distance
        over the target's diameter).
    """
    d = np.asarray(distance, float)
    median = float(np.median(d))
    fraction = median / target_diameter if target_diameter > 0 else math.inf
    if fraction <= limits.max_median_distance_fraction:
        return []
    message = (f"the warped SOURCE vertices lie a median {median:.3g} mm from TARGET, {100 * fraction:.1f} % of its "
               f"diameter (limit {100 * limits.max_median_distance_fraction:g} %): the surfaces are probably in "
               "different frames (RAS against LPS: a GIFTI converted to another format keeps RAS) or units.")
    if hint:
        message += " " + hint
    return [Finding(None, "median_distance_fraction", fraction, limits.max_median_distance_fraction, message)]

"""Tuning by consistency and hold-out (the paper's Section 5 leaves parameter tuning to the user).

Every candidate setting registers A to B and B to A and is scored, in mm, by

* the inverse-consistency error ``mean |tau_BA(tau_AB(x)) - x|`` over A's labels padded
  by the warp's ``pad`` (:mod:`volreg.evaluation.consistency`), the two directions registered
  by :func:`volreg.pipeline.two_way.register_both_ways`;
* a hold-out locational cost: the mean distance from each label's surface vertices,
  carried by the warp, to the same label's surface in the other volume, both ways.  The
  warp is fitted to feature values at octree samples, never at these vertices;
  the distance is to the nearest vertex of the other surface (marching-cubes vertices,
  about half a voxel apart);
* with landmarks, the mean landmark error of both directions.

The score is their sum: the identity warp is perfectly consistent but far from the
other surface, an overfitted warp fits the surfaces but disagrees with its reverse.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from scipy.spatial import cKDTree

from volreg.evaluation.consistency import error_on_grid, padded_region, warp_pad
from volreg.pipeline.two_way import register_both_ways
from volreg.settings import Protocol, replace_settings
from volreg.features.label_surfaces import Surface, label_surfaces
from volreg.errors import RegistrationDiverged, RegistrationInputError
from volreg.grid import LabelVolume

__all__ = ["grid_settings", "holdout_surface_distance", "score_setting", "tune_settings"]


def grid_settings(grid: Mapping[str, Sequence[float]]) -> list[dict[str, float]]:
    """Every combination of the values in ``grid`` (cartesian product, in the keys' order)."""
    keys = list(grid)
    return [dict(zip(keys, values)) for values in itertools.product(*(grid[k] for k in keys))]


def holdout_surface_distance(warp, source: Mapping[int, Surface], target: Mapping[int, Surface]) -> float:
    """Mean over labels of the mean distance (mm) from ``warp(source vertices)`` to the target surface's vertices.

    Only labels with a surface on both sides count; ``nan`` if there is none.
    """
    per_label = []
    for label, surface in source.items():
        if label not in target:
            continue
        distance, _ = cKDTree(target[label].vertices).query(warp(surface.vertices))
        per_label.append(float(distance.mean()))
    return float(np.mean(per_label)) if per_label else float("nan")


def score_setting(
    a: LabelVolume,
    b: LabelVolume,
    protocol: Protocol,
    values: Mapping[str, float],
    *,
    a_surfaces: Mapping[int, Surface],
    b_surfaces: Mapping[int, Surface],
    drive_labels=None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict:
    """Register both ways with ``values`` replacing the protocol's ``[warp]`` settings, and score.

    Returns
    -------
    dict
        The values, ``consistency_mm`` (mean over A's padded labels), ``consistency_p95_mm``,
        ``holdout_mm``, ``landmark_mm`` (or ``None``), ``score_mm`` (their sum) and ``seconds``.
    """
    t0 = time.perf_counter()
    p = replace_settings(protocol, values)
    both = register_both_ways(a, b, protocol=p, drive_labels=drive_labels, landmarks=landmarks)
    forward, backward = both.forward.warp, both.backward.warp
    error = error_on_grid(forward, backward, a)[padded_region(a, warp_pad(forward, a))]
    holdout = 0.5 * (holdout_surface_distance(forward, a_surfaces, b_surfaces)
                     + holdout_surface_distance(backward, b_surfaces, a_surfaces))
    landmark = None
    if landmarks is not None:
        landmark = 0.5 * float(np.linalg.norm(forward(landmarks[0]) - landmarks[1], axis=1).mean()
                               + np.linalg.norm(backward(landmarks[1]) - landmarks[0], axis=1).mean())
    consistency = float(error.mean()) if error.size else 0.0
    return {
        **{k: float(v) for k, v in values.items()},
        "consistency_mm": consistency,
        "consistency_p95_mm": float(np.percentile(error, 95)) if error.size else 0.0,
        "holdout_mm": holdout,
        "landmark_mm": landmark,
        "score_mm": consistency + holdout + (landmark or 0.0),
        "seconds": time.perf_counter() - t0,
    }


def tune_settings(
    a: LabelVolume,
    b: LabelVolume,
    protocol: Protocol,
    grid: Mapping[str, Sequence[float]],
    *,
    drive_labels=None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    on_score: Callable[[int, int, dict, dict], None] | None = None,
) -> tuple[list[dict], int]:
    """Score every combination of the ``grid`` values (:func:`score_setting`) and pick the best.

    Parameters
    ----------
    a, b : LabelVolume
    protocol : Protocol
        Gives every setting the grid does not replace.
    grid : mapping of str to sequence of float
        ``[warp]`` settings and their candidate values (:func:`grid_settings`).
    drive_labels, landmarks
        As :func:`score_setting`.
    on_score : callable, optional
        ``on_score(i, n, values, row)`` after each of the ``n`` settings is scored.

    Returns
    -------
    rows : list of dict
        One :func:`score_setting` row per combination, in :func:`grid_settings` order.
    best : int
        The index of the row with the lowest finite ``score_mm`` (the first of equals).

    Raises
    ------
    RegistrationInputError
        No label has a surface in both volumes: nothing to score the hold-out on.
    RegistrationDiverged
        No setting gave a finite score.
    """
    combos = grid_settings(grid)
    a_surfaces = label_surfaces(a, on_small="warn", smoothing=protocol.surface.smoothing)
    b_surfaces = label_surfaces(b, on_small="warn", smoothing=protocol.surface.smoothing)
    if not set(a_surfaces) & set(b_surfaces):
        # the hold-out distance, and so every score, would be NaN, and the pick arbitrary
        raise RegistrationInputError(
            f"No label has a surface in both volumes (A: {sorted(a_surfaces) or 'none'}, B: {sorted(b_surfaces) or 'none'}; "
            "labels under min_voxels are skipped), so no setting can be scored on the hold-out surface distance; "
            "expected at least one label large enough in both.")
    rows = []
    for i, values in enumerate(combos):
        row = score_setting(a, b, protocol, values, a_surfaces=a_surfaces, b_surfaces=b_surfaces,
                            drive_labels=drive_labels, landmarks=landmarks)
        rows.append(row)
        if on_score is not None:
            on_score(i, len(combos), values, row)
    scored = [i for i, row in enumerate(rows) if np.isfinite(row["score_mm"])]
    if not scored:
        raise RegistrationDiverged(f"None of the {len(rows)} settings gave a finite score; expected at least one "
                                   "(narrow the grid to settings that register this pair).")
    best = min(scored, key=lambda i: rows[i]["score_mm"])
    return rows, best

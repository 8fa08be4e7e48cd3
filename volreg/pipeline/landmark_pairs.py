"""Checks of corresponding landmarks before any work: equal counts, placed points, inside the images,
distinct fixed points.

:func:`check_landmark_pairs` takes the two point sets as
:func:`volreg.io.landmarks.read_landmarks` reads them (unplaced control points kept, as rows of
NaN) and gives the pairs a registration uses, or refuses them in one line naming the file.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

from volreg.errors import UsageError
from volreg.grid import LabelVolume, world_box

__all__ = ["check_landmark_pairs"]


def check_landmark_pairs(a: np.ndarray, b: np.ndarray, paths: tuple[str | os.PathLike[str], str | os.PathLike[str]],
                         fixed: LabelVolume | None = None, moving: LabelVolume | None = None, *,
                         note: Callable[[str], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Corresponding landmarks as a registration uses them, checked.

    Parameters
    ----------
    a, b : ndarray, shape (n, dim)
        Fixed (source) and moving (target) points, world mm (LPS), in corresponding order; an
        unplaced control point is a row of NaN.
    paths : (path-like, path-like)
        The files they were read from, named in the messages.
    fixed, moving : LabelVolume, optional
        Where given, each set's points must have its dimension and lie in its image's extent.
    note : callable, optional
        ``note(message)`` with one line naming the pairs left out because a point is not placed.

    Returns
    -------
    a, b : ndarray, shape (m, dim)
        The pairs with both points placed, world mm (LPS).

    Raises
    ------
    UsageError
        Unequal counts, no pair with both points placed, a point of the wrong dimension or outside
        its image, or two fixed points that coincide; the message begins with ``--landmarks:``.
    """
    if len(a) != len(b):
        raise UsageError(
            f"--landmarks: `{paths[0]}` has {len(a)} points and `{paths[1]}` {len(b)}; "
            "expected the same number, in corresponding order."
        )
    unplaced = np.isnan(a).any(axis=1) | np.isnan(b).any(axis=1)
    if unplaced.any():
        which = ", ".join(str(i + 1) for i in np.flatnonzero(unplaced)[:10])
        if unplaced.all():
            raise UsageError("--landmarks: no pair has both points placed (Slicer positionStatus \"undefined\"); "
                             "expected at least one placed pair.")
        if note is not None:
            note(f"--landmarks: left out {int(unplaced.sum())} pair(s) with a control point not placed "
                 f"(Slicer positionStatus \"undefined\"): {which}.")
        a, b = a[~unplaced], b[~unplaced]
    for points, volume, path, role in ((a, fixed, paths[0], "first"), (b, moving, paths[1], "second")):
        if volume is not None:
            _check_inside(points, volume, path, role)
    if len(a) > 1:
        _check_distinct(a, fixed, paths[0])
    return a, b


def _check_inside(points: np.ndarray, volume: LabelVolume, path, role: str) -> None:
    """Refuse points of another dimension than ``volume``'s, or outside its image's extent."""
    if points.shape[1] != volume.ndim:
        raise UsageError(f"--landmarks: `{path}` holds {points.shape[1]}-D points for a {volume.ndim}-D image.")
    lo, hi = world_box(volume)
    outside = np.flatnonzero(np.any((points < lo) | (points > hi), axis=1))
    if outside.size:
        i = int(outside[0])
        raise UsageError(
            f"--landmarks: point {i + 1} of `{path}` ({', '.join(f'{v:.1f}' for v in points[i])} mm) lies outside the "
            f"{role} image's extent ({np.round(lo, 1).tolist()}..{np.round(hi, 1).tolist()} mm LPS); expected "
            "points inside it (check the file's coordinate system: LPS or RAS)."
        )


def _check_distinct(a: np.ndarray, fixed: LabelVolume | None, path) -> None:
    """Refuse two fixed points that coincide: one fixed point cannot be sent to two places, nor
    pinned twice (the landmark start's kernel system would be singular)."""
    from scipy.spatial import cKDTree

    tol, within = (0.1 * float(np.min(fixed.spacing)), "within a tenth of a voxel") if fixed is not None \
        else (1e-3, "within 1 micrometre")
    close = sorted(cKDTree(a).query_pairs(tol))
    if close:
        i, j = close[0]
        raise UsageError(
            f"--landmarks: points {i + 1} and {j + 1} of `{path}` coincide "
            f"({', '.join(f'{v:.2f}' for v in a[i])} mm, {within}); expected distinct "
            f"{'fixed' if fixed is not None else 'source'} landmarks (remove the repeated pair)."
        )

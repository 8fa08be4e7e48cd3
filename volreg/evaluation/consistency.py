"""The consistency test (paper Section 5): warp forward and back, the original must come back.

Registering A to B gives ``tau_AB`` (an A point to its B partner, the pull-back
of ``volreg register A B``); registering B to A gives ``tau_BA``.  If both are
right, ``tau_BA(tau_AB(x)) = x`` for every ``x`` near A's objects; the
inverse-consistency error ``|tau_BA(tau_AB(x)) - x|`` (mm) measures how far
they disagree.  An identity warp is perfectly consistent and useless, so the
error is reported beside the registration's accuracy, never alone.

Also here: the padded neighbourhood of a label volume's objects (where the
error is summarised) and the round trip of A's labels through B's grid.
Pure functions on arrays; the command is :mod:`volreg._consistency_cli`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy import ndimage

from volreg.warp.field import displacement_on_grid
from volreg.evaluation.metrics import dice
from volreg.warp.resample import resample_labels
from volreg.grid import LabelVolume

__all__ = [
    "padded_region",
    "round_trip_error",
    "error_summary",
    "error_on_grid",
    "round_trip_labels",
    "round_trip_dice",
]

ProgressCallback = Callable[[str, int, int], None]


def padded_region(volume: LabelVolume, pad: float) -> np.ndarray:
    """Voxels of the objects (non-zero labels) and of the background within ``pad`` mm of them.

    Parameters
    ----------
    volume : LabelVolume
    pad : float, mm
        ``>= 0``; distances use the voxel spacing (Euclidean distance transform).

    Returns
    -------
    (*volume.shape) bool ndarray
    """
    if not (np.isfinite(pad) and pad >= 0):
        raise ValueError(f"Expected `pad` >= 0 mm, got {pad!r}.")
    objects = volume.array != 0
    if not objects.any():
        return objects
    distance = ndimage.distance_transform_edt(~objects, sampling=volume.spacing)
    return distance <= pad


def round_trip_error(forward, backward, points: np.ndarray, *, progress: ProgressCallback | None = None) -> np.ndarray:
    """``|backward(forward(x)) - x|`` at ``points``.

    Parameters
    ----------
    forward, backward : KernelWarp (or anything callable on (N, D) points)
        ``forward`` maps A points into B, ``backward`` B points into A.
    points : (N, D) float ndarray, mm (A's world frame, LPS)

    Returns
    -------
    (N,) float ndarray, mm
    """
    there = forward(points, progress=progress)
    back = backward(there, progress=progress)
    return np.linalg.norm(back - points, axis=1)


def error_summary(errors: np.ndarray, voxel: float | None = None) -> dict:
    """Mean, median, 95th percentile and maximum of errors (mm, and in voxels if ``voxel`` mm is given).

    An empty input gives ``count`` 0 and ``None`` for the statistics.
    """
    errors = np.asarray(errors, dtype=float).ravel()
    out: dict = {"count": int(errors.size)}
    keys = ("mean", "median", "p95", "max")
    if errors.size == 0:
        out.update({f"{k}_mm": None for k in keys})
        return out
    stats = (errors.mean(), np.median(errors), np.percentile(errors, 95), errors.max())
    out.update({f"{k}_mm": float(v) for k, v in zip(keys, stats)})
    if voxel is not None:
        out.update({f"{k}_voxels": float(v) / voxel for k, v in zip(keys, stats)})
    return out


def _union_box(warps) -> tuple[np.ndarray, np.ndarray] | None:
    boxes = [w.bounds() for w in warps if hasattr(w, "bounds")]
    boxes = [b for b in boxes if b is not None]
    if not boxes:
        return None
    return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)


def error_on_grid(
    forward,
    backward,
    grid: LabelVolume,
    *,
    chunk: int = 1 << 18,
    progress: ProgressCallback | None = None,
) -> np.ndarray:
    """The inverse-consistency error ``|backward(forward(x)) - x|`` at every voxel centre of ``grid``.

    Only voxels inside the union of the two warps' support boxes can have a
    non-zero error (outside both, both warps are the identity); only they are
    evaluated.

    Returns
    -------
    (*grid.shape) float ndarray, mm
    """
    out = np.zeros(int(np.prod(grid.shape)))
    box = _union_box((forward, backward))
    window = None if box is None else grid.index_window(*box)
    if window is None:
        return out.reshape(grid.shape)
    sub_shape = tuple(s.stop - s.start for s in window)
    start = np.array([s.start for s in window])
    total = int(np.prod(sub_shape))
    for s in range(0, total, chunk):
        index = np.stack(np.unravel_index(np.arange(s, min(s + chunk, total)), sub_shape), axis=1) + start
        points = grid.index_to_world(index)
        out[np.ravel_multi_index(tuple(index.T), grid.shape)] = round_trip_error(forward, backward, points)
        if progress is not None:
            progress("round trip", min(s + chunk, total), total)
    return out.reshape(grid.shape)


def round_trip_labels(
    a: LabelVolume,
    b_grid: LabelVolume,
    forward,
    backward,
    *,
    progress: ProgressCallback | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """A's labels warped onto B's grid and back onto A's grid.

    With pull-back warps, A on B's grid samples A at ``backward(y)`` for every
    B voxel ``y``; back on A's grid it samples that at ``forward(x)``.  Both
    resamplings are label-preserving (:func:`volreg.resample.resample_labels`).

    Returns
    -------
    on_b : (*b_grid.shape) ndarray, A's dtype
    back : (*a.shape) ndarray, A's dtype
    """
    at_b = b_grid.grid_points() + displacement_on_grid(backward, b_grid)
    on_b = resample_labels(a, at_b, method="label", progress=progress).astype(a.array.dtype, copy=False)
    at_a = a.grid_points() + displacement_on_grid(forward, a)
    back = resample_labels(b_grid.with_array(on_b), at_a, method="label", progress=progress)
    back = back.astype(a.array.dtype, copy=False)
    return on_b, back


def round_trip_dice(a: np.ndarray, back: np.ndarray, labels) -> dict[int, float]:
    """Dice per label between A and its round trip (same grid)."""
    return {int(v): dice(a == v, back == v) for v in labels}

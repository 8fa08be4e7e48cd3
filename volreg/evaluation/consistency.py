"""The consistency test (paper Section 5): warp forward and back, the original must come back.

Registering A to B gives ``tau_AB`` (an A point to its B partner, the pull-back
of ``volreg register A B``); registering B to A gives ``tau_BA``.  If both are
right, ``tau_BA(tau_AB(x)) = x`` for every ``x`` near A's objects; the
inverse-consistency error ``|tau_BA(tau_AB(x)) - x|`` (mm) measures how far
they disagree.  An identity warp is perfectly consistent and useless, so the
error is reported beside the registration's accuracy, never alone.

Also here: the padded neighbourhood of a label volume's objects (where the
error is summarised) and the round trip of A's labels through B's grid.
:func:`consistency_test` gives the test's figures for a pair of warps;
:func:`volreg.outputs.consistency.write_consistency_test` registers both ways (or takes both
warps), runs the test and writes its outputs, all or nothing, as ``volreg consistency`` does.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy import ndimage

from volreg.warp.field import displacement_on_grid, linear_displacement_on_grid, support_slices
from volreg.warp.model import linear_outside
from volreg.evaluation.metrics import dice
from volreg.warp.resample import resample_labels
from volreg.grid import LabelVolume, as_grid

__all__ = [
    "consistency_test",
    "padded_region",
    "round_trip_error",
    "error_summary",
    "error_on_grid",
    "round_trip_labels",
    "round_trip_dice",
    "warp_pad",
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


def error_on_grid(
    forward,
    backward,
    grid: LabelVolume,
    *,
    chunk: int = 1 << 18,
    progress: ProgressCallback | None = None,
) -> np.ndarray:
    """The inverse-consistency error ``|backward(forward(x)) - x|`` at every voxel centre of ``grid``.

    Outside the box where the chain ``backward(forward(x))`` is linear
    (:func:`~volreg.warp.model.linear_outside`: ``forward``'s support box and the
    preimage of ``backward``'s under ``forward``'s linear part) the round trip
    is ``M x`` with ``M`` the product of the two linear parts, and the error
    ``|M x - x|`` is filled in closed form (zero without linear parts); only
    the voxels inside the box are evaluated.  A map without ``bounds()`` makes
    every voxel evaluated.

    Returns
    -------
    (*grid.shape) float ndarray, mm
    """
    grid = as_grid(grid, "grid")
    chain = (forward, backward)
    _, linear = linear_outside(chain, dim=grid.ndim)
    window = support_slices(chain, grid)
    if linear.is_identity or (window is not None and all(
            s.start == 0 and s.stop == n for s, n in zip(window, grid.shape))):
        out = np.zeros(int(np.prod(grid.shape)))
    else:
        out = np.linalg.norm(linear_displacement_on_grid(linear, grid), axis=-1).ravel()
    if window is None:
        return out.reshape(grid.shape)
    for part in grid.chunks(chunk, window):
        out[part.flat] = round_trip_error(forward, backward, part.points)
        if progress is not None:
            progress("round trip", part.done, part.total)
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


def warp_pad(warp, volume: LabelVolume) -> float:
    """The padding of the warp volume X that ``warp`` was fitted in, mm: where the consistency error counts.

    :func:`~volreg.warp.fit.fit_warp` records the pad it used (``warp.settings["pad"]``:
    the protocol's ``pad``, or 10 % of the source diameter when that is unset), so every
    fitted warp, saved or not, gives it.  A warp that records none (made by hand, or a
    model file written without it) gets 10 % of ``volume``'s largest extent.  The pad is
    a distance in ``volume``'s (fixed) frame, where the kernel centres lie: a linear
    part of the warp does not change it.

    Parameters
    ----------
    warp : KernelWarp
    volume : LabelVolume
        The volume whose points the warp maps (A for the forward warp).

    Returns
    -------
    float, mm
    """
    pad = warp.settings.get("pad")
    if isinstance(pad, (int, float)) and pad >= 0:
        return float(pad)
    return 0.1 * float(np.max(np.array(volume.shape) * volume.spacing))


def consistency_test(
    a: LabelVolume,
    b: LabelVolume,
    forward,
    backward,
    *,
    progress: ProgressCallback | None = None,
) -> tuple[dict, np.ndarray]:
    """The consistency test (paper Section 5): how far ``backward(forward(x))`` lands from ``x``.

    Parameters
    ----------
    a, b : LabelVolume
        The two label volumes; the error is measured in A's world frame (LPS mm).
    forward : KernelWarp
        Maps A points to their B partners (``volreg register A B``).
    backward : KernelWarp
        Maps B points to their A partners (``volreg register B A``).
    progress : callable, optional
        ``progress(stage, done, total)``.

    Returns
    -------
    report : dict
        ``definition``; ``voxel_mm`` (A's mean spacing, the unit of the ``*_voxels``
        figures); ``pad_mm`` (:func:`warp_pad` of ``forward``); ``region`` (the error over
        A's objects padded by ``pad_mm``: :func:`error_summary`); ``surface_vertices`` (at
        the vertices of A's label surfaces, all labels together); ``mean_round_trip_dice``;
        ``labels`` (per label of A: the error over its voxels and at its surface vertices,
        and the Dice of A's labels against their round trip through B's grid).
    error : (*a.shape) float ndarray, mm
        ``|backward(forward(x)) - x|`` at every voxel centre of A.
    """
    from volreg.features.label_surfaces import label_surfaces

    voxel = float(np.mean(a.spacing))
    pad = warp_pad(forward, a)
    error = error_on_grid(forward, backward, a, progress=progress)
    region = padded_region(a, pad)
    labels = [int(v) for v in a.labels()]
    meshes = label_surfaces(a, labels, on_small="warn")
    _, back = round_trip_labels(a, b, forward, backward, progress=progress)
    dice = round_trip_dice(a.array, back, labels)
    per_label = {}
    all_vertex_errors = []
    for v in labels:
        entry = {"voxels": error_summary(error[a.array == v], voxel), "round_trip_dice": dice[v]}
        if v in meshes:
            vertex_error = np.linalg.norm(backward(forward(meshes[v].vertices)) - meshes[v].vertices, axis=1)
            entry["surface_vertices"] = error_summary(vertex_error, voxel)
            all_vertex_errors.append(vertex_error)
        per_label[str(v)] = entry
    report = {
        "definition": "|tau_BA(tau_AB(x)) - x| for x in A's world frame (LPS mm); voxels = mm / mean spacing of A",
        "voxel_mm": voxel,
        "pad_mm": pad,
        "region": error_summary(error[region], voxel),
        "surface_vertices": error_summary(np.concatenate(all_vertex_errors) if all_vertex_errors else [], voxel),
        "mean_round_trip_dice": float(np.mean(list(dice.values()))) if dice else None,
        "labels": per_label,
    }
    return report, error

"""Resampling images through a warp: label-preserving for labels, linear or B-spline otherwise.

All functions take the *positions* at which to sample -- world points (LPS mm),
typically ``tau(x) = x + u(x)`` at the voxel centres ``x`` of the fixed grid
(:func:`volreg.warp.field.displacement_on_grid`) -- and the image to sample, with its
geometry.  Points outside the image get the background (0).

Label interpolation
-------------------
``"label"`` (the default for labels): for each label, a signed distance map
(mm, negative inside: :func:`signed_distance_map`, the Euclidean distance
transform of the mask and of its complement) is interpolated
linearly at the points; a point takes the label whose distance is most
negative, and the background where every distance is positive.  (Only points
whose 2^D interpolation voxels hold two values or more need the maps, and there
only distances up to one voxel diagonal: the maps are computed clipped to that,
which leaves every comparison as it was.)  The boundary
then runs half-way between voxel centres of different labels and moves
smoothly with the warp, instead of the staircase of nearest neighbour; only
label values present in the input can come out, in the input's dtype, and at
voxel centres (the identity) the input comes back bit for bit.  ``"nearest"``
is nearest neighbour.  The same scheme as ITK's label-Gaussian interpolator and
greedy's ``-ri LABEL``, with linear instead of Gaussian-smoothed indicators.
"""

from __future__ import annotations

from typing import Callable, Literal

import numpy as np
from scipy import ndimage

from volreg.features.distance_maps import clipped_signed_distance
from volreg.grid import Grid, GridLike, LabelVolume, as_grid
from volreg.kernels.grid import rows_within

__all__ = ["resample_labels", "resample_labels_at", "resample_image", "signed_distance_map"]

ProgressCallback = Callable[[str, int, int], None]


#: Stand-in for an infinite distance (mm): no boundary within the array.
FAR_MM = 1e9


def signed_distance_map(mask: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Signed distance (mm) of each voxel centre to the mask's boundary: negative inside.

    ``d = edt(outside) - edt(inside)``: an inside voxel gets minus its distance
    to the nearest outside voxel, an outside voxel its distance to the nearest
    inside voxel, so that linear interpolation crosses zero half-way between
    an inside and an outside voxel.

    Parameters
    ----------
    mask : (n_i, n_j[, n_k]) bool ndarray
    spacing : (D,) float ndarray, mm

    Returns
    -------
    float32 ndarray of ``mask.shape``, mm
    """
    mask = np.asarray(mask, dtype=bool)
    outside = ndimage.distance_transform_edt(~mask, sampling=spacing) if mask.any() else np.full(mask.shape, np.inf)
    inside = ndimage.distance_transform_edt(mask, sampling=spacing) if (~mask).any() else np.full(mask.shape, np.inf)
    # A mask that is empty or fills the whole array has no boundary: a large finite distance
    # (not +-inf, which linear interpolation turns into NaN, so that the label would never win).
    return np.clip(outside - inside, -FAR_MM, FAR_MM).astype(np.float32)


def _indices(image: LabelVolume | Grid, points: np.ndarray) -> np.ndarray:
    """Continuous indices of world ``points`` (..., D) in ``image``, flattened to (N, D)."""
    points = np.asarray(points, dtype=float)
    if points.shape[-1] != image.ndim:
        raise ValueError(f"Expected `points` with a last axis of length {image.ndim}, got shape {points.shape}.")
    return image.world_to_index(points.reshape(-1, image.ndim))


def _mixed_stencils(array: np.ndarray, index: np.ndarray, points: np.ndarray, out: np.ndarray,
                    chunk: int = 1 << 20) -> np.ndarray:
    """Give the points whose 2^D interpolation voxels all hold one value that value; return the others.

    Parameters
    ----------
    array : (n_0, ..., n_{D-1}) ndarray
        The labels.
    index : (N, D) float ndarray
        Continuous indices of all points.
    points : (M,) int ndarray
        The rows of ``index`` to look at (inside the image).
    out : (N,) ndarray
        Written at the points whose stencil holds a single value.

    Returns
    -------
    (K,) int ndarray
        The rows of ``points`` whose stencil holds two values or more, in their order.
    """
    shape = array.shape
    strides = [int(np.prod(shape[d + 1:], dtype=np.int64)) for d in range(array.ndim)]  # C order, in voxels
    # Each corner's voxel is taken by its flat position: the lowest corner's, plus per axis a step
    # of one stride or none (clamped at the image's edges, as the interpolation is). Integer sums
    # of columns instead of gathering D index arrays per corner: the 3 mm frog's 1.8 M points in
    # 0.09 s instead of 0.19 s.
    values = np.ascontiguousarray(array).reshape(-1)
    mixed = []
    for s in range(0, len(points), chunk):
        rows = points[s : s + chunk]
        idx = index[rows]
        flat = np.zeros(len(rows), dtype=np.int64)
        offsets: list = [None]  # of the 2^D corners from the lowest one; None: the lowest itself
        for d in range(array.ndim):
            low = np.floor(idx[:, d]).astype(np.int64)
            high = np.minimum(low + 1, shape[d] - 1)
            np.maximum(high, 0, out=high)
            np.clip(low, 0, shape[d] - 1, out=low)
            flat += low * strides[d]
            step = (high - low) * strides[d]
            offsets += [step if o is None else o + step for o in offsets]
        first = values.take(flat)
        same = np.ones(len(rows), dtype=bool)
        for o in offsets[1:]:
            same &= values.take(flat + o) == first
        out[rows[same]] = first[same]
        mixed.append(rows[~same])
    return np.concatenate(mixed) if mixed else points


def resample_labels(
    image: LabelVolume,
    points: np.ndarray,
    *,
    method: Literal["label", "nearest"] = "label",
    margin: int = 2,
    progress: ProgressCallback | None = None,
) -> np.ndarray:
    """Sample a label volume at world points, keeping label identity.

    Parameters
    ----------
    image : LabelVolume
        The labels to sample (e.g. the moving image).
    points : (..., D) float ndarray, LPS mm
        Where to sample (e.g. ``tau(x)`` on the fixed grid).
    method : {"label", "nearest"}
        Per-label signed distances interpolated linearly, then the most
        negative wins (see the module notes); or nearest neighbour.
    margin : int
        Voxels around each label's bounding box where its distance map is
        computed (beyond, the label cannot win).
    progress : callable, optional
        ``progress("resample labels", done, total)`` per label.

    Returns
    -------
    ndarray of ``points.shape[:-1]``, ``image.array.dtype``
        Only values present in ``image`` (and 0) occur.
    """
    if method not in ("label", "nearest"):  # before the indices are computed
        raise ValueError(f"Expected `method` 'label' or 'nearest', got {method!r}.")
    return resample_labels_at(image, _indices(image, points), method=method, margin=margin,
                              progress=progress).reshape(np.shape(points)[:-1])


def resample_labels_at(
    image: LabelVolume,
    index: np.ndarray,
    *,
    method: Literal["label", "nearest"] = "label",
    margin: int = 2,
    progress: ProgressCallback | None = None,
) -> np.ndarray:
    """:func:`resample_labels` at continuous voxel indices of ``image`` rather than world points.

    Parameters
    ----------
    image : LabelVolume
    index : (N, D) float ndarray
        Continuous indices into ``image`` (voxel ``i`` is centred at ``i``), e.g. from
        :func:`volreg.warp.field.indices_through`.
    method, margin, progress
        As :func:`resample_labels`.

    Returns
    -------
    (N,) ndarray, ``image.array.dtype``
    """
    if method not in ("label", "nearest"):
        raise ValueError(f"Expected `method` 'label' or 'nearest', got {method!r}.")
    index = np.asarray(index, dtype=float)
    if index.ndim != 2 or index.shape[1] != image.ndim:
        raise ValueError(f"Expected `index` of shape (N, {image.ndim}), got {index.shape}.")
    array = image.array
    # The image covers its voxels: continuous indices in [-1/2, n - 1/2] (as ITK).
    size = np.array(image.shape)
    valid = rows_within(index, np.full(image.ndim, -0.5), size - 0.5)
    if method == "nearest":
        nearest = np.clip(np.floor(index[valid] + 0.5).astype(np.int64), 0, size - 1)
        out = np.zeros(len(index), dtype=array.dtype)
        out[valid] = array[tuple(nearest.T)]
        return out

    out = np.zeros(len(index), dtype=array.dtype)
    best = np.zeros(len(index), dtype=np.float32)  # a point is a label's only where its distance < 0
    boxes = image.label_boxes()
    labels = image.labels()
    # A point whose linear stencil holds one value only takes that value: that label's distance is
    # negative at every corner, every other label's positive (the background: all positive). Only
    # the other points, near a boundary, need the distance maps below.
    slab_order = _mixed_stencils(array, index, np.flatnonzero(valid), out)
    # Those points' interpolation voxels lie within one voxel diagonal of a voxel of another
    # value: the distances of a label that one of them holds are at most that long at all of
    # them, and a label none of them holds is positive at all of them. Distances clipped to
    # the diagonal (a little more, for rounding) therefore give the same labels as the full
    # maps, near the boundaries only (the 1 mm phantom's two labels: 0.17 s instead of 2.3 s).
    diagonal = 1.001 * float(np.linalg.norm(image.spacing))
    # With many labels, the points sorted by their first index: each label's candidates
    # are then one slab of them, and small labels do not each scan every point (500 labels at
    # 1.5 mm: 14 s instead of 29 s). With few labels the sort would cost more than it saves.
    if len(labels) > 8:
        slab_order = slab_order[np.argsort(index[slab_order, 0], kind="stable")]
    # Their indices gathered once in that order: each label's candidates are then a slice.
    slab_index = index[slab_order]
    slab_key = slab_index[:, 0] if len(labels) > 8 else None
    for n, value in enumerate(labels):
        box = boxes[int(value)]
        lo = np.array([max(s.start - margin, 0) for s in box])
        hi = np.array([min(s.stop + margin, size) for s, size in zip(box, image.shape)])
        # Points whose linear stencil touches the crop.
        first, stop = 0, len(slab_order)
        if slab_key is not None:
            first = np.searchsorted(slab_key, lo[0] - 1, side="right")
            stop = np.searchsorted(slab_key, hi[0], side="left")
        candidates = slab_index[first:stop]
        touches = rows_within(candidates, lo - 1, hi, closed=False)
        near = slab_order[first:stop][touches]
        if near.size:
            crop = array[tuple(slice(a, b) for a, b in zip(lo, hi))]
            sdf = clipped_signed_distance(crop == value, image.spacing, diagonal)
            at = (candidates[touches] - lo).T
            d = ndimage.map_coordinates(sdf, at, order=1, mode="nearest")
            win = d < best[near]
            sel = near[win]
            best[sel] = d[win]
            out[sel] = value
        if progress is not None:
            progress("resample labels", n + 1, len(labels))
    return out


def resample_image(
    array: np.ndarray,
    geometry: GridLike,
    points: np.ndarray,
    *,
    order: Literal[0, 1, 3] = 1,
    fill: float = 0.0,
) -> np.ndarray:
    """Sample an intensity image at world points (nearest, linear or cubic B-spline).

    Parameters
    ----------
    array : (n_i, n_j[, n_k]) real ndarray
        The image values, ITK index order.
    geometry : Grid, LabelVolume or (shape, affine)
        The image's grid: origin, spacing and direction (a volume's array is not used).
    points : (..., D) float ndarray, LPS mm
    order : {0, 1, 3}
        Interpolation order (``scipy.ndimage.map_coordinates``).
    fill : float
        Value outside the image.

    Returns
    -------
    float64 ndarray of ``points.shape[:-1]``
        NaN and Inf voxels reach only the points within one voxel of them (as with
        linear interpolation), also with ``order=3``, whose prefilter would otherwise
        spread them over the whole image.
    """
    if order not in (0, 1, 3):
        raise ValueError(f"Expected `order` 0, 1 or 3, got {order!r}.")
    geometry = as_grid(geometry, "geometry")
    array = np.asarray(array)
    if array.shape != geometry.shape:
        raise ValueError(f"Expected `array` of shape {geometry.shape} (the grid of `geometry`), got {array.shape}.")
    shape = np.shape(points)[:-1]
    index = _indices(geometry, points)
    if order == 0:
        index = np.floor(index + 0.5)
    array = array.astype(np.float64, copy=False)
    missing = ~np.isfinite(array)
    if order == 3 and missing.any():
        # The B-spline prefilter is global: one NaN would spread over the whole image.  Fill
        # non-finite voxels from their nearest finite neighbour, interpolate, and give the
        # points next to a non-finite voxel what linear interpolation gives (NaN or Inf there).
        if missing.all():
            filled = np.zeros_like(array)
        else:
            nearest = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
            filled = array[tuple(nearest)]
        values = ndimage.map_coordinates(filled, index.T, order=3, mode="constant", cval=fill, prefilter=True)
        touched = ndimage.map_coordinates(missing.astype(np.float64), index.T, order=1, mode="constant", cval=0.0) > 0
        values[touched] = ndimage.map_coordinates(array, index.T[:, touched], order=1, mode="constant", cval=fill)
        return values.reshape(shape)
    values = ndimage.map_coordinates(array, index.T, order=max(order, 1) if order else 0,
                                     mode="constant", cval=fill, prefilter=order == 3)
    return values.reshape(shape)

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

``"gaussian"`` is that scheme with Gaussian-smoothed indicators: each label's mask
blurred by a Gaussian of :data:`GAUSSIAN_SIGMA` times the voxels' geometric-mean
spacing and read at the points by cubic B-spline; a point takes the label whose
blurred indicator is largest, the background's (one minus the labels' sum)
included.  Between voxel centres it reads a boundary from several voxels rather
than two, so it tells better which side of a boundary a point lies on: on labels
sampled from analytic shapes on oblique grids and read at random points, it gives
the wrong label at fewer points than ``"label"`` (and ``"label"`` at fewer than
nearest neighbour).  At voxel centres the input comes back, as with
``"label"``.  Ties (a boundary through the point) go to the lower label value, or
to a preferred value given per point (:func:`resample_labels_at`, ``prefer``).
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

#: Standard deviation of the ``"gaussian"`` label interpolation's blur, in voxels (of the
#: geometric-mean spacing). With it the registrations that read one volume's labels on the
#: other's coarser grid end nearest the truth (`bench_pose.py`), and labels sampled from analytic
#: shapes are misread at about as few random points as with the blur that misreads the fewest.
GAUSSIAN_SIGMA = 0.8

#: ``"gaussian"`` with ``prefer``: a preferred value whose blurred indicator is within this of
#: the largest is taken (a tie: the boundary passes within about a thousandth of a voxel).
TIE = 1e-3

#: How close (voxels, on every axis) a point must be to a voxel centre to take that voxel's
#: label as it is under ``"gaussian"``.
_AT_CENTRE = 1e-3


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
    # of columns instead of gathering D index arrays per corner: about half the time.
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
    method: Literal["label", "nearest", "gaussian"] = "label",
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
    method : {"label", "nearest", "gaussian"}
        Per-label signed distances interpolated linearly, then the most
        negative wins (see the module notes); nearest neighbour; or per-label
        Gaussian-blurred indicators, the largest wins.
    margin : int
        Voxels around each label's bounding box where its distance map is
        computed (beyond, the label cannot win); ``"gaussian"`` adds the blur's reach.
    progress : callable, optional
        ``progress("resample labels", done, total)`` per label.

    Returns
    -------
    ndarray of ``points.shape[:-1]``, ``image.array.dtype``
        Only values present in ``image`` (and 0) occur.
    """
    if method not in ("label", "nearest", "gaussian"):  # before the indices are computed
        raise ValueError(f"Expected `method` 'label', 'nearest' or 'gaussian', got {method!r}.")
    return resample_labels_at(image, _indices(image, points), method=method, margin=margin,
                              progress=progress).reshape(np.shape(points)[:-1])


def resample_labels_at(
    image: LabelVolume,
    index: np.ndarray,
    *,
    method: Literal["label", "nearest", "gaussian"] = "label",
    margin: int = 2,
    progress: ProgressCallback | None = None,
    prefer: np.ndarray | None = None,
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
    prefer : (N,) integer ndarray, optional
        ``"gaussian"`` only: at each point a value to take on a tie, where its blurred indicator
        is within :data:`TIE` of the largest (e.g. another volume's label at the same place).

    Returns
    -------
    (N,) ndarray, ``image.array.dtype``
    """
    if method not in ("label", "nearest", "gaussian"):
        raise ValueError(f"Expected `method` 'label', 'nearest' or 'gaussian', got {method!r}.")
    index = np.asarray(index, dtype=float)
    if index.ndim != 2 or index.shape[1] != image.ndim:
        raise ValueError(f"Expected `index` of shape (N, {image.ndim}), got {index.shape}.")
    if prefer is not None and (method != "gaussian" or np.shape(prefer) != (len(index),)):
        raise ValueError(f"Expected `prefer` of shape ({len(index)},) with method 'gaussian', got shape "
                         f"{np.shape(prefer)} with {method!r}.")
    array = image.array
    # The image covers its voxels: continuous indices in [-1/2, n - 1/2] (as ITK).
    size = np.array(image.shape)
    valid = rows_within(index, np.full(image.ndim, -0.5), size - 0.5)
    out = np.zeros(len(index), dtype=array.dtype)
    if method == "nearest":
        nearest = np.clip(np.floor(index[valid] + 0.5).astype(np.int64), 0, size - 1)
        out[valid] = array[tuple(nearest.T)]
        return out

    # A point whose linear stencil holds one value only takes that value: that label's distance is
    # negative at every corner, every other label's positive (the background: all positive). Only
    # the other points, near a boundary, need the distance maps below.
    near_boundary = _mixed_stencils(array, index, np.flatnonzero(valid), out)
    blur = None
    if method == "gaussian":
        # At a voxel centre the voxel's own label, as "label" gives it there.
        near_boundary = _take_at_centres(array, index, near_boundary, out)
        blur = _Blur.of(image, len(index), prefer is not None)
        margin = max(margin, blur.margin)
    best, near_boundary = _read_labels(image, index, near_boundary, margin, blur, prefer, out, progress)
    if blur is not None:
        blur.finish(array, index, near_boundary, best, prefer, out)
    return out


def _take_at_centres(array: np.ndarray, index: np.ndarray, rows: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Give the ``rows`` of ``index`` within :data:`_AT_CENTRE` of a voxel centre that voxel's
    value (in ``out``); return the other rows."""
    near_centre = np.all(np.abs(index[rows] - np.round(index[rows])) < _AT_CENTRE, axis=1)
    centres = rows[near_centre]
    out[centres] = array[tuple(np.clip(np.round(index[centres]).astype(np.int64), 0,
                                       np.array(array.shape) - 1).T)]
    return rows[~near_centre]


class _Blur:
    """The ``"gaussian"`` reading's blur and the sums it keeps over the labels.

    ``total``: the labels' blurred indicators summed per point (the background's is one minus
    it: the blur and the spline are linear); ``preferred``: the blurred indicator of each point's
    preferred value, where one is given.
    """

    def __init__(self, sigma: float, margin: int, total: np.ndarray, preferred: np.ndarray | None) -> None:
        self.sigma, self.margin, self.total, self.preferred = sigma, margin, total, preferred

    @classmethod
    def of(cls, image: LabelVolume, n: int, with_prefer: bool) -> "_Blur":
        """The blur of ``image`` (:data:`GAUSSIAN_SIGMA`) for ``n`` points, and the margin (voxels)
        around a label's box that its reach needs."""
        sigma = GAUSSIAN_SIGMA * float(np.exp(np.mean(np.log(image.spacing))))  # mm
        margin = int(np.ceil(4 * sigma / np.min(image.spacing))) + 2
        return cls(sigma, margin, np.zeros(n, dtype=np.float32), np.zeros(n, dtype=np.float32) if with_prefer else None)

    def finish(self, array: np.ndarray, index: np.ndarray, rows: np.ndarray, best: np.ndarray,
               prefer: np.ndarray | None, out: np.ndarray) -> None:
        """At ``rows``, the background where its blurred indicator is the largest, then the
        preferred values on ties (in place in ``out``)."""
        rest = 1.0 - self.total[rows]  # the background's blurred indicator
        background = rows[rest > -best[rows]]
        out[background] = 0
        if self.preferred is not None:
            wanted = prefer[rows]
            lead = np.maximum(-best[rows], rest) - np.where(wanted == 0, rest, self.preferred[rows])
            tied = lead < TIE
            out[rows[tied]] = wanted[tied]
            _prefer_between_centres(array, index, rows, prefer, out)


def _read_labels(image: LabelVolume, index: np.ndarray, rows: np.ndarray, margin: int, blur: _Blur | None,
                 prefer: np.ndarray | None, out: np.ndarray,
                 progress: ProgressCallback | None) -> tuple[np.ndarray, np.ndarray]:
    """Label by label, the label whose distance (or minus blurred indicator, with ``blur``) is
    most negative at the ``rows`` of ``index`` (in place in ``out``).

    Parameters
    ----------
    image : LabelVolume
    index : (N, D) float ndarray
        Continuous indices into ``image``.
    rows : (K,) int ndarray
        The rows to read: those near a boundary.
    margin : int
        Voxels around each label's box where its map is computed.
    blur : _Blur or None
        ``"gaussian"``: blurred indicators (its sums are updated); None: signed distances.
    prefer : (N,) integer ndarray or None
    out : (N,) ndarray
        Written at the rows where a label wins.
    progress : callable, optional
        ``progress("resample labels", done, total)`` per label.

    Returns
    -------
    best : (N,) float32 ndarray
        The winning distance (or minus blurred indicator) per row, 0 where none is negative.
    rows : (K,) int ndarray
        ``rows`` in the order they were read (by first index where there are many labels).
    """
    array = image.array
    best = np.zeros(len(index), dtype=np.float32)  # a point is a label's only where its distance < 0
    boxes = image.label_boxes()
    labels = image.labels()
    # Those points' interpolation voxels lie within one voxel diagonal of a voxel of another
    # value: the distances of a label that one of them holds are at most that long at all of
    # them, and a label none of them holds is positive at all of them. Distances clipped to
    # the diagonal (a little more, for rounding) therefore give the same labels as the full
    # maps, near the boundaries only, at a fraction of their cost.
    diagonal = 1.001 * float(np.linalg.norm(image.spacing))
    # With many labels, the points sorted by their first index: each label's candidates
    # are then one slab of them, and small labels do not each scan every point. With few
    # labels the sort would cost more than it saves.
    if len(labels) > 8:
        rows = rows[np.argsort(index[rows, 0], kind="stable")]
    # Their indices gathered once in that order: each label's candidates are then a slice.
    slab_index = index[rows]
    slab_key = slab_index[:, 0] if len(labels) > 8 else None
    for n, value in enumerate(labels):
        box = boxes[int(value)]
        lo = np.array([max(s.start - margin, 0) for s in box])
        hi = np.array([min(s.stop + margin, size) for s, size in zip(box, image.shape)])
        # Points whose linear stencil touches the crop.
        first, stop = 0, len(rows)
        if slab_key is not None:
            first = np.searchsorted(slab_key, lo[0] - 1, side="right")
            stop = np.searchsorted(slab_key, hi[0], side="left")
        candidates = slab_index[first:stop]
        touches = rows_within(candidates, lo - 1, hi, closed=False)
        near = rows[first:stop][touches]
        if near.size:
            crop = array[tuple(slice(a, b) for a, b in zip(lo, hi))]
            at = (candidates[touches] - lo).T
            if blur is not None:
                # Minus the blurred indicator, so that the largest wins as the most negative distance.
                blurred = ndimage.gaussian_filter((crop == value).astype(np.float32), blur.sigma / image.spacing,
                                                  mode="nearest")
                d = -ndimage.map_coordinates(blurred, at, order=3, mode="nearest")
                blur.total[near] -= d
                if blur.preferred is not None:
                    mine = prefer[near] == value
                    blur.preferred[near[mine]] = -d[mine]
            else:
                sdf = clipped_signed_distance(crop == value, image.spacing, diagonal)
                d = ndimage.map_coordinates(sdf, at, order=1, mode="nearest")
            win = d < best[near]
            sel = near[win]
            best[sel] = d[win]
            out[sel] = value
        if progress is not None:
            progress("resample labels", n + 1, len(labels))
    return best, rows


def _prefer_between_centres(array: np.ndarray, index: np.ndarray, rows: np.ndarray, prefer: np.ndarray,
                            out: np.ndarray) -> None:
    """At the rows of ``index`` equally near to several voxel centres -- half-way between them
    along some axes, on them along the others, as where a grid of twice the spacing has its
    centres at the corners of eight voxels -- take ``prefer`` where one of those nearest voxels
    holds it (in place in ``out``).

    There the labels do not tell which value the point has: the nearest samples are split, and
    a blur decides by farther voxels, whose curved boundaries pull it inwards (a small ball,
    blurred, reads as a smaller one, the more so the smaller it is).
    """
    frac = index[rows] - np.floor(index[rows])
    half = np.abs(frac - 0.5) < _AT_CENTRE
    mid = np.all(half | (frac < _AT_CENTRE) | (frac > 1.0 - _AT_CENTRE), axis=1) & np.any(half, axis=1)
    rows, half = rows[mid], half[mid]
    if not rows.size:
        return
    low = np.where(half, np.floor(index[rows]), np.round(index[rows])).astype(np.int64)
    wanted = prefer[rows]
    holds = np.zeros(len(rows), dtype=bool)
    for corner in range(2 ** index.shape[1]):
        bits = (corner >> np.arange(index.shape[1])) & 1
        at = np.clip(low + half * bits, 0, np.array(array.shape) - 1)
        holds |= array[tuple(at.T)] == wanted
    out[rows[holds]] = wanted[holds]


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

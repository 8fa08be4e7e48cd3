"""Overlap and distance measures between label volumes on one grid, and folding.

Dice per label; mean symmetric surface distance and the 95th-percentile
Hausdorff distance (the larger of the two directed 95th percentiles of
boundary-voxel distances, as MONAI's ``compute_hausdorff_distance``), both in
mm using the voxel spacing (nearest boundary voxels by k-d trees or distance
transforms, the same distances); the folded fraction of a Jacobian-determinant map.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["dice", "surface_distances", "label_scores", "folded_fraction"]


def dice(a: np.ndarray, b: np.ndarray) -> float:
    """Dice overlap ``2 |A & B| / (|A| + |B|)`` of two boolean masks (1.0 when both are empty)."""
    a = np.asarray(a, dtype=bool)
    b = np.asarray(b, dtype=bool)
    total = int(a.sum()) + int(b.sum())
    return 1.0 if total == 0 else 2.0 * int(np.count_nonzero(a & b)) / total


def _boundary(mask: np.ndarray) -> np.ndarray:
    """Voxels of ``mask`` with a face neighbour outside it (the image edge counts as outside)."""
    eroded = ndimage.binary_erosion(mask, structure=ndimage.generate_binary_structure(mask.ndim, 1), border_value=0)
    return mask & ~eroded


#: Below this fraction of the window's voxels on the two boundaries, nearest boundary voxels are
#: found by k-d trees instead of distance transforms of the whole window: the same figures, and
#: a tree costs what its boundary voxels cost where a transform costs the whole window.
#: Transforms remain for boundaries that fill much of their window (a speckled label), where a
#: tree of every voxel would cost more.
_TREE_FRACTION = 0.5


def _boundary_distances(ba: np.ndarray, bb: np.ndarray, spacing: np.ndarray,
                        tree: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Distances (mm) from each voxel of ``ba`` to the nearest of ``bb``, and from ``bb`` to ``ba``
    (both non-empty), between voxel centres: by k-d trees of the boundary voxels or by distance
    transforms of the window (``tree``: which; default by :data:`_TREE_FRACTION`)."""
    if tree is None:
        tree = np.count_nonzero(ba) + np.count_nonzero(bb) < _TREE_FRACTION * ba.size
    if not tree:
        return (ndimage.distance_transform_edt(~bb, sampling=spacing)[ba],
                ndimage.distance_transform_edt(~ba, sampling=spacing)[bb])
    from scipy.spatial import cKDTree

    # A voxel on both boundaries is at distance 0 from the other: only the rest are searched.
    # After a good registration that is most of them.  The distances come grouped, zeros first:
    # their mean and percentiles are those of every voxel.  Sliding-midpoint trees: built sooner
    # than balanced ones, and the nearest distances are exact either way.
    only_a, only_b = ba & ~bb, bb & ~ba
    both = np.zeros(int(np.count_nonzero(ba)) - int(np.count_nonzero(only_a)))
    pa, pb = np.argwhere(ba) * spacing, np.argwhere(bb) * spacing
    qa, qb = np.argwhere(only_a) * spacing, np.argwhere(only_b) * spacing
    return (np.concatenate([both, cKDTree(pb, balanced_tree=False).query(qa)[0]]),
            np.concatenate([np.zeros(len(pb) - len(qb)), cKDTree(pa, balanced_tree=False).query(qb)[0]]))


def surface_distances(a: np.ndarray, b: np.ndarray, spacing: np.ndarray) -> tuple[float, float]:
    """Mean symmetric surface distance and 95 % Hausdorff distance between two masks, mm.

    Parameters
    ----------
    a, b : (n_i, n_j[, n_k]) bool ndarrays on the same grid
    spacing : (D,) float ndarray, mm

    Returns
    -------
    (mean, hd95) : floats, mm
        ``nan`` when either mask is empty.
    """
    a = np.asarray(a, dtype=bool)
    b = np.asarray(b, dtype=bool)
    if not a.any() or not b.any():
        return float("nan"), float("nan")
    # Work in the union's bounding box, padded so that boundaries are interior.
    box = ndimage.find_objects((a | b).astype(np.int8))[0]
    window = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in box)
    a, b = a[window], b[window]
    ba, bb = _boundary(a), _boundary(b)
    to_b, to_a = _boundary_distances(ba, bb, spacing)
    mean = float((to_b.sum() + to_a.sum()) / (len(to_b) + len(to_a)))
    hd95 = float(max(np.percentile(to_b, 95), np.percentile(to_a, 95)))
    return mean, hd95


def label_scores(reference: np.ndarray, other: np.ndarray, labels, spacing: np.ndarray) -> dict[int, dict[str, float]]:
    """Dice, mean surface distance and HD95 (mm) of each label of ``other`` against ``reference``.

    Returns
    -------
    dict of int to dict
        ``{label: {"dice": ..., "mean_surface_distance_mm": ..., "hd95_mm": ...}}``
    """
    if np.shape(reference) != np.shape(other):
        raise ValueError(f"Expected `other` of shape {np.shape(reference)}, got {np.shape(other)}.")
    from volreg._threads import thread_map
    from volreg.grid import label_boxes

    reference, other = np.asarray(reference), np.asarray(other)
    boxes = (label_boxes(reference), label_boxes(other))

    def score(v) -> dict[str, float]:
        # Within the union of the label's boxes in both, padded by a voxel: outside it neither
        # has the label, so Dice and the boundaries are those of the whole arrays.
        present = [b[int(v)] for b in boxes if int(v) in b]
        if int(v) == 0:  # the background has no box
            window = tuple(slice(None) for _ in range(reference.ndim))
        elif present:
            window = tuple(slice(max(min(b[a].start for b in present) - 1, 0), max(b[a].stop for b in present) + 1)
                           for a in range(reference.ndim))
        else:
            window = tuple(slice(0, 0) for _ in range(reference.ndim))
        a = reference[window] == v
        b = other[window] == v
        mean, hd95 = surface_distances(a, b, spacing)
        return {"dice": dice(a, b), "mean_surface_distance_mm": mean, "hd95_mm": hd95}

    # Labels on parallel threads: the k-d tree searches, distance transforms and erosions
    # release the GIL.
    labels = [int(v) for v in labels]
    return dict(zip(labels, thread_map(score, labels)))


def folded_fraction(det: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Fraction of voxels (within ``mask`` if given) where ``det d tau/dx <= 0``."""
    det = np.asarray(det)
    values = det if mask is None else det[np.asarray(mask, dtype=bool)]
    return 0.0 if values.size == 0 else float(np.count_nonzero(values <= 0) / values.size)

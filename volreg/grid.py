"""In-memory label volumes: an integer array and its voxel-to-world geometry.

The world frame is ITK physical space: LPS, millimetres (see ``DESIGN.md``).
Array axes follow ITK's index order ``(i, j, k)``: ``array[i, j, k]`` is the
voxel whose physical point is ``origin + direction @ (spacing * (i, j, k))``.
(SimpleITK's ``GetArrayFromImage`` returns ``(k, j, i)``; the readers in
:mod:`volreg.io` transpose it.)  Everything here is dimension-generic
(``D`` = 2 or 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from volreg.errors import GeometryError

__all__ = ["LabelVolume"]


@dataclass(frozen=True, eq=False)
class LabelVolume:
    """An integer label array on a grid with ITK/LPS geometry.

    Parameters
    ----------
    array : (n_0, ..., n_{D-1}) integer ndarray
        Label values, indexed ``[i, j, k]`` (ITK index order).
    origin : (D,) float ndarray, mm
        Physical (LPS) position of voxel ``(0, ..., 0)``.
    spacing : (D,) float ndarray, mm
        Voxel size along each index axis; strictly positive.
    direction : (D, D) float ndarray
        Orthonormal matrix whose column ``d`` is the physical direction of
        index axis ``d``.
    """

    array: np.ndarray
    origin: np.ndarray
    spacing: np.ndarray
    direction: np.ndarray

    def __post_init__(self) -> None:
        array = np.asarray(self.array)
        if array.ndim not in (2, 3):
            raise GeometryError(
                f"Expected `array` to be 2-D or 3-D, got {array.ndim}-D with shape {array.shape}."
            )
        if not np.issubdtype(array.dtype, np.integer) and array.dtype != np.bool_:
            raise GeometryError(f"Expected `array` to hold integer labels, got dtype {array.dtype}.")
        d = array.ndim
        origin = np.asarray(self.origin, dtype=float).reshape(-1)
        spacing = np.asarray(self.spacing, dtype=float).reshape(-1)
        direction = np.asarray(self.direction, dtype=float)
        if origin.shape != (d,):
            raise GeometryError(f"Expected `origin` of length {d}, got shape {origin.shape}.")
        if spacing.shape != (d,) or not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
            raise GeometryError(f"Expected `spacing` of {d} positive finite values, got {spacing}.")
        if not np.all(np.isfinite(origin)):
            raise GeometryError(f"Expected a finite `origin`, got {origin}.")
        if direction.shape != (d, d) or not np.allclose(direction.T @ direction, np.eye(d), atol=1e-4):
            raise GeometryError(
                f"Expected `direction` to be an orthonormal {d}x{d} matrix, got {direction.tolist()}."
            )
        object.__setattr__(self, "array", array)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "spacing", spacing)
        object.__setattr__(self, "direction", direction)

    @property
    def ndim(self) -> int:
        """Number of spatial dimensions ``D``."""
        return self.array.ndim

    @property
    def shape(self) -> tuple[int, ...]:
        """Grid size in voxels, ITK index order."""
        return self.array.shape

    @property
    def affine(self) -> np.ndarray:
        """(D+1, D+1) homogeneous index-to-LPS-world matrix, mm."""
        d = self.ndim
        a = np.eye(d + 1)
        a[:d, :d] = self.direction * self.spacing[None, :]
        a[:d, d] = self.origin
        return a

    def index_to_world(self, index: np.ndarray) -> np.ndarray:
        """Map continuous voxel indices to LPS world points.

        Parameters
        ----------
        index : (N, D) float ndarray
            Continuous indices ``(i, j, k)``.

        Returns
        -------
        (N, D) float ndarray, mm
        """
        index = np.asarray(index, dtype=float)
        return index @ (self.direction * self.spacing[None, :]).T + self.origin

    def world_to_index(self, points: np.ndarray) -> np.ndarray:
        """Map LPS world points (mm) to continuous voxel indices, ``(N, D)``."""
        points = np.asarray(points, dtype=float)
        return ((points - self.origin) @ self.direction) / self.spacing

    def grid_points(self) -> np.ndarray:
        """World coordinates of every voxel centre, shape ``(*shape, D)``, mm."""
        idx = np.stack(np.meshgrid(*[np.arange(n) for n in self.shape], indexing="ij"), axis=-1)
        return self.index_to_world(idx.reshape(-1, self.ndim)).reshape(*self.shape, self.ndim)

    def index_window(self, lo: np.ndarray, hi: np.ndarray) -> tuple[slice, ...] | None:
        """Index slices covering the world box ``[lo, hi]`` (each (D,), mm), clipped to the grid.

        ``None`` when the box misses the grid.
        """
        corners = np.array(list(np.ndindex(*([2] * self.ndim))), dtype=float)
        box = self.world_to_index(np.asarray(lo, float) + corners * (np.asarray(hi, float) - lo))
        start = np.clip(np.floor(box.min(axis=0)).astype(int), 0, self.shape)
        stop = np.clip(np.ceil(box.max(axis=0)).astype(int) + 1, 0, self.shape)
        if np.any(stop <= start):
            return None
        return tuple(slice(int(a), int(b)) for a, b in zip(start, stop))

    def labels(self) -> np.ndarray:
        """Sorted non-zero label values present in the volume."""
        values = np.unique(self.array)
        return values[values != 0]

    def label_boxes(self) -> dict[int, tuple[slice, ...]]:
        """Bounding box of every non-zero label present, as index slices.

        One pass over the array (``scipy.ndimage.find_objects``) when the labels
        are non-negative and below 2^24; otherwise one pass per label, so that a
        large label value does not ask for a list of that length.

        Returns
        -------
        dict of int to tuple of ``ndim`` slices
        """
        from scipy import ndimage

        array = self.array.view(np.uint8) if self.array.dtype == np.bool_ else self.array
        if array.size and array.min() >= 0 and array.max() < 1 << 24:
            return {v + 1: box for v, box in enumerate(ndimage.find_objects(array)) if box is not None}
        return {int(v): ndimage.find_objects((array == v).view(np.uint8))[0] for v in self.labels()}

    def same_geometry(self, other: "LabelVolume", atol: float = 1e-6) -> bool:
        """True when ``other`` has the same grid size, origin, spacing and direction."""
        return (
            self.shape == other.shape
            and np.allclose(self.origin, other.origin, atol=atol)
            and np.allclose(self.spacing, other.spacing, atol=atol)
            and np.allclose(self.direction, other.direction, atol=atol)
        )

    def with_array(self, array: np.ndarray) -> "LabelVolume":
        """A volume on the same grid holding ``array`` (same shape required)."""
        array = np.asarray(array)
        if array.shape != self.shape:
            raise GeometryError(f"Expected `array` of shape {self.shape}, got {array.shape}.")
        return LabelVolume(array, self.origin, self.spacing, self.direction)

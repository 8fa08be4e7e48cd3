"""Voxel grids and label volumes: geometry, index <-> world, chunked traversal.

The world frame is ITK physical space: LPS, millimetres (see docs/conventions.md).
Array axes follow ITK's index order ``(i, j, k)``: voxel ``[i, j, k]`` has the
physical point ``origin + direction @ (spacing * (i, j, k))``.
(SimpleITK's ``GetArrayFromImage`` returns ``(k, j, i)``; the readers in
:mod:`volreg.io` transpose it.)  Everything here is dimension-generic
(``D`` = 2 or 3).

:class:`Grid` is the geometry alone (shape, origin, spacing, direction);
:class:`LabelVolume` is a grid plus an integer array.  Functions that need
only a grid (sampling a warp or an implicit surface at voxel centres,
resampling onto a reference) take either, or a ``(shape, affine)`` pair
(:func:`as_grid`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from volreg.errors import GeometryError

__all__ = [
    "Grid", "GridLike", "LabelVolume", "VoxelChunk", "as_grid", "box_diameter", "inside_field_of_view", "label_counts",
    "label_world_boxes", "world_box",
]


@dataclass(frozen=True, eq=False)
class VoxelChunk:
    """A run of voxels of a grid, for evaluating something voxel by voxel in bounded memory.

    Attributes
    ----------
    index : (M, D) int64 ndarray
        Voxel indices ``(i, j, k)`` in the grid.
    flat : (M,) int64 ndarray
        The same voxels as positions in the grid's C-order flattening
        (``np.ravel_multi_index(index.T, grid.shape)``).
    points : (M, D) float ndarray, mm
        Their voxel centres in LPS world coordinates.
    done : int
        Voxels of the traversal covered so far, this chunk included.
    total : int
        Voxels in the whole traversal (for progress reports).
    """

    index: np.ndarray
    flat: np.ndarray
    points: np.ndarray
    done: int
    total: int


#: Rows per block in :func:`apply_affine`: a block's columns and temporaries stay in cache.
_AFFINE_ROWS = 1 << 13


def apply_affine(points: np.ndarray, matrix: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``points @ matrix.T + offset`` for (N, D) points, column by column, block by block.

    Each output column is ``offset[a] + matrix[a, 0] p_0 + matrix[a, 1] p_1 + ...`` in that
    order (as :meth:`Grid.grid_points` sums it, so the two agree to the last bit), over blocks
    of :data:`_AFFINE_ROWS` rows that stay in cache: 5.7 M points take 90 ms, against 270 ms
    over whole columns.  No BLAS: its product (80 ms) rounds differently, and the threads
    OpenBLAS starts for a large product spin afterwards, slowing the compiled loops beside it.

    Parameters
    ----------
    points : (N, D) float array_like
    matrix : (E, D) float ndarray
    offset : (E,) float ndarray

    Returns
    -------
    (N, E) float ndarray
    """
    p = np.asarray(points, dtype=float)
    matrix = np.asarray(matrix, dtype=float)
    if p.ndim != 2 or p.shape[1] != matrix.shape[1]:
        return p @ matrix.T + offset
    out = np.empty((p.shape[0], matrix.shape[0]))
    term = np.empty(min(len(p), _AFFINE_ROWS))
    for s in range(0, len(p), _AFFINE_ROWS):
        block, rows = p[s : s + _AFFINE_ROWS], out[s : s + _AFFINE_ROWS]
        t = term[: len(block)]
        for a in range(matrix.shape[0]):
            column = rows[:, a]
            column[...] = offset[a]
            for b in range(matrix.shape[1]):
                np.multiply(block[:, b], matrix[a, b], out=t)
                column += t
    return out


def box_diameter(points: np.ndarray) -> float:
    """The diagonal of the axis-aligned bounding box of ``points`` (N, D), mm (0 for no points).

    The bounds are taken column by column (numpy reduces a C-ordered (N, 3) array along its first
    axis much more slowly than each column), with the same values as ``points.min(axis=0)``.
    """
    points = np.asarray(points)
    if len(points) == 0:
        return 0.0
    lo = np.array([points[:, d].min() for d in range(points.shape[1])])
    hi = np.array([points[:, d].max() for d in range(points.shape[1])])
    return float(np.linalg.norm(hi - lo))


def label_counts(values: np.ndarray) -> dict[int, int]:
    """The voxel count of each non-zero value of an integer array.

    Parameters
    ----------
    values : int ndarray, any shape

    Returns
    -------
    dict of int to int
        Value -> count, in ascending order of value; 0 (background) left out.
    """
    if values.size and values.min() >= 0 and values.max() < 2**24:
        c = np.bincount(values.ravel().astype(np.int64))
        return {int(v): int(c[v]) for v in np.flatnonzero(c) if v != 0}
    labels, c = np.unique(values, return_counts=True)
    return {int(v): int(n) for v, n in zip(labels, c) if v != 0}


def label_boxes(array: np.ndarray) -> dict[int, tuple[slice, ...]]:
    """Bounding box of every non-zero value of an integer ``array``, as index slices.

    One pass over the array (``scipy.ndimage.find_objects``) when the values are
    non-negative and below 2^24; otherwise one pass per value, so that a large value
    does not ask for a list of that length.

    Returns
    -------
    dict of int to tuple of ``array.ndim`` slices
    """
    from scipy import ndimage

    array = array.view(np.uint8) if array.dtype == np.bool_ else array
    if array.size and array.min() >= 0 and array.max() < 1 << 24:
        return {v + 1: box for v, box in enumerate(ndimage.find_objects(array)) if box is not None}
    values = np.unique(array)
    return {int(v): ndimage.find_objects((array == v).view(np.uint8))[0] for v in values[values != 0]}


def _geometry(d: int, origin, spacing, direction) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate and normalise the geometry of a ``D``-dimensional grid (the one place it is checked)."""
    origin = np.asarray(origin, dtype=float).reshape(-1)
    spacing = np.asarray(spacing, dtype=float).reshape(-1)
    direction = np.asarray(direction, dtype=float)
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
    return origin, spacing, direction


@dataclass(frozen=True, eq=False)
class Grid:
    """A voxel grid with ITK/LPS geometry (no values).

    Parameters
    ----------
    shape : tuple of D ints
        Grid size in voxels, ITK index order ``(n_i, n_j[, n_k])``; D = 2 or 3.
    origin : (D,) float ndarray, mm
        Physical (LPS) position of voxel ``(0, ..., 0)``.
    spacing : (D,) float ndarray, mm
        Voxel size along each index axis; strictly positive.
    direction : (D, D) float ndarray
        Orthonormal matrix whose column ``d`` is the physical direction of
        index axis ``d``.

    Raises
    ------
    GeometryError
        If ``shape`` is not 2 or 3 non-negative integers, or the geometry is
        invalid (wrong lengths, non-positive spacing, non-orthonormal direction).

    See Also
    --------
    Grid.from_affine : a grid from a ``(shape, affine)`` pair.
    """

    shape: tuple[int, ...]
    origin: np.ndarray
    spacing: np.ndarray
    direction: np.ndarray

    def __post_init__(self) -> None:
        try:
            shape = tuple(int(n) for n in self.shape)
            valid = all(n == m and n >= 0 for n, m in zip(shape, self.shape))
        except (TypeError, ValueError):
            valid = False
        if not valid or len(shape) not in (2, 3):
            raise GeometryError(f"Expected `shape` to be 2 or 3 non-negative integers, got {self.shape!r}.")
        origin, spacing, direction = _geometry(len(shape), self.origin, self.spacing, self.direction)
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "spacing", spacing)
        object.__setattr__(self, "direction", direction)

    @classmethod
    def from_affine(cls, shape: tuple[int, ...], affine: np.ndarray) -> Grid:
        """The grid of ``shape`` whose index-to-LPS-world matrix is ``affine``.

        Parameters
        ----------
        shape : tuple of D ints
        affine : (D+1, D+1) float ndarray, mm
            Homogeneous index-to-world matrix in LPS (as :attr:`affine`; a
            NIfTI/nibabel affine is RAS: negate its first two rows first).
            Its columns must be orthogonal (no shear).

        Raises
        ------
        GeometryError
            If ``affine`` is not ``(D+1, D+1)`` with last row ``(0, ..., 0, 1)``,
            has a zero column, or is sheared.
        """
        d = len(shape)
        affine = np.asarray(affine, dtype=float)
        if affine.shape != (d + 1, d + 1) or not np.allclose(affine[d], np.eye(d + 1)[d]):
            raise GeometryError(
                f"Expected `affine` to be a homogeneous {d + 1}x{d + 1} matrix for a grid of shape {tuple(shape)}, "
                f"got {affine.tolist()}."
            )
        linear = affine[:d, :d]
        spacing = np.linalg.norm(linear, axis=0)
        if not np.all(spacing > 0):
            raise GeometryError(f"Expected `affine` with non-zero columns (voxel sizes), got {affine.tolist()}.")
        return cls(tuple(shape), affine[:d, d], spacing, linear / spacing[None, :])

    @property
    def ndim(self) -> int:
        """Number of spatial dimensions ``D``."""
        return len(self.shape)

    @property
    def grid(self) -> Grid:
        """The grid itself (so that a grid and a :class:`LabelVolume` both have ``.grid``)."""
        return self

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
        return apply_affine(index, self.direction * self.spacing[None, :], self.origin)

    def world_to_index(self, points: np.ndarray) -> np.ndarray:
        """Map LPS world points (mm) to continuous voxel indices, ``(N, D)``."""
        m = self.direction.T / self.spacing[:, None]
        return apply_affine(points, m, -m @ self.origin)

    def grid_points(self) -> np.ndarray:
        """World coordinates of every voxel centre, shape ``(*shape, D)``, mm.

        The values of :meth:`index_to_world` at every index (the same products and sums, in the
        same order), each axis's term broadcast from its own index line: no index array is made
        (on tens of millions of voxels that array costs more than the products).
        """
        matrix = self.direction * self.spacing[None, :]
        out = np.empty((*self.shape, self.ndim))
        for a in range(self.ndim):
            column = out[..., a]
            column[...] = self.origin[a]
            for b, n in enumerate(self.shape):
                column += (matrix[a, b] * np.arange(n, dtype=float)).reshape([-1 if c == b else 1 for c in range(self.ndim)])
        return out

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

    def chunks(self, n: int, window: tuple[slice, ...] | None = None) -> Iterator[VoxelChunk]:
        """The voxels of ``window`` (default: the whole grid) in runs of at most ``n``.

        Voxels come in C order of the window (last index fastest), so that
        ``n`` bounds the memory of whatever is evaluated per voxel (e.g.
        ``n x D`` world points and their images under a warp).

        Parameters
        ----------
        n : int
            Voxels per chunk, ``>= 1``.
        window : tuple of D slices, optional
            A box of the grid, as :meth:`index_window` returns (step 1, within
            the grid).

        Yields
        ------
        VoxelChunk
            Indices, flat positions and world points (mm) of the chunk's voxels.
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise GeometryError(f"Expected `n` to be a positive number of voxels, got {n!r}.")
        window = self._checked_window(window)
        total = int(np.prod([s.stop - s.start for s in window]))
        for first in range(0, total, int(n)):
            yield self.chunk(first, min(first + int(n), total), window)

    def _checked_window(self, window: tuple[slice, ...] | None) -> tuple[slice, ...]:
        if window is None:
            return tuple(slice(0, size) for size in self.shape)
        if len(window) != self.ndim or not all(
            isinstance(s, slice) and s.step in (None, 1) and isinstance(s.start, (int, np.integer))
            and isinstance(s.stop, (int, np.integer)) and 0 <= s.start <= s.stop <= size
            for s, size in zip(window, self.shape)
        ):
            raise GeometryError(f"Expected `window` of {self.ndim} slices within the grid {self.shape}, got {window}.")
        return window

    def chunk(self, first: int, stop: int, window: tuple[slice, ...] | None = None) -> VoxelChunk:
        """The voxels ``first`` to ``stop - 1`` of ``window`` in C order: one of :meth:`chunks`,
        made on its own (so that chunks can be made on several threads).

        Parameters
        ----------
        first, stop : int
            Positions in the window's C-order traversal, ``0 <= first <= stop <= voxels``.
        window : tuple of D slices, optional
            As for :meth:`chunks`.

        Returns
        -------
        VoxelChunk
        """
        window = self._checked_window(window)
        sub_shape = tuple(s.stop - s.start for s in window)
        total = int(np.prod(sub_shape))
        if not 0 <= first <= stop <= total:
            raise GeometryError(f"Expected 0 <= `first` <= `stop` <= {total}, got {first} and {stop}.")
        start = np.array([s.start for s in window])
        index = np.stack(np.unravel_index(np.arange(first, stop), sub_shape), axis=1) + start
        flat = np.ravel_multi_index(tuple(index.T), self.shape)
        return VoxelChunk(index, flat, self.index_to_world(index), stop, total)

    def same_geometry(self, other: Grid | LabelVolume, atol: float = 1e-6) -> bool:
        """True when ``other`` (a grid or a volume) has the same grid size, origin, spacing and direction."""
        return (
            self.shape == other.shape
            and np.allclose(self.origin, other.origin, atol=atol)
            and np.allclose(self.spacing, other.spacing, atol=atol)
            and np.allclose(self.direction, other.direction, atol=atol)
        )

    def with_array(self, array: np.ndarray) -> LabelVolume:
        """A label volume on this grid holding ``array`` (same shape required)."""
        array = np.asarray(array)
        if array.shape != self.shape:
            raise GeometryError(f"Expected `array` of shape {self.shape}, got {array.shape}.")
        return LabelVolume(array, self.origin, self.spacing, self.direction)


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

    Notes
    -----
    The geometry is a :class:`Grid` (:attr:`grid`); the geometric methods
    below are the grid's.
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
        grid = Grid(array.shape, self.origin, self.spacing, self.direction)
        object.__setattr__(self, "array", array)
        object.__setattr__(self, "origin", grid.origin)
        object.__setattr__(self, "spacing", grid.spacing)
        object.__setattr__(self, "direction", grid.direction)
        object.__setattr__(self, "_grid", grid)

    @property
    def grid(self) -> Grid:
        """The volume's grid: shape, origin, spacing and direction, without the labels."""
        return self._grid

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
        return self._grid.affine

    def index_to_world(self, index: np.ndarray) -> np.ndarray:
        """Map continuous voxel indices ``(N, D)`` to LPS world points ``(N, D)``, mm (:meth:`Grid.index_to_world`)."""
        return self._grid.index_to_world(index)

    def world_to_index(self, points: np.ndarray) -> np.ndarray:
        """Map LPS world points (mm) to continuous voxel indices, ``(N, D)`` (:meth:`Grid.world_to_index`)."""
        return self._grid.world_to_index(points)

    def grid_points(self) -> np.ndarray:
        """World coordinates of every voxel centre, shape ``(*shape, D)``, mm."""
        return self._grid.grid_points()

    def index_window(self, lo: np.ndarray, hi: np.ndarray) -> tuple[slice, ...] | None:
        """Index slices covering the world box ``[lo, hi]`` (each (D,), mm), clipped to the grid.

        ``None`` when the box misses the grid.
        """
        return self._grid.index_window(lo, hi)

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
        return label_boxes(self.array)

    def same_geometry(self, other: Grid | LabelVolume, atol: float = 1e-6) -> bool:
        """True when ``other`` (a grid or a volume) has the same grid size, origin, spacing and direction."""
        return self._grid.same_geometry(other, atol=atol)

    def with_array(self, array: np.ndarray) -> LabelVolume:
        """A volume on the same grid holding ``array`` (same shape required)."""
        return self._grid.with_array(array)


#: What :func:`as_grid` accepts: a grid, a label volume, or ``(shape, affine)``.
GridLike = Grid | LabelVolume | tuple


def as_grid(target: GridLike, name: str = "grid") -> Grid:
    """The :class:`Grid` of ``target``: a grid, a label volume's grid, or a ``(shape, affine)`` pair.

    Parameters
    ----------
    target : Grid, LabelVolume or (shape, affine)
        ``affine`` is the ``(D+1, D+1)`` index-to-LPS-world matrix, mm
        (:meth:`Grid.from_affine`).
    name : str
        The argument's name, for the error message.

    Raises
    ------
    GeometryError
        If ``target`` is none of these.
    """
    if isinstance(target, Grid):
        return target
    if isinstance(target, LabelVolume):
        return target.grid
    if isinstance(target, tuple) and len(target) == 2:
        shape, affine = target
        return Grid.from_affine(tuple(shape), affine)
    raise GeometryError(
        f"Expected `{name}` to be a Grid, a LabelVolume or a (shape, affine) pair, got {type(target).__name__}."
    )


def inside_field_of_view(volume, points: np.ndarray, margin: float) -> np.ndarray:
    """Whether each point (N, D), mm, lies inside ``volume``'s voxel domain by at least ``margin`` mm
    (axes of a single voxel do not count)."""
    index = volume.world_to_index(points)
    keep = np.ones(len(points), dtype=bool)
    for axis, (n, step) in enumerate(zip(volume.shape, volume.spacing)):
        if n <= 1:
            continue
        m = margin / step
        keep &= (index[:, axis] >= -0.5 + m) & (index[:, axis] <= n - 0.5 - m)
    return keep


def label_world_boxes(volume, labels: list[int], to_fixed=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The world (mm) bounding boxes ``(lo, hi)`` of ``labels``' voxels in ``volume`` (those it
    holds), their corners taken through ``to_fixed`` (a point map) when given.

    Parameters
    ----------
    volume : LabelVolume
    labels : list of int
    to_fixed : callable, optional
        ``(N, D) mm -> (N, D) mm``, applied to each box's voxel corners.

    Returns
    -------
    list of (lo, hi)
        (D,) float ndarrays, mm; one per label of ``labels`` that ``volume`` holds.
    """
    if not labels:
        return []
    all_boxes = volume.label_boxes()
    out = []
    for label in labels:
        if label not in all_boxes:
            continue
        box = all_boxes[label]
        corners = np.array([[s.start - 0.5 if c == 0 else s.stop - 0.5 for s, c in zip(box, bits)]
                            for bits in np.ndindex(*([2] * len(box)))], float)
        world = volume.index_to_world(corners)
        if to_fixed is not None:
            world = to_fixed(world)
        out.append((world.min(axis=0), world.max(axis=0)))
    return out



def world_box(volume) -> tuple[np.ndarray, np.ndarray]:
    """The LPS bounding box of the voxel domain of ``volume`` (voxel corners, not centres).

    Returns
    -------
    lo, hi : (D,) float ndarrays, mm
    """
    corners = np.array(list(np.ndindex(*([2] * volume.ndim))), dtype=float)
    pts = volume.index_to_world(corners * (np.array(volume.shape) - 1)[None] + (corners - 0.5))
    return pts.min(axis=0), pts.max(axis=0)

"""Uniform cell grids over point sets, for the radius queries every kernel sum makes."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from volreg.kernels._compiled import _cell_sort, put_rows, take_rows

__all__ = ["SORT_ABOVE", "CellGrid", "column_bounds", "put_rows", "rows_within", "spatial_order", "take_rows"]

#: Most grid cells of a CellGrid (int32 start offsets: 64 MiB); larger grids get larger cells.
_MAX_CELLS = 1 << 24

#: Evaluations of more points than this visit them in spatial order first.
SORT_ABOVE = 50_000


@dataclass(frozen=True, eq=False)
class CellGrid:
    """Points binned on a uniform grid of cubic cells, for radius queries.

    Attributes
    ----------
    points : (M, D) float ndarray, mm
        The points, reordered cell by cell (row-major, last axis fastest).
    order : (M,) int ndarray
        ``points == original_points[order]``.
    start : (n_cells + 1,) int32 ndarray
        Points of cell ``c`` are ``points[start[c]:start[c + 1]]``.
    lo : (D,) float ndarray, mm
        Corner of cell ``(0, ..., 0)``.
    cell : float, mm
        Cell edge length.
    dims : (D,) int64 ndarray
        Number of cells per axis.
    radius : float, mm
        The query radius the grid was built for; a query visits the cells
        whose box is closer than ``radius``.
    """

    points: np.ndarray
    order: np.ndarray
    start: np.ndarray
    lo: np.ndarray
    cell: float
    dims: np.ndarray
    radius: float

    @cached_property
    def columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Coordinates as three contiguous (M,) float arrays, mm (z zeros in 2-D), for SIMD loops."""
        cols = [np.ascontiguousarray(self.points[:, a]) for a in range(self.points.shape[1])]
        while len(cols) < 3:
            cols.append(np.zeros(len(self.points)))
        return tuple(cols)

    @classmethod
    def build(cls, points: np.ndarray, radius: float, *, subdivisions: int = 1) -> CellGrid:
        """Bin points for queries of radius ``radius``.

        Parameters
        ----------
        points : (M, D) float ndarray, mm
            M > 0 points.
        radius : float, mm
            Query radius (> 0).
        subdivisions : int, optional
            Cells have edge ``radius / subdivisions`` (larger if the grid would
            exceed 2^24 cells).  Smaller cells mean fewer candidate points per
            query but more runs to look up; 1 is fastest on surface-like point
            sets.

        Returns
        -------
        CellGrid
        """
        points = np.ascontiguousarray(points, dtype=float)
        if points.ndim != 2 or points.shape[0] == 0:
            raise ValueError(f"Expected `points` of shape (M, D) with M > 0, got {points.shape}.")
        if not radius > 0:
            raise ValueError(f"Expected a positive `radius`, got {radius}.")
        lo, cell, dims = _cell_layout(points, float(radius) / max(1, int(subdivisions)))
        order, start = _cell_sort(_read_only(points), lo, cell, dims)
        return cls(points[order], order, start.astype(np.int32), lo, cell, dims, float(radius))


def _read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a``: the sort gets one argument type whether or not the caller's
    array is writable, so numba compiles it once."""
    view = a.view()
    view.flags.writeable = False
    return view


def column_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(points.min(axis=0), points.max(axis=0))`` of (N, D) points, column by column.

    numpy reduces a C-ordered (N, 3) array along its first axis an order of magnitude more
    slowly than each of its columns, and
    kernel sums, octree sampling and the inverse take the bounds of millions of points many
    times.  The same values (NaN where a column holds one).
    """
    points = np.asarray(points)
    lo = np.array([points[:, d].min() for d in range(points.shape[1])])
    hi = np.array([points[:, d].max() for d in range(points.shape[1])])
    return lo, hi


def rows_within(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, closed: bool = True) -> np.ndarray:
    """``np.all((points >= lo) & (points <= hi), axis=1)`` for (N, D) points, column by column
    (faster, for the reason of :func:`column_bounds`); with ``closed``
    False, the open box (``>`` and ``<``)."""
    points = np.asarray(points)
    inside = np.ones(len(points), dtype=bool)
    for d in range(points.shape[1]):
        column = points[:, d]
        inside &= (column >= lo[d]) & (column <= hi[d]) if closed else (column > lo[d]) & (column < hi[d])
    return inside


def _cell_layout(points: np.ndarray, cell: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Uniform grid covering ``points``.

    Parameters
    ----------
    points : (M, D) float ndarray, mm
    cell : float, mm
        Wanted cell edge.

    Returns
    -------
    lo : (D,) float ndarray, mm
        Corner of cell ``(0, ..., 0)``.
    cell : float, mm
        ``cell``, grown by factors of 1.25 until there are at most 2^24 cells.
    dims : (D,) int64 ndarray
        Cells per axis.
    """
    lo, hi = column_bounds(points)
    extent = hi - lo
    while True:
        dims = np.floor(extent / cell).astype(np.int64) + 1
        if np.prod(dims.astype(float)) <= _MAX_CELLS:  # float: no int64 overflow
            return lo, cell, dims
        cell *= 1.25


def max_runs(grid: CellGrid) -> int:
    """Upper bound on the contiguous runs of points one radius query of ``grid`` visits."""
    per_axis = int(np.ceil(grid.radius / grid.cell)) * 2 + 2
    return per_axis ** (grid.points.shape[1] - 1)


def spatial_order(points: np.ndarray, cell: float, *, above: int = SORT_ABOVE) -> np.ndarray | None:
    """A permutation visiting points cell by cell, or None when there are too few points for it to pay.

    Neighbouring queries share kernel centres, which then stay in cache.

    Parameters
    ----------
    points : (N, D) float ndarray, mm
    cell : float, mm
        Cell edge.
    above : int
        The fewest points worth sorting, less one (default :data:`SORT_ABOVE`).

    Returns
    -------
    (N,) int64 ndarray or None
        None when ``N <= above`` or ``cell`` is not positive.
    """
    if len(points) <= above or not cell > 0:
        return None
    points = np.ascontiguousarray(points, dtype=float)
    return _cell_sort(_read_only(points), *_cell_layout(points, float(cell)))[0]

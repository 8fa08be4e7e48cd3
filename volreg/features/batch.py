"""Many feature functions evaluated together, each at its own points.

The locational cost (3)-(6) has one feature pair per label, and each label's
feature is evaluated only at the samples near its surface: with hundreds of
labels, a few dozen points each.  Evaluated one by one, such a feature costs far
more in Python calls and in starting and joining parallel loops than in
arithmetic (hundreds of labels: tens of thousands of feature evaluations per
objective call).  :class:`FeatureBatch` concatenates the kernel
grids of implicit surfaces and the spline coefficients of voxel distance maps
once, and evaluates every feature at its segment of one array of points in one
compiled loop per kind, parallel over the features.  The values are those of the
features' own ``evaluate`` up to rounding (the same sums, possibly reassociated).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from volreg._threads import run_parts
from volreg.features.distance_maps import _POINTS, VoxelDistance, _bspline3_segments
from volreg.features.implicit import ImplicitSurface
from volreg.features.mapped import LinearlyMapped, congruence
from volreg.kernels._compiled import _segmented_sums
from volreg.kernels.grid import max_runs

__all__ = ["FeatureBatch"]

#: Fewest queries per part of the implicit surfaces' sums (each query sums every level of its
#: surface, so a part of this many outweighs the cost of handing it to a thread).
_QUERIES = 64


class _Implicit:
    """The levels of several implicit surfaces as one set of concatenated cell grids."""

    def __init__(self, surfaces: Sequence[ImplicitSurface], dim: int) -> None:
        cols, coef, starts, lo, cell, dims, sigma, runs = [[] for _ in range(3)], [], [], [], [], [], [], []
        jobs = [0]
        poff, soff = [0], [0]
        for surface in surfaces:
            for level in surface.levels:
                grid = level.grid
                for c, column in zip(cols, grid.columns):
                    c.append(column)
                coef.append(np.asarray(level.alpha, float)[grid.order])
                starts.append(grid.start)
                lo.append(grid.lo)
                cell.append(grid.cell)
                dims.append(grid.dims)
                sigma.append(level.width)
                runs.append(max_runs(grid))
                poff.append(poff[-1] + len(grid.points))
                soff.append(soff[-1] + len(grid.start))
            jobs.append(jobs[-1] + len(surface.levels))
        empty = np.zeros(0)
        self.px, self.py, self.pz = (np.ascontiguousarray(np.concatenate(c)) if c else empty for c in cols)
        self.coef = np.ascontiguousarray(np.concatenate(coef)) if coef else empty
        self.start = np.ascontiguousarray(np.concatenate(starts)) if starts else np.zeros(0, np.int32)
        self.lo = np.ascontiguousarray(np.reshape(lo, (-1, dim)), dtype=float)
        self.cell = np.asarray(cell, float)
        self.dims = np.ascontiguousarray(np.reshape(dims, (-1, dim)), dtype=np.int64)
        self.sigma = np.asarray(sigma, float)
        self.max_runs = int(max(runs, default=1))
        self.jobs = np.asarray(jobs, np.int64)
        self.poff = np.asarray(poff, np.int64)
        self.soff = np.asarray(soff, np.int64)
        self.offset = np.array([s.offset for s in surfaces], float)
        self.dim = dim

    def evaluate(self, points: np.ndarray, rstart: np.ndarray, order: int) -> list[np.ndarray]:
        n, dim = len(points), self.dim
        val = np.zeros((n, 1))
        grad = np.zeros((n, 1, dim)) if order >= 1 else np.zeros((0, 1, dim))
        hess = np.zeros((n, 1, dim, dim)) if order >= 2 else np.zeros((0, 1, dim, dim))
        # Parts of equal numbers of points, not of features: one feature may hold most of them (a
        # parcellation's white core, under the many parcels), and parts of whole features
        # kept the second thread idle most of the time.
        run_parts(_segmented_sums, n, points, rstart, self.jobs, self.poff, self.soff, self.px,
                  self.py, self.pz, self.coef, self.start, self.lo, self.cell, self.dims, self.sigma, self.max_runs,
                  int(order), val, grad, hess, grain=_QUERIES)
        val[:, 0] += np.repeat(self.offset, np.diff(rstart))
        out = [val[:, 0], grad[:, 0], hess[:, 0]]
        return out[: order + 1]


class _Voxel:
    """The spline coefficients of several voxel distance maps, concatenated."""

    def __init__(self, maps: Sequence[VoxelDistance], dim: int) -> None:
        self.coef = np.ascontiguousarray(np.concatenate([m._coef.ravel() for m in maps]))
        self.coff = np.concatenate([[0], np.cumsum([m._coef.size for m in maps])]).astype(np.int64)
        self.shapes = np.array([m._coef.shape for m in maps], np.int64)
        self.origin = np.array([m.origin for m in maps], float)
        self.to_index = np.array([m._to_index for m in maps], float)
        self.lo = np.array([m.lo for m in maps], float)
        self.step = np.array([m._step for m in maps], float)
        diagonal = all(m._step_outer is not None for m in maps)
        self.step_outer = np.array([m._step_outer for m in maps], float) if diagonal else None
        # Maps of one volume share its grid's axes and spacing: then the index of a point is one
        # product for every map, less each map's own offset (``origin @ to_index + lo``).
        self.shared = bool(np.all(self.to_index == self.to_index[0]) and np.all(self.step == self.step[0]))
        self.offset = np.einsum("md,mde->me", self.origin, self.to_index) + self.lo
        self.dim = dim

    def evaluate(self, points: np.ndarray, rstart: np.ndarray, order: int) -> list[np.ndarray]:
        n, d = len(points), self.dim
        which = np.repeat(np.arange(len(rstart) - 1), np.diff(rstart))
        if self.shared:
            index = points @ self.to_index[0] - self.offset[which]
        else:
            index = np.einsum("nd,nde->ne", points - self.origin[which], self.to_index[which]) - self.lo[which]
        if d == 2:
            index = np.concatenate([index, np.zeros((n, 1))], axis=1)
        f = np.empty(n)
        g = np.empty((n, 3)) if order >= 1 else np.empty((0, 3))
        h = np.empty((n, 3, 3)) if order >= 2 else np.empty((0, 3, 3))
        run_parts(_bspline3_segments, n, self.coef, self.coff, self.shapes, rstart,
                  np.ascontiguousarray(index), int(order), f, g, h, grain=_POINTS)
        out = [f]
        if order >= 1:
            if self.shared:
                out.append(g[:, :d] @ self.step[0].T)
            else:
                step = self.step[which]
                out.append(np.einsum("nb,nab->na", g[:, :d], step))
        if order >= 2:
            if self.step_outer is not None:
                out.append(h[:, :d, :d] * (self.step_outer[0] if self.shared else self.step_outer[which]))
            elif self.shared:
                out.append(self.step[0] @ h[:, :d, :d] @ self.step[0].T)
            else:
                out.append(np.einsum("nab,nbc,nec->nae", self.step[which], h[:, :d, :d], self.step[which]))
        return out


class FeatureBatch:
    """Feature functions of several objects, evaluated each at its own segment of points.

    Supports :class:`~volreg.features.implicit.ImplicitSurface` and
    :class:`~volreg.features.distance_maps.VoxelDistance`, each possibly seen through
    one common :class:`~volreg.features.mapped.LinearlyMapped` map; build with
    :meth:`build`, which says when a set of features is not supported.

    Parameters
    ----------
    features : sequence of ImplicitSurface, VoxelDistance or LinearlyMapped of them
        All in D dimensions; the mapped ones all through the same linear map, or none mapped.
    """

    def __init__(self, features: Sequence) -> None:
        features = list(features)
        if not features:
            raise ValueError("Expected at least one feature, got none.")
        mapped = [isinstance(f, LinearlyMapped) for f in features]
        if any(mapped) and not all(mapped):
            raise ValueError("Expected every feature or none to be a `LinearlyMapped` one.")
        self.linear = features[0] if all(mapped) else None
        inner = [f.feature if m else f for f, m in zip(features, mapped)]
        if self.linear is not None and not all(_same_map(f, self.linear) for f in features):
            raise ValueError("Expected every `LinearlyMapped` feature to use the same linear map.")
        dims = {int(f.dim) for f in inner}
        if len(dims) != 1:
            raise ValueError(f"Expected features of one dimension, got {sorted(dims)}.")
        self.dim = dims.pop()
        kinds = [_kind(f) for f in inner]
        if None in kinds:
            raise ValueError(f"Expected ImplicitSurface or VoxelDistance features, got {type(inner[kinds.index(None)]).__name__}.")
        self.n_features = len(features)
        self._groups = []
        for kind, cls in (("implicit", _Implicit), ("voxel", _Voxel)):
            members = np.array([i for i, k in enumerate(kinds) if k == kind], np.int64)
            if len(members):
                self._groups.append((members, cls([inner[i] for i in members], self.dim)))

    @classmethod
    def build(cls, features: Sequence) -> FeatureBatch | None:
        """A batch of ``features``, or None where one of them is not supported (or the
        mapped ones differ in their map)."""
        try:
            return cls(features)
        except (ValueError, AttributeError):
            return None

    def evaluate(self, points: np.ndarray, starts: np.ndarray, *, order: int = 1) -> tuple[np.ndarray, ...]:
        """Every feature at its own points.

        Parameters
        ----------
        points : (R, D) float ndarray, mm
            Feature ``i`` is evaluated at ``points[starts[i]:starts[i + 1]]``.
        starts : (F + 1,) int ndarray
            Segment boundaries, non-decreasing, from 0 to R.
        order : {0, 1, 2}

        Returns
        -------
        f : (R,) float ndarray, mm
        gradient : (R, D) float ndarray (if ``order >= 1``)
        hessian : (R, D, D) float ndarray, 1/mm (if ``order >= 2``)
        """
        points = np.ascontiguousarray(points, dtype=float)
        starts = np.asarray(starts, dtype=np.int64)
        n, d = len(points), self.dim
        if points.ndim != 2 or points.shape[1] != d:
            raise ValueError(f"Expected `points` of shape (R, {d}), got {points.shape}.")
        if starts.shape != (self.n_features + 1,) or starts[0] != 0 or starts[-1] != n or np.any(np.diff(starts) < 0):
            raise ValueError(f"Expected `starts` of {self.n_features + 1} non-decreasing offsets from 0 to {n}.")
        if order not in (0, 1, 2):
            raise ValueError(f"Expected `order` in (0, 1, 2), got {order}.")
        if not np.all(np.isfinite(points)):
            raise ValueError("Expected finite values in `points`, found NaN or Inf.")
        if self.linear is not None:
            points = np.ascontiguousarray(self.linear.linear(points))
        if len(self._groups) == 1:  # one kind of feature: its rows are all the rows, in order
            out = list(self._groups[0][1].evaluate(points, starts, order))
        else:
            out = [np.empty(n), np.empty((n, d)), np.empty((n, d, d))][: order + 1]
            counts = np.diff(starts)
            for members, group in self._groups:
                sizes = counts[members]
                rows = _segment_rows(starts[members], sizes)
                rstart = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
                for o, part in zip(out, group.evaluate(points[rows], rstart, order)):
                    o[rows] = part
        if self.linear is not None:
            a, s = self.linear._matrix, self.linear._scale
            out[0] = out[0] / s
            if order >= 1:
                out[1] = out[1] @ a / s
            if order >= 2:
                # Not a compiled loop: as fast at these sizes, and one loop less for a first run
                # to compile.
                out[2] = congruence(out[2], a) / s
        return tuple(out)


def _segment_rows(begins: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """The rows ``begins[i]:begins[i] + sizes[i]`` of every segment, concatenated."""
    total = int(sizes.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    return np.arange(total) - np.repeat(first - begins, sizes)


def _kind(feature) -> str | None:
    if isinstance(feature, ImplicitSurface):
        return "implicit"
    if isinstance(feature, VoxelDistance):
        return "voxel"
    return None


def _same_map(feature: LinearlyMapped, reference: LinearlyMapped) -> bool:
    return bool(np.array_equal(feature.linear.matrix, reference.linear.matrix)
                and np.array_equal(feature.linear.translation, reference.linear.translation))

"""The labels of two volumes as the linear stage reads them: moments, boundary samples, distance maps.

Per label and volume (:func:`_label_shape`): volume, centroid and second moments in world mm
(LPS), and voxel-face centres of its boundary in random order.  Per label, volume and level
(:func:`_distance_map`): the signed distance to the label's boundary (mm, positive outside) and
its gradient on the volume's grid coarsened towards the level's spacing, over the label's box
plus a margin; a :class:`_MapBank` samples several labels' maps at once, and a :class:`_Side`
caches one volume's maps by coarsening.  The fit itself is :func:`volreg.warp.linear.fit_linear`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from volreg.features.distance_maps import euclidean_distance

#: Voxels of margin inside a field of view beyond which a mapped sample carries no cost.
_FOV_MARGIN_VOXELS = 2.0


@dataclass(frozen=True, eq=False)
class _LabelShape:
    """One label of one volume: moments (world mm) and boundary samples."""

    label: int
    volume_mm3: float
    centroid: np.ndarray  # (D,) mm
    covariance: np.ndarray  # (D, D) mm^2, second central moments of the solid
    area_mm2: float  # voxel-face area of the boundary
    points: np.ndarray  # (K, D) mm, boundary face centres in random order
    box: tuple  # index slices of the label in its volume
    extent_mm: float  # largest side of the label's world bounding box

    @property
    def thickness_mm(self) -> float:
        """``2 V / A``: the thickness of a sheet, two thirds of a ball's radius."""
        return 2.0 * self.volume_mm3 / max(self.area_mm2, 1e-12)


def _label_shape(volume, label: int, box: tuple, cap: int, rng: np.random.Generator) -> _LabelShape:
    """Moments and up to ``cap`` boundary face centres of ``label`` in ``volume`` (world mm).

    The boundary is the set of voxel faces between the label and another value
    inside the image (faces on the image edge are no boundary); each face centre
    lies on the zero level of the distance maps of :func:`_distance_map`.
    """
    array = volume.array
    d = array.ndim
    lo = np.array([max(s.start - 1, 0) for s in box])
    hi = np.array([min(s.stop + 1, n) for s, n in zip(box, array.shape)])
    mask = array[tuple(slice(a, b) for a, b in zip(lo, hi))] == label
    count = int(mask.sum())
    coords = [np.arange(a, b, dtype=float) for a, b in zip(lo, hi)]
    first = np.empty(d)
    second = np.empty((d, d))
    for a in range(d):
        marginal = mask.sum(axis=tuple(k for k in range(d) if k != a), dtype=np.float64)
        first[a] = marginal @ coords[a]
        second[a, a] = marginal @ coords[a] ** 2
        for b in range(a + 1, d):
            plane = mask.sum(axis=tuple(k for k in range(d) if k not in (a, b)), dtype=np.float64)
            second[a, b] = second[b, a] = coords[a] @ plane @ coords[b]
    mean = first / count
    # Central moments of the voxels, plus each voxel's own (a box of side 1: 1/12).
    cov_index = second / count - np.outer(mean, mean) + np.eye(d) / 12.0
    lin = volume.direction * volume.spacing[None, :]
    voxel = float(np.prod(volume.spacing))
    faces = []
    area = 0.0
    for a in range(d):
        lower = [slice(None)] * d
        upper = [slice(None)] * d
        lower[a], upper[a] = slice(None, -1), slice(1, None)
        edge = mask[tuple(lower)] != mask[tuple(upper)]
        idx = np.argwhere(edge).astype(float)
        idx[:, a] += 0.5
        faces.append(idx + lo)
        area += len(idx) * voxel / volume.spacing[a]
    faces = np.concatenate(faces) if faces else np.zeros((0, d))
    if len(faces) > cap:
        faces = faces[rng.choice(len(faces), cap, replace=False)]
    else:
        faces = faces[rng.permutation(len(faces))]
    corners = np.array(list(np.ndindex(*([2] * d))), dtype=float)
    start = np.array([s.start for s in box], dtype=float) - 0.5
    size = np.array([s.stop - s.start for s in box], dtype=float)
    world_corners = volume.index_to_world(start + corners * size)
    return _LabelShape(
        label=int(label),
        volume_mm3=count * voxel,
        centroid=volume.index_to_world(mean[None])[0],
        covariance=lin @ cov_index @ lin.T,
        area_mm2=float(area),
        points=volume.index_to_world(faces),
        box=box,
        extent_mm=float(np.ptp(world_corners, axis=0).max()),
    )


def _union_moments(shapes: list[_LabelShape]) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume (mm^3), centroid (mm) and second central moments (mm^2) of a union of labels."""
    vol = np.array([s.volume_mm3 for s in shapes])
    cen = np.array([s.centroid for s in shapes])
    total = vol.sum()
    c = vol @ cen / total
    cov = sum(v * (s.covariance + np.outer(s.centroid - c, s.centroid - c)) for v, s in zip(vol, shapes)) / total
    return float(total), c, cov


def _distance_map(volume, label: int, box: tuple, factors: np.ndarray, margin_mm: float):
    """Signed distance to the boundary of ``label`` (mm, positive outside) and its gradient,
    on the volume's grid coarsened by the integer ``factors`` over the label's box plus a margin.

    The mask is block-averaged over ``factors`` voxels and thresholded at one half;
    beyond the image edge it is continued by the edge voxels (a cut label is not
    closed by the edge).  Distances are exact Euclidean distances between cell
    centres (:func:`~volreg.features.distance_maps.euclidean_distance`) shifted by half a cell, so
    that the zero level lies on the faces between inside and outside cells.

    Returns
    -------
    None, or (origin, step, values)
        ``origin`` (D,): the native continuous index of cell 0's centre; ``step`` (D,)
        mm; ``values`` (*shape, D + 1): the distance and its gradient along the
        grid's axes (mm per mm).  None when the coarsened mask is empty or full.
    """
    array = volume.array
    f = np.asarray(factors, dtype=int)
    step = f * volume.spacing
    margin = np.ceil(margin_mm / step).astype(int) + 1
    size = np.array([s.stop - s.start for s in box])
    cells = -(-size // f) + 2 * margin
    start = np.array([s.start for s in box]) - margin * f
    stop = start + cells * f
    lo, hi = np.maximum(start, 0), np.minimum(stop, array.shape)
    mask = array[tuple(slice(a, b) for a, b in zip(lo, hi))] == label
    pad = [(int(a - s), int(e - b)) for s, e, a, b in zip(start, stop, lo, hi)]
    if any(v for pair in pad for v in pair):
        mask = np.pad(mask, pad, mode="edge")
    if np.any(f > 1):
        shape = [v for pair in zip(cells, f) for v in pair]
        votes = mask.reshape(shape).sum(axis=tuple(range(1, 2 * len(f), 2)), dtype=np.int32)
        mask = 2 * votes >= int(np.prod(f))
    if mask.all() or not mask.any():
        return None
    half = 0.5 * float(step.min())
    dist = euclidean_distance(~mask, step)
    dist -= half
    np.subtract(half, euclidean_distance(mask, step), out=dist, where=mask)
    # Single precision (a millionth of a mm at these distances): a large label's map takes half
    # the memory, and the two volumes' maps are made in less time.
    values = np.empty(dist.shape + (dist.ndim + 1,), dtype=np.float32)
    values[..., 0] = dist
    _gradient_into(dist, step, values[..., 1:])
    return start + (f - 1) / 2.0, step, values


#: Values per slab of :func:`_gradient_into` (its float64 temporaries stay in cache).
_SLAB_VALUES = 1 << 16


def _gradient_into(dist: np.ndarray, step: np.ndarray, out: np.ndarray) -> None:
    """``np.gradient(dist, step[a], axis=a)`` into ``out[..., a]`` for every axis ``a``.

    The same values (differences in float64, cast on assignment), computed slab by slab along
    the first axis instead of as whole float64 arrays, whose temporaries for a large map cost
    more time than the differences themselves.

    Parameters
    ----------
    dist : (N0, ...) float64 ndarray, at least 2 cells along every axis
    step : (D,) float, mm
    out : (N0, ..., D) float ndarray, written
    """
    n = dist.shape[0]
    rows = max(4, _SLAB_VALUES // max(1, dist[0].size))
    for s in range(0, n, rows):
        e = min(n, s + rows)
        # Along the first axis from a row more on each side (where there is one), so that the
        # slab's first and last rows get central differences too; the other axes from the slab.
        a0, b0 = max(s - 1, 0), min(e + 1, n)
        out[s:e, ..., 0] = np.gradient(dist[a0:b0], step[0], axis=0)[s - a0 : e - a0]
        for a in range(1, dist.ndim):
            out[s:e, ..., a] = np.gradient(dist[s:e], step[a], axis=a)


#: The most bytes of a bank's maps that :class:`_MapBank` also copies into one array.
_JOIN_BYTES = 64 << 20


class _MapBank:
    """Distance maps of several labels of one volume, sampled together.

    Every map is a ``(cells, D + 1)`` block of its own (the maps as made, not copied
    into one array: a large label's map on a fine grid is big); a sample names
    its map by position.  Small maps together (at most :data:`_JOIN_BYTES`) are also
    copied into one array, so that the samples of all of them are read in one gather
    rather than map by map (many small labels' maps).  Values are
    multilinear interpolants of the distance and of its (central-difference) gradient;
    beyond a map's box the distance continues as ``d(q) + |p - q|`` (``q`` the nearest
    point of the box), a lower bound that keeps pulling stray points back.
    """

    def __init__(self, volume, entries: list[tuple]):
        d = volume.ndim
        self.volume = volume
        self.dim = d
        blocks, shapes, origins, steps = [], [], [], []
        for origin, step, values in entries:
            blocks.append(values.reshape(-1, d + 1))
            shapes.append(values.shape[:d])
            origins.append(origin)
            steps.append(step)
        self.blocks = blocks
        self.shapes = np.array(shapes, dtype=np.int64).reshape(-1, d)
        self.strides = np.ones_like(self.shapes)
        for a in range(d - 2, -1, -1):
            self.strides[:, a] = self.strides[:, a + 1] * self.shapes[:, a + 1]
        self.origins = np.array(origins, dtype=float).reshape(-1, d)
        self.steps = np.array(steps, dtype=float).reshape(-1, d)
        self.factors = self.steps / volume.spacing[None, :]
        self.corners = np.array(list(np.ndindex(*([2] * d))), dtype=np.int64)
        sizes = np.array([len(b) for b in blocks], dtype=np.int64)
        self.starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        nbytes = sum(b.nbytes for b in blocks)
        self.joined = np.concatenate(blocks) if len(blocks) > 1 and nbytes <= _JOIN_BYTES else None

    def lookup(self, which: np.ndarray) -> tuple:
        """Per-sample constants of maps ``which`` (N,) for :meth:`sample`."""
        inv_f = 1.0 / self.factors[which]
        top = (self.shapes[which] - 1).astype(float)
        strides = self.strides[which]
        if self.joined is None:
            maps, first = np.unique(which, return_index=True)
            if np.all(which[1:] >= which[:-1]):  # the samples come map by map: each map's a slice
                ends = np.append(first[1:], len(which))
                groups = [(m, slice(int(b), int(e))) for m, b, e in zip(maps, first, ends)]
            else:
                groups = [(m, np.flatnonzero(which == m)) for m in maps]
        else:  # one group: every sample's cells counted from the joined array's start
            groups = [(None, self.starts[which])]
        return (inv_f, self.origins[which] * inv_f, top, np.maximum(top - 1.0, 0.0), self.steps[which],
                groups, strides, strides @ self.corners.T)

    def sample(self, lookup: tuple, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (N,) mm and world gradients (N, D) at ``points`` (N, D) mm, of the maps
        whose :meth:`lookup` is ``lookup``."""
        inv_f, shift, top, top1, step, groups, strides, corner_offsets = lookup
        idx = self.volume.world_to_index(points) * inv_f - shift
        q = np.clip(idx, 0.0, top)
        excess = (idx - q) * step  # mm along the grid axes
        i0 = np.minimum(np.floor(q), top1)
        t = q - i0
        base = np.einsum("ij,ij->i", i0.astype(np.int64), strides)
        weights = np.stack([1.0 - t, t], axis=0)  # (2, N, D)
        corner_w = []
        for corner in self.corners:
            w = weights[corner[0], :, 0]
            for a in range(1, self.dim):
                w = w * weights[corner[a], :, a]
            corner_w.append(w)
        n, k_all = len(points), len(self.corners)
        acc = np.empty((n, self.dim + 1))
        for m, rows in groups:  # the samples of each map from its own block (or all at once), corners in order
            if m is None:
                block, b, co, w_rows = self.joined, base + rows, corner_offsets, corner_w
            else:
                block, b, co, w_rows = self.blocks[m], base[rows], corner_offsets[rows], [w[rows] for w in corner_w]
            cells = np.take(block, (b[:, None] + co).ravel(), axis=0).reshape(len(b), k_all, self.dim + 1)
            part = np.zeros((len(b), self.dim + 1))
            for k in range(k_all):
                part += w_rows[k][:, None] * cells[:, k]
            if m is None:
                acc = part
            else:
                acc[rows] = part
        dist, grad = acc[:, 0], acc[:, 1:]
        out = np.sqrt(np.einsum("ij,ij->i", excess, excess))
        far = out > 0
        if np.any(far):
            dist = dist + out
            grad = np.where(excess != 0, excess / np.where(far, out, 1.0)[:, None], grad)
        return dist, grad @ self.volume.direction.T


def _inside_fov(volume, points: np.ndarray) -> np.ndarray:
    """Whether ``points`` (N, D) mm lie in ``volume``'s field of view less two of its voxels."""
    idx = volume.world_to_index(points)
    n = np.array(volume.shape, dtype=float)
    margin = np.minimum(_FOV_MARGIN_VOXELS, np.maximum(n - 1.0, 0.0) / 2.0)
    return np.all((idx >= -0.5 + margin) & (idx <= n - 0.5 - margin), axis=1)


class _Samples:
    """Boundary samples of one side: points (mm), the map each is compared to, weights, and
    whether each belongs to a label cut by the edge of either image."""

    def __init__(self, points: np.ndarray, which: np.ndarray, weights: np.ndarray, cut: np.ndarray | None = None):
        self.points, self.which, self.weights = points, which, weights
        self.cut = np.zeros(len(points), dtype=bool) if cut is None else cut

    def subset(self, keep: np.ndarray) -> _Samples:
        return _Samples(self.points[keep], self.which[keep], self.weights[keep], self.cut[keep])

    def kept(self, other_volume, mapped: np.ndarray) -> np.ndarray:
        """Which samples carry cost once mapped to ``mapped`` (N, D) mm in the other volume:
        all of an uncut label (its distance continues beyond the image, see :class:`_MapBank`,
        so a map cannot win by pushing it out of view), and those of a cut label that land
        inside the other volume's field of view less two voxels."""
        return ~self.cut | _inside_fov(other_volume, mapped)

    def __len__(self) -> int:
        return len(self.points)


def _level_factors(volume, spacing_mm: float) -> np.ndarray:
    """Integer coarsening of ``volume``'s grid per axis towards an isotropic ``spacing_mm``."""
    return np.maximum(1, np.round(spacing_mm / volume.spacing)).astype(int)


class _Side:
    """One volume's labels for the fit: shapes, and distance maps cached by coarsening."""

    def __init__(self, volume, shapes: dict[int, _LabelShape]):
        self.volume, self.shapes = volume, shapes
        self._maps: dict[tuple, tuple | None] = {}
        self._banks: dict[tuple, tuple[_MapBank, dict[int, int]]] = {}

    def map_key(self, label: int, spacing_mm: float, floor_mm: float) -> tuple:
        """The label and the grid coarsening of its map at a level (spacing, mm)."""
        h = max(floor_mm, min(spacing_mm, 0.5 * self.shapes[label].thickness_mm))
        return label, tuple(int(v) for v in _level_factors(self.volume, h))

    def _compute(self, key: tuple):
        label, factors = key
        shape = self.shapes[label]
        h = float(np.min(np.asarray(factors) * self.volume.spacing))
        margin = max(3.0 * h, min(0.1 * shape.extent_mm, 20.0))
        return _distance_map(self.volume, label, shape.box, np.asarray(factors), margin)

    def label_map(self, key: tuple):
        if key not in self._maps:
            self._maps[key] = self._compute(key)
        return self._maps[key]

    def missing(self, labels: list[int], spacing_mm: float, floor_mm: float) -> list[tuple]:
        """The keys of the maps of ``labels`` at a level not made yet."""
        keys = {self.map_key(label, spacing_mm, floor_mm) for label in labels}
        return sorted(k for k in keys if k not in self._maps)

    def cells(self, key: tuple) -> int:
        """About how many voxels the map of ``key`` covers (its label's box): its cost."""
        return int(np.prod([s.stop - s.start for s in self.shapes[key[0]].box]))

    def bank(self, labels: list[int], spacing_mm: float, floor_mm: float) -> tuple[_MapBank, dict[int, int]]:
        """The maps of ``labels`` at a level, and the position of each label's map in it."""
        keys = tuple(self.map_key(label, spacing_mm, floor_mm) for label in labels)
        _make_maps([self], labels, spacing_mm, floor_mm)
        if keys not in self._banks:
            entries, where = [], {}
            for key in keys:
                entry = self.label_map(key)
                if entry is not None:
                    where[key[0]] = len(entries)
                    entries.append(entry)
            self._banks[keys] = (_MapBank(self.volume, entries), where)
        return self._banks[keys]

    def samples(self, labels: list[int], where: dict[int, int], count: int, cut: set[int]) -> _Samples:
        """Up to ``count`` boundary points per label, weighted so that each label's total
        weight is its boundary area (mm^2, normalised later); ``cut``: labels cut by an image edge."""
        pts, which, weights, cuts = [], [], [], []
        for label in labels:
            if label not in where:
                continue
            shape = self.shapes[label]
            p = shape.points[:count]
            if not len(p):
                continue
            pts.append(p)
            which.append(np.full(len(p), where[label], dtype=np.int64))
            weights.append(np.full(len(p), shape.area_mm2 / len(p)))
            cuts.append(np.full(len(p), label in cut))
        d = self.volume.ndim
        if not pts:
            return _Samples(np.zeros((0, d)), np.zeros(0, dtype=np.int64), np.zeros(0))
        return _Samples(np.concatenate(pts), np.concatenate(which), np.concatenate(weights), np.concatenate(cuts))


def _make_maps(sides: list[_Side], labels: list[int], spacing_mm: float, floor_mm: float) -> None:
    """Make the maps of ``labels`` at a level that the ``sides`` lack, all together on the
    thread budget, largest first (the distance transforms release the GIL for much of their
    work): the two volumes' largest maps are made at once."""
    from volreg._threads import thread_map

    jobs = [(side, key) for side in sides for key in side.missing(labels, spacing_mm, floor_mm)]
    jobs.sort(key=lambda job: -job[0].cells(job[1]))
    for (side, key), value in zip(jobs, thread_map(lambda job: job[0]._compute(job[1]), jobs)):
        side._maps[key] = value


@dataclass(frozen=True, eq=False)
class _LabelPair:
    """Both volumes' labels for one fit, and what every solve of it shares.

    Attributes
    ----------
    fixed, moving : _Side
    labels : list of int
        The labels that drive the fit.
    cut : set of int
        Labels cut by the edge of either image (:func:`~volreg.warp.linear.cut_labels`).
    floor_mm : float
        The finest map spacing (the coarser volume's voxel), mm.
    centre : (D,) float ndarray, mm
        The fixed labels' centroid: the parameters of a solve are about it.
    radius : float, mm
        Half the fixed labels' diameter: the size of a rotation or stretch parameter.
    """

    fixed: _Side
    moving: _Side
    labels: list
    cut: set
    floor_mm: float
    centre: np.ndarray
    radius: float

    def level(self, spacing_mm: float, count: int) -> tuple[_MapBank, _MapBank, _Samples, _Samples]:
        """Both volumes' map banks at a level, and up to ``count`` boundary samples per label of each.

        The fixed samples (``fwd``) are read on the moving maps and the moving samples
        (``back``) on the fixed ones; their weights are normalised to a mean of one.

        Returns
        -------
        bank_f, bank_m : _MapBank
        fwd, back : _Samples
        """
        _make_maps([self.fixed, self.moving], self.labels, spacing_mm, self.floor_mm)
        bank_f, where_f = self.fixed.bank(self.labels, spacing_mm, self.floor_mm)
        bank_m, where_m = self.moving.bank(self.labels, spacing_mm, self.floor_mm)
        fwd = self.fixed.samples(self.labels, where_m, count, self.cut)
        back = self.moving.samples(self.labels, where_f, count, self.cut)
        norm = np.mean(np.concatenate([fwd.weights, back.weights])) if len(fwd) + len(back) else 1.0
        fwd.weights, back.weights = fwd.weights / norm, back.weights / norm
        return bank_f, bank_m, fwd, back

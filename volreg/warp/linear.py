"""The linear part of a registration: ``x -> A x + b``, found before the kernel warp.

A registration's map is ``tau(x) = A x + b + sum_j c_j k(x, x_j)``: the linear part
brings the moving object into the pose and size of the fixed one (a kernel warp of
compact support cannot rotate an object by 20 degrees), the kernel expansion (paper
eq. 9) does the rest.  Points are ``(N, D)`` arrays in world millimetres (LPS), D = 2
or 3; the map is a pull-back (fixed point -> moving point), as ITK's transforms are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from volreg.features.distance_maps import euclidean_distance
from volreg.grid import apply_affine
from volreg.settings import LINEAR_KINDS

__all__ = ["LINEAR_KINDS", "LinearFit", "LinearMap", "cut_labels", "fit_linear"]


def _as_matrix(matrix) -> np.ndarray:
    a = np.array(matrix, dtype=float)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or a.shape[0] not in (2, 3):
        raise ValueError(f"Expected `matrix` of shape (D, D) with D = 2 or 3, got {a.shape}.")
    if not np.all(np.isfinite(a)):
        raise ValueError("Expected finite values in `matrix`, found NaN or Inf.")
    det = float(np.linalg.det(a))
    if not det > 0:
        raise ValueError(f"Expected `matrix` with a positive determinant (no reflection, no collapse), got {det:.3g}.")
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class LinearMap:
    """The map ``x -> matrix @ x + translation`` in world mm (LPS).

    Parameters
    ----------
    matrix : (D, D) float array_like
        ``A``; its determinant must be positive (orientation kept).
    translation : (D,) float array_like, mm
        ``b``.
    """

    matrix: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        a = _as_matrix(self.matrix)
        b = np.array(self.translation, dtype=float).reshape(-1)
        if b.shape != (a.shape[0],) or not np.all(np.isfinite(b)):
            raise ValueError(f"Expected a finite `translation` of shape ({a.shape[0]},), got {np.shape(self.translation)}.")
        b.flags.writeable = False
        object.__setattr__(self, "matrix", a)
        object.__setattr__(self, "translation", b)

    @classmethod
    def identity(cls, dim: int) -> "LinearMap":
        """``x -> x`` in ``dim`` dimensions."""
        return cls(np.eye(dim), np.zeros(dim))

    @property
    def dim(self) -> int:
        """Number of spatial dimensions D."""
        return int(self.matrix.shape[0])

    @property
    def is_identity(self) -> bool:
        """Whether the map is ``x -> x`` exactly."""
        return bool(np.array_equal(self.matrix, np.eye(self.dim)) and not np.any(self.translation))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """``A x + b`` at ``points``, (N, D) mm."""
        return apply_affine(points, self.matrix, self.translation)

    def inverse(self) -> "LinearMap":
        """``y -> A^-1 (y - b)``."""
        inv = np.linalg.inv(self.matrix)
        return LinearMap(inv, -inv @ self.translation)

    def then(self, other: "LinearMap") -> "LinearMap":
        """The map ``x -> other(self(x))``."""
        return LinearMap(other.matrix @ self.matrix, other.matrix @ self.translation + other.translation)

    def describe(self) -> dict:
        """What a reviewer reads off the map (JSON-ready).

        Returns
        -------
        dict
            ``matrix`` (D x D), ``translation`` (mm), ``rotation_deg`` (angle of the
            rotation ``R`` of the polar decomposition ``A = R S``), ``scales`` (the
            eigenvalues of the symmetric stretch ``S``, largest first) and ``determinant``
            (the volume ratio, moving to fixed).
        """
        a = self.matrix
        u, s, vt = np.linalg.svd(a)
        rot = u @ vt  # det(A) > 0 gives det(rot) = +1
        cos = (np.trace(rot) - (self.dim - 2)) / 2 if self.dim == 3 else rot[0, 0]
        angle = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        return dict(
            matrix=a.tolist(),
            translation=self.translation.tolist(),
            rotation_deg=angle,
            scales=[float(v) for v in s],
            determinant=float(np.linalg.det(a)),
        )


# --------------------------------------------------------------------------------------
# Fitting the linear map to two label volumes
# --------------------------------------------------------------------------------------

#: Labels that drive the linear fit at most (the largest by volume in the fixed volume).
MAX_LINEAR_LABELS = 30
#: Object diameter over grid spacing, coarse to fine (each level's distance-map spacing).
_LEVEL_DIVISORS = (16.0, 32.0, 64.0)
#: Boundary samples per label and volume at each level (coarse to fine), and in all
#: (per volume): many labels share the second budget.
_LEVEL_SAMPLES = (600, 1200, 2500)
_LEVEL_TOTAL = (4000, 8000, 16000)
#: Least-squares evaluations per level, and per start candidate at the coarsest level.
_LEVEL_EVALUATIONS = 40
_CANDIDATE_EVALUATIONS = 8
#: least_squares' xtol, ftol and gtol at every level.
_LEVEL_TOLERANCE = 1e-5
#: The linear stage keeps the identity (or its start) over the fitted map unless the fitted map's
#: mean Dice is higher by more than this. Read by nearest neighbour between grids of other
#: resolutions, the same labels at 1 mm and at 0.8 x 0.8 x 2.5 mm, with no motion, overlapped
#: 0.0026-0.0043 better through affine maps fitted to the thick slices' staircase (one turned
#: 3.9 degrees: 0.47 mm mean endpoint error, 0.25 mm with the identity kept); on every posed pair
#: of `bench_pose.py` the fitted map gains 0.020 or more.
KEEP_MARGIN = 0.005

#: Voxels of margin inside a field of view beyond which a mapped sample carries no cost.
_FOV_MARGIN_VOXELS = 2.0
#: A start whose score is within this factor of the best one's competes on rotation: the
#: least rotated of them wins.
_NEAR_BEST = 1.5
#: Where two of the labels' second moments differ by less than this fraction, their turn about
#: the third axis is searched at the finest level (:func:`_free_axis`), in steps of
#: ``_TURN_STEP_DEG``; of the turns whose score is within ``_TURN_TIE`` of the best, the smallest.
_TURN_AXIS_TOL = 0.1
_TURN_STEP_DEG = 5.0
_TURN_TIE = 0.02


@dataclass(frozen=True, eq=False)
class LinearFit:
    """The result of :func:`fit_linear`.

    Attributes
    ----------
    map : LinearMap
        The pull-back ``x -> A x + b`` (fixed point -> moving point, LPS mm).
    log : dict
        JSON-ready record of the fit: ``kind``; ``start`` (``"centroids"``: the
        Procrustes fit of the label centroids or the centroids' translation alone;
        ``"principal axes"``; or ``"identity"``: the family of the start kept) and
        ``start_candidate`` (its name); ``candidates`` (name, closed-form map and the
        cost after a few iterations at the coarsest level); ``levels`` (per level:
        ``spacing_mm``, ``f_scale_mm``, ``samples``, ``cost``, ``iterations``,
        ``mean_abs_distance_mm``); ``labels`` (the labels that drove the fit);
        ``cut_labels`` (``fixed`` / ``moving``: labels touching the image edge);
        ``overlap`` (mean Dice through the ``identity``, the ``start`` and the ``refined``
        map, compared two at a time: the start against the refined map, then the identity
        against the one kept, each pair over the voxels both send into the moving image) and
        ``kept_instead`` (``None``, or which of the first two was kept);
        ``map`` (:meth:`LinearMap.describe`); ``seconds``.
    """

    map: LinearMap
    log: dict


def cut_labels(volume) -> list[int]:
    """The labels of ``volume`` with a voxel on the outermost layer of an axis.

    Such a label is cut by the edge of the image (a partial field of view): its
    centroid and moments are those of the visible part only.  Axes of length 1 do
    not count (a single slice is not a cut along its normal).

    Parameters
    ----------
    volume : LabelVolume

    Returns
    -------
    list of int
        Sorted non-zero label values.
    """
    array = np.asarray(volume.array)
    found: set[int] = set()
    for axis, n in enumerate(array.shape):
        if n <= 1:
            continue
        for index in (0, n - 1):
            found.update(int(v) for v in np.unique(np.take(array, index, axis=axis)))
    found.discard(0)
    return sorted(found)


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


# ----------------------------------------------------------------------------- starts


def _procrustes(p: np.ndarray, q: np.ndarray, w: np.ndarray, kind: str) -> tuple[LinearMap, str]:
    """Weighted fit of ``q ~ A p + b`` to point pairs (Kabsch, Umeyama or least squares).

    Parameters
    ----------
    p, q : (n, D) float ndarray, mm
        Fixed and moving points (label centroids).
    w : (n,) float ndarray
        Non-negative weights.
    kind : {"rigid", "similarity", "affine"}
        An affine fit is kept only when it is well conditioned (at least 2 D pairs,
        a moderate condition number and no reflection); otherwise the similarity.

    Returns
    -------
    LinearMap, str
        The map and the model actually fitted.
    """
    d = p.shape[1]
    w = w / w.sum()
    mp, mq = w @ p, w @ q
    x, y = p - mp, q - mq
    cross = (y * w[:, None]).T @ x
    u, sv, vt = np.linalg.svd(cross)
    flip = np.ones(d)
    flip[-1] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag(flip) @ vt
    scale = 1.0
    if kind != "rigid":
        scale = float(sv @ flip / (w @ np.sum(x * x, axis=1)))
    a = scale * rot
    used = "rigid" if kind == "rigid" else "similarity"
    if kind == "affine" and len(p) >= 2 * d:
        xh = np.hstack([x, np.ones((len(x), 1))]) * np.sqrt(w)[:, None]
        sol, *_ = np.linalg.lstsq(xh, y * np.sqrt(w)[:, None], rcond=None)
        cand = sol[:d].T
        s_cand = np.linalg.svd(cand, compute_uv=False)
        if np.linalg.det(cand) > 0 and s_cand[0] / s_cand[-1] < 3.0:
            a, used = cand, "affine"
    return LinearMap(a, mq - a @ mp), used


def _spans(points: np.ndarray, weights: np.ndarray) -> bool:
    """Whether weighted points span their space: D + 1 of them, not nearly on a plane (line)."""
    n, d = points.shape
    if n < d + 1:
        return False
    w = weights / weights.sum()
    x = (points - w @ points) * np.sqrt(w)[:, None]
    s = np.linalg.svd(x, compute_uv=False)
    return bool(s[-1] > 0.15 * s[0])


def _axis_candidates(fixed: list[_LabelShape], moving: list[_LabelShape], kind: str) -> list[tuple[str, LinearMap]]:
    """Principal-axes starts: ``R = E_m diag(s) E_f^T`` for every sign choice with det +1,
    the centroids' translation, and the volume ratio's scale (similarity); for an affine map,
    the scales along the axes that carry one union's second moments onto the other's,
    ``A = E_m diag(s sqrt(l_m / l_f)) E_f^T`` (``l``: the moments' eigenvalues, mm^2)."""
    vf, cf, covf = _union_moments(fixed)
    vm, cm, covm = _union_moments(moving)
    d = len(cf)
    scale = 1.0 if kind == "rigid" else (vm / vf) ** (1.0 / d)
    lf, ef = np.linalg.eigh(covf)
    lm, em = np.linalg.eigh(covm)
    ef, em, lf, lm = ef[:, ::-1], em[:, ::-1], lf[::-1], lm[::-1]
    tiny = 1e-12 * max(float(lf.max()), float(lm.max()), 1e-300)
    axes = np.sqrt(np.maximum(lm, tiny) / np.maximum(lf, tiny)) if kind == "affine" else np.full(d, scale)
    out = []
    for signs in np.ndindex(*([2] * d)):
        s = 1.0 - 2.0 * np.array(signs, dtype=float)
        if np.linalg.det(em @ np.diag(s) @ ef.T) < 0:
            continue
        a = em @ np.diag(s * axes) @ ef.T
        label = "".join("+" if v > 0 else "-" for v in s)
        out.append((f"principal axes {label}", LinearMap(a, cm - a @ cf)))
    out.append(("centroid translation", LinearMap(scale * np.eye(d), cm - scale * cf)))
    return out


# ----------------------------------------------------------------------------- distance maps


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
    # Single precision (a millionth of a mm at these distances): a 1 mm brain-size label's map
    # is then 140 MB instead of 280, and the linear stage's two such maps are made in less time.
    values = np.empty(dist.shape + (dist.ndim + 1,), dtype=np.float32)
    values[..., 0] = dist
    _gradient_into(dist, step, values[..., 1:])
    return start + (f - 1) / 2.0, step, values


#: Values per slab of :func:`_gradient_into` (its float64 temporaries stay in cache).
_SLAB_VALUES = 1 << 16


def _gradient_into(dist: np.ndarray, step: np.ndarray, out: np.ndarray) -> None:
    """``np.gradient(dist, step[a], axis=a)`` into ``out[..., a]`` for every axis ``a``.

    The same values (differences in float64, cast on assignment), computed slab by slab along
    the first axis instead of as whole float64 arrays: for the 1 mm phantom's grey shell map
    (8.8 M cells) those took 0.56 s of the map's 1.23 s, and the whole map now takes 0.44 s.

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
    into one array: on a 1 mm brain-size volume each is hundreds of MB); a sample names
    its map by position.  Small maps together (at most :data:`_JOIN_BYTES`) are also
    copied into one array, so that the samples of all of them are read in one gather
    (a hundred labels' maps were read map by map and corner by corner).  Values are
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


# ----------------------------------------------------------------------------- the cost


def _right_jacobian(v: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3) at rotation vector ``v``: ``R(v + e) ~ R(v) exp([J_r e]x)``."""
    theta = float(np.linalg.norm(v))
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    if theta < 1e-6:
        return np.eye(3) - 0.5 * k + k @ k / 6.0
    return np.eye(3) - (1 - np.cos(theta)) / theta**2 * k + (theta - np.sin(theta)) / theta**3 * k @ k


class _Local:
    """The local map ``G(x) = c + M (x - c) + t`` of a parameter vector, about the centre ``c``.

    rigid: ``t`` (D), rotation vector (3) or angle (1); similarity adds the log-scale;
    affine: ``t`` and ``M - I`` (D x D, row-major).
    """

    def __init__(self, kind: str, dim: int):
        self.kind, self.dim = kind, dim
        n_rot = 3 if dim == 3 else 1
        self.size = dim + (dim * dim if kind == "affine" else n_rot + (kind == "similarity"))

    def x_scale(self, radius: float) -> np.ndarray:
        """Characteristic size of each parameter: mm for translations, 1 / radius otherwise."""
        out = np.full(self.size, 1.0 / radius)
        out[: self.dim] = 1.0
        return out

    def matrix(self, p: np.ndarray):
        """``M`` and what its derivatives need: the rotation, scale and right Jacobian."""
        d = self.dim
        if self.kind == "affine":
            return np.eye(d) + p[d:].reshape(d, d), None, 1.0, None
        if d == 3:
            v = p[3:6]
            theta = float(np.linalg.norm(v))
            if theta < 1e-12:
                rot = np.eye(3)
            else:
                k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / theta
                rot = np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * k @ k
            jr = _right_jacobian(v)
        else:
            c, s = np.cos(p[2]), np.sin(p[2])
            rot, jr = np.array([[c, -s], [s, c]]), None
        scale = float(np.exp(p[-1])) if self.kind == "similarity" else 1.0
        return scale * rot, rot, scale, jr

    def derivative_rows(self, h: np.ndarray, u: np.ndarray, parts) -> np.ndarray:
        """Rows ``h^T d(M u)/dp`` for the non-translation parameters, (N, size - D)."""
        m, rot, scale, jr = parts
        d = self.dim
        if self.kind == "affine":
            return (h[:, :, None] * u[:, None, :]).reshape(len(h), d * d)
        cols = []
        if d == 3:
            q = h @ rot  # rows R^T h
            cols.append(scale * np.cross(u, q) @ jr)
        else:
            ju = np.stack([-u[:, 1], u[:, 0]], axis=1)
            cols.append((scale * np.sum(h * (ju @ rot.T), axis=1))[:, None])
        if self.kind == "similarity":
            cols.append(np.sum(h * (u @ m.T), axis=1)[:, None])
        return np.hstack(cols)

    def compose(self, start: LinearMap, p: np.ndarray, centre: np.ndarray) -> LinearMap:
        """The map ``start o G``."""
        m = self.matrix(p)[0]
        a0, b0 = start.matrix, start.translation
        return LinearMap(a0 @ m, a0 @ (centre - m @ centre + p[: self.dim]) + b0)


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


class _Cost:
    """The symmetric locational distance cost (paper eq. 3 with exact signed distances).

    Fixed boundary points ``x`` count ``d_m(T x)^2``, moving boundary points ``y``
    count ``d_f(T^-1 y)^2``, with ``T = start o G(p)``; residuals are ``sqrt(w) d``
    and their Jacobian is analytic (chain rule through the interpolated gradients).
    """

    def __init__(self, local: _Local, start: LinearMap, centre: np.ndarray, bank_f: _MapBank, bank_m: _MapBank,
                 fwd: _Samples, back: _Samples):
        self.local, self.start, self.centre = local, start, centre
        self.bank_f, self.bank_m = bank_f, bank_m
        self.fwd, self.back = fwd, back
        self.look_f, self.look_b = bank_m.lookup(fwd.which), bank_f.lookup(back.which)
        self.u = fwd.points - centre
        self.v = start.inverse()(back.points) - centre
        self.sw_f, self.sw_b = np.sqrt(fwd.weights), np.sqrt(back.weights)
        self._key = None

    def evaluate(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = p.tobytes()
        if key == self._key:
            return self._r, self._jac
        d = self.local.dim
        parts = self.local.matrix(p)
        m = parts[0]
        a0, b0 = self.start.matrix, self.start.translation
        t = p[:d]
        res, rows = [], []
        if len(self.fwd):
            y = self.u @ (a0 @ m).T + (a0 @ (self.centre + t) + b0)
            dist, g = self.bank_m.sample(self.look_f, y)
            h = g @ a0
            res.append(self.sw_f * dist)
            rows.append(self.sw_f[:, None] * np.hstack([h, self.local.derivative_rows(h, self.u, parts)]))
        if len(self.back):
            det = np.linalg.det(m)
            if not det > 1e-6:
                r = np.full(len(self.fwd) + len(self.back), 1e6)
                self._key, self._r, self._jac = key, r, np.zeros((len(r), self.local.size))
                return self._r, self._jac
            minv = np.linalg.inv(m)
            w = (self.v - t) @ minv.T
            dist, g = self.bank_f.sample(self.look_b, self.centre + w)
            h = g @ minv
            res.append(self.sw_b * dist)
            rows.append(-self.sw_b[:, None] * np.hstack([h, self.local.derivative_rows(h, w, parts)]))
        self._key, self._r, self._jac = key, np.concatenate(res), np.vstack(rows)
        return self._r, self._jac


# ----------------------------------------------------------------------------- the driver


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


def _finite(value: float) -> float | None:
    """``value`` as a float, or None when it is NaN or infinite (JSON has neither)."""
    return float(value) if np.isfinite(value) else None


def _voxel_size(volume) -> float:
    """Geometric mean of the voxel sides, mm."""
    return float(np.prod(volume.spacing) ** (1.0 / volume.ndim))


def _run(local, start, centre, bank_f, bank_m, fwd, back, f_scale, radius, max_nfev, tol):
    """One least-squares solve from ``start``; the field-of-view masks are those of ``start``."""
    from scipy.optimize import least_squares

    keep_f = fwd.kept(bank_m.volume, start(fwd.points))
    keep_b = back.kept(bank_f.volume, start.inverse()(back.points))
    fwd_k, back_k = fwd.subset(keep_f), back.subset(keep_b)
    n_valid, n_total = len(fwd_k) + len(back_k), len(fwd) + len(back)
    if n_valid < local.size:
        return start, dict(cost=float("inf"), score=float("inf"), iterations=0, valid=n_valid, total=n_total,
                           mean_abs_distance_mm=float("nan")), (keep_f, keep_b)
    cost = _Cost(local, start, centre, bank_f, bank_m, fwd_k, back_k)
    result = least_squares(
        lambda p: cost.evaluate(p)[0], np.zeros(local.size), jac=lambda p: cost.evaluate(p)[1],
        method="trf", tr_solver="lsmr", loss="soft_l1", f_scale=f_scale, x_scale=local.x_scale(radius),
        max_nfev=max_nfev, xtol=tol, ftol=tol, gtol=tol,
    )
    found = local.compose(start, result.x, centre)
    r = cost.evaluate(result.x)[0]
    weights = np.concatenate([fwd_k.weights, back_k.weights])
    info = dict(
        cost=float(result.cost),
        # Mean robust cost per sample, raised where samples left the field of view (a
        # start cannot win by pushing the labels out of the image).
        score=float(result.cost / n_valid * (n_total / n_valid) ** 2),
        iterations=int(result.nfev),
        valid=int(n_valid),
        total=int(n_total),
        mean_abs_distance_mm=float(np.sum(np.abs(r) * np.sqrt(weights)) / np.sum(weights)),
    )
    return found, info, (keep_f, keep_b)


def _mean_dice(fixed, moving, maps: list[LinearMap], labels: list[int], boxes_f: dict, pooled: bool = False
               ) -> np.ndarray:
    """Mean Dice over ``labels`` of the fixed labels and the moving ones read through each map
    (nearest neighbour), at most about 2^18 fixed voxel centres: the labels' box widened by half
    its size on each side, every ``step``-th voxel.  ``pooled``: the labels' overlaps and sizes
    summed before the ratio (``sum 2 |A_v & B_v| / sum (|A_v| + |B_v|)``), so that each label
    weighs by its size and a label of a few voxels cannot outweigh the rest.

    Only voxels sent into the moving image count: beyond its field of view the moving image
    says nothing (read as background there, a map that squeezed the fixed labels into a moving
    image cut through them overlapped "better" than the right one).  A map under which no label
    lies on either side of the voxels it sends inside scores 0 (nothing it aligns was seen; the
    identity of two images apart); the others are compared on the voxels that all of them send
    inside, each over the labels on either side there (a map with none there scores 0).

    Returns
    -------
    (len(maps),) float ndarray
    """
    from volreg.evaluation.metrics import dice
    from volreg.kernels.grid import rows_within
    from volreg.warp.resample import resample_labels_at

    lo = np.min([[b.start for b in boxes_f[v]] for v in labels], axis=0)
    hi = np.max([[b.stop for b in boxes_f[v]] for v in labels], axis=0)
    reach = (hi - lo) // 2
    lo, hi = np.maximum(lo - reach, 0), np.minimum(hi + reach, fixed.shape)
    step = max(1, int(np.ceil((np.prod(hi - lo, dtype=float) / 2**18) ** (1.0 / fixed.ndim))))
    axes = [np.arange(a, b, step) for a, b in zip(lo, hi)]
    index = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, fixed.ndim)
    points = fixed.index_to_world(index)
    label_f = fixed.array[tuple(index.T)]
    size_m = np.array(moving.shape)
    wanted = np.isin(label_f, labels)

    def seen(where: np.ndarray, label_m: np.ndarray) -> list:
        present = set(np.unique(label_f[where & wanted]).tolist())
        present |= set(np.unique(label_m[where]).tolist())
        return [v for v in labels if v in present]

    insides, reads = [], []
    for linear in maps:
        at = moving.world_to_index(linear(points))
        insides.append(rows_within(at, np.full(moving.ndim, -0.5), size_m - 0.5))
        reads.append(resample_labels_at(moving, at, method="nearest"))  # background outside
    active = [k for k in range(len(maps)) if seen(insides[k], reads[k])]
    common = np.logical_and.reduce([insides[k] for k in active]) if active else np.zeros(len(points), bool)
    out = []
    for k in range(len(maps)):
        compared = seen(common, reads[k]) if k in active else []
        if not compared:
            out.append(0.0)
            continue
        f, m = label_f[common], reads[k][common]
        if pooled:
            both = sum(2 * np.count_nonzero((f == v) & (m == v)) for v in compared)
            size = sum(np.count_nonzero(f == v) + np.count_nonzero(m == v) for v in compared)
            out.append(both / size)
        else:
            out.append(float(np.mean([dice(f == v, m == v) for v in compared])))
    return np.array(out)


def fit_linear(fixed, moving, *, kind: str = "affine", labels=None, progress=None) -> LinearFit:
    """Find the linear pull-back ``x -> A x + b`` (fixed -> moving, LPS mm) that aligns two label volumes.

    A closed-form start from the labels' moments, tested by the cost below, then a
    coarse-to-fine least-squares fit of the symmetric locational distance cost
    (paper eq. 3, with the labels' exact signed distances as the feature functions).

    1. **Start.** Per label: volume, centroid and second moments in world mm.  When
       at least D + 1 labels, uncut by the image edge in both volumes, have centroids
       that span the space, a weighted Procrustes fit of the centroid pairs (Kabsch
       for rigid, Umeyama for similarity, least squares for affine when well
       conditioned).  Otherwise the principal axes of the labels' union,
       ``R = E_m diag(s) E_f^T`` for each sign choice with det +1, with the centroids'
       translation and the volume ratio's scale (for an affine map, the scales along
       the axes that carry one union's second moments onto the other's:
       ``E_m diag(s sqrt(l_m / l_f)) E_f^T``); and the centroid translation alone.
       The identity is always a candidate.  Each candidate runs a few iterations at
       the coarsest level; of those whose cost is within 1.5 times the lowest, the
       least rotated start wins (a near-symmetric object also fits upside down).
    2. **Refinement.** Per label and volume, signed distance maps (mm, positive
       outside) on the volume's grid coarsened towards the level's spacing
       (object diameter / 16, / 32, / 64, never finer than the coarser volume's
       voxel, nor coarser than half a label's thickness) over the label's box plus a
       margin.  Samples are each label's boundary (voxel-face centres), thinned to a
       bounded number per label: fixed ones cost ``d_m(A x + b)^2``, moving ones
       ``d_f(A^-1 (y - b))^2`` (the symmetric cost keeps an affine map from
       shrinking), under a soft-L1 loss of scale twice the level's spacing, each
       label weighted by its boundary area.  ``scipy.optimize.least_squares`` with
       the analytic Jacobian; the parameters are about the fixed centroid
       (translation, rotation vector or angle, log-scale, or the full matrix).  For an
       affine map the starts' iterations and every level but the finest fit a
       similarity about the start's matrix, the finest level the full matrix: a smooth
       object turned is matched by a stretch along oblique axes as well as by the
       turn, and a coarse affine fit took the stretch (a spheroid turned 20 degrees:
       6 degrees found, its long axis 11 degrees off).  Where the principal axes
       started the fit and two of the union's second moments are within 10 % of each
       other, the turn about the third axis is not shown at the coarse levels (a
       spheroidal brain shows it only by its folds): before the finest level is
       solved, its cost is evaluated at turns about that axis in steps of 5 degrees
       and the lowest kept (of those within 2 % of it, the smallest turn), logged as
       ``turn_search``.
    3. **Partial fields of view.** Samples of a label cut by the edge of either image
       (:func:`cut_labels`) whose image falls outside the other volume's field of view
       less two of its voxels carry no cost, and cut labels are left out of the
       centroid start.  Samples of uncut labels always count (beyond a map's box its
       distance keeps growing), so no map wins by pushing a label out of view.
    4. **Overlap check.** The labels' mean Dice through the identity, the chosen start and
       the fitted map (nearest neighbour, at most about 2^18 fixed voxels); the first of
       them, in that order, whose Dice is the highest is kept.  Where the labels do not
       determine the map (one smooth organ: every ``A = L R L^-1`` maps an ellipsoid of
       semi-axes ``L`` onto itself) the fit drifts with the grids' differences without
       overlapping better, and on grids too coarse for the object (one organ over a few
       5 mm slices) it can run into a degenerate map that the coarse samples favour.

    The ``MAX_LINEAR_LABELS`` largest labels (by volume in ``fixed``) drive the fit.

    Parameters
    ----------
    fixed, moving : LabelVolume
        The two volumes, of one dimension (2 or 3).
    kind : {"none", "rigid", "similarity", "affine"}
        The family of maps; ``"none"`` returns the identity at once.
    labels : sequence of int, optional
        Labels to align (non-zero, present in both volumes).  Default: every non-zero
        label present in both.
    progress : callable, optional
        ``progress(stage, done, total)``: ``"linear start"`` per candidate, then
        ``"fit linear"`` per level.

    Returns
    -------
    LinearFit
        The map and a JSON-ready log.

    Raises
    ------
    ValueError
        An unknown ``kind``; volumes of different dimensions; a requested label absent
        from a volume; no label in common (:class:`~volreg.errors.RegistrationInputError`).
    """
    import time

    from volreg.errors import RegistrationInputError

    t_begin = time.perf_counter()
    if kind not in LINEAR_KINDS:
        raise ValueError(f"Expected `kind` in {LINEAR_KINDS}, got {kind!r}.")
    if moving.ndim != fixed.ndim:
        raise ValueError(f"Expected `moving` of the same dimension as `fixed` ({fixed.ndim}-D), got {moving.ndim}-D.")
    dim = fixed.ndim
    if kind == "none":
        ident = LinearMap.identity(dim)
        return LinearFit(ident, dict(kind="none", start="identity", start_candidate="identity", candidates=[],
                                     levels=[], labels=[],
                                     cut_labels=dict(fixed=cut_labels(fixed), moving=cut_labels(moving)),
                                     map=ident.describe(), seconds=time.perf_counter() - t_begin))

    boxes_f, boxes_m = fixed.label_boxes(), moving.label_boxes()
    if labels is None:
        chosen = sorted(set(boxes_f) & set(boxes_m))
        if not chosen:
            raise RegistrationInputError("Expected `fixed` and `moving` to share a non-zero label, found none.")
    else:
        chosen = sorted({int(v) for v in labels})
        absent = [v for v in chosen if v == 0 or v not in boxes_f or v not in boxes_m]
        if absent or not chosen:
            raise RegistrationInputError(
                f"Expected `labels` to be non-zero labels present in both volumes, got {absent[:10] or 'none'}.")

    # The largest labels drive the fit.
    voxel_f = float(np.prod(fixed.spacing))
    sizes = {v: int(np.count_nonzero(fixed.array[boxes_f[v]] == v)) * voxel_f for v in chosen}
    drive = sorted(sorted(chosen, key=lambda v: -sizes[v])[:MAX_LINEAR_LABELS])
    cap = _LEVEL_SAMPLES[-1]
    shapes_f = {v: _label_shape(fixed, v, boxes_f[v], cap, np.random.default_rng(abs(v))) for v in drive}
    shapes_m = {v: _label_shape(moving, v, boxes_m[v], cap, np.random.default_rng(abs(v))) for v in drive}
    side_f, side_m = _Side(fixed, shapes_f), _Side(moving, shapes_m)
    cut_f, cut_m = cut_labels(fixed), cut_labels(moving)
    cut = set(cut_f) | set(cut_m)

    if not any(len(s.points) for s in shapes_f.values()) or not any(len(s.points) for s in shapes_m.values()):
        # No label has a boundary inside an image (a volume filled by one label): nothing to align.
        ident = LinearMap.identity(dim)
        return LinearFit(ident, dict(kind=kind, start="identity", start_candidate="identity (no label boundary in an "
                                     "image)", candidates=[], levels=[], labels=[int(v) for v in drive],
                                     cut_labels=dict(fixed=cut_f, moving=cut_m), map=ident.describe(),
                                     seconds=time.perf_counter() - t_begin))

    # Object size, centre, levels.
    _, centre, _ = _union_moments(list(shapes_f.values()))
    lo = np.min([s.points.min(axis=0) for s in shapes_f.values() if len(s.points)], axis=0)
    hi = np.max([s.points.max(axis=0) for s in shapes_f.values() if len(s.points)], axis=0)
    diameter = max(float(np.linalg.norm(hi - lo)), 1e-6)
    radius = 0.5 * diameter
    floor_mm = max(_voxel_size(fixed), _voxel_size(moving))
    levels: list[tuple[float, int, tuple]] = []
    for i, div in enumerate(_LEVEL_DIVISORS):
        h = max(floor_mm, diameter / div)
        grids = (tuple(_level_factors(fixed, h)), tuple(_level_factors(moving, h)))
        if levels and levels[-1][2] == grids:
            levels[-1] = (h, i, grids)  # the same grids as the coarser level: one level
        else:
            levels.append((h, i, grids))
    spacings = [h for h, _, _ in levels]
    counts = [min(_LEVEL_SAMPLES[i], _LEVEL_TOTAL[i] // len(drive)) for _, i, _ in levels]
    local = _Local(kind, dim)
    # For an affine map the starts and every level but the finest fit a similarity about the
    # start's matrix (which keeps the start's own stretch), the finest the whole affine map: a
    # smooth object turned can be matched by a stretch along oblique axes as well (every
    # ``A = L R L^-1`` maps an ellipsoid of semi-axes ``L`` onto itself), and a coarse affine fit
    # stopped there, short of the turn that the finer levels' detail then needed.
    coarse_local = _Local("similarity", dim) if kind == "affine" and len(spacings) > 1 else local

    # Candidates.
    uncut = [v for v in drive if v not in cut]
    weights = np.array([np.sqrt(shapes_f[v].volume_mm3 * shapes_m[v].volume_mm3) for v in uncut])
    candidates: list[tuple[str, str, LinearMap]] = []
    if uncut and _spans(np.array([shapes_f[v].centroid for v in uncut]), weights) and \
            _spans(np.array([shapes_m[v].centroid for v in uncut]), weights):
        pf = np.array([shapes_f[v].centroid for v in uncut])
        pm = np.array([shapes_m[v].centroid for v in uncut])
        fitted, model = _procrustes(pf, pm, weights, kind)
        candidates.append(("centroids", f"centroids ({model})", fitted))
        _, cf, _ = _union_moments([shapes_f[v] for v in uncut])
        _, cm, _ = _union_moments([shapes_m[v] for v in uncut])
        candidates.append(("centroids", "centroid translation", LinearMap(np.eye(dim), cm - cf)))
    else:
        basis = uncut if uncut else drive
        for name, cand in _axis_candidates([shapes_f[v] for v in basis], [shapes_m[v] for v in basis], kind):
            family = "centroids" if name == "centroid translation" else "principal axes"
            candidates.append((family, name, cand))
    candidates.append(("identity", "identity", LinearMap.identity(dim)))

    _make_maps([side_f, side_m], drive, spacings[0], floor_mm)
    bank_f, where_f = side_f.bank(drive, spacings[0], floor_mm)
    bank_m, where_m = side_m.bank(drive, spacings[0], floor_mm)
    fwd = side_f.samples(drive, where_m, counts[0], cut)
    back = side_m.samples(drive, where_f, counts[0], cut)
    norm = np.mean(np.concatenate([fwd.weights, back.weights])) if len(fwd) + len(back) else 1.0
    fwd.weights, back.weights = fwd.weights / norm, back.weights / norm
    f_scale = 2.0 * spacings[0]
    tried = []
    scored = []
    for i, (family, name, cand) in enumerate(candidates):
        found, info, _ = _run(coarse_local, cand, centre, bank_f, bank_m, fwd, back, f_scale, radius,
                              _CANDIDATE_EVALUATIONS, 1e-5)
        described = cand.describe()
        tried.append(dict(name=name, family=family, start=described, cost=_finite(info["score"]),
                          iterations=info["iterations"]))
        scored.append((info["score"], round(described["rotation_deg"]), i, family, name, found))
        if progress is not None:
            progress("linear start", i + 1, len(candidates))
    # Of the starts that fit about as well as the best, the least rotated (whole degrees, then
    # the order above): near-symmetric anatomy fits turned upside down almost as well, and
    # scans are rarely upside down.  The start's rotation, not that of its few iterations: on
    # grids too coarse for the object the coarse cost turns even the right start.
    lowest = min(row[0] for row in scored)
    near = [row for row in scored if row[0] <= _NEAR_BEST * lowest]
    _, _, index, start_family, start_name, current = min(near or scored, key=lambda row: (row[1], row[2]))
    chosen_start = candidates[index][2]
    # Where the labels' moments are (nearly) symmetric about an axis and no spread of label
    # centroids shows the turn about it, only finer detail does (a spheroidal brain's folds):
    # the coarse levels cannot tell, and the finest level's cost is searched over that turn.
    by_centroids = any(family == "centroids" and name != "centroid translation" for family, name, _ in candidates)
    turn_axis = None if by_centroids or dim != 3 else _free_axis([shapes_f[v] for v in (uncut or drive)])
    turn_log = None

    # Coarse to fine.
    level_log = []
    for level, (h, count) in enumerate(zip(spacings, counts)):
        _make_maps([side_f, side_m], drive, h, floor_mm)
        bank_f, where_f = side_f.bank(drive, h, floor_mm)
        bank_m, where_m = side_m.bank(drive, h, floor_mm)
        fwd = side_f.samples(drive, where_m, count, cut)
        back = side_m.samples(drive, where_f, count, cut)
        norm = np.mean(np.concatenate([fwd.weights, back.weights])) if len(fwd) + len(back) else 1.0
        fwd.weights, back.weights = fwd.weights / norm, back.weights / norm
        f_scale = 2.0 * h
        iterations = 0
        if turn_axis is not None and level == len(spacings) - 1 and len(spacings) > 1:
            current, turn_log = _turn_search(current, turn_axis, centre, lambda m: _run(
                coarse_local, m, centre, bank_f, bank_m, fwd, back, f_scale, radius, 1, _LEVEL_TOLERANCE)[1]["score"])
        for _ in range(3):  # solve again while the field-of-view masks change
            # 1e-5 at every level: the last level at 1e-8 took 15 evaluations instead of 6 on the
            # 100-label parcellation (0.1 s) and moved the map by 1e-6 of its matrix and 1e-5 mm,
            # far below what the kernel warp then corrects.
            level_local = local if level == len(spacings) - 1 else coarse_local
            found, info, used = _run(level_local, current, centre, bank_f, bank_m, fwd, back, f_scale, radius,
                                     _LEVEL_EVALUATIONS, _LEVEL_TOLERANCE)
            iterations += info["iterations"]
            if not np.isfinite(info["cost"]):
                break
            current = found
            after = (fwd.kept(moving, current(fwd.points)), back.kept(fixed, current.inverse()(back.points)))
            if all(np.array_equal(a, b) for a, b in zip(used, after)):
                break
        level_log.append(dict(spacing_mm=float(h), f_scale_mm=float(f_scale), samples=int(info["valid"]),
                              samples_outside_view=int(info["total"] - info["valid"]), cost=_finite(info["cost"]),
                              iterations=int(iterations),
                              mean_abs_distance_mm=_finite(info["mean_abs_distance_mm"])))
        if progress is not None:
            progress("fit linear", level + 1, len(spacings))

    # The fit minimises boundary distances on maps coarsened to each level.  Where the labels do
    # not determine the map it drifts with the grids' differences (one smooth organ: every
    # A = L R L^-1 maps an ellipsoid of semi-axes L onto itself), and on grids too coarse for the
    # object (a few thick slices) it can run into a degenerate map the coarse samples favour.
    # The labels' overlap checks it: the chosen start is kept instead of the fitted map where its
    # mean Dice is as high, to KEEP_MARGIN (and above 0: on voxels where neither overlaps a label
    # the two are not told apart), then the identity instead of that likewise. Two maps at a
    # time, each pair on the voxels both send into the moving image: all three at once were
    # compared on the voxels every one of them sends inside, which for images far apart (33 mm on
    # a 40 mm grid) is a corner far from the labels, where the centroids' translation beat a fit
    # that had found the 22 degree turn, and the identity one that had found a 45 mm shift.
    maps = [("identity", LinearMap.identity(dim)), ("start", chosen_start), ("refined", current)]
    overlap = {}
    pick = len(maps) - 1
    for k in range(len(maps) - 2, -1, -1):
        pair = _mean_dice(fixed, moving, [maps[k][1], maps[pick][1]], drive, boxes_f)
        overlap.setdefault(maps[pick][0], float(pair[1]))
        overlap[maps[k][0]] = float(pair[0])
        if pair[0] >= pair[1] - KEEP_MARGIN and pair[0] > 0:
            pick = k
    kept = None if pick == len(maps) - 1 else maps[pick][0]
    current = maps[pick][1]
    log = dict(
        kind=kind,
        overlap={name: overlap[name] for name, _ in maps},
        kept_instead=kept,
        start=start_family,
        start_candidate=start_name,
        candidates=tried,
        levels=level_log,
        labels=[int(v) for v in drive],
        cut_labels=dict(fixed=cut_f, moving=cut_m),
        diameter_mm=diameter,
        map=current.describe(),
        seconds=time.perf_counter() - t_begin,
    )
    if turn_log is not None:
        log["turn_search"] = turn_log
    return LinearFit(current, log)


def _free_axis(shapes: list[_LabelShape]) -> np.ndarray | None:
    """The axis (3,) about which the union's second moments are nearly symmetric (two of them
    within :data:`_TURN_AXIS_TOL` of each other), or None."""
    _, _, cov = _union_moments(shapes)
    lam, vec = np.linalg.eigh(cov)  # ascending
    if lam[2] <= 0:
        return None
    if (lam[2] - lam[1]) / lam[2] < _TURN_AXIS_TOL:
        return vec[:, 0]
    if (lam[1] - lam[0]) / max(lam[1], 1e-300) < _TURN_AXIS_TOL:
        return vec[:, 2]
    return None


def _turned(linear: LinearMap, axis: np.ndarray, centre: np.ndarray, angle: float) -> LinearMap:
    """``x -> L(R (x - c) + c)``: ``linear`` after a turn by ``angle`` (rad) about ``axis``
    (unit, (3,)) through ``centre`` (mm)."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_rotvec(angle * np.asarray(axis, float)).as_matrix()
    return LinearMap(linear.matrix @ rot, linear.matrix @ (centre - rot @ centre) + linear.translation)


def _turn_search(current: LinearMap, axis: np.ndarray, centre: np.ndarray, score) -> tuple[LinearMap, dict]:
    """``current`` turned about ``axis`` through ``centre`` by the multiple of :data:`_TURN_STEP_DEG`
    whose ``score(map)`` is lowest (of those within :data:`_TURN_TIE` of it, the smallest turn),
    and a JSON-ready log: the axis, the turn (degrees), its score and the lowest score more than
    three steps from it (the runner-up: close to the best where the labels do not show the turn)."""
    import time

    t0 = time.perf_counter()
    angles = np.arange(0.0, 360.0, _TURN_STEP_DEG)
    maps = [_turned(current, axis, centre, np.radians(a)) for a in angles]
    scores = np.array([score(m) for m in maps])
    signed = (angles + 180.0) % 360.0 - 180.0  # the turn in (-180, 180], degrees
    size = np.abs(signed)
    finite = np.isfinite(scores)
    if not finite.any():
        return current, dict(axis=[float(v) for v in axis], degrees=0.0, score=None, runner_up=None,
                             seconds=time.perf_counter() - t0)
    best = float(scores[finite].min())
    near = np.flatnonzero(finite & (scores <= best * (1.0 + _TURN_TIE)))
    pick = int(near[np.argmin(size[near])])
    apart = np.abs((angles - angles[pick] + 180.0) % 360.0 - 180.0) > 3 * _TURN_STEP_DEG
    others = scores[apart & finite]
    return maps[pick], dict(axis=[float(v) for v in axis], degrees=float(signed[pick]), score=float(scores[pick]),
                            runner_up=float(others.min()) if others.size else None, seconds=time.perf_counter() - t0)

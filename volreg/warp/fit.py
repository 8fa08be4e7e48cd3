"""The coarse-to-fine fit of the kernel warp (paper Section 3.5).

For each level, from a kernel width of half the source diameter down to
``min_width`` (halving each time):

1. sample the warp volume X -- the source surfaces padded by ``pad`` mm -- by
   octree subdivision down to boxes of half the width (Section 3.5); the box
   centres are the level's kernel centres.  The locational cost is sampled at
   the finest level's boxes on every level (not in the paper, whose coarse
   levels see only their own few boxes), and each feature only within a band
   around its source surface (``WarpSettings.band``) and, given ``valid``, only
   where ``valid`` holds (e.g. where the target image sees the object);
2. with landmarks, start from the convex problem (12): kernel ridge regression
   of the landmark residuals, solved exactly;
3. minimise the objective (11) (:class:`~volreg.warp.objective.LevelObjective`)
   over the level's coefficients with L-BFGS (Gauss-Newton steps for the smallest
   levels, :func:`_gauss_newton`), on top of the coarser levels, plus a fold
   barrier on ``det d tau / dx`` (not in the paper);
4. guard against folding: if ``det d tau / dx`` falls below ``min_det`` at a
   sample or at the centre of one of its octree children, shrink the level's
   coefficients until it does not (not in the paper, which has no such
   safeguard; logged as ``fold_scale``).

The driver, :func:`fit_warp`, only walks the levels (:func:`_level_schedule`):
it keeps the locational-cost samples of consecutive levels that share a sample
spacing (:class:`_SampleSet`) and hands each level to the per-level solver,
:func:`_fit_level` (steps 2-4).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence
import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.sparse as sp
import scipy.sparse.linalg
from scipy.spatial import cKDTree
from volreg._memory import memory_limit
from volreg._threads import single_blas
from volreg.kernels import CellGrid, SharedPatternCSR, check_points, kernel_gradient_matrices, kernel_matrix, kernel_sum
from volreg.kernels.grid import column_bounds
from volreg.warp.objective import FeaturePair, LevelObjective, simplex_vertices
from volreg.warp.sampling import octree_sample
from volreg.warp.model import KernelWarp, WarpLevel, jacobian_det
from volreg.errors import ProtocolError, RegistrationDiverged
from volreg.settings import WarpSettings

__all__ = ["RegistrationResult", "check_folding", "fit_warp"]


#: Fold-check points with det J below ``fold_margin + FOLD_SLACK`` carry the fold barrier
#: during a level's fit; the rest are checked after it (see :func:`fit_warp`).
FOLD_SLACK = 0.3


#: At most this many fits per level, each adding the points that crossed ``fold_margin``.
FOLD_ROUNDS = 5


def check_folding(warp: KernelWarp, reference, det: np.ndarray, max_fraction: float) -> None:
    """Stop a registration whose warp folds too much of the output grid.

    The fold barrier and guard keep ``det d tau / dx`` positive at the octree samples;
    between them, on a finer voxel grid, a warp can still fold.  This checks the grid.

    Parameters
    ----------
    warp : KernelWarp
        The fitted warp.
    reference : LabelVolume
        The grid ``det`` was computed on (the fixed image).
    det : (*reference.shape) float ndarray
        ``det d tau / dx`` of ``warp`` at every voxel (``jacobian_determinant_on_grid``).
    max_fraction : float
        Largest acceptable fraction of voxels with ``det <= 0``.

    Raises
    ------
    RegistrationDiverged
        If more than ``max_fraction`` of the voxels fold; the message names the first
        level whose addition crossed the threshold (found by re-evaluating the partial
        sums of the levels, only on this failure path) and suggests protocol changes.
    """
    from volreg.warp.field import jacobian_determinant_on_grid
    from volreg.evaluation.metrics import folded_fraction

    folded = folded_fraction(det)
    if folded <= max_fraction:
        return
    levels = warp.levels
    first = len(levels) - 1
    for k in range(1, len(levels)):
        if folded_fraction(jacobian_determinant_on_grid(KernelWarp(levels[:k], dim=warp.dim, linear=warp.linear), reference)) > max_fraction:
            first = k - 1
            break
    raise RegistrationDiverged(
        f"Warp level {first} (kernel width {levels[first].width:.3g} mm) folds space: det(d tau/dx) <= 0 at "
        f"{100 * folded:.2f} % of the fixed grid's voxels, more than max_folded_fraction = {100 * max_fraction:.2g} %. "
        "Change the protocol: raise min_width (or set it to a larger kernel width), lower lambda_loc or alpha, "
        "or raise lambda_fold."
    )


@dataclass
class RegistrationResult:
    """A fitted warp and its per-level log."""

    warp: KernelWarp
    log: list[dict] = field(default_factory=list)


def _landmark_init(kernel_cc, kernel_lc, base_l, targets, lambda_p) -> np.ndarray:
    """Solve (12) for every component: min 1/2 c^T K c + lambda_p |base + K_l c - z|^2.

    Its stationarity condition is the sparse symmetric positive definite system
    ``(K + 2 lambda_p K_l^T K_l) c = 2 lambda_p K_l^T (z - base)``.
    """
    a = (kernel_cc + 2 * lambda_p * (kernel_lc.T @ kernel_lc)).tocsc()
    rhs = 2 * lambda_p * (kernel_lc.T @ (targets - base_l))
    return np.column_stack([scipy.sparse.linalg.spsolve(a, rhs[:, d]) for d in range(rhs.shape[1])])


def _with_children(samples: np.ndarray) -> np.ndarray:
    """Octree samples (on a lattice) plus the centres of their 2^D child boxes."""
    if len(samples) < 2:
        return samples
    edge = float(np.median(cKDTree(samples).query(samples, 2)[0][:, 1]))
    dim = samples.shape[1]
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * dim, indexing="ij")).reshape(dim, -1).T
    children = (samples[:, None, :] + 0.25 * edge * signs[None]).reshape(-1, dim)
    return np.concatenate([samples, children])


def _feature_samples(features, samples: np.ndarray, band: float | None, reach: float) -> list | None:
    """Per feature pair, the samples where its locational cost is counted.

    A sample counts for a feature when it lies within ``band`` mm of the feature's
    source surface points (``|f1(x)| <= band`` for features without points),
    where an implicit surface is distance-like.  Farther out a kernel fit
    extrapolates freely, and ``f1`` and ``f2`` differ there by fitting artefacts
    of tens of mm that the warp would try to explain (far more than near the
    surfaces).  ``band=None`` takes half the finest kernel width of ``f1``
    (objects with ``widths``) or every sample; the narrower the band, the fewer of
    those artefacts the warp follows.

    Returns ``None`` when every feature counts every sample.
    """
    out = []
    for pair in features:
        limit = band
        if hasattr(pair.f1, "band"):  # a feature with its own band (a VoxelDistance)
            limit = pair.f1.band
        elif limit is None and hasattr(pair.f1, "widths"):
            limit = 0.5 * float(min(pair.f1.widths))
        if limit is None or not hasattr(pair.f1, "bounds"):
            out.append(None)
            continue
        if hasattr(pair.f1, "points"):
            # Distance to the surface points, not |f1|: far from its surface a kernel fit can
            # pass through 0 again, which would let far-away samples in.  Only the samples in
            # the points' box grown by that distance can be that near (one label of many: few).
            pts = pair.f1.points
            r = limit + reach
            lo, hi = column_bounds(pts)
            idx = np.flatnonzero(np.all((samples >= lo - r) & (samples <= hi + r), axis=1))
            dist = cKDTree(pts).query(samples[idx], distance_upper_bound=r)[0]
            out.append(idx[np.isfinite(dist)])
            continue
        lo, hi = pair.f1.bounds()
        idx = np.flatnonzero(np.all((samples >= lo - reach) & (samples <= hi + reach), axis=1))
        if len(idx):
            idx = idx[np.abs(pair.f1.evaluate(samples[idx], order=0)[0]) <= limit + reach]
        out.append(idx)
    return None if all(o is None for o in out) else out


def _valid_subsets(subsets: list | None, valid: Callable[[np.ndarray], np.ndarray], samples: np.ndarray,
                   n_features: int) -> tuple[list | None, int]:
    """Intersect the per-feature samples with the samples where ``valid`` holds.

    Parameters
    ----------
    subsets : list of (N_l,) int ndarrays or None, or None
        Per feature, the samples where its locational cost counts (:func:`_feature_samples`);
        ``None`` (for one feature or for all) means every sample.
    valid : callable
        ``valid(samples) -> (N,) bool ndarray``.
    samples : (N, D) float ndarray, mm
        The locational-cost samples.
    n_features : int
        Number of feature pairs.

    Returns
    -------
    subsets : list of (N_l,) int ndarrays or None, or None
        ``subsets`` unchanged when ``valid`` holds at every sample; otherwise one
        sorted index array per feature.
    count : int
        Number of samples where ``valid`` holds.

    Raises
    ------
    ValueError
        If ``valid`` does not return a boolean array of shape (N,).
    """
    mask = np.asarray(valid(samples))
    if mask.shape != (len(samples),) or mask.dtype != bool:
        raise ValueError(f"Expected `valid` to return a bool array of shape ({len(samples)},) (one flag per "
                         f"sample), got {mask.dtype} of shape {mask.shape}.")
    count = int(np.count_nonzero(mask))
    if count == len(samples):
        return subsets, count
    keep = np.flatnonzero(mask)
    per_feature = [None] * n_features if subsets is None else subsets
    return [keep if idx is None else idx[mask[idx]] for idx in per_feature], count


@dataclass(frozen=True)
class _Inputs:
    """The checked inputs of one fit, shared by every level.

    Attributes
    ----------
    features : sequence of FeaturePair
    points : (N, D) float ndarray, mm
        The source surface points.
    diameter : float, mm
        Diagonal of the bounding box of ``points``.
    landmarks : pair of (L, D) float ndarrays, mm, or None
    settings : WarpSettings
        With ``pad`` and ``min_width`` resolved against ``diameter``.
    neighbourhood : (D + 1, D) float ndarray, mm, or None
        Offsets of the neighbourhood cost (5).
    prior : callable or None
    valid : callable or None
        ``valid(samples) -> (N,) bool``: where the locational cost may count.
    tree : scipy.spatial.cKDTree
        A k-d tree of ``points``, shared by every level's octree sampling.
    """

    features: Sequence[FeaturePair]
    points: np.ndarray
    diameter: float
    landmarks: tuple[np.ndarray, np.ndarray] | None
    settings: WarpSettings
    neighbourhood: np.ndarray | None
    prior: Callable[[np.ndarray], np.ndarray] | None
    valid: Callable[[np.ndarray], np.ndarray] | None = None
    tree: cKDTree | None = field(default=None, compare=False, repr=False)


def _check_inputs(features, source_points, landmarks, settings: WarpSettings, prior, valid=None) -> _Inputs:
    """Check the arguments of :func:`fit_warp` and resolve its data-derived settings."""
    if valid is not None and not callable(valid):
        raise ValueError(f"Expected `valid` as a callable (samples (N, D) mm -> (N,) bool) or None, "
                         f"got {type(valid).__name__}.")
    pts = check_points("source_points", source_points)
    if len(pts) < 2:
        raise ValueError(f"Expected at least 2 `source_points`, got {len(pts)}.")
    dim = pts.shape[1]
    lo, hi = column_bounds(pts)
    diameter = float(np.linalg.norm(hi - lo))
    if not diameter > 0:
        raise ValueError(f"Expected `source_points` of positive extent, got {len(pts)} copies of one point.")
    if landmarks is not None:
        if settings.lambda_p <= 0:
            raise ValueError("Expected `lambda_p` > 0 in `settings` when `landmarks` are given (it weighs them).")
        src_l, dst_l = (np.asarray(a, float) for a in landmarks)
        if src_l.shape != dst_l.shape or src_l.ndim != 2 or src_l.shape[1] != dim:
            raise ValueError(
                f"Expected `landmarks` as two arrays of shape (L, {dim}), got {src_l.shape} and {dst_l.shape}."
            )
        if len(src_l) > 1:
            close = sorted(cKDTree(src_l).query_pairs(1e-6 * diameter))
            if close:
                i, j = close[0]
                raise ValueError(f"Expected distinct source `landmarks`, got points {i} and {j} at the same place "
                                 f"({src_l[i].tolist()} mm).")
        landmarks = (src_l, dst_l)
    neighbourhood = simplex_vertices(dim, settings.neighbourhood) if settings.neighbourhood > 0 else None
    return _Inputs(features, pts, diameter, landmarks, settings.resolved(diameter), neighbourhood, prior, valid,
                   cKDTree(pts))


#: Bytes of memory per locational-cost sample of a level's fit (features, neighbour lists,
#: gradients): an order of magnitude, for refusing impossible settings up front.
BYTES_PER_SAMPLE = 2048


def estimated_samples(points: np.ndarray, settings: WarpSettings, step: float) -> float:
    """About how many locational-cost samples the finest sample spacing ``step`` gives.

    The octree boxes (side ``settings.fraction * step``) fill the warp volume X, the
    points' neighbourhood of radius ``settings.pad``; its volume is taken as that of the
    points' padded bounding box (an overestimate for thin or sparse objects).

    Parameters
    ----------
    points : (N, D) float ndarray, mm
    settings : WarpSettings
        With ``pad`` resolved.
    step : float, mm

    Returns
    -------
    float
    """
    ext = np.ptp(np.asarray(points, float), axis=0)
    pad = float(settings.pad)
    box = float(settings.fraction) * float(step)
    return float(np.prod((ext + 2 * pad) / box))


def check_sample_memory(points: np.ndarray, settings: WarpSettings, step: float) -> None:
    """Refuse, before any work, settings whose samples (:func:`estimated_samples`) would not fit in memory.

    Raises
    ------
    ProtocolError
        Naming the settings (``min_width``, ``fraction``, ``sample_spacing``, ``pad``) and
        the estimate, when it exceeds the memory available now (or ``VOLREG_MAX_MEMORY_GB``).
    """
    n = estimated_samples(points, settings, step)
    available, known_as = memory_limit()
    if available is None or n * BYTES_PER_SAMPLE <= available:
        return
    raise ProtocolError(
        f"The warp settings min_width {settings.min_width:g} mm, fraction {settings.fraction:g}, sample_spacing "
        f"{step:g} mm and pad {settings.pad:g} mm would sample about {n:.2g} points at the finest level "
        f"(about {n * BYTES_PER_SAMPLE / 1024**3:.3g} GB) and {available / 1024**3:.3g} GB is {known_as}; expected a "
        f"larger `min_width`, `fraction` or `sample_spacing`, or a smaller `pad` (the objects are "
        f"{np.round(np.ptp(points, axis=0), 1).tolist()} mm across)."
    )


def _level_schedule(diameter: float, settings: WarpSettings) -> tuple[list[float], list[float]]:
    """Kernel width and locational-cost sample spacing of every level (Section 3.5).

    Parameters
    ----------
    diameter : float, mm
        Diagonal of the source's bounding box.
    settings : WarpSettings
        With ``min_width`` resolved (:meth:`WarpSettings.resolved`).

    Returns
    -------
    widths : list of float, mm
        ``diameter / 2, diameter / 4, ...`` down to ``min_width`` (the paper's cascade
        of 1/2, 1/4, ... of the diameter).
    steps : list of float, mm
        Per level, the octree size of the locational-cost samples (see
        ``WarpSettings.sample_spacing``).
    """
    widths = [diameter / 2]
    while widths[-1] / 2 >= settings.min_width * (1 - 1e-9):
        widths.append(widths[-1] / 2)
    # A min_width wider than the coarsest level leaves that level alone: its samples as if
    # min_width were its width (octree boxes wider than the object would hold no sample).
    min_width = min(settings.min_width, widths[-1])
    spacing = settings.sample_scale * min_width if settings.sample_spacing is None else settings.sample_spacing
    # Samples of the locational cost: the finest level's boxes at every level (the paper
    # samples each level at its own boxes, which leaves a coarse level a few dozen points
    # to estimate an integral over X), or `spacing` where that is finer, but no finer than
    # a quarter of the level's kernel width: a coarse level's smooth warp has nothing finer
    # for denser samples to find.
    return widths, [max(spacing, min(width / 4, min_width)) for width in widths]


@dataclass
class _SampleSet:
    """The locational-cost samples of consecutive levels that share a sample spacing.

    The coarser levels' warp at the samples and their Jacobian at the fold-check points
    are carried from level to level (:meth:`add_level`), not re-evaluated through every
    coarser level.

    Attributes
    ----------
    step : float, mm
        The octree size the samples were drawn at.
    points : (N, D) float ndarray, mm
        The samples ``x`` of the locational cost (octree box centres).
    check : (P, D) float ndarray, mm
        The fold-check points: the samples and, where they are sparser than half
        ``min_width``, the centres of their octree children.
    subsets : list of (N_l,) int ndarrays or None
        Per feature, the samples where it counts: within its band (:func:`_feature_samples`)
        and, given ``valid``, where ``valid`` holds (:func:`_valid_subsets`).
    consistency : dict
        ``sample_targets`` and ``lambda_target`` of the consistency term, or empty.
    base : (N, D) float ndarray, mm
        ``tau_prev(x)`` at ``points``.
    jacobian : (P, D, D) float ndarray
        ``d tau_prev / dx`` at ``check``.
    valid_count : int or None
        Number of samples where ``valid`` holds; ``None`` without ``valid``.
    shared : dict
        What the levels' objectives on these samples share (``LevelObjective.shared``).
    """

    step: float
    points: np.ndarray
    check: np.ndarray
    subsets: list | None
    consistency: dict
    base: np.ndarray
    jacobian: np.ndarray
    valid_count: int | None = None
    shared: dict = field(default_factory=dict, repr=False)

    @classmethod
    def build(cls, inputs: _Inputs, step: float, warp: KernelWarp) -> _SampleSet:
        """Samples at octree size ``step`` (mm) under the coarser levels ``warp``."""
        s = inputs.settings
        dim = inputs.points.shape[1]
        samples = octree_sample(inputs.points, s.pad, step, fraction=s.fraction, tree=inputs.tree)
        if len(samples) == 0:
            raise ProtocolError(
                f"The warp settings sample_spacing {step:g} mm, fraction {s.fraction:g} and pad {s.pad:g} mm give no "
                f"sample of the locational cost around objects {np.round(np.ptp(inputs.points, axis=0), 1).tolist()} "
                "mm across; expected a smaller `sample_spacing` (mm) or `sample_scale`.")
        # Fold-check points: the samples and their octree children, a lattice of at most half
        # min_width; samples that dense (sample_scale <= 0.5) are checked as they are.
        finest = min(s.min_width, inputs.diameter / 2)  # as _level_schedule clamps it
        check = samples if step <= 0.5 * finest * (1 + 1e-9) else _with_children(samples)
        if warp.levels or not warp.linear.is_identity:
            jacobian, base = warp.jacobian(check), warp(samples)
        else:
            jacobian, base = np.broadcast_to(np.eye(dim), (len(check), dim, dim)).copy(), samples.copy()
        subsets = _feature_samples(inputs.features, samples, s.band, reach=s.neighbourhood)
        valid_count = None
        if inputs.valid is not None:
            # Samples outside `valid` stay fold-check points but carry no locational cost.
            subsets, valid_count = _valid_subsets(subsets, inputs.valid, samples, len(inputs.features))
        consistency = {}
        if inputs.prior is not None and s.lambda_consistency > 0:
            consistency = dict(sample_targets=np.asarray(inputs.prior(samples), float),
                               lambda_target=s.lambda_consistency)
        return cls(step, samples, check, subsets, consistency, base, jacobian, valid_count)

    def add_level(self, jacobian: np.ndarray, base: np.ndarray) -> None:
        """Carry a fitted level: its Jacobian (P, D, D) at ``check`` is added, and the
        warp at ``points`` becomes ``base`` (N, D), mm."""
        self.jacobian = self.jacobian + jacobian
        self.base = base


class _FoldSet:
    """The fold-check points that carry the fold barrier during a level's fit (its active set).

    The barrier acts only where ``det J < fold_margin``: it is set on the check points near
    that, the fit is checked at every point, and points that crossed the margin join the
    set for another round.  At the end the barrier is 0 at every point outside the set, so
    the minimiser is that of the barrier over all points, without multiplying all of them
    (samples and children: 9x the samples) at each step, which would take most of the fit's
    time with no point active.

    Parameters
    ----------
    check : (P, D) float ndarray, mm
        The fold-check points.
    base : (P, D, D) float ndarray
        The coarser levels' Jacobian at ``check``.
    centres : (M, D) float ndarray, mm
        The level's kernel centres.
    width : float, mm
        The level's kernel width.
    margin : float
        ``fold_margin``.
    """

    def __init__(self, check: np.ndarray, base: np.ndarray, centres: np.ndarray, width: float, margin: float):
        self.check, self.base, self.centres, self.width, self.margin = check, base, centres, width, margin
        self.active = np.zeros(len(check), dtype=bool)

    def rows(self, det: np.ndarray) -> tuple[SharedPatternCSR, np.ndarray]:
        """Add the points with ``det < margin + FOLD_SLACK`` to the active set.

        Parameters
        ----------
        det : (P,) float ndarray
            ``det d tau / dx`` at every check point.

        Returns
        -------
        gradients : SharedPatternCSR
            ``d k(y_p, c_j) / d y`` at the active points (``LevelObjective.fold_gradients``).
        base : (P_active, D, D) float ndarray
            The coarser levels' Jacobian there (``LevelObjective.fold_base``).
        """
        self.active |= det < self.margin + FOLD_SLACK
        idx = np.flatnonzero(self.active)
        return SharedPatternCSR(kernel_gradient_matrices(self.check[idx], self.centres, self.width)), self.base[idx]


def _level_objective(width: float, centres: np.ndarray, grid: CellGrid, samples: _SampleSet, fold: _FoldSet,
                     warp: KernelWarp, inputs: _Inputs) -> tuple[LevelObjective, np.ndarray]:
    """The objective (11) of one level and its starting coefficients.

    Returns
    -------
    objective : LevelObjective
        On the level's centres, with the fold barrier on the first active set.
    start : (M, D) float ndarray
        Zero, or with landmarks the solution of the convex problem (12).
    """
    s = inputs.settings
    k_cc = kernel_matrix(centres, grid, width)
    k_xc = kernel_matrix(samples.points, grid, width)
    kw = {}
    c0 = np.zeros((len(centres), inputs.points.shape[1]))
    if inputs.landmarks is not None:
        src_l, dst_l = inputs.landmarks
        kw = dict(landmark_kernel=kernel_matrix(src_l, grid, width), landmark_base=warp(src_l),
                  landmark_targets=dst_l, lambda_p=s.lambda_p)
        c0 = _landmark_init(sp.csr_matrix(k_cc), kw["landmark_kernel"], kw["landmark_base"], dst_l, s.lambda_p)
    if s.lambda_fold > 0:
        if inputs.landmarks is not None:
            j_level = kernel_sum(samples.check, grid, c0, width, order=1)[1]
        else:
            j_level = np.zeros_like(samples.jacobian)
        gradients, fold_base = fold.rows(jacobian_det(samples.jacobian + j_level))
        kw.update(lambda_fold=s.lambda_fold, fold_margin=s.fold_margin, fold_gradients=gradients,
                  fold_base=fold_base, fold_count=len(samples.check))
    objective = LevelObjective(kernel=k_xc, kernel_centres=k_cc, base=samples.base, samples=samples.points,
                               features=inputs.features, lambda_loc=s.lambda_loc, alpha=s.alpha,
                               neighbourhood=inputs.neighbourhood, feature_samples=samples.subsets, robust=s.robust,
                               shared=samples.shared, **samples.consistency, **kw)
    return objective, c0


#: Levels with at most this many centres are solved in whitened coordinates (:class:`_Whitened`).
WHITEN_MAX_CENTRES = 2500


class _Whitened:
    """A level's objective in the coordinates ``z = L^T C`` of its regulariser ``K = L L^T`` (10).

    The regulariser becomes ``|z|^2 / 2``, so L-BFGS no longer has to learn the
    ill-conditioned Gram matrix of wide kernels; the minimiser is the same, in fewer
    iterations.  Used for the small coarse levels, whose dense Cholesky factor is cheap.
    """

    def __init__(self, objective: LevelObjective, chol: np.ndarray, shape: tuple[int, int]) -> None:
        self.objective, self.chol, self.shape = objective, chol, shape

    @classmethod
    def of(cls, objective: LevelObjective, shape: tuple[int, int]) -> "_Whitened | None":
        """The whitened objective, or None for a level too large (or a Gram matrix not positive definite)."""
        if shape[0] > WHITEN_MAX_CENTRES:
            return None
        gram = objective.kernel_centres.toarray()
        try:
            chol = scipy.linalg.cholesky(gram, lower=True)
        except np.linalg.LinAlgError:
            return None
        return cls(objective, chol, shape)

    def forward(self, coeffs: np.ndarray) -> np.ndarray:
        """``z = L^T C``."""
        return self.chol.T @ coeffs

    def back(self, z: np.ndarray) -> np.ndarray:
        """``C = L^-T z``."""
        # no finiteness check: a diverging objective's NaNs reach the caller's own check
        return scipy.linalg.solve_triangular(self.chol, z, lower=True, trans="T", check_finite=False)

    def __call__(self, flat: np.ndarray) -> tuple[float, np.ndarray]:
        value, grad = self.objective(self.back(flat.reshape(self.shape)).ravel())
        return value, scipy.linalg.solve_triangular(self.chol, grad.reshape(self.shape), lower=True,
                                                    check_finite=False).ravel()


#: Levels with at most this many unknowns (centres times D) are solved by Gauss-Newton
#: (:func:`_gauss_newton`) while no fold-barrier rows are active, with L-BFGS otherwise.  Its
#: model's Hessian is assembled densely, which pays for the coarsest level (a few dozen centres:
#: far fewer iterations than L-BFGS, ending at a lower objective) but not for the next
#: (a couple of hundred centres: slower than L-BFGS).
GAUSS_NEWTON_MAX_UNKNOWNS = 300


def _gauss_newton(objective: LevelObjective, start: np.ndarray, max_iter: int,
                  ftol: float) -> scipy.optimize.OptimizeResult:
    """Minimise a small level's objective by Levenberg-Marquardt steps on its Gauss-Newton model.

    Each step solves ``(H + mu diag(H)) s = -g`` with the model's Hessian ``H``
    (:meth:`~volreg.warp.objective.LevelObjective.gauss_newton_matrix`; positive definite,
    as it holds the regulariser's Gram matrix) and keeps the step only if the objective
    falls; ``mu`` shrinks tenfold after a kept step and grows tenfold after a rejected one.
    Stops as L-BFGS-B does: when a step lowers the objective by at most ``ftol`` relative to
    it (or the model expects no more), or when no step lowers it at all (a minimum to the
    model's precision), or after ``max_iter`` kept steps.

    Parameters
    ----------
    objective : LevelObjective
        :attr:`~volreg.warp.objective.LevelObjective.gauss_newton_ready` must hold.
    start : (M, D) float ndarray
    max_iter : int
    ftol : float

    Returns
    -------
    scipy.optimize.OptimizeResult
        ``x`` (M * D,), ``fun``, ``nit`` (kept steps), ``nfev``, ``success``.
    """
    x = start.ravel().astype(float)
    value, grad, blocks = objective.gauss_newton(x)
    nfev, nit, mu, success = 1, 0, 1e-3, False
    while nit < max_iter and np.isfinite(value) and not success:
        hess = objective.gauss_newton_matrix(blocks)
        scale = np.diag(hess).copy()
        kept = None
        while kept is None and mu <= 1e12:
            try:
                factor = scipy.linalg.cho_factor(hess + mu * np.diag(scale), check_finite=False)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            step = -scipy.linalg.cho_solve(factor, grad, check_finite=False)
            if -(grad @ step) - 0.5 * (step @ hess @ step) <= ftol * max(abs(value), 1.0):
                break  # the model expects less than the tolerance (e.g. a zero gradient): converged
            trial = objective.gauss_newton(x + step)
            nfev += 1
            if np.isfinite(trial[0]) and trial[0] < value:
                kept = trial
            else:
                mu *= 10.0
        if kept is None:  # no step lowers the objective: a minimum, as far as the model sees
            success = True
            break
        nit += 1
        success = (value - kept[0]) / max(abs(value), abs(kept[0]), 1.0) <= ftol
        x = x + step
        value, grad, blocks = kept
        mu = max(mu / 10.0, 1e-12)
    return scipy.optimize.OptimizeResult(x=x, fun=value, nit=nit, nfev=nfev, success=success)


def _minimise(objective: LevelObjective, start: np.ndarray, start_value: float, fold: _FoldSet, grid: CellGrid,
              level: int, width: float, settings: WarpSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Minimise a level's objective with L-BFGS (Gauss-Newton for the smallest levels, see
    :data:`GAUSS_NEWTON_MAX_UNKNOWNS`), in rounds that grow the fold barrier's active set.

    After each round every check point is tested; the points that crossed ``fold_margin``
    outside the active set join it for another round, up to ``FOLD_ROUNDS`` rounds.

    Parameters
    ----------
    objective : LevelObjective
    start : (M, D) float ndarray
        Starting coefficients; ``start_value`` is the objective there (for messages).
    fold : _FoldSet
    grid : CellGrid
        Neighbour grid of the level's centres.
    level : int
    width : float, mm
        The level's index and kernel width.
    settings : WarpSettings

    Raises
    ------
    RegistrationDiverged
        If the objective or the coefficients stop being finite.

    Returns
    -------
    coeffs : (M, D) float ndarray
        The level's coefficients.
    jacobian : (P, D, D) float ndarray
        The level's own Jacobian at the check points.
    det : (P,) float ndarray
        ``det d tau / dx`` of the warp with the level, at the check points.
    info : dict
        ``iterations`` (total over rounds), ``converged`` (last round), ``fold_rounds``.
    """
    coeffs, iterations, converged, rounds = start, 0, True, 0
    while True:
        # A later round (points crossed the margin) gets at least half the budget again.
        budget = settings.max_iter - iterations if rounds == 0 else max(settings.max_iter - iterations,
                                                                        settings.max_iter // 2, 1)
        if objective.gauss_newton_ready and coeffs.size <= GAUSS_NEWTON_MAX_UNKNOWNS:
            res = _gauss_newton(objective, coeffs, budget, settings.tolerance)
        elif (whiten := _Whitened.of(objective, start.shape)) is None:
            res = scipy.optimize.minimize(objective, coeffs.ravel(), jac=True, method="L-BFGS-B",
                                          options=dict(maxiter=budget, ftol=settings.tolerance))
        else:
            res = scipy.optimize.minimize(whiten, whiten.forward(coeffs).ravel(), jac=True, method="L-BFGS-B",
                                          options=dict(maxiter=budget, ftol=settings.tolerance))
            res.x = whiten.back(res.x.reshape(start.shape)).ravel()
        if not (np.isfinite(res.fun) and np.all(np.isfinite(res.x))):
            raise RegistrationDiverged(
                f"Warp level {level} (kernel width {width:.3g} mm) diverged: its objective became {float(res.fun)!r} "
                f"(started at {float(start_value)!r}); expected finite values. Check the inputs, or change the protocol: "
                "lower lambda_loc or alpha, or raise min_width."
            )
        coeffs = res.x.reshape(start.shape)
        iterations += int(res.nit)
        converged = bool(res.success)
        rounds += 1
        jacobian = kernel_sum(fold.check, grid, coeffs, width, order=1)[1]
        det = jacobian_det(fold.base + jacobian)  # at every check point
        if settings.lambda_fold <= 0 or rounds >= FOLD_ROUNDS:
            break
        if not np.any(~fold.active & (det < settings.fold_margin)):
            break
        objective.set_fold(*fold.rows(det), count=len(fold.check))
    return coeffs, jacobian, det, dict(iterations=iterations, converged=converged, fold_rounds=rounds)


def _fold_guard(base: np.ndarray, jacobian: np.ndarray, det: np.ndarray, min_det: float) -> float:
    """The factor that keeps a level from folding space at the check points (not in the paper).

    ``tau`` must stay orientation-preserving.  If the level folds space (``det J < min_det``),
    its coefficients are shrunk by 0.7 at a time, at most 20 times (then dropped: 0); where the
    coarser levels are already below ``min_det``, the level must not make it worse.

    Parameters
    ----------
    base : (P, D, D) float ndarray
        The coarser levels' Jacobian at the check points.
    jacobian : (P, D, D) float ndarray
        The level's own Jacobian there.
    det : (P,) float ndarray
        ``det(base + jacobian)``.
    min_det : float

    Returns
    -------
    float
        The factor, in [0, 1], for the level's coefficients (logged as ``fold_scale``).
    """
    floor = min(min_det, float(jacobian_det(base).min()))
    scale = 1.0
    for _ in range(20):
        if det.min() >= floor:
            break
        scale *= 0.7
        det = jacobian_det(base + scale * jacobian)
    else:
        scale = 0.0
    return scale


def _fit_level(level: int, width: float, samples: _SampleSet, warp: KernelWarp,
               inputs: _Inputs) -> tuple[WarpLevel, dict]:
    """Fit one level of kernel width ``width`` (mm) on top of the coarser levels ``warp``.

    Steps 2-4 of the module docstring: the landmark start (12), the minimisation of (11) with the
    fold barrier, the fold guard.  ``samples`` then carries the level too.

    Returns
    -------
    WarpLevel
        The level's centres, coefficients and width.
    dict
        Its log entry (without ``level``, ``width`` and ``seconds``).
    """
    s = inputs.settings
    # Centres: octree boxes of half the width (Section 3.5), plus the source landmarks
    # (the representer theorem puts kernels at every training point, so landmarks
    # away from X can be fitted too).
    centres = octree_sample(inputs.points, s.pad, width, fraction=s.fraction, tree=inputs.tree)
    if len(centres) == 0:
        # A warp volume thinner than the level's boxes (a label a few voxels across, whose pad
        # is a fraction of a voxel): no box centre lies within the pad, so the boxes that meet
        # it carry the level (their centres within the pad plus a box's half-diagonal).
        reach = s.pad + s.fraction * width * np.sqrt(inputs.points.shape[1]) / 2
        centres = octree_sample(inputs.points, reach, width, fraction=s.fraction, tree=inputs.tree)
    if inputs.landmarks is not None:
        centres = np.concatenate([centres, inputs.landmarks[0]])
    grid = CellGrid.build(centres, width)
    fold = _FoldSet(samples.check, samples.jacobian, centres, width, s.fold_margin)
    objective, c0 = _level_objective(width, centres, grid, samples, fold, warp, inputs)
    e0, _ = objective(c0.ravel())
    terms0 = dict(objective.last_terms)
    coeffs, jacobian, det, info = _minimise(objective, c0, e0, fold, grid, level, width, s)
    # The fold guard, at the fold-check points (the samples and, where they are sparser than
    # half min_width, their octree children).
    scale = _fold_guard(samples.jacobian, jacobian, det, s.min_det)
    coeffs = scale * coeffs
    samples.add_level(scale * jacobian, objective.warp_samples(coeffs))
    entry = dict(samples=int(len(samples.points)), centres=int(len(centres)), iterations=info["iterations"],
                 converged=info["converged"], fold_points=int(np.count_nonzero(fold.active)),
                 fold_rounds=info["fold_rounds"], fold_scale=scale, objective_start=float(e0),
                 objective=float(objective(coeffs.ravel())[0]), terms_start=terms0, terms=dict(objective.last_terms))
    if samples.valid_count is not None:
        entry["valid_samples"] = samples.valid_count
    return WarpLevel(centres, coeffs, width), entry


@single_blas
def fit_warp(
    features: Sequence[FeaturePair],
    source_points: np.ndarray,
    *,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    settings: WarpSettings = WarpSettings(),
    prior: Callable[[np.ndarray], np.ndarray] | None = None,
    valid: Callable[[np.ndarray], np.ndarray] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    stop: Callable[[KernelWarp], bool] | None = None,
) -> RegistrationResult:
    """Fit the kernel warp coarse to fine (paper Sections 3.4-3.5).

    Parameters
    ----------
    features : sequence of FeaturePair
        Feature functions of the source (``f1``) and target (``f2``), e.g. one
        pair of implicit surfaces per label (6).
    source_points : (N, D) float ndarray, mm
        Points of the source surfaces (defining the warp volume X and the diameter).
    landmarks : pair of (L, D) float ndarrays, optional
        Source landmarks and their target positions, mm.
    settings : WarpSettings
    prior : callable, optional
        ``prior(points) -> (N, D)`` positions the warp should map the points to, e.g.
        :class:`~volreg.warp.inverse.InverseWarp` of the opposite registration; with
        ``settings.lambda_consistency > 0`` the objective gains
        ``lambda_consistency mean_x |tau(x) - prior(x)|^2`` over the samples.
    valid : callable, optional
        ``valid(samples) -> (N,) bool ndarray``, given the locational-cost samples
        (``(N, D)`` float ndarray, mm, source space): where it is ``False`` a sample
        carries no locational cost (3)-(6) for any feature, e.g. where the target
        image does not see the object (a label cut by the image edge, whose cut is
        not a boundary of the object and must not pull the warp).  Those samples
        stay fold-check points; the regulariser, landmark and consistency terms
        are unchanged, and the locational cost keeps its normalisation by the
        number of all samples (a masked sample counts as zero cost).  Called once
        per sample set (levels sharing a sample spacing share it).  ``None``
        (default): every sample counts, as does a mask that is ``True``
        everywhere, with identical results.
    progress : callable, optional
        ``progress(stage, done, total)`` after each level.
    stop : callable, optional
        ``stop(warp) -> bool`` after each level but the last, given the warp fitted so far:
        ``True`` ends the fit there (the finer levels are not fitted), e.g. where a check
        outside the locational cost shows the coarse levels already going wrong.

    Returns
    -------
    RegistrationResult
        The warp (its ``settings`` with ``pad`` and ``min_width`` resolved) and one log
        entry per level fitted: ``level``, ``width`` (mm), ``samples``, ``centres``,
        ``iterations``, ``converged``, ``fold_points``, ``fold_rounds``, ``fold_scale``,
        ``objective_start``, ``objective``, ``terms_start``, ``terms``, ``seconds``;
        with ``valid``, also ``valid_samples`` (the samples where it holds).

    Raises
    ------
    ValueError
        Bad inputs, or ``valid`` returning anything but a bool array of shape (N,).
    RegistrationDiverged
        If a level's objective stops being finite.
    """
    inputs = _check_inputs(features, source_points, landmarks, settings, prior, valid)
    widths, steps = _level_schedule(inputs.diameter, inputs.settings)
    check_sample_memory(inputs.points, inputs.settings, min(steps))
    warp = KernelWarp(dim=inputs.points.shape[1], settings=asdict(inputs.settings))
    log = []
    samples = None
    for level, (width, step) in enumerate(zip(widths, steps)):
        t0 = time.perf_counter()
        if samples is None or step != samples.step:
            samples = _SampleSet.build(inputs, step, warp)
        fitted, entry = _fit_level(level, width, samples, warp, inputs)
        warp = warp.with_level(fitted)
        log.append(dict(level=level, width=width, **entry, seconds=time.perf_counter() - t0))
        if progress is not None:
            progress("fit warp", level + 1, len(widths))
        if stop is not None and level + 1 < len(widths) and stop(warp):
            break
    return RegistrationResult(warp, log)

"""Surface-to-surface registration: the coarse-to-fine driver (paper Section 3.5).

For each level, from a kernel width of half the source diameter down to
``min_width`` (halving each time):

1. sample the warp volume X -- the source surfaces padded by ``pad`` mm -- by
   octree subdivision down to boxes of half the width (Section 3.5); the box
   centres are the level's kernel centres.  The locational cost is sampled at
   the finest level's boxes on every level (not in the paper, whose coarse
   levels see only their own few boxes), and each feature only within a band
   around its source surface (``WarpSettings.band``);
2. with landmarks, start from the convex problem (12): kernel ridge regression
   of the landmark residuals, solved exactly;
3. minimise the objective (11) (:class:`~volreg.objective.LevelObjective`) over
   the level's coefficients with L-BFGS, on top of the coarser levels, plus a
   fold barrier on ``det d tau / dx`` (not in the paper);
4. guard against folding: if ``det d tau / dx`` falls below ``min_det`` at a
   sample or at the centre of one of its octree children, shrink the level's
   coefficients until it does not (not in the paper, which has no such
   safeguard; logged as ``fold_scale``).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.optimize
import scipy.sparse as sp
import scipy.sparse.linalg
from scipy.spatial import cKDTree

from ._threads import single_blas, thread_map
from .implicit import ImplicitSurface
from .kernels import CellGrid, SharedPatternCSR, _check_points, kernel_gradient_matrices, kernel_matrix, kernel_sum
from .objective import FeaturePair, LevelObjective, simplex_vertices
from .sampling import octree_sample
from .warp import KernelWarp, WarpLevel, jacobian_det

__all__ = [
    "WarpSettings",
    "RegistrationResult",
    "LabelRegistration",
    "RegistrationDiverged",
    "check_folding",
    "register_surfaces",
    "register_labels",
    "fit_warp",
]


#: Fold-check points with det J below ``fold_margin + FOLD_SLACK`` carry the fold barrier
#: during a level's fit; the rest are checked after it (see :func:`fit_warp`).
FOLD_SLACK = 0.3
#: At most this many fits per level, each adding the points that crossed ``fold_margin``.
FOLD_ROUNDS = 5


class RegistrationDiverged(RuntimeError):
    """The optimisation of a level failed (NaN/Inf objective or coefficients, or a warp that folds
    too much of the output grid): no warp is returned or written."""


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
    from .field import jacobian_determinant_on_grid
    from .metrics import folded_fraction

    folded = folded_fraction(det)
    if folded <= max_fraction:
        return
    levels = warp.levels
    first = len(levels) - 1
    for k in range(1, len(levels)):
        if folded_fraction(jacobian_determinant_on_grid(KernelWarp(levels[:k], dim=warp.dim), reference)) > max_fraction:
            first = k - 1
            break
    raise RegistrationDiverged(
        f"Warp level {first} (kernel width {levels[first].width:.3g} mm) folds space: det(d tau/dx) <= 0 at "
        f"{100 * folded:.2f} % of the fixed grid's voxels, more than max_folded_fraction = {100 * max_fraction:.2g} %. "
        "Change the protocol: raise min_width (or set it to a larger kernel width), lower lambda_loc or alpha, "
        "or raise lambda_fold."
    )


@dataclass(frozen=True)
class WarpSettings:
    """Settings of the warp fit (the protocol's warp section).

    Attributes
    ----------
    pad : float, mm, optional
        Padding of the warp volume X around the source surfaces; default 10 % of
        the source diameter.  A wider pad puts signed distances further from the
        surface into the cost (11), which carry more of the shape around each point:
        on a blob with eight bumps under a known warp, 15 mm (24 % of the diameter,
        with ``sample_scale = 2``) took the worst of four endpoint errors from 1.02 to
        0.90 % of the diameter; on an ellipsoid it did not help (BENCHMARKS.md).
    min_width : float, mm, optional
        Finest kernel width; default 1/16 of the source diameter.
    lambda_loc : float
        Weight of the locational cost (11), per unit of mean cost.
    alpha : float, mm^2
        Weight of the gradient term (4); 0 gives the distance-only cost (3).
    lambda_p : float
        Landmark weight (8).
    neighbourhood : float, mm
        If > 0, the neighbourhood cost (5) over a regular simplex of this radius.
    fraction : float
        Octree boxes stop below ``fraction * width`` (paper: 1/2).
    max_iter : int
        L-BFGS iterations per level.
    tolerance : float
        L-BFGS stops a level when an iteration lowers the objective by less than this
        fraction of it (scipy's ``ftol``).  On the frog demo 1e-6 gave the same endpoint
        error as scipy's default 2.2e-9 (0.611 mm mean, 1.47 mm p95) in 80 instead of 173
        iterations over the 4 levels; 1e-5: 0.611 / 1.47 mm in 55; 1e-4: 0.612 / 1.47 mm in 37.
    lambda_fold : float
        Weight of the fold barrier (not in the paper): ``lambda_fold mean
        max(0, fold_margin - det d tau/dx)^2`` over the samples and their
        octree children, so that L-BFGS keeps the warp orientation-preserving.
        During a level's fit only the points with ``det < fold_margin + FOLD_SLACK``
        carry it; points that end below ``fold_margin`` join them for another fit
        (up to ``FOLD_ROUNDS``), so the result is the barrier's over every point.
    fold_margin : float
        Determinant below which the barrier acts.
    sample_spacing : float, mm, optional
        The locational cost is sampled at the centres of octree boxes of X
        smaller than ``fraction * s``, with ``s = max(sample_spacing,
        min(width / 4, min_width))`` at a level of kernel width ``width``:
        ``sample_spacing`` at every level when it is ``min_width`` or more, and
        where it is finer, only at the levels whose width is below
        ``4 * min_width``; default ``sample_scale * min_width`` (1: the
        finest level's boxes at every level).
    sample_scale : float
        See ``sample_spacing``; cost grows about as ``sample_scale^-2``
        (samples crowd the surfaces).
    band : float, mm, optional
        The locational cost of a feature counts only at samples within this
        distance of its source surface; default half the finest kernel width
        of that feature's ``f1`` (see ``_feature_samples``).
    lambda_consistency : float
        Symmetric option (not in the paper): weight of ``mean_x |tau(x) - t(x)|^2`` over
        the locational-cost samples, where ``t`` is the inverse of a registration in the
        opposite direction (``fit_warp(prior=...)``; ``volreg consistency`` passes the
        forward warp's Newton inverse to the backward fit).  0 = off; ignored when no
        ``prior`` is given.
    robust : float, mm
        If > 0, the distance term uses a pseudo-Huber loss of this scale (not in the
        paper; see :class:`~volreg.objective.LevelObjective`); 0 = squared residuals,
        as in (3).  Implicit surfaces of resampled labels disagree by tens of mm at a
        few samples (seen on thin, fragmented labels), which the squared loss
        lets dominate: on the frog demo (``fast``) the true warp's squared distance
        cost was 14x the fitted warp's, 90 % of it from one label.  Measured there
        (endpoint error, mean mm): 0 -> 2.15, 1 -> 1.37, 0.5 -> 1.28, 0.25 -> 1.24.
    max_folded_fraction : float
        Health check on the output grid (:func:`check_folding`): if the warp folds space
        (``det d tau / dx <= 0``) at more than this fraction of the fixed grid's voxels,
        the registration stops with :class:`RegistrationDiverged` naming the first level
        that crossed it, instead of writing a folded warp.
    min_det : float
        Last-resort fold guard: after each level, its coefficients are shrunk (by 0.7 at a
        time) until ``det d tau / dx >= min_det`` at every sample point (or, where
        the coarser levels are already below that, until the level makes the
        minimum no worse).
    """

    pad: float | None = None
    min_width: float | None = None
    lambda_loc: float = 100.0
    alpha: float = 10.0
    lambda_p: float = 100.0
    neighbourhood: float = 0.0
    fraction: float = 0.5
    max_iter: int = 200
    tolerance: float = 1e-6
    lambda_fold: float = 1e5
    fold_margin: float = 0.3
    min_det: float = 0.1
    band: float | None = None
    sample_spacing: float | None = None
    sample_scale: float = 1.0
    lambda_consistency: float = 0.0
    max_folded_fraction: float = 0.01
    robust: float = 0.5

    def __post_init__(self) -> None:
        for name in ("lambda_loc", "alpha", "lambda_p", "neighbourhood", "lambda_fold", "fold_margin", "min_det",
                     "lambda_consistency", "robust"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"Expected `{name}` >= 0, got {value}.")
        for name in ("pad", "min_width", "band", "sample_spacing"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f"Expected a positive `{name}` (mm), got {value}.")
        if not (np.isfinite(self.sample_scale) and 0 < self.sample_scale <= 16):
            raise ValueError(f"Expected `sample_scale` in (0, 16], got {self.sample_scale}.")
        if not (np.isfinite(self.max_folded_fraction) and 0 <= self.max_folded_fraction <= 1):
            raise ValueError(f"Expected `max_folded_fraction` in [0, 1], got {self.max_folded_fraction}.")
        if not 0 < self.fraction <= 1:
            raise ValueError(f"Expected `fraction` in (0, 1], got {self.fraction}.")
        if not (np.isfinite(self.tolerance) and 0 < self.tolerance < 1):
            raise ValueError(f"Expected `tolerance` in (0, 1), got {self.tolerance}.")
        if self.max_iter < 0:
            raise ValueError(f"Expected `max_iter` >= 0, got {self.max_iter}.")


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
    of tens of mm that the warp would try to explain (measured on the frog: rms
    ``f1 - f2`` 0.8-1.1 mm within 10 mm of a surface, 3-12 mm at 20-80 mm).
    ``band=None`` takes half the finest kernel width of ``f1`` (objects with
    ``widths``) or every sample.  On the frog demo (``fast`` protocol), fixed
    bands of 6 and 12 mm gave endpoint errors of 1.80 and 1.84 mm; half, one
    and two finest widths (6-11, 13-21, 25-43 mm) 2.15, 2.99 and 3.48 mm;
    the identity 3.09 mm.

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
            # pass through 0 again, which would let far-away samples in.
            dist = cKDTree(pair.f1.points).query(samples, distance_upper_bound=limit + reach)[0]
            out.append(np.flatnonzero(np.isfinite(dist)))
            continue
        lo, hi = pair.f1.bounds()
        idx = np.flatnonzero(np.all((samples >= lo - reach) & (samples <= hi + reach), axis=1))
        if len(idx):
            idx = idx[np.abs(pair.f1.evaluate(samples[idx], order=0)[0]) <= limit + reach]
        out.append(idx)
    return None if all(o is None for o in out) else out


@single_blas
def fit_warp(
    features: Sequence[FeaturePair],
    source_points: np.ndarray,
    *,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    settings: WarpSettings = WarpSettings(),
    prior: Callable[[np.ndarray], np.ndarray] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
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
        :class:`~volreg.inverse.InverseWarp` of the opposite registration; with
        ``settings.lambda_consistency > 0`` the objective gains
        ``lambda_consistency mean_x |tau(x) - prior(x)|^2`` over the samples.
    progress : callable, optional
        ``progress(stage, done, total)`` after each level.

    Returns
    -------
    RegistrationResult
    """
    pts = _check_points("source_points", source_points)
    if len(pts) < 2:
        raise ValueError(f"Expected at least 2 `source_points`, got {len(pts)}.")
    dim = pts.shape[1]
    diameter = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    pad = 0.1 * diameter if settings.pad is None else settings.pad
    min_width = diameter / 16 if settings.min_width is None else settings.min_width
    widths = [diameter / 2]
    while widths[-1] / 2 >= min_width * (1 - 1e-9):
        widths.append(widths[-1] / 2)
    if landmarks is not None:
        if settings.lambda_p <= 0:
            raise ValueError("Expected `lambda_p` > 0 in `settings` when `landmarks` are given (it weighs them).")
        src_l, dst_l = (np.asarray(a, float) for a in landmarks)
        if src_l.shape != dst_l.shape or src_l.ndim != 2 or src_l.shape[1] != dim:
            raise ValueError(
                f"Expected `landmarks` as two arrays of shape (L, {dim}), got {src_l.shape} and {dst_l.shape}."
            )
    neighbourhood = simplex_vertices(dim, settings.neighbourhood) if settings.neighbourhood > 0 else None
    spacing = settings.sample_scale * min_width if settings.sample_spacing is None else settings.sample_spacing
    warp = KernelWarp(dim=dim, settings=dict(asdict(settings), pad=pad, min_width=min_width))
    log = []
    level_spacing = None
    for li, width in enumerate(widths):
        t0 = time.perf_counter()
        # Samples of the locational cost: the finest level's boxes at every level (the
        # paper samples each level at its own boxes, which leaves a coarse level a few
        # dozen points to estimate an integral over X), or `spacing` where that is
        # finer, but no finer than a quarter of the level's kernel width: on the frog
        # demo the coarser levels gained nothing from denser samples (BENCHMARKS.md).
        step = max(spacing, min(width / 4, min_width))
        if step != level_spacing:
            level_spacing = step
            samples = octree_sample(pts, pad, step, fraction=settings.fraction)
            # Fold-check points: the samples and their octree children, a lattice of at most half
            # min_width; samples that dense (sample_scale <= 0.5) are checked as they are.
            check = samples if step <= 0.5 * min_width * (1 + 1e-9) else _with_children(samples)
            # The coarser levels' Jacobian at the fold-check points and their warp at the samples,
            # carried from level to level (not re-evaluated through every coarser level).
            if warp.levels:
                j_prev, base = warp.jacobian(check), warp(samples)
            else:
                j_prev, base = np.broadcast_to(np.eye(dim), (len(check), dim, dim)).copy(), samples.copy()
            subsets = _feature_samples(features, samples, settings.band, reach=settings.neighbourhood)
            consistency = {}
            if prior is not None and settings.lambda_consistency > 0:
                consistency = dict(sample_targets=np.asarray(prior(samples), float),
                                   lambda_target=settings.lambda_consistency)
        # Centres: octree boxes of half the width (Section 3.5), plus the source landmarks
        # (the representer theorem puts kernels at every training point, so landmarks
        # away from X can be fitted too).
        boxes = octree_sample(pts, pad, width, fraction=settings.fraction)
        use_landmarks = landmarks is not None
        centres = np.concatenate([boxes, src_l]) if use_landmarks else boxes
        grid = CellGrid.build(centres, width)
        k_cc = kernel_matrix(centres, grid, width)
        k_xc = kernel_matrix(samples, grid, width)
        kw = {}
        if use_landmarks:
            kw = dict(landmark_kernel=kernel_matrix(src_l, grid, width), landmark_base=warp(src_l),
                      landmark_targets=dst_l, lambda_p=settings.lambda_p)
        c0 = np.zeros((len(centres), dim))
        if use_landmarks:
            c0 = _landmark_init(sp.csr_matrix(k_cc), kw["landmark_kernel"], kw["landmark_base"], dst_l,
                                settings.lambda_p)
        # The fold barrier acts only where det J < fold_margin: it is set on the check points
        # near that (the active set), the fit is checked at every point, and points that
        # crossed the margin join the set for another round.  At the end the barrier is 0 at
        # every point outside the set, so the minimiser is that of the barrier over all
        # points, without multiplying all of them (samples and children: 9x the samples) at
        # each step (on the frog demo that was 70 % of the fit's time, with no point active).
        j_level = kernel_sum(check, grid, c0, width, order=1)[1] if use_landmarks else np.zeros_like(j_prev)
        active = np.zeros(len(check), dtype=bool)

        def fold_rows(det):
            """Add the points with det < fold_margin + FOLD_SLACK to the active set; its rows."""
            active[:] |= det < settings.fold_margin + FOLD_SLACK
            idx = np.flatnonzero(active)
            return SharedPatternCSR(kernel_gradient_matrices(check[idx], centres, width)), j_prev[idx]

        if settings.lambda_fold > 0:
            gradients, fold_base = fold_rows(jacobian_det(j_prev + j_level))
            kw.update(lambda_fold=settings.lambda_fold, fold_margin=settings.fold_margin, fold_gradients=gradients,
                      fold_base=fold_base, fold_count=len(check))
        objective = LevelObjective(kernel=k_xc, kernel_centres=k_cc, base=base, samples=samples,
                                   features=features, lambda_loc=settings.lambda_loc, alpha=settings.alpha,
                                   neighbourhood=neighbourhood, feature_samples=subsets, robust=settings.robust, **consistency, **kw)
        e0, _ = objective(c0.ravel())
        terms0 = dict(objective.last_terms)
        coeffs, iterations, converged, rounds = c0, 0, True, 0
        while True:
            # A later round (points crossed the margin) gets at least half the budget again.
            budget = settings.max_iter - iterations if rounds == 0 else max(settings.max_iter - iterations,
                                                                            settings.max_iter // 2, 1)
            res = scipy.optimize.minimize(objective, coeffs.ravel(), jac=True, method="L-BFGS-B",
                                          options=dict(maxiter=budget, ftol=settings.tolerance))
            if not (np.isfinite(res.fun) and np.all(np.isfinite(res.x))):
                raise RegistrationDiverged(
                    f"Warp level {li} (kernel width {width:.3g} mm) diverged: its objective became {float(res.fun)!r} "
                    f"(started at {float(e0)!r}); expected finite values. Check the inputs, or change the protocol: "
                    "lower lambda_loc or alpha, or raise min_width."
                )
            coeffs = res.x.reshape(-1, dim)
            iterations += int(res.nit)
            converged = bool(res.success)
            rounds += 1
            j_level = kernel_sum(check, grid, coeffs, width, order=1)[1]
            det = jacobian_det(j_prev + j_level)  # at every check point
            if settings.lambda_fold <= 0 or rounds >= FOLD_ROUNDS:
                break
            if not np.any(~active & (det < settings.fold_margin)):
                break
            objective.set_fold(*fold_rows(det), count=len(check))
        # Fold guard: tau must stay orientation-preserving, checked at the fold-check points
        # (the samples and, where they are sparser than half min_width, their octree children).
        # If the level folds space there (det J < min_det), shrink its coefficients;
        # where coarser levels are already below min_det, it must not make it worse.
        floor = min(settings.min_det, float(jacobian_det(j_prev).min()))
        scale = 1.0
        for _ in range(20):
            if det.min() >= floor:
                break
            scale *= 0.7
            det = jacobian_det(j_prev + scale * j_level)
        else:
            scale = 0.0
        coeffs = scale * coeffs
        warp = warp.with_level(WarpLevel(centres, coeffs, width))
        j_prev = j_prev + scale * j_level
        base = objective.warp_samples(coeffs)
        log.append(dict(level=li, width=width, samples=int(len(samples)), centres=int(len(centres)),
                        iterations=iterations, converged=converged, fold_points=int(np.count_nonzero(active)),
                        fold_rounds=rounds, fold_scale=scale, objective_start=float(e0),
                        objective=float(objective(coeffs.ravel())[0]),
                        terms_start=terms0, terms=dict(objective.last_terms),
                        seconds=time.perf_counter() - t0))
        if progress is not None:
            progress("fit warp", li + 1, len(widths))
    return RegistrationResult(warp, log)


def _as_implicit(surface, **kwargs) -> tuple[ImplicitSurface, np.ndarray]:
    """An ImplicitSurface and its points from a pyvista mesh, an ImplicitSurface, or (points, normals)."""
    if isinstance(surface, ImplicitSurface):
        return surface, surface.points
    if isinstance(surface, tuple):
        pts, normals = (np.asarray(a, float) for a in surface)
        return ImplicitSurface(pts, normals, **kwargs), pts
    try:
        import pyvista as pv
    except ImportError:  # pragma: no cover - pyvista is a dependency
        pv = None
    if pv is not None and isinstance(surface, pv.PolyData):
        mesh = surface.triangulate().compute_normals(point_normals=True, cell_normals=False,
                                                     auto_orient_normals=True, consistent_normals=True)
        pts = np.asarray(mesh.points, float)
        return ImplicitSurface(pts, np.asarray(mesh.point_data["Normals"], float), **kwargs), pts
    raise TypeError(
        f"Expected `source`/`target` as pyvista PolyData, ImplicitSurface or (points, normals), got {type(surface).__name__}."
    )


@single_blas
def register_surfaces(
    source,
    target,
    *,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    settings: WarpSettings = WarpSettings(),
    progress: Callable[[str, int, int], None] | None = None,
) -> RegistrationResult:
    """Register ``source`` onto ``target``: ``result.warp`` maps source points to target points.

    Parameters
    ----------
    source, target : pyvista.PolyData, ImplicitSurface, (points, normals), or lists of them
        One object or several (one per label: several feature functions, (6)),
        in the same order for both.
    landmarks : pair of (L, D) float ndarrays, optional
        Source landmark points and their target positions, mm.
    settings : WarpSettings
    progress : callable, optional

    Returns
    -------
    RegistrationResult
        ``.warp`` (:class:`~volreg.warp.KernelWarp`) and ``.log`` (per level:
        width, samples, iterations, objective terms, seconds).
    """
    sources = source if isinstance(source, list) else [source]
    targets = target if isinstance(target, list) else [target]
    if len(sources) != len(targets):
        raise ValueError(f"Expected as many `target` objects as `source` objects, got {len(targets)} and {len(sources)}.")
    pairs, points = [], []
    for s, t in zip(sources, targets):
        f1, p1 = _as_implicit(s)
        f2, _ = _as_implicit(t)
        pairs.append(FeaturePair(f1, f2))
        points.append(p1)
    return fit_warp(pairs, np.concatenate(points), landmarks=landmarks, settings=settings, progress=progress)


def _diameter(points: np.ndarray) -> float:
    """Diagonal of the bounding box of ``points``, mm."""
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


#: A label drives the warp by default when at least this fraction of its voxels lies in
#: pieces holding >= 5 % of the label each (in both volumes).  On the frog demo (3 mm), with
#: the robust distance term, its labels at 0.87 (13), 0.73 (12) and 0.54 (1) gave endpoint
#: errors of 0.70 mm driving 13 and 0.75 driving all three (``fast`` with a 24 mm finest width
#: and 48 mm sample spacing), and 0.96 driving 13 against 1.28 driving none (``fast`` as
#: shipped); with the squared cost (3), driving 13 had made it worse.
COMPACT_FRACTION = 0.8

#: Pieces of a driving label smaller than this fraction of its voxels are removed before its
#: surface is made.  Measured on the frog at 3 mm (2026-12-02): 0.05 -> endpoint error
#: 0.611 / 1.468 mm (mean / p95), Dice 0.887; 0.01 -> 0.521 / 1.175, Dice 0.888 (the small bones
#: of the skeleton, label 13, then drive the warp); at full resolution no change (0.296 -> 0.295 mm).
SPECK_FRACTION = 0.01


def despeckle(volume, labels, *, piece: float = 0.05, judge: float | None = None):
    """Remove each label's specks: connected pieces (face connectivity) smaller than
    ``piece`` times the label's voxel count (they are set to 0).

    ``judge`` (default ``piece``) is the piece fraction by which ``kept`` is measured.

    Returns
    -------
    cleaned : LabelVolume
    kept : dict of int to float
        Per label, the fraction of its voxels that lies in pieces of at least ``judge``
        times the label's voxel count.
    """
    from scipy import ndimage

    array = volume.array.copy()
    kept = {}
    boxes = volume.label_boxes()
    for v in labels:
        box = boxes.get(v, tuple(slice(0, n) for n in volume.shape))
        mask = volume.array[box] == v
        pieces, n = ndimage.label(mask)
        sizes = np.bincount(pieces.ravel())[1:]
        total = int(sizes.sum())
        if total == 0:
            kept[v] = 0.0
            continue
        small = np.flatnonzero(sizes < piece * total) + 1
        kept[v] = float(sizes[sizes >= (piece if judge is None else judge) * total].sum() / total)
        if len(small):
            sub = array[box]
            sub[np.isin(pieces, small)] = 0
    return volume.with_array(array), kept


class RegistrationInputError(ValueError):
    """Inputs that cannot be registered (no common label, grids far apart, ...)."""


@dataclass
class LabelRegistration(RegistrationResult):
    """A label-volume registration: the warp (fixed -> moving), its log, and what drove it.

    Attributes
    ----------
    labels : list of int
        The labels whose surfaces drove the warp.
    skipped : list of str
        Labels left out (too small in one of the volumes), with the reason.
    distance_labels : list of int
        The labels whose voxel signed-distance maps drove the warp (protocol
        ``surface.distance_weight`` > 0).
    stages : list of dict
        Per stage: ``{"stage", "seconds"}``.
    """

    labels: list = field(default_factory=list)
    skipped: list = field(default_factory=list)
    stages: list = field(default_factory=list)
    distance_labels: list = field(default_factory=list)


@single_blas
def register_labels(
    fixed,
    moving,
    *,
    drive_labels: Sequence[int] | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    protocol=None,
    prior: Callable[[np.ndarray], np.ndarray] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> LabelRegistration:
    """Register two label volumes: ``result.warp`` maps fixed points to moving points (pull-back).

    Each driving label gives one feature pair (paper (6)): the kernel implicit
    surface (Section 4) of its boundary in the fixed volume (``f1``, O1) and in
    the moving volume (``f2``, O2).  With the protocol's
    ``surface.distance_weight`` > 0 (the presets) every label present in both
    volumes (or every drive label) also gives a pair of voxel signed-distance
    maps (:class:`~volreg.distance_maps.VoxelDistance`, not in the paper), so that
    labels too small or too fragmented for a surface drive the warp as well
    (frog demo at 3 mm: endpoint error 0.52 / 1.18 -> 0.51 / 0.84 mm, mean / p95;
    at 1 x 1 x 1.5 mm 0.29 / 1.08 -> 0.21 / 0.40).  The warp is fitted in the
    padded neighbourhood of the fixed surfaces (:func:`fit_warp`).

    Parameters
    ----------
    fixed, moving : LabelVolume
    drive_labels : sequence of int, optional
        Labels whose surfaces (and distance maps) drive the warp; default every label present in
        both volumes except speckled ones (less than :data:`COMPACT_FRACTION` of
        the voxels in pieces of at least 5 % of the label, see :func:`despeckle`).
        Specks (pieces under :data:`SPECK_FRACTION` of the label) are removed
        before the surfaces are made.  Labels too small to give a surface in
        either volume are skipped (their distance maps still count).
        ``result.skipped`` says which and why.
    landmarks : pair of (L, D) float ndarrays, optional
        Fixed-space points and their moving-space partners, LPS mm.
    protocol : Protocol, optional
        Default :func:`volreg.protocol.load_protocol` ``("default")``.
    prior : callable, optional
        Target positions for the symmetric option (see :func:`fit_warp`), e.g. the
        inverse of a registration of ``moving`` to ``fixed``.
    progress : callable, optional
        ``progress(stage, done, total)``.

    Returns
    -------
    LabelRegistration

    Raises
    ------
    RegistrationInputError
        No label in common, a requested label absent from a volume, or, with
        the protocol's ``distance_weight`` 0, no label with a surface in both
        volumes (with distance maps every common label drives, surface or not).
    """
    from .protocol import load_protocol  # protocol imports this module
    from .surfaces import label_surfaces, voxel_size

    protocol = load_protocol("default") if protocol is None else protocol
    if fixed.ndim != moving.ndim:
        raise RegistrationInputError(f"Expected `fixed` and `moving` of the same dimension, got {fixed.ndim}-D and {moving.ndim}-D.")
    common = sorted(set(fixed.labels().tolist()) & set(moving.labels().tolist()))
    if not common:
        raise RegistrationInputError(
            f"The fixed and moving volumes have no label in common (fixed: {fixed.labels().tolist()[:20]}, "
            f"moving: {moving.labels().tolist()[:20]}); expected the same label values for the same structures."
        )
    if drive_labels is None:
        labels = common
    else:
        labels = [int(v) for v in drive_labels]
        if not labels:
            raise RegistrationInputError("Expected at least one label in `drive_labels`, got none.")
        absent = [v for v in labels if v not in common]
        if absent:
            raise RegistrationInputError(
                f"Drive label {absent[0]} is not present in both volumes (labels in both: {common[:30]})."
            )
    stages = []
    t0 = time.perf_counter()
    skipped = []
    # Specks (pieces under SPECK_FRACTION of a label) are removed before the surfaces are
    # made; whether a label is speckled is judged on pieces of at least 5 %.
    clean_fixed, speckled_f = despeckle(fixed, labels, piece=SPECK_FRACTION, judge=0.05)
    clean_moving, speckled_m = despeckle(moving, labels, piece=SPECK_FRACTION, judge=0.05)
    if drive_labels is None:
        # Speckled labels (a sheet broken into many pieces by the voxel grid) give pieces in
        # one volume that have no partner in the other; their implicit surfaces then differ by
        # tens of mm near the surfaces and mislead the warp.  They are warped, not driving.
        for v in labels:
            frac = min(speckled_f[v], speckled_m[v])
            if frac < COMPACT_FRACTION:
                how = ("only its voxel distance map does" if protocol.surface.distance_weight > 0
                       else "name it in drive_labels to use it anyway")
                skipped.append(f"Label {v}'s surface does not drive the warp: only {100 * frac:.0f} % of its voxels lie in "
                               f"pieces of at least 5 % of the label (speckled); {how}.")
        labels = [v for v in labels if min(speckled_f[v], speckled_m[v]) >= COMPACT_FRACTION]
        if not labels and protocol.surface.distance_weight <= 0:
            raise RegistrationInputError(
                "Every common label is speckled (many small pieces) and the protocol's distance_weight is 0; "
                "choose drive_labels explicitly, or set distance_weight > 0 so that the labels' distance maps drive."
            )
    surfaces = {}
    for name, volume in (("fixed", clean_fixed), ("moving", clean_moving)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            surfaces[name] = label_surfaces(volume, labels, on_small="warn", smoothing=protocol.surface.smoothing,
                                            progress=progress)
        if protocol.surface.distance_weight > 0:
            skipped += [f"{name} volume: {str(w.message).rstrip('.')}; its voxel distance map drives instead." for w in caught]
        else:
            skipped += [f"{name} volume: {w.message}" for w in caught]
    s_fixed, s_moving = surfaces["fixed"], surfaces["moving"]
    used = [v for v in labels if v in s_fixed and v in s_moving]
    if not used and protocol.surface.distance_weight <= 0:
        # With distance maps (distance_weight > 0) every label drives, with a surface or not.
        raise RegistrationInputError(
            f"No label of {labels[:30]} gives a surface in both volumes and the protocol's distance_weight is 0; "
            "nothing drives the warp (set distance_weight > 0 to drive by the labels' voxel distance maps)."
        )
    stages.append(dict(stage="surfaces", seconds=time.perf_counter() - t0))

    t0 = time.perf_counter()
    pairs = []
    w_fixed = protocol.surface.min_width_voxels * voxel_size(fixed)
    w_moving = protocol.surface.min_width_voxels * voxel_size(moving)
    jobs = []
    for v in used:
        # One coarsest width and one offset for both objects of a label: far from the
        # surfaces f1 and f2 then agree (f = b), instead of differing by a constant that
        # the locational cost would try to explain by moving points.
        top = max(_diameter(s_fixed[v].vertices), _diameter(s_moving[v].vertices)) / 2
        top = max(top, w_fixed, w_moving)
        jobs += [(s_fixed[v], w_fixed, top), (s_moving[v], w_moving, top)]

    def fit(job) -> ImplicitSurface:
        surface, min_width, top = job
        return ImplicitSurface(surface.vertices, surface.normals, min_width=min_width, max_width=top, offset=top)

    # The fits are independent: on two threads (numba releases the GIL) the frog's took 1.3 s
    # instead of 2.3 s at 3 mm, with identical results.
    fits = thread_map(fit, jobs)
    try:
        for i, (f1, f2) in enumerate(zip(fits, fits)):
            pairs.append(FeaturePair(f1, f2))
            if progress is not None:
                progress("fit implicit surfaces", i + 1, len(used))
    finally:
        fits.close()  # joins the threads, also when progress raises (an interrupt)
    stages.append(dict(stage="implicit surfaces", seconds=time.perf_counter() - t0))

    weight = protocol.surface.distance_weight
    distance_labels = []
    if weight > 0:
        # Voxel signed-distance features: every label in both volumes (or the chosen
        # drive labels), also those too small or too fragmented for a surface.
        t0 = time.perf_counter()
        distance_labels = common if drive_labels is None else labels
        boxes_f, boxes_m = fixed.label_boxes(), moving.label_boxes()
        for i, v in enumerate(distance_labels):
            pairs.append(FeaturePair(_voxel_distance(fixed, v, boxes_f, protocol.surface),
                                     _voxel_distance(moving, v, boxes_m, protocol.surface), weight))
            if progress is not None:
                progress("voxel distance maps", i + 1, len(distance_labels))
        stages.append(dict(stage="voxel distance maps", seconds=time.perf_counter() - t0))

    t0 = time.perf_counter()
    points = [s_fixed[v].vertices for v in used]
    # Labels that drive only through their distance maps: their boundary voxels join the
    # points whose padded neighbourhood is the warp volume X.
    points += [_boundary_points(fixed, v, boxes_f[v]) for v in distance_labels if v not in used]
    points = np.concatenate(points)
    result = fit_warp(pairs, points, landmarks=landmarks, settings=protocol.warp, prior=prior, progress=progress)
    stages.append(dict(stage="fit warp", seconds=time.perf_counter() - t0))
    return LabelRegistration(result.warp, result.log, labels=used, skipped=skipped, stages=stages,
                             distance_labels=[int(v) for v in distance_labels])


def _boundary_points(volume, value: int, box) -> np.ndarray:
    """World points (LPS mm, (N, D)) of the voxels of label ``value`` on its boundary
    (with a face neighbour of another value), within its bounding box ``box``."""
    from scipy import ndimage

    window = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
    mask = volume.array[window] == value
    edge = mask & ~ndimage.binary_erosion(mask, border_value=0)  # never empty: the box holds the label
    return volume.index_to_world(np.argwhere(edge) + np.array([w.start for w in window]))


def _voxel_distance(volume, value: int, boxes: dict, settings):
    """The :class:`~volreg.distance_maps.VoxelDistance` of label ``value`` of ``volume`` (its
    bounding box in ``boxes``), with the clip and blur of ``settings`` (a SurfaceSettings;
    voxels of the largest spacing)."""
    from .distance_maps import VoxelDistance

    unit = float(np.max(volume.spacing))
    clip, smoothing = settings.distance_clip * unit, settings.distance_smoothing * unit
    # Only the label's box, padded beyond VoxelDistance's own crop, is compared with the value.
    pad = np.ceil((clip + 3 * smoothing) / volume.spacing).astype(int) + 3
    lo = np.array([max(b.start - p, 0) for b, p in zip(boxes[value], pad)])
    window = tuple(slice(a, min(b.stop + p, n)) for a, b, p, n in zip(lo, boxes[value], pad, volume.shape))
    origin = volume.origin + volume.direction @ (volume.spacing * lo)
    return VoxelDistance(volume.array[window] == value, volume.spacing, origin, volume.direction,
                         clip=clip, smoothing=smoothing)

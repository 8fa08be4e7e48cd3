"""The coarse-to-fine fit of the kernel warp (paper Section 3.5).

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
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence
import numpy as np
import scipy.optimize
import scipy.sparse as sp
import scipy.sparse.linalg
from scipy.spatial import cKDTree
from volreg._threads import single_blas
from volreg.kernels import CellGrid, SharedPatternCSR, _check_points, kernel_gradient_matrices, kernel_matrix, kernel_sum
from volreg.warp.objective import FeaturePair, LevelObjective, simplex_vertices
from volreg.warp.sampling import octree_sample
from volreg.warp.model import KernelWarp, WarpLevel, jacobian_det
from volreg.errors import RegistrationDiverged
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
        if folded_fraction(jacobian_determinant_on_grid(KernelWarp(levels[:k], dim=warp.dim), reference)) > max_fraction:
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

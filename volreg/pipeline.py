"""Surface-to-surface registration: the coarse-to-fine driver (paper Section 3.5).

For each level, from a kernel width of half the source diameter down to
``min_width`` (halving each time):

1. sample the warp volume X -- the source surfaces padded by ``pad`` mm -- by
   octree subdivision down to boxes of half the width (Section 3.5); the box
   centres are both the level's kernel centres and its sample points;
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

from .implicit import ImplicitSurface
from .kernels import CellGrid, _check_points, kernel_gradient_matrices, kernel_matrix, kernel_sum
from .objective import FeaturePair, LevelObjective, simplex_vertices
from .sampling import octree_sample
from .warp import KernelWarp, WarpLevel

__all__ = ["WarpSettings", "RegistrationResult", "register_surfaces", "fit_warp"]


@dataclass(frozen=True)
class WarpSettings:
    """Settings of the warp fit (the protocol's warp section).

    Attributes
    ----------
    pad : float, mm, optional
        Padding of the warp volume X around the source surfaces; default 10 % of
        the source diameter.
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
    lambda_fold : float
        Weight of the fold barrier (not in the paper): ``lambda_fold mean
        max(0, fold_margin - det d tau/dx)^2`` over the samples and their
        octree children, so that L-BFGS keeps the warp orientation-preserving.
    fold_margin : float
        Determinant below which the barrier acts.
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
    lambda_p: float = 0.0
    neighbourhood: float = 0.0
    fraction: float = 0.5
    max_iter: int = 200
    lambda_fold: float = 1e5
    fold_margin: float = 0.3
    min_det: float = 0.1

    def __post_init__(self) -> None:
        for name in ("lambda_loc", "alpha", "lambda_p", "neighbourhood", "lambda_fold", "fold_margin", "min_det"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"Expected `{name}` >= 0, got {value}.")
        for name in ("pad", "min_width"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f"Expected a positive `{name}` (mm), got {value}.")
        if not 0 < self.fraction <= 1:
            raise ValueError(f"Expected `fraction` in (0, 1], got {self.fraction}.")
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


def fit_warp(
    features: Sequence[FeaturePair],
    source_points: np.ndarray,
    *,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    settings: WarpSettings = WarpSettings(),
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
    warp = KernelWarp(dim=dim, settings=dict(asdict(settings), pad=pad, min_width=min_width))
    log = []
    for li, width in enumerate(widths):
        t0 = time.perf_counter()
        samples = octree_sample(pts, pad, width, fraction=settings.fraction)
        use_landmarks = landmarks is not None
        # Centres: the samples, plus the source landmarks (the representer theorem puts
        # kernels at every training point, so landmarks away from X can be fitted too).
        centres = np.concatenate([samples, src_l]) if use_landmarks else samples
        grid = CellGrid.build(centres, width)
        k_cc = kernel_matrix(centres, grid, width)
        k_xc = k_cc[: len(samples)] if use_landmarks else k_cc  # samples are the first centres
        base = warp(samples)
        kw = {}
        if use_landmarks:
            kw = dict(landmark_kernel=kernel_matrix(src_l, grid, width), landmark_base=warp(src_l),
                      landmark_targets=dst_l, lambda_p=settings.lambda_p)
        check = _with_children(samples)
        j_prev = warp.jacobian(check)  # coarser levels' Jacobian at the fold-check points
        if settings.lambda_fold > 0:
            kw.update(fold_gradients=kernel_gradient_matrices(check, centres, width), fold_base=j_prev,
                      lambda_fold=settings.lambda_fold, fold_margin=settings.fold_margin)
        objective = LevelObjective(kernel=k_xc, kernel_centres=k_cc, base=base, samples=samples,
                                   features=features, lambda_loc=settings.lambda_loc, alpha=settings.alpha,
                                   neighbourhood=neighbourhood, **kw)
        c0 = np.zeros((len(centres), dim))
        if use_landmarks:
            c0 = _landmark_init(sp.csr_matrix(k_cc), kw["landmark_kernel"], kw["landmark_base"], dst_l,
                                settings.lambda_p)
        e0, _ = objective(c0.ravel())
        terms0 = dict(objective.last_terms)
        res = scipy.optimize.minimize(objective, c0.ravel(), jac=True, method="L-BFGS-B",
                                      options=dict(maxiter=settings.max_iter))
        coeffs = res.x.reshape(-1, dim)
        # Fold guard: tau must stay orientation-preserving, checked at the samples
        # and at the centres of their octree children (the next level's samples).
        # If the level folds space there (det J < min_det), shrink its coefficients;
        # where coarser levels are already below min_det, it must not make it worse.
        j_level = kernel_sum(check, grid, coeffs, width, order=1)[1]
        floor = min(settings.min_det, float(np.linalg.det(j_prev).min()))
        scale = 1.0
        for _ in range(20):
            if np.linalg.det(j_prev + scale * j_level).min() >= floor:
                break
            scale *= 0.7
        else:
            scale = 0.0
        coeffs = scale * coeffs
        warp = warp.with_level(WarpLevel(centres, coeffs, width))
        log.append(dict(level=li, width=width, samples=int(len(samples)), centres=int(len(centres)),
                        iterations=int(res.nit),
                        converged=bool(res.success), fold_scale=scale, objective_start=float(e0),
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

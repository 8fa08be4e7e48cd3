"""The warp objective (11) of one level and its analytic gradient.

At a level of kernel width ``sigma`` with centres ``x_j`` (the level's training
points, paper Section 3.5) the warp is

    tau(x) = tau_prev(x) + sum_j c_j k(x, x_j)                        (9)

where ``tau_prev`` holds the coarser levels (fixed).  The objective over the
coefficients ``C`` (M, D) is (11) with the empirical measure on the sample
points ``x`` (mean over them, so ``lambda_loc`` does not depend on how densely
a level is sampled):

    E(C) = 1/2 sum_d C_d^T K C_d                                      (10)
         + lambda_p sum_i |tau(p_i) - z_i|^2                          (8)
         + lambda_loc mean_x sum_l w_l [ (f1_l(x) - f2_l(tau(x)))^2    (3), (6)
                                  + alpha |grad f1_l(x) - grad f2_l(tau(x))|^2 ]   (4)

Optionally (not in the paper) a consistency term ``lambda_target mean_x |tau(x) - t(x)|^2``
pulls the warp towards given positions ``t(x)`` of the samples, e.g. the
inverse of a registration in the opposite direction (the symmetric option).

``f1_l``, ``f2_l`` are feature functions (one implicit surface per label and
object, (6)); ``alpha`` (mm^2) weighs the gradient term, ``alpha = 0`` giving
the distance-only cost (3).  Optionally the neighbourhood cost (5) replaces
``f(x)`` by ``f(x + dx)`` for ``dx`` over the vertices of a regular simplex.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.sparse as sp

from volreg.features.batch import FeatureBatch
from volreg.kernels import SharedPatternCSR

__all__ = ["FeaturePair", "LevelObjective", "simplex_vertices"]

#: ``evaluate(points, order) -> (f, grad f[, hess f])`` as ImplicitSurface.evaluate.
Feature = Callable[..., tuple]


@dataclass(frozen=True)
class FeaturePair:
    """One feature function of each object (paper (6)): ``f1`` on O1, ``f2`` on O2.

    ``f1`` and ``f2`` are objects with ``evaluate(points, order=...)`` returning
    ``(f, grad f[, hess f])`` (e.g. :class:`~volreg.features.implicit.ImplicitSurface`).
    """

    f1: object
    f2: object
    weight: float = 1.0


def simplex_vertices(dim: int, radius: float) -> np.ndarray:
    """Vertices of a regular simplex centred at 0 with circumradius ``radius`` (mm).

    Returns
    -------
    (dim + 1, dim) float ndarray
    """
    e = np.eye(dim + 1) - 1.0 / (dim + 1)
    # Orthonormal basis of the hyperplane sum = 0, then project the unit vectors.
    q, _ = np.linalg.qr(e[:, :dim])
    v = e @ q
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return radius * v


@dataclass
class LevelObjective:
    """Objective (11) for one level's coefficients, with analytic gradient.

    Parameters
    ----------
    kernel : (N, M) sparse matrix
        ``k(x_n, c_j)`` between the sample points and the level's centres.
    kernel_centres : (M, M) sparse matrix
        ``k(c_i, c_j)`` among the centres (the regulariser's Gram matrix (10)).
    base : (N, D) float ndarray, mm
        ``tau_prev(x)`` at the sample points.
    samples : (N, D) float ndarray, mm
        The sample points ``x`` themselves.
    features : sequence of FeaturePair
    lambda_loc : float
        Weight of the locational cost (``WarpSettings.lambda_loc``).
    alpha : float, mm^2
        Weight of its gradient term (4); 0 (default) gives the distance-only cost (3).
    landmark_kernel : (L, M) sparse matrix, optional
        ``k(p_i, c_j)`` for source landmarks ``p_i``.
    landmark_base : (L, D) float ndarray, mm, optional
        ``tau_prev(p_i)``.
    landmark_targets : (L, D) float ndarray, mm, optional
        ``z_i``.
    lambda_p : float
        Landmark weight (8).
    neighbourhood : (K, D) float ndarray, mm, optional
        Offsets ``dx`` of the neighbourhood cost (5) (e.g. :func:`simplex_vertices`);
        default only ``dx = 0``.
    fold_gradients : list of D (P, M) sparse matrices or SharedPatternCSR, optional
        ``d k(y_p, c_j) / d y_b`` at fold-check points ``y_p``
        (:func:`~volreg.kernels.kernel_gradient_matrices`).
    fold_base : (P, D, D) float ndarray, optional
        Jacobian of ``tau_prev`` at the fold-check points.
    lambda_fold : float
        Weight of the fold barrier (not in the paper): ``lambda_fold mean_p
        max(0, fold_margin - det J(y_p))^2`` keeps the warp orientation-preserving.
        0 (default) = off.
    fold_margin : float, optional
        Determinant below which the barrier acts (``WarpSettings.fold_margin``);
        required when ``lambda_fold > 0``.
    fold_count : int, optional
        The number of fold-check points the barrier's mean runs over; default the
        rows of ``fold_gradients``.  Larger when those rows are only the points where
        the barrier can act (:meth:`set_fold`): elsewhere its terms are 0.
    sample_targets : (N, D) float ndarray, mm, optional
        ``t(x)``: positions the samples should map to (consistency term).
    lambda_target : float
        Weight of the consistency term ``lambda_target mean_x |tau(x) - t(x)|^2``
        (mm^-2 times the locational cost's units); 0 = off.
    robust : float, mm
        If > 0, the distance term (3) uses the pseudo-Huber loss
        ``2 robust^2 (sqrt(1 + (r / robust)^2) - 1)`` of the residual
        ``r = f1(x) - f2(tau(x))`` instead of ``r^2`` (not in the paper): equal to
        ``r^2`` for ``|r| << robust``, growing only linearly beyond, so that the few
        samples where two implicit surfaces disagree by tens of mm (seen on thin,
        fragmented labels after resampling) do not outweigh the rest.  0 = off.
    feature_samples : list of (N_l,) int ndarrays or None, optional
        For each feature pair, the indices of the samples where it can be
        non-constant (``None``: all).  Elsewhere both ``f1`` and ``f2(tau)`` sit
        at their offsets, their residual is a constant with zero gradient, and
        skipping those samples changes neither the minimiser nor the gradient
        (with many labels, each label's surface is near few samples).
    batched : bool
        Evaluate the ``f2`` (and, once, the ``f1``) of all feature pairs in one compiled
        pass (:class:`~volreg.features.batch.FeatureBatch`) where they support it
        (implicit surfaces and voxel distance maps, through one common linear map).
        ``False``: one feature at a time; the two agree up to rounding.
    shared : dict, optional
        Kept across the objectives of one sample set (the levels of a fit that share their
        samples): the first fills it with the features' batches and the fixed features at the
        samples, which the others then reuse, given the same samples, features and offsets.
    """

    kernel: sp.spmatrix
    kernel_centres: sp.spmatrix
    base: np.ndarray
    samples: np.ndarray
    features: Sequence[FeaturePair]
    lambda_loc: float
    alpha: float = 0.0
    landmark_kernel: sp.spmatrix | None = None
    landmark_base: np.ndarray | None = None
    landmark_targets: np.ndarray | None = None
    lambda_p: float = 0.0
    neighbourhood: np.ndarray | None = None
    fold_gradients: list | SharedPatternCSR | None = None
    fold_base: np.ndarray | None = None
    lambda_fold: float = 0.0
    fold_margin: float | None = None
    fold_count: int | None = None
    feature_samples: Sequence[np.ndarray | None] | None = None
    sample_targets: np.ndarray | None = None
    lambda_target: float = 0.0
    robust: float = 0.0
    batched: bool = True
    _f1: list = field(default_factory=list, init=False, repr=False)
    last_terms: dict = field(default_factory=dict, init=False, repr=False)
    _dense: tuple | None = field(default=None, init=False, repr=False)
    _memo: tuple | None = field(default=None, init=False, repr=False)
    shared: dict | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.kernel = sp.csr_matrix(self.kernel)
        self.kernel_centres = sp.csr_matrix(self.kernel_centres)
        # Products in parallel over rows (with the transpose precomputed).
        self._kernel = SharedPatternCSR([self.kernel])
        self._kernel_centres = SharedPatternCSR([self.kernel_centres])
        n, m = self.kernel.shape
        self.dim = self.base.shape[1]
        if self.samples.shape != self.base.shape or self.base.shape[0] != n:
            raise ValueError(f"Expected `samples` and `base` of shape ({n}, D), got {self.samples.shape}, {self.base.shape}.")
        if self.kernel_centres.shape != (m, m):
            raise ValueError(f"Expected `kernel_centres` of shape ({m}, {m}), got {self.kernel_centres.shape}.")
        offsets = np.zeros((1, self.dim)) if self.neighbourhood is None else np.asarray(self.neighbourhood, float)
        self.offsets = offsets
        # f1 and its gradient at the (fixed) sample points, once per offset.
        order = 1 if self.alpha > 0 else 0
        subsets = [None] * len(self.features) if self.feature_samples is None else list(self.feature_samples)
        if len(subsets) != len(self.features):
            raise ValueError(f"Expected one entry of `feature_samples` per feature, got {len(subsets)} for {len(self.features)}.")
        self._subsets = [None if s is None else np.asarray(s, dtype=np.intp) for s in subsets]
        # Levels that share their samples and features share what follows (the fixed features at
        # the samples: an evaluation of every feature, and the batches' layout).
        key = (tuple(id(pair) for pair in self.features), tuple(id(s) for s in subsets), id(self.samples),
               order, offsets.tobytes(), self.batched)
        if self.shared is not None and self.shared.get("key") == key:
            (self._batch, self._f1, self._rows, self._starts, self._row_weight,
             self._f1_rows) = self.shared["features"]
        else:
            self._prepare_features(n, order)
            if self.shared is not None:
                self.shared.update(key=key, keep=(self.features, subsets, self.samples),
                                   features=(self._batch, self._f1, self._rows, self._starts, self._row_weight,
                                             self._f1_rows))
        if self.lambda_p > 0:
            if self.landmark_kernel is None or self.landmark_base is None or self.landmark_targets is None:
                raise ValueError("Expected `landmark_kernel`, `landmark_base` and `landmark_targets` when `lambda_p` > 0.")
            self.landmark_kernel = sp.csr_matrix(self.landmark_kernel)
            self.landmark_kernel_t = self.landmark_kernel.T.tocsr()
        self.n_centres = m
        if not (np.isfinite(self.robust) and self.robust >= 0):
            raise ValueError(f"Expected `robust` >= 0 (mm), got {self.robust}.")
        if self.lambda_target > 0 and (self.sample_targets is None or np.shape(self.sample_targets) != self.samples.shape):
            raise ValueError(f"Expected `sample_targets` of shape {self.samples.shape} when `lambda_target` > 0.")
        if self.lambda_fold > 0:
            if self.fold_gradients is None or self.fold_base is None:
                raise ValueError("Expected `fold_gradients` and `fold_base` when `lambda_fold` > 0.")
            if self.fold_margin is None:
                raise ValueError("Expected `fold_margin` (the determinant below which the barrier acts) "
                                 "when `lambda_fold` > 0.")
            self.set_fold(self.fold_gradients, self.fold_base, self.fold_count)

    def _prepare_features(self, n: int, order: int) -> None:
        """The features' batches and the fixed features (f1, up to ``order``) at the ``n`` samples."""
        offsets = self.offsets
        self._rows = self._starts = self._row_weight = self._f1_rows = None
        # With many labels each feature sits at a few dozen samples: evaluated one by one, the
        # calls cost far more than the arithmetic.  The batch evaluates all at once.
        self._batch = FeatureBatch.build([pair.f2 for pair in self.features]) if self.batched and self.features else None
        fixed_batch = FeatureBatch.build([pair.f1 for pair in self.features]) if self._batch is not None else None
        self._f1 = []
        if self._batch is None or fixed_batch is None:
            self._f1 = [
                [pair.f1.evaluate((self.samples if idx is None else self.samples[idx]) + dx, order=order)
                 for dx in offsets]
                for pair, idx in zip(self.features, self._subsets)
            ]
        if self._batch is not None:
            rows = [np.arange(n) if idx is None else idx for idx in self._subsets]
            counts = np.array([len(r) for r in rows], dtype=np.int64)
            self._rows = np.concatenate(rows).astype(np.intp)
            self._starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
            self._row_weight = np.repeat(np.array([pair.weight for pair in self.features], float), counts)
            if fixed_batch is not None:
                self._f1_rows = [fixed_batch.evaluate(self.samples[self._rows] + dx, self._starts, order=order)
                                 for dx in offsets]
            else:
                self._f1_rows = [tuple(np.concatenate([f1[k][j] for f1 in self._f1]) for j in range(order + 1))
                                 for k in range(len(offsets))]

    def set_fold(self, gradients, base: np.ndarray, count: int | None = None) -> None:
        """Replace the fold barrier's check points (``lambda_fold`` stays).

        Parameters
        ----------
        gradients : list of D (P, M) sparse matrices or SharedPatternCSR
            As ``fold_gradients``, at P points (P may be 0).
        base : (P, D, D) float ndarray
            As ``fold_base``.
        count : int, optional
            As ``fold_count``; default P.
        """
        # The D gradient matrices share one pattern: each product reads it once.  Only
        # the shared copy is kept (these are the largest matrices of a level).
        self._memo = None  # the objective changes
        self._fold = gradients if isinstance(gradients, SharedPatternCSR) else SharedPatternCSR(gradients)
        self.fold_gradients = None
        self.fold_base = np.asarray(base, dtype=float)
        if self._fold.shape[0] != len(self.fold_base) or self._fold.shape[1] != self.kernel.shape[1]:
            raise ValueError(f"Expected fold gradients of shape ({len(self.fold_base)}, {self.kernel.shape[1]}), "
                             f"got {self._fold.shape}.")
        self.fold_count = len(self.fold_base) if count is None else int(count)
        if self.fold_count < len(self.fold_base):
            raise ValueError(f"Expected `fold_count` >= {len(self.fold_base)} (the rows given), got {self.fold_count}.")

    def warp_samples(self, coeffs: np.ndarray) -> np.ndarray:
        """``tau(x)`` at the sample points for coefficients ``coeffs`` (M, D)."""
        return self.base + self._kernel.matmul(coeffs)[:, :, 0]

    def __call__(self, flat: np.ndarray) -> tuple[float, np.ndarray]:
        """Objective and gradient at flattened coefficients (M * D,), for scipy.optimize.

        The last call's result is kept: a level evaluates its start before L-BFGS does, and its
        end again for the log, each an evaluation of every feature at every sample.
        """
        flat = np.asarray(flat, dtype=float)
        key = flat.tobytes()
        if self._memo is not None and self._memo[0] == key:
            _, value, grad, terms = self._memo
            self.last_terms = dict(terms)
            return value, grad.copy()
        value, grad = self._evaluate(flat, None)
        self._memo = (key, value, grad.copy(), dict(self.last_terms))
        return value, grad

    @property
    def gauss_newton_ready(self) -> bool:
        """Whether :meth:`gauss_newton` applies: no fold-barrier rows are active (the barrier
        is the one term without a Gauss-Newton model here)."""
        return self.lambda_fold <= 0 or self.fold_base is None or len(self.fold_base) == 0

    def gauss_newton(self, flat: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """Objective, gradient, and the Gauss-Newton model of the sample terms' curvature.

        The locational cost's residuals are linearised in ``tau`` (for the pseudo-Huber loss,
        its iteratively reweighted least-squares weight ``1 / sqrt(1 + (r / robust)^2)``):
        per sample, the (D, D) block ``B_x`` such that the model's Hessian in ``tau(x)`` is
        ``B_x`` (with the consistency term's ``2 lambda_target / N I``).
        :meth:`gauss_newton_matrix` turns the blocks into the model's Hessian in the
        coefficients.

        Parameters
        ----------
        flat : (M * D,) float ndarray

        Returns
        -------
        value : float
        gradient : (M * D,) float ndarray
        blocks : (N, D, D) float ndarray, per sample

        Raises
        ------
        ValueError
            If the fold barrier has active rows (:attr:`gauss_newton_ready` is False).
        """
        if not self.gauss_newton_ready:
            raise ValueError("Expected no active fold-barrier rows for a Gauss-Newton model.")
        blocks = np.zeros((len(self.samples), self.dim, self.dim))
        value, grad = self._evaluate(flat, blocks)
        return value, grad, blocks

    def gauss_newton_matrix(self, blocks: np.ndarray) -> np.ndarray:
        """The Gauss-Newton model's Hessian in the coefficients, dense (M * D, M * D).

        ``H[(j, a), (k, b)] = sum_x K_xj K_xk B_x[a, b] + delta_ab (K_cc[j, k] +
        2 lambda_p (K_l^T K_l)[j, k])``: the regulariser (10) and the landmark term (8) are
        quadratic, so theirs is exact.  Dense: for the small coarse levels only.

        Parameters
        ----------
        blocks : (N, D, D) float ndarray
            From :meth:`gauss_newton`.
        """
        if self._dense is None:  # the same at every step: made once
            common = self.kernel_centres.toarray()
            if self.lambda_p > 0:
                lk = self.landmark_kernel.toarray()
                common = common + 2.0 * self.lambda_p * (lk.T @ lk)
            self._dense = (self.kernel.toarray(), common)
        k, common = self._dense
        m, d = self.n_centres, self.dim
        h = np.zeros((m, d, m, d))
        for a in range(d):
            for b in range(a, d):
                part = k.T @ (blocks[:, a, b, None] * k)
                h[:, a, :, b] = part
                if b != a:
                    h[:, b, :, a] = part.T
        for a in range(d):
            h[:, a, :, a] += common
        return h.reshape(m * d, m * d)

    def _evaluate(self, flat: np.ndarray, blocks: np.ndarray | None) -> tuple[float, np.ndarray]:
        """Objective and gradient; with ``blocks`` (N, D, D) (zeros), also the Gauss-Newton
        blocks of :meth:`gauss_newton`, added into it."""
        c = flat.reshape(self.n_centres, self.dim)
        kc = self._kernel_centres.matmul(c)[:, :, 0]
        reg = 0.5 * float(np.einsum("md,md->", c, kc))
        grad = kc.copy()
        tau = self.warp_samples(c)
        n = len(tau)
        dist_term = 0.0
        grad_term = 0.0
        g_tau = np.zeros_like(tau)
        scale = self.lambda_loc / (n * len(self.offsets))
        order = 2 if self.alpha > 0 else 1
        if self._batch is not None:
            dist_term, grad_term = self._batched_terms(tau, g_tau, order, 2 * scale, blocks)
        else:
            for pair, f1_list, idx in zip(self.features, self._f1, self._subsets):
                dists, grads, g_l, b_l = _feature_terms(pair, f1_list, idx, tau=tau, offsets=self.offsets,
                                                        order=order, alpha=self.alpha, robust=self.robust,
                                                        factor=2 * scale, curvature=blocks is not None)
                for value in dists:
                    dist_term += value
                for value in grads:
                    grad_term += value
                if idx is None:
                    g_tau += g_l
                else:
                    g_tau[idx] += g_l  # the indices of one feature are distinct
                if blocks is not None:
                    if idx is None:
                        blocks += b_l
                    else:
                        blocks[idx] += b_l
        consistency = 0.0
        if self.lambda_target > 0:
            resid = tau - self.sample_targets
            consistency = self.lambda_target * float(np.einsum("nd,nd->", resid, resid)) / n
            g_tau += (2.0 * self.lambda_target / n) * resid
            if blocks is not None:
                blocks += (2.0 * self.lambda_target / n) * np.eye(self.dim)
        grad += self._kernel.rmatmul_sum(g_tau[:, :, None])
        loc = scale * (dist_term + grad_term)
        land = 0.0
        if self.lambda_p > 0:
            resid = self.landmark_base + self.landmark_kernel @ c - self.landmark_targets
            land = self.lambda_p * float(np.einsum("ld,ld->", resid, resid))
            grad += self.landmark_kernel_t @ (2 * self.lambda_p * resid)
        fold = 0.0
        if self.lambda_fold > 0 and len(self.fold_base):
            jac = self.fold_base + self._fold.matmul(c)  # jac[:, :, b] += G_b @ c
            det, cof = _det_cofactor(jac)
            short = np.maximum(self.fold_margin - det, 0.0)
            p = self.fold_count
            fold = self.lambda_fold * float(short @ short) / p
            w = (-2.0 * self.lambda_fold / p) * short[:, None, None] * cof  # dE/dJ, (P, D, D)
            grad += self._fold.rmatmul_sum(w)  # sum_b G_b^T @ w[:, :, b]
        self.last_terms = dict(regulariser=reg, landmarks=land, distance=scale * dist_term,
                               gradient=scale * grad_term, folding=fold, consistency=consistency)
        return reg + land + loc + fold + consistency, grad.ravel()

    def _batched_terms(self, tau: np.ndarray, g_tau: np.ndarray, order: int, factor: float,
                       blocks: np.ndarray | None = None) -> tuple[float, float]:
        """The locational cost's distance and gradient sums (unscaled) over all feature pairs
        at once (:class:`~volreg.features.batch.FeatureBatch`); adds their derivative with
        respect to ``tau`` (scaled by ``factor / 2``) to ``g_tau`` (N, D) in place, and with
        ``blocks`` (N, D, D) their Gauss-Newton blocks (:meth:`gauss_newton`)."""
        w = self._row_weight
        dist_term = 0.0
        grad_term = 0.0
        g_rows = np.zeros((len(self._rows), self.dim))
        b_rows = None if blocks is None else np.zeros((len(self._rows), self.dim, self.dim))
        tau_rows = tau[self._rows]
        for dx, f1 in zip(self.offsets, self._f1_rows):
            out = self._batch.evaluate(tau_rows + dx, self._starts, order=order)
            r = f1[0] - out[0]  # (R,)
            reweight = 1.0
            if self.robust > 0:
                root = np.sqrt(1.0 + (r / self.robust) ** 2)
                dist_term += 2.0 * self.robust**2 * float(w @ (root - 1.0))
                r = r / root  # d/dr of the loss, halved: r / sqrt(1 + (r / robust)^2)
                reweight = 1.0 / root
            else:
                dist_term += float(w @ (r * r))
            g_rows -= (factor * w * r)[:, None] * out[1]
            if b_rows is not None:
                b_rows += (factor * w * reweight)[:, None, None] * out[1][:, :, None] * out[1][:, None, :]
            if self.alpha > 0:
                rg = f1[1] - out[1]  # (R, D)
                grad_term += self.alpha * float(w @ np.einsum("nd,nd->n", rg, rg))
                g_rows -= (factor * self.alpha * w)[:, None] * np.einsum("nab,nb->na", out[2], rg)
                if b_rows is not None:
                    b_rows += (factor * self.alpha * w)[:, None, None] * np.einsum("nca,ncb->nab", out[2], out[2])
        for d in range(self.dim):
            g_tau[:, d] += np.bincount(self._rows, weights=g_rows[:, d], minlength=len(tau))
        if b_rows is not None:
            flat = blocks.reshape(len(tau), self.dim * self.dim)
            for e, column in enumerate(b_rows.reshape(len(self._rows), self.dim * self.dim).T):
                flat[:, e] += np.bincount(self._rows, weights=column, minlength=len(tau))
        return dist_term, grad_term


def _feature_terms(pair: FeaturePair, f1_list: list, idx: np.ndarray | None, *, tau: np.ndarray, offsets: np.ndarray,
                   order: int, alpha: float, robust: float, factor: float,
                   curvature: bool = False) -> tuple[list[float], list[float], np.ndarray, np.ndarray | None]:
    """One feature pair's share of the locational cost (3)-(6) and its gradient.

    Parameters
    ----------
    pair : FeaturePair
    f1_list : list of tuples
        Per offset, ``f1`` (and its gradient) at the pair's samples.
    idx : (N_l,) int ndarray or None
        The pair's samples (None: all).
    tau : (N, D) float ndarray, mm
        The warp at every sample.
    offsets : (K, D) float ndarray, mm
        Offsets ``dx`` of the neighbourhood cost (5).
    order : {1, 2}
        Derivatives of ``f2`` needed (2 with the gradient term).
    alpha : float, mm^2
        Weight of the gradient term (4).
    robust : float, mm
        Pseudo-Huber scale of the distance term, 0 for squares.
    factor : float
        ``2 lambda_loc / (N K)``: the scale of the gradient.
    curvature : bool
        Also return the pair's Gauss-Newton blocks (:meth:`LevelObjective.gauss_newton`).

    Returns
    -------
    dists, grads : lists of K floats
        The pair's weighted distance and gradient sums per offset (unscaled).
    g_l : (N_l, D) float ndarray
        Derivative of the scaled cost with respect to ``tau`` at the pair's samples.
    b_l : (N_l, D, D) float ndarray or None
        With ``curvature``, the Gauss-Newton blocks at the pair's samples.
    """
    tau_l = tau if idx is None else tau[idx]
    g_l = np.zeros_like(tau_l)
    b_l = np.zeros(tau_l.shape + tau_l.shape[1:]) if curvature else None
    dists, grads = [], []
    for dx, f1 in zip(offsets, f1_list):
        out = pair.f2.evaluate(tau_l + dx, order=order)
        r = f1[0] - out[0]  # (N_l,)
        reweight = 1.0
        if robust > 0:
            root = np.sqrt(1.0 + (r / robust) ** 2)
            dists.append(pair.weight * 2.0 * robust**2 * float(np.sum(root - 1.0)))
            r = r / root  # d/dr of the loss, halved: r / sqrt(1 + (r / robust)^2)
            reweight = 1.0 / root
        else:
            dists.append(pair.weight * float(r @ r))
        g_l -= (factor * pair.weight) * r[:, None] * out[1]
        if curvature:
            b_l += (factor * pair.weight * np.broadcast_to(reweight, r.shape))[:, None, None] * \
                out[1][:, :, None] * out[1][:, None, :]
        if alpha > 0:
            rg = f1[1] - out[1]  # (N_l, D)
            grads.append(pair.weight * alpha * float(np.einsum("nd,nd->", rg, rg)))
            g_l -= (factor * pair.weight * alpha) * np.einsum("nab,nb->na", out[2], rg)
            if curvature:
                b_l += (factor * pair.weight * alpha) * np.einsum("nca,ncb->nab", out[2], out[2])
    return dists, grads, g_l, b_l


def _det_cofactor(jac: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Determinants (P,) and cofactor matrices (P, D, D) of 2x2 or 3x3 matrices
    (``d det / d J = cofactor``, defined also where ``det = 0``)."""
    if jac.shape[1] == 2:
        cof = np.stack([np.stack([jac[:, 1, 1], -jac[:, 1, 0]], -1),
                        np.stack([-jac[:, 0, 1], jac[:, 0, 0]], -1)], 1)
    else:
        cof = np.stack([np.cross(jac[:, 1], jac[:, 2]), np.cross(jac[:, 2], jac[:, 0]),
                        np.cross(jac[:, 0], jac[:, 1])], 1)
    det = np.einsum("nab,nab->n", jac, cof) / jac.shape[1]
    return det, cof

"""Sparse matrices that share one sparsity pattern, with products that read the pattern once."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from volreg._threads import run_parts
from volreg.kernels._compiled import _csr_matmul_shared, _csr_matmul_shared_sum

#: Fewest matrix rows per part of a product (:func:`volreg._threads.run_parts`).
_ROWS = 256

__all__ = ["SharedPatternCSR"]


class SharedPatternCSR:
    """Up to 3 sparse (N, M) matrices with one sparsity pattern, and their transposes.

    For example the D gradient matrices of
    :func:`~volreg.kernels.sums.kernel_gradient_matrices`.  Products with up to
    3 columns read the pattern once and run over rows in parallel (scipy's
    ``csr_matvecs`` is single-threaded and reads the pattern once per matrix).

    Parameters
    ----------
    matrices : sequence of 1 to 3 scipy.sparse matrices, all (N, M) with the same pattern
    """

    def __init__(self, matrices) -> None:
        mats = [sp.csr_matrix(a) for a in matrices]
        if not 1 <= len(mats) <= 3:
            raise ValueError(f"Expected 1 to 3 matrices, got {len(mats)}.")
        first = mats[0]
        first.sort_indices()
        for a in mats[1:]:
            a.sort_indices()
            if a.shape != first.shape or not (np.array_equal(a.indptr, first.indptr)
                                              and np.array_equal(a.indices, first.indices)):
                raise ValueError("Expected matrices that share one sparsity pattern.")
        self.shape = first.shape
        self.indptr, self.indices = first.indptr, first.indices
        self.data = np.ascontiguousarray(np.stack([a.data for a in mats], axis=1))  # (nnz, B)
        # The transposed pattern, and where each of its entries sits in ``data``.
        where = sp.csr_matrix((np.arange(1, first.nnz + 1, dtype=float), first.indices, first.indptr),
                              shape=first.shape).T.tocsr()
        where.sort_indices()
        self.t_indptr, self.t_indices = where.indptr, where.indices
        self.t_data = np.ascontiguousarray(self.data[where.data.astype(np.int64) - 1])

    def matmul(self, x: np.ndarray) -> np.ndarray:
        """Products with every matrix.

        Parameters
        ----------
        x : (M, k) float ndarray, k <= 3

        Returns
        -------
        (N, k, B) float ndarray
            ``out[:, :, b] = A_b @ x``.
        """
        x = np.ascontiguousarray(x, dtype=float)
        out = np.zeros((len(self.indptr) - 1, x.shape[1], self.data.shape[1]))
        run_parts(_csr_matmul_shared, len(out), self.indptr, self.indices, self.data, x, out, grain=_ROWS)
        return out

    def rmatmul_sum(self, y: np.ndarray) -> np.ndarray:
        """Sum of the transposed products.

        Parameters
        ----------
        y : (N, k, B) float ndarray, k <= 3

        Returns
        -------
        (M, k) float ndarray
            ``sum_b A_b.T @ y[:, :, b]``.
        """
        y = np.ascontiguousarray(y, dtype=float)
        out = np.zeros((len(self.t_indptr) - 1, y.shape[1]))
        run_parts(_csr_matmul_shared_sum, len(out), self.t_indptr, self.t_indices, self.t_data, y, out,
                  grain=_ROWS)
        return out

"""The Wu kernel (paper eq. 13) and sparse neighbour sums over it.

``k(r) = (1 - r)_+^4 (4 + 16 r + 12 r^2 + 3 r^3)`` with ``r = |x - y| / sigma``
is compactly supported on ``|x - y| < sigma`` and C^2 in up to three dimensions,
so every kernel sum is a neighbour query and its gradient and Hessian exist in
closed form (:mod:`volreg.kernels.wu`).

Modules
-------
wu
    The kernel and its derivatives: numpy reference and the compiled helper.
grid
    :class:`CellGrid`, uniform cell grids for radius queries; spatial orders.
sums
    :func:`kernel_sum` (compiled, over a CellGrid), :func:`kernel_sum_reference`
    (scipy KD-tree, the test oracle), :func:`kernel_matrix`,
    :func:`kernel_gradient_matrices`; :func:`check_points`, the check of every
    point array the kernel sums and their callers take.
sparse
    :class:`SharedPatternCSR`, products with matrices sharing one pattern.
_compiled
    Every numba loop, private except :func:`segmented_sums`: the kernel sums of many point sets,
    each at its own segment of the queries, in one parallel loop (for :mod:`volreg.features.batch`).
"""

from volreg.kernels._compiled import segmented_sums
from volreg.kernels.grid import CellGrid, put_rows, spatial_order, take_rows
from volreg.kernels.sparse import SharedPatternCSR
from volreg.kernels.sums import (
    check_points,
    kernel_gradient_matrices,
    kernel_matrix,
    kernel_sum,
    kernel_sum_reference,
)
from volreg.kernels.wu import wu, wu_derivatives

__all__ = [
    "CellGrid",
    "SharedPatternCSR",
    "check_points",
    "kernel_gradient_matrices",
    "kernel_matrix",
    "kernel_sum",
    "kernel_sum_reference",
    "put_rows",
    "segmented_sums",
    "spatial_order",
    "take_rows",
    "wu",
    "wu_derivatives",
]

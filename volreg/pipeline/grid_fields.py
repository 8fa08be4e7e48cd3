"""A fitted warp on voxel grids: the forward field on the fixed grid, the inverse on the moving one.

:func:`sample_on_fixed_grid` gives the displacement u(x) = tau(x) - x and the analytic
Jacobian determinant at the fixed voxel centres (refusing a warp that folds) and the moving
labels resampled through it; :func:`inverse_on_moving_grid` inverts the warp at every moving
voxel centre (:class:`~volreg.warp.inverse.InverseWarp`), starting from the sampled forward field.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from volreg.warp.field import displacement_on_grid, fields_on_grid, indices_through
from volreg.warp.fit import check_folding
from volreg.warp.inverse import GridStart, InverseWarp, linear_part
from volreg.warp.resample import resample_labels_at

__all__ = ["INVERSE_GRID_TOL", "FixedGridFields", "inverse_on_moving_grid", "sample_on_fixed_grid"]


class FixedGridFields(NamedTuple):
    """The warp sampled at the voxel centres of the fixed grid, (X, Y, Z[, 3]) arrays."""

    displacement: np.ndarray  # u(x) = tau(x) - x, mm
    jacobian: np.ndarray  # det d tau / dx
    warped: np.ndarray  # the moving labels at tau(x)


def sample_on_fixed_grid(warp, fixed, moving, max_folded_fraction: float, progress) -> FixedGridFields:
    """The warp's displacement and Jacobian determinant on the fixed grid, checked for folding
    (:func:`~volreg.warp.fit.check_folding`), and the moving labels resampled through it
    (label-preserving)."""
    u, jac = fields_on_grid(warp, fixed, progress=progress)
    check_folding(warp, fixed, jac, max_folded_fraction)  # before more work
    # The moving labels at tau(x), from their indices there: no world points of the grid
    index = indices_through(fixed, u, moving)
    warped = resample_labels_at(moving, index, method="label", progress=progress).reshape(fixed.shape)
    return FixedGridFields(u, jac, warped)


#: The inverse written on the moving grid holds to this fraction of the grid's smallest spacing
#: (1 micrometre at 1 mm), checked exactly at every voxel.
INVERSE_GRID_TOL = 1e-3


def inverse_on_moving_grid(warp, moving, progress=None, fixed=None, displacement=None):
    """The warp's inverse (:class:`~volreg.warp.inverse.InverseWarp`) and its displacement on the moving grid, mm.

    To :data:`INVERSE_GRID_TOL` of the moving grid's smallest spacing.  Given the warp's
    ``displacement`` on the ``fixed`` grid, each voxel starts from its interpolated inverse
    (:class:`~volreg.warp.inverse.GridStart`), which one exact evaluation of the warp checks;
    chord steps, then Newton's method, go on only where that is not within the tolerance.
    """
    start = None if displacement is None else GridStart(displacement, fixed, linear_part(warp))
    # Nearly every start is within the tolerance already: checking it costs one evaluation of
    # tau, where polishing every voxel further would take its Jacobian and a second evaluation.
    inverse = InverseWarp(warp, start=start, tol=INVERSE_GRID_TOL * float(np.min(moving.spacing)))
    return inverse, displacement_on_grid(inverse, moving, progress=progress, stage="invert warp")

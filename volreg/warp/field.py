"""Dense fields of a warp on a voxel grid: displacements and Jacobian determinants.

A warp (:class:`~volreg.warp.model.KernelWarp`, :class:`~volreg.warp.inverse.InverseWarp`
or anything with ``evaluate``) is continuous; these functions sample it at the
voxel centres of a reference grid (a :class:`~volreg.grid.Grid`, a
:class:`~volreg.grid.LabelVolume`, whose array is not used, or a
``(shape, affine)`` pair).  Only the voxels inside the warp's support box are
evaluated -- elsewhere ``tau(x) = x`` exactly -- in chunks
(:meth:`~volreg.grid.Grid.chunks`), with a progress callback.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from volreg._threads import single_blas
from volreg.grid import GridLike, as_grid
from volreg.warp.model import jacobian_det

__all__ = ["displacement_on_grid", "fields_on_grid", "jacobian_determinant_on_grid", "support_slices"]

ProgressCallback = Callable[[str, int, int], None]


def support_slices(warp, reference: GridLike) -> tuple[slice, ...] | None:
    """Index slices of ``reference`` covering the warp's support box (``None``: no voxel).

    A warp without ``bounds()`` (e.g. a composition) is taken to move every voxel.
    """
    reference = as_grid(reference, "reference")
    if not hasattr(warp, "bounds"):
        return tuple(slice(0, n) for n in reference.shape)
    bounds = warp.bounds()
    if bounds is None:
        return None
    return reference.index_window(*bounds)


def _on_grid(warp, reference: GridLike, order: int, chunk: int, progress: ProgressCallback | None, stage: str):
    """Yield ``(flat voxel indices, world points, evaluate(...) output)`` chunk by chunk over the support."""
    reference = as_grid(reference, "reference")
    window = support_slices(warp, reference)
    if window is None:
        return
    for part in reference.chunks(chunk, window):
        yield part.flat, part.points, warp.evaluate(part.points, order=order)
        if progress is not None:
            progress(stage, part.done, part.total)


def displacement_on_grid(
    warp,
    reference: GridLike,
    *,
    chunk: int = 1 << 18,
    progress: ProgressCallback | None = None,
    stage: str = "evaluate warp",
) -> np.ndarray:
    """``u(x) = tau(x) - x`` at every voxel centre of ``reference``.

    Parameters
    ----------
    warp : KernelWarp, InverseWarp or any object with ``evaluate(points, order=...)``
    reference : Grid, LabelVolume or (shape, affine)
        The grid whose voxel centres are sampled (a volume's array is not used).
    chunk : int
        Voxels evaluated at a time: bounds the memory to a few ``chunk x D x D`` floats.
    progress : callable, optional
        ``progress(stage, done, total)`` after each chunk.
    stage : str
        The stage name passed to ``progress``.

    Returns
    -------
    (*reference.shape, D) float64 ndarray, LPS mm
        Zero outside the warp's support.  This is the field that ANTs and ITK
        call a displacement field on the fixed (reference) grid.
    """
    reference = as_grid(reference, "reference")
    out = np.zeros((int(np.prod(reference.shape)), reference.ndim))
    for flat, points, (tau, *_) in _on_grid(warp, reference, 0, chunk, progress, stage):
        out[flat] = tau - points
    return out.reshape(*reference.shape, reference.ndim)


def jacobian_determinant_on_grid(
    warp, reference: GridLike, *, chunk: int = 1 << 17, progress: ProgressCallback | None = None
) -> np.ndarray:
    """``det d tau / dx`` at every voxel centre of ``reference``, from the analytic Jacobian.

    Parameters
    ----------
    warp : KernelWarp, InverseWarp or any object with ``evaluate(points, order=...)``
    reference : Grid, LabelVolume or (shape, affine)
        The grid whose voxel centres are sampled (a volume's array is not used).
    chunk : int
        Voxels evaluated at a time: bounds the memory to a few ``chunk x D x D`` floats.
    progress : callable, optional
        ``progress(stage, done, total)`` after each chunk.

    Returns
    -------
    (*reference.shape) float64 ndarray
        1 outside the warp's support; ``<= 0`` where the warp folds space.
    """
    reference = as_grid(reference, "reference")
    out = np.ones(int(np.prod(reference.shape)))
    for flat, _, (_, jac) in _on_grid(warp, reference, 1, chunk, progress, "Jacobian"):
        out[flat] = jacobian_det(jac)
    return out.reshape(reference.shape)


@single_blas
def fields_on_grid(
    warp, reference: GridLike, *, chunk: int = 1 << 17, progress: ProgressCallback | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The displacement and the Jacobian determinant at every voxel centre, in one pass.

    The same values as :func:`displacement_on_grid` and
    :func:`jacobian_determinant_on_grid`, from one evaluation of ``tau`` and its
    analytic Jacobian per voxel instead of two evaluations (on the frog at its
    native 1 x 1 x 1.5 mm the displacement alone took 15 s of 32 million voxels).

    Parameters
    ----------
    warp : KernelWarp, InverseWarp or any object with ``evaluate(points, order=...)``
    reference : Grid, LabelVolume or (shape, affine)
        The grid whose voxel centres are sampled (a volume's array is not used).
    chunk : int
        Voxels evaluated at a time: bounds the memory to a few ``chunk x D x D`` floats.
    progress : callable, optional
        ``progress(stage, done, total)`` after each chunk.

    Returns
    -------
    u : (*reference.shape, D) float64 ndarray, LPS mm
        ``tau(x) - x``; zero outside the warp's support.
    det : (*reference.shape) float64 ndarray
        ``det d tau / dx``; 1 outside the warp's support.
    """
    reference = as_grid(reference, "reference")
    n = int(np.prod(reference.shape))
    u = np.zeros((n, reference.ndim))
    det = np.ones(n)
    for flat, points, (tau, jac) in _on_grid(warp, reference, 1, chunk, progress, "evaluate warp"):
        u[flat] = tau - points
        det[flat] = jacobian_det(jac)
    return u.reshape(*reference.shape, reference.ndim), det.reshape(reference.shape)

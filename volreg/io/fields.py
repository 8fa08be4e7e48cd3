"""Displacement fields as ANTs and ITK read and write them (NIfTI-1, 5-D, intent vector).

Convention (docs/conventions.md): a displacement field lives on the fixed
(reference) grid; voxel ``x`` holds ``u(x) = tau(x) - x`` in ITK physical
space (LPS, mm), so that a moving image is pulled back as
``moving(x + u(x))``.  On disk: NIfTI-1, float32, shape ``(X, Y, Z, 1, 3)``
(``(X, Y, 1, 1, 2)`` in 2-D), intent code 1007 (vector), identical qform and
sform (code 1) holding the RAS form of the LPS grid.  The vector components
are *not* flipped to RAS: ITK (and so ANTs, SimpleITK, Slicer) store them as
LPS, and read them back as such.
"""

from __future__ import annotations

import os
from pathlib import Path

import nibabel as nib
import numpy as np
import SimpleITK as sitk

from volreg.grid import Grid, GridLike, as_grid
from volreg.errors import VolregIOError
from volreg.io._atomic import atomic_output
from volreg.io.images import _check_input, _check_nifti, _sitk_reason

__all__ = ["write_displacement", "read_displacement"]

_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def _nifti_suffix(path: Path, what: str) -> None:
    name = path.name.lower()
    if not (name.endswith(".nii") or name.endswith(".nii.gz")):
        raise VolregIOError(f"{what} `{path}` must be NIfTI (.nii or .nii.gz), the format ANTs and ITK read fields from.")


def _ras_affine(like: Grid) -> np.ndarray:
    """4x4 RAS affine of a 2-D or 3-D LPS grid (2-D grids get a unit third axis)."""
    a = np.eye(4)
    d = like.ndim
    a[:d, :d] = like.direction * like.spacing[None, :]
    a[:d, 3] = like.origin
    return _LPS_TO_RAS @ a


def write_displacement(
    displacement: np.ndarray, like: GridLike, path: str | os.PathLike[str], *, force: bool = False
) -> None:
    """Write a displacement field in the ANTs/ITK convention, atomically.

    Parameters
    ----------
    displacement : (*like.shape, D) float ndarray, LPS mm
        ``u(x) = tau(x) - x`` at the voxel centres of ``like``.
    like : Grid, LabelVolume or (shape, affine)
        The reference (fixed) grid: origin, spacing, direction (a volume's array is not used).
    path : path-like
        ``.nii.gz`` (or ``.nii``).
    force : bool
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        On a shape mismatch, a non-finite value, a non-NIfTI path, or an
        existing ``path`` without ``force``.
    """
    like = as_grid(like, "like")
    p = Path(path)
    _nifti_suffix(p, "Displacement field")
    u = np.asarray(displacement)
    want = (*like.shape, like.ndim)
    if u.shape != want:
        raise VolregIOError(f"Expected `displacement` of shape {want} (grid of `like`, then D), got {u.shape}.")
    if not np.all(np.isfinite(u)):
        raise VolregIOError("Expected a finite `displacement`; it holds NaN or Inf.")
    if like.ndim == 2:
        data = u.astype(np.float32)[:, :, None, None, :]
    else:
        data = u.astype(np.float32)[:, :, :, None, :]
    affine = _ras_affine(like)
    img = nib.Nifti1Image(data, affine)
    img.header.set_intent("vector")
    img.header.set_qform(affine, code=1)
    img.header.set_sform(affine, code=1)
    img.header.set_xyzt_units("mm", "sec")
    with atomic_output(p, force=force) as tmp:
        nib.save(img, str(tmp))


def read_displacement(path: str | os.PathLike[str]) -> tuple[np.ndarray, Grid]:
    """Read an ANTs/ITK displacement field.

    Returns
    -------
    displacement : (*shape, D) float64 ndarray, LPS mm
        A new C-order array that owns its memory.
    grid : Grid
        The field's grid: shape, origin, spacing, direction.

    Raises
    ------
    VolregIOError
        If the file is unreadable or not a vector image with D components on a D-D grid.
    """
    p = Path(path)
    suffix = _check_input(p, "Displacement field")
    if suffix in (".nii", ".nii.gz"):
        # SimpleITK zero-fills a truncated file: a warp that silently becomes the identity there.
        _check_nifti(p, suffix, "Displacement field")
    try:
        img = sitk.ReadImage(str(p))
    except RuntimeError as exc:
        raise VolregIOError(f"Displacement field `{p}` could not be read: {_sitk_reason(exc)}.") from exc
    dim = img.GetDimension()
    if img.GetNumberOfComponentsPerPixel() != dim or dim not in (2, 3):
        raise VolregIOError(
            f"Displacement field `{p}` has {img.GetNumberOfComponentsPerPixel()} components on a {dim}-D grid; "
            "expected a 2-D or 3-D vector image with one component per axis (ANTs/ITK warp)."
        )
    array = sitk.GetArrayFromImage(img)  # (k, j, i, D), a copy
    # (i, j, k, D) as float64 in one more copy, C order, owning its memory.
    u = np.array(array.transpose(*range(dim - 1, -1, -1), dim), dtype=np.float64, order="C")
    if not np.all(np.isfinite(u)):
        raise VolregIOError(f"Displacement field `{p}` holds NaN or Inf; expected finite displacements in mm.")
    grid = Grid(
        u.shape[:-1],
        np.array(img.GetOrigin()),
        np.array(img.GetSpacing()),
        np.array(img.GetDirection()).reshape(dim, dim),
    )
    return u, grid

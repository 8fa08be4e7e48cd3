"""Multi-frame images: one 3-D (or 2-D) frame per label, as a 4-D NIfTI file."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from volreg.errors import VolregIOError
from volreg.grid import Grid, LabelVolume, as_grid
from volreg.io._atomic import atomic_output

__all__ = ["read_frames", "write_frames"]

#: LPS (ITK, volreg) to RAS (NIfTI) world coordinates.
_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def _ras_affine(grid: Grid) -> np.ndarray:
    a = grid.affine
    if grid.ndim == 2:  # a 2-D grid as the plane z = 0
        a3 = np.eye(4)
        a3[:2, :2], a3[:2, 3] = a[:2, :2], a[:2, 2]
        a = a3
    return _LPS_TO_RAS @ a


def write_frames(frames: np.ndarray, like: Grid | LabelVolume, path: str | os.PathLike[str], *,
                 force: bool = False) -> None:
    """Write frames on one grid as a 4-D float32 NIfTI image (the frames along the fourth axis), atomically.

    Parameters
    ----------
    frames : (F, *shape) real ndarray
        One frame per entry of the first axis, each in ITK index order on ``like``'s grid.
    like : Grid or LabelVolume
        Origin, spacing and direction (LPS, mm).
    path : path-like
        ``.nii`` or ``.nii.gz``.
    force : bool
        Overwrite an existing ``path``.

    Raises
    ------
    VolregIOError
        A shape that is not ``(F, *like.shape)``, another suffix, or an existing ``path`` without ``force``.
    """
    import nibabel as nib

    grid = as_grid(like)
    frames = np.asarray(frames)
    if frames.ndim != grid.ndim + 1 or frames.shape[1:] != grid.shape:
        raise VolregIOError(f"Expected frames of shape (F, {', '.join(map(str, grid.shape))}), got {frames.shape}.")
    p = Path(path)
    if not (p.name.endswith(".nii") or p.name.endswith(".nii.gz")):
        raise VolregIOError(f"Expected a `.nii` or `.nii.gz` path for frames, got `{p}`.")
    data = np.moveaxis(frames.astype(np.float32, copy=False), 0, -1)
    if grid.ndim == 2:
        data = data[:, :, None, :]
    image = nib.Nifti1Image(data, _ras_affine(grid))
    image.header.set_xyzt_units("mm")
    image.set_qform(image.affine, code=1)
    image.set_sform(image.affine, code=1)
    with atomic_output(p, force=force) as tmp:
        nib.save(image, str(tmp))


def read_frames(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read what :func:`write_frames` wrote.

    Returns
    -------
    frames : (F, n_i, n_j, n_k) float32 ndarray
    affine : (4, 4) float ndarray
        The index-to-LPS-world matrix, mm.
    """
    import nibabel as nib

    image = nib.load(str(path))
    data = np.asarray(image.dataobj, dtype=np.float32)
    return np.moveaxis(data, -1, 0), _LPS_TO_RAS @ image.affine

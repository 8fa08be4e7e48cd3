"""The demo pair: pyvista's frog tissues and a copy deformed by a known smooth warp.

Pure functions: they return arrays and volumes; reading the file and writing
outputs is the CLI's job (``volreg demo``).
"""

from __future__ import annotations

import os

import numpy as np

from volreg.synthetic import GaussianBumps, deform_labels
from volreg.grid import LabelVolume

__all__ = ["frog_path", "block_mode", "frog_pair"]


def frog_path() -> str:
    """Path of ``frog_tissues.vti`` inside the installed pyvista (no download)."""
    from pyvista import examples

    return os.path.join(os.path.dirname(examples.__file__), "frog_tissues.vti")


def block_mode(volume: LabelVolume, factors) -> LabelVolume:
    """Downsample labels by integer ``factors`` per axis, each block taking its most frequent label.

    Striding (``array[::3]``) would break thin tissues into specks; the block
    mode keeps a label where it fills most of a block.  The grid keeps its
    direction; the origin moves to the centre of the first block.
    """
    f = np.asarray(factors, dtype=int)
    if f.shape != (volume.ndim,) or np.any(f < 1):
        raise ValueError(f"Expected `factors` of {volume.ndim} positive integers, got {factors!r}.")
    shape = np.array(volume.shape) // f
    a = volume.array[tuple(slice(0, n * k) for n, k in zip(shape, f))]
    # one row per block, sorted: the mode is the value of the longest run, the smallest on a tie
    ndim = volume.ndim
    rows = a.reshape(np.stack([shape, f], axis=1).ravel()).transpose(*range(0, 2 * ndim, 2), *range(1, 2 * ndim, 2))
    rows = np.sort(rows.reshape(int(np.prod(shape)), int(np.prod(f))), axis=1)
    out = rows[:, 0].copy()
    run = np.ones(len(rows), dtype=np.int32)
    best = run.copy()
    for j in range(1, rows.shape[1]):
        run = np.where(rows[:, j] == rows[:, j - 1], run + 1, 1)
        win = run > best
        best[win] = run[win]
        out[win] = rows[win, j]
    out = out.reshape(tuple(shape))
    origin = volume.index_to_world(((f - 1) / 2.0)[None])[0]
    return LabelVolume(out, origin, volume.spacing * f, volume.direction)


def frog_pair(
    full: LabelVolume, *, factors=(3, 3, 2), max_displacement: float = 8.0, seed: int = 0
) -> tuple[LabelVolume, LabelVolume, GaussianBumps]:
    """Fixed = the frog labels block-downsampled by ``factors`` (3 x 3 x 2: 3 mm voxels);
    moving = fixed deformed by a known smooth warp ``tau`` (max ``max_displacement`` mm).

    Returns
    -------
    fixed, moving : LabelVolume
    tau : GaussianBumps
        The true pull-back warp: fixed point ``x`` corresponds to moving point ``tau(x)``.
    """
    fixed = block_mode(full, factors) if any(k != 1 for k in factors) else full
    points = fixed.grid_points().reshape(-1, fixed.ndim)[fixed.array.ravel() > 0]
    lo, hi = points.min(axis=0), points.max(axis=0)
    scale = 0.15 * float(np.linalg.norm(hi - lo))
    tau = GaussianBumps.random(lo, hi, max_displacement=max_displacement, scale=scale, count=10,
                               rng=np.random.default_rng(seed))
    return fixed, deform_labels(fixed, tau), tau

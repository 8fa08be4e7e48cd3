"""Checks of a pair of label volumes before any work: one dimension, grids that meet, memory.

:func:`check_pair` refuses, in one line naming the volumes, a pair that cannot be registered
(volumes of different dimensions, grids apart in world space without a linear stage, a job
larger than the memory free now).
"""

from __future__ import annotations

import numpy as np

from volreg._memory import available_bytes
from volreg.errors import RegistrationInputError
from volreg.grid import world_box

__all__ = ["check_pair", "estimated_peak_gb"]

#: Peak memory of a registration, estimated before it starts: a base plus bytes per voxel of the
#: two grids, set from the measured peaks of registrations from 3.5 M to 64 M voxels (the estimate
#: errs on the high side).
_BASE_GB = 1.2

_BYTES_PER_VOXEL = 150
def estimated_peak_gb(fixed, moving) -> float:
    """Rough peak memory of registering ``moving`` to ``fixed`` (:func:`volreg.outputs.registration.write_registration`), GB."""
    voxels = int(np.prod(fixed.shape)) + int(np.prod(moving.shape))
    return _BASE_GB + _BYTES_PER_VOXEL * voxels / 1024**3


def _check_memory(fixed, moving, fixed_name, moving_name) -> None:
    """Refuse a job that would not fit in the memory available now, before it starts."""
    need = estimated_peak_gb(fixed, moving)
    available = available_bytes()
    if available is not None and need * 1024**3 > available:
        raise RegistrationInputError(
            f"Registering `{moving_name}` ({moving.shape}) to `{fixed_name}` ({fixed.shape}) would need about "
            f"{need:.1f} GB of memory and {available / 1024**3:.1f} GB is available; expected smaller grids "
            "(downsample the label volumes) or more free memory."
        )


def check_pair(fixed, moving, fixed_name: object = "fixed", moving_name: object = "moving", *,
               linear: str = "none") -> None:
    """Refuse, before any work, a pair of label volumes that cannot be registered.

    Parameters
    ----------
    fixed, moving : LabelVolume
    fixed_name, moving_name : str or path-like
        How the messages name the volumes (e.g. their files).
    linear : {"none", "rigid", "similarity", "affine"}
        The protocol's linear stage.  With one, grids far apart in world space are
        fine (the stage brings the labels together, as scans from two scanners need);
        without, they cannot be registered.

    Raises
    ------
    RegistrationInputError
        Volumes of different dimensions, grids that do not overlap in world (LPS)
        space when ``linear`` is ``"none"``, or a registration whose estimated peak
        memory (:func:`estimated_peak_gb`) exceeds the memory available now.
    """
    if fixed.ndim != moving.ndim:
        raise RegistrationInputError(
            f"`{fixed_name}` is {fixed.ndim}-D and `{moving_name}` {moving.ndim}-D; expected two volumes of one dimension."
        )
    lo1, hi1 = world_box(fixed)
    lo2, hi2 = world_box(moving)
    if linear == "none" and (np.any(hi1 < lo2) or np.any(hi2 < lo1)):
        raise RegistrationInputError(
            f"The grids of `{fixed_name}` and `{moving_name}` do not overlap in world (LPS) space "
            f"(fixed {np.round(lo1, 1).tolist()}..{np.round(hi1, 1).tolist()} mm, moving "
            f"{np.round(lo2, 1).tolist()}..{np.round(hi2, 1).tolist()} mm) and the protocol has no linear stage; "
            "check their origins and orientations, or use a linear stage ([linear] kind)."
        )
    _check_memory(fixed, moving, fixed_name, moving_name)




"""Checks before any work: a pair of label volumes (one dimension, grids that meet), and the memory
each job needs, estimated from its images' headers before any voxel is read.

:func:`check_pair` refuses, in one line naming the volumes, a pair that cannot be registered
(volumes of different dimensions, grids apart in world space without a linear stage, a job
larger than the memory free now); :func:`check_pair_headers` makes the memory check from the
files' headers alone, so that a file declaring more than the machine holds is refused before it
is decompressed.  :func:`surface_peak_bytes` and :func:`apply_peak_bytes` are the least that
``volreg surface`` and ``volreg apply`` hold at once (:func:`volreg.io.footprint.check_job_memory`).
"""

from __future__ import annotations

import os

import numpy as np

from volreg._memory import MAX_MEMORY, memory_limit
from volreg.errors import RegistrationInputError
from volreg.grid import world_box
from volreg.io.footprint import ImageFootprint, image_footprint

__all__ = ["check_pair", "check_pair_memory", "check_pair_headers", "estimated_peak_gb", "surface_peak_bytes",
           "apply_peak_bytes"]

#: Peak memory of a registration, estimated before it starts: a base plus bytes per voxel of the
#: two grids, set from the measured peaks of registrations from 3.5 M to 64 M voxels (the estimate
#: errs on the high side).
_BASE_GB = 1.2

_BYTES_PER_VOXEL = 150

#: What ``volreg surface`` holds per voxel besides the labels, at least: a label's signed distance
#: on the grid (float32), the transposed copy the image writer makes of it and SimpleITK's image.
SURFACE_BYTES_PER_VOXEL = 12

#: What ``volreg apply`` holds per voxel of the reference grid and per axis, at least: the voxels'
#: world points, the displacement there and the points they are sent to, in float64.
APPLY_BYTES_PER_AXIS = 3 * 8


def estimated_peak_gb(fixed, moving) -> float:
    """Rough peak memory of registering ``moving`` to ``fixed`` (:func:`volreg.outputs.registration.write_registration`), GB.

    ``fixed`` and ``moving`` need only a ``shape``: volumes, grids, or the
    :class:`~volreg.io.footprint.ImageFootprint` of their files.
    """
    voxels = int(np.prod(fixed.shape, dtype=object)) + int(np.prod(moving.shape, dtype=object))
    return _BASE_GB + _BYTES_PER_VOXEL * voxels / 1024**3


def check_pair_memory(fixed, moving, fixed_name: object = "fixed", moving_name: object = "moving") -> None:
    """Refuse a registration that would not fit in the memory it may use (:func:`volreg._memory.memory_limit`).

    Parameters
    ----------
    fixed, moving : LabelVolume, Grid or ImageFootprint
        Anything with the grid's ``shape``.
    fixed_name, moving_name : str or path-like
        How the message names them.

    Raises
    ------
    RegistrationInputError
        Naming both, the estimate (:func:`estimated_peak_gb`) and the limit.
    """
    need = estimated_peak_gb(fixed, moving)
    available, known_as = memory_limit()
    if available is not None and need * 1024**3 > available:
        raise RegistrationInputError(
            f"Registering `{moving_name}` ({tuple(moving.shape)}) to `{fixed_name}` ({tuple(fixed.shape)}) would need "
            f"about {need:.1f} GB of memory and {available / 1024**3:.1f} GB is {known_as}; expected smaller grids "
            f"(downsample the label volumes) or more free memory (set {MAX_MEMORY} to change the limit)."
        )


def check_pair_headers(fixed: str | os.PathLike[str], moving: str | os.PathLike[str]) -> None:
    """Refuse, from the two files' headers alone, a registration that would not fit in memory.

    Every check of the readers that needs only a header is made on both (the file's name in
    each message); no voxel is read or decompressed.

    Raises
    ------
    VolregIOError
        A header the readers refuse.
    RegistrationInputError
        As :func:`check_pair_memory`.
    """
    a, b = image_footprint(fixed, "Label image"), image_footprint(moving, "Label image")
    check_pair_memory(a, b, fixed, moving)


def surface_peak_bytes(image: ImageFootprint) -> int:
    """The least memory ``volreg surface`` holds at once for the label volume ``image``, bytes.

    Reading holds the voxels twice (SimpleITK's buffer and the array it is copied to); then the
    labels stay while each label's signed distance is sampled on the grid and written
    (:data:`SURFACE_BYTES_PER_VOXEL`).  The meshes and the fits come on top, with the surfaces' size.
    """
    return max(2 * image.nbytes, image.nbytes + SURFACE_BYTES_PER_VOXEL * image.voxels)


def apply_peak_bytes(image: ImageFootprint, reference: ImageFootprint, field: ImageFootprint | None = None) -> int:
    """The least memory ``volreg apply`` holds at once to resample ``image`` onto ``reference``'s grid, bytes.

    Reading holds the image twice; then it stays while the reference grid's points, the
    displacement there and the points it sends them to are held
    (:data:`APPLY_BYTES_PER_AXIS` per voxel and axis), with the output (one value per reference
    voxel) and, for a displacement ``field``, its components in float64.
    """
    need = image.nbytes + reference.voxels * (APPLY_BYTES_PER_AXIS * reference.ndim + image.itemsize)
    if field is not None:
        need += field.voxels * field.components * 8
    return max(2 * image.nbytes, need)


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
    check_pair_memory(fixed, moving, fixed_name, moving_name)




"""What a job's images take in memory, from their headers alone, and the refusal of a job that would not fit.

A header declares an image's size in a few bytes, and a compressed file of a few megabytes may
declare gigabytes that the readers then decompress and allocate, twice over while SimpleITK hands
its buffer to numpy.  Each command holds more: the grid's world points, a displacement, signed
distances, all the size of its grids.  So every command that reads images first sums what its job
needs at least from the headers (:func:`image_footprint`, nothing decompressed), and
:func:`check_job_memory` refuses, in one line naming the largest file, the estimate and the limit,
a job that could not fit in the memory available (or ``VOLREG_MAX_MEMORY_GB``), before any voxel
is read.  The per-file limit of the readers (``VOLREG_MAX_IMAGE_GB``,
:func:`~volreg.io._guards.max_image_bytes`) applies as well.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from volreg._memory import MAX_MEMORY, memory_limit
from volreg.errors import VolregIOError
from volreg.io.images import image_header

__all__ = ["ImageFootprint", "image_footprint", "check_job_memory"]


@dataclass(frozen=True)
class ImageFootprint:
    """The size an image file declares, as its header says it.

    Attributes
    ----------
    path : pathlib.Path
    what : str
        What the file is, for messages (``"Label image"``).
    shape : tuple of ints
        Voxels along every axis, ITK index order (extra axes of size 1 included).
    components : int
        Values per voxel.
    itemsize : int
        Bytes of one value, as read.
    """

    path: Path
    what: str
    shape: tuple[int, ...]
    components: int
    itemsize: int

    @property
    def voxels(self) -> int:
        """Voxels of the grid."""
        count = 1
        for n in self.shape:
            count *= int(n)
        return count

    @property
    def ndim(self) -> int:
        """Spatial axes: 2 or 3 (extra axes of size 1 are not counted)."""
        shape = list(self.shape)
        while len(shape) > 2 and shape[-1] == 1:
            shape.pop()
        return len(shape)

    @property
    def nbytes(self) -> int:
        """Bytes of the voxels as the file's type holds them."""
        return self.voxels * self.components * self.itemsize


def image_footprint(path: str | os.PathLike[str], what: str = "Image") -> ImageFootprint:
    """The size ``path`` declares, read from its header (:func:`volreg.io.images.image_header`).

    Raises
    ------
    VolregIOError
        Everything the header shows that the readers refuse (named as they name it).
    """
    shape, components, itemsize = image_header(path, what)
    return ImageFootprint(Path(path), what, tuple(shape), components, itemsize)


def check_job_memory(command: str, need: int, largest: ImageFootprint) -> None:
    """Refuse a job that needs more than the memory it may use, before it reads any voxel.

    Parameters
    ----------
    command : str
        What the job is, for the message (``"surface"``, ``"apply"``).
    need : int
        The least bytes the job holds at once, estimated from its images' headers.
    largest : ImageFootprint
        The image the message names (the one that contributes most).

    Raises
    ------
    VolregIOError
        One line: the file and its shape, the estimate and the limit (the memory available now,
        or ``VOLREG_MAX_MEMORY_GB``).
    """
    limit, known_as = memory_limit()
    if limit is None or need <= limit:
        return
    raise VolregIOError(
        f"{largest.what} `{largest.path}` has shape {tuple(largest.shape)} ({largest.voxels:,} voxels): {command} "
        f"would need at least {need / 1024**3:.3g} GB of memory and {limit / 1024**3:.3g} GB is {known_as}; "
        f"expected a smaller image (downsample it) or more free memory (set {MAX_MEMORY} to change the limit)."
    )

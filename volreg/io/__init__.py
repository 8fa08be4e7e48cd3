"""File formats: label volumes, scalar images, meshes and JSON summaries.

The only modules in volreg that import SimpleITK, nibabel or pyvista for
files.  Readers validate and raise :class:`VolregIOError` (a ``ValueError``)
with one line naming the file and the problem (quoting the file's content only as
a short :func:`excerpt`); writers are atomic and refuse
to overwrite unless ``force=True``.
"""

from volreg.errors import VolregIOError, VolregWarning, excerpt
from volreg.io._atomic import atomic_output, check_writable, user_path
from volreg.io.images import read_grid, read_image, read_labels, write_labels, write_scalar
from volreg.io.meshes import read_mesh, write_mesh
from volreg.io.summary import write_json, write_text

__all__ = [
    "VolregIOError",
    "VolregWarning",
    "atomic_output",
    "check_writable",
    "excerpt",
    "read_grid",
    "read_image",
    "read_labels",
    "read_mesh",
    "write_json",
    "write_labels",
    "write_mesh",
    "write_scalar",
    "write_text",
    "user_path",
]

"""Named arrays in a compressed ``.npz`` archive, written atomically and read without pickle.

A volreg archive names its kind in a ``format`` member (a string such as
``"volreg-shape-model-1"``); :func:`read_arrays` refuses another kind, an archive that would
inflate beyond what it holds (:func:`~volreg.io._guards.check_npz`), and any object array.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Mapping

import numpy as np

from volreg.errors import VolregIOError
from volreg.io._atomic import atomic_output
from volreg.io._guards import check_npz

__all__ = ["read_arrays", "write_arrays"]


def write_arrays(arrays: Mapping[str, np.ndarray], path: str | os.PathLike[str], *, format: str,
                 force: bool = False) -> None:
    """Write ``arrays`` and ``format`` to ``path`` as a compressed ``.npz`` (no pickle), atomically.

    Parameters
    ----------
    arrays : mapping of str to ndarray
        Numeric, boolean or fixed-width string arrays.
    path : path-like
        Written under exactly this name.
    format : str
        Stored as the ``format`` member.
    force : bool
        Whether an existing ``path`` may be replaced.
    """
    with atomic_output(path, force=force) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, format=np.array(format), **{k: np.asarray(v) for k, v in arrays.items()})


def read_arrays(path: str | os.PathLike[str], what: str, format: str, *, option: str | None = None) -> dict[str, np.ndarray]:
    """Every array of an archive :func:`write_arrays` wrote with ``format``.

    Parameters
    ----------
    path : path-like
    what : str
        How messages name the file ("Shape model").
    format : str
        The ``format`` member expected.
    option : str, optional
        The argument that named the file, for the messages.

    Raises
    ------
    VolregIOError
        One line naming the file: missing, unreadable, not an archive, or not of ``format``.
    """
    name = os.fspath(path)
    label = f"{option} `{name}`" if option else f"{what} `{name}`"
    if not os.path.exists(name):
        raise VolregIOError(f"{label} does not exist; expected a {what.lower()} file (.npz).")
    if os.path.isdir(name):
        raise VolregIOError(f"{label} is a directory; expected a {what.lower()} file (.npz).")
    try:
        fh = open(name, "rb")
    except OSError as exc:
        raise VolregIOError(f"{label} cannot be opened: {exc.strerror or exc}.") from None
    with fh:
        check_npz(fh, name, what)
        try:
            data = np.load(fh, allow_pickle=False)
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            raise VolregIOError(f"{label} is not a readable .npz archive; expected a {what.lower()} file.") from None
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise VolregIOError(f"{label} is a single array; expected a {what.lower()} archive (.npz).")
        with data:
            try:
                arrays = {k: data[k] for k in data.files}
            except (OSError, ValueError, EOFError, zipfile.BadZipFile):
                raise VolregIOError(f"{label} has an unreadable member; expected a {what.lower()} file.") from None
    found = str(arrays["format"])[:40] if "format" in arrays and arrays["format"].dtype.kind == "U" else ""
    if found != format:
        raise VolregIOError(f"{label} is not a volreg {what.lower()} (format {found or 'missing'!r}); expected "
                            f"format {format!r}.")
    return arrays

"""Atomic, refuse-to-overwrite file output.

Every writer in :mod:`volreg.io` writes into a temporary file next to the
final one and renames it into place only when the write has succeeded, so an
interrupted or failed command never leaves a half-written output behind.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from volreg.errors import VolregIOError

__all__ = ["VolregIOError", "atomic_output", "check_writable"]


def _exists_message(path: Path) -> str:
    return f"Output `{path}` exists; pass --force to overwrite."


def _check_one(path: Path, force: bool) -> None:
    if path.is_dir():
        raise VolregIOError(f"Output `{path}` is a directory; expected a file name.")
    if path.exists() or path.is_symlink():
        if not force:
            raise VolregIOError(_exists_message(path))
    parent = path.parent
    if not parent.is_dir():
        raise VolregIOError(f"Output directory `{parent}` of `{path}` does not exist.")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise VolregIOError(f"Output directory `{parent}` of `{path}` is not writable.")


def check_writable(paths: Iterable[str | os.PathLike[str]], force: bool = False) -> None:
    """Check up front that every output can be written.

    Call this before any computation so that a command refuses at once
    instead of after minutes of work.

    Parameters
    ----------
    paths : iterable of path-like
        The output files a command is about to write.
    force : bool, default False
        Whether existing files may be overwritten.

    Raises
    ------
    VolregIOError
        If an output exists and ``force`` is false, is a directory, or its
        directory does not exist or is not writable; also if the same path is
        listed twice.
    """
    seen: set[Path] = set()
    for p in paths:
        path = Path(p)
        key = path.resolve()
        if key in seen:
            raise VolregIOError(f"Output `{path}` is given more than once; expected distinct outputs.")
        seen.add(key)
        _check_one(path, force)


def _new_temp(path: Path) -> Path:
    """Create (exclusively) an empty temporary file beside ``path`` and return its name.

    The name keeps the real file name as its tail (``.tmp-1a2b3c4d-label.nii.gz``)
    so writers that pick a format from the suffix still work.  The file is
    created with mode ``0o666`` filtered by the umask, like an ordinary new file.
    """
    for _ in range(100):
        tmp = path.with_name(f".tmp-{secrets.token_hex(4)}-{path.name}")
        try:
            fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
        except FileExistsError:
            continue
        except OSError as exc:
            raise VolregIOError(f"Cannot create a temporary file beside `{path}`: {exc.strerror}.") from exc
        os.close(fd)
        return tmp
    raise VolregIOError(f"Cannot create a temporary file beside `{path}`: too many name collisions.")


@contextmanager
def atomic_output(path: str | os.PathLike[str], *, force: bool = False) -> Iterator[Path]:
    """Write a file atomically: yield a temporary path, rename it into place on success.

    Parameters
    ----------
    path : path-like
        The final output file.
    force : bool, default False
        Whether an existing ``path`` may be replaced.

    Yields
    ------
    pathlib.Path
        A temporary file in the same directory as ``path`` whose name ends
        with ``path``'s name (so its suffix, e.g. ``.nii.gz``, is kept).  It
        exists (empty) when yielded; the caller writes to it.

    Raises
    ------
    VolregIOError
        Before anything is written, if ``path`` exists and ``force`` is false,
        or its directory is missing or not writable.

    Notes
    -----
    On success the temporary file is moved onto ``path`` with
    :func:`os.replace` (atomic on POSIX within one file system).  On any
    exception inside the ``with`` block the temporary file is removed, the
    exception propagates, and ``path`` is left as it was.
    """
    final = Path(path)
    _check_one(final, force)
    tmp = _new_temp(final)
    try:
        yield tmp
        if not force and (final.exists() or final.is_symlink()):
            # Someone created it while we were writing.
            raise VolregIOError(_exists_message(final))
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise

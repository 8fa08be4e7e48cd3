"""Atomic, refuse-to-overwrite file output, and output folders that are all or nothing.

Every writer in :mod:`volreg.io` writes into a temporary file next to the
final one and renames it into place only when the write has succeeded, so an
interrupted or failed command never leaves a half-written output behind.
:func:`output_folder` extends that to a folder of outputs: on any failure the
files a run wrote and the folders it created are removed again.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from volreg.errors import UsageError, VolregIOError

__all__ = ["VolregIOError", "OutputFolder", "atomic_output", "check_writable", "make_directory", "output_folder"]


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


def make_directory(path: str | os.PathLike[str]) -> list[Path]:
    """Create ``path`` and any missing parents.

    Parameters
    ----------
    path : path-like
        The folder to create; an existing folder is fine.

    Returns
    -------
    list of pathlib.Path
        The folders created, outermost first (empty if ``path`` existed).

    Raises
    ------
    UsageError
        If ``path`` exists and is not a folder.
    VolregIOError
        If a folder cannot be created; the folders created before it are removed again.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UsageError(f"Output directory `{path}` exists and is not a directory; expected a directory for -o.")
    missing = []
    p = path
    while not p.exists():
        missing.append(p)
        if p.parent == p:
            break
        p = p.parent
    created: list[Path] = []
    for d in reversed(missing):
        try:
            d.mkdir()
        except OSError as exc:
            _remove_directories(created)
            raise VolregIOError(f"Output directory `{d}` could not be created: {exc.strerror}.") from exc
        created.append(d)
    return created


def _remove_directories(created: list[Path]) -> None:
    """Remove folders that were created, innermost first, while they are empty."""
    for d in reversed(created):
        try:
            d.rmdir()
        except OSError:
            return


class OutputFolder:
    """The record of one run's outputs in a folder: the files it wrote and the folders it created.

    Made by :func:`output_folder`, which removes what is recorded here if the run fails.

    Attributes
    ----------
    path : pathlib.Path
        The folder.
    created : list of pathlib.Path
        Folders this run created (``path`` and missing parents, and those of inner
        transactions that completed), outermost first.
    written : list of pathlib.Path
        Files this run wrote, in order (also those of inner transactions that completed).
    """

    def __init__(self, path: Path, created: list[Path]) -> None:
        self.path = path
        self.created = list(created)
        self.written: list[Path] = []

    def record(self, path: str | os.PathLike[str]) -> Path:
        """Record ``path`` as written by this run (call it once the file is complete); return it."""
        path = Path(path)
        self.written.append(path)
        return path

    def _adopt(self, inner: "OutputFolder") -> None:
        """Take over the records of a completed inner transaction."""
        self.written += inner.written
        self.created += inner.created

    def _remove(self) -> None:
        """Remove the files written and then the folders created (innermost first, while empty)."""
        for path in self.written:
            path.unlink(missing_ok=True)
        _remove_directories(self.created)


#: The innermost open :func:`output_folder` of this thread (or task), if any.
_open_folder: ContextVar[OutputFolder | None] = ContextVar("volreg_output_folder", default=None)


@contextmanager
def output_folder(
    path: str | os.PathLike[str], force: bool = False, *, require_empty: bool = True
) -> Iterator[OutputFolder]:
    """An all-or-nothing output folder: create it, yield the record of what the run writes there.

    Parameters
    ----------
    path : path-like
        The output folder; it and any missing parents are created.
    force : bool, default False
        Whether a folder that is not empty may be written into.
    require_empty : bool, default True
        Refuse a non-empty folder unless ``force``.  ``False`` leaves it to
        :func:`check_writable` to refuse the outputs that exist.

    Yields
    ------
    OutputFolder
        Call :meth:`OutputFolder.record` with each file once it is written.

    Raises
    ------
    UsageError
        If ``path`` is a non-empty folder (with ``require_empty`` and without
        ``force``) or exists and is not a folder.
    VolregIOError
        If the folder cannot be created.

    Notes
    -----
    On any exception in the ``with`` block (``BaseException``: a ``KeyboardInterrupt``
    too) the recorded files are removed, then the folders this run created while
    they are empty, and the exception propagates.  A transaction opened inside
    another one (in the same thread) hands its records to the outer one when it
    completes, so that a failure later in the outer one removes them as well.
    """
    path = Path(path)
    if require_empty and path.is_dir() and any(path.iterdir()) and not force:
        raise UsageError(f"Output directory `{path}` exists and is not empty; pass --force to write into it.")
    folder = OutputFolder(path, make_directory(path))
    outer = _open_folder.get()
    token = _open_folder.set(folder)
    try:
        yield folder
    except BaseException:
        folder._remove()
        raise
    finally:
        _open_folder.reset(token)
    if outer is not None:
        outer._adopt(folder)

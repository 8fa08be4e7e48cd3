"""Atomic, refuse-to-overwrite file output, and output folders that are all or nothing.

Every writer in :mod:`volreg.io` writes into a temporary file next to the
final one and renames it into place only when the write has succeeded, so an
interrupted or failed command never leaves a half-written output behind.
:func:`output_folder` extends that to a folder of outputs: a run writes its
whole result into a hidden sibling folder, which replaces the output folder
only once every output is written, so the output folder holds either the
previous complete result or the new complete one, whenever the run stops.
"""

from __future__ import annotations

import hashlib
import os
import secrets
import shutil
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

from volreg._signals import SignalsHeld
from volreg.errors import UsageError, VolregIOError

__all__ = [
    "VolregIOError", "OutputFolder", "atomic_output", "check_writable", "make_directory", "output_folder",
    "recover_folder",
]


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
        except FileExistsError as exc:
            if d.is_dir():  # made meanwhile by another process (batch workers share the parents)
                continue
            _remove_directories(created)
            raise VolregIOError(f"Output directory `{d}` could not be created: {exc.strerror}.") from exc
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
    """The record of one run's outputs in a folder: where to write them, the files written, the folders created.

    Made by :func:`output_folder`, which puts the files in place when the run completes
    and removes them if it fails.

    Attributes
    ----------
    path : pathlib.Path
        Where the run writes its outputs: a hidden sibling of ``final`` (the staging
        folder, which replaces ``final`` when the run completes), or ``final`` itself
        when the folder cannot be replaced as a whole (see :func:`output_folder`).
    final : pathlib.Path
        The output folder as named by the user.
    created : list of pathlib.Path
        Folders this run created (``final``'s missing parents, and ``final`` or inner
        folders when written in place), outermost first.
    written : list of pathlib.Path
        Files this run wrote, in order (also those of inner transactions that completed).
    """

    def __init__(self, path: Path, created: list[Path], final: Path | None = None) -> None:
        self.path = path
        self.final = path if final is None else final
        self.created = list(created)
        self.written: list[Path] = []

    def record(self, path: str | os.PathLike[str]) -> Path:
        """Record ``path`` as written by this run (call it once the file is complete); return it."""
        path = Path(path)
        self.written.append(path)
        return path

    def check_writable(self, names: Iterable[str], force: bool = False) -> dict[str, Path]:
        """Check up front that the outputs ``names`` (relative to the folder) can be written
        (:func:`check_writable`); return where to write each, under :attr:`path`.

        Raises
        ------
        VolregIOError
            As :func:`check_writable`; the message names the output folder, not the staging one.
        """
        paths = {name: self.path / name for name in names}
        try:
            check_writable(paths.values(), force=force)
        except VolregIOError as exc:
            raise VolregIOError(str(exc).replace(str(self.path), str(self.final))) from None
        return paths

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

#: Staging folders of this process that are open now (recovery leaves them alone).
_staging_open: set[Path] = set()

#: Output folders whose previous complete result a failed or interrupted run left in place.
_kept: list[Path] = []


def kept_results() -> list[Path]:
    """The output folders whose previous complete result a failed or interrupted run of this
    process left in place, oldest first (the command line names them; clear it to reuse)."""
    return _kept


#: The three kinds of hidden siblings of an output folder: a result being written, a complete
#: result about to be swapped in, and the previous result being swapped out.
_KINDS = ("new", "ready", "old")


def _stage_prefix(final: Path) -> str:
    """The start of the names of ``final``'s hidden siblings (the name, or its hash when long)."""
    name = final.name
    if len(os.fsencode(name)) > 160:  # keep the sibling's name under NAME_MAX
        name = hashlib.sha256(os.fsencode(name)).hexdigest()[:16]
    return f".{name}.volreg-"


def _stage_path(final: Path, kind: str) -> Path:
    return final.with_name(f"{_stage_prefix(final)}{kind}-{os.getpid()}-{secrets.token_hex(4)}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def _leftovers(final: Path) -> dict[str, list[Path]]:
    """The hidden siblings of ``final`` that runs no longer alive left behind, by kind."""
    found: dict[str, list[Path]] = {kind: [] for kind in _KINDS}
    prefix = _stage_prefix(final)
    try:
        entries = list(final.parent.iterdir())
    except OSError:
        return found
    for entry in entries:
        if not entry.name.startswith(prefix) or entry in _staging_open:
            continue
        kind, _, rest = entry.name[len(prefix):].partition("-")
        pid = rest.partition("-")[0]
        if kind not in found or not pid.isdigit():
            continue
        if int(pid) != os.getpid() and _pid_alive(int(pid)):
            continue  # a run in progress (another process)
        found[kind].append(entry)
    return found


def _remove_tree(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def recover_folder(path: str | os.PathLike[str]) -> str | None:
    """Finish or undo what a run killed while writing output folder ``path`` left behind.

    A run killed (SIGKILL, power loss) in the middle of :func:`output_folder` can
    leave hidden siblings of ``path``: a staging folder with part of a result, and,
    if it was killed while swapping a complete result in, the previous result set
    aside.  This puts a complete result back at ``path`` if there is none and
    removes the rest.  :func:`output_folder` calls it before every run.

    Parameters
    ----------
    path : path-like
        The output folder.

    Returns
    -------
    str or None
        What was restored (``"new"``: the killed run's complete result, ``"old"``: the
        result before it), or None.
    """
    final = Path(path)
    found = _leftovers(final)
    restored = None
    if not final.exists() and not final.is_symlink():
        for kind in ("ready", "old"):  # a complete new result first, else the previous one
            if found[kind]:
                entry = found[kind].pop()
                try:
                    os.rename(entry, final)
                    restored = "new" if kind == "ready" else "old"
                except OSError:
                    found[kind].append(entry)
                break
    for entries in found.values():
        for entry in entries:
            _remove_tree(entry)
    return restored


def _replaceable(final: Path) -> bool:
    """Whether ``final`` can be replaced as a whole by renaming a sibling onto it."""
    if final.is_symlink():
        return False
    parent = final.parent
    if parent.is_dir() and not os.access(parent, os.W_OK | os.X_OK):
        return False
    if final.exists():
        if os.path.ismount(final):
            return False
        try:  # never swap away the working directory or a folder above it
            here = Path.cwd().resolve()
            target = final.resolve()
        except OSError:
            return False
        if here == target or target in here.parents:
            return False
    return True


def _link_tree(source: Path, target: Path) -> None:
    """Fill ``target`` with ``source``'s contents: hard links to its files (copies where links fail)."""
    def link(src: str, dst: str) -> None:
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)

    shutil.copytree(source, target, symlinks=True, copy_function=link, dirs_exist_ok=True)


def _swap_in(staging: Path, final: Path) -> None:
    """Replace ``final`` (if any) by the complete result in ``staging``; see :func:`recover_folder`."""
    ready = _stage_path(final, "ready")
    old = _stage_path(final, "old")
    with SignalsHeld():
        os.rename(staging, ready)
        _staging_open.discard(staging)
        try:
            if final.exists():
                os.rename(final, old)
            os.rename(ready, final)
        except OSError as exc:
            if old.exists() and not final.exists():
                os.rename(old, final)
            _remove_tree(ready)
            raise VolregIOError(f"Output directory `{final}` could not be replaced: {exc.strerror}.") from exc
        _remove_tree(old)


def _inside(path: Path, folder: Path) -> Path | None:
    """``path`` relative to ``folder`` if it lies inside it (or is it), else None."""
    try:
        return Path(os.path.abspath(path)).relative_to(os.path.abspath(folder))
    except ValueError:
        return None


def _discard_staging(staging: Path, created: list[Path]) -> None:
    """Remove a staging folder, and then the folders its run ``created`` (innermost first, while empty)."""
    _remove_tree(staging)
    _staging_open.discard(staging)
    _remove_directories(created)


def _staged(final: Path) -> tuple[OutputFolder, Path]:
    """A new staging sibling of ``final`` holding hard links to ``final``'s contents, and the record
    of a run writing there: ``(folder, staging)``."""
    created = make_directory(final.parent)
    staging = _stage_path(final, "new")
    try:
        staging.mkdir()
        _staging_open.add(staging)
        if final.is_dir():
            _link_tree(final, staging)
    except OSError as exc:
        _discard_staging(staging, created)
        raise VolregIOError(f"Output directory `{final}` could not be prepared: {exc.strerror}.") from exc
    return OutputFolder(staging, created, final=final), staging


def _prepare(
    final: Path, outer: OutputFolder | None, force: bool, require_empty: bool
) -> tuple[OutputFolder, Path | None]:
    """Check output folder ``final`` and make the record of a run writing to it: ``(folder, staging)``.

    Inside the folder of an outer staged run the run writes into that run's staging folder (and is
    swapped in with it); where ``final`` can be replaced as a whole, into a staging sibling of its
    own (``staging``); elsewhere into ``final`` itself (``staging`` is None in both other cases).
    """
    relative = None if outer is None or outer.path == outer.final else _inside(final, outer.final)
    where = final if relative is None else outer.path / relative
    if where.exists() and not where.is_dir():
        raise UsageError(f"Output directory `{final}` exists and is not a directory; expected a directory for -o.")
    if relative is None:
        recover_folder(final)
    if require_empty and where.is_dir() and any(where.iterdir()) and not force:
        raise UsageError(f"Output directory `{final}` exists and is not empty; pass --force to write into it.")
    if relative is not None:
        return OutputFolder(where, make_directory(where), final=final), None
    if _replaceable(final):
        return _staged(final)
    return OutputFolder(final, make_directory(final)), None


@contextmanager
def output_folder(
    path: str | os.PathLike[str], force: bool = False, *, require_empty: bool = True
) -> Iterator[OutputFolder]:
    """An all-or-nothing output folder: yield where to write the run's outputs, put them in place at the end.

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
        Write each output under :attr:`OutputFolder.path` (not under ``path``) and call
        :meth:`OutputFolder.record` with it once written.  Write a file by replacing it
        (:func:`atomic_output`, as every volreg writer does), never in place: until
        replaced, the files there are hard links to the previous result's.

    Raises
    ------
    UsageError
        If ``path`` is a non-empty folder (with ``require_empty`` and without
        ``force``) or exists and is not a folder.
    VolregIOError
        If the folder cannot be created or replaced.

    Notes
    -----
    The run writes into a hidden sibling folder of ``path`` (named
    ``.<name>.volreg-new-<pid>-<hex>``), which starts as a copy of ``path``'s current
    contents made of hard links, so files of ``path`` that the run does not write
    are kept.  When the ``with`` block completes the sibling replaces ``path`` by
    two renames (SIGINT and SIGTERM are held back meanwhile), and the previous
    folder is removed.  On any exception (``BaseException``: an interrupt too) the
    sibling is removed and ``path`` is left as it was.  A run killed outright
    (SIGKILL) leaves ``path`` holding the previous complete result, or, killed
    between the two renames, a sibling that the next run on ``path`` puts back
    (:func:`recover_folder`).

    Where ``path`` cannot be replaced as a whole (a symbolic link, a mount point, the
    working directory or a folder above it, or a parent folder that is not writable)
    the run writes into ``path`` itself, and a failure removes the files the run
    wrote and the folders it created.

    A transaction opened inside another one's folder (in the same thread) writes into
    the outer one's staging folder and completes with it; other nested ones hand
    their records to the outer one when they complete.
    """
    final = Path(path)
    outer = _open_folder.get()
    # Held from the staging folder's creation until the cleanup below guards it: an interrupt in
    # between would leave the folder behind.  One that came meanwhile is raised in the try.
    held = SignalsHeld()
    held.__enter__()
    try:
        folder, staging = _prepare(final, outer, force, require_empty)
    except BaseException:
        held.__exit__(None, None, None)
        raise
    token = _open_folder.set(folder)
    try:
        held.__exit__(None, None, None)
        yield folder
    except BaseException:
        if staging is not None:
            _discard_staging(staging, folder.created)
            if final.is_dir() and any(final.iterdir()):
                _kept.append(final)
        else:
            folder._remove()
        raise
    finally:
        _open_folder.reset(token)
    if staging is not None:
        try:
            _swap_in(staging, final)
        except BaseException:
            _discard_staging(staging, folder.created)  # where the swap had not begun: the run's outputs go with it
            raise
    elif outer is not None:
        outer._adopt(folder)

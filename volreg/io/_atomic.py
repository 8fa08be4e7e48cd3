"""Atomic, refuse-to-overwrite file output, and output folders that are all or nothing.

Every writer in :mod:`volreg.io` writes into a temporary file next to the
final one and renames it into place only when the write has succeeded, so an
interrupted or failed command never leaves a half-written output behind.
:func:`output_folder` extends that to a folder of outputs: a run writes its
whole result into a hidden sibling folder, which replaces the output folder
only once every output is written, so the output folder holds either the
previous complete result or the new complete one, whenever the run stops.
A folder that cannot be renamed (a mount point, a symbolic link, the working
directory) is written through a hidden folder inside it, whose files replace
the previous ones once all are written; one run at a time holds a folder.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
import re
import secrets
import shutil
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

from volreg._signals import SignalsHeld
from volreg.errors import UsageError, VolregIOError, full_disk
from volreg.io._folder_parts import (
    INSIDE_PREFIX,
    STALE_LIST,
    FolderLock,
    finish_in_place,
    is_mount_point,
    remove_tree,
    writable,
)

__all__ = [
    "VolregIOError", "OutputFolder", "atomic_output", "check_writable", "make_directory", "output_folder",
    "recover_folder", "user_path",
]


def _exists_message(path: Path) -> str:
    return f"Output `{path}` exists; pass --force to overwrite."


def _check_existing(path: Path, force: bool) -> None:
    """Refuse an output ``path`` that is a folder, or that exists without ``force``."""
    if path.is_dir():
        raise VolregIOError(f"Output `{path}` is a directory; expected a file name.")
    if path.exists() or path.is_symlink():
        if not force:
            raise VolregIOError(_exists_message(path))


def _check_one(path: Path, force: bool) -> None:
    _check_existing(path, force)
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
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        full = None if isinstance(exc, KeyboardInterrupt) else full_disk(exc)
        if full is not None:
            # A writer's own words for a full disk (ITK's, VTK's, HDF5's) name the temporary
            # file, or nothing: the error names the output as the user named it.
            raise OSError(full.errno, os.strerror(full.errno), str(final)) from None
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
        Where the run writes its outputs: a hidden staging folder, beside ``final`` (it replaces
        ``final`` when the run completes) or, where ``final`` cannot be replaced as a whole, inside
        it (its files are moved into ``final`` when the run completes); for a transaction opened
        inside another one's folder, the matching place in that one's staging folder.
    final : pathlib.Path
        The output folder as named by the user.
    created : list of pathlib.Path
        Folders this run created (``final``'s missing parents, and inner folders), outermost first.
    written : list of pathlib.Path
        Files this run wrote, in order (also those of inner transactions that completed).
    """

    def __init__(self, path: Path, created: list[Path], final: Path | None = None, *,
                 shadow: Path | None = None) -> None:
        self.path = path
        self.final = path if final is None else final
        self.created = list(created)
        self.written: list[Path] = []
        # Where the folder's earlier outputs are when the staging folder does not hold them (the
        # output folder itself, when it is written through a staging folder inside it), else None.
        self._shadow = shadow
        # (folder relative to ``path``, name patterns): outputs whose earlier versions this run's
        # result must not keep (see :func:`output_folder`'s ``outputs``).
        self._family: list[tuple[Path, tuple[str, ...]]] = []

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
        names = list(names)
        paths = {name: self.path / name for name in names}
        try:
            check_writable(paths.values(), force=force)
            if self._shadow is not None:  # the earlier outputs are in the output folder, not in the staging one
                for name in names:
                    _check_existing(self._shadow / name, force)
        except VolregIOError as exc:
            raise VolregIOError(str(exc).replace(str(self.path), str(self.final))) from None
        return paths

    def _adopt(self, inner: OutputFolder, relative: Path) -> None:
        """Take over the records of a completed inner transaction, whose folder is ``relative`` in this one."""
        self.written += inner.written
        self.created += inner.created
        self._family += [(relative / where, patterns) for where, patterns in inner._family]

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


#: The three kinds of hidden working folders of a run: a result being written, a complete result
#: about to be swapped in, and the previous result being swapped out.
_KINDS = ("new", "ready", "old")

#: What follows the prefix in the name of a hidden working folder: its kind, its run's process id
#: and 8 hex digits.  Matched whole, so that a folder merely starting like one is never taken for one.
_WORKING_NAME = re.compile(r"(new|ready|old)-([0-9]+)-[0-9a-f]{8}")


def _stage_prefix(final: Path) -> str:
    """The start of the names of ``final``'s hidden siblings (the name, or its hash when long)."""
    name = final.name
    if len(os.fsencode(name)) > 160:  # keep the sibling's name under NAME_MAX
        name = hashlib.sha256(os.fsencode(name)).hexdigest()[:16]
    return f".{name}.volreg-"


def _hidden(where: Path, prefix: str, kind: str) -> Path:
    """A new name for a working folder of this run in ``where``."""
    return where / f"{prefix}{kind}-{os.getpid()}-{secrets.token_hex(4)}"


def _stage_path(final: Path, kind: str) -> Path:
    return _hidden(final.parent, _stage_prefix(final), kind)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def _leftovers(directory: Path, prefix: str) -> dict[str, list[Path]]:
    """The working folders named ``PREFIX KIND-PID-HEX`` in ``directory`` that runs no longer alive
    left behind, by kind."""
    found: dict[str, list[Path]] = {kind: [] for kind in _KINDS}
    try:
        entries = list(directory.iterdir())
    except OSError:
        return found
    for entry in entries:
        if not entry.name.startswith(prefix) or entry in _staging_open:
            continue
        match = _WORKING_NAME.fullmatch(entry.name[len(prefix):])
        if match is None:
            continue
        pid = int(match.group(2))
        if pid != os.getpid() and _pid_alive(pid):
            continue  # a run in progress (another process)
        found[match.group(1)].append(entry)
    return found


def _holds_result(folder: Path) -> bool:
    """Whether ``folder`` holds anything besides volreg's hidden working entries."""
    try:
        return any(not entry.name.startswith(INSIDE_PREFIX) for entry in folder.iterdir())
    except OSError:
        return False


def recover_folder(path: str | os.PathLike[str]) -> str | None:
    """Finish or undo what a run killed while writing output folder ``path`` left behind.

    A run killed (SIGKILL, power loss) in the middle of :func:`output_folder` can
    leave hidden working folders: beside ``path``, a staging folder with part of a
    result, and, if it was killed while swapping a complete result in, the previous
    result set aside; inside ``path`` (a folder written in place), a staging folder,
    or a complete result that it was moving in file by file.  This puts a complete
    result back at ``path`` if there is none, finishes moving a complete one in, and
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

    Raises
    ------
    VolregIOError
        If a complete result inside ``path`` cannot be moved in.
    """
    final = Path(path)
    restored = None
    if final.is_dir():
        inside = _leftovers(final, INSIDE_PREFIX)
        for entry in inside["ready"]:  # killed while moving its complete result in: finish the move
            finish_in_place(entry, final)
            restored = "new"
        for entry in inside["new"] + inside["old"]:
            remove_tree(entry)
    named = final if final.name not in ("", "..") else Path(os.path.abspath(final))
    found = _leftovers(named.parent, _stage_prefix(named))
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
            remove_tree(entry)
    return restored


def _replaceable(final: Path) -> bool:
    """Whether ``final`` can be replaced as a whole by renaming a sibling onto it."""
    if final.is_symlink():
        return False
    parent = final.parent
    if parent.is_dir() and not writable(parent):
        return False
    if final.exists():
        if is_mount_point(final):
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
    """Fill ``target`` with ``source``'s contents: hard links to its files (copies where links fail),
    less the hidden working entries of runs that wrote ``source`` in place."""
    def link(src: str, dst: str) -> None:
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)

    def working(folder: str, names: list[str]) -> list[str]:
        return [n for n in names if n.startswith(INSIDE_PREFIX)] if Path(folder) == source else []

    shutil.copytree(source, target, symlinks=True, copy_function=link, dirs_exist_ok=True, ignore=working)


def _stale(root: Path, staging: Path, folder: OutputFolder) -> list[Path]:
    """The outputs of an earlier run in ``root`` (the staging folder, or the output folder written in
    place) that this run's result must not keep: those named by ``folder``'s output patterns that
    this run did not write; relative to ``root``."""
    written = set(folder.written)
    stale = []
    for where, patterns in folder._family:
        try:
            entries = sorted((root / where).iterdir())
        except OSError:
            continue
        for entry in entries:
            relative = where / entry.name
            if any(fnmatch.fnmatchcase(entry.name, p) for p in patterns) and staging / relative not in written:
                stale.append(relative)
    return stale


def _swap_in(staging: Path, final: Path, may_replace: bool) -> None:
    """Replace ``final`` (if any) by the complete result in ``staging``; see :func:`recover_folder`.

    ``may_replace``: whether a ``final`` that exists now may be replaced (false for a folder that
    did not exist when the run started and ``--force`` was not given)."""
    ready = _stage_path(final, "ready")
    old = _stage_path(final, "old")
    with SignalsHeld():
        if not may_replace and (final.exists() or final.is_symlink()):
            raise VolregIOError(f"Output directory `{final}` was made by another program while this run wrote its "
                                "outputs, which were removed; pass --force to replace it.")
        os.rename(staging, ready)
        _staging_open.discard(staging)
        try:
            if final.exists():
                os.rename(final, old)
            os.rename(ready, final)
        except OSError as exc:
            if old.exists() and not final.exists():
                os.rename(old, final)
            remove_tree(ready)
            raise VolregIOError(f"Output directory `{final}` could not be replaced: {exc.strerror}.") from exc
        remove_tree(old)


def _move_in(staging: Path, final: Path, folder: OutputFolder, force: bool) -> None:
    """Put the complete result in ``staging`` (inside ``final``) into ``final`` file by file; see
    :func:`~volreg.io._folder_parts.finish_in_place`."""
    if not force:
        for path in folder.written:  # made meanwhile by another program
            target = final / path.relative_to(staging)
            if target.exists() or target.is_symlink():
                raise VolregIOError(_exists_message(target))
    stale = _stale(final, staging, folder)
    (staging / STALE_LIST).write_text(json.dumps([str(p) for p in stale]))
    ready = _hidden(final, INSIDE_PREFIX, "ready")
    with SignalsHeld():
        try:
            os.rename(staging, ready)
        except OSError as exc:
            raise VolregIOError(f"Output directory `{final}` could not take this run's result: {exc.strerror}.") from exc
        _staging_open.discard(staging)
        finish_in_place(ready, final)


def _inside(path: Path, folder: Path) -> Path | None:
    """``path`` relative to ``folder`` if it lies inside it (or is it), else None."""
    try:
        return Path(os.path.abspath(path)).relative_to(os.path.abspath(folder))
    except ValueError:
        return None


def _discard_staging(staging: Path, created: list[Path]) -> None:
    """Remove a staging folder, and then the folders its run ``created`` (innermost first, while empty)."""
    remove_tree(staging)
    _staging_open.discard(staging)
    _remove_directories(created)


class _Run:
    """One :func:`output_folder` transaction: its record (``folder``), its staging folder (beside the
    output folder, or inside it with ``in_place``; None for a transaction inside an outer one's
    folder, at ``relative`` in ``outer``) and the lock it holds."""

    def __init__(self, folder: OutputFolder, staging: Path | None = None, *, outer: OutputFolder | None = None,
                 relative: Path | None = None, lock: FolderLock | None = None, in_place: bool = False,
                 force: bool = False, may_replace: bool = True) -> None:
        self.folder, self.staging, self.outer, self.relative = folder, staging, outer, relative
        self.lock, self.in_place, self.force, self.may_replace = lock, in_place, force, may_replace

    def abandon(self) -> None:
        """The run failed or was interrupted: remove what it wrote; the output folder keeps what it held."""
        if self.staging is None:
            self.folder._remove()
            return
        try:
            _discard_staging(self.staging, [])
            if _holds_result(self.folder.final):
                _kept.append(self.folder.final)
        finally:
            self._release(failed=True)

    def complete(self) -> None:
        """The run completed: put its result in place (an inner one's: hand it to the outer one)."""
        if self.staging is None:
            if self.outer is not None:
                self.outer._adopt(self.folder, self.relative)
            return
        final, folder, failed = self.folder.final, self.folder, True
        try:
            if self.in_place:
                _move_in(self.staging, final, folder, self.force)
            else:
                for relative in _stale(self.staging, self.staging, folder):
                    remove_tree(self.staging / relative)
                _swap_in(self.staging, final, self.may_replace)
            failed = False
        finally:
            if failed:
                # The swap had not begun where the staging folder is still there, and a failed swap
                # beside the folder puts it back: the folder then keeps what it held.
                if (self.staging.exists() or not self.in_place) and _holds_result(final):
                    _kept.append(final)
                _discard_staging(self.staging, [])
            self._release(failed)

    def _release(self, failed: bool) -> None:
        """Release the lock; after a failure, remove the folders the run created (the lock file's too)."""
        if self.lock is not None:
            self.lock.release()
            self.lock = None
        if failed:
            _remove_directories(self.folder.created)


_STAGED_PART = re.compile(r"^\.(?P<name>.+)\.volreg-(new|old)-\d+-[0-9a-f]+$")
_INNER_STAGE = re.compile(r"^\.volreg-(new|old)-\d+-[0-9a-f]+$")
_TEMP_FILE = re.compile(r"^\.tmp-[0-9a-f]{8}-(?P<name>.+)$")


def user_path(path: str | os.PathLike[str]) -> str:
    """``path`` as the user named it: each staging folder (``.OUT.volreg-new-PID-HEX`` beside an
    output folder, ``.volreg-new-PID-HEX`` inside one) and temporary file (``.tmp-HEX-NAME``)
    of this module replaced by the output it stands for.

    A message quotes paths through this, so that it never names a hidden working path that is
    gone once the run has failed."""
    parts = []
    for part in Path(os.fsdecode(path)).parts:
        if _INNER_STAGE.match(part):
            continue
        staged = _STAGED_PART.match(part) or _TEMP_FILE.match(part)
        parts.append(staged.group("name") if staged else part)
    return str(Path(*parts)) if parts else os.fsdecode(path)


def _name_final(exc: BaseException, folder: OutputFolder) -> None:
    """Make an OSError about a file in the staging folder name the file in the output folder instead
    (its messages, a full disk's, name the output as the user named it)."""
    if isinstance(exc, OSError) and exc.filename is not None:
        relative = _inside(Path(os.fsdecode(exc.filename)), folder.path)
        if relative is not None:
            exc.filename = str(folder.final / relative)


def _check_folder_writable(final: Path) -> None:
    """Refuse, before any work, an output folder that this process cannot write into or create."""
    probe = final
    while not (probe.exists() or probe.is_symlink()) and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir() or writable(probe):
        return
    if probe == final:
        raise VolregIOError(f"Output directory `{final}` is not writable; expected a folder you can write into "
                            "for -o.")
    raise VolregIOError(f"Output directory `{final}` cannot be created: `{probe}` is not writable; expected a "
                        "folder you can write into for -o.")


def _patterns(outputs: tuple[str, ...], force: bool) -> list[tuple[Path, tuple[str, ...]]]:
    """The output patterns a run on a folder records: with ``force`` only (without, nothing is replaced)."""
    return [(Path("."), outputs)] if force and outputs else []


def _nested(final: Path, outer: OutputFolder, relative: Path, force: bool, require_empty: bool,
            outputs: tuple[str, ...]) -> _Run:
    """A transaction on folder ``final``, at ``relative`` in the open ``outer`` one: written into its
    staging folder, put in place with it."""
    where = outer.path / relative
    shadow = None if outer._shadow is None else outer._shadow / relative
    existing = where if shadow is None else shadow
    for place in (where, existing):
        if place.exists() and not place.is_dir():
            raise UsageError(f"Output directory `{final}` exists and is not a directory; expected a directory for -o.")
    if require_empty and not force and existing.is_dir() and _holds_result(existing):
        raise UsageError(f"Output directory `{final}` exists and is not empty; pass --force to write into it.")
    folder = OutputFolder(where, make_directory(where), final=final, shadow=shadow)
    folder._family = _patterns(outputs, force)
    return _Run(folder, outer=outer, relative=relative)


def _staged(final: Path, created: list[Path], in_place: bool) -> tuple[OutputFolder, Path]:
    """A new staging folder for ``final`` and the record of a run writing there: ``(folder, staging)``.

    Beside ``final``, it starts with hard links to ``final``'s contents; inside it (``in_place``),
    empty, the earlier outputs staying in ``final`` until the run completes.
    """
    staging = _hidden(final, INSIDE_PREFIX, "new") if in_place else _stage_path(final, "new")
    try:
        staging.mkdir()
        _staging_open.add(staging)
        if final.is_dir() and not in_place:
            _link_tree(final, staging)
    except OSError as exc:
        _discard_staging(staging, [])
        raise VolregIOError(f"Output directory `{final}` could not be prepared: {exc.strerror}.") from exc
    return OutputFolder(staging, created, final=final, shadow=final if in_place else None), staging


def _outermost(final: Path, force: bool, require_empty: bool, outputs: tuple[str, ...]) -> _Run:
    """A transaction on folder ``final`` of its own: checked, locked, and staged beside or inside it."""
    if final.is_symlink() and not final.exists():
        raise UsageError(f"Output directory `{final}` is a symbolic link to `{os.readlink(final)}`, which does not "
                         "exist; expected a directory for -o.")
    if final.exists() and not final.is_dir():
        raise UsageError(f"Output directory `{final}` exists and is not a directory; expected a directory for -o.")
    _check_folder_writable(final)
    created = make_directory(final.parent)
    try:
        lock = FolderLock(final, _stage_prefix)
    except BaseException:
        _remove_directories(created)
        raise
    try:
        recover_folder(final)
        existed = final.exists()
        if require_empty and not force and final.is_dir() and _holds_result(final):
            raise UsageError(f"Output directory `{final}` exists and is not empty; pass --force to write into it.")
        in_place = not _replaceable(final)
        folder, staging = _staged(final, created, in_place)
    except BaseException:
        lock.release()
        _remove_directories(created)
        raise
    folder._family = _patterns(outputs, force)
    return _Run(folder, staging, lock=lock, in_place=in_place, force=force, may_replace=force or existed)


@contextmanager
def output_folder(
    path: str | os.PathLike[str], force: bool = False, *, require_empty: bool = True, outputs: Iterable[str] = ()
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
        :meth:`OutputFolder.check_writable` to refuse the outputs that exist.
    outputs : iterable of str, optional
        Every file the command may write into the folder, whatever its options: names, or
        ``fnmatch`` patterns (``frame_*.vtk``).  With ``force``, those of them in the folder that
        this run does not write (an earlier run's, made with other options) are removed when it
        completes, so that the folder holds this run's outputs and the files that are not volreg's.

    Yields
    ------
    OutputFolder
        Write each output under :attr:`OutputFolder.path` (not under ``path``) and call
        :meth:`OutputFolder.record` with it once written.  Write a file by replacing it
        (:func:`atomic_output`, as every volreg writer does), never in place: until
        replaced, the files there may be hard links to the previous result's.

    Raises
    ------
    UsageError
        If ``path`` is a non-empty folder (with ``require_empty`` and without
        ``force``) or exists and is not a folder.
    VolregIOError
        Before the run, if the folder (or, where it does not exist, the nearest folder above it)
        cannot be written, or another run is writing it; at the end, if it cannot be replaced.

    Notes
    -----
    The run holds a lock on ``path`` (an ``flock`` on a hidden ``.<name>.volreg-lock`` beside it)
    from the start: a second run on ``path`` meanwhile, in this process or another, fails at once.

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

    Where ``path`` cannot be replaced as a whole (a symbolic link, a mount point, bind mounts
    included, the working directory or a folder above it, or a folder whose parent is not
    writable) the staging folder is a hidden folder inside ``path`` (``.volreg-new-<pid>-<hex>``),
    which starts empty: the earlier outputs stay in ``path``, whole, until the run completes;
    then the staging folder is marked complete by a rename and its files replace their namesakes
    one by one (signals held back), and a run killed meanwhile is finished by the next run on
    ``path``.

    A transaction opened inside another one's folder (in the same thread) writes into
    the outer one's staging folder and completes with it.
    """
    final = Path(path)
    outer = _open_folder.get()
    # Held from the staging folder's creation until the cleanup below guards it: an interrupt in
    # between would leave the folder behind.  One that came meanwhile is raised in the try.
    held = SignalsHeld()
    held.__enter__()
    try:
        relative = None if outer is None else _inside(final, outer.final)
        if relative is not None:
            run = _nested(final, outer, relative, force, require_empty, tuple(outputs))
        else:
            run = _outermost(final, force, require_empty, tuple(outputs))
    except BaseException:
        held.__exit__(None, None, None)
        raise
    token = _open_folder.set(run.folder)
    try:
        held.__exit__(None, None, None)
        yield run.folder
    except BaseException as exc:
        _name_final(exc, run.folder)
        run.abandon()
        raise
    finally:
        _open_folder.reset(token)
    try:
        run.complete()
    except OSError as exc:
        _name_final(exc, run.folder)
        raise

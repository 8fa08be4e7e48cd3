"""Parts of :func:`volreg.io._atomic.output_folder`: one run per output folder (a lock), whether a
folder can be renamed (mount points), and putting a complete result into a folder file by file.

An output folder that cannot be replaced as a whole by a rename (a mount point, a symbolic link,
the working directory) is written through a hidden staging folder inside it; once the result
there is complete, that folder is marked ready by a rename and its files are moved in one by one
(:func:`finish_in_place`).  A run killed while moving them leaves the ready folder, and the next
run on the folder moves the rest (:func:`volreg.io._atomic.recover_folder`).
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import shutil
from pathlib import Path

from volreg.errors import VolregIOError

__all__ = ["INSIDE_PREFIX", "STALE_LIST", "FolderLock", "finish_in_place", "is_mount_point", "remove_tree", "writable"]

#: The start of the names of the hidden entries a run keeps inside an output folder it writes in
#: place (``.volreg-new-PID-HEX``, ``.volreg-ready-PID-HEX``, the lock ``.volreg-lock``).
INSIDE_PREFIX = ".volreg-"

#: Inside a ready staging folder: the paths (relative to the output folder) of the earlier run's
#: outputs that this run does not write, removed once its files are in place.
STALE_LIST = f"{INSIDE_PREFIX}stale.json"


def writable(path: Path) -> bool:
    """Whether this process may create and remove entries in folder ``path`` (``False`` on a
    read-only file system, also for root)."""
    return os.access(path, os.W_OK | os.X_OK)


def remove_tree(path: Path) -> None:
    """Remove a file, a symbolic link or a folder with its contents, if there."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _unescape_mount_point(field: bytes) -> str:
    """A mount point as /proc/self/mountinfo writes it (space, tab, newline and backslash as ``\\ooo``)."""
    return os.fsdecode(re.sub(rb"\\([0-7]{3})", lambda m: bytes([int(m.group(1), 8)]), field))


def _mount_points() -> set[str]:
    """The mount points of this process's mount namespace (none where /proc is not there)."""
    try:
        with open("/proc/self/mountinfo", "rb") as fh:
            lines = fh.read().splitlines()
    except OSError:
        return set()
    return {_unescape_mount_point(line.split()[4]) for line in lines if len(line.split()) > 4}


def is_mount_point(path: Path) -> bool:
    """Whether folder ``path`` is a mount point, bind mounts of a folder of the same file system included.

    ``os.path.ismount`` compares the device and inode of the folder and its parent, which a bind
    mount of another folder of the same file system passes as an ordinary folder; renaming such a
    folder fails ("Device or resource busy").  The mount table is read as well.
    """
    if os.path.ismount(path):
        return True
    try:
        if os.stat(path).st_dev != os.stat(os.path.join(path, "..")).st_dev:
            return True
    except OSError:
        return False
    return os.path.realpath(path) in _mount_points()


class FolderLock:
    """An exclusive lock on one output folder, held by a run for its whole transaction.

    The lock is ``fcntl.flock`` on a hidden file beside the folder (``.NAME.volreg-lock``), or
    inside it (``.volreg-lock``) where its parent cannot be written; the file is removed when the
    lock is released.  Taking it does not wait: a second run on the folder fails at once.

    Parameters
    ----------
    final : pathlib.Path
        The output folder as named by the user (its real path decides where the lock lives, so that
        a symbolic link and the folder it points to share one lock).
    prefix : callable
        ``prefix(folder)``: the start of the names of ``folder``'s hidden siblings.

    Raises
    ------
    VolregIOError
        When another run holds the lock (naming it by its process id), or the lock file cannot be made.
    """

    def __init__(self, final: Path, prefix) -> None:
        self.final = final
        real = Path(os.path.realpath(final))
        if real.parent != real and real.parent.is_dir() and writable(real.parent):
            self.path: Path | None = real.parent / f"{prefix(real)}lock"
        elif real.is_dir():
            self.path = real / f"{INSIDE_PREFIX}lock"
        else:  # nowhere to put it; the folder's own checks refuse this case
            self.path = None
        self.fd: int | None = None
        if self.path is not None:
            self._acquire()

    def _acquire(self) -> None:
        assert self.path is not None
        for _ in range(100):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_RDWR | os.O_CLOEXEC, 0o666)
            except OSError as exc:
                raise VolregIOError(f"Output directory `{self.final}` could not be locked for this run: "
                                    f"{exc.strerror}.") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                holder = self._holder(fd)
                os.close(fd)
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise VolregIOError(f"Output directory `{self.final}` could not be locked for this run: "
                                        f"{exc.strerror}.") from None
                raise VolregIOError(
                    f"Output directory `{self.final}` is being written by another volreg run{holder}; expected one run "
                    "per output folder (wait for it to end, or choose another -o).") from None
            # A run that ended may have removed the file between our open and our lock: lock the file
            # that is there now.
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
                self.fd = fd
                return
            os.close(fd)
        raise VolregIOError(f"Output directory `{self.final}` could not be locked for this run: its lock file "
                            "keeps being replaced.")

    @staticmethod
    def _holder(fd: int) -> str:
        """`` (process N)`` for the process id the holder wrote into the lock file, if it did."""
        try:
            text = os.pread(fd, 32, 0).decode().strip()
        except (OSError, UnicodeDecodeError):
            return ""
        return f" (process {text})" if text.isdigit() else ""

    def release(self) -> None:
        """Remove the lock file and release the lock (removed first, while still held: see :meth:`_acquire`)."""
        if self.fd is None:
            return
        assert self.path is not None
        try:
            if os.path.samestat(os.fstat(self.fd), os.stat(self.path)):
                self.path.unlink()
        except OSError:
            pass
        os.close(self.fd)
        self.fd = None


def _staged_files(ready: Path) -> list[tuple[Path, bool]]:
    """``(path relative to ready, is_folder)`` of every entry under ``ready``, folders before their contents."""
    entries: list[tuple[Path, bool]] = []
    for dirpath, dirnames, filenames in os.walk(ready):
        here = Path(dirpath).relative_to(ready)
        for name in sorted(dirnames):
            entries.append((here / name, not (Path(dirpath) / name).is_symlink()))
        entries.extend((here / name, False) for name in sorted(filenames))
    return [(rel, folder) for rel, folder in entries if rel != Path(STALE_LIST)]


def finish_in_place(ready: Path, final: Path) -> None:
    """Move the complete result in ``ready`` (a hidden folder inside ``final``) into ``final``, file by
    file, then remove the outputs of the earlier run that the new result does not hold (listed in
    ``ready``'s :data:`STALE_LIST`) and ``ready`` itself.

    Each file replaces its namesake by ``os.replace``; a folder of the result is merged into
    ``final``'s.  Doing it again after an interruption finishes the move.

    Raises
    ------
    VolregIOError
        If a file cannot be moved; ``ready`` is left for the next run on ``final`` to finish.
    """
    try:
        stale = json.loads((ready / STALE_LIST).read_text())
    except (OSError, ValueError):
        stale = []
    try:
        for rel, is_folder in _staged_files(ready):
            target = final / rel
            if is_folder:
                if target.is_symlink() or (target.exists() and not target.is_dir()):
                    target.unlink()
                target.mkdir(exist_ok=True)
                continue
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            os.replace(ready / rel, target)
    except OSError as exc:
        raise VolregIOError(f"Output directory `{final}` could not take this run's result: {exc.strerror}; "
                            f"the next run on it finishes putting it in place.") from exc
    for rel in stale if isinstance(stale, list) else []:
        if isinstance(rel, str) and rel and not Path(rel).is_absolute() and ".." not in Path(rel).parts:
            remove_tree(final / rel)
    remove_tree(ready)

"""Errors and warnings volreg raises for its users' inputs.

Every error that describes a user's input (a file, an argument, a protocol, a pair of
volumes that cannot be registered) derives from :class:`VolregError`; the command line
reports any of them as one line and exits with status 2.  Each also derives from the
built-in class it has always been (``ValueError``, ``TypeError`` or ``RuntimeError``), so
code that catches those keeps working.  Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import errno
import os
import re

__all__ = [
    "EXCERPT_CHARS",
    "excerpt",
    "exception_text",
    "full_disk",
    "SchedulerUnavailable",
    "TemplateError",
    "VolregError",
    "VolregIOError",
    "GeometryError",
    "SurfaceError",
    "ProtocolError",
    "RegistrationInputError",
    "RegistrationDiverged",
    "UsageError",
    "ArgumentTypeError",
    "VolregWarning",
]


#: The most characters of a file's content that a message quotes (:func:`excerpt`).
EXCERPT_CHARS = 40

#: Where an excerpt leaves characters out.
_ELISION = "..."


def _printable(text: str, escape_backslash: bool) -> list[str]:
    """``text`` as pieces that print on one line: each character that is not printable (a line
    break, a control character, a bidirectional override) as its Python escape."""
    pieces = []
    for c in text:
        if c == "\\" and escape_backslash:
            pieces.append("\\\\")
        elif c.isprintable():
            pieces.append(c)
        else:
            pieces.append(repr(c)[1:-1])  # \n, \x00, \u202e
    return pieces


def _shortened(pieces: list[str], limit: int) -> str:
    """The pieces joined, or, where they are longer than ``limit`` characters, their start and end
    with :data:`_ELISION` between, ``limit`` characters in all."""
    if sum(len(p) for p in pieces) <= limit:
        return "".join(pieces)
    keep = max(limit - len(_ELISION), 2)
    head, tail, used = [], [], 0
    for p in pieces:  # the start: half of what is kept, whole pieces only (an escape is not cut)
        if used + len(p) > (keep + 1) // 2:
            break
        head.append(p)
        used += len(p)
    room = keep - used
    for p in reversed(pieces[len(head):]):
        if len(p) > room:
            break
        tail.append(p)
        room -= len(p)
    return "".join(head) + _ELISION + "".join(reversed(tail))


def excerpt(value: object, limit: int = EXCERPT_CHARS, *, quote: bool = True) -> str:
    """How a message quotes something read from a user's file: short, on one line, printable.

    A message names files and says what was expected; of a file's content it shows at most this
    excerpt, so that a file that is not what it claims to be (a key, a list of paths, or another
    file reached through a link) is not copied onto the terminal or into a log.

    Parameters
    ----------
    value : object
        A string read from a file (a field, a line, a key), or a value parsed from one (its
        ``repr`` is quoted).
    limit : int
        The most characters shown (escapes included, quotes not); a longer text keeps its start
        and end, with ``...`` between.
    quote : bool
        Put a string in single quotes, as ``repr`` does (``'ten'``); without, it stands as it is
        (for a text the message already sets off, e.g. in backticks).

    Returns
    -------
    str
        Characters that are not printable (line breaks, control characters, bidirectional
        overrides) are escaped as Python escapes them (``\\n``, ``\\x00``, ``\\u202e``).
    """
    if isinstance(value, str):
        shown = _shortened(_printable(value, escape_backslash=quote), limit)
        return f"'{shown}'" if quote else shown
    return _shortened(_printable(repr(value), escape_backslash=False), limit)


_QUOTED = re.compile(r"'[^']*'|\"[^\"]*\"")


def exception_text(exc: BaseException | str, limit: int = EXCERPT_CHARS) -> str:
    """The first line of a library's exception, as a message may carry it.

    Parsers quote what they failed on (``could not convert string to float: '...'``, a
    ``KeyError`` of a value read from a file): each quoted part is cut to an :func:`excerpt` of
    ``limit`` characters, and characters that are not printable are escaped.  Without any text,
    the exception's type's name.  ``exc`` may also be such a text (a library's message line).
    """
    text = str(exc).strip()
    line = text.splitlines()[0].strip() if text else ""
    if not line:
        return type(exc).__name__ if isinstance(exc, BaseException) else ""
    parts, start = [], 0
    for found in _QUOTED.finditer(line):
        parts.append("".join(_printable(line[start:found.start()], escape_backslash=False)))
        inner = found.group(0)
        parts.append(inner[0] + _shortened(_printable(inner[1:-1], escape_backslash=False), limit) + inner[-1])
        start = found.end()
    parts.append("".join(_printable(line[start:], escape_backslash=False)))
    return "".join(parts)


#: The errors of a device without room (a full disk, a user's quota used up).
FULL_DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT)

#: How the C libraries volreg writes through (ITK, VTK, HDF5, zlib) word a full disk in the
#: errors they raise instead of the system's OSError.
_FULL_DISK_TEXT = re.compile(r"no space left on device|disk quota exceeded|errno\s*=?\s*(28|122)\b|"
                             r"ran out of disk space|out of disk space", re.IGNORECASE)


def full_disk(exc: BaseException) -> OSError | None:
    """The full-device error behind ``exc``, or None.

    A library may raise a full disk as an error of its own (ITK's ``RuntimeError``, VTK's,
    HDF5's, a Dask task's), with the system's ``OSError`` in its chain of causes or only in its
    text: either is found here, in ``exc`` or in any exception it was raised from or during.

    Returns
    -------
    OSError or None
        An ``OSError`` with ``errno`` ``ENOSPC`` or ``EDQUOT`` (the one found, or a new one
        where only a message said so, with no file name), or None where nothing says the
        device was full.
    """
    seen: set[int] = set()
    chain: list[BaseException] = []
    while exc is not None and id(exc) not in seen and len(seen) < 50:
        seen.add(id(exc))
        chain.append(exc)
        if isinstance(exc, OSError) and exc.errno in FULL_DISK_ERRNOS:
            return exc
        exc = exc.__cause__ or exc.__context__
    for link in chain:
        found = _FULL_DISK_TEXT.search(str(link)[:100_000])
        if found:
            code = errno.EDQUOT if "quota" in found.group(0).lower() or found.group(1) == "122" else errno.ENOSPC
            return OSError(code, os.strerror(code))
    return None


class VolregError(Exception):
    """Base of every error volreg raises about its users' inputs; the message is one line."""


class VolregIOError(VolregError, ValueError):
    """Raised when a file cannot be read or written; the message names the file."""


class GeometryError(VolregError, ValueError):
    """Raised when a volume's geometry (origin, spacing, direction) is invalid."""


class SurfaceError(VolregError, ValueError):
    """A label cannot give a surface (absent from the volume, or too small)."""


class ProtocolError(VolregError, ValueError):
    """A protocol file that cannot be used: unreadable, unknown key, bad value."""


class RegistrationInputError(VolregError, ValueError):
    """Inputs that cannot be registered (no common label, grids far apart, ...)."""


class RegistrationDiverged(VolregError, RuntimeError):
    """The optimisation of a level failed (NaN/Inf objective or coefficients, or a warp that folds
    too much of the output grid): no warp is returned or written."""


class UsageError(VolregError, ValueError):
    """A command-line request that cannot be carried out (bad argument or combination)."""


class ArgumentTypeError(VolregError, TypeError):
    """An argument of a public function of the wrong kind (a list where a label volume is
    expected, a number where a callable is): the message names the argument and what it takes."""


class SchedulerUnavailable(VolregError, RuntimeError):
    """No Dask scheduler answered at the address given for a cohort (nothing was registered)."""


class TemplateError(VolregError, RuntimeError):
    """A cohort template cannot be built (fewer than two subjects registered to it in an iteration)."""


class CohortInterrupted(KeyboardInterrupt):  # an interrupt, not an error: outside __all__'s errors
    """A cohort's run interrupted by SIGINT or SIGTERM after its cluster stopped: the finished pairs
    are kept (a rerun skips them).

    Attributes
    ----------
    signal_name : str
        ``"SIGINT"`` or ``"SIGTERM"``.
    finished, total : int
        Pairs finished (their results complete on disk) and pairs planned.
    """

    def __init__(self, signal_name: str, finished: int, total: int) -> None:
        super().__init__(signal_name)
        self.signal_name, self.finished, self.total = signal_name, finished, total


class VolregWarning(UserWarning):
    """An input that is read, but not unambiguously (the command line prints it as one line)."""

"""Progress bars on stderr for volreg's ``progress(stage, done, total)`` callbacks.

Numerical code reports progress through a plain callback and never prints;
the command line turns that callback into tqdm bars here.
"""

from __future__ import annotations

import sys
from types import TracebackType

from tqdm import tqdm

__all__ = ["ProgressBars", "note_interrupt", "clear_interrupt", "raise_if_interrupted"]

#: Names of signals (``"SIGINT"``, ``"SIGTERM"``) whose KeyboardInterrupt was raised where it
#: could not propagate: inside a ctypes callback, as while numba compiles (llvmlite reports it as
#: "Exception ignored" and carries on).  The next progress report raises it again.
_pending: list[str] = []


def note_interrupt(name: str) -> None:
    """Record an interrupt (a signal name) for the next :func:`raise_if_interrupted`."""
    _pending.append(name)


def clear_interrupt() -> None:
    """Forget recorded interrupts (at the start and end of a command)."""
    _pending.clear()


def raise_if_interrupted() -> None:
    """Raise ``KeyboardInterrupt(name)`` if an interrupt was recorded and not yet raised."""
    if _pending:
        name = _pending[0]
        _pending.clear()
        raise KeyboardInterrupt(name)


class ProgressBars:
    """A ``progress(stage, done, total)`` callback that draws one tqdm bar per stage.

    A bar is opened the first time a stage reports, advanced to ``done`` on
    every call, and closed when ``done >= total``.  A stage that starts over
    (``done`` going backwards, or a new ``total``) gets a fresh bar.

    Parameters
    ----------
    quiet : bool, default False
        Draw nothing.  Otherwise bars follow tqdm's ``disable=None`` rule:
        shown only when stderr is a terminal, so logs and pipes stay clean.

    Examples
    --------
    >>> with ProgressBars(quiet=True) as progress:
    ...     for i in range(3):
    ...         progress("fit", i + 1, 3)
    """

    def __init__(self, *, quiet: bool = False) -> None:
        self.quiet = bool(quiet)
        self._bars: dict[str, tqdm] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        """Report that ``done`` of ``total`` steps of ``stage`` are finished (and raise an
        interrupt recorded by :func:`note_interrupt` since the last report)."""
        raise_if_interrupted()
        done, total = int(done), int(total)
        bar = self._bars.get(stage)
        if bar is not None and (bar.total != total or done < bar.n):
            self._close(stage)
            bar = None
        if bar is None:
            bar = tqdm(
                total=total,
                desc=stage,
                file=sys.stderr,  # looked up now, so redirected stderr is honoured
                disable=True if self.quiet else None,
                leave=True,
                dynamic_ncols=True,
            )
            self._bars[stage] = bar
        bar.update(min(done, total) - bar.n)
        if done >= total:
            self._close(stage)

    def _close(self, stage: str) -> None:
        bar = self._bars.pop(stage, None)
        if bar is not None:
            bar.close()

    def close(self) -> None:
        """Close every bar still open (e.g. after an error)."""
        for stage in list(self._bars):
            self._close(stage)

    def __enter__(self) -> "ProgressBars":
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

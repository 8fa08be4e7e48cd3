"""Hold SIGINT and SIGTERM back for a block that an interrupt must not cut short.

Two kinds of block need it: the few renames that swap a complete result into place
(:mod:`volreg.io._atomic`), and numba compiling a loop or loading it from its cache
(:func:`volreg._jit.njit`).  An interrupt raised inside numba's compiler, or inside LLVM's
callbacks into Python, leaves LLVM's objects half-built: the process then crashed
(a segmentation fault) in the next compiled loop it loaded or at exit, after the command's
one-line report of the interrupt.
"""

from __future__ import annotations

import signal
import threading

__all__ = ["SignalsHeld", "exit_on_early_signals"]


def _early_exit(signum, frame) -> None:
    """Report a signal that came while the command was starting, and end the process at once."""
    import os
    import sys

    name = signal.Signals(signum).name
    try:
        sys.stderr.write(f"volreg: interrupted by {name} while starting; nothing was written.\n")
        sys.stderr.flush()
    except (OSError, ValueError, AttributeError):  # no stderr to report on
        pass
    os._exit(130 if signum == signal.SIGINT else 128 + int(signum))


def exit_on_early_signals() -> None:
    """Make SIGINT and SIGTERM end the process with one line and status 130 / 143 from now on.

    For the command line only, installed before anything heavy is imported: an interrupt that
    came during Python's own imports (numpy, numba, VTK) ended in a KeyboardInterrupt traceback,
    and a SIGTERM then ended the process silently (status -15).  Nothing is written while the
    command starts, so ending at once is safe; the command installs its own handlers (which
    remove what a run wrote) before it writes anything.  A SIGINT that is ignored (a job in
    the background) stays ignored.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    for signum in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, _early_exit)


class SignalsHeld:
    """Hold SIGINT and SIGTERM back (main thread) until the block ends.

    Their handlers are replaced by one that notes the signal, and the handler of a noted one
    runs once the block has ended: the command's handler then raises its KeyboardInterrupt
    there.  (Blocking them in the main thread's signal mask is not enough: the kernel then
    hands a signal sent to the process to another of its threads, a compiled loop's helper,
    and Python runs the handler in the main thread all the same; an interrupt between two
    renames left the staging folder behind.)  Off the main thread, where no handler can be
    set and none runs, the block is not held.  Blocks may nest.
    """

    _SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __enter__(self):
        self.previous: dict = {}
        self.noted: list[int] = []
        if threading.current_thread() is threading.main_thread():
            try:
                for signum in self._SIGNALS:
                    # recorded before the swap: a handler may run (and raise) right after it
                    self.previous[signum] = signal.getsignal(signum)
                    signal.signal(signum, lambda signum, frame: self.noted.append(signum))
            except BaseException:  # a pending handler raised around a swap: undo the swaps made
                self._restore()
                raise
        return self

    def _restore(self) -> BaseException | None:
        """Put every replaced handler back; return what a pending handler raised meanwhile, if anything.

        ``signal.signal`` first runs the handlers of signals that came meanwhile, and when one of
        those raises, the swap is not made; a handler may also run right after a swap.  Each swap
        is made until it holds, so that no handler stays replaced."""
        raised = None
        for signum, handler in self.previous.items():
            while handler is not None:  # None: a handler not set from Python, which cannot be set again
                try:
                    signal.signal(signum, handler)
                    break
                except BaseException as exc:  # noqa: BLE001 - raised again once every handler is back
                    raised = raised or exc
        return raised

    def __exit__(self, *exc) -> None:
        raised = self._restore()
        if raised is not None:
            raise raised
        for signum in self.noted[:1]:  # now, as it would have been handled in the block
            handler = self.previous[signum]
            if callable(handler):
                handler(signum, None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(signum)

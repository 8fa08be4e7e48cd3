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

__all__ = ["SignalsHeld"]


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
            for signum in self._SIGNALS:
                self.previous[signum] = signal.signal(signum, lambda signum, frame: self.noted.append(signum))
        return self

    def __exit__(self, *exc) -> None:
        for signum, handler in self.previous.items():
            signal.signal(signum, handler)
        for signum in self.noted[:1]:  # now, as it would have been handled in the block
            handler = self.previous[signum]
            if callable(handler):
                handler(signum, None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(signum)

"""Errors and warnings volreg raises for its users' inputs.

Every error that describes a user's input (a file, an argument, a protocol, a pair of
volumes that cannot be registered) derives from :class:`VolregError`; the command line
reports any of them as one line and exits with status 2.  Each also derives from the
built-in class it has always been (``ValueError``, ``TypeError`` or ``RuntimeError``), so
code that catches those keeps working.  Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

__all__ = [
    "SchedulerUnavailable",
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

"""``njit`` for volreg's compiled loops, with an on-disk cache wherever one can be written.

numba keeps compiled loops in a cache beside the sources (``__pycache__``) or, where the
package directory is read-only, in the user's cache directory.  Where neither can be written
(a read-only install and a read-only home, as on shared clusters and in containers run as
another user) ``numba.njit(cache=True)`` raises at import.  This module probes once, at the
first decoration: the default locations; else a folder under the system's temporary
directory (one per user, shared by the processes of a batch); else no cache (every process
compiles again, slower to start but correct).  ``NUMBA_CACHE_DIR``, when set, is numba's and
is left alone.
"""

from __future__ import annotations

import os
import tempfile
import warnings

import numba
from numba.core import config as _numba_config

__all__ = ["njit", "cache_location"]

#: Where compiled loops are cached: "default" (numba's own choice), a folder, or None (no cache).
_LOCATION: str | None | bool = False  # False: not probed yet


def _probe() -> bool:
    """Whether numba can cache a function defined in this package with its current settings."""

    def _probe_function():  # pragma: no cover - never called
        return 0

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            numba.njit(cache=True)(_probe_function)
    except RuntimeError:  # "cannot cache function ...: no locator available for file ..."
        return False
    return True


def _temporary_cache() -> str | None:
    """A per-user numba cache folder under the system's temporary directory, if one can be made."""
    from volreg._cache_folder import fallback_cache_folder

    path = fallback_cache_folder()
    try:
        os.makedirs(path, mode=0o700, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError:
        return None
    return path


def cache_location() -> str | None:
    """Where volreg's compiled loops are cached (probed once per process).

    Returns
    -------
    str or None
        ``"default"`` where numba's own locations work (or ``NUMBA_CACHE_DIR`` is set), the
        fallback folder under the temporary directory, or ``None`` when nothing can be
        written (the loops are then compiled in every process).
    """
    global _LOCATION
    if _LOCATION is False:
        if _probe():
            _LOCATION = "default"
        else:
            path = _temporary_cache()
            if path is not None:
                _numba_config.CACHE_DIR = path
                os.environ["NUMBA_CACHE_DIR"] = path  # worker processes started later inherit it
                _LOCATION = path if _probe() else None
                if _LOCATION is None:
                    _numba_config.CACHE_DIR = ""
                    del os.environ["NUMBA_CACHE_DIR"]
            else:
                _LOCATION = None
    return _LOCATION


def njit(*args, cache: bool = True, **kwargs):
    """``numba.njit`` with ``cache=True`` only where a cache can be written (see the module notes).

    Used as ``@njit(parallel=True)`` or ``@njit``; the keyword arguments are numba's.
    """
    if args and callable(args[0]):  # bare @njit
        return njit(**kwargs)(args[0])
    use_cache = cache and cache_location() is not None
    # NumPy's error model: a division by zero gives inf or NaN (as in NumPy) instead of raising,
    # so numba emits no zero test before each division. volreg's loops divide only by checked
    # quantities (widths, spacings, determinants above a floor); the loops compile about 10 %
    # faster (the first run's cost) and give the same results up to the last bit of float32 outputs.
    kwargs.setdefault("error_model", "numpy")
    decorate = numba.njit(*args, cache=use_cache, **kwargs)

    def decorator(function):
        return _compiled_with_signals_held(decorate(function))

    return decorator


def _compiled_with_signals_held(dispatcher):
    """``dispatcher`` (a numba dispatcher), its ``compile`` run with SIGINT and SIGTERM held.

    numba compiles a loop, or loads it from its cache, on the loop's first call with new
    argument types (``Dispatcher.compile``).  An interrupt raised inside that work (numba's
    Python code, or LLVM's callbacks into Python) left LLVM's objects half-built, and the
    process crashed by a segmentation fault in the next loop it loaded or at exit, after the
    command had reported the interrupt.  Held (:class:`volreg._signals.SignalsHeld`), it is
    raised once the loop is ready, at most a compilation later (a few seconds on a first run,
    milliseconds from the cache).  The unwrapped method stays reachable as
    ``dispatcher.compile.__wrapped__`` (the compile-ahead helper, which SIGTERM ends at once).
    """
    from volreg._signals import SignalsHeld

    compile_now = dispatcher.compile

    def compile_held(sig):
        with SignalsHeld():
            return compile_now(sig)

    compile_held.__wrapped__ = compile_now
    dispatcher.compile = compile_held
    return dispatcher

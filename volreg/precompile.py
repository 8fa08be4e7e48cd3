"""Compile the loops of a first run on both ends at once: the command, and a helper process.

On a fresh install numba compiles volreg's loops the first time each is called and caches
them on disk (:mod:`volreg._jit`); a registration calls twelve, and compiling them takes
about 10 s of one core, imports included.  Compiling is pure Python and holds the GIL, so
threads cannot share it, but processes can share numba's on-disk cache: a command that
registers volumes starts one helper process (:func:`start`) that compiles the loops of the
later stages (from :data:`HELPER_FROM` on) into the cache, then the earlier ones from the last
back (:func:`helper_order`), while the command goes on and compiles the first-needed ones itself.
When the command reaches a loop the helper has cached, numba loads it instead of compiling it.
The two meet among the early loops; the helper is stopped when the command ends (:func:`stop`),
and what it cached stays for the next run.

``batch`` on a local cluster starts one helper per worker instead (``start(shares)``), each
compiling a share of the loops (:func:`shares_of`), and submits its tasks once they have ended
(:func:`wait`): its workers would otherwise each compile the same loops at once.

The helper is started only where the cache can be written and at least two of these loops
are not cached yet, so a warm run costs only the check (a few small index reads).  On a fresh
install, where no index file of the last of :data:`LOOPS` exists anywhere, the helper starts
before that check and makes it itself, so that it compiles while the command still imports.
``VOLREG_COMPILE_AHEAD=0`` turns it off.  Results do not depend on it: a loop loaded from the
cache is the one the next (warm) run uses anyway.
"""

from __future__ import annotations

import importlib
import os
import re
import signal
import subprocess
import sys
import time

__all__ = ["HELPER_FROM", "LOOPS", "SHARED_CALLEES", "argument_types", "cold_loops", "helper_order", "shares_of", "start",
           "stop", "wait"]

#: The compiled loops of a 3-D label-volume registration (``register``, ``consistency``,
#: ``tune``), in the order a run first calls them, with the argument types it calls them with:
#: ``float64[2]`` a C-contiguous 2-D float64 array, ``ro:`` a read-only one, a bare name a
#: scalar.  ``tests/test_precompile.py`` checks that a registration calls each with exactly these.
LOOPS = (
    ("volreg.features.distance_maps", "_squared_distance_lines", "int64 int64 float64[3] int64 float64"),
    ("volreg.features.distance_maps", "_clipped_sdf_band",
     "int64 int64 bool[3] bool[3] int64[2] float32[1] float32 float32[3]"),
    ("volreg.features.distance_maps", "_bspline3_segments",
     "int64 int64 float32[1] int64[1] int64[2] int64[1] float64[2] int64 float64[1] float64[2] float64[3]"),
    ("volreg.kernels._compiled", "_cell_sort", "ro:float64[2] float64[1] float64 int64[1]"),
    ("volreg.kernels._compiled", "_grid_pairs",
     "int64 int64 float64[2] float64[2] int64[1] int32[1] float64[1] float64 int64[1] int64 float64 "
     "int64[1] int32[1] float32[1] bool"),
    ("volreg.kernels._compiled", "_csr_matmul_shared",
     "int64 int64 int32[1] int32[1] float64[2] float64[2] float64[3]"),
    ("volreg.kernels._compiled", "_csr_matmul_shared_sum",
     "int64 int64 int32[1] int32[1] float64[2] float64[3] float64[2]"),
    ("volreg.kernels._compiled", "_query_blocks", "float64[2] float64 int64"),
    ("volreg.kernels._compiled", "_blocked_sum_vector",
     "int64 int64 float64[2] int64[1] float64[1] float64[1] float64[1] float64[2] int32[1] float64[1] "
     "float64 int64[1] float64 float64[2] float64[3]"),
    ("volreg.kernels._compiled", "_take_rows", "int64 int64 float64[2] int64[1] float64[2]"),
    ("volreg.kernels._compiled", "_put_rows", "int64 int64 float64[2] int64[1] float64[2]"),
    ("volreg.warp.inverse", "_grid_fixed_point",
     "int64 int64 float64[4] float64[2] float64[1] float64[2] float64[1] float64[2] int64 float64 "
     "float64[2]"),
)

#: The first of :data:`LOOPS` that the helper compiles: the warp fit's first.  The command
#: reaches the distance maps' loops (the linear stage, the voxel distance maps, the B-spline
#: reader) before a helper started with it could have compiled them, so it compiles those itself
#: while the helper compiles the warp fit's and the outputs' loops in the order they are needed,
#: and then the earlier ones from the last back, until the two meet (:func:`helper_order`).  Of
#: the starting points tried, this one left a first run least behind a warm one.
HELPER_FROM = next(i for i, (_, name, _) in enumerate(LOOPS) if name == "_cell_sort")

_WORD = re.compile(r"(ro:)?(bool|int32|int64|float32|float64)(?:\[([1-4])\])?")


def argument_types(spec: str) -> tuple:
    """The numba argument types that a :data:`LOOPS` entry's text names.

    Parameters
    ----------
    spec : str
        Space-separated words: ``float64`` (a scalar), ``float64[2]`` (a C-contiguous 2-D
        array), ``ro:float64[2]`` (the same, read-only); dtypes bool, int32, int64, float32,
        float64.

    Returns
    -------
    tuple of numba types
    """
    from numba.core import types

    dtypes = {"bool": types.boolean, "int32": types.int32, "int64": types.int64,
              "float32": types.float32, "float64": types.float64}
    out = []
    for word in spec.split():
        match = _WORD.fullmatch(word)
        if match is None:
            raise ValueError(f"argument type `{word}`: expected e.g. float64, float64[2] or ro:float64[2]")
        readonly, name, ndim = match.groups()
        if ndim is None:
            if readonly:
                raise ValueError(f"argument type `{word}`: only arrays can be read-only")
            out.append(dtypes[name])
        else:
            out.append(types.Array(dtypes[name], int(ndim), "C", readonly=bool(readonly)))
    return tuple(out)


def helper_order(cold: list[int]) -> list[int]:
    """The order in which the helper compiles the cold loops (indices into :data:`LOOPS`).

    Those from :data:`HELPER_FROM` on in the order a run needs them, then the earlier ones
    from the last back.  All from the last back, the helper would meet the command in the warp
    fit's largest loop, which both would then compile.

    Parameters
    ----------
    cold : list of int
        Indices into :data:`LOOPS`, in any order.

    Returns
    -------
    list of int
    """
    ordered = sorted(set(cold))
    return [i for i in ordered if i >= HELPER_FROM] + [i for i in reversed(ordered) if i < HELPER_FROM]


#: The kernel sums and their neighbour searches, which call the same compiled functions (cell
#: ranges, gathers, the kernel): :func:`shares_of` keeps them on one helper, where compiling them
#: shares that work; split across two helpers each would compile the callees again.
SHARED_CALLEES = ("_grid_pairs", "_blocked_sum_vector", "_query_blocks", "_cell_sort")


def shares_of(order: list[int], n: int) -> list[list[int]]:
    """The loops ``order`` (indices into :data:`LOOPS`, as :func:`helper_order` gives them)
    split among ``n`` helpers, each share in that order.

    Those of :data:`SHARED_CALLEES` together in the first share, the others dealt in turn to
    the other shares; with one helper, or none of those loops, all dealt in turn to all.

    Parameters
    ----------
    order : list of int
    n : int
        At least 1.

    Returns
    -------
    list of n lists of int
        Some may be empty (fewer loops than helpers).
    """
    n = max(1, int(n))
    together = [i for i in order if LOOPS[i][1] in SHARED_CALLEES]
    if n == 1 or not together:
        return [list(order[k::n]) for k in range(n)]
    rest = [i for i in order if LOOPS[i][1] not in SHARED_CALLEES]
    return [together] + [rest[k::n - 1] for k in range(n - 1)]


def _dispatcher(index: int):
    module, name, _ = LOOPS[index]
    return getattr(importlib.import_module(module), name)


def cold_loops() -> list[int] | None:
    """The indices into :data:`LOOPS` of the loops not in numba's on-disk cache yet.

    Returns
    -------
    list of int, or None
        None where this cannot be told (no cache, or a numba whose cache is laid out
        differently): nothing is then compiled ahead.
    """
    from volreg._jit import cache_location

    if cache_location() is None:
        return None
    cold = []
    indexes: dict = {}
    try:
        for i, (_, _, spec) in enumerate(LOOPS):
            dispatcher = _dispatcher(i)
            cache = dispatcher._cache
            if id(dispatcher) not in indexes:
                indexes[id(dispatcher)] = cache._cache_file._load_index()
            key = cache._index_key(argument_types(spec), dispatcher.targetctx.codegen())
            if key not in indexes[id(dispatcher)]:
                cold.append(i)
    except Exception:  # numba's cache internals changed: compile as before, in the command alone
        return None
    return cold


def _first_index_seen() -> bool:
    """Whether an index file of the last of :data:`LOOPS` lies in any folder where numba or
    :mod:`volreg._jit` would cache it, for any version of the source.

    Looked up without importing numba or the loop's module (which takes 0.6 s): under
    ``NUMBA_CACHE_DIR`` where it is set (numba then caches nowhere else), otherwise beside the
    source, under the user's cache folder and under volreg's fallback folder in the temporary
    directory (numba's subfolder there is named after the source folder and a SHA-1 of its path).
    """
    import glob
    import hashlib

    import volreg
    from volreg._cache_folder import fallback_cache_folder

    module, name, _ = LOOPS[-1]
    parts = module.split(".")[1:]
    source_dir = os.path.join(os.path.dirname(os.path.abspath(volreg.__file__)), *parts[:-1])
    pattern = f"{parts[-1]}.{name}-*.nbi"
    sub = f"{os.path.basename(source_dir)}_{hashlib.sha1(source_dir.encode()).hexdigest()}"
    user_cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    if os.environ.get("NUMBA_CACHE_DIR"):
        folders = [os.path.join(os.environ["NUMBA_CACHE_DIR"], sub)]
    else:
        folders = [os.path.join(source_dir, "__pycache__"), os.path.join(user_cache, "numba", sub),
                   os.path.join(fallback_cache_folder(), sub)]
    return any(glob.glob(os.path.join(glob.escape(folder), pattern)) for folder in folders)


def start(shares: int = 1) -> list[subprocess.Popen]:
    """Start the helper processes that compile the cold loops into the cache (:func:`helper_order`).

    Where no index file of the last of :data:`LOOPS` exists yet (a fresh install), the helpers
    start at once and find the cold loops themselves, so that they compile while this process
    imports (a first run on the frog: 13.9 -> 13.3 s, medians of 6, against 7.6 s warm);
    otherwise this process checks the cache first (:func:`cold_loops`) and starts helpers
    only for two cold loops or more.

    Parameters
    ----------
    shares : int
        How many helpers, each compiling its share of the cold loops (:func:`shares_of`): one
        beside a command that compiles the rest itself; one per worker where the workers wait
        for them (``batch``, :func:`wait`), so that no two processes compile the same loop.

    Returns
    -------
    list of subprocess.Popen
        The helpers, to be passed to :func:`stop`; empty where none was started (turned off by
        ``VOLREG_COMPILE_AHEAD=0``, no cache, fewer than two loops cold, or no process could be
        started).
    """
    if os.environ.get("VOLREG_COMPILE_AHEAD", "1").strip() == "0":
        return []
    shares = max(1, int(shares))
    if _first_index_seen():
        cold = cold_loops()
        if cold is None or len(cold) < 2:
            return []
        order = helper_order(cold)
        words = [[str(i) for i in share] for share in shares_of(order, shares) if share]
    else:
        words = [["cold", f"{k}/{shares}"] for k in range(shares)]
    helpers = []
    for share in words:
        command = [sys.executable, "-m", "volreg.precompile", *share]
        try:
            helpers.append(subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                            stderr=subprocess.DEVNULL, close_fds=True))
        except OSError:
            break
    return helpers


def wait(helpers: list[subprocess.Popen], timeout: float = 600.0) -> None:
    """Wait until the helpers have ended (at most ``timeout`` seconds in all; then go on)."""
    deadline = time.monotonic() + timeout
    for helper in helpers:
        try:
            helper.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            return


def stop(helpers: list[subprocess.Popen]) -> None:
    """Stop the helpers that still run (what they cached stays); wait until they have ended."""
    for helper in helpers:
        if helper.poll() is not None:
            continue
        try:
            helper.terminate()
            helper.wait(timeout=10)
        except (subprocess.TimeoutExpired, KeyboardInterrupt):  # a step that ignores SIGTERM; a second Ctrl-C
            helper.kill()
            helper.wait()
        except ProcessLookupError:  # pragma: no cover - ended meanwhile
            pass


class _Stopped(Exception):
    """SIGTERM in the helper while numba writes a cache file and no write hook could be set;
    an Exception (not BaseException) so that numba's cache writer removes its temporary file."""


_stopping: list[bool] = []
_writing: list[bool] = []
_write_hooked: list[bool] = []


def _on_sigterm(signum, frame) -> None:
    """End the helper at once, unless numba is writing a cache file: then at the end of the write.

    Nothing is unwound: an exception raised into numba's compiler (or LLVM's callbacks) can leave
    its objects half-built, and their finalisers then crashed the process at exit.  A compiled
    loop is written to a temporary name and renamed, so ending between writes leaves no partial
    file."""
    _stopping.append(True)
    if not _writing and _write_hooked:
        os._exit(0)
    if not _write_hooked:
        raise _Stopped


def _hook_cache_writes() -> None:
    """Mark numba's cache writes (:data:`_writing`) so that SIGTERM waits for the one under way,
    and end the helper right after it where SIGTERM came meanwhile.  Without the hook (a numba
    whose cache writer is named differently) SIGTERM raises :class:`_Stopped` as before."""
    import contextlib

    try:
        from numba.core import caching

        original = caching.IndexDataCacheFile._open_for_write
    except (ImportError, AttributeError):  # pragma: no cover - numba's internals changed
        return

    @contextlib.contextmanager
    def marked(self, filepath):
        _writing.append(True)
        try:
            with original(self, filepath) as f:
                yield f
        finally:
            _writing.pop()
            if _stopping and not _writing:
                os._exit(0)

    caching.IndexDataCacheFile._open_for_write = marked
    _write_hooked.append(True)


def _main(argv: list[str]) -> int:
    """The helper: compile the :data:`LOOPS` entries whose indices ``argv`` gives, in that order
    (or, given ``cold K/N``, share K of N (:func:`shares_of`) of those not cached yet, in
    :func:`helper_order`; ``cold`` alone: all of them).

    SIGTERM ends it as soon as Python runs again (LLVM's compiling is not interrupted), or
    right after a cache file under way is written (:func:`_on_sigterm`).  So does the end of the
    command that started it, by any signal (SIGKILL included), after the loop being compiled.
    Exit status 0 either way.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the command, which stops the helper
    _hook_cache_writes()
    signal.signal(signal.SIGTERM, _on_sigterm)
    if hasattr(signal, "pthread_sigmask"):
        # The command starts its helpers while it holds SIGINT and SIGTERM blocked (until its own
        # handlers are in place), and a blocked mask is inherited: unblocked here, or SIGTERM would
        # wait until every loop is compiled.  One that came meanwhile is acted on now.
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    previous = sys.unraisablehook
    sys.unraisablehook = lambda u: None if _stopping else previous(u)
    try:
        os.nice(5)  # the command's own parallel loops come first
    except (AttributeError, OSError):  # pragma: no cover - not on POSIX
        pass
    parent = os.getppid()
    if argv[:1] == ["cold"]:  # started at once: find the cold loops here, and take share k of n
        k, n = (int(w) for w in (argv[1] if len(argv) > 1 else "0/1").split("/"))
        shares = shares_of(helper_order(cold_loops() or []), n)
        argv = [str(i) for i in shares[k]] if 0 <= k < len(shares) else []
    try:
        for word in argv:
            if _stopping or os.getppid() != parent:  # stopped, or the command was killed outright
                break
            i = int(word)
            compile_now = _dispatcher(i).compile  # unheld (see volreg._jit): SIGTERM ends the helper at once
            getattr(compile_now, "__wrapped__", compile_now)(argument_types(LOOPS[i][2]))
    except Exception:
        if not _stopping:  # a bug
            raise
    return 0


if __name__ == "__main__":
    # Ended without the interpreter's finalisation: nothing is left to flush, and a SIGTERM that
    # came during it would meet the default handler (exit status -15) or LLVM's finalisers.
    os._exit(_main(sys.argv[1:]))

"""volreg's threads: compiled loops split into parts, independent jobs side by side, one BLAS thread.

**Loops in parts.**  volreg's hot loops (kernel sums, sparse products, B-spline and distance
passes, the inverse's fixed point) are serial numba functions that release the GIL and take
two leading arguments, ``part`` and ``parts``: each covers the items
:func:`part_range` gives it of its outermost loop, and writes only those items' outputs.
:func:`run_parts` runs the parts of one call on the calling thread and on a pool of helper
threads that take the next part as they come free, so a part that takes longer than the
others does not hold the rest up.  numba's own parallel loops (``prange``) would compile each
body twice (the function and its parallel kernel); serial loops compile in about half the time,
and compiling is most of a first run's cost (:mod:`volreg.precompile`).

**Independent jobs** (the implicit-surface fits of several labels) run on :func:`thread_map`'s
threads; jobs that become ready one after another while other work goes on (the outputs'
writes, each as soon as its array exists) on a :class:`JobQueue`'s.  The loops they call
share the same helper pool.

**One BLAS thread.**  The OpenBLAS libraries that numpy and scipy bundle keep worker threads
of their own, which busy-wait for a while after each call (L-BFGS-B's vector operations
between two objective evaluations are such calls).  On a machine of few cores they take the
cores from the loops' threads, and a kernel sum that meets them waits for them.  volreg's own
BLAS work is small vector operations, which gain nothing from threads.

The number of threads is numba's (``NUMBA_NUM_THREADS``, by default the machine's cores;
``numba.set_num_threads`` lowers it for the calling thread).
"""

from __future__ import annotations

import itertools
import os
import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor, wait
from functools import wraps
from typing import Callable, Generator, Sequence, TypeVar

import numba
from threadpoolctl import threadpool_limits

from volreg._jit import njit

__all__ = ["JobQueue", "part_range", "query_workers", "run_parts", "single_blas", "thread_map"]

T = TypeVar("T")
R = TypeVar("R")

#: Parts per thread that :func:`run_parts` splits a loop into (more parts balance uneven work).
PARTS_PER_THREAD = 4


def single_blas(func):
    """Decorator: run ``func`` with BLAS limited to one thread (restored afterwards)."""

    @wraps(func)
    def wrapper(*args, **kwargs):
        with threadpool_limits(limits=1, user_api="blas"):
            return func(*args, **kwargs)

    return wrapper


@njit(inline="always")
def part_range(n, part, parts):  # pragma: no cover - compiled
    """The items ``[first, stop)`` of ``range(n)`` that part ``part`` of ``parts`` covers
    (contiguous, sizes differing by at most one)."""
    return n * part // parts, n * (part + 1) // parts


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        with _POOL_LOCK:
            if _POOL is None:
                _POOL = ThreadPoolExecutor(max_workers=max(numba.config.NUMBA_NUM_THREADS - 1, 1),
                                           thread_name_prefix="volreg-loop")
    return _POOL


def _forget_pool() -> None:  # a forked child has the pool object but none of its threads
    global _POOL
    _POOL = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


#: The loops :func:`run_parts` has called in this process (compiled or loaded by then).
_RUN_BEFORE: set = set()


def run_parts(loop: Callable, n: int, *args, grain: int = 1) -> None:
    """Run a compiled loop's parts (see the module notes) on the calling thread and the helpers.

    Parameters
    ----------
    loop : numba dispatcher
        Called as ``loop(part, parts, *args)`` for every ``part`` in ``range(parts)``; each
        call covers ``part_range(n', part, parts)`` of the loop's own outermost range ``n'``.
    n : int
        The length of that range (or an estimate).
    *args
        The loop's further arguments.
    grain : int
        The fewest items worth a part of their own (cheap items: a few hundred or more).

    Notes
    -----
    With ``t`` threads the loop is split into ``min(n // grain, PARTS_PER_THREAD * t)`` parts,
    taken in order by the calling thread and ``t - 1`` helpers; one part, on the calling thread
    alone, where that is one or ``t`` is 1.  A loop's first call in the process runs its first
    part on the calling thread before the helpers start (which compiles the loop there).
    Results do not depend on the split: each part writes its own items.  An error in any part
    is raised here once every part that started has ended.
    """
    threads = numba.get_num_threads()
    parts = min(int(n) // max(int(grain), 1), PARTS_PER_THREAD * threads)
    if threads < 2 or parts < 2:
        loop(0, 1, *args)
        return
    first = 0
    if loop not in _RUN_BEFORE:
        # A loop's first call compiles it or loads it from numba's cache: done here, alone.  A
        # helper compiling meanwhile waits for llvmlite's lock, which an interrupt caught inside
        # llvmlite's Python code can leave held by this thread (re-entrant for it alone): the
        # command then hung with the helper waiting and this thread waiting for the helper.
        loop(0, parts, *args)
        _RUN_BEFORE.add(loop)
        first = 1
    taken = itertools.count(first)

    def drain():
        for part in iter(taken.__next__, None):
            if part >= parts:
                return
            loop(part, parts, *args)

    pool = _pool()
    helpers = [pool.submit(drain) for _ in range(min(threads, parts) - 1)]
    try:
        drain()
    finally:
        started = [h for h in helpers if not h.cancel()]  # a helper not yet started has nothing left
        wait(started)
    for h in started:
        h.result()


_JOB = threading.local()  # .active: this thread runs thread_map's jobs


def _mark_job_thread() -> None:
    _JOB.active = True


def query_workers() -> int:
    """The thread count for library calls that take one (``workers`` of scipy's k-d tree
    queries): numba's, as for volreg's own loops; 1 inside :func:`thread_map`'s jobs, which
    already keep the threads busy (there, scipy's threads started per query cost the 100-label
    parcellation's implicit surfaces 11 %)."""
    return 1 if getattr(_JOB, "active", False) else numba.get_num_threads()


def thread_map(func: Callable[[T], R], items: Sequence[T], *, ahead: int | None = None) -> Generator[R, None, None]:
    """``map(func, items)`` on ``numba.get_num_threads()`` Python threads (in order).

    For independent jobs that release the GIL: compiled loops (the implicit-surface fits of
    several labels; the loops they run in parts share :func:`run_parts`' helpers) and library
    calls that do (scipy's distance transforms, zlib's compression, file writes).  Serial with
    one thread.  On an exception (a KeyboardInterrupt too) jobs not yet started are cancelled;
    running ones finish first.  A caller that may stop before the last result calls
    ``.close()`` on the generator to join the threads.

    Parameters
    ----------
    func : callable
    items : sequence
    ahead : int, optional
        At most this many jobs submitted and not yet yielded (at least the thread count), so
        that results waiting for an earlier one stay few (chunks of a large grid); default: all.
    """
    workers = min(numba.get_num_threads(), len(items))
    if workers <= 1:
        yield from map(func, items)
        return
    pool = ThreadPoolExecutor(max_workers=workers, initializer=_mark_job_thread)
    try:
        if ahead is None:
            yield from pool.map(func, items)
            return
        pending: deque = deque()
        queued = iter(items)
        for item in itertools.islice(queued, max(int(ahead), workers)):
            pending.append(pool.submit(func, item))
        while pending:
            result = pending.popleft().result()
            for item in itertools.islice(queued, 1):
                pending.append(pool.submit(func, item))
            yield result
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


class JobQueue:
    """Independent jobs run in the background as they are submitted, on ``numba.get_num_threads()``
    threads: for work that becomes ready while the calling thread goes on with other work (the
    outputs' writes, each as soon as its array exists, during the inverse and the metrics).

    With one thread, each job runs at once on the calling thread.  Jobs should release the
    GIL (compression, file writes, compiled loops) to overlap with the caller.  Use as a
    context manager: leaving it, on an exception too (a KeyboardInterrupt), cancels the jobs
    not yet started and waits for the running ones, so no job outlives the block.

    Examples
    --------
    >>> with JobQueue() as jobs:
    ...     jobs.submit(print, "written")
    ...     jobs.wait()
    written
    """

    def __init__(self) -> None:
        threads = numba.get_num_threads()
        self._pool = (ThreadPoolExecutor(max_workers=threads, initializer=_mark_job_thread,
                                         thread_name_prefix="volreg-job") if threads > 1 else None)
        self._futures: list = []

    def submit(self, func: Callable[..., R], *args) -> Future:
        """Run ``func(*args)`` in the background (at once, with one thread); its future."""
        if self._pool is None:
            future: Future = Future()
            future.set_result(func(*args))  # an error is raised here, at once
            return future
        future = self._pool.submit(func, *args)
        self._futures.append(future)
        return future

    def wait(self) -> None:
        """Wait for every submitted job; raise the first job's error (in submission order)."""
        futures, self._futures = self._futures, []
        wait(futures)
        for f in futures:
            f.result()

    def close(self) -> None:
        """Cancel the jobs not yet started and wait for the running ones (their errors are dropped:
        :meth:`wait` is where they are raised)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "JobQueue":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

"""One BLAS thread while volreg's compiled loops run.

volreg's hot loops (kernel sums, sparse products) are numba-parallel over all
cores.  The OpenBLAS libraries that numpy and scipy bundle keep worker threads
of their own, which busy-wait for a while after each call (L-BFGS-B's vector
operations between two objective evaluations are such calls).  On a 2-core
machine they took the cores from numba's threads, and a parallel loop then
waited for a scheduler time slice: on the 3 mm frog registration 332 of 3914
calls of one kernel sum took about 7 ms each instead of tens of microseconds,
and the whole registration took 8.3 s instead of 4.1 s with BLAS held to one
thread.  volreg's own BLAS work is small
vector operations, which gain nothing from threads.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import wraps
from typing import Callable, Generator, Sequence, TypeVar

import numba
from threadpoolctl import threadpool_limits

from volreg._jit import njit

__all__ = ["single_blas", "thread_map"]

T = TypeVar("T")
R = TypeVar("R")


def single_blas(func):
    """Decorator: run ``func`` with BLAS limited to one thread (restored afterwards)."""

    @wraps(func)
    def wrapper(*args, **kwargs):
        with threadpool_limits(limits=1, user_api="blas"):
            return func(*args, **kwargs)

    return wrapper


@njit(parallel=True)
def _touch(n):  # pragma: no cover - compiled
    total = 0
    for i in numba.prange(n):
        total += i
    return total


def _concurrent_numba() -> bool:
    """Whether numba's parallel loops may be entered from two Python threads at once: its
    OpenMP and TBB layers allow it, the fallback workqueue layer aborts the process."""
    _touch(2)  # the threading layer is chosen at the first parallel call
    return numba.threading_layer() in ("omp", "tbb")


def thread_map(func: Callable[[T], R], items: Sequence[T], *, parallel_loops: bool = True) -> Generator[R, None, None]:
    """``map(func, items)`` on ``numba.get_num_threads()`` Python threads (in order).

    For independent jobs that release the GIL: compiled loops (the implicit-surface fits
    of several labels), or with ``parallel_loops=False`` library calls that do (scipy's
    distance transforms, zlib's compression, file writes).  Serial with one numba thread,
    or, for jobs that run numba's parallel loops (``parallel_loops``, the default), where
    its threading layer does not allow them concurrently.  On an exception (a
    KeyboardInterrupt too) jobs not yet started are cancelled; running ones finish first.
    A caller that may stop before the last result calls ``.close()`` on the generator to
    join the threads.
    """
    workers = min(numba.get_num_threads(), len(items))
    if workers <= 1 or (parallel_loops and not _concurrent_numba()):
        yield from map(func, items)
        return
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        yield from pool.map(func, items)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)

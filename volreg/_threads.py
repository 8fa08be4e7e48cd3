"""One BLAS thread while volreg's compiled loops run.

volreg's hot loops (kernel sums, sparse products) are numba-parallel over all
cores.  The OpenBLAS libraries that numpy and scipy bundle keep worker threads
of their own, which busy-wait for a while after each call (L-BFGS-B's vector
operations between two objective evaluations are such calls).  On a 2-core
machine they took the cores from numba's threads, and a parallel loop then
waited for a scheduler time slice: on the 3 mm frog registration 332 of 3914
calls of one kernel sum took about 7 ms each instead of tens of microseconds,
and the whole registration took 8.3 s instead of 4.1 s with BLAS held to one
thread (BENCHMARKS.md, "BLAS threads").  volreg's own BLAS work is small
vector operations, which gain nothing from threads.
"""

from __future__ import annotations

from functools import wraps

from threadpoolctl import threadpool_limits

__all__ = ["single_blas"]


def single_blas(func):
    """Decorator: run ``func`` with BLAS limited to one thread (restored afterwards)."""

    @wraps(func)
    def wrapper(*args, **kwargs):
        with threadpool_limits(limits=1, user_api="blas"):
            return func(*args, **kwargs)

    return wrapper

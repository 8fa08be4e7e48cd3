"""BLAS held to one thread inside volreg's entry points, and independent fits on threads
(volreg/_threads.py)."""

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from volreg._threads import _concurrent_numba, single_blas, thread_map
from volreg.features.implicit import ImplicitSurface
from volreg.warp.field import fields_on_grid
from volreg.warp.fit import fit_warp
from volreg.register import register_labels, register_surfaces
from volreg.features.label_surfaces import implicit_surfaces


def _blas_threads() -> list[int]:
    np.dot(np.ones(4), np.ones(4))  # make sure numpy's BLAS is loaded
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_single_blas_limits_inside_and_restores_after():
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        assert before and max(before) == 2  # the limit we set, so the check below can fail
        inside = single_blas(_blas_threads)()
        assert inside == [1] * len(before)
        assert _blas_threads() == before


def test_single_blas_passes_results_and_errors_through():
    assert single_blas(lambda a, *, b: a + b)(1, b=2) == 3

    def boom():
        raise ValueError("bad `x`")

    with threadpool_limits(limits=2, user_api="blas"):
        with pytest.raises(ValueError, match="bad `x`"):
            single_blas(boom)()
        assert max(_blas_threads()) == 2


@pytest.mark.parametrize("func", [register_labels, register_surfaces, fit_warp, fields_on_grid, implicit_surfaces])
def test_entry_points_run_with_one_blas_thread(func):
    assert callable(func.__wrapped__)  # functools.wraps of the wrapper below
    assert func.__code__ is single_blas(lambda: None).__code__


def test_thread_map_keeps_the_order_and_raises_a_jobs_error():
    assert list(thread_map(lambda i: i * i, list(range(25)))) == [i * i for i in range(25)]
    partial = thread_map(lambda i: i + 1, list(range(25)))
    assert next(partial) == 1
    partial.close()  # stops early: the remaining jobs are cancelled, the threads joined

    def boom(i):
        if i == 3:
            raise ValueError("bad `x`")
        return i

    with pytest.raises(ValueError, match="bad `x`"):
        list(thread_map(boom, list(range(8))))


def test_implicit_fits_on_threads_equal_serial_fits():
    """The labels' implicit surfaces are fitted on numba's threads in register_labels: the
    same fits as one after another, to the bit."""
    import numba
    from shapes import Ellipsoid

    rng = np.random.default_rng(0)
    shapes = [Ellipsoid((20, 14, 10), (0, 0, 0)), Ellipsoid((8, 8, 12), (5, -3, 2)), Ellipsoid((15, 6, 6), (0, 9, 0))]
    jobs = [s.surface_points(1500, rng) for s in shapes]

    def fit(job):
        return ImplicitSurface(*job, min_width=3.0)

    if numba.get_num_threads() < 2 or not _concurrent_numba():
        pytest.skip("thread_map is serial here (one numba thread, or numba's workqueue layer)")
    threaded = list(thread_map(fit, jobs))
    for a, b in zip(threaded, map(fit, jobs)):
        assert len(a.levels) == len(b.levels) > 1
        for la, lb in zip(a.levels, b.levels):
            np.testing.assert_array_equal(la.alpha, lb.alpha)
            np.testing.assert_array_equal(la.centres, lb.centres)


@pytest.mark.parametrize("preset, expected", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_idle_openmp_threads_sleep_unless_the_user_says_otherwise(preset, expected):
    """numba's OpenMP runtime reads OMP_WAIT_POLICY when its first parallel loop loads it;
    volreg sets it to PASSIVE before that (a user's value is kept)."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if preset is not None:
        env["OMP_WAIT_POLICY"] = preset
    code = ("import os, numpy as np; from volreg.kernels import kernel_sum; import numba; "
            "print(os.environ.get('OMP_WAIT_POLICY'))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == expected


def test_jobs_without_parallel_loops_run_concurrently_whatever_numbas_threading_layer():
    """Two jobs that each wait for the other finish only when they run at the same time
    (the distance transforms of the label scores, the writes of the outputs)."""
    import threading

    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("one numba thread: thread_map is serial")
    barrier = threading.Barrier(2, timeout=20)
    assert list(thread_map(lambda i: (barrier.wait(), i)[1], [0, 1], parallel_loops=False)) == [0, 1]


def test_label_scores_on_threads_equal_one_label_at_a_time():
    from volreg.evaluation.metrics import label_scores

    rng = np.random.default_rng(1)
    a = rng.integers(0, 4, (18, 16, 14))
    b = np.where(rng.random(a.shape) < 0.2, rng.integers(0, 4, a.shape), a)
    spacing = np.array([1.0, 1.5, 2.0])
    together = label_scores(a, b, [1, 2, 3], spacing)
    assert list(together) == [1, 2, 3]
    for v in (1, 2, 3):
        assert together[v] == label_scores(a, b, [v], spacing)[v]
        assert 0 < together[v]["dice"] < 1 and together[v]["hd95_mm"] > 0


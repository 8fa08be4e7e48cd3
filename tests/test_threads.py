"""BLAS held to one thread inside volreg's entry points, and independent fits on threads
(volreg/_threads.py)."""

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from volreg._threads import JobQueue, run_parts, single_blas, thread_map
from volreg.features.implicit import ImplicitSurface
from volreg.warp.field import fields_on_grid
from volreg.warp.fit import fit_warp
from volreg.pipeline.labels import register_labels
from volreg.pipeline.surfaces import register_surfaces
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


def test_thread_map_ahead_keeps_the_order_and_few_results_waiting():
    """With ``ahead``, at most that many jobs are submitted and not yet yielded, and the results
    come in order even when a later job ends first."""
    import threading
    import time

    lock = threading.Lock()
    started, yielded, most = [0], [0], [0]

    def job(i):
        with lock:
            started[0] += 1
            most[0] = max(most[0], started[0] - yielded[0])
        time.sleep(0.02 if i % 3 == 0 else 0.001)
        return i * i

    out = []
    for value in thread_map(job, list(range(30)), ahead=4):
        out.append(value)
        with lock:
            yielded[0] += 1
    assert out == [i * i for i in range(30)]
    assert 1 <= most[0] <= 4, most[0]


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

    if numba.get_num_threads() < 2:
        pytest.skip("thread_map is serial here (one thread)")
    threaded = list(thread_map(fit, jobs))
    for a, b in zip(threaded, map(fit, jobs)):
        assert len(a.levels) == len(b.levels) > 1
        for la, lb in zip(a.levels, b.levels):
            np.testing.assert_array_equal(la.alpha, lb.alpha)
            np.testing.assert_array_equal(la.centres, lb.centres)


def test_jobs_run_concurrently():
    """Two jobs that each wait for the other finish only when they run at the same time
    (the distance transforms of the label scores, the writes of the outputs)."""
    import threading

    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("one numba thread: thread_map is serial")
    barrier = threading.Barrier(2, timeout=20)
    assert list(thread_map(lambda i: (barrier.wait(), i)[1], [0, 1])) == [0, 1]


def test_job_queue_runs_jobs_beside_the_caller_and_raises_the_first_error():
    """Submitted jobs run while the caller goes on (the outputs' writes during the inverse):
    a job and the caller that each wait for the other both get through; wait() raises the
    first failed job's error, in submission order."""
    import threading

    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("one numba thread: the queue runs each job at once")
    barrier = threading.Barrier(2, timeout=20)
    done = []
    with JobQueue() as jobs:
        jobs.submit(lambda: done.append(barrier.wait() is not None))
        barrier.wait()  # the caller meets the job: it runs in the background
        jobs.wait()
    assert done == [True]

    def fail(message):
        raise ValueError(message)

    with JobQueue() as jobs:
        jobs.submit(done.append, "fine")
        jobs.submit(fail, "bad `first`")
        jobs.submit(fail, "bad `second`")
        with pytest.raises(ValueError, match="first"):
            jobs.wait()
    assert done[-1] == "fine"


def test_job_queue_leaves_no_job_running_after_its_block():
    """Leaving the block on an error waits for the running job and cancels those not started,
    so nothing writes after the caller has cleaned up."""
    import threading
    import time

    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("one numba thread: the queue runs each job at once")
    ran, release = [], threading.Event()

    def slow(name):
        release.wait(20)
        time.sleep(0.05)
        ran.append(name)

    with pytest.raises(KeyboardInterrupt):
        with JobQueue() as jobs:
            for i in range(numba.get_num_threads() + 3):
                jobs.submit(slow, i)
            release.set()
            raise KeyboardInterrupt
    count = len(ran)
    assert 1 <= count < numba.get_num_threads() + 3  # the running ones ended, the rest were cancelled
    time.sleep(0.2)
    assert len(ran) == count  # and nothing ran afterwards


def test_job_queue_with_one_thread_runs_each_job_at_once_on_the_caller():
    import threading

    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        where = []
        with JobQueue() as jobs:
            jobs.submit(lambda: where.append(threading.get_ident()))
            assert where == [threading.get_ident()]  # already run, here
            jobs.wait()
    finally:
        numba.set_num_threads(threads)


@pytest.mark.parametrize("threads", [1, 2], ids=["one-thread", "two-threads"])
def test_job_queue_gives_each_jobs_result(threads):
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        with JobQueue() as jobs:
            futures = [jobs.submit(pow, 2, k) for k in range(5)]
            assert [f.result() for f in futures] == [1, 2, 4, 8, 16]
            jobs.wait()
    finally:
        numba.set_num_threads(before)


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



def test_part_ranges_cover_each_item_once_in_order():
    from volreg._threads import part_range

    for n in (0, 1, 5, 31, 1000):
        for parts in (1, 2, 3, 8, 40):
            ranges = [part_range.py_func(n, p, parts) for p in range(parts)]
            assert ranges[0][0] == 0 and ranges[-1][1] == n
            assert all(a[1] == b[0] for a, b in zip(ranges, ranges[1:]))
            sizes = [stop - first for first, stop in ranges]
            assert max(sizes) - min(sizes) <= 1


def _counting_loop():
    import numba

    from volreg._threads import part_range

    @numba.njit(nogil=True)
    def count(part, parts, hits, seen):
        first, stop = part_range(len(hits), part, parts)
        for i in range(first, stop):
            hits[i] += 1
        seen[part] = parts

    return count


@pytest.mark.parametrize("n, grain", [(1, 1), (7, 1), (1000, 1), (1000, 300), (1000, 5000)])
def test_run_parts_runs_every_item_once(n, grain):
    import numba

    from volreg._threads import PARTS_PER_THREAD

    count = _counting_loop()
    hits = np.zeros(n, np.int64)
    seen = np.zeros(64, np.int64)
    run_parts(count, n, hits, seen, grain=grain)
    assert np.all(hits == 1)
    parts = seen[0]
    expected = max(min(n // grain, PARTS_PER_THREAD * numba.get_num_threads()), 1)
    if numba.get_num_threads() < 2 or expected < 2:
        expected = 1
    assert parts == expected
    assert np.all(seen[:parts] == parts) and np.all(seen[parts:] == 0)


def test_run_parts_on_one_thread_is_one_part_on_the_caller():
    import threading

    import numba

    callers = []

    def loop(part, parts, out):
        callers.append(threading.get_ident())
        out[part] = parts

    out = np.zeros(4, np.int64)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        run_parts(loop, 1000, out)
    finally:
        numba.set_num_threads(threads)
    assert out.tolist() == [1, 0, 0, 0] and callers == [threading.get_ident()]


def test_a_loops_first_call_runs_its_first_part_alone_on_the_caller():
    """The first call of a loop runs part 0 on the calling thread before any helper starts (the
    call that compiles the loop, so that no helper waits for llvmlite's lock meanwhile); later
    calls share the parts from the start.  Every part runs once either way."""
    import threading

    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("one thread: a single part")
    events = []
    lock = threading.Lock()

    def loop(part, parts, out):
        with lock:
            events.append(("start", part, threading.get_ident()))
        out[part] += 1
        with lock:
            events.append(("end", part, threading.get_ident()))

    for call in range(2):
        events.clear()
        out = np.zeros(64, np.int64)
        run_parts(loop, 1000, out)
        parts = sum(1 for e in events if e[0] == "start")
        assert parts >= 2 and np.all(out[:parts] == 1) and not out[parts:].any()
        if call == 0:
            assert events[:2] == [("start", 0, threading.get_ident()), ("end", 0, threading.get_ident())]


def test_run_parts_raises_a_parts_error_after_every_started_part_ended():
    import threading
    import time

    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("one thread: a single part")
    ended = []
    lock = threading.Lock()

    def loop(part, parts, out):
        if part == 1:
            raise ValueError("bad part")
        time.sleep(0.05)
        with lock:
            ended.append(part)

    with pytest.raises(ValueError, match="bad part"):
        run_parts(loop, 100, None)
    n_ended = len(ended)
    time.sleep(0.3)
    assert len(ended) == n_ended  # nothing still running once the error was raised


def test_kernel_sums_in_parts_equal_one_part_to_the_bit():
    import numba

    from volreg.kernels import kernel_sum

    rng = np.random.default_rng(3)
    centres = rng.uniform(-20, 20, (3000, 3))
    coef = rng.normal(size=(3000, 3))
    queries = rng.uniform(-22, 22, (20000, 3))
    threads = numba.get_num_threads()
    together = kernel_sum(queries, centres, coef, 6.0, order=1)
    numba.set_num_threads(1)
    try:
        alone = kernel_sum(queries, centres, coef, 6.0, order=1)
    finally:
        numba.set_num_threads(threads)
    for a, b in zip(together, alone):
        np.testing.assert_array_equal(a, b)


def test_library_queries_use_volregs_thread_count():
    import numba

    from volreg._threads import query_workers

    threads = numba.get_num_threads()
    assert query_workers() == threads
    if threads >= 2:  # thread_map's jobs run side by side already: one worker each
        assert list(thread_map(lambda _: query_workers(), [0, 1])) == [1, 1]
    numba.set_num_threads(1)
    try:
        assert query_workers() == 1
    finally:
        numba.set_num_threads(threads)

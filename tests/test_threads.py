"""BLAS held to one thread inside volreg's entry points (volreg/_threads.py)."""

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from volreg._threads import single_blas
from volreg.field import fields_on_grid
from volreg.pipeline import fit_warp, register_labels, register_surfaces
from volreg.surfaces import implicit_surfaces


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

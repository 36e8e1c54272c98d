"""Every executor computes with one BLAS thread, so a step gives the same bytes on any of them: a
diagnosis' verdict at a threshold followed the thread count before the serial executor did too."""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

from cpas_bayes.core.executor import Executor, make_executor


def _blas_threads():
    return sorted({p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"})


def test_the_serial_executor_of_make_executor_holds_blas_at_one_thread_until_closed():
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        with make_executor(1) as ex:
            assert _blas_threads() == [1]
            assert np.allclose(ex.map(np.linalg.det, [np.eye(3) * 2.0]), [8.0])
        assert _blas_threads() == before


def test_a_bare_executor_leaves_the_callers_threads_alone():
    # a library default (fit_model without an executor) must not change a notebook's BLAS for good
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        ex = Executor()
        assert _blas_threads() == before
        ex.close()

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


def _slow_square(x):
    import time

    time.sleep(0.05 * x)
    return x * x


def test_a_task_clock_returns_what_its_executor_returns_and_times_each_task():
    from cpas_bayes.core.task_clock import TaskClock

    with make_executor(1) as inner:
        clock = TaskClock(inner)
        assert clock.map(_slow_square, [1, 3, 2]) == [1, 9, 4]
        handle = clock.submit(_slow_square, 2)
        assert handle.result() == 4 and handle.result() == 4
        assert clock.workers == inner.workers and clock.describe() == inner.describe()
    assert len(clock.seconds) == 4
    assert all(0.05 * x <= s < 0.05 * x + 0.2 for x, s in zip([1, 3, 2, 2], clock.seconds))

"""Life in a worker process of a local pool (:class:`cpas_bayes.core.executor.ProcessExecutor`): one BLAS
thread, messages to the parent through a queue, and an end as soon as the process that started the pool
goes (SIGTERM, the parent-death signal, or a watch on the owner's pid), its temporary files removed."""

from __future__ import annotations

import os
import signal
import sys
import time

_BLAS_LIMIT = None  # keeps the threadpoolctl limiter alive in a worker
_IN_WORKER = False  # set in worker processes: tasks started from a task run in it, one after another


def limit_blas_threads():
    """One BLAS/OpenMP/numba thread in this process (called in every worker)."""
    global _BLAS_LIMIT, _IN_WORKER
    _IN_WORKER = True
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    import numba
    from threadpoolctl import threadpool_limits

    _BLAS_LIMIT = threadpool_limits(limits=1)
    numba.set_num_threads(1)  # the Monte Carlo kernel's prange: the workers are the parallelism


_REPORTS = None  # in a pool worker: the queue that carries tasks' messages to the parent
_REMOVE_TEMPORARIES = None  # in a pool worker: core.files.remove_temporaries, loaded before any signal comes


def _end_worker(code):
    """End this worker now: its temporary files removed, no clean-up of anything else (no orphan writes).

    A second signal may arrive while this runs (SIGTERM from the parent and the
    parent-death signal at once); whatever it raises, the process ends.
    """
    try:
        if _REMOVE_TEMPORARIES is not None:
            _REMOVE_TEMPORARIES()
    finally:
        os._exit(code)


def _on_sigterm(signum, frame):
    _end_worker(128 + signum)


def _set_parent_death_signal(sig):
    """Linux: the kernel sends ``sig`` to this process when its parent ends. Returns whether it is set."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_process(pid, interval=0.5):
    """A daemon thread that ends this worker as soon as process ``pid`` (the one that started the pool) ends."""
    import threading

    try:
        handle = os.pidfd_open(pid)  # Linux ≥ 5.3: readable once the process has ended; no pid reuse race
    except ProcessLookupError:
        _end_worker(1)
    except (AttributeError, OSError):
        handle = None

    def alive():
        try:
            os.kill(pid, 0)
            return True
        except ProcessLookupError:
            return False
        except PermissionError:
            return True

    def watch():
        if handle is not None:
            import select

            select.select([handle], [], [])
        else:
            while alive():
                time.sleep(interval)
        _end_worker(1)

    threading.Thread(target=watch, name="cpas-bayes-parent-watch", daemon=True).start()


def init_worker(reports, owner_pid=None):
    global _REPORTS, _REMOVE_TEMPORARIES
    from cpas_bayes.core.files import remove_temporaries

    _REPORTS, _REMOVE_TEMPORARIES = reports, remove_temporaries
    # The parent handles Ctrl-C and terminates the pool; workers must not die mid-write on it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_sigterm)
    _set_parent_death_signal(signal.SIGTERM)  # the fork server (or, with spawn, the owner) ending
    if owner_pid is not None:
        _watch_process(owner_pid)  # the owner ending (the fork server outlives it while workers run)
    # A worker starts no processes. Under a fork-like default numba guards its thread pool's start with a named
    # semaphore, which a worker ended by SIGTERM (Ctrl-C in the parent) cannot unlink: the resource tracker
    # then reported "2 leaked semaphore objects" after every interrupted fit.
    import multiprocessing

    multiprocessing.set_start_method("spawn", force=True)
    limit_blas_threads()


def call_reporting(args):
    """Run one task in a pool worker; its messages, then an end marker, go through the worker's queue."""
    fn, item, index = args
    if index is None:
        return fn(item)
    try:
        return fn(item, lambda *message: _REPORTS.put((index, message)))
    finally:
        _REPORTS.put((index, None))  # after every message of this task (one queue, first in first out)


def in_worker() -> bool:
    """True inside a task of a process pool or a Dask worker."""
    import multiprocessing as mp

    if _IN_WORKER or mp.current_process().daemon:
        return True
    if "distributed" in sys.modules:
        try:
            sys.modules["distributed"].get_worker()
            return True
        except ValueError:
            return False
    return False

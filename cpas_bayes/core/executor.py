"""Where independent tasks run: in this process, a local process pool, or a Dask cluster.

One small interface serves every parallel step of the package (a fit's
ensembles, a diagnosis' candidates, a campaign's tests, Monte Carlo batches)::

    with make_executor(workers=4) as ex:                      # local processes
    with make_executor(workers=4, scheduler="local") as ex:   # a Dask LocalCluster
    with make_executor(scheduler="tcp://host:8786") as ex:    # a running Dask scheduler
        results = ex.map(task, items)
        pairs = ex.map_chained(first, then, items)   # then((item, first(item))) once first is done
        later = ex.submit(task, item)    # starts now (in this process: when asked)
        ...                              # other work here meanwhile
        result = later.result()

``map`` returns the results in the order of ``items`` whatever order they
finished in, and every task carries its own seed, so a step gives the same
bytes on any executor and any number of workers. Each worker runs one BLAS
thread: the tasks are the parallelism, and a multi-threaded BLAS could change
the last bits of a sum from one machine load to the next.

Tasks are top-level functions of ``cpas_bayes`` taking one picklable item. A
task that reports progress takes a second argument ``report`` (a callable, or
None where the executor cannot carry messages back, as on Dask); ``map(...,
on_report=f)`` calls ``f(*message)`` in the calling process for each one.

Ctrl-C stops the workers at once and raises ``KeyboardInterrupt`` in the
caller; every task writes its outputs atomically and checkpoints as it goes,
so rerunning the same command resumes.

Workers die with the process that started them, however it ends (even
SIGKILL, which runs no clean-up): each worker watches that process (a pidfd
on Linux, a poll elsewhere) and asks the kernel for SIGTERM when its own
parent, the fork server, goes (``PR_SET_PDEATHSIG``). On SIGTERM a worker
removes the temporary files of its writes under way and exits at once, so no
orphan goes on writing checkpoints beside a rerun.
Limits checked before any work (by the command line and campaign configs):
at most ``MAX_LOCAL_WORKERS`` local processes (twice this machine's cores,
at least 4: the tasks are compute-bound, and every worker holds its own copy
of the numerical libraries and the task's data), and a Dask scheduler address
must answer a TCP connection within ``CONNECT_TIMEOUT`` seconds
(:func:`cpas_bayes.core.scheduler_address.scheduler_problem`).
"""

from __future__ import annotations

import logging
import os
import sys
import time

from cpas_bayes.core.interrupts import raise_if_requested
from cpas_bayes.core.scheduler_address import CONNECT_TIMEOUT, SCHEDULER_FIX
from cpas_bayes.core.worker_process import call_reporting, in_worker, init_worker, limit_blas_threads


def _cores():
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


MAX_LOCAL_WORKERS = max(4, 2 * _cores())

class _OneThreadHere:
    """One BLAS and numba thread in *this* process while local workers share its cores.

    The caller keeps working while the pool runs (a fit's MAP search while the
    workers start, the ESS checks between chunks): with a multi-threaded BLAS
    beside busy workers the threads oversubscribe the cores, and OpenBLAS's
    spin-waiting threads then stall. Measured on 2 cores: the two-Drogue MAP
    search took 4.4 s beside one busy process with BLAS's default 2 threads,
    1.65 s with one (1.4 s alone).

    ``numba=False``: BLAS alone, numba's threads (and OpenMP's) left as they are (the serial
    executor's, :class:`Executor`).
    """

    def __init__(self, numba=True):
        from threadpoolctl import threadpool_limits

        self._limits = threadpool_limits(limits=1, user_api=None if numba else "blas")
        self._numba = None
        if numba and "numba" in sys.modules:
            import numba

            self._numba = numba.get_num_threads()
            numba.set_num_threads(1)

    def restore(self):
        if self._limits is not None:
            self._limits.restore_original_limits()
            self._limits = None
        if self._numba is not None:
            import numba

            numba.set_num_threads(self._numba)
            self._numba = None


def _progress_bar(total, desc, progress):
    from tqdm import tqdm

    show = sys.stderr.isatty() if progress is None else bool(progress)
    return tqdm(total=total, desc=desc, unit="task", disable=not show or total <= 1, leave=False)


class Executor:
    """Runs tasks one after another in this process (the reference the others must match).

    ``one_blas_thread``: BLAS runs one thread in this process until :meth:`close`, as it does in every
    worker of a pool and, while a pool runs, in its caller (:class:`_OneThreadHere`). A multi-threaded
    BLAS sums in another order, and a verdict at a threshold followed the thread count: a diagnosis
    named a term (gain 10.3) with one thread and not (9.8, under the rule's 10) with two.
    :func:`make_executor` sets it; numba's threads are left as they are (the Monte Carlo kernel's
    parallelism when it runs here).
    """

    kind = "serial"
    workers = 1

    def __init__(self, one_blas_thread=False):
        self._blas = _OneThreadHere(numba=False) if one_blas_thread else None

    def map(self, fn, items, desc="tasks", progress=None, on_report=None):
        """``[fn(item) for item in items]``, with ``fn(item, report)`` when ``on_report`` is given."""
        items = list(items)
        out = []
        with _progress_bar(len(items), desc, progress) as bar:
            for item in items:
                raise_if_requested()
                out.append(fn(item, on_report) if on_report is not None else fn(item))
                bar.update(1)
        return out

    def map_chained(self, first, then, items, costs=None, desc="tasks", progress=None, on_report=None):
        """``[(a, then((item, a))) for item in items]`` with ``a = first(item)``: two tasks per item, the
        second started once its item's first is done and given its result (``report`` as in :meth:`map`).
        ``then`` may be a tuple of such tasks, in order of priority: ``(a, b, c, ...)`` per item.

        On workers every ``first`` is handed out, costliest first (``costs``, stable among equals), before
        any later task; then the ready tasks of ``then[0]``, costliest first, before any of ``then[1]``, and
        so on. A phase of whole items ends on one worker finishing the last item while the rest idle; split,
        it ends on the later tasks, and small tasks of low priority (figures) fill the workers that the last
        large ones leave idle. Here: item after item, its tasks in order.
        """
        thens = _later_tasks(then)
        items = list(items)
        out = []
        call = (lambda fn, x: fn(x, on_report)) if on_report is not None else (lambda fn, x: fn(x))
        with _progress_bar((1 + len(thens)) * len(items), desc, progress) as bar:
            for item in items:
                raise_if_requested()
                row = [call(first, item)]
                bar.update(1)
                for fn in thens:
                    raise_if_requested()
                    row.append(call(fn, (item, row[0])))
                    bar.update(1)
                out.append(tuple(row))
        return out

    def _chained_on_workers(self, launch, wait_a_little, first, then, items, costs, bar):
        """The dispatch of :meth:`map_chained` on ``self.workers`` workers; ``launch(fn, item, index)`` starts a
        task and returns its future (``done()``, ``result()``), ``wait_a_little()`` idles briefly."""
        thens = _later_tasks(then)
        n, width = len(items), 1 + len(thens)
        costs = [1.0] * n if costs is None else [float(c) for c in costs]
        firsts = sorted(range(n), key=lambda i: -costs[i])[::-1]   # popped from the end: costliest first
        ready = [[] for _ in thens]          # per later task: the items whose first is done, in that order
        running, results = {}, [[None] * width for _ in range(n)]
        while firsts or any(ready) or running:
            while len(running) < self.workers and (firsts or any(ready)):
                if firsts:
                    i = firsts.pop()
                    running[launch(first, items[i], width * i)] = (0, i)
                else:
                    k = next(k for k, r in enumerate(ready) if r)
                    i = max(ready[k], key=lambda j: costs[j])   # the first ready among equals
                    ready[k].remove(i)
                    running[launch(thens[k], (items[i], results[i][0]), width * i + 1 + k)] = (1 + k, i)
            finished = [f for f in running if f.done()]
            if not finished:
                wait_a_little()
                raise_if_requested()
                continue
            for f in finished:
                stage, i = running.pop(f)
                results[i][stage] = f.result()   # a task's error stops the map here
                if stage == 0:
                    for r in ready:
                        r.append(i)
                bar.update(1)
        return [tuple(r) for r in results]

    def submit(self, fn, item):
        """Start ``fn(item)`` and return a handle whose ``result()`` waits for it. Here the task runs
        when ``result()`` is first called, so work done meanwhile in this process comes first."""
        return _Deferred(fn, item)

    def describe(self):
        return "this process"

    def close(self):
        if self._blas is not None:
            self._blas.restore()
            self._blas = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _later_tasks(then):
    """``map_chained``'s ``then``, one task or a tuple of them, as a tuple."""
    return tuple(then) if isinstance(then, (tuple, list)) else (then,)


def _task_count(then, items):
    return (1 + len(_later_tasks(then))) * len(items)


class _Deferred:
    """A task of the serial executor: run on the first ``result()``."""

    def __init__(self, fn, item):
        self._fn, self._item, self._done, self._value = fn, item, False, None

    def result(self):
        if not self._done:
            raise_if_requested()
            self._value, self._done, self._item = self._fn(self._item), True, None
        return self._value


class _Pending:
    """A task submitted to a pool or cluster: ``result()`` waits in short steps, so that Ctrl-C stays
    responsive (:mod:`cpas_bayes.core.interrupts`); on an interrupt or error it calls ``on_failure``."""

    def __init__(self, future, on_failure):
        self._future, self._on_failure = future, on_failure

    def result(self):
        try:
            while True:
                raise_if_requested()
                try:
                    return self._future.result(timeout=0.1)
                except TimeoutError:
                    continue
        except BaseException:
            self._on_failure(self._future)
            raise


def _call_without_reports(args):
    fn, item = args
    return fn(item, None)


# imported by the fork server beside the tasks' modules: numba started once there, not in every worker
_NUMBA_START = "cpas_bayes.core.numba_start"


def start_worker_server(modules):
    """Start the fork server of local workers now, importing ``modules`` (names) in it.

    For a program that knows what its workers will run before it imports it itself
    (:mod:`cpas_bayes.app.entry`): the server's imports then overlap the program's own. A pool made
    later uses this server (its own preload list is ignored once the server runs). Nothing where
    the platform has no fork server (spawned workers import on their own).
    """
    import multiprocessing as mp

    if "forkserver" not in mp.get_all_start_methods():
        return
    from multiprocessing import forkserver

    mp.get_context("forkserver").set_forkserver_preload(sorted(set(modules) | {_NUMBA_START}))
    forkserver.ensure_running()


class ProcessExecutor(Executor):
    """A local pool of ``workers`` processes.

    Workers are forked from a fork server that has imported the package but
    run nothing (plain fork is unsafe here: the Monte Carlo kernel starts
    OpenMP threads, and a process forked after that aborts). A worker that
    dies (killed, out of memory) fails the map with an error instead of
    hanging it.
    """

    kind = "processes"

    def __init__(self, workers):
        import multiprocessing as mp

        if workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        self.workers = int(workers)
        if "forkserver" in mp.get_all_start_methods():
            from multiprocessing import forkserver

            self._ctx = mp.get_context("forkserver")
            # The server imports what the caller has imported of the package (the tasks' modules and
            # their numerical libraries), so that workers start warm without this layer naming them;
            # unless it was started earlier (start_worker_server), with the modules the program named.
            self._ctx.set_forkserver_preload(sorted({m for m in sys.modules if m.startswith("cpas_bayes.")
                                                     and not m.endswith("__main__")} | {_NUMBA_START}))
            # Start the server now: its imports (~2 s) overlap the caller's work until the first map.
            forkserver.ensure_running()
        else:
            self._ctx = mp.get_context("spawn")
        self._pool = None
        self._reports = None
        self._not_ours = set()
        self._threads = _OneThreadHere()

    def _ensure_pool(self):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        if self._pool is None:
            self._not_ours = set(mp.active_children())
            self._reports = self._ctx.Queue()
            self._pool = ProcessPoolExecutor(self.workers, mp_context=self._ctx, initializer=init_worker,
                                             initargs=(self._reports, os.getpid()))
        return self._pool

    def _drain(self, on_report, open_tasks, timeout=0.0):
        import queue

        while True:
            try:
                index, message = self._reports.get(timeout=timeout) if timeout else self._reports.get_nowait()
            except queue.Empty:
                return
            if message is None:
                open_tasks.discard(index)
            else:
                on_report(*message)

    def _drain_to_the_end(self, on_report, open_tasks):
        while open_tasks:  # the last messages may still be in the queue's pipe
            self._drain(on_report, open_tasks, timeout=1.0)

    def _stop(self, futures):
        """Ctrl-C or a failed task: stop the rest now; their checkpoints are complete files."""
        for f in futures:
            f.cancel()
        self._terminate()

    def map(self, fn, items, desc="tasks", progress=None, on_report=None):
        from concurrent.futures import FIRST_EXCEPTION, wait

        items = list(items)
        if not items:
            return []
        pool = self._ensure_pool()
        reporting = on_report is not None
        futures = []
        try:
            futures = [pool.submit(call_reporting, (fn, item, i if reporting else None))
                       for i, item in enumerate(items)]
            open_tasks = set(range(len(items))) if reporting else set()
            with _progress_bar(len(items), desc, progress) as bar:
                done = 0
                while done < len(futures):
                    # a short wait keeps Ctrl-C and the messages responsive
                    finished, _ = wait(futures, timeout=0.2, return_when=FIRST_EXCEPTION)
                    raise_if_requested()
                    if reporting:
                        self._drain(on_report, open_tasks)
                    if any(f.exception() is not None for f in finished):
                        break
                    bar.update(len(finished) - done)
                    done = len(finished)
            results = [f.result() for f in futures]
            self._drain_to_the_end(on_report, open_tasks)
            return results
        except BaseException:
            self._stop(futures)
            raise

    def map_chained(self, first, then, items, costs=None, desc="tasks", progress=None, on_report=None):
        items = list(items)
        pool = self._ensure_pool()
        reporting = on_report is not None
        open_tasks, launched = set(), []

        def launch(fn, item, index):
            if reporting:
                open_tasks.add(index)
            launched.append(pool.submit(call_reporting, (fn, item, index if reporting else None)))
            return launched[-1]

        def wait_a_little():
            if reporting:
                self._drain(on_report, open_tasks, timeout=0.05)
            else:
                time.sleep(0.05)
        try:
            with _progress_bar(_task_count(then, items), desc, progress) as bar:
                results = self._chained_on_workers(launch, wait_a_little, first, then, items, costs, bar)
            self._drain_to_the_end(on_report, open_tasks)
            return results
        except BaseException:
            self._stop(launched)
            raise

    map_chained.__doc__ = Executor.map_chained.__doc__

    def submit(self, fn, item):
        """Start ``fn(item)`` on a worker now; ``result()`` of the handle waits for it (Ctrl-C or a failure
        stops the pool, as in :meth:`map`)."""
        future = self._ensure_pool().submit(call_reporting, (fn, item, None))
        return _Pending(future, lambda f: (f.cancel(), self._terminate()))

    def _terminate(self):
        import multiprocessing as mp

        if self._pool is None:
            return
        workers = [p for p in mp.active_children() if p not in self._not_ours]
        for p in workers:
            p.terminate()
        self._pool.shutdown(wait=True, cancel_futures=True)
        for p in workers:
            p.join()
        self._pool = None

    def describe(self):
        return f"{self.workers} local processes"

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self._reports is not None:
            self._reports.close()
            self._reports.join_thread()
            self._reports = None
        self._threads.restore()


class DaskExecutor(Executor):
    """Tasks on a Dask distributed cluster: a running scheduler (``address``) or a LocalCluster.

    Workers of a remote cluster need ``cpas_bayes`` installed and must see the
    output folder (a shared file system), since each task writes its own files.
    """

    kind = "dask"

    def __init__(self, address=None, workers=2):
        try:
            from distributed import Client, LocalCluster
        except ImportError:  # pragma: no cover - depends on the installation
            raise RuntimeError("the Dask engine needs the 'distributed' package: "
                               "pip install 'cpas_bayes[dask]'") from None
        self.address = address
        self.cluster = None
        if address is None:
            # Worker processes (not threads): the likelihood holds the GIL between numpy calls.
            self.cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                        dashboard_address=None, silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
            self._threads = _OneThreadHere()
        else:
            try:
                self.client = Client(address, timeout=f"{CONNECT_TIMEOUT:g}s")
            except (OSError, TimeoutError, ValueError) as exc:
                from cpas_bayes.core.errors import InputError

                raise InputError("command line", f"option --scheduler {address}",
                                 f"no Dask scheduler answered within {CONNECT_TIMEOUT:g} s ({exc})",
                                 SCHEDULER_FIX) from None
        self.client.run(limit_blas_threads)
        self.workers = max(1, len(self.client.scheduler_info()["workers"]))

    def map(self, fn, items, desc="tasks", progress=None, on_report=None):
        items = list(items)
        if not items:
            return []
        args = [(fn, item) for item in items] if on_report is not None else items
        target = _call_without_reports if on_report is not None else fn
        futures = self.client.map(target, args, pure=False)
        try:
            with _progress_bar(len(items), desc, progress) as bar:
                done = 0
                while True:
                    finished = sum(f.done() for f in futures)  # the futures' local state: no scheduler call
                    bar.update(finished - done)
                    done = finished
                    if done == len(futures) or any(f.status == "error" for f in futures):
                        break  # gather returns the results or raises the task's error
                    time.sleep(0.05)  # a short wait keeps Ctrl-C responsive
                    raise_if_requested()
            return self.client.gather(futures)
        except BaseException:
            self.client.cancel(futures)
            raise

    def map_chained(self, first, then, items, costs=None, desc="tasks", progress=None, on_report=None):
        items = list(items)
        launched = []

        def launch(fn, item, index):
            if on_report is not None:   # the cluster carries no messages back: the task gets None
                launched.append(self.client.submit(_call_without_reports, (fn, item), pure=False))
            else:
                launched.append(self.client.submit(fn, item, pure=False))
            return launched[-1]
        try:
            with _progress_bar(_task_count(then, items), desc, progress) as bar:
                return self._chained_on_workers(launch, lambda: time.sleep(0.05), first, then, items, costs, bar)
        except BaseException:
            self.client.cancel(launched)
            raise

    map_chained.__doc__ = Executor.map_chained.__doc__

    def submit(self, fn, item):
        """Start ``fn(item)`` on the cluster now; ``result()`` of the handle waits for it."""
        return _Pending(self.client.submit(fn, item, pure=False), lambda f: self.client.cancel([f]))

    def describe(self):
        where = self.address or "a LocalCluster"
        return f"Dask on {where} ({self.workers} workers)"

    def close(self):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
            self._threads.restore()


def make_executor(workers=1, scheduler=None) -> Executor:
    """The executor for ``--workers N`` and ``--scheduler``.

    ``scheduler`` None: this process when ``workers`` is 1, else a local
    process pool; ``"local"``: a Dask LocalCluster of ``workers`` processes;
    ``"tcp://HOST:PORT"`` (any Dask address): that cluster. Inside a task
    (a worker of any executor) always this process: the parallelism is the
    outer map's, and pools do not nest.
    """
    if in_worker():
        return Executor()
    if scheduler:
        return DaskExecutor(None if scheduler == "local" else scheduler, workers)
    if workers is None or workers <= 1:
        return Executor(one_blas_thread=True)
    return ProcessExecutor(workers)

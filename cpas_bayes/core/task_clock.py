"""How long each task of a step took, where it ran: an executor that times the tasks it passes on.

What a step spends in tasks can be spread over workers; what it spends around them cannot. A benchmark
that reads only a step's wall time counts both as serial (the campaign's pool, ``benchmarks/run.py``).
"""

from __future__ import annotations

import time

from cpas_bayes.core.executor import Executor


def _timed_call(job):
    fn, item = job
    started = time.perf_counter()
    result = fn(item)
    return result, time.perf_counter() - started


class TaskClock(Executor):
    """Runs tasks on another executor (``inner``, left open) and keeps how long each took where it ran
    (``seconds``, in the order they were collected). Tasks that report progress run untimed."""

    def __init__(self, inner):
        super().__init__()
        self.inner = inner
        self.kind, self.workers = inner.kind, inner.workers
        self.seconds = []

    def map(self, fn, items, desc="tasks", progress=None, on_report=None):
        if on_report is not None:
            return self.inner.map(fn, items, desc=desc, progress=progress, on_report=on_report)
        pairs = self.inner.map(_timed_call, [(fn, item) for item in items], desc=desc, progress=progress)
        self.seconds.extend(s for _, s in pairs)
        return [r for r, _ in pairs]

    def map_chained(self, first, then, items, costs=None, desc="tasks", progress=None, on_report=None):
        """The inner executor's, untimed (no step of the package times chained tasks yet)."""
        return self.inner.map_chained(first, then, items, costs, desc=desc, progress=progress, on_report=on_report)

    def submit(self, fn, item):
        return _Clocked(self.inner.submit(_timed_call, (fn, item)), self.seconds)

    def describe(self):
        return self.inner.describe()

    def close(self):   # the inner executor belongs to the caller
        pass


class _Clocked:
    def __init__(self, handle, seconds):
        self._handle, self._seconds, self._value, self._done = handle, seconds, None, False

    def result(self):
        if not self._done:
            self._value, took = self._handle.result()
            self._seconds.append(took)
            self._done = True
        return self._value

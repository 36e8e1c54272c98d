"""Ctrl-C (and SIGTERM) that is never lost.

Python raises ``KeyboardInterrupt`` wherever the main thread happens to be
when the signal arrives. Inside a weakref callback or a ``__del__`` run by the
garbage collector, an exception cannot propagate: Python prints "Exception
ignored in ..." and goes on, so a fit interrupted at that moment would run to
its end (seen once in about eight Ctrl-C's beside a busy process).

While :func:`catching` is active, the signal handler also records the
request. :func:`raise_if_requested` raises ``KeyboardInterrupt`` again at
points where stopping is safe (every executor's wait loop, every sampling
chunk), and the "ignored" report of a dropped interrupt is silenced, since the
interrupt has not been dropped after all.
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager

_requested = threading.Event()


def _on_signal(signum, frame):
    _requested.set()
    raise KeyboardInterrupt


def _quiet_for_interrupts(previous):
    def hook(unraisable):
        if _requested.is_set() and isinstance(unraisable.exc_value, KeyboardInterrupt):
            return  # raise_if_requested delivers it at the next safe point
        previous(unraisable)

    return hook


def raise_if_requested():
    """Raise ``KeyboardInterrupt`` if a signal came while :func:`catching` is active (it may have been dropped)."""
    if _requested.is_set():
        raise KeyboardInterrupt


def requested() -> bool:
    return _requested.is_set()


@contextmanager
def catching(signals=(signal.SIGINT, signal.SIGTERM)):
    """Handle ``signals`` as recorded interrupts in this block; the previous handlers afterwards.

    Outside the main thread (where Python cannot set handlers) the block runs
    with the handlers as they are. A signal the process was started ignoring
    (a shell's background job ignores SIGINT) stays ignored, as Unix programs do.
    """
    _requested.clear()
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for s in signals:
            if signal.getsignal(s) is not signal.SIG_IGN:
                previous[s] = signal.signal(s, _on_signal)
    hook = sys.unraisablehook
    sys.unraisablehook = _quiet_for_interrupts(hook)
    try:
        yield
    finally:
        sys.unraisablehook = hook
        for s, handler in previous.items():
            signal.signal(s, handler)
        _requested.clear()

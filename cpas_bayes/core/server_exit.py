"""Imported only by the workers' fork server, last of its preloads: the server then ends at once.

The fork server (:mod:`cpas_bayes.core.executor`) imports the numerical stack
and keeps the program's standard output and error open. When the program
ends, the server's ordinary exit frees that stack object by object (about
0.6 s after a ``fit``), and a shell pipe or a ``subprocess`` reading the
program's output waits for it. The handler registered here runs first of the
server's exit handlers (they run last registered, first run): it flushes the
two streams and ends the process. The server holds no outputs and no
temporary files of its own; its workers end by ``os._exit`` already
(:mod:`multiprocessing.forkserver`) and never run exit handlers.

Nothing else may import this module: in the program itself the handler
would skip the exit handlers that remove its temporary folders.
"""

from __future__ import annotations

import atexit
import os
import sys


def _end_now():
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):   # closed or absent: nothing more to say on it
            pass
    os._exit(0)


atexit.register(_end_now)

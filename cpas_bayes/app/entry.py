"""The ``cpas-bayes`` program: start the worker server, then load the command line.

Loading the command line imports the numerical stack (about 2 s), and a
command that runs its tasks in local worker processes needs the same imports
in the fork server its workers come from (:class:`cpas_bayes.core.executor.ProcessExecutor`).
Started from inside the command, the server imported after the command line
had, and the first tasks waited for it (a two-Drogue ``fit``'s first chunk:
2.6 s, of which 0.6 s sampling). Started here, before anything heavy, the two
import side by side on two cores.

Only the arguments are read here; the command line checks them as before. A
command that will not start local workers (``--workers 1``, ``--scheduler``,
``--help``) starts no server.

Run as a program (:func:`run_program`), the process ends as soon as the
command has: its exit handlers run and its streams are flushed, but the
interpreter does not then free the numerical stack object by object (about
1 s after a ``fit``, measured with ``strace``: nothing but ``munmap``). Every
output is already closed and renamed into place by then.
"""

from __future__ import annotations

import sys

_CLI = "cpas_bayes.app.cli"
# arviz_stats: a fit's DataTree carries the accessor its ESS was computed by, so every worker that unpickles a
# figure's task would import it (0.35 s each) if the server had not
_FIT = ("cpas_bayes.inference.fit_folder", "cpas_bayes.inference.predictive_checks", "cpas_bayes.outputs.fit_figures",
        "cpas_bayes.outputs.plots.fit",
        "arviz_stats.accessors")
_DIAGNOSE = ("cpas_bayes.inference.diagnose", "cpas_bayes.outputs.diagnosis", "cpas_bayes.outputs.plots.diagnose")

# What each command's workers run, beyond what the command line imports: the tasks' modules.
WORKER_MODULES = {
    "fit": _FIT,
    "diagnose": _FIT + _DIAGNOSE,
    "pool": ("cpas_bayes.population.pool",),
    "campaign": _FIT + _DIAGNOSE + ("cpas_bayes.app.campaign", "cpas_bayes.loads.compare"),
    "demo": _FIT + _DIAGNOSE + ("cpas_bayes.app.campaign", "cpas_bayes.app.demo", "cpas_bayes.loads.compare"),
}
_NO_WORKERS = {"--help", "-h", "--scheduler"}


def _option_value(args, name):
    for i, a in enumerate(args):
        if a == name and i + 1 < len(args):
            return args[i + 1]
        if a.startswith(name + "="):
            return a.split("=", 1)[1]
    return None


def worker_modules(args):
    """The modules to preload in the worker server for command line ``args``, or None: no local workers."""
    if not args or args[0] not in WORKER_MODULES:
        return None
    if any(a in _NO_WORKERS or a.startswith("--scheduler=") for a in args):
        return None
    if _option_value(args, "--workers") == "1":
        return None
    return (_CLI,) + WORKER_MODULES[args[0]]


def main(argv=None):
    """Run ``cpas-bayes`` on ``argv`` (default the process' arguments); the exit status."""
    args = list(sys.argv[1:] if argv is None else argv)
    modules = worker_modules(args)
    if modules:
        import os

        from cpas_bayes.core.executor import start_worker_server

        os.environ.setdefault("MPLBACKEND", "Agg")   # as run_cli sets it, before the workers inherit it
        start_worker_server(modules)
    from cpas_bayes.app.cli import main as run

    return run(argv)


def run_program():
    """The console script: :func:`main`, then end the process without the interpreter's teardown."""
    import atexit
    import os
    import threading

    status = main()
    status = status if isinstance(status, int) else (0 if status is None else 1)
    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.main_thread()):
        sys.exit(status)        # a thread still running: the ordinary exit, which waits for it
    atexit._run_exitfuncs()     # what exit would run: the workers' server stopped, temporary folders removed
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):   # a closed pipe: nothing more can be said on it
            pass
    os._exit(status)

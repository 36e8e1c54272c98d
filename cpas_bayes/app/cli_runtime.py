"""How the ``cpas-bayes`` process runs a command: exit statuses, interrupts, the figure backend.

Bad input ends with one message naming the file, the place and the fix (exit
status 2); an unexpected fault with a short message (exit status 1, the
traceback only when ``CPAS_BAYES_DEBUG=1``); Ctrl-C and SIGTERM with what the
running command left behind (exit status 130).
"""

from __future__ import annotations

import os
import traceback

import click

from cpas_bayes.core import interrupts
from cpas_bayes.core.errors import InputError
from cpas_bayes.core.ownership import output_error

# What Ctrl-C leaves behind, said by the command that is running (see run_cli()).
_NOTHING_HALF_WRITTEN = ("interrupted; nothing half-written was left (every output is written to a temporary file "
                         "and renamed)")
_INTERRUPTED = [_NOTHING_HALF_WRITTEN]


def on_interrupt(message):
    """What an interrupt of the running command leaves behind, said if it comes."""
    _INTERRUPTED[0] = f"interrupted; {message}"


def _select_backend():
    """Figures go to files: Agg, in this process and in the worker processes it starts.

    The library itself never selects a backend (a notebook keeps its own); the
    CLI does, unless the user chose one with MPLBACKEND.
    """
    import os

    if "MPLBACKEND" not in os.environ:
        os.environ["MPLBACKEND"] = "Agg"  # read by the workers' matplotlib
        import matplotlib

        matplotlib.use("Agg")


def run_cli(group, argv=None):
    """Run the click ``group`` on ``argv``, turning bad input into one clear message; the exit status.

    SIGTERM (kill, a batch system's stop) ends a command as Ctrl-C does, and an
    interrupt that lands where Python drops exceptions still ends it
    (:mod:`cpas_bayes.core.interrupts`).
    """
    _select_backend()
    _INTERRUPTED[0] = _NOTHING_HALF_WRITTEN
    with interrupts.catching():
        return _run(group, argv)


def _run(group, argv):
    try:
        group.main(args=argv, prog_name="cpas-bayes", standalone_mode=False)
    except InputError as exc:
        click.secho(f"error: {exc}", fg="red", err=True)
        return 2
    except OSError as exc:  # an output (or input) the system refused: the path and the fix, not a traceback
        if os.environ.get("CPAS_BAYES_DEBUG") == "1":
            traceback.print_exc()
        click.secho(f"error: {output_error(exc, exc.filename or '', verb='used')}", fg="red", err=True)
        return 2
    except click.exceptions.Abort:
        click.echo(_INTERRUPTED[0], err=True)
        return 130
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 1
    except KeyboardInterrupt:
        click.echo(_INTERRUPTED[0], err=True)
        return 130
    except Exception as exc:  # noqa: BLE001 - the last line of defence for a CLI user
        if os.environ.get("CPAS_BAYES_DEBUG") == "1":
            traceback.print_exc()
        click.secho(f"internal error: {type(exc).__name__}: {exc}\n"
                    "rerun with CPAS_BAYES_DEBUG=1 to see the traceback and report it.", fg="red", err=True)
        return 1
    return 0

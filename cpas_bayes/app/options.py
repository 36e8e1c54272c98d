"""The command line's option types and checks: every option is refused before any work starts.

Numbers are click ranges (a value outside is a usage error naming the
option, exit status 2); paths and addresses are checked by callbacks while
the command line is parsed, so a refused option leaves no output behind.
The limits, and why:

=================  ==========================  ==========================================================
option             allowed                     why
=================  ==========================  ==========================================================
``--seed``         0 … 2⁶³ − 1                 numpy seeds are non-negative; TOML integers are 64-bit
``--workers``      1 … ``MAX_LOCAL_WORKERS``   twice the cores (at least 4): the tasks are compute-bound,
                                               and each process holds its own libraries and data
``--ensembles``    1 … ``MAX_ENSEMBLES`` (16)  R-hat needs 2 or more; beyond 16 only memory grows
``--runs``         1 … 10,000,000, and what    :mod:`cpas_bayes.loads.budget`: every run is kept in
                   fits in half the memory     memory; checked before anything is drawn
``--batch``        1 … 100,000                 runs simulated at once
``--magnitude``    finite, within the effect's :data:`cpas_bayes.data.synth.EFFECT_MAGNITUDE_LIMITS`
                   limits
``--stop``         ``tau`` or ``ess``          :mod:`cpas_bayes.inference.stopping`; ``ess`` needs 2 or more
                                               ensembles: its R-hat compares ensembles
``--ess-target``   100 … 100,000, with         below 100 neither ESS nor R-hat estimates are reliable
                   ``--stop ess`` only         (fit health warns below 400); 100,000 is 100× the default
``--scheduler``    ``local`` or an address     the scheduler must answer within 5 s
                   that answers
``--priors``       an existing TOML file       read within :func:`cpas_bayes.core.inputs.read_toml`'s limits
``--out``          a folder, or a path where   never a file; new, empty or written by cpas-bayes;
                   one can be made, outside    never an input bundle folder or inside one (outputs
                   every input bundle          would mix with the bundle's own files)
=================  ==========================  ==========================================================
"""

from __future__ import annotations

import functools
from pathlib import Path

import click

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.executor import MAX_LOCAL_WORKERS
from cpas_bayes.core.scheduler_address import SCHEDULER_FIX, scheduler_problem
from cpas_bayes.core.inputs import read_toml
from cpas_bayes.core.ownership import check_output, check_outside_inputs
from cpas_bayes.data.bundle_csv import TOML_NAME, bundle_folders
from cpas_bayes.inference.stopping import STOP_RULES
from cpas_bayes.loads.budget import MAX_BATCH, MAX_RUNS

MAX_SEED = 2**63 - 1
MAX_ENSEMBLES = 16

SEED = click.IntRange(0, MAX_SEED)
WORKERS = click.IntRange(1, MAX_LOCAL_WORKERS)
ENSEMBLES = click.IntRange(1, MAX_ENSEMBLES)
RUNS = click.IntRange(1, MAX_RUNS)
BATCH = click.IntRange(1, MAX_BATCH)
STOP = click.Choice(STOP_RULES)
ESS_TARGETS = click.IntRange(100, 100_000)


def stop_problem(stop, ess_target, ensembles):
    """(option, why) when ``--stop``, ``--ess-target`` and ``--ensembles`` do not go together, else None."""
    if ess_target is not None and stop != "ess":
        return "--ess-target", "a target of effective sample size applies only with --stop ess"
    if stop == "ess" and ensembles < 2:
        return "--ensembles", ("--stop ess (the default) needs 2 or more ensembles, because its R-hat compares "
                               "them; give --ensembles 2 or more, or --stop tau")
    return None


def check_scheduler(ctx, param, value):
    """``--scheduler``: ``local``, or a Dask scheduler address that answers within the connect timeout."""
    problem = scheduler_problem(value)
    if problem:
        raise click.BadParameter(f"{problem}. Fix: {SCHEDULER_FIX}", ctx=ctx, param=param)
    return value


def _refusal_as_bad_parameter(check, ctx, param, value):
    """Run ``check(value)``; its refusal becomes click's option error (exit 2, the option named)."""
    if value is None:
        return value
    try:
        check(value)
    except InputError as exc:
        raise click.BadParameter(str(exc), ctx=ctx, param=param) from None
    return value


# The file each command always writes at the top of its --out: it says which command's output a folder is.
# Outputs of two commands share names (fit and montecarlo both write summary.json; figures too), so a
# command refuses a folder holding another command's output, whose files it would otherwise replace.
OUTPUT_SIGNATURES = {"fit": "posterior.nc", "montecarlo": "runs.csv", "pool": "memo.toml", "compare": "compare.json",
                     "diagnose": "diagnosis.json", "reduce": "reduction.json", "campaign": "campaign.json",
                     "synth": "truth.json", "import": "import.json"}


def other_command_output(path, command):
    """The (command, file) of another command's output held in folder ``path``, or None."""
    if command not in OUTPUT_SIGNATURES:
        return None
    for other, name in OUTPUT_SIGNATURES.items():
        if other != command and (Path(path) / name).is_file():
            return other, name
    return None


def check_out(ctx, param, value, takes_bundles=False):
    """``--out``: the output-folder rule of :mod:`cpas_bayes.core.ownership`, checked while the line is parsed;
    an empty path (an unset shell variable) and a folder holding another command's output are refused. For a
    command that reads bundles (``takes_bundles``), a bundle folder (one holding test.toml) is refused as such
    first; whether ``--out`` lies inside an input bundle is checked as the command starts (:func:`out_option`)."""
    if value is None:
        return None
    if str(value).strip() == "":
        raise click.BadParameter("an empty path (an unset shell variable?) would write into the current folder. "
                                 "Fix: give the output folder's path", ctx=ctx, param=param)
    value = Path(value)
    if takes_bundles and (value / TOML_NAME).is_file():
        _check_out_of_inputs(ctx, param, value, value)
    _refusal_as_bad_parameter(check_output, ctx, param, value)
    found = other_command_output(value, ctx.info_name)
    if found:
        other, name = found
        raise click.BadParameter(f"{value} holds the output of 'cpas-bayes {other}' ({name}); each command's output "
                                 "needs a folder of its own, since their files share names (summary.json, figures). "
                                 f"Fix: give {ctx.info_name} a folder of its own (new, empty, or an earlier "
                                 f"{ctx.info_name} output)", ctx=ctx, param=param)
    return value


def _check_out_of_inputs(ctx, param, out, given):
    """Refuse ``--out`` ``out`` that is or lies inside an input bundle folder: ``given``, or the bundles in it
    when it is a folder of bundles (a campaign's, whose ``--out`` may sit beside them). A ``given`` that holds no
    bundle is refused by the command itself, before it writes."""
    folders = bundle_folders(given)
    _refusal_as_bad_parameter(lambda v: check_outside_inputs(v, folders), ctx, param, out)


def check_fit_folders(ctx, param, value):
    """``pool``'s FITDIRS: each a fit folder with a readable summary.json, checked before any worker starts
    (the posterior files are read by the workers)."""
    from cpas_bayes.inference.fit_folder import read_summary

    for folder in value or ():
        try:
            read_summary(folder)
        except InputError as exc:
            raise click.BadParameter(str(exc), ctx=ctx, param=param) from None
    return value


def check_toml_file(ctx, param, value):
    """``--priors``: an existing file that reads as TOML within the limits (its tables are checked by the fit)."""
    return _refusal_as_bad_parameter(read_toml, ctx, param, value)


def out_option(help_text, inputs=None, **kwargs):
    """``--out`` with its check. ``inputs`` names the command's parameter holding its input bundle folder (or
    folder of bundles): ``--out`` may not be one of them or lie inside one
    (:func:`~cpas_bayes.core.ownership.check_outside_inputs`). Checked as the command starts, before any work:
    click processes arguments after every option, so ``--out``'s callback cannot."""
    # a str first, so that the callback sees an empty argument as empty (Path("") reads as ".")
    callback = check_out if inputs is None else functools.partial(check_out, takes_bundles=True)
    option = click.option("--out", type=click.Path(), callback=callback, help=help_text, **kwargs)
    if inputs is None:
        return option

    def decorate(command):
        @functools.wraps(command)     # its click parameters and help come along
        def checked(**params):
            if params.get("out") is not None and params.get(inputs) is not None:
                ctx = click.get_current_context()
                param = next(p for p in ctx.command.params if p.name == "out")
                _check_out_of_inputs(ctx, param, Path(params["out"]), params[inputs])
            return command(**params)
        return option(checked)
    return decorate


def seed_option(help_text):
    return click.option("--seed", type=SEED, default=0, show_default=True, help=help_text)


def term_names(value, param_hint):
    """The model terms named in a comma-separated ``value`` (``--candidates``, ``--with``), each known and named
    once; a usage error naming the option otherwise."""
    from cpas_bayes.core.inputs import did_you_mean
    from cpas_bayes.stats.model_terms import EXTENSIONS

    names = tuple(c.strip() for c in value.split(",") if c.strip())
    unknown = list(dict.fromkeys(n for n in names if n not in EXTENSIONS))
    if unknown or not names:
        # a few of the unknown names, each cut short: a pasted file must not fill the terminal
        shown = ", ".join(n if len(n) <= 40 else n[:40] + "…" for n in unknown[:3]) + (
            f" and {len(unknown) - 3} more" if len(unknown) > 3 else "")
        raise click.BadParameter(f"unknown extension(s) {shown or '(none given)'}"
                                 f"{did_you_mean(unknown[0], EXTENSIONS) if unknown else ''}; use any of "
                                 f"{', '.join(EXTENSIONS)}", param_hint=param_hint)
    if len(set(names)) < len(names):
        raise click.BadParameter(f"{sorted({n for n in names if names.count(n) > 1})[0]} is given twice",
                                 param_hint=param_hint)
    return names


def terms_problem(names, test):
    """The message refusing terms ``names`` for ``test``, or None: terms acting on channels the test lacks, or
    two terms that each bring their own error model."""
    from cpas_bayes.stats.model_parts import own_error_models
    from cpas_bayes.stats.model_terms import EXTENSIONS, applies

    lacking = [n for n in names if not applies(n, test)]
    if lacking:
        return (f"{', '.join(lacking)} act{'s' if len(lacking) == 1 else ''} on load cells, and {test.name} has "
                f"none: leave {'it' if len(lacking) == 1 else 'them'} out")
    own = own_error_models(EXTENSIONS[n] for n in names)
    if len(own) > 1:
        return f"{' and '.join(own)} each bring their own error model: give one of them"
    return None


def priors_option():
    return click.option("--priors", type=click.Path(path_type=Path), default=None, callback=check_toml_file,
                        help="TOML file whose tables replace the default priors (same layout as priors/*.toml).")


# ---------------------------------------------------------------------------
# the campaign TOML's values: field -> (type, low, high); None: no bound. Checked by load_config.

MAX_STEPS = 100_000          # a fit's steps per ensemble: 5× the default; chains stay ≤ ~100 MB per ensemble
STEP_CAPS = click.IntRange(500, MAX_STEPS)   # fit --max-steps: at least one chunk of the ESS rule
CONFIG_LIMITS = {
    "seed": (int, 0, MAX_SEED),
    "workers": (int, 1, MAX_LOCAL_WORKERS),
    "fit_ensembles": (int, 1, MAX_ENSEMBLES),
    "fit_max_steps": (int, 100, MAX_STEPS),
    "fit_check_every": (int, 10, 10_000),
    "fit_tau_factor": (float, 0.0, None),
    "fit_ess_target": (int, 100, 100_000),
    "montecarlo_runs": (int, 1, MAX_RUNS),
    "compare_runs": (int, 1, MAX_RUNS),
    "pool_draws": (int, 100, 1_000_000),
}


def value_problem(value, kind, low=None, high=None):
    """Why ``value`` is not a ``kind`` (int or float) in [low, high] (floats: finite and above ``low``), or None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (kind is int and not isinstance(value, int)):
        return f"{value!r:.60} is not {'a whole number' if kind is int else 'a number'}"
    if kind is float:
        if value != value or value in (float("inf"), float("-inf")):
            return f"{value} is not a finite number"
        if low is not None and not value > low:
            return f"{value:g} must be more than {low:g}"
    elif (low is not None and value < low) or (high is not None and value > high):
        return f"{value:,} is outside {low:,} … {high:,}"
    return None

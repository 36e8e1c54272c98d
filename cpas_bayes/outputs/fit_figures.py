"""A fit's figures as tasks: which figures, with which data, into which files; the drawing is
:mod:`cpas_bayes.outputs.plots.fit`'s.

This module imports no matplotlib: the process that plans the figures and computes the checks (a fit
command's own) leaves the drawing to its workers, whose server has imported the plotting modules, and
does not spend 0.45-0.6 s of CPU on matplotlib's import beside workers that already fill the cores.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cpas_bayes.core.inputs import inside
from cpas_bayes.core.ownership import claim_folder
from cpas_bayes.inference.check_draws import posterior_matrix, predict_draws
from cpas_bayes.inference.predictive_checks import run_checks

BAND_DRAWS = 400
CORNER_FIELDS = ("start", "n_p", "expopen", "ck", "tk", "eps")
CORNER_UNITS = {"start": "s", "tk": "s"}
TRACE_PARAMETERS = 6
FIGURE_PARTS = ("draws", "checks")   # the figures of the posterior's draws; those of the predictive checks


def band_draws(fit, n_draws, rng):
    """Predictions of ``n_draws`` posterior draws picked by ``rng``: what the bands and loads figures show."""
    model = fit.model
    draws = posterior_matrix(fit.tree, model.names).reshape(-1, model.ndim)
    pick = rng.choice(draws.shape[0], size=min(n_draws, draws.shape[0]), replace=False)
    return predict_draws(model, draws[pick])


def corner_groups(model):
    """[(chute id, stage k (1-based), [parameter names])] of each parachute stage of ``model``.

    A composite cluster's parachutes share their parameters: their group's stage once,
    under the first parachute's id.
    """
    out, seen = [], set()
    for i, p in enumerate(model.parachutes):
        for k in range(1, len(p.stages) + 1):
            names = [n for n in (model.parameter_name(i, f"s{k}.{f}") for f in CORNER_FIELDS) if n is not None]
            if tuple(names) not in seen:
                seen.add(tuple(names))
                out.append((p.id, k, names))
    return out


def worst_rhat_parameters(fit, n=TRACE_PARAMETERS):
    """Names of the ``n`` parameters with the largest R-hat in the summary's diagnostics."""
    per = fit.summary.get("diagnostics_per_parameter", {}) or {}
    ranked = sorted(per, key=lambda name: -(per[name].get("rhat") or 0.0))
    names = [name for name in ranked if name in fit.model.index][:n]
    return names or list(fit.model.names[:n])


def _figure_task(job):
    """Draw one figure and save it: a task of an executor (``job`` = (drawer, path, args, kwargs)). The drawing
    module is imported here, in the process that draws: a worker's server has imported it already."""
    from cpas_bayes.outputs.plots.fit import draw_figure

    return draw_figure(job)


@dataclass
class StartedFigures:
    """The corners of a fit drawing on the workers before its DataTree exists (:func:`start_corner_figures`):
    the figures' random generator, the loads figure's stream and the corners' tasks."""

    rng: np.random.Generator
    loads_stream: np.random.Generator
    tasks: list


def start_corner_figures(model, sampling, out, executor, rng=0):
    """Submit the corner figures from the sampled draws (a
    :class:`cpas_bayes.inference.fit.SamplingResult`), the same files as :func:`write_fit_figures` draws:
    the workers draw them while this process assembles the DataTree, which they would otherwise wait for
    idle (1-1.5 s of a two-Drogue fit command). Pass the result as ``write_fit_figures(started=...)``."""
    chains, _, _ = sampling.stacked()
    rng = np.random.default_rng(rng)
    loads_stream, jobs = _corner_jobs(model, lambda name: chains[:, :, model.index[name]], claim_folder(out), rng)
    return StartedFigures(rng, loads_stream, [executor.submit(_figure_task, job) for job in jobs])


def write_fit_figures(fit, out, checks=None, n_draws=BAND_DRAWS, rng=0, executor=None, parts=FIGURE_PARTS,
                      started=None, meanwhile=None):
    """Write every figure of a fit into folder ``out``; return their paths.

    ``checks`` (:class:`cpas_bayes.inference.predictive_checks.FitChecks`) is computed if not given; it may
    also be a function of no arguments that returns them, called here while the executor's workers draw
    the figures that need no checks (bands, loads, corners, trace), so that the two overlap.
    ``executor`` (:mod:`cpas_bayes.core.executor`) draws the figures in parallel, one task each (about
    1 s of matplotlib apiece); the figures do not depend on it: each has its own random stream.
    ``parts`` (of :data:`FIGURE_PARTS`) draws some of them: ``"draws"`` (bands, trace, corners, loads) or
    ``"checks"`` (PPC, LOO-PIT, residuals), each the same file as a call that draws both with the same
    ``checks`` argument (a campaign draws the first later, as a task of its own). ``started``: the corners
    :func:`start_corner_figures` submitted already (then ``rng`` is the one given there). ``meanwhile``: a
    function of no arguments called once every figure is submitted, while the workers draw them.
    """
    from cpas_bayes.core.executor import Executor

    unknown = [p for p in parts if p not in FIGURE_PARTS]
    if unknown:
        raise ValueError(f"unknown figure parts {unknown}; use some of {FIGURE_PARTS}")
    executor = executor or Executor()
    out = claim_folder(out)
    rng = started.rng if started else np.random.default_rng(rng)
    if checks is None and "checks" in parts:
        checks = run_checks(fit, rng=rng)
    tasks = list(started.tasks) if started else []
    jobs = _draw_figure_jobs(fit, out, n_draws, rng, started) if "draws" in parts else []
    tasks += [executor.submit(_figure_task, job) for job in jobs]
    if "checks" in parts:
        checks = checks() if callable(checks) else checks
        tasks += [executor.submit(_figure_task, job) for job in _check_figure_jobs(checks, out)]
    if meanwhile:
        meanwhile()
    return [task.result() for task in tasks]


def _corner_jobs(model, values_of, out, rng):
    """(the loads figure's random stream, the corner figures as tasks, most parameters first);
    ``values_of(name)``: a parameter's posterior draws."""
    groups = corner_groups(model)
    # spawned streams do not depend on what the generator drew before: the same whether the corners start
    # before the bands' draws are picked or after
    streams = iter(rng.spawn(len(groups) + 1))
    loads_stream, jobs = next(streams), []
    for pid, k, names in groups:
        values = np.column_stack([np.asarray(values_of(n), float).ravel() for n in names])
        short = [n.rsplit(".", 1)[-1] for n in names]
        labels = [f"{s} [{CORNER_UNITS.get(s, '-')}]" for s in short]
        title = (f"{model.test.name}: {pid} stage {k} posterior — narrow, single-peaked clouds mean the "
                 "data pin the parameters; tilted ones show trade-offs")
        jobs.append(("corner", inside(out, f"corner_{pid}_s{k}.png"), (values, short, labels, title),
                     {"rng": next(streams)}))
    return loads_stream, sorted(jobs, key=lambda job: -len(job[2][1]))


def _draw_figure_jobs(fit, out, n_draws, rng, started=None):
    """The figures of the posterior's draws as tasks: bands, trace, corners (most parameters first; none when
    ``started`` has them), loads."""
    pred = band_draws(fit, n_draws, rng)
    if started:
        loads_stream, corners = started.loads_stream, []
    else:
        post = fit.tree["posterior"]
        loads_stream, corners = _corner_jobs(fit.model, lambda name: post[name].values, out, rng)
    # the slowest first, so that two workers finish together (bands and trace ~0.7 s each, a corner of six
    # parameters 0.6 s, of five 0.4 s, loads 0.35 s)
    return ([("bands", out / "bands.png", (fit, pred), {}),
             ("trace", out / "trace.png", (fit, worst_rhat_parameters(fit)), {})]
            + corners + [("loads", out / "loads.png", (fit, pred, loads_stream), {})])


def _check_figure_jobs(checks, out):
    return [("ppc", out / "ppc.png", (checks.ppc,), {}),
            ("loo_pit", out / "loo_pit.png", (checks.loo_pit,), {}),
            ("residuals", out / "residuals.png", (checks.residuals,), {})]

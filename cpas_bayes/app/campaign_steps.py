"""What a campaign runs, step by step: each step's content hash, its run into a temporary folder, and the
work of the per-test steps (reduction, fit, diagnosis) and the pooled ones (Monte Carlo, load comparison).

:mod:`cpas_bayes.app.campaign` decides which steps run, in which order and where; the tasks here are
top-level functions of one picklable job, so any executor (:mod:`cpas_bayes.core.executor`) can ship
them to a worker. A test's fit and its diagnosis are two tasks (:func:`fit_task`, :func:`diagnosis_task`):
the diagnosis reads the fit from its folder, and the fit task hands it the reduction it made.
"""

from __future__ import annotations

import functools
import hashlib
import json
import time as _time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from cpas_bayes import __version__
from cpas_bayes.core.errors import InputError
from cpas_bayes.core.files import atomic_directory, write_json
from cpas_bayes.core.inputs import inside, read_json
from cpas_bayes.data.bundle import CSV_NAME, TOML_NAME
from cpas_bayes.data.reduction import reduce_test

STAMP = "stamp.json"


# ---------------------------------------------------------------------------
# hashing and steps


def digest(*parts) -> str:
    """A short hash of ``parts`` (bytes, or anything JSON can write)."""
    h = hashlib.sha256()
    for part in parts:
        h.update(part if isinstance(part, bytes) else json.dumps(part, sort_keys=True, default=str).encode())
        h.update(b"\0")
    return h.hexdigest()[:20]


def folder_digest(folder) -> str:
    """Hash of every file's name and bytes in a folder (a bundle, a priors folder)."""
    folder = Path(folder)
    files = sorted(p for p in folder.rglob("*") if p.is_file() and not p.name.startswith("."))
    return digest(*[part for p in files for part in (str(p.relative_to(folder)), p.read_bytes())])


def bundle_digest(folder, priors_files=()) -> str:
    """Hash of what reading a bundle reads: its test.toml and data.csv, and the test's own prior files (which
    may sit outside its folder). Other files in the folder (notes, a fit written inside it) leave it as it is:
    hashing the whole folder re-ran a test's steps after each fit written there and read its 30 MB."""
    folder = Path(folder)
    return digest(*[(folder / name).read_bytes() for name in (TOML_NAME, CSV_NAME)],
                   *[Path(f).read_bytes() for f in priors_files])


@dataclass
class StepRecord:
    name: str
    key: str
    status: str                 # "ran" or "cached"
    seconds: float
    task_seconds: float | None = None   # a step that runs tasks of its own (the pool): their sum ...
    tasks: int | None = None            # ... their count ...
    longest_task_seconds: float | None = None   # ... and the longest, each timed where it ran


def _stamped(stamp, key):
    """Whether the stamp file ``stamp`` holds ``key`` (a missing or damaged stamp: no, the step runs again)."""
    try:
        return stamp.is_file() and json.loads(stamp.read_text(encoding="utf-8"))["key"] == key
    except (ValueError, KeyError, TypeError, OSError):
        return False


def run_step(folder, key, work, records, name, echo, stamp=STAMP):
    """Run ``work(tmp)`` into a temporary folder renamed onto ``folder`` unless its stamp holds ``key``.

    ``stamp`` other than :data:`STAMP`: a step that adds files to a folder another step wrote (a fit's
    draw figures): ``work(folder)`` writes each file atomically in place, then the stamp file is written."""
    folder = Path(folder)
    if _stamped(folder / stamp, key):
        records.append(StepRecord(name, key, "cached", 0.0))
        echo(f"  {name}: unchanged, kept")
        return False
    started = _time.perf_counter()
    if stamp == STAMP:
        with atomic_directory(folder) as tmp:
            work(Path(tmp))
            write_json(Path(tmp) / STAMP, {"key": key, "version": __version__})
    else:
        work(folder)
        write_json(folder / stamp, {"key": key, "version": __version__})
    seconds = _time.perf_counter() - started
    records.append(StepRecord(name, key, "ran", seconds))
    echo(f"  {name}: done in {seconds:.0f} s")
    return True


def test_folder(out, name, *parts):
    """``OUT/tests/<name>/<parts>``, refused if the test's name would lead outside ``OUT/tests``."""
    return inside(Path(out) / "tests", name).joinpath(*parts)


LOGGER_COST = 13   # a logger bundle's fit and diagnosis per stage, in units of a q̄ bundle's (Measured figures)


def test_cost(test) -> float:
    """A test's relative cost of fit and diagnosis, to hand out the costliest first: its stages and canopies
    (the parameters grow with them), times :data:`LOGGER_COST` without a q̄ channel. On the benchmark run
    the two-Drogue example took 15 s (6 units: 2.6 s each), the three-Main 37 s (12: 3.1 s), a one-canopy
    logger drop 70 s (2: 35 s)."""
    units = sum(len(p.stages) + 1 for p in test.parachutes)
    return float(units * (1 if test.measured_qbar else LOGGER_COST))


# ---------------------------------------------------------------------------
# the steps' work


def _reduce_work(reduced):
    def work(tmp):
        from cpas_bayes.outputs.reduction import write_reduction

        write_reduction(reduced(), tmp)
    return work


def _fit_work(test, reduced, config, checkpoint, echo, executor=None):
    def work(tmp):
        from cpas_bayes.inference.predictive_checks import check_report, run_checks
        from cpas_bayes.inference.fit import fit_model, prepare_model
        from cpas_bayes.inference.fit_folder import record_checks
        from cpas_bayes.outputs.fit_figures import write_fit_figures

        model = prepare_model(test, reduced(), priors=config.priors, decay=config.decay,
                              below_previous=config.below_previous)
        fit = fit_model(model, replace(config.sampler(), progress=False), out=tmp, checkpoint_dir=checkpoint,
                        executor=executor)
        checks = run_checks(fit, rng=config.seed)
        warnings = record_checks(fit, checks, tmp)
        write_json(tmp / "checks.json", check_report(fit, checks=checks))
        # the checks' figures here; those of the draws later, as a task of their own (figures_task)
        write_fit_figures(fit, tmp, checks=checks, executor=executor, parts=("checks",))
        write_json(tmp / "map.json", {"names": list(model.names),
                                      "theta": [float(v) for v in fit.sampling.theta_map],
                                      "log_posterior": float(fit.sampling.log_post_map)})
        d = fit.summary["diagnostics"]
        echo(f"    {test.name}: R-hat max {d['rhat_max']:.3f}, ESS bulk min {d['ess_bulk_min']:.0f}"
             + (f", {len(warnings)} fit health warning(s)" if warnings else ""))
    return work


def load_baseline_fit(test, reduction, folder, config):
    """The baseline fit of a test from its fit folder (model rebuilt from ``reduction``, MAP from map.json)."""
    from cpas_bayes.inference.fit import Fit, SamplingResult, prepare_model
    from cpas_bayes.inference.fit_folder import POSTERIOR_NAME, load_datatree, read_summary

    folder = Path(folder)
    model = prepare_model(test, reduction, priors=config.priors, decay=config.decay,
                          below_previous=config.below_previous)
    fix = f"delete {folder} so that the campaign refits the test, and re-run the campaign"
    m = read_json(folder / "map.json", fix, what="MAP file")
    theta, lp = m.get("theta"), m.get("log_posterior")
    if m.get("names") != list(model.names):
        raise InputError(folder / "map.json", "key 'names'", "does not match the model's parameters", fix)
    if (not isinstance(theta, list) or len(theta) != len(model.names)
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in theta)):
        raise InputError(folder / "map.json", "key 'theta'", f"not {len(model.names)} finite numbers", fix)
    if isinstance(lp, bool) or not isinstance(lp, (int, float)):
        raise InputError(folder / "map.json", "key 'log_posterior'", "missing or not a number", fix)
    sampling = SamplingResult(names=list(model.names), runs=[], theta_map=np.array(theta, float),
                              log_post_map=float(lp), options=config.sampler())
    summary = read_summary(folder)
    return Fit(model, sampling, load_datatree(folder / POSTERIOR_NAME), summary)


def _diagnose_work(test, reduced, config, fit_folder, echo, executor=None):
    def work(tmp):
        from cpas_bayes.inference.candidate_fits import DIAGNOSIS_SAMPLER, DiagnoseOptions
        from cpas_bayes.inference.diagnose import diagnose_test
        from cpas_bayes.outputs.diagnosis import write_diagnosis
        from cpas_bayes.inference.fit_folder import POSTERIOR_NAME, build_summary, convergence, save_datatree, write_summary

        fit = load_baseline_fit(test, reduced(), fit_folder, config)
        options = DiagnoseOptions(seed=config.seed, candidates=tuple(config.candidates), priors=config.priors,
                                  decay=config.decay, below_previous=config.below_previous, mode=config.diagnose,
                                  model_forms=config.model_forms,
                                  sampler=replace(DIAGNOSIS_SAMPLER, workers=config.workers, progress=False))
        d = diagnose_test(test, options, reduction=reduced(), baseline_fit=fit, echo=lambda m: echo("    " + m), executor=executor)
        write_diagnosis(d, tmp)
        if d.named_fit is not None:  # the named terms together, without the discrepancy
            named = d.named_fit.fit
            ext = tmp / "extended"
            save_datatree(named.tree, ext / POSTERIOR_NAME)
            write_summary(ext, build_summary(named.model, named.tree, convergence(named.tree, named.sampling),
                                             named.sampling.options))
        echo(f"    {test.name}: {d.verdict}: {', '.join(d.causes) or 'none'}")
    return work


def _compare_work(test, memo_folder, fit_folder, config):
    def work(tmp):
        from cpas_bayes.loads.compare import compare_loads
        from cpas_bayes.outputs.compare import write_comparison
        from cpas_bayes.population.memo import load_memo
        from cpas_bayes.inference.fit_folder import load_fit

        comparison = compare_loads(test, load_memo(memo_folder), load_fit(fit_folder), runs=config.compare_runs,
                                   rng=np.random.default_rng([config.seed, 11]))
        write_comparison(comparison, tmp)
    return work


def _montecarlo_work(like, memo_folder, config):
    def work(tmp):
        from cpas_bayes.population.memo import load_memo
        from cpas_bayes.loads.fill_time import compare_fill_time_dispersion
        from cpas_bayes.loads.montecarlo import run_monte_carlo
        from cpas_bayes.outputs.montecarlo import write_fill_time_comparison, write_monte_carlo

        memo = load_memo(memo_folder)
        result = run_monte_carlo(memo, like, config.montecarlo_runs, np.random.default_rng([config.seed, 21]))
        write_monte_carlo(result, tmp, memo, extra={"like": like.name, "seed": config.seed})
        comparison = compare_fill_time_dispersion(memo, like, config.montecarlo_runs,
                                                  np.random.default_rng([config.seed, 22]))
        write_fill_time_comparison(comparison, tmp, extra={"like": like.name, "seed": config.seed})
    return work


# ---------------------------------------------------------------------------
# tasks: what one worker does


def fit_task(job, report=None, executor=None):
    """Reduce and fit one test; returns its step records, the messages not yet shown, and the reduction when
    this task made one (for its diagnosis; None when both steps were up to date)."""
    test, config, out, bundle_key, fit_key, diag_key = job
    log = []
    echo = report if report is not None else log.append
    records = []
    base = test_folder(out, test.name)
    reduced = functools.cache(lambda: reduce_test(test))  # once per run, only if a step is not up to date
    echo(f"{test.name}:")
    run_step(base / "reduction", bundle_key, _reduce_work(reduced), records, f"{test.name} reduction", echo)
    run_step(base / "fit", fit_key,
             _fit_work(test, reduced, config, inside(out / ".checkpoints", test.name), echo, executor),
             records, f"{test.name} fit", echo)
    made = reduced() if reduced.cache_info().currsize else None
    return records, log, made


def diagnosis_task(job_and_fit, report=None, executor=None):
    """Diagnose one test from its fit folder (after :func:`fit_task`, whose result comes with the job);
    returns its step records and the messages not yet shown (none without a diagnosis)."""
    job, fitted = job_and_fit
    test, config, out, bundle_key, fit_key, diag_key = job
    log = []
    records = []
    if diag_key is None:
        return records, log
    echo = report if report is not None else log.append
    reduced = _reduction_from(test, fitted)
    base = test_folder(out, test.name)
    run_step(base / "diagnosis", diag_key, _diagnose_work(test, reduced, config, base / "fit", echo, executor),
             records, f"{test.name} diagnosis", echo)
    return records, log


FIGURES_STAMP = "figures.json"   # in a fit folder: the fit step's key once its draws' figures are drawn


def figures_task(job_and_fit, report=None, executor=None):
    """Draw the figures of a test's posterior draws (bands, trace, corners, loads) into its fit folder, after
    the fit step, which drew its checks' figures; returns the step records and the messages not yet shown.

    A task of its own so that it can wait: drawn last, these small tasks (~4 s) fill the workers that the
    last diagnoses leave idle. Each figure is written atomically, then ``figures.json`` with the fit step's
    key; a rerun draws them again only when that key changed or was never written (a refit replaces the whole
    fit folder, the stamp with it)."""
    from cpas_bayes.outputs.fit_figures import write_fit_figures

    job, fitted = job_and_fit
    test, config, out, bundle_key, fit_key, diag_key = job
    log, records = [], []
    reduced = _reduction_from(test, fitted)

    def work(folder):
        fit = load_baseline_fit(test, reduced(), folder, config)
        write_fit_figures(fit, folder, executor=executor, parts=("draws",))
    run_step(test_folder(out, test.name, "fit"), fit_key, work, records, f"{test.name} figures",
             report if report is not None else log.append, stamp=FIGURES_STAMP)
    return records, log


def _reduction_from(test, fitted):
    """The reduction :func:`fit_task` handed on (``fitted``: its result), or made here when it made none."""
    made = fitted[2] if fitted is not None else None
    return functools.cache(lambda: made if made is not None else reduce_test(test))


def test_steps(job, report=None, executor=None):
    """Reduce, fit, diagnose one test and draw its fit's figures in this process (``executor`` for the fit's
    ensembles, the diagnosis' fits and the figures); returns its step records and the messages not yet shown."""
    fitted = fit_task(job, report, executor)
    diagnosed = diagnosis_task((job, fitted), report, executor)
    drawn = figures_task((job, fitted), report, executor)
    return fitted[0] + diagnosed[0] + drawn[0], fitted[1] + diagnosed[1] + drawn[1]


def pooled_step_task(job, report=None):
    """A Monte Carlo of one configuration or the load comparison of one test (after the memo)."""
    kind, folder, key, name, args = job
    work = _montecarlo_work(*args) if kind == "montecarlo" else _compare_work(*args)
    log = []
    records = []
    run_step(folder, key, work, records, name, report if report is not None else log.append)
    return records, log


def collect(results, records, echo):
    """Add the tasks' step records in task order; show the messages they could not send as they ran."""
    for recs, log, *_ in results:
        records.extend(recs)
        for message in log:
            echo(message)

"""The main job: a folder of flight-test bundles in, a model memo and an evidence report out.

``run_campaign(DIR, OUT, config)`` (``cpas-bayes campaign DIR --out OUT``):

1. validate every bundle in DIR (all problems reported together, nothing run);
2. per test: reduce, fit (posterior + checks), diagnose (a logger bundle's with
   the terms that apply to it: breathing and the discrepancy), draw the fit's
   figures (on workers: three chained tasks, the figures last);
3. pool the fits by parachute kind and stage into the memo (the fit of a test
   whose diagnosis names a *measurement* cause — friction drift, sensor lag —
   is replaced by its extended fit, whose inflation parameters are free of it;
   physical causes the Monte Carlo does not fly are reported, not pooled away;
   a test with an ``unexplained`` misfit is pooled as it is and flagged in
   the manifest's ``flags`` and the report);
4. per cluster configuration: Monte Carlo with n_p dispersed and the n_p vs n
   fill-time comparison; per test: the load comparison (memo and own fit);
5. the report (:mod:`cpas_bayes.outputs.report`).

Every step writes into its own folder under OUT through a temporary folder
renamed into place, with ``stamp.json`` holding the content hash of its
inputs: the bytes of the bundle, the prior files, the options and the package
version, chained through the steps that feed it. A rerun skips every step
whose hash is unchanged, so adding one test costs one fit (plus the pooled
steps, which depend on all tests). Fit checkpoints live in
``OUT/.checkpoints`` so an interrupted fit resumes.

OUT follows the output-folder rule of :mod:`cpas_bayes.core.ownership` (new,
empty, or written by cpas-bayes), and every path built from a name in the
data (test names, parachute kinds) is checked to stay inside it.

Layout of OUT::

    campaign.json                  manifest: tests, steps, hashes, timings
    index.html, report.md          the report
    tests/<test>/reduction/        reduced.csv, reduction.json, reduction.png
    tests/<test>/fit/              posterior.nc, summary.json, checks.json, map.json, figures
                                   (figures.json: the fit's key once the draws' figures are drawn)
    tests/<test>/diagnosis/        diagnosis.json, diagnosis.md, figures (+ extended/ fit if named)
    tests/<test>/compare/          compare.json, compare.png
    memo/                          memo.toml, memo_draws.csv, memo.md, forest plots
    montecarlo/<config>/           runs.csv, summary.json, peak_loads.png, fill_times.png,
                                   np_vs_n.json, fill_time_np_vs_n.png
"""

from __future__ import annotations

import time as _time
import unicodedata
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from cpas_bayes import __version__
from cpas_bayes.app.campaign_config import CampaignConfig
from cpas_bayes.app.campaign_steps import (StepRecord, bundle_digest, collect, diagnosis_task, digest, figures_task,
                                           fit_task, folder_digest, pooled_step_task, run_step, test_cost,
                                           test_folder, test_steps)
from cpas_bayes.core.errors import InputError
from cpas_bayes.core.files import write_json
from cpas_bayes.core.inputs import inside, read_json
from cpas_bayes.core.ownership import check_output, check_outside_inputs, claim_folder
from cpas_bayes.data.bundle import TOML_NAME, read_bundle
from cpas_bayes.data.bundle_csv import bundle_folders
from cpas_bayes.stats.model_terms import EXTENSIONS

MEASUREMENT_CAUSES = ("friction_drift", "sensor_lag")


# ---------------------------------------------------------------------------
# hashing


def priors_digest(config: CampaignConfig) -> str:
    from cpas_bayes.stats.priors import PRIORS_DIR

    parts = [folder_digest(PRIORS_DIR)]
    if config.priors:
        parts.append(Path(config.priors).read_bytes())
    return digest(*parts)


# ---------------------------------------------------------------------------
# discovery


def find_bundles(folder) -> list:
    """Bundle folders in ``folder`` (itself, or its sub-folders holding a test.toml), sorted."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "", "not a folder", "give the folder that holds the test bundles")
    found = bundle_folders(folder)
    if not found:
        raise InputError(folder, "", f"no bundle (a folder with {TOML_NAME}) inside",
                         "put one folder per flight test in it (docs/test-bundle.md)")
    return found


def validate_all(paths):
    """Read every bundle; raise one InputError listing every bad one."""
    tests, problems = [], []
    for p in paths:
        try:
            tests.append(read_bundle(p))
        except InputError as exc:
            problems.append(str(exc))
    if problems:
        raise InputError(Path(paths[0]).parent, f"{len(problems)} of {len(paths)} bundles",
                         "invalid:\n  " + "\n  ".join(problems),
                         "fix or remove them (cpas-bayes validate BUNDLE shows one at a time)")
    # compared as a case-insensitive file system would: 'T1' and 't1' would share one folder there
    keys = [unicodedata.normalize("NFC", t.name).casefold() for t in tests]
    dupes = sorted({t.name for t, k in zip(tests, keys) if keys.count(k) > 1})
    if dupes:
        raise InputError(Path(paths[0]).parent, f"test names {dupes}", "used by more than one bundle (names that "
                         "differ only in upper/lower case count as the same: they would share one output folder)",
                         "give every bundle its own [test] name")
    return tests


def check_run_counts(tests, config, workers=1):
    """Refuse, before any step, Monte Carlo and comparison run counts beyond :mod:`cpas_bayes.loads.budget`'s
    limits for these tests' configurations, with ``workers`` pooled steps side by side."""
    from cpas_bayes.loads.budget import check_runs
    from cpas_bayes.loads.montecarlo import ClusterLayout

    layouts = {}
    for test in tests:
        layouts.setdefault(configuration_of(test), []).append(ClusterLayout.from_test(test))
    parallel = max(1, min(int(workers), len(layouts) + len(tests)))
    for group in layouts.values():
        check_runs(group[0], config.montecarlo_runs, results=3, table=True, parallel=parallel,
                   source="campaign options", where="key 'montecarlo.runs'")
        for layout in group:
            check_runs(layout, config.compare_runs, results=2, parallel=parallel, source="campaign options",
                       where="key 'compare.runs'", what="load comparison")


def configuration_of(test) -> str:
    """A name for the cluster configuration flown: kinds × count and stage count, e.g. ``2xdrogue-2st``."""
    kinds = {}
    for p in test.parachutes:
        kinds.setdefault(p.kind, []).append(len(p.stages))
    return "+".join(f"{len(v)}x{k}-{max(v)}st" for k, v in sorted(kinds.items()))


# ---------------------------------------------------------------------------
# the campaign


@dataclass
class CampaignResult:
    out: Path
    tests: list
    causes: dict                # test → list of causes ([] none; None without a diagnosis)
    flags: dict = field(default_factory=dict)   # test → pool_flags codes
    steps: list = field(default_factory=list)
    report: Path | None = None
    seconds: float = 0.0


UNEXPLAINED = "unexplained"


def diagnosed_causes(out, test_name):
    """The causes a test's ``diagnosis.json`` names, in its order (None without a diagnosis; [] for none).

    Reads the key ``causes`` (a list of catalogued terms, possibly followed by
    ``"unexplained"``, or ``"unexplained"`` alone); a file written before that key
    existed gives ``[cause]``, or [] for ``"none"``. Refuses a damaged file or a
    name that is neither a catalogued term nor ``"unexplained"``.
    """
    diag = test_folder(out, test_name, "diagnosis")
    doc = diag / "diagnosis.json"
    if not doc.is_file():
        return None
    fix = f"delete {diag} and re-run the campaign"
    data = read_json(doc, fix, what="diagnosis")
    if not isinstance(data, dict):
        raise InputError(doc, "", "not a JSON object", fix)
    if "causes" in data and data["causes"] is not None:
        key, causes = "causes", data["causes"]
        if not isinstance(causes, list) or not all(isinstance(c, str) for c in causes):
            raise InputError(doc, "key 'causes'", "not a list of names", fix)
    else:
        key, cause = "cause", data.get("cause")
        causes = [] if cause == "none" else [cause]
    for cause in causes:
        if cause != UNEXPLAINED and cause not in EXTENSIONS:
            raise InputError(doc, f"key {key!r}", f"{cause!r:.40} is not 'none', 'unexplained' or a catalogued "
                             f"term ({', '.join(EXTENSIONS)})", fix)
    return list(causes)


def verdict_of(causes):
    """``"none"``, ``"named"`` (a catalogued term among the causes) or ``"unexplained"``; None without a diagnosis."""
    if causes is None:
        return None
    if any(c != UNEXPLAINED for c in causes):
        return "named"
    return UNEXPLAINED if causes else "none"


def diagnosed_cause(out, test_name):
    """The first cause a test's ``diagnosis.json`` names, ``'none'`` for none (None without a diagnosis)."""
    causes = diagnosed_causes(out, test_name)
    return None if causes is None else (causes[0] if causes else "none")


def pooled_fit_folder(out, test_name):
    """The fit a test contributes to the memo: its extended fit when a measurement cause was named."""
    diag = test_folder(out, test_name, "diagnosis")
    causes = diagnosed_causes(out, test_name) or []
    if any(c in MEASUREMENT_CAUSES for c in causes) and (diag / "extended").is_dir():
        return diag / "extended"
    return test_folder(out, test_name, "fit")


def pool_flags(out, test_name):
    """Why a test's contribution to the memo deserves a second look: a list of short codes ([] for none).

    ``"unexplained"``: the diagnosis found a misfit no catalogued term explains, so
    the pooled fit (baseline, or extended for a measurement cause) still carries it;
    ``"no_extended_fit"``: a measurement cause was named but no extended fit was
    written, so the baseline fit was pooled.
    """
    causes = diagnosed_causes(out, test_name) or []
    flags = []
    if UNEXPLAINED in causes:
        flags.append("unexplained")
    if (any(c in MEASUREMENT_CAUSES for c in causes)
            and not (test_folder(out, test_name, "diagnosis", "extended")).is_dir()):
        flags.append("no_extended_fit")
    return flags


def run_campaign(folder, out, config: CampaignConfig = CampaignConfig(), echo=print,
                 executor=None) -> CampaignResult:
    """Run (or resume) the campaign of the bundles in ``folder`` into ``out``; return what was done.

    ``executor`` (:mod:`cpas_bayes.core.executor`; default ``config.workers`` local
    processes) runs the tests side by side, each as three chained tasks (fit,
    diagnosis, the fit's draw figures) — or, with fewer tests than workers,
    one test at a time with its ensembles side by side — and then the pool's
    tasks and the Monte Carlo and load comparison steps. Results do not depend on it.
    """
    from cpas_bayes.core.executor import make_executor

    own = executor is None
    executor = executor if executor is not None else make_executor(config.workers)
    try:
        return _run_campaign(folder, Path(out), config, echo, executor)
    finally:
        if own:
            executor.close()


def _run_campaign(folder, out, config, echo, executor) -> CampaignResult:
    from cpas_bayes.core.task_clock import TaskClock
    from cpas_bayes.outputs.report import write_report
    from cpas_bayes.stats.priors import check_override_applies, priors_of_test

    started = _time.perf_counter()
    check_output(out)
    paths = find_bundles(folder)
    check_outside_inputs(out, paths)   # its outputs never among a bundle's files
    tests = validate_all(paths)
    for t in tests:   # a bad or missing prior file: before any step
        priors_of_test(t, config.priors)
    check_override_applies(config.priors, [p.kind for t in tests for p in t.parachutes],
                           "remove 'priors' from the campaign's configuration")
    configs = {}
    for path, test in zip(paths, tests):
        test_folder(out, test.name)  # every path from a name checked before anything runs
        name = configuration_of(test)
        inside(out / "montecarlo", name)
        configs.setdefault(name, (path, test))
    check_run_counts(tests, config, executor.workers)
    claim_folder(out)
    echo(f"{len(tests)} bundles valid in {folder}; running on {executor.describe()}")
    records: list[StepRecord] = []
    prior_key = priors_digest(config)
    options = asdict(config)
    fit_keys, diag_keys = {}, {}
    jobs = []
    for path, test in zip(paths, tests):
        bundle_key = digest(bundle_digest(path, test.priors_files), __version__)
        fit_opts = {k: options[k] for k in ("seed", "decay", "fit_ensembles", "fit_max_steps", "fit_tau_factor",
                                            "fit_check_every")}
        if config.below_previous != CampaignConfig.below_previous:   # keyed only when set: default keys unchanged
            fit_opts["below_previous"] = config.below_previous
        if config.fit_stop != "tau":   # fits of the τ rule, the only rule before the ESS rule, keep their keys
            fit_opts.update(fit_stop=config.fit_stop, fit_ess_target=config.fit_ess_target)
            if config.fit_proposal != "de":  # fits of DE alone, the only proposal before, keep their keys
                fit_opts["fit_proposal"] = config.fit_proposal
        if config.fit_coordinates != "model":   # fits sampled in θ as written, the only way before, keep their keys
            fit_opts["fit_coordinates"] = config.fit_coordinates
        fit_keys[test.name] = digest(bundle_key, prior_key, fit_opts)
        if config.diagnose != "off":
            diag_keys[test.name] = digest(fit_keys[test.name], config.diagnose, list(config.candidates))
        jobs.append((test, config, out, bundle_key, fit_keys[test.name], diag_keys.get(test.name)))
    if executor.workers > 1 and len(jobs) >= executor.workers:
        # fits first, each diagnosis once its fit is done, the fits' draw figures last: the phase ends on
        # small figure tasks, not on whole tests
        results = executor.map_chained(fit_task, (diagnosis_task, figures_task), jobs,
                                       [test_cost(j[0]) for j in jobs], desc="tests", on_report=echo)
        # per test: its three tasks' step records, then their messages, each in task order
        results = [([rec for task in rows for rec in task[0]], [m for task in rows for m in task[1]])
                   for rows in results]
    else:  # fewer tests than workers: one test at a time, each fit's ensembles side by side
        results = [test_steps(job, echo, executor) for job in jobs]
    collect(results, records, echo)
    causes = {test.name: diagnosed_causes(out, test.name) for test in tests}
    flags = {test.name: pool_flags(out, test.name) for test in tests}

    pool_sources = {t.name: pooled_fit_folder(out, t.name) for t in tests}
    pool_key = digest(sorted(fit_keys.items()), sorted(diag_keys.items()), config.pool_draws, config.seed)

    clock = TaskClock(executor)   # what the pool spends in its own tasks can spread over workers

    def pool_work(tmp):
        from cpas_bayes.outputs.memo import write_pool
        from cpas_bayes.population.pool import pool_folders

        result = pool_folders([pool_sources[t.name] for t in tests], seed=config.seed, n_draws=config.pool_draws,
                              executor=clock)
        write_pool(result, tmp, provenance={"campaign": str(folder), "tests": [t.name for t in tests],
                                            "fits": {k: str(v.relative_to(out)) for k, v in pool_sources.items()}},
                   executor=clock)
    echo("memo:")
    if run_step(out / "memo", pool_key, pool_work, records, "pool", echo) and clock.seconds:
        records[-1] = replace(records[-1], task_seconds=sum(clock.seconds), tasks=len(clock.seconds),
                              longest_task_seconds=max(clock.seconds))

    echo("Monte Carlo and load comparisons:")
    jobs = []
    for name, (path, like) in configs.items():
        key = digest(pool_key, bundle_digest(path), config.montecarlo_runs, config.seed)
        jobs.append(("montecarlo", inside(out / "montecarlo", name), key,
                     f"Monte Carlo {name} ({config.montecarlo_runs} runs)", (like, out / "memo", config)))
    for test in tests:
        key = digest(pool_key, fit_keys[test.name], config.compare_runs, config.seed)
        jobs.append(("compare", test_folder(out, test.name, "compare"), key, f"{test.name} load comparison",
                     (test, out / "memo", test_folder(out, test.name, "fit"), config)))
    collect(executor.map(pooled_step_task, jobs, desc="steps", on_report=echo), records, echo)
    seconds = _time.perf_counter() - started
    manifest = {"campaign": config.name or Path(folder).name, "folder": str(folder), "version": __version__,
                "config": options, "tests": [t.name for t in tests],
                "configurations": {k: v[1].name for k, v in configs.items()},
                "causes": causes, "verdicts": {k: verdict_of(v) for k, v in causes.items()},
                "flags": flags, "pooled_fits": {k: str(v.relative_to(out)) for k, v in pool_sources.items()},
                "steps": [asdict(r) for r in records], "seconds": seconds}
    write_json(out / "campaign.json", manifest)
    report = write_report(out)
    echo(f"report: {report}")
    return CampaignResult(out=out, tests=[t.name for t in tests], causes=causes, flags=flags, steps=records,
                          report=report, seconds=_time.perf_counter() - started)

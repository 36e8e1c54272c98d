"""Benchmarks of cpas_bayes on this machine: prints a table and writes JSON.

    python benchmarks/run.py [--out benchmarks/results.json] [--only fit_drogue,fit_main]

Measured (not timed tests):
* fit_drogue / fit_main: wall time of a full posterior (MAP, 4 ensembles to 50 τ,
  DataTree; 2 worker processes) on the bundled two-Drogue and three-Main
  examples, ESS per second (minimum bulk ESS over parameters / wall time),
  and in the same run a Nelder–Mead point fit of the same model (scipy, from
  the same first guess): once with fminsearch's default budget (200·D
  evaluations), and restarted from its own result until a restart gains
  less than 0.01 in log posterior (a converged point fit). The ratio
  posterior / converged point fit is the headline; the single run is shown
  because it is what a script with default options returns.
* diagnose_drogue / diagnose_main: wall time of ``cpas-bayes diagnose`` (mode
  full: baseline, the generic discrepancy, the model forms, every catalogued
  term whose MAP rises by > 5 sampled with the discrepancy, forward selection,
  PSIS-LOO, gain, no figures) on the same examples; and in mode screen.

* fit_command_drogue / fit_command_main: wall time of the whole command a user
  types, ``cpas-bayes fit BUNDLE --out DIR`` (a fresh process: imports, MAP,
  sampling under the default ESS rule, DataTree, checks and every figure); the
  median of five runs.
* step_cost: one ensemble of the two-Drogue fit in this process, 2,000 steps
  from the MAP's ball: time per step, of it the log posterior's, and the rest
  (the sampler's own bookkeeping), with emcee's DEMove and with the package's
  vectorised move (the same proposal law; :mod:`cpas_bayes.inference.moves`).
* term_cost: one log posterior call of 2·D + 2 walkers for the diagnosis' models with an added mass and
  a load-cell lag (alone, together, with the discrepancy) on a synthetic Drogue and Main pair (seed 30015),
  and with canopy breathing (alone, with the discrepancy, beside a lag; seed 30000).
* campaign: ``--campaign-tests`` (50) synthetic two-Drogue tests (the
  package's simulator, seeds 5000…, no hidden effect) through the main job
  with the default campaign options on 2 workers, timed end to end; from the
  campaign's own step timings, the serial fraction and the efficiency that
  Amdahl's law predicts for 4, 16 and 64 workers (T(N) = S + max(W/N, the
  longest test), S what runs alone, W the work spread over workers: the tests'
  steps, the Monte Carlo and comparisons, and the pool's own tasks, timed
  where they ran; also the same law with the whole pool step counted serial).

* montecarlo_main: 10,000 runs of the three-Main cluster (the bundled example's
  configuration, a memo with the example's ranges) in this process and on 2
  worker processes: runs per second.
* parallel: the same work in this process and on 2 worker processes — 4
  ensembles of the two-Drogue fit with a fixed 2,000 steps from the same
  MAP, and 100,000 Monte Carlo runs (one numba thread in this process) —
  parallel efficiency T₁ / (2·T₂). The serial MAP search before the
  ensembles is not in it (fit_drogue's wall time includes it).

Results are merged into the JSON file, so ``--only`` refreshes some entries.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy import optimize

from cpas_bayes import __version__
from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.data.bundle import example_bundles, read_bundle
from cpas_bayes.inference.fit import SamplerOptions, fit_model, prepare_model
from cpas_bayes.inference.start import first_guess


def nelder_mead_point_fit(model, gain_tol=0.01, max_restarts=100):
    """The in-house practice: fminsearch-style Nelder–Mead on −log posterior from the first guess.

    Returns the first run (default budget 200·D evaluations) and the restarted
    fit (each restart from the last result, until it gains < ``gain_tol``).
    """
    x = first_guess(model)
    budget = 200 * model.ndim
    t0 = time.perf_counter()
    runs = []
    for _ in range(max_restarts):
        res = optimize.minimize(lambda z: -model(z[None])[0], x, method="Nelder-Mead",
                                options={"maxiter": budget, "maxfev": budget, "adaptive": True})
        runs.append((time.perf_counter() - t0, -float(res.fun), int(res.nfev)))
        gained = -res.fun - (runs[-2][1] if len(runs) > 1 else -np.inf)
        x = res.x
        if len(runs) > 1 and gained < gain_tol:
            break
    first = runs[0]
    return {"single_wall_s": first[0], "single_log_post": first[1], "single_evaluations": first[2],
            "converged_wall_s": runs[-1][0], "converged_log_post": runs[-1][1], "restarts": len(runs),
            "converged_evaluations": sum(r[2] for r in runs)}


def bench_fit(path):
    test = read_bundle(path)
    model = prepare_model(test, reduce_test(test))
    model(first_guess(model)[None])  # compile outside the clocks
    nm = nelder_mead_point_fit(model)
    t0 = time.perf_counter()
    fit = fit_model(model, SamplerOptions(seed=0, progress=False))  # its 2 workers start inside the clock
    wall = time.perf_counter() - t0
    d = fit.summary["diagnostics"]
    return {"test": test.name, "parameters": model.ndim, "bins": int(model.obs.n_bins),
            "posterior_wall_s": wall, "ess_bulk_min": d["ess_bulk_min"], "ess_per_s": d["ess_bulk_min"] / wall,
            "rhat_max": d["rhat_max"], "tau_max_steps": d["tau_max"], "steps_per_ensemble": d["steps"],
            "converged": d["converged"], "map_log_post": fit.sampling.log_post_map,
            "nelder_mead": nm, "posterior_over_point_fit": wall / nm["converged_wall_s"],
            "posterior_over_single_nelder_mead": wall / nm["single_wall_s"]}


COMMAND_RUNS = 5   # the whole command is timed this many times and the median reported: one run varies by ±15 %


def bench_fit_command(path, runs=COMMAND_RUNS):
    import subprocess
    import tempfile

    walls = []
    for _ in range(runs):
        with tempfile.TemporaryDirectory() as tmp:
            command = [sys.executable, "-m", "cpas_bayes", "fit", str(path), "--out", str(Path(tmp) / "fit")]
            t0 = time.perf_counter()
            subprocess.run(command, check=True, capture_output=True)
            walls.append(time.perf_counter() - t0)
            summary = json.loads((Path(tmp) / "fit" / "summary.json").read_text())
            figures = len(list((Path(tmp) / "fit").glob("*.png")))
    d = summary["diagnostics"]
    wall = float(np.median(walls))
    return {"test": path.name, "wall_s": wall, "walls_s": walls, "figures": figures, "steps_per_ensemble": d["steps"],
            "rhat_max": d["rhat_max"], "ess_bulk_min": d["ess_bulk_min"],
            "summary": f"cpas-bayes fit, whole command, median of {runs} runs "
                       f"({', '.join(f'{w:.1f}' for w in walls)} s): {len(d['steps'])} ensembles of "
                       f"{max(d['steps'])} steps, {figures} figures, R-hat {d['rhat_max']:.4f}"}


def bench_step_cost():
    import emcee

    from cpas_bayes.inference.moves import VectorisedDEMove
    from cpas_bayes.inference.start import find_map, initial_walkers, laplace_covariance

    test = read_bundle(next(p for p in example_bundles() if p.name.startswith("drogue")))
    model = prepare_model(test, reduce_test(test))
    theta, _ = find_map(model, np.random.default_rng(0), 2)
    walkers = 2 * model.ndim + 2
    init = initial_walkers(model, theta, laplace_covariance(model, theta), walkers, np.random.default_rng(1))
    out = {}
    for name, move in (("emcee_demove", emcee.moves.DEMove()), ("vectorised_demove", VectorisedDEMove())):
        spent = [0.0]

        def log_post(x):
            t = time.perf_counter()
            value = model(x)
            spent[0] += time.perf_counter() - t
            return value

        sampler = emcee.EnsembleSampler(walkers, model.ndim, log_post, vectorize=True, moves=[(move, 1.0)])
        sampler.run_mcmc(init, 200, progress=False)
        spent[0] = 0.0
        t0 = time.perf_counter()
        sampler.run_mcmc(None, 2000, progress=False, thin_by=5)   # 10,000 steps, every fifth stored
        wall = time.perf_counter() - t0
        out[name] = {"step_ms": 1e3 * wall / 10000, "log_posterior_ms": 1e3 * spent[0] / 10000,
                     "overhead_ms": 1e3 * (wall - spent[0]) / 10000,
                     "acceptance": float(np.mean(sampler.acceptance_fraction))}
    a, b = out["emcee_demove"], out["vectorised_demove"]
    return {**out, "walkers": walkers,
            "summary": f"per step of {walkers} walkers: log posterior {b['log_posterior_ms']:.2f} ms; sampler "
                       f"overhead {a['overhead_ms']:.2f} ms with emcee's DEMove, {b['overhead_ms']:.2f} ms "
                       f"vectorised (acceptance {a['acceptance']:.3f} / {b['acceptance']:.3f})"}


def makespan(durations, workers):
    """Wall time of tasks handed in order to the first free of ``workers`` (what the executor's map does)."""
    free = [0.0] * max(1, workers)
    for d in durations:
        i = free.index(min(free))
        free[i] += d
    return max(free)


def chained_makespan(firsts, thens, workers):
    """Wall time of chained tasks dispatched as ``Executor.map_chained`` does with equal costs: every first
    task, in order, to the first free worker; then, whenever a worker is free, the ready task of the
    highest-priority later kind, in the order the firsts finished. ``thens``: per later kind (in priority
    order) the items' durations."""
    import heapq
    from collections import deque

    n = len(firsts)
    ready = [deque() for _ in thens]
    running, idle, now, end, next_first, seq = [], max(1, workers), 0.0, 0.0, 0, 0
    while True:
        while idle and (next_first < n or any(ready)):
            if next_first < n:
                stage, i, next_first = 0, next_first, next_first + 1
                took = firsts[i]
            else:
                k = next(k for k, r in enumerate(ready) if r)
                stage, i = 1 + k, ready[k].popleft()
                took = thens[k][i]
            heapq.heappush(running, (now + took, seq, stage, i))
            seq += 1
            idle -= 1
        if not running:
            return end
        now, _, stage, i = heapq.heappop(running)
        end = max(end, now)
        idle += 1
        if stage == 0:
            for r in ready:
                r.append(i)


def amdahl(steps, wall, workers):
    """Serial part and predicted efficiency from a campaign's step records (campaign.json "steps").

    The campaign runs in three phases, each a set of tasks on the workers: the tests (each its reduction
    and fit in one task, its diagnosis in a second and the fit's draw figures in a third, both started once
    the first is done, the figures last: :func:`chained_makespan`),
    the pool (its own tasks, ``task_seconds``, with the rest of the pool step
    in the calling process), and the Monte Carlo and load comparisons. Each phase's wall time on N workers
    is predicted by handing its measured task times, in the campaign's order, to the first free worker
    (:func:`makespan`), so the imbalance at the end of a phase is predicted for N workers rather than
    counted as serial. S, the serial part, is what runs alone: the pool step less its tasks, plus the wall
    time the three phases' makespans on the measured workers leave unexplained (validation, starting the
    workers, the hand-offs, the report). T(N) = S + Σ makespan_N, T(1) = S + all the tasks' work,
    efficiency T(1)/(N·T(N)). ``conservative``: the law as first reported here, T(N) = S' + max(W/N,
    longest test) with the whole pool step and the measured phases' imbalance counted as serial.
    """
    tests, fits, diagnoses, figures, after = {}, {}, {}, {}, []
    pooled, pool_tasks, pool_serial, pool_longest = 0.0, 0.0, 0.0, 0.0
    n_pool_tasks = 0
    for r in steps:
        if r["name"] == "pool":
            work = r.get("task_seconds") or 0.0
            pooled += r["seconds"]
            pool_tasks += work
            n_pool_tasks += r.get("tasks") or 0
            pool_longest = max(pool_longest, r.get("longest_task_seconds") or 0.0)
            pool_serial += max(0.0, r["seconds"] - work / workers)
        elif r["name"].endswith((" reduction", " fit", " diagnosis", " figures")):
            test, step = r["name"].rsplit(" ", 1)
            tests[test] = tests.get(test, 0.0) + r["seconds"]
            part = {"diagnosis": diagnoses, "figures": figures}.get(step, fits)
            part[test] = part.get(test, 0.0) + r["seconds"]
        else:
            after.append(r["seconds"])

    def pool_span(n):   # the pool's tasks are recorded as a sum, a count and the longest
        return max(pool_tasks / n, pool_longest) if n_pool_tasks else 0.0

    def phases(n):
        names = list(tests)
        later = [[diagnoses.get(t, 0.0) for t in names], [figures.get(t, 0.0) for t in names]]
        return (chained_makespan([fits.get(t, 0.0) for t in names], later, n)
                + pool_span(n) + makespan(after, n))

    work = sum(tests.values()) + sum(after) + pool_tasks
    serial = pool_serial + max(0.0, wall - pool_serial - phases(workers))
    predicted = {n: (serial + work) / (n * (serial + phases(n))) for n in (4, 16, 64)}
    # the earlier law, kept for comparison
    spread = sum(tests.values()) + sum(after)
    unaccounted = max(0.0, wall - pooled - spread / workers)
    longest = max(tests.values(), default=0.0)
    t1 = pooled + unaccounted + spread
    conservative = {n: t1 / (n * (pooled + unaccounted + max(spread / n, longest))) for n in (4, 16, 64)}
    fraction = serial / (serial + work)
    return {"serial_s": serial, "spread_s": work, "pool_s": pooled, "pool_task_s": pool_tasks,
            "unaccounted_s": serial - pool_serial, "longest_test_s": longest,
            "makespans_s": {n: phases(n) for n in (workers, 4, 16, 64)},
            "serial_fraction": fraction, "predicted_efficiency": predicted,
            "amdahl_efficiency": amdahl_law(fraction),
            "predicted_efficiency_pool_serial": conservative}


def amdahl_law(serial_fraction, sizes=(4, 16, 64)):
    """Amdahl's law alone, E(N) = 1 / (N·s + 1 − s): every task divisible, only the serial fraction s counts."""
    return {n: 1.0 / (n * serial_fraction + 1.0 - serial_fraction) for n in sizes}


def bench_campaign(n_tests):
    import tempfile

    from cpas_bayes.app.campaign import CampaignConfig, run_campaign
    from cpas_bayes.data.bundle_write import write_bundle
    from cpas_bayes.data.synth import synthesize

    with tempfile.TemporaryDirectory() as tmp:
        bundles = Path(tmp) / "bundles"
        for i in range(n_tests):
            test, _ = synthesize("drogue", "none", 5000 + i, name=f"BENCH-D{i + 1:02d}")
            write_bundle(test, bundles / test.name)
        config = CampaignConfig(workers=2)
        t0 = time.perf_counter()
        run_campaign(bundles, Path(tmp) / "out", config, echo=lambda *a: None)
        wall = time.perf_counter() - t0
        manifest = json.loads((Path(tmp) / "out" / "campaign.json").read_text())
    steps = manifest["steps"]
    by_kind = {}
    for r in steps:
        kind = r["name"].rsplit(" ", 1)[-1] if r["name"] != "pool" else "pool"
        kind = "montecarlo" if r["name"].startswith("Monte Carlo") else kind
        by_kind[kind] = by_kind.get(kind, 0.0) + r["seconds"]
    law = amdahl(steps, wall, config.workers)
    eff = law["predicted_efficiency"]
    return {"tests": n_tests, "workers": config.workers, "diagnose": config.diagnose, "wall_s": wall,
            "per_test_s": wall / n_tests, "step_seconds": by_kind, **law,
            "summary": f"{n_tests} two-Drogue tests, default options on {config.workers} workers: "
                       f"{wall / n_tests:.1f} s per test; serial fraction {100 * law['serial_fraction']:.1f} %, "
                       f"predicted efficiency {100 * eff[4]:.0f} / {100 * eff[16]:.0f} / {100 * eff[64]:.0f} % "
                       f"on 4 / 16 / 64 workers with the measured tasks scheduled (Amdahl's law alone: "
                       f"{' / '.join(f'{100 * v:.0f}' for v in law['amdahl_efficiency'].values())} %; the earlier "
                       "law, whole pool step serial: "
                       f"{' / '.join(f'{100 * v:.0f}' for v in law['predicted_efficiency_pool_serial'].values())} %)"}


def bench_diagnose(path, mode):
    from dataclasses import replace

    from cpas_bayes.inference.candidate_fits import DIAGNOSIS_SAMPLER, DiagnoseOptions
    from cpas_bayes.inference.diagnose import diagnose_test

    test = read_bundle(path)
    t0 = time.perf_counter()
    d = diagnose_test(test, DiagnoseOptions(mode=mode, sampler=replace(DIAGNOSIS_SAMPLER, progress=False)))
    wall = time.perf_counter() - t0
    return {"test": test.name, "mode": mode, "wall_s": wall, "cause": d.cause, "causes": d.causes,
            "verdict": d.verdict, "models_sampled": sorted(d.candidates), "model_forms": d.model_forms,
            "elpd_diff": {r["name"]: r["elpd_diff"] for r in d.versus_baseline.to_dict("records")},
            "summary": f"{d.verdict} ({', '.join(d.causes) or 'none'}); {len(d.candidates)} models sampled "
                       f"beside the baseline and {len(d.model_forms)} model forms"}


def _main_memo():
    """A memo spanning the bundled three-Main example's inflation parameters (uniform families)."""
    import pandas as pd

    from cpas_bayes.population.memo import Memo, MemoEntry

    spec = {"parachute": {"cd_o": (0.50, 0.54)},
            "first": {"n_p": (14.0, 21.0), "n": (14.0, 21.0), "expopen": (1.6, 2.9), "eps": (0.05, 0.07)},
            "reefed1": {"n_p": (8.0, 13.0), "n": (8.0, 13.0), "expopen": (1.6, 2.9), "eps": (0.18, 0.20)},
            "full_open": {"n_p": (6.0, 7.5), "n": (6.0, 7.5), "expopen": (1.4, 1.8)}}
    rng = np.random.default_rng(1)
    entries, cols = {}, {}
    for stage, params in spec.items():
        for parameter, (low, high) in params.items():
            entry = MemoEntry("main", stage, parameter, "uniform", {"low": low, "high": high}, (low, high))
            entries[("main", stage, parameter)] = entry
            cols[f"{stage}.{parameter}"] = entry.sample(rng, 4000)
    frame = pd.DataFrame(cols)
    frame.insert(0, "kind", "main")
    return Memo(entries, frame, {"method": "benchmark ranges"})


def _time_monte_carlo(runs, executor):
    from cpas_bayes.loads.montecarlo import run_monte_carlo
    from cpas_bayes.physics.engine import ensure_compiled

    like = read_bundle(next(p for p in example_bundles() if p.name.startswith("main")))
    ensure_compiled()
    t0 = time.perf_counter()
    run_monte_carlo(_main_memo(), like, runs, np.random.default_rng(0), progress=False, executor=executor)
    return time.perf_counter() - t0


def bench_montecarlo():
    from cpas_bayes.core.executor import ProcessExecutor

    runs = 10000
    serial = _time_monte_carlo(runs, None)
    with ProcessExecutor(2) as ex:
        ex.map(abs, [1, 2])  # start the workers outside the clock
        pooled = _time_monte_carlo(runs, ex)
    return {"configuration": "3xmain-3st", "runs": runs, "wall_s": serial, "runs_per_s": runs / serial,
            "wall_s_2_workers": pooled, "runs_per_s_2_workers": runs / pooled,
            "summary": f"{runs / serial:,.0f} runs/s in one process, {runs / pooled:,.0f} on 2 workers"}


def bench_parallel():
    """Efficiency T1/(2·T2) of the parallel stages: ensembles of a fit (from the same MAP and walker
    balls), and Monte Carlo batches (one numba thread in the single-process run, for a fair T1)."""
    import numba

    from cpas_bayes.core.executor import Executor, ProcessExecutor
    from cpas_bayes.inference.fit import _ensemble_task
    from cpas_bayes.inference.start import find_map, initial_walkers, laplace_covariance

    test = read_bundle(next(p for p in example_bundles() if p.name.startswith("drogue")))
    model = prepare_model(test, reduce_test(test))
    options = SamplerOptions(seed=0, n_ensembles=4, max_steps=2000, check_every=500, stop="tau", tau_factor=1e9,
                             progress=False)
    theta, _ = find_map(model, np.random.default_rng(0), 2)
    cov = laplace_covariance(model, theta)
    jobs = [(model, initial_walkers(model, theta, cov, 2 * model.ndim + 2, np.random.default_rng(e)), e, options,
             None, f"ensemble {e}") for e in range(4)]
    timings = {}
    threads = numba.get_num_threads()
    for workers in (1, 2):
        with (Executor() if workers == 1 else ProcessExecutor(workers)) as ex:
            ex.map(abs, [1, 2])  # workers started outside the clock
            t0 = time.perf_counter()
            ex.map(_ensemble_task, jobs)
            timings[f"ensembles_{workers}"] = time.perf_counter() - t0
            numba.set_num_threads(1)
            timings[f"montecarlo_{workers}"] = _time_monte_carlo(100000, ex if workers > 1 else None)
            numba.set_num_threads(threads)
    fit_eff = timings["ensembles_1"] / (2 * timings["ensembles_2"])
    mc_eff = timings["montecarlo_1"] / (2 * timings["montecarlo_2"])
    return {**{f"{k}_wall_s": v for k, v in timings.items()}, "ensembles_efficiency": fit_eff,
            "montecarlo_efficiency": mc_eff,
            "summary": f"efficiency 1→2 workers: 4 fit ensembles {100 * fit_eff:.0f} %, "
                       f"100,000 Monte Carlo runs {100 * mc_eff:.0f} %"}


CAMPAIGN_TESTS = 50


TERM_MODELS = {("sensor_lag+added_mass", 30015): ("added_mass", "sensor_lag", "added_mass+sensor_lag",
                                                   "added_mass+sensor_lag+discrepancy"),
               ("sensor_lag+canopy_breathing", 30000): ("canopy_breathing", "canopy_breathing+discrepancy",
                                                        "sensor_lag+canopy_breathing+discrepancy")}


def bench_term_cost(calls=20):
    """One log posterior call of a batch of 2·D + 2 walkers near the prior medians, for the diagnosis' models
    with a term at lagged times (the load-cell lag beside an added mass, seed 30015) or a breathing canopy
    (beside a lag, seed 30000) on a synthetic Drogue pair and Main pair: the mean of ``calls`` calls after
    one to compile."""
    from cpas_bayes.data.synth import synthesize
    from cpas_bayes.stats.model_terms import make_extension

    out = {}
    for scenario in ("drogue", "main"):
        for (effect, seed), labels in TERM_MODELS.items():
            test, _ = synthesize(scenario, effect, seed)
            reduction = reduce_test(test)
            for label in labels:
                model = prepare_model(test, reduction, extensions=[make_extension(n) for n in label.split("+")])
                rng = np.random.default_rng(1)
                theta = np.array([p.prior.ppf(0.5) for p in model.parameters])
                rows = theta * (1 + 1e-3 * rng.standard_normal((2 * model.ndim + 2, model.ndim)))
                for name, value in {"lag": 0.02, "lag_response": 0.01, "k_a": 0.6, "mass_lag": 0.05}.items():
                    if name in model.index:
                        rows[:, model.index[name]] = value * (1 + 0.3 * rng.random(rows.shape[0]))
                model(rows)
                t0 = time.perf_counter()
                for _ in range(calls):
                    model(rows)
                out[f"{scenario}:{label}"] = 1e3 * (time.perf_counter() - t0) / calls
    return {"batch_ms": out, "summary": "; ".join(f"{k} {v:.1f} ms" for k, v in out.items())}


def _logger_bundle(scenario, seed, effect="none"):
    """A synthetic logger bundle (no q̄: accelerometer and GNSS) in a folder that lives as long as the process."""
    import tempfile

    from cpas_bayes.data.synth_logger import write_logger_synthetic

    folder = Path(tempfile.mkdtemp(prefix="cpas-bench-")) / f"{scenario}-{seed}"
    return write_logger_synthetic(scenario, seed, folder, effect=effect, magnitude=0.08 if effect != "none" else None)

BENCHES = {
    "fit_drogue": lambda: bench_fit(next(p for p in example_bundles() if p.name.startswith("drogue"))),
    "fit_main": lambda: bench_fit(next(p for p in example_bundles() if p.name.startswith("main"))),
    "fit_command_drogue": lambda: bench_fit_command(next(p for p in example_bundles()
                                                         if p.name.startswith("drogue"))),
    "fit_command_main": lambda: bench_fit_command(next(p for p in example_bundles() if p.name.startswith("main"))),
    "step_cost": bench_step_cost,
    "term_cost": bench_term_cost,
    "diagnose_drogue": lambda: bench_diagnose(next(p for p in example_bundles() if p.name.startswith("drogue")),
                                              "full"),
    "diagnose_main": lambda: bench_diagnose(next(p for p in example_bundles() if p.name.startswith("main")), "full"),
    "diagnose_screen_main": lambda: bench_diagnose(next(p for p in example_bundles() if p.name.startswith("main")),
                                                   "screen"),
    "fit_logger_drop": lambda: bench_fit(_logger_bundle("logger-drop", 3)),
    "fit_command_logger_drop": lambda: bench_fit_command(_logger_bundle("logger-drop", 3)),
    "diagnose_logger_drop": lambda: bench_diagnose(_logger_bundle("logger-drop", 3, "canopy_breathing"), "screen"),
    "montecarlo_main": bench_montecarlo,
    "parallel": bench_parallel,
    "campaign": lambda: bench_campaign(CAMPAIGN_TESTS),
}


def _write_json(path, results):
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(results, indent=2, default=float) + "\n")
    tmp.replace(path)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results.json"))
    parser.add_argument("--only", default=",".join(BENCHES), help="comma-separated subset of " + ", ".join(BENCHES))
    parser.add_argument("--campaign-tests", type=int, default=CAMPAIGN_TESTS,
                        help="tests in the campaign benchmark (default %(default)s)")
    args = parser.parse_args(argv)
    unknown = [n for n in args.only.split(",") if n not in BENCHES]
    if unknown:
        parser.error(f"unknown benchmark {unknown[0]!r}; choose from {', '.join(BENCHES)}")
    if args.campaign_tests < 1:
        parser.error("--campaign-tests must be at least 1")
    BENCHES["campaign"] = lambda: bench_campaign(args.campaign_tests)
    results = json.loads(args.out.read_text()) if args.out.is_file() else {}
    results["machine"] = {"cpus": os.cpu_count(), "platform": platform.platform(), "python": sys.version.split()[0],
                          "cpas_bayes": __version__}
    for name in args.only.split(","):
        print(f"running {name} ...", flush=True)
        results[name] = BENCHES[name]()
        _write_json(args.out, results)   # after each: a long run interrupted keeps what it measured
    print(f"\n{'benchmark':<22} {'wall [s]':>9}  notes")
    for name, r in results.items():
        if name == "machine":
            continue
        if "posterior_wall_s" in r:
            nm = r["nelder_mead"]
            print(f"{name:<22} {r['posterior_wall_s']:9.1f}  ESS/s {r['ess_per_s']:.0f}, R-hat {r['rhat_max']:.4f}; "
                  f"Nelder-Mead converged {nm['converged_wall_s']:.1f} s ({nm['restarts']} runs, ratio "
                  f"{r['posterior_over_point_fit']:.1f}), single run {nm['single_wall_s']:.1f} s stopping "
                  f"{r['map_log_post'] - nm['single_log_post']:.0f} short of the MAP's log p")
        elif "wall_s" in r:
            print(f"{name:<22} {r['wall_s']:9.1f}  {r['summary']}")
        else:
            print(f"{name:<22} {'':>9}  {r['summary']}")
    _write_json(args.out, results)
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())

"""Measured peak loads against predicted ones, with the measurement's own uncertainty (seed Fig. 17, 26, 31).

For a reduced flight test, every stage's measured peak load — the
accelerometer total (Eq. 6) with its Eq. 7 sigma, and the scaled load-cell
sum with its sigma, both from :func:`cpas_bayes.data.reduction.reduce_test` — is set
against predicted distributions of the same quantity from

* ``population``: the population predictive, a Monte Carlo of this test's
  configuration with parameter sets drawn from the model memo
  (:func:`cpas_bayes.loads.montecarlo.run_monte_carlo`): "would the memo have
  predicted this test?";
* ``posterior``: the posterior predictive of the test's own fit: the
  trajectory is simulated from the test's first data sample with parameter
  sets drawn jointly from the fit's posterior draws (``load_fit(FIT).draws``:
  ``<id>.cds_o``, ``<id>.s<k>.{start, n_p, expopen, ck, tk, eps}``,
  ``vehicle_weight``, ``vehicle_cds``), with n_p dispersed as in the fit.
  The fit itself computes each stage's fill time with the *measured*
  airspeed at the stage start; the simulation uses the simulated one, so the
  posterior predictive also tests the trajectory model. (Reconstructed loads
  with the measured q̄ would only restate the fit.)

The predicted peak of cluster stage k is the peak of the simulated total
Σ F_i from the earliest start of stage k to the earliest start of stage k+1
(the reduction's stage interval, on each run's own starts); by seed Eq. 6
and 10, Σ F_i = W_V·G − q̄·CDS_V is what the accelerometer channel measures.

Percentile of a measurement (accounting for its sigma)
------------------------------------------------------
A measured peak m carries an error e ~ N(0, σ²). The distribution to place
it in is therefore the predicted peaks X convolved with N(0, σ²), whose CDF
at m is, over the predicted draws x_j (j = 1…J)::

    percentile = 100 · P(X + e ≤ m) = 100 · (1/J) · Σ_j Φ((m − x_j)/σ)

(σ = 0 gives the empirical percentile, ties counted half). A measurement at
the predicted median reads ≈ 50; 2.5 or 97.5 is a 2-sigma-like surprise.

Probability that the prediction exceeds the measurement: with the true peak
L ~ N(m, σ²) given the measurement (flat prior), ::

    p_exceed = P(X > L) = (1/J) · Σ_j Φ((x_j − m)/σ) = 1 − percentile/100

``p_exceed_without_sigma`` = share of predicted draws above m is reported
beside it, and ``percentile_without_sigma`` likewise.

:mod:`cpas_bayes.outputs.compare` writes a comparison (``compare.json``,
``compare.png``; ``cpas-bayes compare``).
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field

import numpy as np
from scipy import special

from cpas_bayes.data.bundle import FlightTest
from cpas_bayes.core.errors import InputError
from cpas_bayes.core.summaries import quantile_summary
from cpas_bayes.population.memo import Memo
from cpas_bayes.loads.montecarlo import (QUANTILE_LEVELS, ClusterLayout, MonteCarloResult, assemble_inputs,
                                         run_monte_carlo, simulate_runs)
from cpas_bayes.inference.fit_folder import FitRecord, POSTERIOR_NAME, SUMMARY_NAME
from cpas_bayes.loads.budget import check_runs
from cpas_bayes.physics.engine import choose_engine, ensure_compiled
from cpas_bayes.data.reduction import Reduction, reduce_test
from cpas_bayes.physics.trajectory import SimulationOptions

SOURCES = ("population", "posterior")
CHANNELS = ("accelerometer", "load_cells")
DEFAULT_HISTORY_RUNS = 1000


# ---------------------------------------------------------------------------
# the statistics


def _normal_cdf(z):
    return 0.5 * special.erfc(-np.asarray(z, float) / math.sqrt(2.0))


def measurement_percentile(predicted, measured, sigma=0.0):
    """100·P(X + e ≤ m): the measured value's percentile in the predicted draws convolved with N(0, σ²).

    ``predicted`` draws x_j (non-finite ones dropped); ``sigma`` the
    measurement's 1-sigma. See the module notes.
    """
    x = np.asarray(predicted, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return math.nan
    if sigma > 0:
        return float(100.0 * np.mean(_normal_cdf((measured - x) / sigma)))
    return float(100.0 * (np.mean(x < measured) + 0.5 * np.mean(x == measured)))


def exceedance_probability(predicted, measured, sigma=0.0):
    """P(X > L), L ~ N(m, σ²) the true peak given the measurement: 1 − percentile/100 (module notes)."""
    p = measurement_percentile(predicted, measured, sigma)
    return 1.0 - p / 100.0 if math.isfinite(p) else math.nan


@dataclass(frozen=True)
class PeakComparison:
    """One stage's measured peak (one channel) against one predicted distribution."""

    source: str
    channel: str
    stage_index: int
    stage_label: str
    measured: float        # N
    sigma: float           # N, the measurement's 1-sigma
    time: float            # s
    percentile: float      # with the measurement sigma (convolved)
    percentile_without_sigma: float
    p_exceed: float        # P(prediction > true peak), with the sigma
    p_exceed_without_sigma: float

    def to_json(self, units):
        return {"measured": units.from_si(self.measured, "force"), "sigma": units.from_si(self.sigma, "force"),
                "time": self.time, "percentile": self.percentile,
                "percentile_without_sigma": self.percentile_without_sigma, "p_exceed": self.p_exceed,
                "p_exceed_without_sigma": self.p_exceed_without_sigma}


def stage_comparisons(predictions: dict, peaks) -> tuple:
    """PeakComparison for every source, stage and measured channel.

    ``predictions`` maps a source name to a MonteCarloResult (its
    ``outputs.stage_peak_load`` (B, K) in N); ``peaks`` is a reduction's
    ``peaks`` (StagePeaks per stage, SI).
    """
    out = []
    for source, result in predictions.items():
        for k, pk in enumerate(peaks):
            if k >= result.outputs.stage_peak_load.shape[1]:
                continue
            draws = result.outputs.stage_peak_load[:, k]
            for channel, peak in (("accelerometer", pk.accelerometer), ("load_cells", pk.load_cells)):
                if peak is None:
                    continue
                out.append(PeakComparison(
                    source, channel, k, pk.stage.label, peak.load, peak.sigma, peak.time,
                    measurement_percentile(draws, peak.load, peak.sigma),
                    measurement_percentile(draws, peak.load, 0.0),
                    exceedance_probability(draws, peak.load, peak.sigma),
                    exceedance_probability(draws, peak.load, 0.0)))
    return tuple(out)


# ---------------------------------------------------------------------------
# posterior predictive


def _check_fit_matches(fit: FitRecord, layout: ClusterLayout):
    where = fit.source_file(SUMMARY_NAME)
    if fit.test != layout.test_name:
        raise InputError(where, "key 'test'", f"the fit is of test {fit.test!r}, the bundle is {layout.test_name!r}",
                         "pass the fit folder written for this bundle")
    fitted = {pid: info for pid, info in fit.summary["parachutes"].items()}
    for i, pid in enumerate(layout.ids):
        info = fitted.get(pid)
        if info is None or len(info.get("stages", [])) != int(layout.stages_per_chute[i]):
            raise InputError(where, f"key 'parachutes.{pid}'",
                             f"the fit's parachutes {sorted(fitted)} (with their stages) do not match the "
                             f"bundle's {list(layout.ids)}", "pass the fit folder written for this bundle")


def posterior_run_inputs(fit: FitRecord, layout: ClusterLayout, runs: int, rng: np.random.Generator):
    """``runs`` parameter sets drawn jointly from the fit's posterior draws (one draw index per run, all names).

    Without replacement when the fit holds at least ``runs`` draws. Absent
    C_k / t_k (finite mass) are 1 / 0; the full-open ε is 1. Returns
    (RunInputs, number of draws available).
    """
    _check_fit_matches(fit, layout)
    names = []
    for i, pid in enumerate(layout.ids):
        names.append((f"{pid}.cds_o", (i, "cds_o")))
        n = int(layout.stages_per_chute[i])
        for k in range(n):
            pre = f"{pid}.s{k + 1}"
            roles = [("start", "start"), ("n_p", "fill"), ("expopen", "expopen")]
            if layout.inflations[i] == "infinite":
                roles += [("ck", "ck"), ("tk", "tk")]
            if k < n - 1:
                roles.append(("eps", "eps"))
            names += [(f"{pre}.{name}", (i, k, role)) for name, role in roles]
    missing = [name for name, _ in names if name not in fit.draws]
    if missing:
        raise InputError(fit.source_file(POSTERIOR_NAME), f"posterior variable '{missing[0]}'", "missing",
                         "rerun 'cpas-bayes fit' for this bundle with this version of cpas_bayes")
    available = int(np.asarray(fit.draws[names[0][0]]).size)
    pick = rng.choice(available, size=runs, replace=runs > available)
    values = {key: np.asarray(fit.draws[name], float)[pick] for name, key in names}
    weight = np.asarray(fit.draws["vehicle_weight"], float)[pick] if "vehicle_weight" in fit.draws else None
    cds_v = np.asarray(fit.draws["vehicle_cds"], float)[pick] if "vehicle_cds" in fit.draws else None
    return assemble_inputs(layout, values, "n_p", runs, weight, cds_v), available


def posterior_predictive(test: FlightTest, fit: FitRecord, runs: int, rng: np.random.Generator, batch=None,
                         progress=None, options: SimulationOptions = SimulationOptions(),
                         history_runs=DEFAULT_HISTORY_RUNS, engine="auto") -> MonteCarloResult:
    """Simulate ``test``'s flight with ``runs`` parameter sets from its own posterior (module notes)."""
    layout = ClusterLayout.from_test(test)
    engine_used = choose_engine(engine, options)
    if engine_used == "compiled":
        ensure_compiled()
    clock, cpu = _time.perf_counter(), _time.process_time()
    inputs, available = posterior_run_inputs(fit, layout, runs, rng)
    outputs = simulate_runs(layout, inputs, options, engine_used, batch, history_runs, progress,
                            desc="posterior predictive")
    runtime, cpu = _time.perf_counter() - clock, _time.process_time() - cpu
    return MonteCarloResult(layout, inputs, outputs, "n_p", True, runtime, engine_used, options,
                            {"fit": str(fit.source), "posterior_draws_available": available}, cpu)


# ---------------------------------------------------------------------------
# the comparison


@dataclass(frozen=True)
class LoadComparison:
    """A reduced test, its predictions by source and every stage's comparison."""

    test: FlightTest
    reduction: Reduction
    predictions: dict                 # source -> MonteCarloResult
    comparisons: tuple                # PeakComparison
    settings: dict = field(default_factory=dict)

    @property
    def stage_labels(self):
        return [pk.stage.label for pk in self.reduction.peaks]

    def find(self, source, channel, stage_index):
        for c in self.comparisons:
            if (c.source, c.channel, c.stage_index) == (source, channel, stage_index):
                return c
        return None

    def to_json(self):
        u = self.test.units
        stages = []
        for k, pk in enumerate(self.reduction.peaks):
            predicted = {}
            for source, result in self.predictions.items():
                o = result.outputs
                predicted[source] = {
                    "peak_load": quantile_summary(u.from_si(o.stage_peak_load[:, k], "force"), QUANTILE_LEVELS,
                                                  finite_only=True),
                    "peak_time": quantile_summary(o.stage_peak_time[:, k], QUANTILE_LEVELS, finite_only=True)}
            comparisons = {}
            for c in self.comparisons:
                if c.stage_index == k:
                    comparisons.setdefault(c.source, {})[c.channel] = c.to_json(u)
            stages.append({
                "stage": pk.stage.label, "interval": [pk.stage.start, pk.stage.end],
                "measured": {"accelerometer": pk.accelerometer.to_json(u),
                             "load_cells": pk.load_cells.to_json(u) if pk.load_cells else None},
                "predicted": predicted, "comparisons": comparisons})
        sources = {}
        for source, result in self.predictions.items():
            sources[source] = {**result.source, "runs": result.runs, "fill_constant_dispersed": result.mode,
                               "joint": result.joint, "engine": result.engine, "dt_s": result.options.dt,
                               "runtime_s": result.runtime_s}
        return {
            "test": self.test.name,
            "bundle": str(self.test.source) if self.test.source else None,
            "units": {"force": u.label("force"), "time": "s"},
            "method": {
                "percentile": "100·P(X + e ≤ m): the measured peak m placed in the predicted peaks X convolved "
                              "with its measurement error e ~ N(0, σ²), i.e. 100·mean_j Φ((m − x_j)/σ)",
                "p_exceed": "P(X > L) with the true peak L ~ N(m, σ²): mean_j Φ((x_j − m)/σ) = 1 − percentile/100",
                "without_sigma": "the same with σ = 0 (empirical share of predicted draws)",
                "measured": "reduction peaks: accelerometer total (Eq. 6) with its Eq. 7 sigma, and the scaled "
                            "load-cell sum with its sigma, after the reduction's peak filter",
                "predicted": "peak of the simulated Σ F_i (= W_V·G − q̄·CDS_V) in the stage's interval",
                "posterior": "trajectory simulated from the first data sample with joint posterior draws of the "
                             "fit; V_i is the simulated airspeed at each stage start (the fit used the measured one)",
            },
            "sources": sources,
            "stages": stages,
            **self.settings,
        }


def compare_loads(test: FlightTest, memo: Memo | None = None, fit: FitRecord | None = None, runs=2000, rng=None,
                  mode="n_p", joint=True, history_runs=DEFAULT_HISTORY_RUNS, batch=None, progress=None,
                  options: SimulationOptions = SimulationOptions(), reduction: Reduction | None = None,
                  engine="auto") -> LoadComparison:
    """Reduce ``test`` (unless ``reduction`` is given) and compare its stage peaks with the predictions.

    At least one of ``memo`` (population predictive, ``runs`` Monte Carlo
    runs with ``mode``/``joint``) and ``fit`` (posterior predictive, ``runs``
    posterior draws) is needed. ``history_runs`` load histories per source
    give the bands of the figure.
    """
    if memo is None and fit is None:
        raise InputError(test.label, "options --memo/--fit", "nothing to compare the measurement with",
                         "give a memo (--memo memo.toml), a fit of this test (--fit FITDIR), or both")
    check_runs(ClusterLayout.from_test(test), runs, results=(memo is not None) + (fit is not None),
               source="compare_loads", what="load comparison")
    rng = np.random.default_rng() if rng is None else rng
    reduction = reduce_test(test) if reduction is None else reduction
    predictions = {}
    if memo is not None:
        predictions["population"] = run_monte_carlo(memo, test, runs, rng, mode=mode, joint=joint, batch=batch,
                                                    progress=progress, options=options, engine=engine,
                                                    history_runs=history_runs)
    if fit is not None:
        predictions["posterior"] = posterior_predictive(test, fit, runs, rng, batch=batch, progress=progress,
                                                        options=options, history_runs=history_runs, engine=engine)
    return LoadComparison(test, reduction, predictions, stage_comparisons(predictions, reduction.peaks))

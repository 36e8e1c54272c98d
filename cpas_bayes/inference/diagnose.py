"""Find what the baseline simulation gets wrong, name the cause, measure the gain.

Procedure (``diagnose_test``)
-----------------------------
1. **Show.** Fit the baseline model (:mod:`cpas_bayes.inference.fit`) and run its checks
   (:mod:`cpas_bayes.inference.predictive_checks`, :mod:`cpas_bayes.inference.residuals`):
   standardised residuals per channel and flight phase with lag-1 ACF and
   Ljung–Box, the error multipliers, PPC p-values of the physical statistics,
   LOO-PIT and the bins where Pareto k is high.
2. **Extend.** Fit the baseline plus each candidate term of
   :mod:`cpas_bayes.stats.model_terms` (one at a time, the same model object with one
   hook filled; :mod:`cpas_bayes.inference.candidate_fits`). Each extended fit starts its MAP search from the baseline's
   MAP with the term at the values of ``Extension.start_points`` — for canopy
   breathing the frequency is first read off the baseline's residuals (the
   Lomb–Scargle peak in the prior's band).
3. **Compare.** PSIS-LOO per time bin on the joint log-likelihood of all
   channels of the bin (``log_likelihood["total"]``). For ``correlated_noise``
   the pointwise term is the AR-conditional log p(y_t | y_t−1, θ) (its sum is
   the joint likelihood, so the elpd values are on one scale). The table is
   ``arviz.compare``'s; the elpd difference of each candidate against the
   baseline and its standard error are computed from the paired pointwise
   elpd values, se = √(N·Var(Δelpd_i)).
4. **Name** (the rule, :func:`~cpas_bayes.inference.diagnosis_rule.name_cause`,
   stated in full with the reasons for its thresholds in
   :mod:`cpas_bayes.inference.diagnosis_rule`): the physical candidate with the
   largest elpd gain over the baseline is named when the gain exceeds
   ``min_gain`` (10 log units) and ``min_gain_se`` (2) standard errors, it
   beats ``correlated_noise``, its fitted size is beyond the term's practical
   floor, and it leads clearly any runner-up that also gains more than
   ``min_gain``. Otherwise the cause is ``none`` (and the report says why).
5. **Gain.** Named extension against the baseline: elpd gain ± se, RMSE of
   each channel, 90 %-band coverage of the data, residual lag-1 ACF, error
   multipliers, and the predicted peak load and its time against the measured
   ones. The parameters that moved when the term was added (posterior means
   shifted by more than one baseline sd) are listed for every candidate:
   the identifiability evidence.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.inference.candidate_fits import (BASELINE, CandidateFit, DiagnoseOptions, baseline_from_fit,
                                                 fit_candidate, polish_baseline_map, screen_candidate)
from cpas_bayes.inference.check_draws import check_tree, posterior_median, predict_draws
from cpas_bayes.inference.diagnosis_rule import compare_table, name_cause, versus_baseline
from cpas_bayes.inference.fit import Fit
from cpas_bayes.inference.predictive_checks import physical_series, run_checks, smooth_for_peaks
from cpas_bayes.inference.residuals import residuals
from cpas_bayes.stats.model_terms import PHYSICAL

BAND = 0.90                 # data coverage band of the gain table


@dataclass
class Diagnosis:
    """Everything ``diagnose`` found for one test."""

    test: str
    baseline: CandidateFit
    candidates: dict                 # name -> CandidateFit
    comparison: pd.DataFrame         # arviz.compare table
    versus_baseline: pd.DataFrame    # name, elpd_diff, elpd_diff_se, ...
    cause: str
    reasons: list
    evidence: dict
    gain: dict
    moved: dict
    checks: object                   # the baseline's predictive_checks.FitChecks
    screen: dict = field(default_factory=dict)   # name -> ScreenResult (mode "screen")
    options: DiagnoseOptions = field(default_factory=DiagnoseOptions)


# ---------------------------------------------------------------------------
# the executor's tasks (module-level functions, so that worker processes can run them)


def _screen_task(job):
    name, test, reduction, options, baseline, index = job
    return screen_candidate(name, test, reduction, options, baseline, index=index)


def _candidate_task(job):
    name, test, reduction, options, baseline, index, guesses = job
    return fit_candidate(name, test, reduction, options, baseline=baseline, index=index, guesses=guesses)


# ---------------------------------------------------------------------------
# what moved, what was gained


def moved_parameters(baseline: CandidateFit, candidate: CandidateFit, threshold=1.0):
    """Shared parameters whose posterior mean moved by more than ``threshold`` baseline sds.

    A term that is not identifiable from the data shows up here as large shifts
    of the parameters it trades off with (e.g. added mass against n_p and C_k).
    """
    post_b, post_c = baseline.fit.tree["posterior"], candidate.fit.tree["posterior"]
    out = {}
    for name in baseline.fit.model.names:
        if name not in post_c:
            continue
        b = np.asarray(post_b[name].values, float).ravel()
        c = np.asarray(post_c[name].values, float).ravel()
        sd = float(b.std())
        if sd <= 0:
            continue
        shift = (float(c.mean()) - float(b.mean())) / sd
        if abs(shift) > threshold:
            out[name] = {"baseline_mean": float(b.mean()), "baseline_sd": sd, "extended_mean": float(c.mean()),
                         "extended_sd": float(c.std()), "shift_in_baseline_sd": shift}
    return dict(sorted(out.items(), key=lambda kv: -abs(kv[1]["shift_in_baseline_sd"])))


def fit_quality(candidate: CandidateFit, rng):
    """Per channel: RMSE of the posterior-mean prediction (m²), 90 % predictive-band coverage
    of the data, lag-1 ACF of the standardised residuals; error multipliers; peak loads; the
    residual report and the mean predictions (acc (N,), lc (L, N)) for the figures."""
    fit = candidate.fit
    tree = check_tree(fit, budget=1000, rng=rng)
    report = residuals(fit, tree)
    obs = fit.model.obs
    const, pp = tree["constant_data"], tree["posterior_predictive"]
    mean = {"acc": np.asarray(const["acc_mean"].values), "lc": np.asarray(const["lc_mean"].values)}
    rep = {c: np.asarray(pp[c].values) for c in ("acc", "lc") if c in pp}
    channels = {}
    names = list(report.residuals)
    for i, channel in enumerate(names):
        key, row = ("acc", None) if i == 0 else ("lc", i - 1)
        y = obs.acc if row is None else obs.lc[row]
        m = mean[key] if row is None else mean[key].reshape(obs.lc.shape)[row]
        r = rep[key].reshape(-1, *rep[key].shape[2:])
        r = r if row is None else r[:, row, :]
        lo, hi = np.quantile(r, ((1 - BAND) / 2, (1 + BAND) / 2), axis=0)
        channels[channel] = {"rmse_m2": float(np.sqrt(np.mean((y - m) ** 2))),
                             "coverage_90": float(np.mean((y >= lo) & (y <= hi))),
                             "acf1": float(report.overall(channel)["acf1"])}
    return {"channels": channels, "noise": report.noise, "peaks": peak_comparison(fit, tree),
            "residuals": report, "means": (mean["acc"], mean["lc"].reshape(obs.lc.shape))}


def peak_comparison(fit, tree):
    """Predicted (noise-free, per draw) against measured peak load and its time, per series.

    Measured peaks are taken on the lightly smoothed series (checks'
    Savitzky–Golay), predicted ones on the model prediction of each draw; the
    load cells use each fit's posterior-median friction factor, both sides.
    """
    model, obs = fit.model, fit.model.obs
    post = tree["posterior"]
    theta = np.stack([np.asarray(post[n].values, float).ravel() for n in model.names], axis=-1)
    theta = theta[:: max(1, theta.shape[0] // 200)]
    pred = predict_draws(model, theta)
    scale = posterior_median(fit.tree, "load_scale", 1.0)
    measured = physical_series(model, obs.acc[None], obs.lc[None], scale)
    predicted = physical_series(model, pred["acc"], pred["lc"], scale)
    out = {}
    for series, (_, load) in measured.items():
        smooth = smooth_for_peaks(load[0])
        j = int(np.argmax(smooth))
        p_load = predicted[series][1]
        pj = np.argmax(p_load, axis=1)
        peaks = p_load[np.arange(p_load.shape[0]), pj]
        times = obs.time[pj]
        out[series] = {"measured_peak_n": float(smooth[j]), "measured_time_s": float(obs.time[j]),
                       "predicted_peak_n": float(np.median(peaks)),
                       "predicted_peak_q05_n": float(np.quantile(peaks, 0.05)),
                       "predicted_peak_q95_n": float(np.quantile(peaks, 0.95)),
                       "predicted_time_s": float(np.median(times)),
                       "peak_error_pct": float(100 * (np.median(peaks) - smooth[j]) / smooth[j]),
                       "time_error_s": float(np.median(times) - obs.time[j])}
    return out


def gain_table(baseline_quality, extended_quality, elpd_diff, elpd_diff_se, name):
    """The gain of ``name`` over the baseline, metric by metric (baseline → extended)."""
    channels = {}
    for channel, b in baseline_quality["channels"].items():
        e = extended_quality["channels"][channel]
        channels[channel] = {metric: {"baseline": b[metric], "extended": e[metric]} for metric in b}
    noise = {k: {"baseline": v["mean"], "extended": extended_quality["noise"][k]["mean"]}
             for k, v in baseline_quality["noise"].items() if k in extended_quality["noise"]}
    peaks = {}
    for series, b in baseline_quality["peaks"].items():
        e = extended_quality["peaks"][series]
        peaks[series] = {"measured_peak_n": b["measured_peak_n"], "measured_time_s": b["measured_time_s"],
                         "peak_error_pct": {"baseline": b["peak_error_pct"], "extended": e["peak_error_pct"]},
                         "time_error_s": {"baseline": b["time_error_s"], "extended": e["time_error_s"]},
                         "predicted_peak_n": {"baseline": b["predicted_peak_n"], "extended": e["predicted_peak_n"]}}
    return {"extension": name, "elpd_gain": elpd_diff, "elpd_gain_se": elpd_diff_se, "channels": channels,
            "error_multipliers": noise, "peaks": peaks}


# ---------------------------------------------------------------------------
# one test, end to end


def _evidence(checks, candidate_table):
    """What the baseline's checks show, condensed for the JSON (full tables beside it)."""
    res = checks.residuals
    table = res.table
    by_channel = table[table["phase"] == "all"].set_index("channel")
    ppc = checks.ppc.table
    flags = ppc[(ppc["p_value"] < 0.01) | (ppc["p_value"] > 0.99)]
    worst_phase = (table[table["phase"] != "all"].assign(abs_acf=lambda d: d["acf1"].abs())
                   .sort_values("abs_acf", ascending=False).head(5))
    return {
        "residuals": {ch: {"mean": float(r["mean"]), "sd": float(r["sd"]), "acf1": float(r["acf1"]),
                           "ljung_box_p": float(r["ljung_box_p"])} for ch, r in by_channel.iterrows()},
        "most_correlated_phases": worst_phase[["channel", "phase", "n", "mean", "sd", "acf1", "ljung_box_p"]]
        .to_dict("records"),
        "error_multipliers": res.noise,
        "ppc_flags": flags.to_dict("records"),
        "loo_pit": checks.loo_pit.table.to_dict("records"),
        "pareto_k": {**res.elpd_loo, "high_bins": res.high_pareto_k.to_dict("records")},
        "candidates": candidate_table.to_dict("records"),
    }


def diagnose_test(test, options: DiagnoseOptions = DiagnoseOptions(), reduction=None, echo=None,
                  baseline_fit: Fit | None = None, executor=None) -> Diagnosis:
    """Fit the baseline and the candidates, compare them, name the cause and measure its gain.

    Mode ``full`` samples every candidate. Mode ``screen`` first finds each
    physical candidate's MAP from the baseline's and samples only those that
    pass :func:`screen_candidate` (plus ``correlated_noise`` to compare with);
    when none passes, the cause is ``none`` without further sampling.
    ``baseline_fit`` reuses a baseline fit instead of sampling one.

    ``executor`` (:mod:`cpas_bayes.core.executor`; default ``options.sampler.workers``
    local processes) runs the screens and the candidate fits side by side, or
    a lone fit's ensembles; every fit has its own seed, so the diagnosis is
    the same on any executor.
    """
    from cpas_bayes.core.executor import make_executor

    own = executor is None
    executor = executor if executor is not None else make_executor(options.sampler.workers)
    try:
        return _diagnose(test, options, reduction, echo, baseline_fit, executor)
    finally:
        if own:
            executor.close()


def _diagnose(test, options, reduction, echo, baseline_fit, executor):
    say = echo or (lambda msg: None)
    reduction = reduction if reduction is not None else reduce_test(test)
    if baseline_fit is None:
        say(f"{test.name}: baseline fit")
        baseline = fit_candidate(BASELINE, test, reduction, options, echo=echo, executor=executor)
    else:
        baseline = baseline_from_fit(baseline_fit)
    screen = {}
    to_fit = list(options.candidates)
    if options.mode == "screen":
        baseline = polish_baseline_map(baseline, options)
        names = [n for n in options.candidates if n in PHYSICAL]
        results = executor.map(_screen_task, [(n, test, reduction, options, baseline, i + 1)
                                              for i, n in enumerate(names)], desc="screen", progress=False)
        for name, r in zip(names, results):
            screen[name] = r
            say(f"{test.name}: screen {name}: MAP gain {r.map_gain:+.1f}"
                + (f", size {r.size:.3g}" if r.size is not None else "") + (" → sample" if r.passed else ""))
        passed = [n for n, r in screen.items() if r.passed]
        to_fit = passed + ([n for n in options.candidates if n not in PHYSICAL] if passed else [])
    elif options.mode != "full":
        raise ValueError(f"unknown diagnosis mode {options.mode!r}; use 'full' or 'screen'")
    jobs = [(name, test, reduction, options, baseline, options.candidates.index(name) + 1,
             [screen[name].theta_map] if name in screen else None) for name in to_fit]
    if executor.workers > 1 and len(jobs) > 1:
        say(f"{test.name}: fit with {', '.join(to_fit)} on {executor.describe()}")
        fitted = executor.map(_candidate_task, jobs, desc="candidates", progress=False)
    else:  # one fit at a time, its ensembles side by side
        fitted = []
        for i, job in enumerate(jobs):
            say(f"{test.name}: fit with {job[0]} ({i + 1}/{len(jobs)})")
            fitted.append(fit_candidate(*job[:5], echo=echo, index=job[5], guesses=job[6], executor=executor))
    candidates = dict(zip(to_fit, fitted))
    rng = np.random.default_rng([options.seed, 7])
    checks = run_checks(baseline.fit, rng=rng)
    table = versus_baseline(baseline, candidates)
    if candidates:
        cause, reasons = name_cause(baseline, candidates, options)
    else:
        cause = "none"
        reasons = [f"no physical term raised the MAP log posterior by more than {options.screen_gain:g} with a "
                   "fitted size beyond its practical floor: "
                   + "; ".join(f"{n} {r.map_gain:+.1f}" + (f" (size {r.size:.3g})" if r.size is not None else "")
                               for n, r in screen.items())]
    evidence = _evidence(checks, table)
    physical = table[table["physical"]].sort_values("elpd_diff", ascending=False) if len(table) else table
    shown = cause if cause != "none" else (str(physical.iloc[0]["name"]) if len(physical) else None)
    gain = {}
    if shown is not None:
        row = table.set_index("name").loc[shown]
        base_q = fit_quality(baseline, rng)
        ext_q = fit_quality(candidates[shown], rng)
        gain = gain_table(base_q, ext_q, float(row["elpd_diff"]), float(row["elpd_diff_se"]), shown)
        gain["named"] = cause != "none"
        # for the figures, not the JSON
        gain["residuals"] = {"baseline": base_q["residuals"], "extended": ext_q["residuals"]}
        gain["means"] = {"baseline": base_q["means"], "extended": ext_q["means"]}
    moved = {name: moved_parameters(baseline, c) for name, c in candidates.items()}
    comparison = compare_table(baseline, candidates) if candidates else pd.DataFrame()
    return Diagnosis(test=test.name, baseline=baseline, candidates=candidates, comparison=comparison,
                     versus_baseline=table, cause=cause, reasons=reasons, evidence=evidence, gain=gain, moved=moved,
                     checks=checks, screen=screen, options=options)

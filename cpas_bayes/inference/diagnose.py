"""Find what the baseline simulation gets wrong, name the causes, measure the gain.

Procedure (``diagnose_test``)
-----------------------------
1. **Show.** Fit the baseline model (:mod:`cpas_bayes.inference.fit`) and run its checks
   (:mod:`cpas_bayes.inference.predictive_checks`, :mod:`cpas_bayes.inference.residuals`):
   standardised residuals per channel and flight phase with lag-1 ACF and
   Ljung–Box, the error multipliers, PPC p-values of the physical statistics,
   LOO-PIT and the bins where Pareto k is high.
2. **Measure the misfit.** Fit the baseline plus the generic discrepancy
   (:mod:`cpas_bayes.stats.discrepancy`): its elpd gain says how much
   structure there is to explain, its fitted shape where (channel, phase, time).
3. **Name, forward.** For each catalogued term T that applies to the test's
   channels (:mod:`cpas_bayes.stats.model_terms`) find the MAP of named + T +
   discrepancy from the reference's MAP and from the baseline's with the
   discrepancy off (where the term, not the discrepancy, takes the misfit
   first); sample it when the MAP log posterior
   rises by > 5 (mode ``screen``: also with T's size beyond its floor) — the
   MAP gain bounds the elpd gain from above, so a term that cannot raise the
   best fit cannot predict held-out bins better) and judge T against
   named + discrepancy (:mod:`cpas_bayes.inference.diagnosis_rule`), largest
   MAP gain first (terms that could not rival a passing leader wait a round);
   mode full refits with up to 4× the steps a term that gains and fails only on
   convergence, from its first fit's MAP; name the best passing term,
   add it to the reference and try the others again, until none passes.
4. **Unexplained?** Fit the named terms without the discrepancy: the
   discrepancy's gain over them is what is left; ``unexplained`` joins the
   causes when that remainder is significant and the named terms explain less
   than half of the discrepancy's gain — or when nothing was named and the
   baseline fails its own adequacy checks. ``none`` needs both: nothing named
   and an adequate baseline.
5. **Gain and model form.** The named terms against the baseline: elpd gain ±
   se, RMSE of each channel, 90 %-band coverage, residual lag-1 ACF, error
   multipliers, peak loads; the parameters that moved (> 1 sd listed, > 3 sd
   said in words). The seed's model-form arguments by ΔELPD: individual vs
   composite cluster model, linear vs exponential decay.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.inference.candidate_fits import (BASELINE, DISCREPANCY, SCREEN_PARTS, CandidateFit,
                                                 DiagnoseOptions, baseline_from_fit, best_screen, fit_candidate,
                                                 fit_model_form, for_tasks, model_label, polish_baseline_map,
                                                 restart_points, screen_candidate, verdict_names)
from cpas_bayes.inference.check_draws import check_tree, posterior_median, predict_draws
from cpas_bayes.inference.diagnosis_rule import (adequacy, cannot_rival, check_term, choose_term, compare_table,
                                                 fit_converged, kinematic_findings, paired_difference, passes,
                                                 structured_phases, terms_to_try, unexplained_share,
                                                 versus_baseline, withdrawn_terms)
from cpas_bayes.inference.fit import Fit
from cpas_bayes.inference.predictive_checks import physical_series, run_checks, smooth_for_peaks
from cpas_bayes.inference.residuals import channel_phases, residuals
from cpas_bayes.stats.discrepancy import channel_sigma, discrepancy_shape
from cpas_bayes.stats.model_terms import PHYSICAL

BAND = 0.90                 # data coverage band of the gain table
FORM_MARGIN = 4.0           # elpd: a model form wins clearly beyond 2 se and this (a likelihood ratio of e⁴)
RETRY_STEPS_FACTOR = 4      # a gaining but unconverged candidate is refitted with up to this many times the steps


@dataclass
class Diagnosis:
    """Everything ``diagnose`` found for one test."""

    test: str
    baseline: CandidateFit
    candidates: dict                 # model label -> CandidateFit (every model fitted)
    comparison: pd.DataFrame         # arviz.compare table
    versus_baseline: pd.DataFrame    # name, elpd_diff, elpd_diff_se, ... (every model against the baseline)
    cause: str                       # the first of ``causes``, or "none"
    reasons: list
    evidence: dict
    gain: dict
    moved: dict
    checks: object                   # the baseline's predictive_checks.FitChecks
    screen: dict = field(default_factory=dict)   # term -> ScreenResult of the first round (mode "screen")
    options: DiagnoseOptions = field(default_factory=DiagnoseOptions)
    causes: list = field(default_factory=list)   # named terms in order, then "unexplained" if so
    rounds: list = field(default_factory=list)   # forward selection: [{named, reference, checks, chosen, reasons}]
    unexplained: dict | None = None  # elpd_gain, elpd_gain_se, share_explained, where
    discrepancy: dict = field(default_factory=dict)   # gain over the baseline, shape (C, N) mean/sd, channels
    adequacy: dict = field(default_factory=dict)      # adequate, failures
    model_forms: list = field(default_factory=list)   # [{comparison, better, other, elpd_diff, elpd_diff_se}]
    named_fit: CandidateFit | None = None             # the named terms without the discrepancy
    warnings: list = field(default_factory=list)

    @property
    def verdict(self):
        """``named``, ``unexplained`` or ``none``."""
        if any(c != "unexplained" for c in self.causes):
            return "named"
        return "unexplained" if self.causes else "none"


# ---------------------------------------------------------------------------
# the executor's tasks (module-level functions, so that worker processes can run them)


def _screen_task(job):
    label, term, test, reduction, options, reference, baseline, part, named_plain = job
    return screen_candidate(label, test, reduction, options, reference, baseline=baseline, term=term, part=part,
                            named_plain=named_plain)


def _candidate_task(job, executor=None):
    label, test, reduction, options, reference, baseline, guesses = job
    if label.startswith("form:"):
        return fit_model_form(label[5:], test, reduction, options, executor=executor)
    return fit_candidate(label, test, reduction, options, reference=reference, baseline=baseline, guesses=guesses,
                         executor=executor)


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
    """Fit the baseline, the discrepancy and the candidates; name the causes, say what is unexplained.

    The procedure is the module's. Both modes MAP-screen each term before
    sampling it (a MAP gain > 5); mode ``screen`` also needs the term's size at
    its MAP beyond its practical floor. ``baseline_fit`` reuses a baseline fit
    instead of sampling one.

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


def _run_fits(executor, jobs, say, test_name):
    """Fit the jobs side by side, or one at a time with their ensembles side by side.

    Side by side only when there are at least two fits per worker (or fewer ensembles than workers): with
    fewer, the workers wait for the slowest fit (measured on the Main example: an added-mass fit of 152 s
    beside a sensor-lag fit of 52 s, one worker idle for 100 s), while one fit's ensembles advance in
    lockstep on all of them. A fit's draws are the same either way."""
    if not jobs:
        return []
    ensembles = jobs[0][3].sampler.n_ensembles
    if executor.workers > 1 and len(jobs) > 1 and (len(jobs) >= 2 * executor.workers or ensembles < executor.workers):
        say(f"{test_name}: fit {', '.join(j[0] for j in jobs)} on {executor.describe()}")
        return executor.map(_candidate_task, jobs, desc="candidates", progress=False)
    fitted = []
    for i, job in enumerate(jobs):
        say(f"{test_name}: fit {job[0]} ({i + 1}/{len(jobs)})")
        fitted.append(_candidate_task(job, executor=executor))
    return fitted


def _model_form_jobs(test, reduction, options, baseline):
    if not options.model_forms:
        return []
    forms = ["form:" + ("exponential" if options.decay == "linear" else "linear")]
    kinds = [p.kind for p in test.parachutes]
    if len(kinds) > len(set(kinds)):      # a cluster of like canopies: individual against composite
        forms.insert(0, "form:composite")
    return [(f, test, reduction, options, None, baseline, None) for f in forms]


def _model_forms(baseline, fits, options):
    rows = []
    for label, fit in fits.items():
        form = label[5:]
        diff, se = paired_difference(baseline, fit)
        if form == "composite":   # the fitted model is the individual one
            mine, other = "individual", "composite"
        else:
            mine, other = options.decay, form
        better, worse, margin = (mine, other, diff) if diff >= 0 else (other, mine, -diff)
        rows.append({"comparison": "cluster" if form == "composite" else "decay", "better": better, "other": worse,
                     "elpd_diff": margin, "elpd_diff_se": se,
                     "clear": bool(margin > max(options.min_gain_se * se, FORM_MARGIN)),
                     "in_words": f"{better} beats {worse} by {margin:.1f} ± {se:.1f} in elpd"
                                 + ("" if margin > max(options.min_gain_se * se, FORM_MARGIN)
                                    else f" (within 2 se or {FORM_MARGIN:g}: no clear winner)"),
                     "converged": fit_converged(fit.fit)})
    return rows


def discrepancy_where(candidate: CandidateFit, phase_fit: Fit, max_regions=6, draws=200, rng=None):
    """Where the fitted discrepancy is clearly non-zero: [{channel, phase, t_start, t_end, size_sigma}].

    A bin counts when the posterior mean of δ is beyond 2 posterior sd and beyond
    the bin's stated 1-sigma; runs closer than 3 bins merge, runs of fewer than
    3 bins are dropped, the largest (by Σ|δ|/σ) are kept. Phases are those of
    ``phase_fit``'s residual report.
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    model, post = candidate.fit.model, candidate.fit.tree["posterior"]
    theta = np.stack([np.asarray(post[n].values, float).ravel() for n in model.names], axis=-1)
    theta = theta[rng.choice(theta.shape[0], size=min(draws, theta.shape[0]), replace=False)]
    mean, sd = discrepancy_shape(model, theta)
    obs = model.obs
    sigma = channel_sigma(obs)
    phases = channel_phases(phase_fit)
    names = list(phases)
    regions = []
    for c, channel in enumerate(names):
        hit = (np.abs(mean[c]) > 2 * sd[c]) & (np.abs(mean[c]) > sigma[c])
        idx = np.flatnonzero(hit)
        if idx.size == 0:
            continue
        runs, start, prev = [], idx[0], idx[0]
        for i in idx[1:]:
            if i - prev > 3:
                runs.append((start, prev))
                start = i
            prev = i
        runs.append((start, prev))
        for lo, hi in runs:
            if hi - lo + 1 < 3:
                continue
            mid = (lo + hi) // 2
            labels, counts = np.unique(phases[channel][lo:hi + 1], return_counts=True)
            regions.append({"channel": channel, "phase": str(labels[np.argmax(counts)]),
                            "t_start": float(obs.time[lo]), "t_end": float(obs.time[hi]),
                            "peak_m2": float(mean[c][lo + np.argmax(np.abs(mean[c][lo:hi + 1]))]),
                            "size_sigma": float(np.sum(np.abs(mean[c][lo:hi + 1]) / sigma[c][lo:hi + 1])),
                            "t_mid": float(obs.time[mid])})
    regions.sort(key=lambda r: -r["size_sigma"])
    return regions[:max_regions], {"time": obs.time, "mean": mean, "sd": sd, "sigma": sigma, "channels": names}


def discrepancy_energy(candidate: CandidateFit, draws=100):
    """Σ (posterior mean of δ / stated 1-sigma)² over channels and bins: how much discrepancy a model keeps."""
    model, post = candidate.fit.model, candidate.fit.tree["posterior"]
    theta = np.stack([np.asarray(post[n].values, float).ravel() for n in model.names], axis=-1)
    theta = theta[np.linspace(0, theta.shape[0] - 1, min(draws, theta.shape[0])).astype(int)]
    mean, _ = discrepancy_shape(model, theta)
    obs = model.obs
    sigma = channel_sigma(obs)
    return float(np.sum((mean / sigma) ** 2))


def _forward_selection(test, reduction, options, baseline, discrepancy, terms, executor, say):
    """Name terms one at a time, each judged with the discrepancy present; returns (named, reference, rounds,
    fits, first screen)."""
    named, reference, rounds, fits, first_screen = [], discrepancy, [], {}, {}
    named_plain = None      # the named terms' optimum without the discrepancy (None: the baseline's MAP)
    trial = None            # a term named without a clear lead over ``trial[1]``
    # taking the discrepancy over (the rule's second path) needs a misfit the discrepancy found to begin with
    misfit = passes(*paired_difference(discrepancy, baseline), options)
    while len(named) < options.max_causes:
        remaining = [t for t in terms if t not in named]
        if not remaining:
            break
        labels = {t: model_label(named + [t], discrepancy=True) for t in remaining}
        # every round screens first: a term whose MAP cannot rise cannot gain out of sample
        # each screen's two groups of starts as tasks of their own: an added mass's searches from the
        # reference (~60 s on a Main) would otherwise hold one worker while the other idles
        light_reference, light_baseline = for_tasks(reference), for_tasks(baseline)
        # the "off" groups first: their plain searches are the long tasks, so the workers end together
        tasks = [(t, part) for part in reversed(SCREEN_PARTS) for t in remaining]
        results = executor.map(_screen_task, [(labels[t], t, test, reduction, options, light_reference,
                                               light_baseline, part, named_plain) for t, part in tasks],
                               desc="screen", progress=False)
        screen = {t: best_screen([r for (u, _), r in zip(tasks, results) if u == t]) for t in remaining}
        for t, r in screen.items():
            say(f"{test.name}: screen {t} with {reference.name}: MAP gain {r.map_gain:+.1f}"
                + (f", size {r.size:.3g}" if r.size is not None else "") + (" → sample" if r.passed else ""))
        if not named:
            first_screen = screen
        # largest MAP gain first: a leader no other screened term could rival leaves them to the next round
        # (not while a term is on trial: its rival must be judged in this one)
        to_fit = sorted([t for t in remaining if screen[t].passed], key=lambda t: -screen[t].map_gain)
        reference_energy = discrepancy_energy(reference)
        fitted, judged, waiting = {}, {}, []
        for batch in (to_fit[:1], to_fit[1:]):
            if not batch:
                continue
            leader = max(judged.values(), key=lambda c: c.elpd_diff) if judged else None
            if leader is not None and trial is None and all(cannot_rival(leader, screen[t].map_gain, options)
                                                            for t in batch):
                waiting = batch
                break
            _fit_and_judge(batch, test, reduction, options, reference, light_reference, light_baseline, screen,
                           labels, misfit, reference_energy, executor, say, fitted, judged)
        checks = [judged[t] for t in to_fit if t in judged]
        fits.update({labels[t]: f for t, f in fitted.items()})
        chosen, clear, reasons = choose_term(checks, {f.name: f for f in fitted.values()}, options)
        if trial is not None:
            earlier, rival = trial
            rival_check = next((c for c in checks if c.term == rival), None)
            if not (rival_check and rival_check.gains and rival_check.eligible):
                named.remove(earlier)
                reasons.append(f"{earlier} and {rival} explain the same structure and neither leads clearly: "
                               "neither is named")
                rounds.append({"named": list(named), "reference": reference.name, "checks": checks,
                               "screen": screen, "chosen": None, "reasons": reasons})
                reference = fits.get(model_label(named, discrepancy=True), discrepancy)
                break
            trial = None
        if waiting:
            reasons.append(f"not sampled this round: {', '.join(waiting)} (MAP gain "
                           + ", ".join(f"{screen[t].map_gain:+.1f}" for t in waiting)
                           + f"), which could not rival {chosen}; tried again with it in the reference")
        rounds.append({"named": list(named), "reference": reference.name, "checks": checks, "screen": screen,
                       "chosen": chosen, "reasons": reasons, "waiting": waiting})
        if chosen is None:
            break
        if not clear:
            passing = sorted([c for c in checks if c.gains and c.eligible and c.term != chosen],
                             key=lambda c: -c.elpd_diff)
            trial = (chosen, passing[0].term)
        named.append(chosen)
        reference = fitted[chosen]
        named_plain = screen[chosen].plain_optimum
    return named, reference, rounds, fits, first_screen


def _fit_and_judge(terms, test, reduction, options, reference, light_reference, light_baseline, screen, labels,
                   misfit, reference_energy, executor, say, fitted, judged):
    """Sample named + T + discrepancy for each of ``terms`` from its screen's MAP and judge it against
    ``reference``, into ``fitted`` {term: CandidateFit} and ``judged`` {term: TermCheck}.

    The form parameters of a term (an added mass's lag) can need more steps than the diagnosis' budget: in
    mode full a term that gains and fails only on convergence gets one longer fit from its MAP
    (:func:`_long_options`). Not at once: a Main's added mass (k_a 0.4, seed 40001) given the longer fit
    from the screen's MAP ended at R-hat 1.14 after 8,000 steps (217 s), where the first fit (2,000 steps,
    R-hat 1.04) and a longer one from its MAP settled the comparison in 108 s."""
    jobs = [(labels[t], test, reduction, options, light_reference, light_baseline, [screen[t].theta_map])
            for t in terms]
    fitted.update(zip(terms, _run_fits(executor, jobs, say, test.name)))

    def judge(t):
        share = 1.0 - discrepancy_energy(fitted[t]) / reference_energy if reference_energy > 0 else None
        return check_term(t, fitted[t], reference, options, misfit=misfit, share=share)

    judged.update({t: judge(t) for t in terms})
    retry = [t for t in terms if options.mode == "full"    # mode screen is the quick look
             and judged[t].gains and not judged[t].converged
             and not (judged[t].below_floor or judged[t].at_edge or judged[t].size_repeats_prior)]
    if retry:
        say(f"{test.name}: {', '.join(retry)} gained but did not converge: a fit up to {RETRY_STEPS_FACTOR}× "
            "longer, until the parameters the verdict reads are on target")
        jobs = [(labels[t], test, reduction, _long_options(options, verdict_names(fitted[t].fit.model, t)),
                 light_reference, light_baseline, restart_points(fitted[t].fit)) for t in retry]
        fitted.update(zip(retry, _run_fits(executor, jobs, say, test.name)))
        judged.update({t: judge(t) for t in retry})


def _long_options(options, stop_on):
    """The longer fit of a term: up to RETRY_STEPS_FACTOR× the steps (both limits: with the same seed a fit
    whose τ rule was met would stop where it did), stopping once ``stop_on``, the parameters the verdict
    reads (the term's and the discrepancy's, :func:`verdict_names`), reach their ESS and R-hat targets: a
    Drogue's added mass (k_a 0.4) stopped at 3× with k_a at ESS 397 held back by a decay time's 327."""
    return replace(options, sampler=replace(options.sampler, stop_on=stop_on,
                                            max_steps=options.sampler.max_steps * RETRY_STEPS_FACTOR,
                                            tau_factor=options.sampler.tau_factor * RETRY_STEPS_FACTOR))


def _diagnose(test, options, reduction, echo, baseline_fit, executor):
    say = echo or (lambda msg: None)
    if options.mode not in ("full", "screen"):
        raise ValueError(f"unknown diagnosis mode {options.mode!r}; use 'full' or 'screen'")
    reduction = reduction if reduction is not None else reduce_test(test)
    if baseline_fit is None:
        say(f"{test.name}: baseline fit")
        baseline = fit_candidate(BASELINE, test, reduction, options, echo=echo, executor=executor)
    else:
        baseline = baseline_from_fit(baseline_fit)
    baseline = polish_baseline_map(baseline, options)
    warnings = list(reduction.warnings)   # what the readings themselves show comes first (data.bundle_notes)
    kinematic, kinematic_where = kinematic_findings(test)   # the accelerometer against the airspeed's rate
    terms, not_tried = terms_to_try(options.candidates, test, kinematic)
    warnings += not_tried
    generic = [n for n in options.candidates if n not in PHYSICAL and n != DISCREPANCY]

    # the discrepancy, the model forms and any generic alternatives asked for, side by side
    light_baseline = for_tasks(baseline)     # the workers read its model and MAP, not its draws
    jobs = [(DISCREPANCY, test, reduction, options, light_baseline, light_baseline, None)]
    jobs += _model_form_jobs(test, reduction, options, light_baseline)
    jobs += [(g, test, reduction, options, light_baseline, light_baseline, None) for g in generic]
    first = dict(zip([j[0] for j in jobs], _run_fits(executor, jobs, say, test.name)))
    discrepancy = first[DISCREPANCY]
    forms = {k: v for k, v in first.items() if k.startswith("form:")}
    fits = {k: v for k, v in first.items() if not k.startswith("form:")}

    named, reference, rounds, more, screen = _forward_selection(test, reduction, options, baseline, discrepancy,
                                                                terms, executor, say)
    fits.update(more)
    named_fit = None
    if named:
        label = model_label(named)
        named_fit = _run_fits(executor, [(label, test, reduction, options, for_tasks(reference), light_baseline,
                                          None)], say, test.name)[0]
        fits[label] = named_fit
    final = named_fit or baseline

    rng = np.random.default_rng([options.seed, 7])
    checks = run_checks(baseline.fit, rng=rng)
    adequate, failures = adequacy(checks, options, kinematic)
    total, total_se = paired_difference(discrepancy, baseline)
    remaining, remaining_se = paired_difference(reference, final)
    share = unexplained_share(total, remaining) if named else 0.0
    withdrawn, why = withdrawn_terms(named, rounds, share, passes(remaining, remaining_se, options), options)
    if withdrawn:   # stand-ins: the verdict is as if nothing had been named
        named, final, reference, named_fit = [], baseline, discrepancy, None
        remaining, remaining_se = total, total_se
    left = passes(remaining, remaining_se, options)
    reasons = [x for r in rounds for x in r["reasons"]] + ([why] if withdrawn else [])
    unexplained = None
    is_unexplained = (left and (not named or share < options.min_share)) or (not named and not adequate) or kinematic
    where, shape = discrepancy_where(reference, final.fit)
    if is_unexplained:
        # where the discrepancy sits; failing that (a misfit too fast or too fine for a smooth term), the
        # channel × phase rows whose residuals the adequacy check found structured
        places = [{k: w[k] for k in ("channel", "phase", "t_start", "t_end")} for w in where]
        unexplained = {"elpd_gain": remaining, "elpd_gain_se": remaining_se, "share_explained": share,
                       "where": kinematic_where + places or structured_phases(checks)}
        if named:
            reasons.append(f"the named terms explain {100 * share:.0f} % of the discrepancy's gain; what is left "
                           f"gains {remaining:.1f} ± {remaining_se:.1f}: unexplained")
        elif left:
            reasons.insert(0, f"the generic discrepancy gains {remaining:.1f} ± {remaining_se:.1f} over the baseline "
                              "and no catalogued term explains it: unexplained")
        else:
            reasons.insert(0, "no catalogued term explains the misfit and the baseline fails its own checks: "
                              + "; ".join(failures[:3]))
    elif not named:
        reasons.insert(0, f"nothing to explain: the generic discrepancy gains {total:.1f} ± {total_se:.1f} and the "
                          "baseline passes its own checks (multipliers, residual structure, PPC, LOO-PIT)")
    causes = list(named) + (["unexplained"] if is_unexplained else [])
    cause = causes[0] if causes else "none"

    table = versus_baseline(baseline, fits)
    evidence = _evidence(checks, table)
    gain = {}
    if named_fit is not None:
        row = table.set_index("name").loc[named_fit.name]
        base_q = fit_quality(baseline, rng)
        ext_q = fit_quality(named_fit, rng)
        gain = gain_table(base_q, ext_q, float(row["elpd_diff"]), float(row["elpd_diff_se"]), named_fit.name)
        gain["named"] = True
        gain["residuals"] = {"baseline": base_q["residuals"], "extended": ext_q["residuals"]}
        gain["means"] = {"baseline": base_q["means"], "extended": ext_q["means"]}
    moved = {name: moved_parameters(baseline, c) for name, c in fits.items()}
    for name, m in moved.items():
        big = [f"{k} ({v['shift_in_baseline_sd']:+.1f} sd)" for k, v in m.items()
               if abs(v["shift_in_baseline_sd"]) > options.moved_sd]
        if big and name.split("+")[0] in named + [DISCREPANCY]:
            warnings.append(f"adding {name} moved {', '.join(big[:4])} by more than {options.moved_sd:g} baseline "
                            "sd: those parameters trade off with it")
    warnings += [f"the fit of {c.model} did not converge: {c.term} could not be named from it"
                 for r in rounds for c in r["checks"] if not c.converged]
    comparison = compare_table(baseline, fits)
    return Diagnosis(test=test.name, baseline=baseline, candidates=fits, comparison=comparison,
                     versus_baseline=table, cause=cause, reasons=reasons, evidence=evidence, gain=gain, moved=moved,
                     checks=checks, screen=screen, options=options, causes=causes, rounds=rounds,
                     unexplained=unexplained,
                     discrepancy={"elpd_gain": total, "elpd_gain_se": total_se, "where": where, "shape": shape,
                                  "model": reference.name},
                     adequacy={"adequate": adequate, "failures": failures},
                     model_forms=_model_forms(baseline, forms, options), named_fit=named_fit, warnings=warnings)

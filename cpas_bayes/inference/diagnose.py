"""Find what the baseline simulation gets wrong, name the cause, measure the gain.

Procedure (``diagnose_test``)
-----------------------------
1. **Show.** Fit the baseline model (:mod:`cpas_bayes.inference.fit`) and run its checks
   (:mod:`cpas_bayes.inference.predictive_checks`): standardised residuals per channel and flight
   phase with lag-1 ACF and Ljung–Box, the error multipliers, PPC p-values of
   the physical statistics, LOO-PIT and the bins where Pareto k is high.
2. **Extend.** Fit the baseline plus each candidate term of
   :mod:`cpas_bayes.stats.model_terms` (one at a time, the same model object with one
   hook filled). Each extended fit starts its MAP search from the baseline's
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
4. **Name** (the rule, :func:`name_cause`): the physical candidate with the
   largest elpd gain over the baseline is named when

   * its gain exceeds ``min_gain`` (10 log units) *and* ``min_gain_se`` (2)
     standard errors,
   * it beats ``correlated_noise`` (higher elpd): structure that a generic
     AR(1) error model explains as well is not evidence of a physical cause,
   * its fitted size is practical: the posterior median of the term's size
     parameter is beyond the floor the term declares
     (``Extension.practical_floor``: k_a 0.05, Δs 0.015, lag 10 ms, ring
     amplitude 1 %) — a region of practical equivalence around "no effect".
     Small differences between simulators or data systems fit as tiny sizes
     with real elpd gains; they are not causes,
   * if the runner-up physical candidate also gains more than ``min_gain``,
     the best leads it by more than ``min_margin_se`` (2) standard errors of
     their paired difference, or by more than ``min_gain`` with at least
     ``min_margin_ratio`` (1.5) times its gain: two terms that explain the
     same misfit about equally well do not name one of them. (The ratio
     matters for strong effects, where a runner-up term bent to its prior's
     edges also gains hundreds and the paired se, carried by a few bins, is
     large.)

   Why 10 and 2 se rather than the common "4 and 4 se": the effects sought act
   in a few transients (a fill, a peak), so the pointwise elpd differences are
   concentrated in a few dozen bins and their se ≈ gain/√m for m bins carrying
   the gain — a 4-se rule then fails on any localized effect however large. On
   clean synthetic and independent bundles the physical terms gain < 2 (they
   cannot overfit by much: one to three parameters, judged out of sample),
   while the smallest simulated effects gain ≥ 20; 10 sits between.

   Otherwise the cause is ``none`` (and the report says why).
5. **Gain.** Named extension against the baseline: elpd gain ± se, RMSE of
   each channel, 90 %-band coverage of the data, residual lag-1 ACF, error
   multipliers, and the predicted peak load and its time against the measured
   ones. The parameters that moved when the term was added (posterior means
   shifted by more than one baseline sd) are listed for every candidate:
   the identifiability evidence.
"""

from __future__ import annotations

import math
import time as _time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from cpas_bayes.stats.model_terms import EXTENSIONS, PHYSICAL, make_extension
from cpas_bayes.inference.fit import Fit, SamplerOptions, fit_model, prepare_model

CANDIDATES = PHYSICAL + ("correlated_noise",)
BASELINE = "baseline"

# Short fits: the comparison needs ~1,000 nearly independent draws per model,
# not a memo-grade posterior. Two ensembles still give a nested R-hat.
DIAGNOSIS_SAMPLER = SamplerOptions(n_ensembles=2, check_every=500, max_steps=2000, tau_factor=10.0,
                                   tau_rtol=0.25, map_starts=2, workers=2, progress=True)

BAND = 0.90                 # data coverage band of the gain table
BREATHING_BAND_HZ = (0.1, 3.0)


@dataclass(frozen=True)
class DiagnoseOptions:
    """Knobs of a diagnosis; the defaults are the rule stated in the module docstring."""

    seed: int = 0
    candidates: tuple = CANDIDATES
    min_gain: float = 10.0
    min_gain_se: float = 2.0
    min_margin_se: float = 2.0
    min_margin_ratio: float = 1.5
    sampler: SamplerOptions = DIAGNOSIS_SAMPLER
    priors: object = None
    decay: str = "linear"
    mode: str = "full"               # "full": sample every candidate; "screen": MAP screen first
    screen_gain: float = 5.0         # screen: a physical term is sampled if its MAP gain exceeds this


@dataclass
class CandidateFit:
    """One fitted model of the comparison and its PSIS-LOO."""

    name: str
    fit: Fit
    loo: object
    seconds: float

    @property
    def pointwise_elpd(self):
        return np.asarray(self.loo.elpd_i.values, float).ravel()


@dataclass
class ScreenResult:
    """A candidate's MAP next to the baseline's: the cheap first look of mode ``screen``."""

    name: str
    map_gain: float          # log posterior at the extended MAP − at the baseline MAP
    size: float | None       # the term's size parameter at its MAP (None: no physical size)
    passed: bool
    theta_map: np.ndarray
    seconds: float


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
    checks: object                   # the baseline's checks.FitChecks
    screen: dict = field(default_factory=dict)   # name -> ScreenResult (mode "screen")
    options: DiagnoseOptions = field(default_factory=DiagnoseOptions)


# ---------------------------------------------------------------------------
# fitting the candidates


def psis_loo(tree):
    """``arviz.loo`` on the joint per-bin log-likelihood, pointwise values kept."""
    import arviz as az

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Estimated shape parameter of Pareto", category=UserWarning)
        return az.loo(tree, var_name="total", pointwise=True)


def breathing_frequency_guess(model, theta, band=BREATHING_BAND_HZ):
    """Frequency (Hz) of the strongest oscillation left in the residuals at θ after the first peak.

    Lomb–Scargle periodograms (the bins are unevenly spaced) of every channel's
    standardised residual after the earliest peak drag area, summed over the
    channels, maximised over ``band``. The load cells see each canopy's ring
    alone; in the accelerometer the canopies' rings partly cancel.
    """
    from scipy.signal import lombscargle

    obs = model.obs
    pred = model.predict(theta[None])
    first_peak = obs.time[int(np.argmax(pred.acc[0]))]
    keep = obs.time > first_peak
    if keep.sum() < 16:
        return None
    series = [(obs.acc - pred.acc[0]) / np.hypot(obs.acc_sigma, obs.acc_qbar)]
    series += [(obs.lc[r] - pred.lc[0, r]) / np.hypot(obs.lc_sigma[r], obs.lc_qbar[r]) for r in range(obs.lc.shape[0])]
    freqs = np.linspace(band[0], band[1], 800)
    power = np.zeros_like(freqs)
    t = obs.time[keep]
    for r in series:
        x = r[keep] - r[keep].mean()
        # each channel normalised by its variance, so one noisy channel does not dominate
        power += lombscargle(t, x, 2 * np.pi * freqs) / max(float(np.var(x)), 1e-12)
    return float(freqs[int(np.argmax(power))])


def extension_starts(model, baseline_model, baseline_map, extension):
    """MAP starting points of an extended model: the baseline's MAP plus each of the term's start points."""
    base = dict(zip(baseline_model.names, baseline_map))
    rows = []
    for point in extension.start_points(model):
        theta = np.array([p.prior.ppf(0.5) for p in model.parameters], dtype=float)
        for i, name in enumerate(model.names):
            if name in base:
                theta[i] = base[name]
            elif name in point:
                theta[i] = point[name]
        rows.append(theta)
    return rows


def _extended_model(name, test, reduction, options, baseline):
    if name == "canopy_breathing":
        guess = breathing_frequency_guess(baseline.fit.model, baseline.fit.sampling.theta_map)
        extension = make_extension(name, frequency_guess=guess)
    else:
        extension = make_extension(name)
    model = prepare_model(test, reduction, options.priors, options.decay, extensions=[extension])
    return model, extension


def fit_candidate(name, test, reduction, options: DiagnoseOptions, baseline=None, echo=None, index=0, guesses=None,
                  executor=None):
    """Fit the baseline (``name == "baseline"``) or the baseline plus one extension.

    ``guesses`` replace the extension's MAP starts (e.g. the screen's MAP);
    ``executor`` runs the fit's ensembles.
    """
    started = _time.perf_counter()
    sampler = replace(options.sampler, seed=int(np.random.default_rng([options.seed, index]).integers(2**31 - 1)))
    if name == BASELINE:
        model = prepare_model(test, reduction, options.priors, options.decay)
        fit = fit_model(model, sampler, echo=echo, executor=executor)
    else:
        model, extension = _extended_model(name, test, reduction, options, baseline)
        if guesses is None:
            guesses = extension_starts(model, baseline.fit.model, baseline.fit.sampling.theta_map, extension)
        fit = fit_model(model, replace(sampler, map_starts=max(len(guesses), sampler.map_starts)),
                        echo=echo, guesses=guesses, executor=executor)
    return CandidateFit(name=name, fit=fit, loo=psis_loo(fit.tree), seconds=_time.perf_counter() - started)


def polish_baseline_map(baseline: CandidateFit, options: DiagnoseOptions) -> CandidateFit:
    """Rerun the baseline's MAP search from its MAP: the screen's gains are differences from it, so a
    baseline optimum left short (a short fit, a stalled search) would show as a gain of every term."""
    from cpas_bayes.inference.fit import find_map

    sampling = baseline.fit.sampling
    theta, log_post = find_map(baseline.fit.model, np.random.default_rng([options.seed, 5]), 2,
                               [sampling.theta_map])
    if log_post > sampling.log_post_map:
        sampling = replace(sampling, theta_map=theta, log_post_map=float(log_post))
        baseline = replace(baseline, fit=replace(baseline.fit, sampling=sampling))
    return baseline


def screen_candidate(name, test, reduction, options: DiagnoseOptions, baseline: CandidateFit, index=0):
    """MAP of the baseline plus ``name`` from the baseline's MAP; passes when the log posterior rises by
    more than ``options.screen_gain`` with the term's size beyond its practical floor.

    The MAP gain bounds the elpd gain from above up to the width terms (a term
    that cannot raise the best fit cannot predict held-out bins better), so a
    term failing the screen could not have passed the naming rule's
    ``min_gain`` > ``screen_gain``.
    """
    from cpas_bayes.inference.fit import find_map

    started = _time.perf_counter()
    model, extension = _extended_model(name, test, reduction, options, baseline)
    guesses = extension_starts(model, baseline.fit.model, baseline.fit.sampling.theta_map, extension)
    rng = np.random.default_rng([options.seed, index, 3])
    theta, log_post = find_map(model, rng, max(len(guesses), options.sampler.map_starts), guesses)
    gain = float(log_post - baseline.fit.sampling.log_post_map)
    size = None
    passed = gain > options.screen_gain
    if extension.practical_floor is not None:
        param, floor = extension.practical_floor
        size = float(theta[model.index[param]])
        passed = passed and abs(size) >= floor
    return ScreenResult(name=name, map_gain=gain, size=size, passed=bool(passed), theta_map=theta,
                        seconds=_time.perf_counter() - started)


def _screen_task(job):
    name, test, reduction, options, baseline, index = job
    return screen_candidate(name, test, reduction, options, baseline, index=index)


def _candidate_task(job):
    name, test, reduction, options, baseline, index, guesses = job
    return fit_candidate(name, test, reduction, options, baseline=baseline, index=index, guesses=guesses)


# ---------------------------------------------------------------------------
# comparison and the rule


def paired_difference(a: CandidateFit, b: CandidateFit):
    """elpd(a) − elpd(b) and its standard error from the paired pointwise values."""
    d = a.pointwise_elpd - b.pointwise_elpd
    return float(d.sum()), float(math.sqrt(d.size * np.var(d, ddof=1)))


def compare_table(baseline, candidates):
    """``arviz.compare`` over the baseline and the candidates (ranked by elpd)."""
    import arviz as az

    trees = {BASELINE: baseline.fit.tree, **{n: c.fit.tree for n, c in candidates.items()}}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=UserWarning)
        table = az.compare(trees, var_name="total")
    return table


def versus_baseline(baseline, candidates):
    """One row per candidate: elpd difference against the baseline, its se, p_loo, Pareto-k > 0.7 count."""
    rows = []
    for name, c in candidates.items():
        diff, se = paired_difference(c, baseline)
        k = np.asarray(c.loo.pareto_k.values, float)
        rows.append({"name": name, "elpd_diff": diff, "elpd_diff_se": se,
                     "z": diff / se if se > 0 else float("inf"), "elpd_loo": float(c.loo.elpd),
                     "p_loo": float(c.loo.p), "n_high_pareto_k": int(np.sum(k > 0.7)),
                     "physical": name in PHYSICAL, "seconds": c.seconds,
                     "converged": bool(c.fit.summary["diagnostics"]["converged"]),
                     "rhat_max": float(c.fit.summary["diagnostics"]["rhat_max"])})
    columns = ["name", "elpd_diff", "elpd_diff_se", "z", "elpd_loo", "p_loo", "n_high_pareto_k", "physical",
               "seconds", "converged", "rhat_max"]
    return pd.DataFrame(rows, columns=columns)


def name_cause(baseline, candidates, options: DiagnoseOptions):
    """Apply the naming rule; returns (cause, reasons)."""
    table = versus_baseline(baseline, candidates)
    physical = table[table["physical"]].sort_values("elpd_diff", ascending=False)
    if physical.empty:
        return "none", ["no physical candidate was fitted"]
    best = physical.iloc[0]
    reasons = []
    ok = True
    floor = EXTENSIONS[best["name"]].practical_floor
    if floor is not None:
        param, size = floor
        median = extension_parameters(candidates[best["name"]])[param]["median"]
        if abs(median) < size:
            ok = False
            reasons.append(f"{best['name']}'s fitted size {param} = {median:.3g} is below the practical floor "
                           f"{size:g}: a real but negligible effect, not a cause")
    if not (best["elpd_diff"] > options.min_gain and best["elpd_diff"] > options.min_gain_se * best["elpd_diff_se"]):
        ok = False
        reasons.append(f"the best physical term, {best['name']}, gains {best['elpd_diff']:.1f} ± "
                       f"{best['elpd_diff_se']:.1f} in elpd; the rule needs > {options.min_gain:g} and > "
                       f"{options.min_gain_se:g} se")
    if "correlated_noise" in candidates:
        diff, se = paired_difference(candidates[best["name"]], candidates["correlated_noise"])
        if diff <= 0:
            ok = False
            reasons.append(f"{best['name']} does not beat AR(1) correlated noise (elpd difference "
                           f"{diff:.1f} ± {se:.1f})")
        else:
            reasons.append(f"{best['name']} beats AR(1) correlated noise by {diff:.1f} ± {se:.1f}")
    if len(physical) > 1:
        second = physical.iloc[1]
        diff, se = paired_difference(candidates[best["name"]], candidates[second["name"]])
        clear = diff > options.min_margin_se * se or (
            diff > options.min_gain and best["elpd_diff"] >= options.min_margin_ratio * second["elpd_diff"])
        if second["elpd_diff"] > options.min_gain and not clear:
            ok = False
            reasons.append(f"{best['name']} is not clearly ahead of {second['name']} ({diff:.1f} ± {se:.1f}; "
                           f"the rule needs > {options.min_margin_se:g} se, or > {options.min_gain:g} and "
                           f"{options.min_margin_ratio:g}× its gain)")
        else:
            reasons.append(f"{best['name']} leads {second['name']} by {diff:.1f} ± {se:.1f}")
    if ok:
        reasons.insert(0, f"{best['name']} gains {best['elpd_diff']:.1f} ± {best['elpd_diff_se']:.1f} in elpd "
                          f"over the baseline ({best['z']:.1f} se)")
        return str(best["name"]), reasons
    return "none", reasons


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


def extension_parameters(candidate: CandidateFit):
    """Posterior mean, sd and 90 % interval of the term's own parameters."""
    model, post = candidate.fit.model, candidate.fit.tree["posterior"]
    out = {}
    for p in model.parameters:
        if p.group != candidate.name:
            continue
        x = np.asarray(post[p.name].values, float).ravel()
        q05, q50, q95 = np.quantile(x, (0.05, 0.5, 0.95))
        out[p.name] = {"mean": float(x.mean()), "sd": float(x.std()), "median": float(q50),
                       "q05": float(q05), "q95": float(q95), "unit": p.unit}
    return out


def fit_quality(candidate: CandidateFit, rng):
    """Per channel: RMSE of the posterior-mean prediction (m²), 90 % predictive-band coverage
    of the data, lag-1 ACF of the standardised residuals; error multipliers; peak loads; the
    residual report and the mean predictions (acc (N,), lc (L, N)) for the figures."""
    from cpas_bayes.inference import predictive_checks as chk

    fit = candidate.fit
    tree = chk.check_tree(fit, budget=1000, rng=rng)
    report = chk.residuals(fit, tree)
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
    from cpas_bayes.inference import predictive_checks as chk

    model, obs = fit.model, fit.model.obs
    post = tree["posterior"]
    theta = np.stack([np.asarray(post[n].values, float).ravel() for n in model.names], axis=-1)
    theta = theta[:: max(1, theta.shape[0] // 200)]
    pred = chk.predict_draws(model, theta)
    scale = chk.posterior_median(fit.tree, "load_scale", 1.0)
    measured = chk.physical_series(model, obs.acc[None], obs.lc[None], scale)
    predicted = chk.physical_series(model, pred["acc"], pred["lc"], scale)
    out = {}
    for series, (_, load) in measured.items():
        smooth = chk.smooth_for_peaks(load[0])
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


def baseline_from_fit(fit: Fit) -> CandidateFit:
    """Use an existing baseline fit (e.g. a campaign's) as the diagnosis' baseline."""
    return CandidateFit(name=BASELINE, fit=fit, loo=psis_loo(fit.tree), seconds=0.0)


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
    from cpas_bayes.inference import predictive_checks as chk
    from cpas_bayes.data.reduction import reduce_test

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
    checks = chk.run_checks(baseline.fit, rng=rng)
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


# ---------------------------------------------------------------------------
# output

DIAGNOSIS_NAME = "diagnosis.json"

_WHAT = {
    "added_mass": "the air mass carried along with each canopy (enclosed and apparent) adds a momentum term "
                  "d(m_a·V)/dt to the load while the canopy grows and the system decelerates; without it the "
                  "model reaches the peak load too early and too sharp",
    "friction_drift": "the load-cell friction factor changes during the test, so one constant scale factor "
                      "cannot match the load cells to the accelerometer in every stage",
    "sensor_lag": "the load cells run behind the accelerometer's time base: every load-cell feature arrives "
                  "late by the same delay",
    "canopy_breathing": "the canopies' drag area rings (breathes) after each peak, a damped oscillation the "
                        "stage law does not have",
    "correlated_noise": "the errors are correlated in time (a generic AR(1) process), which no physical term "
                        "explains better",
}


def diagnosis_document(d: Diagnosis):
    """The ``diagnosis.json`` content (SI)."""
    from cpas_bayes.core.files import jsonable

    rows = []
    for r in d.versus_baseline.to_dict("records"):
        c = d.candidates[r["name"]]
        rows.append({"name": r["name"], "elpd_diff": r["elpd_diff"], "elpd_diff_se": r["elpd_diff_se"],
                     "params": extension_parameters(c), "physical": r["physical"], "p_loo": r["p_loo"],
                     "n_high_pareto_k": r["n_high_pareto_k"], "converged": r["converged"],
                     "rhat_max": r["rhat_max"], "seconds": r["seconds"], "moved": d.moved[r["name"]]})
    for name, r in d.screen.items():
        if name in d.candidates:
            continue
        size = {} if r.size is None else {EXTENSIONS[name].practical_floor[0]: {"map": r.size}}
        rows.append({"name": name, "elpd_diff": None, "elpd_diff_se": None, "params": size, "physical": True,
                     "screened_out": True, "map_gain": r.map_gain, "seconds": r.seconds})
    gain = {k: v for k, v in d.gain.items() if k not in ("residuals", "means")}
    o = d.options
    return jsonable({
        "test": d.test,
        "cause": d.cause,
        "reasons": d.reasons,
        "rule": {"min_gain": o.min_gain, "min_gain_se": o.min_gain_se, "min_margin_se": o.min_margin_se,
                 "text": f"the physical term with the largest elpd gain is named when the gain is > "
                         f"{o.min_gain:g} and > {o.min_gain_se:g} se, it beats correlated_noise, and, when the next "
                         f"physical term also gains > {o.min_gain:g}, it leads that term by > {o.min_margin_se:g} "
                         f"se of their paired difference or by > {o.min_gain:g} with {o.min_margin_ratio:g}x its "
                         "gain; the named term's size must pass its practical floor; otherwise none",
                 "loo": "PSIS-LOO per time bin on the joint log-likelihood of all channels of the bin; "
                        "correlated_noise uses the AR-conditional log p(y_t | y_t-1)"},
        "mode": o.mode,
        "screen": {n: {"map_gain": r.map_gain, "size": r.size, "passed": r.passed} for n, r in d.screen.items()},
        "candidates": rows,
        "baseline": {"elpd_loo": float(d.baseline.loo.elpd), "se": float(d.baseline.loo.se),
                     "p_loo": float(d.baseline.loo.p), "seconds": d.baseline.seconds,
                     "converged": bool(d.baseline.fit.summary["diagnostics"]["converged"])},
        "comparison": d.comparison.reset_index().rename(columns={"index": "model"}),
        "gain": gain,
        "evidence": d.evidence,
        "units": "SI",
    })


def _fmt_gain_rows(gain):
    lines = ["| channel | RMSE baseline → extended | 90 % band coverage | lag-1 ACF |", "|---|---|---|---|"]
    for ch, m in gain["channels"].items():
        lines.append(f"| {ch} | {m['rmse_m2']['baseline']:.3g} → {m['rmse_m2']['extended']:.3g} m² | "
                     f"{m['coverage_90']['baseline']:.2f} → {m['coverage_90']['extended']:.2f} | "
                     f"{m['acf1']['baseline']:+.2f} → {m['acf1']['extended']:+.2f} |")
    return lines


def diagnosis_markdown(d: Diagnosis, units):
    """A short ``diagnosis.md`` for a flight-test engineer."""
    force = units.label("force")
    lines = [f"# Diagnosis of {d.test}", ""]
    if d.cause != "none":
        lines += [f"**Cause named: `{d.cause}`.** In words: {_WHAT[d.cause]}.", ""]
    else:
        lines += ["**No physical cause named** (`none`): the baseline simulation explains the data as well as "
                  "any of the candidate terms, within the rule below.", ""]
    lines += ["Why:", ""] + [f"- {r}" for r in d.reasons] + [""]
    lines += ["## Candidates (elpd gain over the baseline, PSIS-LOO)", "",
              "| term | elpd gain ± se | its parameters (posterior mean ± sd) | parameters that moved > 1 sd |",
              "|---|---|---|---|"]
    for r in d.versus_baseline.sort_values("elpd_diff", ascending=False).to_dict("records"):
        params = extension_parameters(d.candidates[r["name"]])
        ptxt = ", ".join(f"{k} = {v['mean']:.3g} ± {v['sd']:.2g}{(' ' + v['unit']) if v['unit'] else ''}"
                         for k, v in params.items())
        moved = d.moved[r["name"]]
        mtxt = ", ".join(f"{k} ({v['shift_in_baseline_sd']:+.1f} sd)" for k, v in list(moved.items())[:4]) or "—"
        lines.append(f"| {r['name']} | {r['elpd_diff']:.1f} ± {r['elpd_diff_se']:.1f} | {ptxt} | {mtxt} |")
    for name, r in d.screen.items():
        if name not in d.candidates:
            size = f"size {r.size:.3g} at the MAP" if r.size is not None else ""
            lines.append(f"| {name} | not sampled: MAP gain {r.map_gain:+.1f} (screen) | {size} | — |")
    lines.append("")
    if d.gain:
        g = d.gain
        title = "Gain of the named term" if g.get("named") else f"What the best physical term ({g['extension']}) would change"
        lines += [f"## {title}", "", f"elpd gain {g['elpd_gain']:.1f} ± {g['elpd_gain_se']:.1f}.", ""]
        lines += _fmt_gain_rows(g) + [""]
        em = ", ".join(f"{k} {v['baseline']:.2f} → {v['extended']:.2f}" for k, v in g["error_multipliers"].items())
        lines += [f"Error multipliers (1 = the stated sigmas suffice): {em}.", ""]
        lines += ["| series | measured peak | baseline: peak error, time error | extended: peak error, time error |",
                  "|---|---|---|---|"]
        for s, p in g["peaks"].items():
            lines.append(f"| {s} | {units.from_si(p['measured_peak_n'], 'force'):,.0f} {force} at "
                         f"{p['measured_time_s']:.2f} s | {p['peak_error_pct']['baseline']:+.1f} %, "
                         f"{p['time_error_s']['baseline']:+.3f} s | {p['peak_error_pct']['extended']:+.1f} %, "
                         f"{p['time_error_s']['extended']:+.3f} s |")
        lines.append("")
    ev = d.evidence
    lines += ["## What the baseline's checks showed", "",
              "| channel | residual sd | lag-1 ACF | Ljung–Box p |", "|---|---|---|---|"]
    for ch, r in ev["residuals"].items():
        lines.append(f"| {ch} | {r['sd']:.2f} | {r['acf1']:+.2f} | {r['ljung_box_p']:.2g} |")
    lines += ["", f"PPC statistics outside 1–99 %: {len(ev['ppc_flags'])}; bins with Pareto k > 0.7: "
                  f"{ev['pareto_k']['n_high_pareto_k']}.", "",
              "Figures: `elpd.png` (the comparison), `screen.png` (MAP screen, mode screen), `residuals.png` "
              "(before/after), `comparison.png` (predictions against the data), `baseline/residuals.png`, "
              "`baseline/ppc.png`, `baseline/loo_pit.png`.", ""]
    return "\n".join(lines)


def _change_window(time, base_mean, ext_mean, data, half_width):
    """Centre of the window where the extended prediction improves the squared error most."""
    gain = (data - base_mean) ** 2 - (data - ext_mean) ** 2
    kernel = np.ones(max(3, int(np.sum(np.abs(time - time[0]) < 2 * half_width))))
    smooth = np.convolve(gain, kernel / kernel.size, mode="same")
    centre = time[int(np.argmax(smooth))]
    return centre - half_width, centre + half_width


def write_diagnosis(d: Diagnosis, out):
    """Write ``diagnosis.json``, ``diagnosis.md``, the tables and the figures into ``out``."""
    import matplotlib.pyplot as plt

    from cpas_bayes.core.files import write_csv, write_json, write_text
    from cpas_bayes.outputs.figures import save_figure
    from cpas_bayes.outputs.plots import diagnose as figs
    from cpas_bayes.outputs.plots.fit import plot_loo_pit, plot_ppc, plot_residuals

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    units = d.baseline.fit.model.test.units

    def save(fig, name):
        save_figure(fig, out / name, dpi=110)
        plt.close(fig)

    if len(d.versus_baseline):
        save(figs.plot_elpd(d.versus_baseline, d.cause, d.options.min_gain, d.options.min_gain_se, d.test),
             "elpd.png")
    if d.screen:
        save(figs.plot_screen(d.screen, d.options.screen_gain, d.test), "screen.png")
    save(plot_residuals(d.checks.residuals), "baseline/residuals.png")
    save(plot_ppc(d.checks.ppc), "baseline/ppc.png")
    save(plot_loo_pit(d.checks.loo_pit), "baseline/loo_pit.png")
    write_csv(out / "baseline" / "residual_table.csv", d.checks.residuals.table)
    write_csv(out / "baseline" / "ppc.csv", d.checks.ppc.table)
    write_csv(out / "candidates.csv", d.versus_baseline)
    if d.gain:
        name = d.gain["extension"]
        reports = d.gain["residuals"]
        save(figs.plot_residual_comparison(reports["baseline"], reports["extended"], name, d.test), "residuals.png")
        model = d.baseline.fit.model
        obs = model.obs
        (base_acc, base_lc), (ext_acc, ext_lc) = d.gain["means"]["baseline"], d.gain["means"]["extended"]
        channels = [("accelerometer drag area (Eq. 8)", obs.acc, base_acc, ext_acc)]
        for row, chute in enumerate(obs.lc_index):
            pid = model.parachutes[int(chute)].id
            channels.append((f"load cell {pid}", obs.lc[row], base_lc[row], ext_lc[row]))
        infinite = all(p.inflation == "infinite" for p in model.parachutes)
        # zoom on the channel the term improves most (load cells carry lag and friction effects)
        best = max(channels, key=lambda c: np.sum((c[1] - c[2]) ** 2 - (c[1] - c[3]) ** 2))
        window = _change_window(obs.time, best[2], best[3], best[1], 1.0 if infinite else 4.0)
        save(figs.plot_fit_comparison(obs.time, channels, units, name, d.test, window), "comparison.png")
    write_text(out / "diagnosis.md", diagnosis_markdown(d, units))
    write_json(out / DIAGNOSIS_NAME, diagnosis_document(d))   # last: its presence marks a complete diagnosis
    return out / DIAGNOSIS_NAME

"""The models a diagnosis compares: the baseline, and the baseline plus one candidate term.

:func:`fit_candidate` samples one of them and computes its PSIS-LOO (step 2 of
the procedure in :mod:`cpas_bayes.inference.diagnose`): an extended fit starts
its MAP search from the baseline's MAP with the term at the values of
``Extension.start_points``; for canopy breathing the frequency is first read
off the baseline's residuals (:func:`breathing_frequency_guess`). Mode
``screen`` first looks at each term's MAP only (:func:`screen_candidate`).
:class:`DiagnoseOptions` holds the knobs of a diagnosis, among them the
thresholds of the naming rule (:mod:`cpas_bayes.inference.diagnosis_rule`).
"""

from __future__ import annotations

import time as _time
import warnings
from dataclasses import dataclass, replace

import numpy as np

from cpas_bayes.inference.fit import Fit, SamplerOptions, fit_model, prepare_model

from cpas_bayes.inference.start import find_map
from cpas_bayes.stats.model_terms import PHYSICAL, make_extension

CANDIDATES = PHYSICAL + ("correlated_noise",)
BASELINE = "baseline"

# Short fits: the comparison needs ~1,000 nearly independent draws per model,
# not a memo-grade posterior. Two ensembles still give a nested R-hat.
DIAGNOSIS_SAMPLER = SamplerOptions(n_ensembles=2, check_every=500, max_steps=2000, tau_factor=10.0,
                                   tau_rtol=0.25, map_starts=2, workers=2, progress=True)

BREATHING_BAND_HZ = (0.1, 3.0)


@dataclass(frozen=True)
class DiagnoseOptions:
    """Knobs of a diagnosis; the defaults are the rule of :mod:`cpas_bayes.inference.diagnosis_rule`."""

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


def baseline_from_fit(fit: Fit) -> CandidateFit:
    """Use an existing baseline fit (e.g. a campaign's) as the diagnosis' baseline."""
    return CandidateFit(name=BASELINE, fit=fit, loo=psis_loo(fit.tree), seconds=0.0)


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

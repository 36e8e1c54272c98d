"""The models a diagnosis compares: the baseline, the generic discrepancy, and named terms.

A model is named by its label: ``baseline``, or the terms it adds joined by
``+`` (``discrepancy``, ``added_mass+discrepancy``,
``added_mass+sensor_lag``; :func:`model_label`). :func:`fit_candidate`
samples one and computes its PSIS-LOO (step 2 of the procedure in
:mod:`cpas_bayes.inference.diagnose`): it starts its MAP search from a
*reference* fit's MAP (the model it extends or trims) with each new term at
the values of ``Extension.start_points``; for canopy breathing the frequency
is first read off the baseline's residuals (:func:`breathing_frequency_guess`).
:func:`screen_candidate` looks at a model's MAP only. :func:`fit_model_form`
fits the baseline in another form (composite cluster, the other decay).
:class:`DiagnoseOptions` holds the knobs of a diagnosis, among them the
thresholds of the naming rule (:mod:`cpas_bayes.inference.diagnosis_rule`).
"""

from __future__ import annotations

import itertools
import time as _time
import zlib
from dataclasses import dataclass, replace

import numpy as np

from cpas_bayes.inference.fit import Fit, SamplerOptions, fit_model, prepare_model

from cpas_bayes.inference.loo import psis_loo as _tree_loo
from cpas_bayes.inference.start import find_map
from cpas_bayes.stats.discrepancy import Discrepancy, residual_envelope
from cpas_bayes.stats.model_terms import PHYSICAL, make_extension

CANDIDATES = PHYSICAL
BASELINE = "baseline"
DISCREPANCY = "discrepancy"

# Short fits: the comparison needs a few hundred nearly independent draws per model (ESS 400, Vehtari et
# al.'s floor for the diagnostics themselves), not a memo-grade posterior. Two ensembles still give a nested
# R-hat; the adaptive proposal's warm-up is short (200 + 2·100 steps), its τ a few steps. The proposal is
# fitted to both ensembles' warm-up draws ("pooled"): each ensemble's own stayed where it was, and a Main's
# added-mass fit ended its 2,000 steps at R-hat 1.156 (the disreef stage's start, n_p and expopen; the mass
# exponent 1.053) against 1.038 (1.013) pooled, from the same start and in the same time. The walkers move
# in peak-time coordinates (inference.coordinates): on that Main (k_a 0.4, seed 40001) the added mass' fit
# stopped at 500 steps (acceptance 0.14) against 2,000 (0.05) in θ, and the diagnosis took 94 s against 149 s.
DIAGNOSIS_SAMPLER = SamplerOptions(n_ensembles=2, check_every=200, max_steps=2000, stop="ess", ess_target=400,
                                   tau_rtol=0.25, map_starts=2, workers=2, progress=True, proposal="pooled",
                                   coordinates="peak_time", warm_up="fixed")

BREATHING_BAND_HZ = (0.1, 3.0)
FULL_MODE_FLOOR_SHARE = 0.5   # mode full samples a term whose MAP size reaches this share of its floor


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
    below_previous: str = "drop"     # the stage law's rule for a stage below the held drag area
    mode: str = "full"               # "screen" also needs a term's size at its MAP beyond the practical floor
    screen_gain: float = 5.0         # a term is sampled when its MAP log posterior rises by more than this
    max_causes: int = 3              # forward selection stops after this many named terms
    min_share: float = 0.5           # named terms must explain this share of the discrepancy's gain
    moved_sd: float = 3.0            # parameters moving more than this (baseline sds) are flagged in words
    model_forms: bool = True         # also compare composite vs individual cluster and the decay forms


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
    plain_optimum: dict | None = None   # the "off" group's optimum of the same terms without the discrepancy


# ---------------------------------------------------------------------------
# fitting the candidates


def psis_loo(tree):
    """``arviz.loo`` on the joint per-bin log-likelihood, pointwise values kept (:func:`.loo.psis_loo`)."""
    return _tree_loo(tree, "total")


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


def model_label(terms, discrepancy=False):
    """The label of the baseline plus ``terms`` (in catalogue order) and, last, the discrepancy."""
    names = [t for t in PHYSICAL if t in terms] + [t for t in terms if t not in PHYSICAL and t != DISCREPANCY]
    names += [DISCREPANCY] if discrepancy else []
    return "+".join(names) if names else BASELINE


def label_terms(label):
    """(physical and other terms, with discrepancy) of a model label."""
    if label == BASELINE:
        return (), False
    parts = tuple(label.split("+"))
    return tuple(p for p in parts if p != DISCREPANCY), DISCREPANCY in parts


def candidate_seed_index(label):
    """A fixed index per model label, so a model's seed does not depend on the order of the fits."""
    return 1 + zlib.crc32(label.encode()) % 100_000


def _model_for(label, test, reduction, options, baseline, **model_options):
    terms, with_discrepancy = label_terms(label)
    extensions = []
    for name in terms:
        if name == "canopy_breathing" and baseline is not None:
            guess = breathing_frequency_guess(baseline.fit.model, baseline.fit.sampling.theta_map)
            extensions.append(make_extension(name, frequency_guess=guess))
        else:
            extensions.append(make_extension(name))
    if with_discrepancy:
        envelope = None
        if baseline is not None:   # every model with the discrepancy gets the same prior: the baseline's envelope
            envelope = residual_envelope(baseline.fit.model, baseline.fit.sampling.theta_map)
        extensions.append(Discrepancy(envelope=envelope))
    return prepare_model(test, reduction, options.priors, model_options.pop("decay", options.decay),
                         extensions=extensions,
                         below_previous=model_options.pop("below_previous", options.below_previous), **model_options)


def _new_terms(model, reference_model):
    """The extensions of ``model`` that ``reference_model`` lacks."""
    known = {e.name for e in reference_model.extensions}
    return [e for e in model.extensions if e.name not in known]


def start_guesses(model, reference, points=None):
    """MAP starts of ``model`` from a fitted ``reference``: its MAP by parameter name, each term the
    reference lacks at each of its ``start_points`` (all combinations), the rest at prior medians.
    ``points`` {term: [start point]} replaces a term's own start points, and restarts a term the
    reference holds (e.g. its discrepancy switched off).

    Values are moved inside the prior's 0.1–99.9 % quantiles: a reference that sat at a bound (a
    discrepancy switched off at its lowest scale) would otherwise start the bounded search where its
    transform is singular, and the new term's parameters would not move."""
    return _start_rows(model, reference.fit.model, reference.fit.sampling.theta_map, points)


def _start_rows(model, reference_model, reference_theta, points=None):
    """:func:`start_guesses` from any optimum ``reference_theta`` of ``reference_model``."""
    return _rows_from(model, dict(zip(reference_model.names, reference_theta)), points)


def _rows_from(model, base, points=None):
    """:func:`start_guesses` from values {name: value}; a term none of whose parameters ``base`` holds is new."""
    points = points or {}
    held = {p.group for p in model.parameters if p.name in base}
    new = [e for e in model.extensions if e.name not in held or e.name in points]
    rows = []
    for combo in itertools.product(*[points.get(e.name, e.start_points(model)) for e in new]) if new else [()]:
        point = {k: v for d in combo for k, v in d.items()}
        theta = np.array([p.prior.ppf(0.5) for p in model.parameters], dtype=float)
        for i, name in enumerate(model.names):
            if name in point:
                theta[i] = point[name]
            elif name in base:
                theta[i] = base[name]
        inner = [(p.prior.ppf(1e-3), p.prior.ppf(1 - 1e-3)) for p in model.parameters]
        rows.append(np.clip(theta, [lo for lo, _ in inner], [hi for _, hi in inner]))
    return rows


def verdict_names(model, term):
    """Names of the parameters a verdict on ``term`` reads in ``model``: the term's (its size, its edges)
    and the discrepancy's (the share it takes over)."""
    return tuple(p.name for p in model.parameters if p.group in (term, DISCREPANCY))


def fit_candidate(label, test, reduction, options: DiagnoseOptions, reference=None, baseline=None, echo=None,
                  index=None, guesses=None, executor=None):
    """Fit the model ``label`` (``"baseline"``, ``"discrepancy"``, ``"added_mass+discrepancy"``, ...).

    A model other than the baseline starts from ``reference``'s MAP (default
    ``baseline``) with its new terms at their start points; ``guesses``
    replace those starts (e.g. a screen's MAP); ``executor`` runs the fit's
    ensembles.
    """
    started = _time.perf_counter()
    index = candidate_seed_index(label) if index is None else index
    sampler = replace(options.sampler, seed=int(np.random.default_rng([options.seed, index]).integers(2**31 - 1)))
    if label == BASELINE:
        model = prepare_model(test, reduction, options.priors, options.decay, below_previous=options.below_previous)
        fit = fit_model(model, sampler, echo=echo, executor=executor)
    else:
        model = _model_for(label, test, reduction, options, baseline)
        # Given optima (a screen's MAP, which searched from every start point) or a reference that holds
        # every term of the model (its MAP is this model's but for the terms dropped) are searched from
        # alone: a jittered copy would cost a whole search (20–60 s on a Main with added mass) to find
        # the same optimum. From a reference that lacks terms, the jittered starts stay.
        reference = reference if reference is not None else baseline
        settled = guesses is not None or not _new_terms(model, reference.fit.model)
        if guesses is None:
            guesses = start_guesses(model, reference)
        starts = len(guesses) if settled else max(len(guesses), sampler.map_starts)
        fit = fit_model(model, replace(sampler, map_starts=starts), echo=echo, guesses=guesses, executor=executor)
    return CandidateFit(name=label, fit=fit, loo=psis_loo(fit.tree), seconds=_time.perf_counter() - started)


def restart_points(fit: Fit):
    """Where a longer fit of ``fit``'s model starts its MAP search: the kept draw of highest log posterior,
    then the fit's own MAP. The ensembles can find far more than the search did on a rugged posterior: a
    Drogue's added mass (k_a 0.9) beside a friction drift, seed 30005, started from a MAP at log p 148.5 and
    its two ensembles' best draws reached 260 and 219 without meeting (R-hat 1.36 after 8,000 steps), so a
    longer fit from that MAP started where neither ensemble stayed."""
    best, best_lp = fit.sampling.theta_map, -np.inf
    for run in fit.sampling.runs:
        lp = np.where(np.isfinite(run.log_prob), run.log_prob, -np.inf)
        w, s = np.unravel_index(int(np.argmax(lp)), lp.shape)
        if lp[w, s] > best_lp:
            best, best_lp = run.draws[w, s], lp[w, s]
    return [np.asarray(best, float), np.asarray(fit.sampling.theta_map, float)]


MODEL_FORMS = {"composite": {"cluster": "composite"}, "exponential": {"decay": "exponential"},
               "linear": {"decay": "linear"}}


def fit_model_form(form, test, reduction, options: DiagnoseOptions, echo=None, executor=None):
    """The baseline in another form: ``composite`` (one set of inflation parameters for the cluster's
    like canopies, as a composite model) or a decay shape (``linear``, ``exponential``)."""
    started = _time.perf_counter()
    index = candidate_seed_index(f"form:{form}")
    sampler = replace(options.sampler, seed=int(np.random.default_rng([options.seed, index]).integers(2**31 - 1)))
    kwargs = dict(MODEL_FORMS[form])
    decay = kwargs.pop("decay", options.decay)
    model = prepare_model(test, reduction, options.priors, decay, below_previous=options.below_previous, **kwargs)
    fit = fit_model(model, sampler, echo=echo, executor=executor)
    return CandidateFit(name=form, fit=fit, loo=psis_loo(fit.tree), seconds=_time.perf_counter() - started)


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


SCREEN_PARTS = ("reference", "off")   # a screen's two groups of starts, which may run as separate tasks


def screen_candidate(label, test, reduction, options: DiagnoseOptions, reference: CandidateFit, baseline=None,
                     term=None, part=None, named_plain=None):
    """MAP of model ``label`` from ``reference``'s MAP; passes when the log posterior rises by more
    than ``options.screen_gain`` (5) and with ``term``'s size at the MAP beyond its practical floor
    (mode ``screen``) or half of it (mode ``full``: the naming rule reads the posterior median).

    The MAP gain bounds the elpd gain from above up to the prior's share (a
    term that cannot raise the best fit cannot predict held-out bins better;
    the log prior density of a term's parameters at their MAP is < 3 for every
    catalogued term), so a term failing the screen could not have passed the
    naming rule's ``min_gain`` (10).

    Two groups of starts (:data:`SCREEN_PARTS`): ``"reference"``, the reference's MAP with the new
    term at each of its start points, and ``"off"`` (none without a discrepancy): the discrepancy
    switched off with the new term at a typical size, at the reference's MAP and at the optimum of the
    same terms without the discrepancy (:func:`_start_from_plain_optimum`; ``named_plain``, {name: value},
    the optimum of the terms named so far without it, where that search starts). ``part`` runs one group;
    the better of the two (:func:`best_screen`) is the screen's answer, the same as ``part=None``'s up
    to the search's early stop.
    """
    if part is not None and part not in SCREEN_PARTS:
        raise ValueError(f"unknown screen part {part!r}; use one of {SCREEN_PARTS} or None")
    started = _time.perf_counter()
    baseline = baseline if baseline is not None else reference
    model = _model_for(label, test, reduction, options, baseline)
    reference_starts = start_guesses(model, reference)
    guesses = {"reference": reference_starts if part in (None, "reference") else [], "off": []}
    plain_optimum = None
    discrepancy = next((e for e in model.extensions if e.name == DISCREPANCY), None)
    key = [options.seed, candidate_seed_index(label), 3] + ([1 + SCREEN_PARTS.index(part)] if part else [])
    if discrepancy is not None and part in (None, "off"):
        # Also with the new term at a typical size (its last start point) and the discrepancy off (its
        # first): from the reference's MAP the discrepancy already holds the misfit, and every search
        # keeps it there with the term small — a Main's added mass stopped at k_a 0.07 (log p 330
        # short) against 0.19 from this start, where the discrepancy switches itself off.
        points = {e.name: e.start_points(model)[-1:] for e in _new_terms(model, reference.fit.model)}
        points[DISCREPANCY] = discrepancy.start_points(model)[:1]
        guesses["off"] = start_guesses(model, reference, points=points)
        rows, plain_optimum = _start_from_plain_optimum(label, test, reduction, options, reference, baseline, model,
                                                        points, np.random.default_rng(key + [9]), named_plain)
        guesses["off"] += rows
    chosen = guesses["reference"] + guesses["off"]
    if not chosen:       # no discrepancy: nothing to switch off
        return None
    # jittered starts (up to ``map_starts`` in all) belong to the reference's group
    off_starts = _OFF_STARTS if discrepancy is not None else 0
    jitter = max(0, options.sampler.map_starts - len(reference_starts) - off_starts)
    theta, log_post = find_map(model, np.random.default_rng(key), len(chosen) + (jitter if part != "off" else 0),
                               chosen)
    gain = float(log_post - reference.fit.sampling.log_post_map)
    size = None
    passed = gain > options.screen_gain
    floor = make_extension(term).practical_floor if term is not None else None
    if floor is not None:
        param, minimum = floor
        size = float(theta[model.index[param]])
        # Mode full samples a term whose MAP size is short of its floor by less than half: a posterior
        # median can sit above the MAP (a skewed size), not at twice it. Mode screen needs the floor.
        share = 1.0 if options.mode == "screen" else FULL_MODE_FLOOR_SHARE
        passed = passed and abs(size) >= share * minimum
    return ScreenResult(name=term or label, map_gain=gain, size=size, passed=bool(passed), theta_map=theta,
                        seconds=_time.perf_counter() - started, plain_optimum=plain_optimum)


_OFF_STARTS = 2    # the "off" group's starts: the discrepancy off at the reference's MAP, and at the plain optimum


def _start_from_plain_optimum(label, test, reduction, options, reference, baseline, model, points, rng,
                              named_plain=None):
    """A start of ``model`` (terms + discrepancy) from the MAP of its terms *without* the discrepancy; the
    discrepancy at its first (off) start point. Returns (the start rows, that MAP {name: value}).

    Without a discrepancy to hold the misfit the new term must explain it, and its own mode is found; the
    search with the discrepancy then starts there. On a Main with a large added mass and a friction drift
    the other starts all ended in a mode where the discrepancy held most of the added mass (k_a 0.24,
    exponent at its lower edge, log p +322 over the reference); from this one at k_a 0.56, exponent 1.43
    (truth 0.58, 1.5), +2,014.

    The plain search starts from the baseline's MAP, with the terms named so far at the reference's values
    and the new term at each of its start points, then from the reference's MAP with the new term at
    ``points``. The baseline's inflation is the plain model's own with its terms off; the reference's was
    shaped by the discrepancy. A Drogue with a sensor lag and an added mass (pairs seed 30011; k_a 0.98,
    exponent 1.5, lag 0.054 s), beside the lag + discrepancy fit: from the reference's MAP (one canopy's
    C_k 47 baseline sd off) the plain search ended at log p −218 (k_a 1.18, exponent 1.99), as it did from
    the baseline's with the mass' typical start behind its 0.12 s lag; from the baseline's with either of
    its other starts, at +406.6 (k_a 0.993, exponent 1.53, lag 0.0542 s).

    After the first round, ``named_plain`` (the optimum of the named terms without the discrepancy, which the
    screen of the last term named found) replaces the baseline's MAP: it is that optimum with the terms named
    so far in their own mode, from which only the new term has to be found. From the baseline's, a Main's
    search for added mass + lag took 37 s and one for added mass + lag + breathing 61 s (pairs seed 30003)."""
    terms, _ = label_terms(label)
    plain = _model_for(model_label(list(terms)), test, reduction, options, baseline)
    new = {k: v for k, v in points.items() if k != DISCREPANCY}
    every = {e.name: e.start_points(plain) for e in plain.extensions if e.name in new}
    if named_plain is None:   # the first round: the baseline's MAP, any named terms at the reference's values
        named_plain = dict(zip(baseline.fit.model.names, baseline.fit.sampling.theta_map))
        named_plain.update({p.name: value for p, value in zip(reference.fit.model.parameters,
                                                              reference.fit.sampling.theta_map)
                            if p.group in terms and p.group not in new})
    starts = _rows_from(plain, named_plain, points=every) + start_guesses(plain, reference, points=new)
    theta, _ = find_map(plain, rng, len(starts), starts)
    return (_start_rows(model, plain, theta, points={DISCREPANCY: points[DISCREPANCY]}),
            dict(zip(plain.names, map(float, theta))))


def best_screen(results):
    """One screen from its parts' results (``None`` for a part without starts): the highest MAP, with the
    parts' seconds summed and the "off" part's plain optimum."""
    found = [r for r in results if r is not None]
    best = max(found, key=lambda r: r.map_gain)
    plain = next((r.plain_optimum for r in found if r.plain_optimum is not None), None)
    return replace(best, seconds=sum(r.seconds for r in found), plain_optimum=plain)


def for_tasks(candidate: CandidateFit) -> CandidateFit:
    """``candidate`` as a start for other models' searches and fits: its model and MAP, without its
    draws, DataTree and LOO, which a worker does not read (they are 60–110 MB on a Main, sent with
    every task)."""
    fit = candidate.fit
    return replace(candidate, loo=None, fit=replace(fit, tree=None, sampling=replace(fit.sampling, runs=[])))


def baseline_from_fit(fit: Fit) -> CandidateFit:
    """Use an existing baseline fit (e.g. a campaign's) as the diagnosis' baseline."""
    return CandidateFit(name=BASELINE, fit=fit, loo=psis_loo(fit.tree), seconds=0.0)


def extension_parameters(candidate: CandidateFit, terms=None):
    """Posterior mean, sd and 90 % interval of the parameters of the model's terms (all of the
    label's terms by default; the discrepancy's scale included when it is one of them)."""
    model, post = candidate.fit.model, candidate.fit.tree["posterior"]
    groups = set(terms) if terms is not None else set(candidate.name.split("+"))
    out = {}
    for p in model.parameters:
        if p.group not in groups:
            continue
        x = np.asarray(post[p.name].values, float).ravel()
        q05, q50, q95 = np.quantile(x, (0.05, 0.5, 0.95))
        out[p.name] = {"mean": float(x.mean()), "sd": float(x.std()), "median": float(q50),
                       "q05": float(q05), "q95": float(q95), "unit": p.unit}
    return out

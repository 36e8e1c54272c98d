"""The diagnosis' rules: when a term is named, when the baseline is adequate, when a misfit is unexplained.

Every comparison is on PSIS-LOO per time bin of the joint log-likelihood of
all channels of the bin; a difference and its standard error come from the
paired pointwise values, se = √(N·Var(Δelpd_i)) (:func:`paired_difference`).

Naming a term (:func:`check_term`, :func:`choose_term`)
--------------------------------------------------------
A catalogued term T is judged *with the generic discrepancy present*:
elpd(named + T + discrepancy) − elpd(named + discrepancy). The discrepancy
(:mod:`cpas_bayes.stats.discrepancy`) soaks up whatever the model lacks, so T
gains only where its physics describes the data better than a smooth
generic curve with many coefficients: a term of the right physics wins even
when the effect's form differs from it a little, and a term standing in for
something else gains little (the discrepancy already took that structure).
T may be named when

* its gain exceeds ``min_gain`` (10) and ``min_gain_se`` (2) standard errors —
  or, when the discrepancy itself found a significant misfit, its gain
  exceeds ``min_gain`` and it takes over ≥ 70 % of the discrepancy (the
  whitened energy of the discrepancy's posterior mean falls by that much when
  T is added). The discrepancy interpolates a smooth misfit well, so a term
  of the right physics may beat it by less than 2 se on the bins while
  explaining nearly all of it; a stand-in leaves most of it in place. A term
  that takes over ≥ 90 % of a significant discrepancy explains it even when
  its gain is within ``min_gain_se`` se of zero: a load-cell lag, which the
  discrepancy on the load cells' drag area mimics almost exactly, was found at
  0.0375 s (true 0.04) and collapsed the discrepancy, gaining −6.9 ± 20.0;
* its fit converged: nested R-hat ≤ 1.01 and bulk ESS ≥ 400 (:func:`fit_converged`) —
  or, for the parameters the verdict reads (the term's and the discrepancy's),
  R-hat ≤ 1.05 and bulk ESS ≥ 400 with the gains its ensembles give one by
  one within the comparison's se of each other (:func:`comparison_settled`:
  the verdict needs the gain and those parameters, and more sampling could move
  the gain by less than the data's own uncertainty about it; the inflation
  law's own parameters may still drift slowly);
* its fitted size is beyond the term's practical floor (``Extension.practical_floor``);
* no parameter of T sits at the edge of its prior: the posterior's 5 % or
  95 % quantile beyond the prior's 0.5 % or 99.5 % point (a stand-in that
  would go further if allowed), except the size parameter's lower side,
  which the floor covers, a lower bound that is a physical limit
  (``Extension.physical_lower_limits``: an added-mass lag of 0, a breathing
  that does not die away), and an angle (``Extension.periodic``: a canopy's
  breathing phase, whose ±π is one point);
* its size parameter does not repeat its prior (posterior variance < 90 % of
  the prior's): otherwise the data did not inform it;
* it leads every other passing term clearly: by > ``min_margin_se`` (2) se of
  their paired difference, or by > ``min_gain`` with ``min_margin_ratio``
  (1.5) × its gain, or by the shape of the misfit: it takes over ≥ 90 % of the
  generic discrepancy where the other takes over ≤ 30 %. When two terms pass
  without a clear lead, the better is taken on trial: it is kept only if the
  other still gains in the next round (then both are real), else the pair is
  ambiguous and neither is named.

Why 10 and 2 se rather than the common "4 and 4 se": the effects sought act
in a few transients (a fill, a peak), so the pointwise differences are
concentrated in a few dozen bins and their se ≈ gain/√m for m bins carrying
the gain — a 4-se rule would fail on any localized effect however large. On
clean tests of two simulators the terms gain < 3; the smallest simulated
effects gain ≥ 20; 10 sits between.

Forward selection: after naming a term it joins the reference model and the
remaining terms are tried again (screened by their MAP gain, then sampled),
until none passes or ``max_causes`` are named. Within a round the term with
the largest MAP gain is sampled first; when it passes and no other screened
term could rival it (:func:`cannot_rival`: a rival's elpd gain is bounded by
its MAP gain plus its prior's share, and even that bound would leave the
leader clearly ahead), the others wait for the next round, where they are
screened and judged again with the leader in the reference.

Adequacy of the baseline (:func:`adequacy`) — what ``none`` requires
--------------------------------------------------------------------
* error multipliers (posterior mean) within [1/1.5, 1.5]: the fitted noise
  is within 50 % of the stated sigmas; a wrong stated sigma is itself a
  finding, and the 1-sigma of a multiplier from a few hundred bins is a few %;
* no residual structure: every channel × phase row's Ljung–Box p-value above
  0.001/rows (Bonferroni at 0.1 % for the whole table: at 1 % one clean
  synthetic Drogue in four failed on a 40-bin pre-deploy row, while the
  effects sought give p < 1e-20);
* at most two posterior-predictive statistics outside [0.005, 0.995]: each
  p-value is resolved to 1/200 by the replicates, and a calibrated model puts
  one of its 30–60 statistics there 1 % of the time each, so ≥ 3 flags happen
  in ≈ 2 % of clean Mains (60 statistics) and 0.4 % of clean Drogues (30);
* LOO-PIT: each channel's KS p-value above 0.001/channels;
* the generic discrepancy does not pass the naming thresholds against the
  baseline (gain > 10 and > 2 se);
* an accelerometer that agrees with the airspeed's rate
  (:mod:`cpas_bayes.data.kinematics`, :func:`kinematic_findings`): a check of
  the readings that no term can pass; when it fails, ``unexplained`` is a cause
  at its windows, and the terms read against the accelerometer are not tried
  (:func:`terms_to_try`).

Unexplained (:func:`unexplained_share`)
----------------------------------------
The discrepancy's gain over the model with the named terms measures what is
left to explain; its share of the discrepancy's gain over the baseline says
how much the named terms explained. ``unexplained`` is a cause when that
remainder passes the naming thresholds and either nothing was named or the
named terms explain less than ``min_share`` (½) of it; and when nothing was
named but the baseline fails its adequacy checks. Named terms are withdrawn as stand-ins
(:func:`withdrawn_terms`) when every one of them was named only for taking the discrepancy's shape over and
alone they explain less than half of its gain, or when every one gained less than twice ``min_gain`` and
they leave an unexplained misfit beside them: slivers of an effect no term describes; or when every one
took over less than a tenth of the discrepancy and they leave such a misfit: structure beside it, faster
than the discrepancy can carry, not the misfit itself.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from cpas_bayes.data.kinematics import accelerometer_kinematics
from cpas_bayes.inference.candidate_fits import (BASELINE, CandidateFit, DiagnoseOptions, psis_loo,
                                                 verdict_names)
from cpas_bayes.inference.fit_health import ESS_MIN, RHAT_MAX
from cpas_bayes.stats.model_terms import PHYSICAL, applies, make_extension

MULTIPLIER_RANGE = (1 / 1.5, 1.5)
FAMILY_ALPHA = 0.001        # Ljung–Box over the channel × phase table (Bonferroni); KS of LOO-PIT likewise
PPC_TAIL = 0.005            # a PPC statistic is flagged outside [PPC_TAIL, 1 − PPC_TAIL] ...
PPC_MAX_FLAGS = 2           # ... and more than this many flags fail the baseline
EDGE_QUANTILE = 0.005
REPEATS_PRIOR = 0.9
RHAT_LOOSE = 1.05           # R-hat a fit may have when its ensembles agree on the gain (comparison_settled)
TAKE_OVER = 0.7             # share of a significant discrepancy a term must take over when its gain is < 2 se
EXPLAINS = 0.9              # ... and the share that names a term whose gain is within 2 se of zero (it explains)
SLIVER = 2.0                # × min_gain: below it, terms beside an unexplained misfit are withdrawn (slivers)
UNTOUCHED = 0.1             # share of the discrepancy below which a term beside an unexplained misfit is withdrawn


def paired_difference(a: CandidateFit, b: CandidateFit):
    """elpd(a) − elpd(b) and its standard error from the paired pointwise values."""
    d = a.pointwise_elpd - b.pointwise_elpd
    return float(d.sum()), float(math.sqrt(d.size * np.var(d, ddof=1)))


def passes(diff, se, options: DiagnoseOptions):
    """The gain thresholds: > ``min_gain`` and > ``min_gain_se`` standard errors."""
    return diff > options.min_gain and diff > options.min_gain_se * se


def compare_table(baseline, candidates):
    """``arviz.compare`` over the baseline and the candidates (ranked by elpd), from the PSIS-LOO each
    already holds: given the trees, it recomputed every one (on a Main, 1.5–2 s each in this process)."""
    import arviz_stats as azs

    results = {BASELINE: baseline.loo, **{n: c.loo for n, c in candidates.items()}}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=UserWarning)
        table = azs.compare(results)
    return table


def ensemble_gains(candidate: CandidateFit, reference: CandidateFit):
    """elpd(candidate) − elpd(reference) with the candidate's PSIS-LOO from each of its ensembles alone."""
    tree = candidate.fit.tree
    ensemble = np.asarray(tree["posterior"]["ensemble"].values)
    gains = []
    for e in np.unique(ensemble):
        sub = tree.isel(chain=np.flatnonzero(ensemble == e), missing_dims="ignore")
        gains.append(float(psis_loo(sub).elpd) - float(reference.loo.elpd))
    return gains


def comparison_settled(candidate: CandidateFit, reference: CandidateFit, se, term=None):
    """Whether a fit short of R-hat 1.01 still settles the comparison: bulk ESS ≥ 400, R-hat ≤ 1.05
    and the gains its ensembles give one by one within ``se`` (the comparison's own standard error
    from the data) of each other — more sampling could then move the gain by less than the data's
    uncertainty about it. Returns (settled, the per-ensemble gains).

    With ``term``, the R-hat and ESS asked are those of the parameters the verdict reads — the term's
    (its size, its edges) and the discrepancy's (the share it takes over) — not of the inflation law's:
    on a Main with added mass the disreef stages' start, n_p and expopen drift together slowly (R-hat
    1.16–1.24 after 6,000 steps, ensemble means 0.8 sd apart) while both ensembles agree on k_a to
    0.1 sd and on the gain."""
    d = candidate.fit.summary["diagnostics"]
    rhat, ess = d["rhat_max"], d["ess_bulk_min"]
    per = candidate.fit.summary.get("diagnostics_per_parameter")
    if term is not None and per:
        read = verdict_names(candidate.fit.model, term)
        rhat = max(per[n]["rhat"] for n in read)
        ess = min(per[n]["ess_bulk"] for n in read)
    if not (ess >= ESS_MIN and rhat <= RHAT_LOOSE):
        return False, []
    gains = ensemble_gains(candidate, reference)
    return bool(max(gains) - min(gains) <= se), gains


def fit_converged(fit):
    """Nested R-hat ≤ 1.01 and bulk ESS ≥ 400 (fit health's thresholds). An ensemble stopped at its
    step limit before its τ rule was met still has what the comparison needs when both are on target:
    a Main's added mass with a lag (τ ≈ 800 steps) met them after 6,000 steps, 8,000 short of 10 τ."""
    d = fit.summary["diagnostics"]
    return bool(d["rhat_max"] <= RHAT_MAX and d["ess_bulk_min"] >= ESS_MIN)


def versus_baseline(baseline, candidates):
    """One row per fitted model: elpd difference against the baseline, its se, p_loo, Pareto-k > 0.7 count."""
    rows = []
    for name, c in candidates.items():
        diff, se = paired_difference(c, baseline)
        k = np.asarray(c.loo.pareto_k.values, float)
        rows.append({"name": name, "elpd_diff": diff, "elpd_diff_se": se,
                     "z": diff / se if se > 0 else float("inf"), "elpd_loo": float(c.loo.elpd),
                     "p_loo": float(c.loo.p), "n_high_pareto_k": int(np.sum(k > 0.7)),
                     "physical": name in PHYSICAL, "seconds": c.seconds,
                     "converged": fit_converged(c.fit),
                     "rhat_max": float(c.fit.summary["diagnostics"]["rhat_max"])})
    columns = ["name", "elpd_diff", "elpd_diff_se", "z", "elpd_loo", "p_loo", "n_high_pareto_k", "physical",
               "seconds", "converged", "rhat_max"]
    return pd.DataFrame(rows, columns=columns)


# ---------------------------------------------------------------------------
# one term, judged against its reference


@dataclass
class TermCheck:
    """What the rule found for one term in one round of forward selection."""

    term: str
    model: str                  # the label of the fitted model (term + named + discrepancy)
    reference: str              # the label it is compared with
    elpd_diff: float
    elpd_diff_se: float
    converged: bool
    size: float | None          # the size parameter's posterior median
    below_floor: bool
    gains: bool = False         # passes the gain thresholds (or takes the discrepancy over)
    share: float | None = None  # fraction of the reference's discrepancy the term takes over
    size_repeats_prior: bool = False
    explains_only: bool = False  # passed only by explaining the discrepancy's shape, not by its gain
    at_edge: list = field(default_factory=list)        # "parameter (upper/lower edge ...)"
    repeats_prior: list = field(default_factory=list)  # parameters whose posterior repeats the prior
    reasons: list = field(default_factory=list)

    @property
    def eligible(self):
        """Everything but the gain and the margin: a fit that may be named if it gains enough."""
        return self.converged and not self.below_floor and not self.at_edge and not self.size_repeats_prior

    def as_dict(self):
        return {"term": self.term, "model": self.model, "reference": self.reference, "elpd_diff": self.elpd_diff,
                "elpd_diff_se": self.elpd_diff_se, "converged": self.converged, "size": self.size,
                "below_floor": self.below_floor, "at_edge": self.at_edge, "repeats_prior": self.repeats_prior,
                "discrepancy_taken_over": self.share,
                "passed": self.gains and self.eligible, "reasons": self.reasons}


def _prior_variance(prior, rng):
    x = prior.sample(rng, 20_000)
    return float(np.var(x[np.isfinite(x)]))


def parameter_health(candidate: CandidateFit, term: str, rng=None):
    """Per parameter of ``term``: posterior quantiles, edge-of-prior side (or None), prior contraction."""
    rng = rng if rng is not None else np.random.default_rng(0)
    model, post = candidate.fit.model, candidate.fit.tree["posterior"]
    extension = make_extension(term)
    floor = extension.practical_floor
    size_name = floor[0] if floor else None
    out = {}
    for p in model.parameters:
        if p.group != term:
            continue
        x = np.asarray(post[p.name].values, float).ravel()
        q05, q50, q95 = np.quantile(x, (0.05, 0.5, 0.95))
        edge = None
        angle = any(p.name.startswith(prefix) for prefix in extension.periodic)   # a circle has no edge
        if not angle and float(p.prior.cdf(q95)) > 1 - EDGE_QUANTILE:
            edge = "upper"
        elif (not angle and float(p.prior.cdf(q05)) < EDGE_QUANTILE and p.name != size_name
              and p.name not in extension.physical_lower_limits):
            edge = "lower"
        prior_var = _prior_variance(p.prior, rng)
        ratio = float(np.var(x) / prior_var) if prior_var > 0 else 0.0
        out[p.name] = {"median": float(q50), "q05": float(q05), "q95": float(q95), "edge": edge,
                       "posterior_to_prior_variance": ratio, "repeats_prior": ratio > REPEATS_PRIOR,
                       "is_size": p.name == size_name}
    return out


def stand_ins_by_shape(named, rounds, share, options):
    """The named terms to withdraw: every one named only because it took the discrepancy's shape over
    (:data:`EXPLAINS`, its gain within 2 se of zero) when the named terms, fitted without the discrepancy,
    explain less than ``options.min_share`` of its gain. Such a term did not explain the misfit: with the
    discrepancy present the stage law's parameters moved and the term took the rest (an over-inflation bump
    of another inflation law, `benchmarks/independent_drops.md` C1: canopy_breathing 3.7 ± 7.0 over the
    discrepancy, the stage's start and expopen moved 30 sd, the breathing alone 3 % of the discrepancy's
    gain). Withdrawn only when every named term is such a one, so the named fit stays the one measured."""
    by_shape = {c.term for r in rounds for c in r["checks"] if c.term == r.get("chosen") and c.explains_only}
    if named and share < options.min_share and set(named) <= by_shape:
        return list(named)
    return []


def slivers_beside_unexplained(named, rounds, share, left, options):
    """The named terms to withdraw: every one gained less than :data:`SLIVER` × ``options.min_gain`` over
    its reference, while the named terms, fitted without the discrepancy, explain less than
    ``options.min_share`` of its gain and what they leave (``left``) passes the naming thresholds.

    Such a term took a sliver of a misfit it does not describe: the misfit stays unexplained either way,
    and an out-of-catalogue effect offers every term some structure to take. A Drogue's pitot lag (detection
    study, seed 20004) had ``added_mass`` named at 10.2 ± 4.1 over the discrepancy, explaining 22 % of the
    discrepancy's gain, the rest gaining 97.7 ± 14.8. Catalogued effects gain far more where they leave a
    misfit beside them (a Drogue's added mass at k_a 0.6: +279 to +418; a Main's lag beside an added mass
    +58 to +74), and a term whose gain is this small leaves no misfit to speak of when it is the cause
    (the rule's 10 sits between clean tests' < 3 and the smallest simulated effects' ≥ 20). As in
    :func:`stand_ins_by_shape`, withdrawn only when every named term is such a one."""
    gains = chosen_gains(rounds)
    if named and left and share < options.min_share and \
            all(gains.get(t, math.inf) < SLIVER * options.min_gain for t in named):
        return list(named)
    return []


def untouched_beside_unexplained(named, rounds, share, left, options):
    """The named terms to withdraw: every one took over less than :data:`UNTOUCHED` of the discrepancy in
    the round that named it, while the named terms, fitted without the discrepancy, explain less than
    ``options.min_share`` of its gain and what they leave (``left``) passes the naming thresholds.

    Such a term gained on structure the smooth discrepancy cannot carry (faster than its knots) and left
    the misfit the discrepancy found where it was: a load path ringing at 3–8 Hz on a Drogue (detection
    study, seeds 20002 and 20003) had ``canopy_breathing`` named at +99.7 ± 18.1 and +94.0 ± 20.6 over the
    discrepancy, taking over −1 % and −40 % of it, the named terms explaining 4 % and 0 % of the
    discrepancy's gain — the breathing's phase per canopy lets two canopies ring against each other in
    the load cells and cancel in the accelerometer, as a load path's ringing does. Catalogued effects that
    are the cause take most of the discrepancy over (breathing laid on the independent simulator's bundles
    99 % and 83 %). A genuine fast effect beside an out-of-catalogue one would be withdrawn too; the verdict
    is then ``unexplained`` alone, which still flags the test. As in :func:`stand_ins_by_shape`, withdrawn
    only when every named term is such a one."""
    chosen = chosen_checks(rounds)
    if named and left and share < options.min_share and \
            all(t in chosen and chosen[t].share is not None and chosen[t].share < UNTOUCHED for t in named):
        return list(named)
    return []


def chosen_checks(rounds):
    """{term: its TermCheck} of the term each round of forward selection chose."""
    return {c.term: c for r in rounds for c in r["checks"] if c.term == r.get("chosen")}


def chosen_gains(rounds):
    """{term: its elpd gain over its reference} of the term each round of forward selection chose."""
    return {t: c.elpd_diff for t, c in chosen_checks(rounds).items()}


def withdrawn_terms(named, rounds, share, left, options):
    """The named terms the verdict withdraws as stand-ins, and the sentence that says why: those of
    :func:`stand_ins_by_shape`, else those of :func:`slivers_beside_unexplained` (``left``: what the named terms
    leave passes the naming thresholds), else those of :func:`untouched_beside_unexplained`. ``([], "")`` when
    the names stand."""
    if withdrawn := stand_ins_by_shape(named, rounds, share, options):
        return withdrawn, (f"{', '.join(withdrawn)} withdrawn: named for taking the discrepancy's shape over, alone "
                           f"it explains {100 * share:.0f} % of the discrepancy's gain (a stand-in)")
    if withdrawn := slivers_beside_unexplained(named, rounds, share, left, options):
        gains = chosen_gains(rounds)
        return withdrawn, (f"{', '.join(withdrawn)} withdrawn: gained {', '.join(f'{gains[t]:.1f}' for t in withdrawn)}"
                           f" over {'its reference' if len(withdrawn) == 1 else 'their references'}, less than "
                           f"{SLIVER * options.min_gain:g}, and the named terms explain {100 * share:.0f} % of the "
                           "discrepancy's gain, the rest a misfit of its own (a sliver of it, not its cause)")
    if withdrawn := untouched_beside_unexplained(named, rounds, share, left, options):
        return withdrawn, (f"{', '.join(withdrawn)} withdrawn: took over less than {100 * UNTOUCHED:.0f} % of the "
                           f"discrepancy, and the named terms explain {100 * share:.0f} % of its gain: it fits "
                           "structure beside the misfit, not the misfit (a stand-in)")
    return [], ""


def check_term(term, candidate: CandidateFit, reference: CandidateFit, options: DiagnoseOptions,
               share=None, misfit=False) -> TermCheck:
    """Judge ``term`` in ``candidate`` (= reference + term) against ``reference`` (the rule above).

    ``share``: the fraction of the reference's discrepancy that the term takes
    over (1 − its whitened energy with the term / without); ``misfit``: whether
    the reference's discrepancy itself passes the gain thresholds.
    """
    diff, se = paired_difference(candidate, reference)
    converged = fit_converged(candidate.fit)
    settled, per_ensemble = (False, [])
    if not converged:
        settled, per_ensemble = comparison_settled(candidate, reference, se, term)
    health = parameter_health(candidate, term)
    size = next((h["median"] for h in health.values() if h["is_size"]), None)
    floor = make_extension(term).practical_floor
    below = floor is not None and size is not None and abs(size) < floor[1]
    check = TermCheck(term=term, model=candidate.name, reference=reference.name, elpd_diff=diff, elpd_diff_se=se,
                      converged=converged or settled, size=size, below_floor=below,
                      at_edge=[f"{n} ({h['edge']} edge of its prior, median {h['median']:.3g})"
                               for n, h in health.items() if h["edge"]],
                      repeats_prior=[n for n, h in health.items() if h["repeats_prior"]],
                      size_repeats_prior=any(h["repeats_prior"] for h in health.values() if h["is_size"]),
                      gains=passes(diff, se, options), share=share)
    takes_over = bool(misfit and share is not None and share >= TAKE_OVER and diff > options.min_gain)
    explains = bool(misfit and share is not None and share >= EXPLAINS and diff > -options.min_gain_se * se)
    r = check.reasons
    if passes(diff, se, options):
        r.append(f"{term} gains {diff:.1f} ± {se:.1f} in elpd over {reference.name}")
    elif takes_over or explains:
        check.gains, check.explains_only = True, not takes_over
        r.append(f"{term} gains {diff:.1f} ± {se:.1f} in elpd over {reference.name} and takes over "
                 f"{100 * share:.0f} % of its discrepancy: the physics explains the misfit the generic term found"
                 + ("" if takes_over else " as well as the generic term does, with one term's parameters"))
    else:
        r.append(f"{term} gains {diff:.1f} ± {se:.1f} in elpd over {reference.name} (the rule needs > "
                 f"{options.min_gain:g} and > {options.min_gain_se:g} se, or > {options.min_gain:g} while taking over "
                 f"≥ {100 * TAKE_OVER:.0f} % of a significant discrepancy, or > −{options.min_gain_se:g} se while "
                 f"taking over ≥ {100 * EXPLAINS:.0f} %"
                 + (f"; it takes over {100 * share:.0f} %" if share is not None else "") + ")")
    rhat, ess = (candidate.fit.summary['diagnostics'][k] for k in ("rhat_max", "ess_bulk_min"))
    spread = f"; its ensembles give {', '.join(f'{g:.1f}' for g in per_ensemble)}" if per_ensemble else ""
    if settled:
        r.append(f"the fit of {candidate.name} is short of R-hat 1.01 ({rhat:.3f}) but the parameters the verdict "
                 f"reads (the term's and the discrepancy's) are within {RHAT_LOOSE} and its ensembles agree on the "
                 f"gain within its se{spread}")
    elif not converged:
        r.append(f"the fit of {candidate.name} did not converge (R-hat {rhat:.3f}, bulk ESS {ess:.0f}{spread}): "
                 f"it cannot name {term}")
    if below:
        r.append(f"{term}'s fitted size {floor[0]} = {size:.3g} is below the practical floor {floor[1]:g}: "
                 "a real but negligible effect, not a cause")
    for edge in check.at_edge:
        r.append(f"{term} is a stand-in, not a cause: {edge}")
    if check.size_repeats_prior:
        r.append(f"{term}'s size posterior repeats its prior: the data do not inform it")
    return check


PRIOR_SHARE = 3.0   # log prior density of a catalogued term's parameters at their MAP stays below this


def cannot_rival(leader: TermCheck, map_gain, options: DiagnoseOptions):
    """Whether a term whose screen rose by ``map_gain`` in log posterior could neither be chosen over
    ``leader`` (a passing term) nor deny it a clear lead (:func:`choose_term`).

    The MAP gain bounds the elpd gain from above up to the prior's share (a term that cannot raise the
    best fit cannot predict held-out bins better), so the rival's gain is at most ``map_gain`` +
    :data:`PRIOR_SHARE`; the leader is clear of that bound by the margin rule without its se."""
    if not (leader.gains and leader.eligible):
        return False
    bound = max(float(map_gain), 0.0) + PRIOR_SHARE
    return bool(leader.elpd_diff - bound > options.min_gain
                and leader.elpd_diff >= options.min_margin_ratio * bound)


def choose_term(checks, candidates, options: DiagnoseOptions):
    """The term to name in one round: (term or None, clear, reasons).

    ``clear`` is False when another passing term is not clearly behind (the
    caller then keeps the choice on trial, see the module docstring).
    """
    passing = sorted([c for c in checks if c.gains and c.eligible], key=lambda c: -c.elpd_diff)
    if not passing:
        return None, True, ["no remaining term passes the rule"]
    best = passing[0]
    reasons = [f"{best.term} gains {best.elpd_diff:.1f} ± {best.elpd_diff_se:.1f} over {best.reference}"]
    if len(passing) == 1:
        return best.term, True, reasons
    second = passing[1]
    diff, se = paired_difference(candidates[best.model], candidates[second.model])
    clear = diff > options.min_margin_se * se or (
        diff > options.min_gain and best.elpd_diff >= options.min_margin_ratio * second.elpd_diff)
    takes_it_all = _takes_it_all(best, second)
    lead = f"{best.term} leads {second.term} by {diff:.1f} ± {se:.1f}"
    if clear:
        reasons.append(lead)
    elif takes_it_all:
        reasons.append(f"{lead}, and takes over {100 * best.share:.0f} % of the discrepancy where {second.term} "
                       f"takes over {100 * second.share:.0f} %")
    else:
        reasons.append(f"{lead} — not clearly: kept on trial, named only if {second.term} still gains with "
                       f"{best.term} included")
    return best.term, clear or takes_it_all, reasons


def _takes_it_all(best: TermCheck, second: TermCheck):
    """Whether ``best`` explains the generic discrepancy's structure and ``second`` hardly touches it: it takes
    over at least :data:`EXPLAINS` of it, the other at most 1 − :data:`TAKE_OVER`. The elpd alone then cannot
    separate them (a lag at 0.08 s on a Main, seed 40001: the lag took over 100 %, a friction drift 5 % with a
    gain of 14.0 ± 5.9 beside it, and on trial neither was named), but the shape of what is missing can."""
    return (best.share is not None and second.share is not None and best.share >= EXPLAINS
            and second.share <= 1.0 - TAKE_OVER)


# ---------------------------------------------------------------------------
# adequacy and what is left unexplained


def adequacy(checks, options: DiagnoseOptions, readings=()):
    """(adequate, failures): the baseline's own checks against the thresholds above, after ``readings``: the
    failures the readings show alone (:func:`kinematic_findings`)."""
    failures = list(readings)
    low, high = MULTIPLIER_RANGE
    for name, q in checks.residuals.noise.items():
        if not low <= q["mean"] <= high:
            failures.append(f"error multiplier {name} = {q['mean']:.2f}: the fitted noise is "
                            f"{q['mean']:.1f}× the stated sigma (the rule allows {low:.2f}–{high:.2f})")
    table = checks.residuals.table
    rows = table[table["ljung_box_p"].notna()]
    if len(rows):
        limit = FAMILY_ALPHA / len(rows)
        bad = rows[rows["ljung_box_p"] < limit]
        for r in bad.sort_values("ljung_box_p").head(4).to_dict("records"):
            failures.append(f"residual structure in {r['channel']}, phase {r['phase']}: lag-1 ACF "
                            f"{r['acf1']:+.2f}, Ljung–Box p = {r['ljung_box_p']:.1e} (< {limit:.1e})")
    ppc = checks.ppc.table
    bad = ppc[(ppc["p_value"] < PPC_TAIL) | (ppc["p_value"] > 1 - PPC_TAIL)] if len(ppc) else ppc
    if len(bad) > PPC_MAX_FLAGS:
        what = "; ".join(" ".join(str(r[k]) for k in ("statistic", "series") if k in r) + f" p = {r['p_value']:.3f}"
                         for r in bad.head(4).to_dict("records"))
        failures.append(f"{len(bad)} posterior-predictive statistics outside [{PPC_TAIL:g}, {1 - PPC_TAIL:g}] "
                        f"(the rule allows {PPC_MAX_FLAGS}): the model cannot reproduce {what}")
    pit = checks.loo_pit.table
    if len(pit):
        limit = FAMILY_ALPHA / len(pit)
        for r in pit[pit["ks_p_value"] < limit].to_dict("records"):
            failures.append(f"LOO-PIT of {r['channel']} is not uniform (KS p = {r['ks_p_value']:.1e})")
    return not failures, failures


def terms_to_try(candidates, test, accelerometer_failures=()):
    """(terms, warnings): the physical ``candidates`` that ``test`` lets the diagnosis try, and a sentence for
    each group not tried. Load-cell terms need load cells. With an accelerometer the airspeed's rate
    contradicts (``accelerometer_failures``, :func:`kinematic_findings`), terms whose evidence is the load
    cells read against the accelerometer (a friction factor's drift, a lag behind its time base) are not tried
    either: a drifting ratio of the two is then the accelerometer's as readily (a 0.05 g zero drift on the
    independent simulator's Main was named ``friction_drift`` and ``sensor_lag``)."""
    physical = [n for n in candidates if n in PHYSICAL]
    terms = [n for n in physical if applies(n, test)]
    out = []
    if skipped := [n for n in physical if n not in terms]:
        why = ("they act on load cells, and the test has none" if test.measured_qbar else
               "they act on load cells, which a logger bundle has none of")
        out.append(f"not tried: {', '.join(skipped)} ({why})")
    if accelerometer_failures and (against := [n for n in terms if make_extension(n).needs_load_cells]):
        terms = [n for n in terms if n not in against]
        out.append(f"not tried: {', '.join(against)} (read against the accelerometer, and "
                   f"{accelerometer_failures[0]})")
    return terms, out


def kinematic_findings(test):
    """(failures, where) of :func:`cpas_bayes.data.kinematics.accelerometer_kinematics`: when the accelerometer
    disagrees with the airspeed's rate, a sentence for the adequacy failures and the failing windows as
    unexplained places ({channel, phase, t_start, t_end}); ``([], [])`` when it agrees or is not checked."""
    check = accelerometer_kinematics(test)
    if check is None or not check.fails:
        return [], []
    a, b, m, s, _ = check.worst
    failures = [f"the accelerometer disagrees with the airspeed's rate, which no term changes: {m:+.3f} g "
                f"(1-sigma {s:.3f} g) over {a:.1f}–{b:.1f} s, χ² {check.p_text}"]
    return failures, [{"channel": "accelerometer", "phase": "against the airspeed's rate", "t_start": t0,
                       "t_end": t1} for t0, t1, _ in check.failing_windows()]


def structured_phases(checks):
    """The channel × phase rows (phase other than ``all``) whose residuals fail the Ljung–Box threshold of
    :func:`adequacy`, with the time span of the phase: [{channel, phase, t_start, t_end}]."""
    table = checks.residuals.table
    rows = table[table["ljung_box_p"].notna()]
    if not len(rows):
        return []
    limit = FAMILY_ALPHA / len(rows)
    out = []
    time = np.asarray(checks.residuals.time, float)
    for r in rows[(rows["ljung_box_p"] < limit) & (rows["phase"] != "all")].sort_values("ljung_box_p").to_dict("records"):
        labels = np.asarray(checks.residuals.phases[r["channel"]])
        t = time[labels == r["phase"]]
        if t.size:
            out.append({"channel": r["channel"], "phase": r["phase"], "t_start": float(t.min()),
                        "t_end": float(t.max())})
    return out


def unexplained_share(total, remaining):
    """Share of the discrepancy's gain over the baseline that the named terms explained, in [0, 1]."""
    if total <= 0:
        return 1.0
    return float(np.clip(1.0 - remaining / total, 0.0, 1.0))

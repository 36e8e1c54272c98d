"""The diagnosis' decision rule: compare the candidates by PSIS-LOO and name the cause.

The candidates are compared by PSIS-LOO per time bin (step 3 of the
procedure in :mod:`cpas_bayes.inference.diagnose`); the elpd difference of
two models and its standard error come from their paired pointwise elpd
values, se = √(N·Var(Δelpd_i)) (:func:`paired_difference`).

The rule (:func:`name_cause`)
-----------------------------
The physical candidate with the largest elpd gain over the baseline is named
when

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
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pandas as pd

from cpas_bayes.inference.candidate_fits import BASELINE, CandidateFit, DiagnoseOptions, extension_parameters
from cpas_bayes.stats.model_terms import EXTENSIONS, PHYSICAL


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

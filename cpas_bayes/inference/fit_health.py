"""Fit health said plainly: the warnings a fit carries in ``summary.json``, the CLI and its figures.

A fit can "converge" and still be wrong in ways an analyst must see before
using it. Each warning is ``{"code", "message", "parameter"?}``; a clean fit
has none. The checks and their thresholds:

``prior_bound``
    A posterior piled against a bound of its prior (not a physical limit such
    as C_k = 1): the data are informative (posterior sd < ½ prior sd) and more
    than 5 % of the draws lie within ¼ posterior sd of the bound. A normal
    posterior whose centre sits 2 sd inside a bound puts 1.7 % there, one cut
    by the bound 12 % or more: the bound, not the data, decides the value.
``stated_value``
    A stage start or the vehicle's weight or drag area that the data place more than 4 stated sigmas
    from the bundle's value, with a posterior sd under ½ the stated sigma (the data, not the bundle,
    decide it): a start on another clock or a typo, which the fit then corrects without saying so. The
    bundle's values are the truth plus their stated 1-sigma noise, so a correct bundle puts one of a
    fit's 4–11 such parameters there with probability under 0.4 % (under 0.07 % where the data fix the
    value far more closely than its sigma, as they fix the starts). A start must also be more than half
    its stage's fill time (t_fp) away: a canopy that opens by another law than the stage law's moves
    the fitted start by a fraction of its fill (an independent simulator's 16 m canopy: 0.41 s before
    the stated line stretch, 4.1 stated sigmas but 0.2 of its 2.1 s fill), a clock or a typo by more.
``error_multiplier``
    A fitted noise multiplier (posterior median) above 2: the residuals are
    more than twice the stated 1-sigma, so either the sigmas or the model are
    wrong, and every interval of the fit is too narrow or too wide with them.
``ppc``
    More than two posterior-predictive statistics with p < 0.005 or p > 0.995
    (the diagnosis' adequacy rule: three or more land there in 0.4–2 % of
    clean tests, while a single one at p = 0 occurs in clean Mains, where a
    threshold-crossing statistic such as a fill time has a narrow, discrete
    replicated range), or one observed statistic more than 5 replicated sd
    (from the 5–95 % range) from the replicated mean. Needs the fit's checks.
``after_data_end``
    A stage's predicted peak (start + t_fp) or the end of its decay
    (+ t_k), posterior median, after the last data sample: the data cannot
    see it, so its fill parameters are the prior's guess.
``convergence``
    R-hat above 1.01 or bulk ESS below 400 for some parameter (an ensemble
    stopped at its step limit is not itself a warning: R-hat and ESS say
    whether its draws suffice).
``sample_rate``
    A stage whose time to peak (t_fp, posterior median) spans fewer than
    MIN_SAMPLES_PER_FILL samples of the record: a slow logger's samples may
    straddle the peak, so the measured peak reads low and the fit's C_k and
    n_p with it (a 20 Hz accelerometer on a 0.3 s fill gives 6 samples).
``clipped_accelerometer``, ``dead_load_cell``, ``flyout_angle``, ``load_before_first_stage``,
``air_data_units``, ``drag_coefficient``, ``accelerometer_kinematics``
    What the readings themselves show (:mod:`cpas_bayes.data.bundle_notes`, which argues each threshold; also
    said by ``validate`` and ``reduce``), listed first: a unit off or a dead channel explains the rest.
"""

from __future__ import annotations

import numpy as np

from cpas_bayes.data.bundle_notes import reading_notes
from cpas_bayes.physics.inflation import stage_tag

EDGE_SHARE = 0.05          # share of draws within EDGE_BAND posterior sd of a bound that counts as piled
EDGE_BAND = 0.25
INFORMATIVE = 0.5          # posterior sd below this share of the prior sd: the data decide
MAX_MULTIPLIER = 2.0
PPC_FLAG = 0.005           # more than PPC_MAX_FLAGS statistics beyond this (two-sided) is a warning
PPC_MAX_FLAGS = 2
PPC_MAX_Z = 5.0            # ... or one statistic this many replicated sd from the replicated mean
_SD_PER_90 = 3.29          # width of a normal's 5-95 % range in sd
RHAT_MAX = 1.01
ESS_MIN = 400
# Bounds that are physics, not a prior's choice: a posterior against them is a finding about the
# canopy (no over-inflation), not a prior that cut the data off.
PHYSICAL_LIMITS = {"ck": (1.0, None), "eps": (0.0, 1.0)}
FROM_BUNDLE = ("vehicle_weight", "vehicle_cds")   # priors built from the bundle's stated values and sigmas
MIN_SAMPLES_PER_FILL = 8
STATED_CONFLICT = 4.0      # stated sigmas between the bundle's value and the posterior median ...
START_FILL_SHARE = 0.5     # ... and, for a stage start, this share of the stage's fill time t_fp
MULTIPLIERS = {"noise_acc": "accelerometer", "noise_lc": "load-cell", "noise_gnss": "GNSS receiver"}


def warning(code, message, parameter=None):
    out = {"code": code, "message": message}
    if parameter is not None:
        out["parameter"] = parameter
    return out


def _prior_sd(prior):
    u = np.linspace(0.0005, 0.9995, 2000)
    return float(np.std(prior.ppf(u)))


def prior_bound_warnings(model, draws):
    """``prior_bound`` warnings: posteriors piled against a (non-physical) bound of their prior."""
    out = []
    for p in model.parameters:
        x = np.asarray(draws.get(p.name, ()), float).ravel()
        if x.size < 10:
            continue
        sd = float(x.std())
        if not np.isfinite(sd) or sd <= 0 or not sd < INFORMATIVE * _prior_sd(p.prior):
            continue
        physical = PHYSICAL_LIMITS.get(p.name.rsplit(".", 1)[-1], (None, None))
        for side, bound in zip(("lower", "upper"), p.prior.support):
            if not np.isfinite(bound) or (physical[side == "upper"] is not None
                                          and np.isclose(bound, physical[side == "upper"])):
                continue
            share = float(np.mean(np.abs(x - bound) < EDGE_BAND * sd))
            if share > EDGE_SHARE:
                fix = ("check the stated value and sigma behind it in the bundle's test.toml"
                       if p.name in FROM_BUNDLE or p.name.endswith(".start") else
                       f"widen the bound in a priors file (--priors) if {bound:g} is not a physical limit")
                unit = f" {p.unit}" if getattr(p, "unit", "") else ""
                out.append(warning(
                    "prior_bound",
                    f"{p.name} is piled against its prior's {side} bound {bound:g}{unit}{_as_coefficient(model, p.name, bound)}"
                    f" (median {np.median(x):.4g}{unit}, {100 * share:.0f} % of draws within {EDGE_BAND:g} sd of "
                    f"it): the prior, not the data, sets it; {fix}", p.name))
    return out


def stated_value_warnings(model, draws):
    """``stated_value`` warnings: a stage start or a vehicle value that the data place far from the bundle's."""
    out = []
    labels = {f"{q.id}.{stage_tag(k)}": st.label
              for q in getattr(model, "parachutes", ()) for k, st in enumerate(q.stages)}
    for p in model.parameters:
        is_start = p.name.endswith(".start")
        x = np.asarray(draws.get(p.name, ()), float).ravel()
        if not (is_start or p.name in FROM_BUNDLE) or x.size < 10:
            continue
        stated, stated_sd = float(p.prior.ppf(0.5)), _prior_sd(p.prior)
        median, sd = float(np.median(x)), float(x.std())
        z = (median - stated) / stated_sd
        if not (abs(z) > STATED_CONFLICT and sd < INFORMATIVE * stated_sd):
            continue
        t_fp = draws.get(p.name[:-len("start")] + "t_fp") if is_start else None
        if t_fp is not None and abs(median - stated) <= START_FILL_SHARE * float(np.median(t_fp)):
            continue   # within the fill: the opening's own shape, not the bundle, may place it there
        q05, q95 = np.quantile(x, (0.05, 0.95))
        unit = f" {p.unit}" if getattr(p, "unit", "") else ""
        if is_start:
            chute, tag = p.name.split(".")[:2]
            label = labels.get(f"{chute}.{tag}")
            what = f"{chute} stage {tag[1:]}{f' ({label})' if label else ''} starts"
            side = "after" if z > 0 else "before"
        else:
            what, side = f"{p.name} is", "above" if z > 0 else "below"
        out.append(warning(
            "stated_value",
            f"{what} at {median:.4g}{unit} by the data (90 %: {q05:.4g} to {q95:.4g}), {abs(z):.1f} stated sigmas "
            f"{side} the bundle's {stated:.4g} ± {stated_sd:.2g}{unit}: correct the value or its sigma in the "
            "bundle's test.toml (a time on another clock, a typo)", p.name))
    return out


def _as_coefficient(model, name, bound):
    """For a drag-area parameter, the bound as the prior file writes it: C_D on the nominal area."""
    if not name.endswith(".cds_o") or not hasattr(model, "chute_prefix"):
        return ""
    prefix = name[:-len(".cds_o")]
    areas = [a for a, q in zip(model.area_o, model.chute_prefix) if q == prefix]
    return f", i.e. cd_o = {bound / areas[0]:.3g} on S_o = {areas[0]:.4g} m²" if areas else ""


def multiplier_warnings(draws):
    out = []
    for name, channel in MULTIPLIERS.items():
        if name in draws:
            m = float(np.median(draws[name]))
            if m > MAX_MULTIPLIER:
                out.append(warning(
                    "error_multiplier",
                    f"the {channel} residuals are {m:.1f}x the stated 1-sigma ({name} > {MAX_MULTIPLIER:g}): the "
                    "stated sigmas are too small or the model misses something (run 'cpas-bayes diagnose'; a misfit it "
                    "leaves unexplained pulls the other terms less in a fit '--with discrepancy')", name))
    return out


def ppc_warnings(ppc_table):
    """``ppc`` warnings from the table of :func:`cpas_bayes.inference.predictive_checks.ppc_statistics`."""
    p = np.asarray(ppc_table["p_value"], float)
    two_sided = np.minimum(p, 1.0 - p)
    ok = np.isfinite(two_sided)
    flagged = ok & (two_sided < PPC_FLAG)
    z = np.zeros(len(p))
    if {"observed", "replicated_mean", "replicated_q05", "replicated_q95"} <= set(ppc_table.columns):
        sd = (np.asarray(ppc_table["replicated_q95"], float) - np.asarray(ppc_table["replicated_q05"], float))
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.abs(np.asarray(ppc_table["observed"], float) - np.asarray(ppc_table["replicated_mean"], float)) \
                / (sd / _SD_PER_90)
        z = np.where(np.isfinite(z), z, 0.0)
    far = flagged & (z > PPC_MAX_Z)
    if not far.any() and flagged.sum() <= PPC_MAX_FLAGS:
        return []
    rows = ppc_table[flagged]
    names = ", ".join(f"{r['statistic']} of {r['parachute']} stage {r['stage']} (p = {r['p_value']:.3f})"
                      for r in rows.head(4).to_dict("records"))
    more = f" and {len(rows) - 4} more" if len(rows) > 4 else ""
    return [warning("ppc", f"replicated data do not look like the measured data: {names}{more}; see ppc.png")]


def timing_warnings(model, draws, data_end):
    """``after_data_end`` warnings: a stage whose peak or decay end falls after the last sample."""
    out = []
    for p in model.parachutes:
        for k in range(len(p.stages)):
            pre = f"{p.id}.{stage_tag(k)}"
            start, t_fp = draws.get(f"{pre}.start"), draws.get(f"{pre}.t_fp")
            if start is None or t_fp is None:
                continue
            peak = float(np.median(np.asarray(start) + np.asarray(t_fp)))
            tk = draws.get(f"{pre}.tk")
            end = peak + (float(np.median(tk)) if tk is not None else 0.0)
            if peak > data_end:
                out.append(warning("after_data_end",
                                   f"{p.id} stage {k + 1}'s predicted peak at {peak:.2f} s is after the data end "
                                   f"({data_end:.2f} s): its fill parameters are the prior's guess", f"{pre}.n_p"))
            elif end > data_end and tk is not None:
                out.append(warning("after_data_end",
                                   f"{p.id} stage {k + 1}'s decay ends at {end:.2f} s, after the data end "
                                   f"({data_end:.2f} s): t_k is not measured", f"{pre}.tk"))
    return out


def sample_rate_warnings(model, draws, sample_interval):
    """``sample_rate`` warnings: fills spanning fewer than MIN_SAMPLES_PER_FILL samples."""
    out = []
    for p in model.parachutes:
        for k in range(len(p.stages)):
            t_fp = draws.get(f"{p.id}.{stage_tag(k)}.t_fp")
            if t_fp is None:
                continue
            fill = float(np.median(t_fp))
            samples = fill / sample_interval
            if 0 < samples < MIN_SAMPLES_PER_FILL:
                if getattr(model, "averages_readings", False):
                    effect = ("the model averages over each reading's interval, so the peak is not read low, "
                              "but the fill's shape (n_p, expopen, C_k) rests on those few readings")
                else:
                    effect = "the samples may straddle the peak, so C_k and n_p may read low"
                out.append(warning(
                    "sample_rate",
                    f"{p.id} stage {k + 1} reaches its peak in {fill:.3f} s, {samples:.1f} samples at "
                    f"{1 / sample_interval:.0f} Hz: {effect}; log faster or treat this stage's peak with care",
                    f"{p.id}.{stage_tag(k)}.n_p"))
    return out


def convergence_warnings(diagnostics):
    out = []
    per = diagnostics.get("per_parameter", {})
    bad_rhat = [n for n, v in per.items() if v["rhat"] > RHAT_MAX]
    low_ess = [n for n, v in per.items() if v["ess_bulk"] < ESS_MIN]
    if bad_rhat:
        out.append(warning("convergence", f"R-hat above {RHAT_MAX} for {', '.join(bad_rhat[:4])}"
                           + (f" and {len(bad_rhat) - 4} more" if len(bad_rhat) > 4 else "")
                           + ": the ensembles disagree; rerun with more steps", bad_rhat[0]))
    if low_ess:
        out.append(warning("convergence", f"bulk ESS below {ESS_MIN} for {', '.join(low_ess[:4])}"
                           + (f" and {len(low_ess) - 4} more" if len(low_ess) > 4 else "")
                           + ": too few independent draws for its intervals", low_ess[0]))
    return out   # an ensemble at its step limit with R-hat and ESS on target has what its intervals need


def reading_health_warnings(test):
    """What the bundle's readings themselves show (:func:`cpas_bayes.data.bundle_notes.reading_notes`, also said
    by ``validate`` and ``reduce``), a column the note names as the warning's parameter."""
    return [warning(code, text, column) for code, column, text in reading_notes(test)]


def fit_warnings(model, tree, diagnostics, ppc_table=None):
    """Every health warning of a fit: ``model`` (TestModel), its DataTree and convergence diagnostics
    (:func:`cpas_bayes.inference.fit_folder.convergence`, with ``per_parameter``); PPC warnings only
    when the table of posterior-predictive statistics is given."""
    post = tree["posterior"]
    draws = {name: np.asarray(post[name].values, float).ravel() for name in post.data_vars}
    out = reading_health_warnings(model.test)   # the readings' own problems first: they explain the rest
    out += prior_bound_warnings(model, draws)
    out += stated_value_warnings(model, draws)
    out += multiplier_warnings(draws)
    if ppc_table is not None:
        out += ppc_warnings(ppc_table)
    native = np.asarray(model.obs.native_time, float)
    out += timing_warnings(model, draws, float(native[-1]))
    out += sample_rate_warnings(model, draws, float(np.median(np.diff(native))))
    out += convergence_warnings(diagnostics)
    return out

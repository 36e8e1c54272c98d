"""Posterior predictive checks of a fitted test: physical statistics and LOO-PIT.

:func:`run_checks` gathers them with the residual diagnostics
(:mod:`cpas_bayes.inference.residuals`) and :func:`check_report` serialises
all three. Everything is computed from ``fit.model`` and the posterior draws,
replicated data sets included (:mod:`cpas_bayes.inference.check_draws`, which
states their error structure). Values are SI.

Physical series the statistics are taken on (seed Eq. 6, 10, 11)
-----------------------------------------------------------------
* parachute i (load cell): the raw drag area lc_i (Eq. 11 before friction
  scaling) is scaled with one fixed factor s̄ (posterior median of
  ``load_scale``), the same for observed and replicated data::

      CDS_i = s̄·(lc_i − w_i) + w_i,      w_i = W_p,i·G/q̄
      F_i   = q̄·CDS_i − W_p,i·G = s̄·(q̄·lc_i − W_p,i·G)          (Eq. 10–11)

* total (accelerometer): the drag area is the channel itself (Eq. 8 with the
  stated weights) and the load its Eq. 6 form::

      CDS_total = acc,      F_total = q̄·acc − Σ W_p,i·G = W_V·G − q̄·CDS_V

q̄ and G are the smoothed native series interpolated at the bin times.

Statistics T, per parachute (and total) and stage
-------------------------------------------------
A stage interval is [t0, t1): t0 the posterior-median start of the stage, t1
that of the next stage (the end of the data for the last). For the total, t0
and t1 are the earliest such starts among the parachutes. Peaks are taken on
a light smoothing, a quadratic Savitzky–Golay filter over
:data:`PEAK_SMOOTHING_BINS` bins (0.1 s in the 0.02 s bins of an
infinite-mass transient), applied identically to observed and replicated
series; the filter keeps a sharp peak's height and removes most noise.

* ``peak_drag_area``: max of the smoothed drag area in the interval.
* ``time_to_peak``: time of that maximum minus t0, refined between bins by the
  vertex of the parabola through the maximum bin and its neighbours.
* ``stage_mean_drag_area``: mean of the (unsmoothed) drag area over the
  steady part of the interval, [t0 + t_s, t1) with
  t_s = min(max(t_settle, ½·(t1 − t0)), ¾·(t1 − t0)) and t_settle the
  posterior median of t_fp + t_k (the end of the modelled transient).
* ``fill_time``: first time in the interval the smoothed drag area reaches
  95 % of the growth from the level held before the stage to its stage
  mean, minus t0::

      threshold = CDS_before + 0.95·(stage mean − CDS_before)

  with CDS_before the mean smoothed drag area over [t0 − 0.25 s, t0) (0 when
  there is no bin); the crossing is interpolated linearly between bins.
  Undefined (NaN) when there is no growth or the threshold is never reached.
* ``peak_load``: max of the smoothed load series in the interval.

Bayesian p-value: p = P(T(y_rep) ≥ T(y)) over the replicated sets, ties
counted half, NaN replicates dropped.
p near 0 means the data show more of T than the model does, near 1 less.

LOO-PIT
-------
PIT_i = P(ỹ_i ≤ y_i | y_−i) by Pareto-smoothed importance sampling
(``arviz.loo_pit``), per channel. Uniform under a calibrated model;
summarised by the Kolmogorov–Smirnov distance D = sup_u |ECDF(u) − u| with
its p-value and the mean and sd of the PIT values (uniform: ½ and
1/√12 ≈ 0.289; a smaller sd means the predictive is too wide, a larger one
too narrow). Neighbouring bins of a dense time series are correlated, so the
KS p-value (which assumes independent values) is optimistic: read D against
the simultaneous 95 % band ε = √(ln(2/0.05)/(2n)) (DKW inequality) as a
guide, not a test.

PSIS-LOO uses the joint log-likelihood of all channels of a bin (``total``);
LOO-PIT needs one per channel and uses each channel's marginal density.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats
from scipy.signal import savgol_filter

from cpas_bayes.core.files import jsonable
from cpas_bayes.inference.check_draws import (ACC_CHANNEL, as_rng, check_tree, posterior_matrix, posterior_median,
                                              predict_draws, replicate_data)
from cpas_bayes.inference.loo import loo_pit as psis_loo_pit
from cpas_bayes.inference.residuals import LJUNG_BOX_LAGS, PARETO_K_LIMIT, ResidualReport, residuals

PEAK_SMOOTHING_BINS = 5          # quadratic Savitzky–Golay window, bins
FILL_FRACTION = 0.95             # fill time: reach this fraction of the growth to the stage mean
BEFORE_WINDOW = 0.25             # s before a stage start that give the held level
PIT_BAND_ALPHA = 0.05            # DKW band of the LOO-PIT ECDF

STATISTICS = ("peak_drag_area", "time_to_peak", "fill_time", "stage_mean_drag_area", "peak_load")
STATISTIC_UNITS = {"peak_drag_area": "area", "time_to_peak": "time", "fill_time": "time",
                   "stage_mean_drag_area": "area", "peak_load": "force"}
SI_LABELS = {"area": "m²", "time": "s", "force": "N"}

TOTAL = "total"


# ---------------------------------------------------------------------------
# stage geometry from the posterior


@dataclass(frozen=True)
class StageWindow:
    """One stage of one series: interval [t0, t1), steady part from ``t_steady``."""

    series: str          # parachute id or "total"
    stage: int           # 1-based
    label: str
    t0: float
    t1: float
    t_steady: float


def stage_windows(fit):
    """Posterior-median stage windows of each parachute with a load cell and of the total.

    The steady part starts t_s = min(max(t_settle, ½·L), ¾·L) after t0, L = t1 − t0,
    t_settle = median(t_fp) + median(t_k) (t_k = 0 for finite mass).
    """
    model, tree = fit.model, fit.tree
    t_end = float(model.obs.time[-1]) + 1e-9
    starts, settles = {}, {}
    for p in model.parachutes:
        starts[p.id] = [posterior_median(tree, f"{p.id}.s{k + 1}.start") for k in range(len(p.stages))]
        settles[p.id] = [posterior_median(tree, f"{p.id}.s{k + 1}.t_fp", 0.0)
                         + posterior_median(tree, f"{p.id}.s{k + 1}.tk", 0.0) for k in range(len(p.stages))]

    def window(series, k, label, t0, t1, settle):
        length = t1 - t0
        t_s = min(max(settle, 0.5 * length), 0.75 * length)
        return StageWindow(series, k + 1, label, t0, t1, t0 + t_s)

    out = []
    lc_chutes = {int(i) for i in model.obs.lc_index}
    for i, p in enumerate(model.parachutes):
        if i not in lc_chutes:
            continue
        s = starts[p.id] + [t_end]
        for k, st in enumerate(p.stages):
            out.append(window(p.id, k, st.label, s[k], s[k + 1], settles[p.id][k]))
    for k in range(model.n_stages):
        having = [p for p in model.parachutes if len(p.stages) > k]
        t0 = min(starts[p.id][k] for p in having)
        nxt = [starts[p.id][k + 1] for p in model.parachutes if len(p.stages) > k + 1]
        t1 = min(nxt) if nxt else t_end
        settle = max(starts[p.id][k] + settles[p.id][k] for p in having) - t0
        out.append(window(TOTAL, k, having[0].stages[k].label, t0, t1, settle))
    return out


# ---------------------------------------------------------------------------
# physical series


def smooth_for_peaks(values):
    """The peak smoothing: quadratic Savitzky–Golay over PEAK_SMOOTHING_BINS bins along the last axis."""
    values = np.asarray(values, float)
    if values.shape[-1] < PEAK_SMOOTHING_BINS:
        return values.copy()
    return savgol_filter(values, PEAK_SMOOTHING_BINS, 2, axis=-1, mode="interp")


def physical_series(model, acc, lc, load_scale):
    """Drag areas and loads of each series from channel arrays (rows of data sets).

    ``acc`` (M, N), ``lc`` (M, L, N); returns {series: (drag area (M, N), load (M, N))}
    with the formulas of the module docstring (fixed scale ``load_scale``).
    """
    obs = model.obs
    qbar = obs.qbar_at(obs.time)
    g = obs.g_at(obs.time)
    out = {}
    for row, chute in enumerate(obs.lc_index):
        p = model.parachutes[int(chute)]
        w = p.weight * g / qbar
        raw = lc[:, row, :]
        out[p.id] = (load_scale * (raw - w) + w, load_scale * (qbar * raw - p.weight * g))
    out[TOTAL] = (acc, qbar * acc - model.chute_weight.sum() * g)
    return out


def _masked_max(values, mask):
    """Max and argmax (index into the full axis) of each row over the columns in ``mask``."""
    idx = np.flatnonzero(mask)
    sub = values[:, idx]
    j = np.argmax(sub, axis=1)
    return sub[np.arange(sub.shape[0]), j], idx[j]


def _vertex_time(time, values, at, mask):
    """Time of the maximum refined by the parabola through the bins at−1, at, at+1 (rows of ``values``).

    Vertex of the parabola through (t_a, y_a), (t_b, y_b), (t_c, y_c)::

        t* = t_b − ½·[(t_b − t_a)²·(y_b − y_c) − (t_b − t_c)²·(y_b − y_a)]
                   / [(t_b − t_a)·(y_b − y_c) − (t_b − t_c)·(y_b − y_a)]

    kept within [t_a, t_c]; the bin time itself where a neighbour is outside the mask.
    """
    n = time.size
    rows = np.arange(values.shape[0])
    a, c = np.clip(at - 1, 0, n - 1), np.clip(at + 1, 0, n - 1)
    inside = (at > 0) & (at < n - 1) & mask[a] & mask[c]
    ta, tb, tc = time[a], time[at], time[c]
    ya, yb, yc = values[rows, a], values[rows, at], values[rows, c]
    num = (tb - ta) ** 2 * (yb - yc) - (tb - tc) ** 2 * (yb - ya)
    den = (tb - ta) * (yb - yc) - (tb - tc) * (yb - ya)
    ok = inside & (np.abs(den) > 0)
    vertex = tb - 0.5 * num / np.where(ok, den, 1.0)
    return np.where(ok, np.clip(vertex, ta, tc), tb)


def _first_crossing(time, values, threshold, mask):
    """First time each row of ``values`` reaches ``threshold`` inside ``mask``, linear between bins.

    NaN where it never does. The crossing between bins j−1 and j (both in the mask) is
    t = t_{j−1} + (thr − y_{j−1})/(y_j − y_{j−1})·(t_j − t_{j−1}); the bin time if j is the
    first bin of the mask.
    """
    idx = np.flatnonzero(mask)
    sub = values[:, idx]
    reached = sub >= threshold[:, None]
    first = np.argmax(reached, axis=1)
    rows = np.arange(values.shape[0])
    j = idx[first]
    prev = np.maximum(first - 1, 0)
    has_prev = first > 0
    y0, y1 = sub[rows, prev], sub[rows, first]
    t0, t1 = time[idx[prev]], time[j]
    frac = np.where(has_prev & (y1 > y0), (threshold - y0) / np.where(y1 > y0, y1 - y0, 1.0), 1.0)
    t = np.where(has_prev, t0 + np.clip(frac, 0.0, 1.0) * (t1 - t0), t1)
    return np.where(reached.any(axis=1), t, np.nan)


def stage_statistics(time, cds, load, window):
    """The five statistics of one stage window for every row of ``cds``/``load`` (M, N).

    Returns {statistic: (M,)}; definitions in the module docstring. Times are
    refined between bins (parabolic vertex for the peak, linear crossing for the
    fill), so they are not tied to the 0.02–0.1 s bin grid.
    """
    in_stage = (time >= window.t0) & (time < window.t1)
    if not in_stage.any():
        nan = np.full(cds.shape[0], np.nan)
        return {name: nan for name in STATISTICS}
    smooth_cds = smooth_for_peaks(cds)
    smooth_load = smooth_for_peaks(load)
    peak, at = _masked_max(smooth_cds, in_stage)
    peak_load, _ = _masked_max(smooth_load, in_stage)
    t_peak = _vertex_time(time, smooth_cds, at, in_stage)

    steady = in_stage & (time >= window.t_steady)
    stage_mean = cds[:, steady].mean(axis=1)

    before = (time >= window.t0 - BEFORE_WINDOW) & (time < window.t0)
    held = smooth_cds[:, before].mean(axis=1) if before.any() else np.zeros(cds.shape[0])
    growth = stage_mean - held
    threshold = held + FILL_FRACTION * growth
    fill = np.where(growth > 0, _first_crossing(time, smooth_cds, threshold, in_stage) - window.t0, np.nan)
    return {"peak_drag_area": peak, "time_to_peak": t_peak - window.t0, "fill_time": fill,
            "stage_mean_drag_area": stage_mean, "peak_load": peak_load}


def bayesian_p_value(replicated, observed):
    """P(T_rep ≥ T_obs) with ties counted half; NaN replicates dropped (NaN if none or T_obs NaN)."""
    rep = np.asarray(replicated, float)
    rep = rep[np.isfinite(rep)]
    if rep.size == 0 or not np.isfinite(observed):
        return float("nan")
    return float(np.mean(rep > observed) + 0.5 * np.mean(rep == observed))


# ---------------------------------------------------------------------------
# posterior predictive statistics


@dataclass
class PPCResult:
    """Table of the statistics and, row by row, the replicated values behind it."""

    table: pd.DataFrame
    replicated: np.ndarray        # (rows, S), aligned with ``table``
    windows: list


def ppc_check(fit, n_draws=200, rng=None) -> PPCResult:
    """Posterior predictive statistics with the replicated values (see :func:`ppc_statistics`)."""
    rng = as_rng(rng)
    model, tree = fit.model, fit.tree
    draws = posterior_matrix(tree, model.names).reshape(-1, model.ndim)
    pick = rng.choice(draws.shape[0], size=min(n_draws, draws.shape[0]), replace=False)
    pred = predict_draws(model, draws[pick])
    acc_rep, lc_rep = replicate_data(model, pred, rng)
    obs = model.obs
    # Row 0 is the observed data set, rows 1.. the replicated ones.
    acc = np.concatenate([obs.acc[None], acc_rep], axis=0)
    lc = np.concatenate([obs.lc[None], lc_rep], axis=0)
    load_scale = posterior_median(tree, "load_scale", 1.0)
    series = physical_series(model, acc, lc, load_scale)
    windows = stage_windows(fit)
    rows, replicated = [], []
    for w in windows:
        cds, load = series[w.series]
        values = stage_statistics(obs.time, cds, load, w)
        for name in STATISTICS:
            v = values[name]
            rep = v[1:]
            finite = rep[np.isfinite(rep)]
            q05, q95 = np.quantile(finite, (0.05, 0.95)) if finite.size else (np.nan, np.nan)
            rows.append({"parachute": w.series, "stage": w.stage, "stage_label": w.label, "statistic": name,
                         "unit": SI_LABELS[STATISTIC_UNITS[name]], "observed": float(v[0]),
                         "replicated_mean": float(finite.mean()) if finite.size else np.nan,
                         "replicated_q05": float(q05), "replicated_q95": float(q95),
                         "n_replicated": int(finite.size), "p_value": bayesian_p_value(rep, v[0])})
            replicated.append(rep)
    table = pd.DataFrame(rows)
    return PPCResult(table=table, replicated=np.array(replicated), windows=windows)


def ppc_statistics(fit, n_draws=200, rng=None) -> pd.DataFrame:
    """Posterior predictive check of the physical statistics, one row per series × stage × statistic.

    Columns: parachute (id or "total"), stage (1-based), stage_label, statistic, unit (SI),
    observed, replicated_mean, replicated_q05, replicated_q95, n_replicated, p_value
    (P(T_rep ≥ T_obs), ties half). ``n_draws`` posterior draws, each with one noise
    realisation; definitions in the module docstring.
    """
    return ppc_check(fit, n_draws, rng).table


# ---------------------------------------------------------------------------
# LOO-PIT


def ks_uniform(values):
    """KS distance of values in [0, 1] from the uniform, its p-value, and the DKW 95 % band half-width."""
    u = np.sort(np.asarray(values, float).ravel())
    n = u.size
    res = stats.kstest(u, "uniform")
    band = math.sqrt(math.log(2.0 / PIT_BAND_ALPHA) / (2.0 * n))
    return float(res.statistic), float(res.pvalue), band


@dataclass
class LooPitResult:
    """LOO-PIT values per channel (each (N,)) and their uniformity summary table."""

    values: dict
    table: pd.DataFrame
    time: np.ndarray
    not_computed: str = ""   # why there are no values (a likelihood with no per-channel density), or ""


_PIT_COLUMNS = ("channel", "n", "ks_distance", "ks_p_value", "dkw_band", "pit_mean", "pit_sd", "frac_outside_90")


def loo_pit(fit, tree=None) -> LooPitResult:
    """LOO-PIT per channel (``accelerometer``, ``load cell <id>``) by ``arviz.loo_pit`` (weights from :mod:`.loo`).

    Table columns: channel, n, ks_distance, ks_p_value (optimistic: correlated
    bins), dkw_band (95 % simultaneous half-width), pit_mean, pit_sd,
    frac_outside_90 (share of PIT values outside [0.05, 0.95], 0.10 if calibrated).
    """
    tree = check_tree(fit) if tree is None else tree
    if "acc" not in tree["log_likelihood"]:   # a term whose errors join the channels (the discrepancy, AR(1))
        return LooPitResult(values={}, table=pd.DataFrame(columns=list(_PIT_COLUMNS)),
                            time=np.asarray(fit.model.obs.time),
                            not_computed=f"not computed: the likelihood of {fit.model.name} joins the channels of "
                                         "each time bin, so no channel has a density of its own to take a PIT "
                                         "from; the PPC and the residuals stand")
    pit = psis_loo_pit(tree, [c for c in ("acc", "lc") if c in tree["observed_data"]])
    # The PSIS-weighted sums can overshoot [0, 1] by round-off; a PIT is a probability.
    values = {ACC_CHANNEL: np.clip(np.asarray(pit["acc"].values, float), 0.0, 1.0)}
    if "lc" in pit:
        lc = np.clip(np.asarray(pit["lc"].values, float), 0.0, 1.0)
        for row, cid in enumerate(pit["lc"]["load_cell"].values):
            values[f"load cell {cid}"] = lc[row]
    rows = []
    for channel, u in values.items():
        d, p, band = ks_uniform(u)
        rows.append({"channel": channel, "n": int(u.size), "ks_distance": d, "ks_p_value": p, "dkw_band": band,
                     "pit_mean": float(u.mean()), "pit_sd": float(u.std(ddof=1)),
                     "frac_outside_90": float(np.mean((u < 0.05) | (u > 0.95)))})
    return LooPitResult(values=values, table=pd.DataFrame(rows), time=np.asarray(fit.model.obs.time))


# ---------------------------------------------------------------------------
# report


@dataclass
class FitChecks:
    """All checks of one fit (what :func:`run_checks` computes, :func:`check_report` serialises)."""

    ppc: PPCResult
    loo_pit: LooPitResult
    residuals: ResidualReport


def run_checks(fit, n_draws=200, rng=None) -> FitChecks:
    """PPC statistics, LOO-PIT and residuals sharing one :func:`check_tree`."""
    rng = as_rng(rng if rng is not None else 0)
    tree = check_tree(fit, rng=rng)
    return FitChecks(ppc=ppc_check(fit, n_draws, rng), loo_pit=loo_pit(fit, tree), residuals=residuals(fit, tree))


def check_report(fit, n_draws=200, rng=None, checks=None) -> dict:
    """The checks as a JSON-serialisable dict (SI; NaN written as null).

    Keys: ``ppc`` (rows of :func:`ppc_statistics`), ``ppc_flags`` (rows with
    p < 0.01 or p > 0.99), ``loo_pit`` (uniformity per channel), ``residuals``
    (channel × phase rows), ``pareto_k`` (elpd_loo, se, p_loo, count and bins
    above 0.7), ``noise`` (error multipliers), ``definitions``.
    """
    checks = run_checks(fit, n_draws, rng) if checks is None else checks
    ppc = checks.ppc.table
    flags = ppc[(ppc["p_value"] < 0.01) | (ppc["p_value"] > 0.99)]
    res = checks.residuals
    report = {
        "ppc": ppc,
        "ppc_flags": flags,
        "loo_pit": checks.loo_pit.table,
        **({"loo_pit_not_computed": checks.loo_pit.not_computed} if checks.loo_pit.not_computed else {}),
        "residuals": res.table,
        "pareto_k": {**res.elpd_loo, "limit": PARETO_K_LIMIT, "high": res.high_pareto_k},
        "noise": res.noise,
        "definitions": {
            "units": "SI",
            "p_value": "P(T(y_rep) >= T(y)), ties counted half",
            "peak_smoothing": f"quadratic Savitzky-Golay over {PEAK_SMOOTHING_BINS} bins",
            "fill_time": f"first reach of held + {FILL_FRACTION}*(stage mean - held), from the stage start",
            "stage_window": "posterior-median starts; steady part from t0 + min(max(t_fp + t_k, L/2), 3L/4)",
            "load_scale": "posterior median applied to observed and replicated load cells alike",
            "residual": "(y - E[y_hat]) / (mean lambda * sqrt(sigma^2 + u_qbar^2))",
            "ljung_box_lags": f"min({LJUNG_BOX_LAGS}, n // 4)",
        },
    }
    return jsonable(report)

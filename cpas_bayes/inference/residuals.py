"""Residual diagnostics of a fitted test: standardised residuals per channel and flight phase.

Their serial correlation (lag-1 autocorrelation, Ljung–Box), PSIS-LOO's
Pareto k per time bin and the posterior error multipliers. Like every check,
computed from ``fit.model`` and the posterior draws
(:mod:`cpas_bayes.inference.check_draws`). Values are SI.

Residuals
---------
Standardised residual of bin j, channel c at the posterior mean prediction::

    r_j = (y_j − E[ŷ_j]) / (λ̄_c·√(σ_j² + u_j²))

with E[ŷ] the mean of the prediction over the draws, λ̄_c the posterior mean
of the channel's error multiplier and √(σ² + u²) the channel's marginal
1-sigma. Under the model r ~ N(0, 1), independent from bin to bin. Each bin is
put in a flight phase from the posterior medians of start, t_fp and t_k
(:func:`classify_phases`). Per channel × phase: n, mean, sd, lag-1
autocorrelation and the Ljung–Box statistic (:func:`ljung_box`). Lags count
bins (0.02–0.1 s apart); pairs (j, j + k) count only when both bins are in
the phase.

PSIS-LOO uses the joint log-likelihood of all channels of a bin (``total``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from cpas_bayes.core.summaries import quantile_summary
from cpas_bayes.inference.check_draws import ACC_CHANNEL, channel_sigma, check_tree, posterior_median
from cpas_bayes.inference.fit_health import MULTIPLIERS
from cpas_bayes.inference.loo import psis_loo

LJUNG_BOX_LAGS = 10              # Ljung–Box lags (fewer when a phase is short: n // 4)
PARETO_K_LIMIT = 0.7             # PSIS-LOO: importance sampling unreliable above this

PHASES = ("pre_deploy", "fill", "overinflation", "steady", "full_open")
# A bin of a cluster channel takes the most dynamic phase of its parachutes.
_CLUSTER_PRIORITY = {"fill": 4, "overinflation": 3, "steady": 2, "full_open": 1, "pre_deploy": 0}


# ---------------------------------------------------------------------------
# residual phases and serial correlation


def classify_phases(time, starts, t_fp, t_k, infinite=True):
    """Flight phase of each bin for one parachute: array of labels from :data:`PHASES`.

    ``starts``, ``t_fp``, ``t_k`` (K,) per stage in time order. With s_k the
    start of stage k and s_K = ∞:

    * ``pre_deploy``      t < s_1
    * ``fill``            s_k ≤ t < s_k + t_fp,k
    * ``overinflation``   s_k + t_fp,k ≤ t < s_k + t_fp,k + t_k,k   (infinite mass only)
    * ``steady``          later in a reefed stage (k < K)
    * ``full_open``       later in the last stage

    each phase cut at s_{k+1}.
    """
    time = np.asarray(time, float)
    starts = np.asarray(starts, float)
    t_fp = np.asarray(t_fp, float)
    t_k = np.asarray(t_k, float) if infinite else np.zeros_like(starts)
    label = np.full(time.shape, "pre_deploy", dtype=object)
    n_stages = starts.size
    for k in range(n_stages):
        end = starts[k + 1] if k + 1 < n_stages else np.inf
        in_stage = (time >= starts[k]) & (time < end)
        tau = time - starts[k]
        label[in_stage] = "full_open" if k == n_stages - 1 else "steady"
        label[in_stage & (tau < t_fp[k] + t_k[k])] = "overinflation"
        label[in_stage & (tau < t_fp[k])] = "fill"
    return label


def cluster_phases(labels):
    """Phase of a channel that sees several parachutes (rows of ``labels``): the most dynamic one.

    Priority fill > overinflation > steady > full_open > pre_deploy: a bin is
    ``full_open`` only when every parachute is steady full open, ``pre_deploy``
    only before every first start.
    """
    labels = np.atleast_2d(np.asarray(labels, dtype=object))
    rank = np.zeros(labels.shape, dtype=int)
    for name, r in _CLUSTER_PRIORITY.items():
        rank[labels == name] = r
    by_rank = np.empty(len(_CLUSTER_PRIORITY), dtype=object)
    for name, r in _CLUSTER_PRIORITY.items():
        by_rank[r] = name
    return by_rank[rank.max(axis=0)]


def autocorrelation(x, max_lag, mask=None):
    """Sample autocorrelation r_1..r_max_lag of ``x`` restricted to ``mask``.

    r_k = Σ_{j: j, j+k ∈ mask} (x_j − x̄)(x_{j+k} − x̄) / Σ_{j ∈ mask} (x_j − x̄)²,
    x̄ the mean over the mask; for a full mask the usual estimator.
    """
    x = np.asarray(x, float)
    mask = np.ones(x.size, bool) if mask is None else np.asarray(mask, bool)
    n = int(mask.sum())
    out = np.full(max_lag, np.nan)
    if n < 2:
        return out
    d = np.where(mask, x - x[mask].mean(), 0.0)
    denom = np.sum(d**2)
    if denom <= 0:
        return out
    for k in range(1, min(max_lag, x.size - 1) + 1):
        out[k - 1] = np.sum(d[:-k] * d[k:]) / denom  # zero outside the mask: only in-mask pairs count
    return out


def ljung_box(x, lags=LJUNG_BOX_LAGS, mask=None):
    """Ljung–Box portmanteau statistic and p-value for serial correlation.

    Q = n·(n + 2)·Σ_{k=1}^{h} r_k² / (n − k),  p = P(χ²_h ≥ Q)

    with r_k from :func:`autocorrelation`, n the number of values in the mask.
    Returns (Q, p, h); NaNs when h < 1.
    """
    x = np.asarray(x, float)
    n = int(x.size if mask is None else np.asarray(mask, bool).sum())
    h = int(min(lags, n - 1))
    if h < 1:
        return float("nan"), float("nan"), 0
    r = autocorrelation(x, h, mask)
    k = np.arange(1, h + 1)
    q = float(n * (n + 2) * np.sum(r**2 / (n - k)))
    return q, float(stats.chi2.sf(q, h)), h


@dataclass
class ResidualReport:
    """Standardised residuals per channel, their phase table, Pareto-k flags and error multipliers."""

    time: np.ndarray
    residuals: dict          # channel -> (N,)
    phases: dict             # channel -> (N,) phase labels
    table: pd.DataFrame      # channel × phase statistics
    pareto_k: np.ndarray     # (N,) PSIS-LOO Pareto k of the bins (all channels of a bin)
    high_pareto_k: pd.DataFrame
    noise: dict              # error multiplier -> {mean, q05, q95}
    elpd_loo: dict

    def overall(self, channel):
        """The channel's whole-record row of :attr:`table` (phase ``all``)."""
        t = self.table
        return t[(t["channel"] == channel) & (t["phase"] == "all")].iloc[0]


def stage_timing_medians(fit):
    """Posterior medians per parachute: (starts (K,), t_fp (K,), t_k (K,), infinite)."""
    tree = fit.tree
    out = {}
    for p in fit.model.parachutes:
        ks = range(1, len(p.stages) + 1)
        out[p.id] = (np.array([posterior_median(tree, f"{p.id}.s{k}.start") for k in ks]),
                     np.array([posterior_median(tree, f"{p.id}.s{k}.t_fp", 0.0) for k in ks]),
                     np.array([posterior_median(tree, f"{p.id}.s{k}.tk", 0.0) for k in ks]),
                     p.inflation == "infinite")
    return out


def channel_phases(fit):
    """Phase labels per channel: each load cell by its parachute, the accelerometer by the cluster."""
    obs = fit.model.obs
    timing = stage_timing_medians(fit)
    per_chute = {pid: classify_phases(obs.time, *t[:3], infinite=t[3]) for pid, t in timing.items()}
    out = {ACC_CHANNEL: cluster_phases(np.array(list(per_chute.values())))}
    for chute in obs.lc_index:
        pid = fit.model.parachutes[int(chute)].id
        out[f"load cell {pid}"] = per_chute[pid]
    return out


def _phase_rows(channel, r, phase):
    rows = []
    for name in ("all",) + PHASES:
        mask = np.ones(r.size, bool) if name == "all" else (phase == name)
        n = int(mask.sum())
        if n == 0:
            continue
        vals = r[mask]
        acf1 = autocorrelation(r, 1, mask)[0] if n > 2 else np.nan
        q, p, h = ljung_box(r, min(LJUNG_BOX_LAGS, n // 4), mask)
        rows.append({"channel": channel, "phase": name, "n": n, "mean": float(vals.mean()),
                     "sd": float(vals.std(ddof=1)) if n > 1 else np.nan, "acf1": float(acf1),
                     "ljung_box_q": q, "ljung_box_lags": h, "ljung_box_p": p})
    return rows


def residuals(fit, tree=None) -> ResidualReport:
    """Standardised residuals r = (y − E[ŷ])/(λ̄·√(σ² + u²)) per channel, tested per flight phase.

    E[ŷ] is the mean prediction over the check draws (:func:`check_tree`), λ̄ the
    posterior mean error multiplier. The table has, per channel × phase (and
    ``all``): n, mean, sd, acf1 (lag-1 autocorrelation), ljung_box_q/_lags/_p
    (h = min(10, n // 4) lags). ``pareto_k`` is PSIS-LOO's k per time bin from
    ``arviz.loo(tree, var_name="total", pointwise=True)`` (weights from :mod:`.loo`); bins above 0.7 are
    listed in ``high_pareto_k`` with the accelerometer's phase there.
    """
    tree = check_tree(fit) if tree is None else tree
    model, obs = fit.model, fit.model.obs
    post = fit.tree["posterior"]
    lam_acc = float(np.mean(post["noise_acc"].values))
    lam_lc = float(np.mean(post["noise_lc"].values)) if "noise_lc" in post else 1.0
    const = tree["constant_data"]
    acc_mean = np.asarray(const["acc_mean"].values)
    lc_mean = np.asarray(const["lc_mean"].values).reshape(obs.lc.shape)
    sig_acc, sig_lc = channel_sigma(obs)
    res = {ACC_CHANNEL: (obs.acc - acc_mean) / (lam_acc * sig_acc)}
    for row, chute in enumerate(obs.lc_index):
        res[f"load cell {model.parachutes[int(chute)].id}"] = (obs.lc[row] - lc_mean[row]) / (lam_lc * sig_lc[row])
    phases = channel_phases(fit)
    rows = []
    for channel, r in res.items():
        rows.extend(_phase_rows(channel, r, phases[channel]))

    loo = psis_loo(tree, "total")
    k = np.asarray(loo.pareto_k.values, float)
    high = np.flatnonzero(k > PARETO_K_LIMIT)
    high_table = pd.DataFrame({"time": obs.time[high], "pareto_k": k[high],
                               "phase": phases[ACC_CHANNEL][high].astype(str)})
    noise = {name: quantile_summary(post[name].values, (0.05, 0.95), sd=False) for name in MULTIPLIERS
             if name in post}
    elpd = {"elpd_loo": float(loo.elpd), "se": float(loo.se), "p_loo": float(loo.p),
            "n_high_pareto_k": int(high.size), "pareto_k_max": float(np.max(k))}
    return ResidualReport(time=np.asarray(obs.time), residuals=res, phases=phases, table=pd.DataFrame(rows),
                          pareto_k=k, high_pareto_k=high_table, noise=noise, elpd_loo=elpd)

"""Posterior draws for the checks: predictions, replicated data and the check tree.

Everything here is computed from ``fit.model`` (its observations and forward
model) and the posterior draws in ``fit.tree["posterior"]``; nothing is read
from the stored ``observed_data`` / ``posterior_predictive`` groups, so a check
can be rerun on a model whose observations were edited (e.g. with
``dataclasses.replace(model.obs, ...)``). Values are SI.

The posterior predictive checks (:mod:`cpas_bayes.inference.predictive_checks`),
the residual diagnostics (:mod:`cpas_bayes.inference.residuals`) and the
diagnosis share these helpers.

Replicated data
---------------
For a posterior draw θ with prediction ŷ(θ) and error multipliers λ_acc,
λ_lc, a replicated data set has the likelihood's error structure (model step
4): an independent part σ_c per channel and a part u_c from the measured q̄,
shared by all channels of a bin (zero for observations without it)::

    y_rep,c = ŷ_c(θ) + λ_c·(σ_c·z_c + u_c·z_q),     z_c, z_q ~ N(0, 1)
"""

from __future__ import annotations

import math

import numpy as np

CHECK_DRAW_BUDGET = 2000         # posterior draws used for LOO-PIT / PSIS-LOO / residuals

ACC_CHANNEL = "accelerometer"    # name of the accelerometer channel; load cells are "load cell <id>"


# ---------------------------------------------------------------------------
# posterior draws and predictions


def posterior_matrix(tree, names):
    """Posterior draws of ``names`` as (chain, draw, D) from a DataTree's posterior group."""
    post = tree["posterior"]
    return np.stack([np.asarray(post[n].values, float) for n in names], axis=-1)


def posterior_median(tree, name, default=np.nan):
    """Median over all posterior draws of one variable; ``default`` if the tree lacks it."""
    post = tree["posterior"]
    if name not in post:
        return default
    return float(np.median(np.asarray(post[name].values)))


def predict_draws(model, theta, batch=256, log_likelihood=False):
    """Model predictions in batches: {acc (S, N), lc (S, L, N), cds (S, P, N), noise_acc, noise_lc (S,)}.

    With ``log_likelihood`` also the pointwise log-likelihood: ``ll_total`` (S, N), all
    channels of a bin jointly, and, when the model gives them, each channel's marginal
    ``ll_acc`` (S, N) and ``ll_lc`` (S, L, N).
    """
    fields = ("acc", "lc", "cds", "noise_acc", "noise_lc")
    parts = {name: [] for name in fields + ("ll_total", "ll_acc", "ll_lc")}
    split = True
    for i in range(0, theta.shape[0], batch):
        rows = theta[i:i + batch]
        pred = model.predict(rows)
        for name in fields:
            parts[name].append(np.asarray(getattr(pred, name), float))
        if not log_likelihood:
            continue
        parts["ll_total"].append(model.pointwise_log_likelihood(rows, pred))
        if model.replaces_error_model:  # an extension's likelihood (e.g. AR(1)) gives the total per bin only
            split = False
            continue
        ll_acc, ll_lc = model.pointwise_log_likelihood(rows, pred, by_channel=True)
        parts["ll_acc"].append(ll_acc)
        parts["ll_lc"].append(ll_lc)
    out = {name: np.concatenate(parts[name], axis=0) for name in fields}
    if log_likelihood:
        out["ll_total"] = np.concatenate(parts["ll_total"], axis=0)
        if split:
            out["ll_acc"] = np.concatenate(parts["ll_acc"], axis=0)
            out["ll_lc"] = np.concatenate(parts["ll_lc"], axis=0)
    return out


def _shared_qbar_parts(obs):
    """The q̄ part of each channel's 1-sigma shared within a bin: (acc (N,), lc (L, N)); zeros if absent."""
    acc_q = getattr(obs, "acc_qbar", None)
    lc_q = getattr(obs, "lc_qbar", None)
    return (np.zeros_like(obs.acc_sigma) if acc_q is None else np.asarray(acc_q, float),
            np.zeros_like(obs.lc_sigma) if lc_q is None else np.asarray(lc_q, float))


def channel_sigma(obs):
    """Marginal 1-sigma of each channel before the error multiplier: √(σ² + u²), (acc (N,), lc (L, N))."""
    acc_q, lc_q = _shared_qbar_parts(obs)
    return np.hypot(obs.acc_sigma, acc_q), np.hypot(obs.lc_sigma, lc_q)


def replicate_data(model, pred, rng):
    """Posterior-predictive data with the likelihood's error structure.

    y_rep,c = ŷ_c + λ_c·(σ_c·z_c + u_c·z_q): independent parts z_c per channel and bin,
    one shared q̄ draw z_q per bin (u = 0 for observations without a shared part).
    """
    acc_noise, lc_noise = model.replicated_noise(rng, pred["acc"].shape[0])
    acc = pred["acc"] + pred["noise_acc"][:, None] * acc_noise
    lc = pred["lc"] + pred["noise_lc"][:, None, None] * lc_noise
    return acc, lc


def as_rng(rng):
    """A numpy Generator: ``rng`` itself, or one seeded with it."""
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)

# ---------------------------------------------------------------------------
# check tree: posterior subset with matching log-likelihood and predictive


def _subset_draws(n_chain, draw_coords, budget):
    """Every k-th stored draw (counting from the last) so that chains × draws ≤ ``budget``."""
    step = max(1, int(math.ceil(n_chain * draw_coords.size / budget)))
    return draw_coords[::-1][::step][::-1]


def check_tree(fit, budget=CHECK_DRAW_BUDGET, rng=None):
    """DataTree for PSIS-LOO and LOO-PIT, every group on the same draws.

    posterior (subset of draws), log_likelihood ``total`` (time), ``acc`` (time),
    ``lc`` (load_cell, time), posterior_predictive ``acc``/``lc`` (one replicate per
    draw) and observed_data ``acc``/``lc``, all recomputed from ``fit.model``.
    Also carries the mean prediction in constant_data (``acc_mean``, ``lc_mean``).
    """
    import arviz_base as azb

    rng = as_rng(rng)
    model, tree = fit.model, fit.tree
    post = tree["posterior"].to_dataset()
    draws = _subset_draws(post.sizes["chain"], np.asarray(post["draw"].values), budget)
    post = post.sel(draw=draws)
    theta = np.stack([np.asarray(post[n].values, float) for n in model.names], axis=-1)
    n_chain, n_draw = theta.shape[:2]
    flat = theta.reshape(-1, model.ndim)
    pred = predict_draws(model, flat, log_likelihood=True)
    acc_rep, lc_rep = replicate_data(model, pred, rng)
    obs = model.obs
    shape = (n_chain, n_draw)
    lc_ids = [model.parachutes[int(i)].id for i in obs.lc_index]
    channels = ("acc", "lc") if lc_ids else ("acc",)
    replicated = {"acc": acc_rep, "lc": lc_rep}
    out = azb.from_dict(
        {
            "posterior": {n: post[n].values for n in model.names},
            "log_likelihood": {name[3:]: pred[name].reshape(shape + pred[name].shape[1:])
                               for name in ("ll_total", "ll_acc", "ll_lc")
                               if name in pred and name[3:] in ("total",) + channels},
            "posterior_predictive": {c: replicated[c].reshape(shape + replicated[c].shape[1:]) for c in channels},
            "observed_data": {c: getattr(obs, c) for c in channels},
            "constant_data": {"acc_mean": pred["acc"].mean(axis=0), "lc_mean": pred["lc"].mean(axis=0)},
        },
        coords={"chain": np.asarray(post["chain"].values), "draw": draws, "time": obs.time,
                "load_cell": lc_ids},
        dims={"acc": ["time"], "lc": ["load_cell", "time"], "total": ["time"],
              "acc_mean": ["time"], "lc_mean": ["load_cell", "time"]},
        check_conventions=False,
    )
    return out

"""PSIS-LOO and LOO-PIT of a fit's DataTree, smoothed by :mod:`cpas_bayes.stats.psis` in one pass.

``arviz.loo`` and ``arviz.loo_pit`` accept precomputed smoothed log weights
and Pareto k̂; given them they return their usual objects (``ELPDDataLOO``,
a Dataset of PIT values), so every reader of these results — the diagnosis
rule, ``arviz.compare``, a user's own tools — is unchanged. The weights are
those ArviZ would compute itself (the same tail rule, the same relative
efficiency r_eff: the mean over posterior variables of the bulk ESS of the
mean per draw), to round-off, at a fraction of the time: ArviZ fits the tail
of one observation at a time in Python.
"""

from __future__ import annotations

import warnings

import numpy as np
import xarray as xr

from cpas_bayes.stats.psis import arviz_tail, psis_log_weights

SAMPLE_DIMS = ("chain", "draw")


def relative_efficiency(tree):
    """ESS of the mean per posterior variable, averaged, over the log-likelihood's draw count (as ArviZ's loo)."""
    posterior = tree["posterior"].to_dataset()
    likelihood = tree["log_likelihood"].to_dataset()
    n_samples = likelihood.sizes["chain"] * likelihood.sizes["draw"]
    if posterior.sizes["chain"] == 1:
        return 1.0
    ess = posterior.azstats.ess(method="mean")
    return float(np.hstack([np.ravel(ess[v].values) for v in ess.data_vars]).mean() / n_samples)


def smoothed_log_weights(log_lik: xr.DataArray, r_eff):
    """PSIS log weights (dims of ``log_lik``) and k̂ (its observation dims) for leaving out each observation."""
    obs_dims = [d for d in log_lik.dims if d not in SAMPLE_DIMS]
    ordered = log_lik.transpose(*obs_dims, *SAMPLE_DIMS)
    values = np.asarray(ordered.values, float)
    n_samples = values.shape[-2] * values.shape[-1]
    flat = -values.reshape(values.shape[:-2] + (n_samples,))
    lw, khat = psis_log_weights(flat, tail=arviz_tail(n_samples, r_eff))
    weights = xr.DataArray(lw.reshape(values.shape), dims=ordered.dims, coords=ordered.coords)
    k = xr.DataArray(np.asarray(khat).reshape(values.shape[:-2]), dims=obs_dims,
                     coords={d: ordered.coords[d] for d in obs_dims if d in ordered.coords})
    return weights.transpose(*log_lik.dims), k


def psis_loo(tree, var_name="total", r_eff=None):
    """``arviz.loo`` of ``var_name`` with pointwise values, from weights smoothed here."""
    import arviz_stats as azs

    r_eff = relative_efficiency(tree) if r_eff is None else r_eff
    weights, k = smoothed_log_weights(tree["log_likelihood"][var_name], r_eff)
    with warnings.catch_warnings():
        # High k̂ is reported by the callers, bin by bin; ArviZ's generic warning adds nothing.
        warnings.filterwarnings("ignore", message="Estimated shape parameter of Pareto", category=UserWarning)
        return azs.loo(tree, var_name=var_name, pointwise=True, reff=r_eff, log_weights=weights, pareto_k=k)


def loo_pit(tree, var_names, r_eff=None):
    """``arviz.loo_pit`` of ``var_names`` (each observed, replicated and with a log-likelihood), weights smoothed here."""
    import arviz_stats as azs

    r_eff = relative_efficiency(tree) if r_eff is None else r_eff
    pairs = {v: smoothed_log_weights(tree["log_likelihood"][v], r_eff) for v in var_names}
    weights = xr.Dataset({v: w for v, (w, _) in pairs.items()})
    k = xr.Dataset({v: kk for v, (_, kk) in pairs.items()})
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Estimated shape parameter of Pareto", category=UserWarning)
        return azs.loo_pit(tree, var_names=list(var_names), log_weights=weights, pareto_k=k)

"""Rank-normalised ESS and nested R-hat of many parameters at once (Vehtari et al. 2021; Margossian et al. 2024).

The same numbers as ArviZ's array functions (``arviz_stats.base.array_stats.ess`` with ``method="bulk"`` or
``"tail"``, and ``rhat_nested``), computed for every parameter in one pass of array operations instead of a
Python loop per parameter: the ESS rule checks them after every sampling chunk, in the main process, while
the workers wait. Agreement with ArviZ is a test (``tests/test_rank_diagnostics.py``).

Input ``x`` has shape (D, C, S): parameters, chains, draws.

* Split chains: the first and last ⌊S/2⌋ draws of each chain become two chains.
* Rank normalisation: z = Φ⁻¹((r − 3/8)/(N + 1/4)), r the average rank among all N draws of a parameter
  (Blom's offset).
* ESS = C·S/τ̂ with τ̂ = −1 + 2·Σ_k P̂_k + ρ̂_{2K}: ρ̂_t = 1 − (W − ⟨acov_t⟩)/var⁺ from the chains' FFT
  autocovariances, P_k = ρ̂_{2k} + ρ̂_{2k+1} summed over Geyer's initial positive sequence (pairs while the
  previous pair sum is positive), made monotone (P̂_k = min(P_k, P̂_{k−1})), τ̂ ≥ 1/log₁₀(C·S).
* Bulk ESS: of the rank-normalised split chains. Tail ESS: the smaller ESS of the indicators
  I(x ≤ q₀.₀₅) and I(x ≤ q₀.₉₅) (split).
* Nested R-hat of the rank-normalised and of the folded (|x − median|) split chains, the larger of the two:
  √(1 + B_ν/W_ν), B_ν the variance of superchain means, W_ν the mean over superchains of within-chain
  variance plus between-chain variance; with one superchain the plain rank R-hat √((B/W + S − 1)/S)
  (ArviZ's ``rhat``).
"""

from __future__ import annotations

import numpy as np
from scipy import fft, special

_BLOM = 3.0 / 8.0


def split_chains(x):
    """(…, C, S) → (…, 2C, ⌊S/2⌋): each chain's first and last halves as chains of their own."""
    half = x.shape[-1] // 2
    return np.concatenate([x[..., :half], x[..., x.shape[-1] - half:]], axis=-2)


def average_ranks(v):
    """Ranks 1…N along each row of ``v`` (R, N), ties sharing their average rank (as
    ``scipy.stats.rankdata(method="average")``, with an unstable sort: about twice as fast)."""
    n = v.shape[1]
    order = np.argsort(v, axis=1)
    ordered = np.take_along_axis(v, order, axis=1)
    starts = np.ones(v.shape, bool)
    starts[:, 1:] = ordered[:, 1:] != ordered[:, :-1]
    ends = np.ones(v.shape, bool)
    ends[:, :-1] = starts[:, 1:]
    idx = np.broadcast_to(np.arange(n), v.shape)
    first = np.maximum.accumulate(np.where(starts, idx, 0), axis=1)
    last = np.minimum.accumulate(np.where(ends, idx, n - 1)[:, ::-1], axis=1)[:, ::-1]
    ranks = np.empty(v.shape)
    np.put_along_axis(ranks, order, (first + last) / 2.0 + 1.0, axis=1)
    return ranks


def rank_normalise(x):
    """z-scores of the average ranks of each parameter's draws, over all its chains (Blom's offset)."""
    d, c, s = x.shape
    flat = x.reshape(d, c * s)
    ranks = average_ranks(flat)
    ranks[~np.isfinite(flat).all(axis=1)] = np.nan    # as ArviZ: no ESS or R-hat of a parameter with NaN
    return special.ndtri((ranks - _BLOM) / (c * s - 2 * _BLOM + 1)).reshape(d, c, s)


def ess(x):
    """Effective sample size of (D, C, S) draws per parameter (D,), by Geyer's initial monotone sequence."""
    x = np.asarray(x, float)
    d, c, s = x.shape
    out = np.full(d, np.nan)
    flat = x.reshape(d, -1)
    constant = (flat.max(axis=1) - flat.min(axis=1)) < np.finfo(float).resolution
    out[constant] = c * s
    live = ~constant & np.all(np.isfinite(flat), axis=1)
    if not live.any():
        return out
    y = x[live] - x[live].mean(axis=-1, keepdims=True)
    m = fft.next_fast_len(2 * s)
    spectrum = np.fft.rfft(y, n=m, axis=-1)
    acov = np.fft.irfft(spectrum * np.conjugate(spectrum), n=m, axis=-1)[..., :s] / s    # (L, C, S), biased
    mean_var = acov[:, :, 0].mean(axis=1) * s / (s - 1.0)
    var_plus = mean_var * (s - 1.0) / s
    if c > 1:
        var_plus = var_plus + np.var(x[live].mean(axis=-1), axis=1, ddof=1)
    rho = 1.0 - (mean_var[:, None] - acov.mean(axis=1)) / var_plus[:, None]     # (L, S)
    rho[:, 0] = 1.0
    # pair 0 and the pairs k ≥ 1 with 2k − 1 < S − 3 can be read
    k_max = max(1, (s - 1) // 2)
    pairs = rho[:, 0:2 * k_max:2] + rho[:, 1:2 * k_max:2]                      # (L, k_max)
    positive = np.cumprod(pairs > 0.0, axis=1)
    n_read = np.minimum(positive.sum(axis=1), k_max - 1)                         # K: pairs read after pair 0
    idx = np.arange(k_max)
    monotone = np.minimum.accumulate(pairs, axis=1)
    summed = np.where(idx[None, :] < n_read[:, None], monotone, 0.0).sum(axis=1)
    rows = np.arange(rho.shape[0])
    last_even = rho[rows, 2 * n_read]
    last_pair = pairs[rows, n_read]
    last = np.where((last_pair >= 0.0) | (last_even > 0.0), last_even, 0.0)
    last = np.where(n_read == 0, 1.0, last)
    tau = np.maximum(-1.0 + 2.0 * summed + last, 1.0 / np.log10(c * s))
    value = c * s / tau
    value[np.isnan(rho).any(axis=1)] = np.nan
    out[live] = value
    return out


def ess_bulk(x):
    """Bulk ESS per parameter of (D, C, S) draws: ESS of the rank-normalised split chains."""
    x = np.asarray(x, float)
    if x.shape[-1] < 4:
        return np.full(x.shape[0], np.nan)
    return ess(rank_normalise(split_chains(x)))


def ess_tail(x, probs=(0.05, 0.95)):
    """Tail ESS per parameter: the smaller ESS of the indicators I(x ≤ q) at the two quantiles ``probs``."""
    x = np.asarray(x, float)
    if x.shape[-1] < 4:
        return np.full(x.shape[0], np.nan)
    d = x.shape[0]
    values = []
    for p in probs:
        q = np.quantile(x.reshape(d, -1), p, axis=1)
        values.append(ess(split_chains((x <= q[:, None, None]).astype(float))))
    out = np.min(values, axis=0)
    out[~np.isfinite(x.reshape(d, -1)).all(axis=1)] = np.nan
    return out


def _nested(z, superchain):
    """√(1 + B_ν/W_ν) of (D, C, S) with chain → superchain ids (C,), equal counts per superchain."""
    ids = np.unique(superchain)
    chain_mean = z.mean(axis=-1)                                  # (D, C)
    chain_var = z.var(axis=-1, ddof=1) if z.shape[-1] > 1 else np.zeros_like(chain_mean)
    per = [superchain == k for k in ids]
    super_mean = np.stack([chain_mean[:, m].mean(axis=1) for m in per], axis=1)
    between = (np.stack([chain_mean[:, m].var(axis=1, ddof=1) for m in per], axis=1)
               if per[0].sum() > 1 else np.zeros_like(super_mean))
    within = np.stack([chain_var[:, m].mean(axis=1) for m in per], axis=1)
    return np.sqrt(1.0 + np.var(super_mean, axis=1, ddof=1) / np.mean(within + between, axis=1))


def _classic(z):
    """√((B/W + S − 1)/S) of (D, C, S): B = S·var(chain means), W = mean within-chain variance."""
    s = z.shape[-1]
    between = s * np.var(z.mean(axis=-1), axis=1, ddof=1)
    within = np.mean(z.var(axis=-1, ddof=1), axis=1)
    return np.sqrt((between / within + s - 1) / s)


def rhat_nested(x, superchain, z_split=None):
    """Rank-normalised nested R-hat per parameter of (D, C, S) draws grouped by ``superchain`` (C,):
    the larger of the bulk and folded values (one superchain: the plain rank R-hat). ``z_split``: the
    rank-normalised split chains, if known."""
    x = np.asarray(x, float)
    superchain = np.asarray(superchain)
    if x.shape[-1] < 4 or x.shape[1] < 2:
        return np.full(x.shape[0], np.nan)
    counts = np.bincount(np.unique(superchain, return_inverse=True)[1])
    if counts.min() != counts.max():
        raise ValueError("every superchain must hold the same number of chains")
    split = split_chains(x)
    ids = np.concatenate([superchain, superchain])
    d = x.shape[0]
    folded = np.abs(split - np.median(split.reshape(d, -1), axis=1)[:, None, None])
    z_split = rank_normalise(split) if z_split is None else z_split
    if counts.size == 1:    # one superchain: the plain rank-normalised split R-hat
        return np.maximum(_classic(z_split), _classic(rank_normalise(folded)))
    return np.maximum(_nested(z_split, ids), _nested(rank_normalise(folded), ids))


def chain_diagnostics(x, superchain, tail_probs=(0.05, 0.95)):
    """(bulk ESS, tail ESS, nested R-hat) per parameter of (D, C, S) draws, sharing one ranking."""
    x = np.asarray(x, float)
    if x.shape[-1] < 4:
        nan = np.full(x.shape[0], np.nan)
        return nan, nan.copy(), nan.copy()
    z_split = rank_normalise(split_chains(x))
    return ess(z_split), ess_tail(x, tail_probs), rhat_nested(x, superchain, z_split)

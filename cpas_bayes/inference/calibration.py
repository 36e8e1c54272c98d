"""Simulation-based calibration of the posterior fits (Talts et al. 2018).

If θ̃ ~ π(θ) and ỹ ~ p(y | θ̃), then θ̃ is a draw from the posterior
p(θ | ỹ) averaged over ỹ, so for any parameter the rank of θ̃ among L draws
θ_1..θ_L of a correct posterior sampler,

    r = #{l : θ_l < θ̃}  ∈ {0, …, L},

is uniform on {0, …, L}, and a central interval of probability p covers θ̃
with probability p. A posterior too narrow piles the ranks at both ends (∪),
one too wide in the middle (∩), a biased one on one side; coverage below p
means overconfidence.

Here the conditioning is a *template* test: its flight condition (airspeed,
q̄, G), time base, stage nominal starts (the start priors), stated weights and
random 1-sigmas. One replica draws θ̃ from the model's prior, simulates the
binned observations from the model's own likelihood at θ̃, refits with the
package's sampler and ranks θ̃ among the pooled posterior draws
(:func:`run_replica`). Only the baseline error model is simulated: an
extension that replaces it (AR(1) errors) is refused.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from cpas_bayes.inference.fit import SamplerOptions, fit_model
from cpas_bayes.stats.model import TestModel
from cpas_bayes.stats.observations import Observations

N_RANKS = 99          # L: draws per rank, so ranks take 100 values and 10 bins hold 10 each
COVERAGE_PROBS = (0.5, 0.9)


def draw_from_prior(model: TestModel, rng, batch=64, max_batches=200):
    """One θ̃ (D,) from the model's joint prior.

    The columns are drawn independently (``model.sample_prior``) and the first
    draw is kept whose ``model.log_prior`` is finite (each parachute's stage
    starts in order) and whose predicted channels are finite. Rejection
    leaves exactly the prior restricted to that set, which is the support of
    the posterior the sampler targets (``log_posterior`` is −inf elsewhere):

        π(θ) ∝ Π_j π_j(θ_j) · 1[starts ordered] · 1[prediction finite]
    """
    for _ in range(max_batches):
        theta = model.sample_prior(rng, batch)
        theta = theta[np.isfinite(model.log_prior(theta))]
        if not theta.size:
            continue
        pred = model.predict(theta)
        finite = np.isfinite(pred.acc).all(axis=1) & np.isfinite(pred.lc).all(axis=(1, 2))
        if finite.any():
            return theta[np.argmax(finite)]
    raise ValueError(f"no prior draw of {max_batches * batch} had ordered stage starts and a finite prediction")


def simulate_observations(model: TestModel, theta, rng) -> Observations:
    """Observations (a copy of ``model.obs``) whose ``acc`` and ``lc`` are drawn from the likelihood at θ.

    Per bin b and channel c (accelerometer, then the load cells)::

        y_c = μ_c(θ) + λ_c·(d_c·ε_c + u_c·η),   ε_c, η ~ N(0, 1) independent,

    η shared by the channels of the bin (the measured q̄'s error), d the
    independent 1-sigma (``acc_sigma``, ``lc_sigma``), u the q̄ part
    (``acc_qbar``, ``lc_qbar``) and λ the error multipliers at θ (``noise_acc``,
    ``noise_lc``). So Cov(y_b) = Λ·(D + u·uᵀ)·Λ with D = diag(d²), the
    covariance of :meth:`TestModel.pointwise_log_likelihood`; bins are
    independent. Everything else (time base, sigmas, flight condition) is kept.
    """
    if model.replaces_error_model:
        raise ValueError(f"the {model.name} model brings its own error model; only the baseline errors "
                         "(independent bins, shared q̄) can be simulated")
    theta = np.asarray(theta, float)
    pred = model.predict(theta[None])
    obs = model.obs
    shared = rng.standard_normal(obs.n_bins)
    acc = pred.acc[0] + pred.noise_acc[0] * (obs.acc_sigma * rng.standard_normal(obs.acc.shape)
                                             + obs.acc_qbar * shared)
    lc = pred.lc[0] + pred.noise_lc[0] * (obs.lc_sigma * rng.standard_normal(obs.lc.shape)
                                          + obs.lc_qbar * shared[None, :])
    return replace(obs, acc=acc, lc=lc)


def model_with_observations(model: TestModel, obs: Observations) -> TestModel:
    """A fresh :class:`TestModel` of the same test, priors, decay, extensions, cluster form and
    below-previous rule on ``obs``.

    Built anew rather than copied with ``obs`` swapped: the constructor derives the
    error model's constants from the sigmas, and a new model cannot keep any of
    them (or anything an extension read) from the old observations.
    """
    old = model.obs
    if obs.time.shape != old.time.shape or obs.lc.shape != old.lc.shape:
        raise ValueError(f"observations of another shape: {obs.lc.shape} load-cell bins, not {old.lc.shape}")
    return TestModel(model.test, obs, model.kind_priors, model.nuisance_priors, decay=model.decay,
                     extensions=model.extensions, cluster=model.cluster, below_previous=model.below_previous)


def rank_of_truth(draws, truth, n_ranks=N_RANKS, rng=None):
    """Talts' rank statistic per parameter: r_j = #{l : θ_lj < θ̃_j} + U{0, …, #{l : θ_lj = θ̃_j}}.

    ``draws`` (S, D) are the pooled posterior draws; L = ``n_ranks`` of them are
    picked at random without replacement (rows far apart in the chains, so
    nearly independent when the ESS is well above L). Ties are broken at random,
    so the rank is uniform on 0..L for a correct posterior. Returns ints (D,).
    """
    draws = np.atleast_2d(np.asarray(draws, float))
    truth = np.asarray(truth, float)
    if draws.shape[1] != truth.size:
        raise ValueError(f"draws have {draws.shape[1]} parameters, truth {truth.size}")
    if not 1 <= n_ranks <= draws.shape[0]:
        raise ValueError(f"n_ranks must be between 1 and the {draws.shape[0]} draws, not {n_ranks}")
    rng = np.random.default_rng(rng)
    picked = draws[rng.choice(draws.shape[0], n_ranks, replace=False)]
    below = (picked < truth).sum(axis=0)
    ties = (picked == truth).sum(axis=0)
    return below + rng.integers(0, ties + 1)


def rank_histogram(ranks, n_ranks=N_RANKS, bins=10):
    """Counts of ranks in ``bins`` bins of 0..L, and each bin's probability under uniform ranks.

    Rank r goes to bin ⌊r·bins/(L + 1)⌋; the probability of a bin is the share of
    the L + 1 values it holds (exactly 1/bins when bins divides L + 1).
    """
    ranks = np.asarray(ranks).ravel()
    if not 2 <= bins <= n_ranks + 1:
        raise ValueError(f"bins must be between 2 and {n_ranks + 1}, not {bins}")
    if ranks.size and (ranks.min() < 0 or ranks.max() > n_ranks):
        raise ValueError(f"ranks must lie in 0..{n_ranks}")
    which = (np.arange(n_ranks + 1) * bins) // (n_ranks + 1)
    probability = np.bincount(which, minlength=bins) / (n_ranks + 1)
    counts = np.bincount((ranks.astype(int) * bins) // (n_ranks + 1), minlength=bins)
    return counts, probability


def rank_uniformity(ranks, n_ranks=N_RANKS, bins=10):
    """Pearson's chi-square test of the ranks' histogram against uniform ranks: (statistic, p-value).

        X² = Σ_k (O_k − E_k)² / E_k,   E_k = n·P(bin k),   p = P(χ²_{bins−1} ≥ X²)

    The ranks are taken as independent; ranks of correlated parameters of one
    replica are not, which widens X²'s spread (the test is then liberal).
    """
    counts, probability = rank_histogram(ranks, n_ranks, bins)
    n = counts.sum()
    if n == 0:
        return float("nan"), float("nan")
    expected = n * probability
    statistic = float(np.sum((counts - expected) ** 2 / expected))
    return statistic, float(stats.chi2.sf(statistic, bins - 1))


def uniform_histogram_band(n, n_ranks=N_RANKS, bins=10, level=0.99):
    """The ``level`` interval (low, high) of one bin's count for n uniform ranks: Binomial(n, P(bin))
    quantiles (Talts et al. Fig. 1's grey band), per bin (bins,)."""
    _, probability = rank_histogram([], n_ranks, bins)
    tail = (1 - level) / 2
    return stats.binom.ppf(tail, n, probability), stats.binom.ppf(1 - tail, n, probability)


def interval_coverage(draws, truth, probs=COVERAGE_PROBS):
    """Whether θ̃ lies inside each central posterior interval [q_{(1−p)/2}, q_{(1+p)/2}]: bool (len(probs), D)."""
    draws = np.atleast_2d(np.asarray(draws, float))
    truth = np.asarray(truth, float)
    out = []
    for p in probs:
        low, high = np.quantile(draws, [(1 - p) / 2, (1 + p) / 2], axis=0)
        out.append((truth >= low) & (truth <= high))
    return np.array(out)


def binomial_band(n, p, level=0.95):
    """The ``level`` interval of the covered fraction k/n when k ~ Binomial(n, p): (low, high)."""
    tail = (1 - level) / 2
    return float(stats.binom.ppf(tail, n, p) / n), float(stats.binom.ppf(1 - tail, n, p) / n)


# ---------------------------------------------------------------------------
# one replica


@dataclass
class ReplicaResult:
    """One SBC replica: the truth, its ranks and coverage per parameter, and the fit's diagnostics."""

    names: list
    truth: np.ndarray             # (D,) θ̃
    ranks: np.ndarray             # (D,) in 0..n_ranks
    covered: np.ndarray           # (len(probs), D) bool
    probs: tuple
    n_ranks: int
    converged: bool               # the fit's own verdict (summary diagnostics)
    rhat_max: float
    ess_bulk_min: float
    steps: int                    # per ensemble (the longest)
    seconds: float                # the fit, MAP search included
    rhat: np.ndarray              # (D,) nested R-hat per parameter
    ess_bulk: np.ndarray          # (D,)
    ess_tail: np.ndarray          # (D,)
    draws: np.ndarray | None = None   # pooled posterior draws (S, D), when asked for


def run_replica(template: TestModel, seed, options: SamplerOptions = SamplerOptions(), n_ranks=N_RANKS,
                probs=COVERAGE_PROBS, keep_draws=False) -> ReplicaResult:
    """Draw θ̃ from ``template``'s prior, simulate its observations, refit, rank θ̃ among the draws.

    ``seed`` (an int or a sequence of ints) seeds three independent streams (θ̃, the
    noise, the rank picks): give one apart from the template's own (a synthetic
    template's seed spawns the same streams). The sampler takes ``options`` as
    given (its own seed included). The fit is
    :func:`cpas_bayes.inference.fit.fit_model`; its pooled draws are
    ``Fit.sampling.stacked()``, the draws of its DataTree's posterior.
    """
    theta_rng, noise_rng, rank_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    truth = draw_from_prior(template, theta_rng)
    model = model_with_observations(template, simulate_observations(template, truth, noise_rng))
    started = time.perf_counter()
    fit = fit_model(model, options)
    seconds = time.perf_counter() - started
    chains, _, _ = fit.sampling.stacked()
    draws = chains.reshape(-1, chains.shape[-1])
    diagnostics = fit.summary["diagnostics"]
    per = [fit.summary["diagnostics_per_parameter"][n] for n in model.names]
    return ReplicaResult(names=list(model.names), truth=truth, ranks=rank_of_truth(draws, truth, n_ranks, rank_rng),
                         covered=interval_coverage(draws, truth, probs), probs=tuple(probs), n_ranks=n_ranks,
                         converged=bool(diagnostics["converged"]), rhat_max=float(diagnostics["rhat_max"]),
                         ess_bulk_min=float(diagnostics["ess_bulk_min"]), steps=int(max(diagnostics["steps"])),
                         seconds=seconds, rhat=np.array([p["rhat"] for p in per]),
                         ess_bulk=np.array([p["ess_bulk"] for p in per]),
                         ess_tail=np.array([p["ess_tail"] for p in per]), draws=draws if keep_draws else None)


def replica_task(job):
    """Executor task (:mod:`cpas_bayes.core.executor`): ``run_replica(*job)``, job = (template, seed, options[,
    n_ranks, probs, keep_draws])."""
    return run_replica(*job)

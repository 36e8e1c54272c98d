"""When a fit has sampled enough: the statistics of the stopping rules and their decision.

Two rules (``SamplerOptions.stop`` in :mod:`cpas_bayes.inference.fit`):

``"tau"``
    Each ensemble on its own runs until its chain is longer than
    ``tau_factor`` (50) integrated autocorrelation times τ and τ moved by less
    than ``tau_rtol`` since the last check (emcee's guidance, Foreman-Mackey
    et al. 2013). It asks for a chain length, not for the precision of the answer.

``"ess"``
    The ensembles advance in lockstep chunks; after each chunk the draws the
    fit would keep are pooled and the run stops when *every* parameter has
    rank-normalised bulk ESS and tail ESS ≥ ``ess_target`` and R-hat ≤
    ``rhat_target`` (Vehtari, Gelman, Simpson, Carpenter & Bürkner 2021,
    "Rank-normalization, folding, and localization: an improved R-hat",
    Bayesian Analysis 16(2)). It asks for what the answer needs.

What "the draws the fit keeps" (:func:`burn_and_thin`, :func:`pool_kept`): per
ensemble e, thinning ½·min τ_e, with τ_e estimated on the whole chain (under
the ESS rule, more if needed to keep at most ``KEPT_DRAWS`` per ensemble); every
ensemble then contributes its last S = min_e S_e kept draws. Burn-in is
2·max τ_e under the τ rule (4 % of a 50 τ chain) and *half the chain* (at
least 2·max τ_e) under the ESS rule. The ESS rule stops after about ten τ,
where τ itself is still under-estimated (on the drogue example τ̂ = 63 steps
after 1,000 steps against 97 after 5,000), so 2·τ̂ may keep part of the
start-up transient; and every ensemble starts from the same Laplace ball, so
R-hat cannot see a transient they share. Discarding half (Gelman et al.'s
convention, Stan's warm-up) makes the discarded part grow with the run, so a
transient is dropped eventually; it costs about a third more steps.

τ must have stopped growing too. ESS and R-hat alone stopped the Main
example after its first chunk (500 steps, τ̂ = 48 steps against 180 at
9,000): the walkers were still spreading from the start, every ensemble alike,
so R-hat was 1.008, and the 90 % intervals came out 7–11 % wider than the τ
rule's. A τ̂ that still grows is that transient's sign, so the ESS rule also
asks that the largest τ over ensembles and parameters be no more than
``tau_rtol`` (5 %) above its value at the previous check, though not the 50 τ
length. A τ̂ that falls is not that sign: it falls when the half-chain burn-in
drops an early, more correlated stretch. (This asked |Δτ̂| < 5 % before, both
ways. τ̂ on the first checks' chains, some 30 τ long, has a sampling error of
about 10 %, so that test failed at random for two or three more checks on
the examples: 2,000–2,250 steps per ensemble where 1,250 suffice. Measured
on both examples, four seeds each, with the adaptive proposal: the one-sided
test stops at 1,250 steps and its 90 % interval endpoints differ from the
two-sided test's by 1.0–1.6 % of the width (rms; the Monte Carlo error of
either is about 1.5 %), widths 0.995–1.011 of the two-sided ones on average;
three synthetic Mains alike (1.3–1.4 % rms, widths 0.996–1.008); the Drogue
SBC, benchmarks/sbc.md, was re-run with it. Asking it of every
parameter of every ensemble, as the τ rule does per ensemble, ran the drogue
example to 7,000 steps, past the τ rule's 5,500: one of 4·29 noisy estimates
always moves by 5 %.)

The statistics are computed on exactly those draws, as the fit's summary
(:func:`cpas_bayes.inference.fit_folder.convergence`) computes them, so a fit
stopped by the ESS rule reports ESS ≥ the target:

* ESS (bulk and tail) treats every walker of every ensemble as a chain
  (E·W chains of S draws). Vehtari et al.'s multi-chain ESS,
  ESS = E·W·S / (1 + 2 Σ_t ρ̂_t) with ρ̂_t = 1 − (W_var − ā_t)/v̂ar⁺
  (ā_t: the walkers' mean autocovariance at lag t, v̂ar⁺ the pooled variance
  including the between-walker part), is then the rank-normalised analogue of
  emcee's own ESS ≈ W·N/τ, whose τ averages the walkers' autocorrelations.
  Bulk ESS is that of the rank-normalised draws (the mean and median); tail
  ESS the smaller of the ESS of the indicators I(θ ≤ q₀.₀₅) and I(θ ≥ q₀.₉₅),
  i.e. of the 90 % interval's endpoints.
* R-hat is the rank-normalised *nested* R-hat (Margossian, Hoffman, Sountsov,
  Riou-Durand, Vehtari & Gelman 2024, "Nested R-hat: assessing the convergence
  of Markov chain Monte Carlo when running many short chains", Bayesian
  Analysis) with the ensembles as super-chains: walkers of one ensemble share
  its proposals and are not independent chains, so the question "have the
  chains forgotten their start" is asked of the ensembles. The same
  dependence between walkers would make the walker-chain ESS optimistic if the
  ensembles had not mixed; the ensembles' agreement (R-hat) is the check on it.
  With one ensemble, the plain rank R-hat over walkers (optimistic).

Why ``ESS_TARGET`` = 1000. The Monte-Carlo standard error of a quantile q_p
estimated from draws with tail ESS N is se(q̂_p) ≈ √(p(1−p)/N) / f(q_p). For a
normal posterior with sd σ and p = 0.05, f(q_p) = φ(1.645)/σ = 0.103/σ, so
se ≈ 2.11 σ/√N, while the 90 % interval is 3.29 σ wide:

    se(endpoint) / width ≈ 0.64/√N  →  3.2 % at N = 400,  2.0 % at N = 1000.

400 is Vehtari et al.'s minimum for the diagnostics themselves to be
reliable, and fit health warns below it; 1000 holds the endpoints of the
reported 90 % intervals to about 2 % of their width (the width itself to
about 3 %), and leaves the 400 floor a margin for the ESS estimate's own
noise. ``RHAT_TARGET`` = 1.01 is Vehtari et al.'s threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ESS_TARGET = 1000
RHAT_TARGET = 1.01
# Tail ESS is that of the 90 % interval's endpoints (Vehtari et al.'s 5 % and 95 % quantiles); ArviZ 1.x's
# default would be its 0.89 ``ci_prob`` read as the quantiles 0.11 and 0.89.
TAIL_QUANTILES = (0.05, 0.95)
# Draws one ensemble keeps under the ESS rule, at most: with the adaptive proposal nearly every stored step is
# an independent draw, and keeping them all (18,000 on the two-Drogue example, 42,000 on the Main) costs the
# pointwise log-likelihood, the DataTree and every figure in proportion (measured: the fit command took as
# long as with differential evolution's 10,000 draws despite 4 s less sampling); four ensembles of 2,500
# still leave an ESS several times the target.
KEPT_DRAWS = 2500
STOP_RULES = ("ess", "tau")


def integrated_time(chain, store_every):
    """Integrated autocorrelation time τ (steps) per parameter of a stored (S, W, D) chain: emcee's
    estimator, τ̂ = 1 + 2 Σ_{t=1..M} ρ̄(t) with ρ̄ the walkers' mean autocorrelation and Sokal's window
    (the first M ≥ 5·τ̂(M)); ``tol=0``: an estimate also on a short chain.

    All walkers of a parameter in one FFT (emcee's ``autocorr.integrated_time`` does one per walker and
    parameter in Python loops); the same numbers to rounding.
    """
    from scipy import fft

    x = np.asarray(chain, float)
    n = x.shape[0]
    size = fft.next_fast_len(2 * n, real=True)    # ≥ 2n: the linear (not circular) autocovariance
    rho = np.empty((n, x.shape[2]))
    for d in range(x.shape[2]):                    # one parameter at a time: its (2n, W) block stays in cache
        spectrum = fft.rfft(x[:, :, d] - x[:, :, d].mean(axis=0), n=size, axis=0)
        acov = fft.irfft(spectrum.real ** 2 + spectrum.imag ** 2, n=size, axis=0)[:n]
        # a walker that never moved in the window (stuck: every proposal rejected) is perfectly correlated,
        # ρ ≡ 1, not 0/0: τ then grows with the window instead of turning NaN
        stuck = np.ptp(x[:, :, d], axis=0) == 0
        with np.errstate(invalid="ignore", divide="ignore"):
            rho[:, d] = np.where(stuck, 1.0, acov / np.where(stuck, 1.0, acov[0])).mean(axis=1)
    taus = 2.0 * np.cumsum(rho, axis=0) - 1.0
    inside = np.arange(n)[:, None] < 5.0 * taus          # Sokal's window, c = 5
    window = np.where(inside.any(axis=0), np.argmin(inside, axis=0), n - 1)
    return store_every * taus[window, np.arange(taus.shape[1])]


def burn_and_thin(tau, store_every, n_stored=None, walkers=None):
    """(burn, thin) in *stored* steps: burn-in 2·max τ, or half of the ``n_stored`` steps if more
    (the ESS rule, see the module's docstring); thinning ½·min τ (at least every stored step), and with
    ``walkers`` given, at least enough that the ensemble keeps no more than ``KEPT_DRAWS`` draws."""
    burn = int(np.ceil(2 * np.max(tau) / store_every))
    if n_stored is not None:
        burn = max(burn, n_stored // 2)
    thin = max(1, int(0.5 * np.min(tau) / store_every))
    if n_stored is not None and walkers is not None:
        thin = max(thin, -(-(n_stored - burn) // max(1, KEPT_DRAWS // walkers)))   # ceil: at most that many steps
    return burn, thin


def pool_kept(kept):
    """Kept draws of E ensembles [(S_e, W, D)] → (E·W chains, S, D) with S = min S_e (each ensemble's last S),
    and the ensemble of each chain (``SamplingResult.stacked`` pools a fit's draws with it)."""
    s = min(k.shape[0] for k in kept)
    chains = np.concatenate([np.swapaxes(k[k.shape[0] - s:], 0, 1) for k in kept], axis=0)
    ensemble = np.concatenate([np.full(k.shape[1], e) for e, k in enumerate(kept)])
    return chains, ensemble


@dataclass(frozen=True)
class ChainStatistics:
    """Per-parameter diagnostics of pooled draws; NaN where the draws are too few to say."""

    ess_bulk: np.ndarray      # (D,)
    ess_tail: np.ndarray      # (D,)
    rhat: np.ndarray          # (D,) nested over ensembles (plain rank R-hat with one ensemble)

    def meets(self, ess_target, rhat_target):
        """True when every parameter has bulk and tail ESS ≥ ``ess_target`` and R-hat ≤ ``rhat_target``
        (NaN, i.e. too few draws, never meets them)."""
        return bool(np.all(self.ess_bulk >= ess_target) and np.all(self.ess_tail >= ess_target)
                    and np.all(self.rhat <= rhat_target))

    def of(self, columns):
        """The statistics of the parameters at ``columns`` only."""
        return ChainStatistics(self.ess_bulk[columns], self.ess_tail[columns], self.rhat[columns])

    def worst(self):
        """(min bulk ESS, min tail ESS, max R-hat) over the parameters."""
        return float(np.min(self.ess_bulk)), float(np.min(self.ess_tail)), float(np.max(self.rhat))


def chain_statistics(chains, ensemble):
    """Rank-normalised bulk ESS, tail ESS and R-hat of (C chains, S draws, D) grouped by ``ensemble`` (C,).

    The numbers ArviZ's ``ess`` and ``rhat_nested`` give (:mod:`cpas_bayes.inference.rank_diagnostics`,
    every parameter at once).
    """
    from cpas_bayes.inference.rank_diagnostics import chain_diagnostics

    by_parameter = np.moveaxis(np.asarray(chains, float), -1, 0)           # (D, C, S): chain and draw axes last
    ess_bulk, ess_tail, rhat = chain_diagnostics(by_parameter, np.asarray(ensemble), TAIL_QUANTILES)
    return ChainStatistics(ess_bulk=ess_bulk, ess_tail=ess_tail, rhat=rhat)


@dataclass(frozen=True)
class EssCheck:
    """One check of the ESS rule at a common chain length: τ, burn and thin of each ensemble, the pooled
    statistics, and whether the targets are met."""

    taus: list                # (D,) per ensemble, steps
    burn_thin: list           # (burn, thin) per ensemble, stored steps
    statistics: ChainStatistics | None
    met: bool


def ess_check(chains, store_every, ess_target=ESS_TARGET, rhat_target=RHAT_TARGET, tau_prev=None, tau_rtol=0.05,
              columns=None):
    """The ESS rule's check on stored chains [(S, W, D)] of E ensembles (all of one length).

    ``columns`` (indices; None: all) are the parameters whose ESS and R-hat the targets ask; τ, burn-in
    and thinning, and the statistics returned, stay those of every parameter.

    τ, burn-in and thinning per ensemble as the fit keeps its draws; then the pooled statistics
    (:func:`chain_statistics`) of the kept draws against the targets. The targets count only once every
    ensemble's τ has stopped growing: max τ < (1 + ``tau_rtol``)·max τ_prev (max over ensembles and parameters),
    ``tau_prev`` being the τ of the previous check (None: not settled). See the module's docstring for why.
    """
    taus = [integrated_time(c, store_every) for c in chains]
    burn_thin = [burn_and_thin(t, store_every, c.shape[0], c.shape[1]) for t, c in zip(taus, chains)]
    # the largest τ of all ensembles and parameters: a per-parameter test over E·D noisy estimates almost
    # never passes at once (measured: it ran the drogue example past the τ rule's length)
    tau_max = max(float(np.max(t)) for t in taus)
    settled = tau_prev is not None and tau_max < (1.0 + tau_rtol) * max(float(np.max(p)) for p in tau_prev)
    kept = [c[b::t] for c, (b, t) in zip(chains, burn_thin)]
    if min(k.shape[0] for k in kept) < 4:     # split R-hat needs at least two draws per half
        return EssCheck(taus, burn_thin, None, False)
    stats = chain_statistics(*pool_kept(kept))
    judged = stats if columns is None else stats.of(columns)
    return EssCheck(taus, burn_thin, stats, settled and judged.meets(ess_target, rhat_target))

"""Population inference from many per-test posteriors: the model memo's dispersions.

Every fitted test gives posterior draws of each inflation parameter under the
prior that fit used. Pooling asks what *population* of parachutes of one kind
the tests were drawn from, per stage key (``first``, ``reefed1``…,
``full_open``) and parameter, and writes the answer as memo entries and
population-predictive draws for Monte Carlo.

Hierarchical model and likelihood
---------------------------------
Test i flew C_i canopies of the kind. Its fit returned S draws
x_{i,c,s} of a parameter from p(x | d_i) ∝ L_i(x)·π_i(x), π_i being the fit's
own prior. The population is a family p(x | λ) (λ: two hyper-parameters),
and each canopy's value is one draw from it. The likelihood of λ is that of
the data with the population in place of the fit's prior, estimated by
reweighting the stored draws (Thrane & Talbot 2019, Eq. 34)::

    L(λ) = Π_i Z_i · Π_c (1/S) Σ_s p(x_{i,c,s} | λ) / π_i(x_{i,c,s})

Z_i (test i's evidence under its own prior) does not depend on λ or on the
family and is dropped. The canopies of one test are reweighted separately:
this takes the test's posterior to factorise between canopies (each has its
own load cell; in Drogue fits the stage parameters of the two canopies
correlate by |r| ≲ 0.1). The exact joint form, one sum over s of the product
over canopies, needs a population no narrower than the posteriors to keep
usable weights, and its sums turn into spikes at single draws otherwise. CDS_o
of sibling canopies does correlate (r ≈ 0.98, through the shared friction
factor), but its posteriors are ~10× narrower than the population spread,
where the factorisation changes nothing. This is the importance-reweighting
route, chosen over the Gaussian approximation because the per-test
posteriors sit on bounded supports (C_k ≥ 1, eps in a box), the derived n
has no Gaussian prior to divide out, and the same sums give an exact
leave-one-test-out criterion on the grid (below).

Effective-sample-size guard: at the inferred λ̂ (hyper-posterior median) the
weights w_s = p(x_{i,c,s} | λ̂)/π_i(x_{i,c,s}) of each canopy have
ESS = (Σ w)²/Σ w². When ESS < ``ess_min`` (20 by default) the Monte Carlo
sum is unreliable (the canopy's posterior is much wider than the population,
or reaches it only in its tail): a :class:`PoolWarning` names the test,
canopy, parameter and ESS, and the result lists it. The test is kept
(dropping it would bias the population towards the well-measured tests);
refit it with more draws or inspect it.

Scale floor: a canopy posterior of sd w reweighted by a population of scale
σ ≪ w keeps ESS ≈ S·√2·σ/w, so the scale hyper-prior starts at
σ_floor = ess_min·w_max/(√2·S) (w_max: the widest canopy posterior, in the
family's coordinate; about 0.1 % of n_p for real Drogue fits). Populations
narrower than that cannot be told from σ_floor with these posteriors; the
memo is then slightly conservative.

Which parameters and which per-test prior
-----------------------------------------
* sampled parameters (``n_p``, ``expopen``, ``ck``, ``tk``, ``eps`` of
  non-final stages): π_i is the fit's prior of that parameter;
* ``cd_o = CDS_o / S_o`` with S_o = π·D_o²/4 per canopy; the fit's prior on
  CDS_o is the kind's cd_o prior scaled by S_o, so
  π_i(cd_o) = π_CDS(cd_o·S_o)·S_o;
* the derived fill constant ``n = n_p·S^(−1/expopen)`` (Eq. 18) has no prior of
  its own. The population model for n replaces the prior of n_p *given
  everything else* o (C_k, expopen, eps, the starts…): at fixed o the map
  n_p ↦ n is linear, n_p = n·k(o) with k = S^(1/expopen), so the induced
  conditional prior is exact::

      π_i(n | o) = π_np(n_p)·k = π_np(n_p)·n_p/n

  evaluated on each draw's own (n_p, n). Reweighting by p(n | λ)/π_i(n | o)
  is exact (the other parameters keep their fit priors), with no density
  estimate;
* ``t_fp`` (peak fill time) is derived from the flight condition and not
  pooled: the per-canopy posterior medians and their range are recorded.

Families, hyper-priors and the hyper-posterior
----------------------------------------------
Families (hyper-parameters λ = (loc, scale)):

=============  ==========================  =================================
family         λ                           p(x | λ)
=============  ==========================  =================================
normal         μ, σ                        N(x; μ, σ²)
truncnormal    μ, σ (of the parent)        N(x; μ, σ²) / (Φ(β) − Φ(α)) on the
                                           fit prior's support [lo, hi]
lognormal      μ = log median, σ_log       N(log x; μ, σ_log²) / x
beta           mean m, sd s on [lo, hi]    Beta(a, b) with a = m'ν, b = (1−m')ν,
                                           m' = (m − lo)/(hi − lo),
                                           ν = m'(1−m')(hi − lo)²/s² − 1
=============  ==========================  =================================

(α, β = (lo − μ)/σ, (hi − μ)/σ.) ``beta`` is offered for the reefing ratio
eps on (0, 1). Hyper-priors are weak and proper: loc flat over the tests'
medians ± 10 spreads (spread = sd of the canopies' posterior medians + the
largest posterior sd; the bound keeps the truncated normal proper, whose
likelihood is flat along μ as σ → ∞); scale half-Cauchy above the floor,
p(σ) = 2/(π s₀ (1 + σ²/s₀²)), s₀ = the width of the fit prior in the family's
coordinate (else twice the tests' spread); beta also needs ν > 0.

The hyper-posterior p(λ | d) ∝ p(λ)·L(λ) is evaluated on grids in
(loc, log scale): a coarse rectangle grown until it holds every cell within
e^−20 of the maximum of the full or of any leave-one-test-out hyper-posterior,
then twice a "sheared" grid whose every log σ row has its own location range
(hierarchical posteriors are funnels: the location is known to ∝ σ + the
tests' widths). Draws are cells drawn by posterior mass, jittered uniformly
within the cell.

Choosing the family: leave-one-test-out predictive density
-----------------------------------------------------------
elpd_LOO = Σ_i log p(d_i | d_−i), with p(d_i | d_−i) = ∫ L_i(λ) p(λ | d_−i) dλ.
On the grid this needs no refit: p(λ | d_−i) ∝ p(λ | d)/L_i(λ), so::

    log p(d_i | d_−i) = logsumexp_g(log post_g) − logsumexp_g(log post_g − log L_i(λ_g))

with log post_g the cell's log mass, exactly up to the grid (tested against
refitting without test i) (the constants Z_i are the same for every family, so
the differences are meaningful). The family with the largest elpd_LOO is
chosen; all values are reported.

Correlated (n_p, expopen)
-------------------------
For each kind and stage a bivariate population with the chosen marginal
families F₁, F₂ joined by a Gaussian copula of correlation ρ (for normal or
lognormal marginals this *is* the bivariate (log-)normal)::

    p(x₁, x₂ | λ₁, λ₂, ρ) = f₁(x₁) f₂(x₂) c_ρ(q₁, q₂),   q_j = Φ⁻¹(F_j(x_j))
    log c_ρ = −½ log(1 − ρ²) − (ρ²(q₁² + q₂²) − 2ρ q₁ q₂) / (2(1 − ρ²))

reweights each canopy's *joint* (n_p, expopen) draws (prior π(n_p)·π(expopen)).
Five hyper-parameters (flat ρ on (−1, 1), the marginals' hyper-priors) are
too many for a grid: the hyper-posterior is sampled by importance sampling
from a multivariate t around its Laplace approximation (Pareto-smoothed,
PSIS), or by emcee when the smoothed weights' k̂ exceeds 0.7. The ρ = 0
model is fitted the same way to the same joint draws, and PSIS
leave-one-test-out elpd compares the two (a test whose PSIS k̂ exceeds 0.7 —
few tests, an influential one — gets its LOO term from a refit without it).
The correlation is kept when the correlated model predicts the left-out tests
better (Δelpd > 0); ρ's median and 90 % interval are reported either way.

Population predictive and the memo
----------------------------------
Predictive draws: λ from the hyper-posterior, then x from p(x | λ) (a
correlated pair jointly through the copula). Naive pooling of the per-test
draws would ignore how few tests there are; this folds the hyper-parameter
uncertainty into the tails. One row of ``memo_draws.csv`` is one parachute:
every column of its kind is a predictive draw, the correlated pair jointly, the
rest independently. The derived n and t_fp are not columns: a Monte Carlo
computes n from the row's n_p by Eq. 18 with the drag area it holds at the
disreef. Each memo entry's ``params`` are the chosen family fitted by
maximum likelihood to its predictive draws (so ``joint=False`` sampling
reproduces the predictive, hyper-uncertainty included); ``quantiles`` are the
draws' 1/5/50/95/99 %; ``criterion`` holds the elpd_LOO of every family
(and, for n_p and expopen, the correlation's). ``bounds`` are the
truncation (truncnormal), the beta's range, or else the fit prior's support;
draws are clipped to them, as :meth:`~cpas_bayes.population.memo.MemoEntry.sample` does.
The t_fp entry is ``uniform`` over the range of the per-canopy posterior
medians; its quantiles are those of the medians, which its ``criterion``
lists by test and canopy.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import optimize, special, stats

from cpas_bayes.core.errors import InputError
from cpas_bayes.population.memo import Memo, MemoEntry

STAGE_PARAMETERS = ("n_p", "n", "expopen", "ck", "tk", "eps")
DRAWN_PARAMETERS = ("n_p", "expopen", "ck", "tk", "eps")   # columns of memo_draws.csv per stage
PARACHUTE_STAGE = "parachute"
PAIR = ("n_p", "expopen")
QUANTILE_LEVELS = {"q01": 0.01, "q05": 0.05, "q50": 0.5, "q95": 0.95, "q99": 0.99}
ESS_MIN = 20.0
PARETO_K_MAX = 0.7
CRITERION_NAME = "loo_test"
METHOD = ("hierarchical population per kind/stage/parameter: per-test posterior draws reweighted by "
          "population/prior (Thrane & Talbot 2019), grid hyper-posterior with flat location and half-Cauchy "
          "scale hyper-priors, family by leave-one-test-out elpd; (n_p, expopen) Gaussian-copula pair "
          "(Laplace + PSIS importance sampling, emcee fallback) kept when its PSIS-LOO elpd beats rho = 0; "
          "population-predictive draws")

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_GRID_THRESHOLD = 20.0      # keep grid points within e^-20 of the maximum
_CHUNK_ELEMENTS = 2_000_000  # batch size of the reweighting sums (floats per temporary)


class PoolWarning(UserWarning):
    """A pooled estimate to look at: low effective sample size, high Pareto k, grid edge."""


# ---------------------------------------------------------------------------
# families


def _log_normal_mass(alpha, beta):
    """log(Φ(β) − Φ(α)) for α < β, elementwise and stable in both tails."""
    alpha, beta = np.broadcast_arrays(np.asarray(alpha, float), np.asarray(beta, float))
    upper = alpha > 0
    lo = np.where(upper, -beta, alpha)
    hi = np.where(upper, -alpha, beta)
    log_hi, log_lo = special.log_ndtr(hi), special.log_ndtr(lo)
    with np.errstate(divide="ignore", invalid="ignore"):
        return log_hi + np.log1p(-np.exp(log_lo - log_hi))


def _half_cauchy_logpdf(sigma, s0):
    """log of p(σ) = 2/(π s₀ (1 + σ²/s₀²)), σ > 0."""
    return math.log(2.0 / (math.pi * s0)) - np.log1p((sigma / s0) ** 2)


def _gauss_kernel(z, loc, scale):
    """−½((z − loc)/scale)², built in place (the reweighting sums' largest temporary)."""
    out = np.asarray(np.subtract(z, loc))
    if out.ndim and out.shape == np.broadcast_shapes(out.shape, np.shape(scale)):
        out /= scale
    else:
        out = np.asarray(out / scale)
    np.square(out, out=out)
    out *= -0.5
    return out


class Family:
    """A two-parameter population family; every method broadcasts over x and λ = (loc, scale).

    The log density splits as
    ``log p(x | λ) = kernel(features(x), λ) + normaliser(λ) + base(x)``:
    ``features`` and ``base`` depend on x only and are computed once per test,
    ``normaliser`` on λ only, so the reweighting sums over many λ cost a few
    array operations each.
    """

    name = ""
    hyper_names = ("loc", "scale")

    def __init__(self, low=-math.inf, high=math.inf):
        self.low, self.high = float(low), float(high)

    def __repr__(self):
        return f"{type(self).__name__}({self.low:g}, {self.high:g})"

    # coordinates
    def coordinate(self, x):
        """The coordinate in which ``loc`` lives (x, or log x for the lognormal)."""
        return np.asarray(x, float)

    def loc_limits(self):
        """Hard limits of ``loc`` (beta: the mean stays inside the support)."""
        return (-math.inf, math.inf)

    def feasible(self, loc, scale):
        return np.isfinite(loc) & (scale > 0)

    # densities
    def features(self, x):
        return np.asarray(x, float)

    def base(self, x):
        x = np.asarray(x, float)
        return np.where((x >= self.low) & (x <= self.high), 0.0, -np.inf)

    def kernel(self, features, loc, scale):
        raise NotImplementedError

    def normaliser(self, loc, scale):
        raise NotImplementedError

    def core(self, features, loc, scale):
        return self.kernel(features, loc, scale) + self.normaliser(loc, scale)

    def logpdf(self, x, loc, scale):
        return self.core(self.features(x), loc, scale) + self.base(x)

    def normal_score(self, x, loc, scale):
        """q = Φ⁻¹(F(x | λ)), the Gaussian-copula coordinate."""
        u = np.clip(self.cdf(x, loc, scale), 1e-15, 1 - 1e-15)
        return special.ndtri(u)

    def cdf(self, x, loc, scale):
        raise NotImplementedError

    def ppf(self, u, loc, scale):
        raise NotImplementedError

    def moments(self, loc, scale):
        """Population mean and standard deviation at λ."""
        raise NotImplementedError

    # the memo
    def memo_params(self, loc, scale):
        raise NotImplementedError

    def fit(self, x, loc_range=(-math.inf, math.inf)):
        """(loc, scale) by maximum likelihood to draws ``x`` (``loc`` kept in ``loc_range``)."""
        raise NotImplementedError


class NormalFamily(Family):
    name = "normal"
    hyper_names = ("mu", "sigma")

    def kernel(self, z, loc, scale):
        return _gauss_kernel(z, loc, scale)

    def normaliser(self, loc, scale):
        return -np.log(scale) - _LOG_SQRT_2PI

    def normal_score(self, x, loc, scale):
        return (np.asarray(x, float) - loc) / scale

    def cdf(self, x, loc, scale):
        return special.ndtr((np.asarray(x, float) - loc) / scale)

    def ppf(self, u, loc, scale):
        return loc + scale * special.ndtri(u)

    def moments(self, loc, scale):
        return np.asarray(loc, float), np.asarray(scale, float)

    def memo_params(self, loc, scale):
        return {"mu": float(loc), "sigma": float(scale)}

    def fit(self, x, loc_range=(-math.inf, math.inf)):
        return float(np.clip(np.mean(x), *loc_range)), float(np.std(x))


class TruncNormalFamily(Family):
    name = "truncnormal"
    hyper_names = ("mu", "sigma")

    def _limits(self, loc, scale):
        return (self.low - loc) / scale, (self.high - loc) / scale

    def kernel(self, z, loc, scale):
        return _gauss_kernel(z, loc, scale)

    def normaliser(self, loc, scale):
        alpha, beta = self._limits(loc, scale)
        return -np.log(scale) - _LOG_SQRT_2PI - _log_normal_mass(alpha, beta)

    def cdf(self, x, loc, scale):
        alpha, beta = self._limits(loc, scale)
        return stats.truncnorm.cdf(x, alpha, beta, loc=loc, scale=scale)

    def ppf(self, u, loc, scale):
        alpha, beta = self._limits(loc, scale)
        return stats.truncnorm.ppf(u, alpha, beta, loc=loc, scale=scale)

    def moments(self, loc, scale):
        """Mean μ + σ·(φ(α) − φ(β))/Z and variance σ²·[1 + (αφ(α) − βφ(β))/Z − ((φ(α) − φ(β))/Z)²],
        Z = Φ(β) − Φ(α), with the ratios φ/Z formed in logs (stable in the tails)."""
        loc, scale = np.asarray(loc, float), np.asarray(scale, float)
        alpha, beta = self._limits(loc, scale)
        log_mass = _log_normal_mass(alpha, beta)

        def ratio(t):   # φ(t)/Z and t·φ(t)/Z, 0 at t = ±inf
            finite = np.isfinite(t)
            safe = np.where(finite, t, 0.0)
            r = np.where(finite, np.exp(-0.5 * safe * safe - _LOG_SQRT_2PI - log_mass), 0.0)
            return r, r * safe

        ra, ta = ratio(alpha)
        rb, tb = ratio(beta)
        shift = ra - rb
        var = np.maximum(1.0 + ta - tb - shift * shift, 0.0)
        return loc + scale * shift, scale * np.sqrt(var)

    def memo_params(self, loc, scale):
        return {"mu": float(loc), "sigma": float(scale)}

    def fit(self, x, loc_range=(-math.inf, math.inf)):
        x = np.asarray(x, float)
        x = x[(x >= self.low) & (x <= self.high)]

        def nll(p):
            value = -np.mean(self.core(x, p[0], math.exp(p[1])))
            return value if np.isfinite(value) else 1e300

        lo = loc_range[0] if math.isfinite(loc_range[0]) else None
        hi = loc_range[1] if math.isfinite(loc_range[1]) else None
        start = np.array([float(np.clip(np.mean(x), *loc_range)), math.log(max(np.std(x), 1e-12))])
        width = self.high - self.low
        top = math.log(10 * width) if math.isfinite(width) else None
        res = optimize.minimize(nll, start, method="Nelder-Mead", bounds=[(lo, hi), (None, top)],
                                options={"xatol": 1e-8, "fatol": 1e-10, "maxiter": 4000})
        return float(res.x[0]), float(math.exp(res.x[1]))


class LogNormalFamily(Family):
    name = "lognormal"
    hyper_names = ("mu_log", "sigma_log")

    def __init__(self, low=0.0, high=math.inf):
        super().__init__(max(low, 0.0), high)

    def coordinate(self, x):
        x = np.asarray(x, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(x > 0, np.log(np.where(x > 0, x, 1.0)), -np.inf)

    def features(self, x):
        return self.coordinate(x)

    def base(self, x):
        x = np.asarray(x, float)
        ok = x > 0
        return np.where(ok, -np.log(np.where(ok, x, 1.0)), -np.inf)

    def kernel(self, z, loc, scale):
        return _gauss_kernel(z, loc, scale)

    def normaliser(self, loc, scale):
        return -np.log(scale) - _LOG_SQRT_2PI

    def normal_score(self, x, loc, scale):
        return (self.coordinate(x) - loc) / scale

    def cdf(self, x, loc, scale):
        return special.ndtr((self.coordinate(x) - loc) / scale)

    def ppf(self, u, loc, scale):
        return np.exp(loc + scale * special.ndtri(u))

    def moments(self, loc, scale):
        mean = np.exp(loc + 0.5 * np.square(scale))
        return mean, mean * np.sqrt(np.expm1(np.square(scale)))

    def memo_params(self, loc, scale):
        return {"median": float(math.exp(loc)), "sigma_log": float(scale)}

    def fit(self, x, loc_range=(-math.inf, math.inf)):
        z = self.coordinate(x)
        return float(np.clip(np.mean(z), *loc_range)), float(np.std(z))


class BetaFamily(Family):
    """Beta on [low, high] (finite), parameterised by its mean and standard deviation."""

    name = "beta"
    hyper_names = ("mean", "sd")

    def __init__(self, low=0.0, high=1.0):
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError("a beta family needs finite bounds low < high")
        super().__init__(low, high)
        self.width = self.high - self.low

    def loc_limits(self):
        return (self.low, self.high)

    def _shape(self, loc, scale):
        """Beta shapes (a, b) from mean and sd; ν = m'(1−m')/s'² − 1."""
        m = (np.asarray(loc, float) - self.low) / self.width
        s = np.asarray(scale, float) / self.width
        with np.errstate(divide="ignore", invalid="ignore"):
            nu = m * (1 - m) / (s * s) - 1.0
        return m * nu, (1 - m) * nu

    def feasible(self, loc, scale):
        a, b = self._shape(loc, scale)
        return (loc > self.low) & (loc < self.high) & (scale > 0) & (a > 0) & (b > 0)

    def features(self, x):
        u = (np.asarray(x, float) - self.low) / self.width
        inside = (u > 0) & (u < 1)
        safe = np.where(inside, u, 0.5)
        return np.stack([np.log(safe), np.log1p(-safe)])

    def base(self, x):
        u = (np.asarray(x, float) - self.low) / self.width
        return np.where((u > 0) & (u < 1), -math.log(self.width), -np.inf)

    def kernel(self, features, loc, scale):
        a, b = self._shape(loc, scale)
        return (a - 1) * features[0] + (b - 1) * features[1]

    def normaliser(self, loc, scale):
        a, b = self._shape(loc, scale)
        return -special.betaln(a, b)

    def logpdf(self, x, loc, scale):
        f = self.features(x)
        return self.core(f, loc, scale) + self.base(x)

    def cdf(self, x, loc, scale):
        a, b = self._shape(loc, scale)
        u = np.clip((np.asarray(x, float) - self.low) / self.width, 0.0, 1.0)
        return special.betainc(a, b, u)

    def ppf(self, u, loc, scale):
        a, b = self._shape(loc, scale)
        return self.low + self.width * special.betaincinv(a, b, u)

    def moments(self, loc, scale):
        return np.asarray(loc, float), np.asarray(scale, float)

    def memo_params(self, loc, scale):
        a, b = self._shape(loc, scale)
        return {"a": float(a), "b": float(b)}

    def fit(self, x, loc_range=(-math.inf, math.inf)):
        u = np.clip((np.asarray(x, float) - self.low) / self.width, 1e-12, 1 - 1e-12)
        a, b, _, _ = stats.beta.fit(u, floc=0.0, fscale=1.0)
        mean = a / (a + b)
        sd = math.sqrt(a * b / ((a + b) ** 2 * (a + b + 1)))
        return self.low + self.width * mean, self.width * sd


_FAMILY_CLASSES = {"normal": NormalFamily, "truncnormal": TruncNormalFamily, "lognormal": LogNormalFamily,
                   "beta": BetaFamily}
FAMILY_NAMES = tuple(_FAMILY_CLASSES)


def make_family(name, low=-math.inf, high=math.inf):
    """The family ``name`` on the support [low, high] (beta defaults to (0, 1) if unbounded)."""
    if isinstance(name, Family):
        return name
    if name not in _FAMILY_CLASSES:
        raise ValueError(f"unknown family {name!r}; use one of {', '.join(FAMILY_NAMES)}")
    if name == "beta" and not (math.isfinite(low) and math.isfinite(high)):
        low, high = 0.0, 1.0
    if name == "lognormal":
        return LogNormalFamily(max(low, 0.0), high)
    return _FAMILY_CLASSES[name](low, high)


# ---------------------------------------------------------------------------
# per-test draws


@dataclass
class PerTestDraws:
    """Posterior draws of one parameter (or a pair) from T tests, stacked for reweighting.

    ``values`` (T, C, S) — or (T, C, S, 2) for a pair — holds the draws of the
    C canopies of each test (tests with fewer canopies are padded and masked);
    ``log_prior`` (T, C, S) is the log of the fit's prior density at those
    draws (the pair's joint prior for a pair); ``mask`` (T, C) marks real canopies.
    """

    values: np.ndarray
    log_prior: np.ndarray
    mask: np.ndarray
    tests: list
    canopies: list = field(default_factory=list)   # per test: canopy labels

    @property
    def n_tests(self):
        return self.values.shape[0]

    @property
    def n_samples(self):
        return self.values.shape[2]

    @classmethod
    def from_arrays(cls, samples_per_test, log_prior_per_test, rng=None, max_samples=None, tests=None):
        """Stack per-test arrays (S,) or (C, S) — or (S, 2) / (C, S, 2) for a pair.

        Tests with more than S_common = min(max_samples, smallest S) draws are
        subsampled without replacement (``rng``), the same draws for every
        canopy of a test.
        """
        if len(samples_per_test) != len(log_prior_per_test):
            raise ValueError("one log-prior array per test is needed")
        if len(samples_per_test) == 0:
            raise ValueError("no tests to pool")
        pair = None
        vals, lps = [], []
        for x, lp in zip(samples_per_test, log_prior_per_test):
            x, lp = np.asarray(x, float), np.asarray(lp, float)
            if pair is None:
                pair = x.ndim == lp.ndim + 1
            if pair:
                x = x if x.ndim == 3 else x[None]
            else:
                x = x if x.ndim == 2 else x[None]
            lp = lp if lp.ndim == 2 else lp[None]
            if x.shape[:2] != lp.shape:
                raise ValueError(f"draws {x.shape} and log prior {lp.shape} of a test do not match")
            vals.append(x)
            lps.append(lp)
        s_common = min(v.shape[1] for v in vals)
        if max_samples is not None:
            s_common = min(s_common, int(max_samples))
        rng = rng if rng is not None else np.random.default_rng(0)
        c_max = max(v.shape[0] for v in vals)
        T = len(vals)
        shape = (T, c_max, s_common) + ((2,) if pair else ())
        values = np.empty(shape)
        log_prior = np.zeros((T, c_max, s_common))
        mask = np.zeros((T, c_max), dtype=bool)
        for i, (x, lp) in enumerate(zip(vals, lps)):
            n = x.shape[1]
            pick = np.sort(rng.choice(n, size=s_common, replace=False)) if n > s_common else np.arange(n)
            c = x.shape[0]
            values[i, :c] = x[:, pick]
            values[i, c:] = x[:1, pick]       # placeholders, masked out
            log_prior[i, :c] = lp[:, pick]
            mask[i, :c] = True
        tests = list(tests) if tests is not None else [f"test {i + 1}" for i in range(T)]
        return cls(values, log_prior, mask, tests, [[str(c + 1) for c in range(v.shape[0])] for v in vals])

    def select(self, which):
        """The same draws for the tests ``which`` (an index array or boolean mask)."""
        idx = np.arange(self.n_tests)[which]
        return PerTestDraws(self.values[idx], self.log_prior[idx], self.mask[idx],
                            [self.tests[i] for i in idx], [self.canopies[i] for i in idx] if self.canopies else [])

    def summaries(self, family):
        """Per-canopy posterior median and sd in the family's coordinate (for grid ranges)."""
        z = family.coordinate(self.values)
        z = z[self.mask]                                    # (units, S)
        return np.median(z, axis=-1), np.std(z, axis=-1)


# ---------------------------------------------------------------------------
# reweighting sums


def _prepare(data: PerTestDraws, family: Family):
    """Features of the draws and the λ-independent part of log p(x|λ)/π(x), masked."""
    feats = family.features(data.values)
    base = family.base(data.values) - data.log_prior
    base = np.where(data.mask[..., None], base, 0.0)
    if not np.all(np.isfinite(base[data.mask])):
        bad = np.argwhere(~np.isfinite(base) & data.mask[..., None])[0]
        raise ValueError(f"test {data.tests[bad[0]]}: a posterior draw lies outside the {family.name} family's "
                         "support or has zero prior density")
    return feats, base


def _logmeanexp(a):
    """log mean exp along the last axis (−inf where every term is −inf); overwrites ``a``."""
    m = np.max(a, axis=-1, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    a -= m
    np.exp(a, out=a)
    with np.errstate(divide="ignore"):
        return np.log(np.mean(a, axis=-1)) + m[..., 0]


def _with_batch_axis(features):
    """Features (T, C, S) — or (k, T, C, S) for a family with k feature arrays — with a λ-batch axis."""
    return features[None] if features.ndim == 3 else features[:, None]


def log_test_likelihoods(data: PerTestDraws, family: Family, loc, scale, prepared=None):
    """log L_i(λ) − log Z_i for every λ = (loc[b], scale[b]) and test i: array (B, T).

    L_i(λ)/Z_i = Π_c (1/S) Σ_s p(x_{i,c,s} | λ)/π_i(x_{i,c,s}) (canopies reweighted
    separately, see the module docstring); the family's normaliser, the same
    for every draw, is added after the sums.
    """
    feats, base = prepared if prepared is not None else _prepare(data, family)
    feats = _with_batch_axis(feats)
    loc = np.atleast_1d(np.asarray(loc, float))
    scale = np.atleast_1d(np.asarray(scale, float))
    T, C, S = data.values.shape[:3]
    n_canopies = data.mask.sum(axis=1)
    out = np.empty((loc.size, T))
    batch = max(1, _CHUNK_ELEMENTS // (T * C * S))
    for start in range(0, loc.size, batch):
        sl = slice(start, start + batch)
        lw = family.kernel(feats, loc[sl][:, None, None, None], scale[sl][:, None, None, None])
        lw += base
        per_canopy = _logmeanexp(lw)                                          # (b, T, C)
        out[sl] = np.where(data.mask[None], per_canopy, 0.0).sum(axis=2)
    return out + n_canopies[None, :] * family.normaliser(loc, scale)[:, None]


def _ess_from_log_weights(lw):
    """(Σ w)²/Σ w² along the last axis, from log weights."""
    return np.exp(2 * special.logsumexp(lw, axis=-1) - special.logsumexp(2 * lw, axis=-1))


def effective_sample_sizes(data: PerTestDraws, family: Family, loc, scale):
    """ESS (T, C) of each canopy's weights w_s = p(x_s|λ)/π(x_s) at one λ (NaN where no canopy)."""
    feats, base = _prepare(data, family)
    ess = _ess_from_log_weights(family.kernel(feats, loc, scale) + base)
    return np.where(data.mask, ess, np.nan)


def scale_floor(data: PerTestDraws, family: Family, ess_min=ESS_MIN):
    """Smallest population scale σ_floor the reweighting sums can resolve (the hyper-prior starts there).

    A canopy whose posterior (sd w in the family's coordinate, S draws) is
    reweighted by a population of scale σ ≪ w keeps an effective sample size
    of about S·√2·σ/w (Gaussian shapes). Below σ = ess_min·w/(√2·S) the sums
    would rest on fewer than ``ess_min`` draws and turn into spikes at single
    draws; narrower populations cannot be told apart from σ_floor with these
    posteriors anyway. σ_floor is that value for the widest canopy posterior.
    """
    _, widths = data.summaries(family)
    return float(np.max(widths)) * ess_min / (math.sqrt(2.0) * data.n_samples)


# ---------------------------------------------------------------------------
# one parameter: grid hyper-posterior


@dataclass
class ParameterPool:
    """Hyper-posterior and population predictive of one parameter under one family."""

    family: Family
    hyper_draws: np.ndarray        # (N, 2): loc, scale
    hyper_median: np.ndarray       # (2,)
    elpd_loo: float
    elpd_pointwise: np.ndarray     # (T,)
    ess: np.ndarray                # (T,) smallest canopy ESS of each test at hyper_median
    low_ess: list                  # "test canopy" labels with ESS < ess_min
    mean_draws: np.ndarray         # (N,) population mean at each hyper draw
    sd_draws: np.ndarray           # (N,) population sd at each hyper draw
    predictive: np.ndarray         # (N,) population-predictive draws
    tests: list
    scale_floor: float = 0.0       # lower end of the scale hyper-prior (see :func:`scale_floor`)
    grid: dict = field(default_factory=dict, repr=False)
    notes: list = field(default_factory=list)

    @property
    def hyper_names(self):
        return self.family.hyper_names

    def interval(self, what="mean", level=0.90):
        """(low, median, high) of the hyper-posterior of the population ``mean`` or ``sd``."""
        x = self.mean_draws if what == "mean" else self.sd_draws
        a = (1 - level) / 2
        return tuple(float(v) for v in np.quantile(x, [a, 0.5, 1 - a]))


def _default_hyper_scale(data, family):
    medians, widths = data.summaries(family)
    spread = float(np.std(medians)) if medians.size > 1 else 0.0
    value = 2.0 * (spread + float(np.median(widths)))
    return value if value > 0 else 1.0


_LOC_BOX_SPREADS = 10.0   # the flat location hyper-prior spans the tests' medians ± 10 spreads


def _location_prior_box(data, family):
    """Support of the flat hyper-prior on ``loc``: the tests' medians ± 10 spreads, within the family's limits.

    spread = sd of the canopies' posterior medians + their largest posterior sd
    (in the family's coordinate). Bounding the location keeps the hyper-posterior
    proper where the likelihood is flat along it (a truncated normal with
    σ → ∞ tends to the uniform whatever μ is).
    """
    medians, widths = data.summaries(family)
    spread = (float(np.std(medians)) if medians.size > 1 else 0.0) + float(np.max(widths))
    if spread <= 0:
        spread = 1e-3 * max(1.0, float(np.max(np.abs(medians))))
    lo, hi = float(np.min(medians)) - _LOC_BOX_SPREADS * spread, float(np.max(medians)) + _LOC_BOX_SPREADS * spread
    lim = family.loc_limits()
    margin = 1e-9 * (lim[1] - lim[0]) if math.isfinite(lim[1] - lim[0]) else 0.0
    return (max(lo, lim[0] + margin), min(hi, lim[1] - margin)), spread, medians


def _initial_box(data, family, floor):
    """First grid: the medians ± 4 spreads (inside the prior box); σ from max(1e-3·6 spreads, σ_floor)
    to 6 spreads."""
    (lo_box, hi_box), spread, medians = _location_prior_box(data, family)
    lo_loc = max(float(np.min(medians)) - 4 * spread, lo_box)
    hi_loc = min(float(np.max(medians)) + 4 * spread, hi_box)
    scale_hi = 6 * spread
    if isinstance(family, BetaFamily):
        scale_hi = min(scale_hi, 0.5 * family.width)
    scale_lo = max(1e-3 * scale_hi, floor)
    scale_hi = max(scale_hi, 10 * scale_lo)
    return [lo_loc, hi_loc, math.log(scale_lo), math.log(scale_hi)], (lo_box, hi_box)


def _evaluate_points(data, family, prepared, hyper_scale, loc, log_scale, dloc, dls, row):
    """Hyper-posterior mass of grid cells centred at (loc, log σ) with sides (dloc, dls).

    log_post = log p(λ) + Σ_i log L_i(λ) + log(cell area): flat loc,
    half-Cauchy σ, and the Jacobian σ of a grid uniform in log σ.
    """
    scale = np.exp(log_scale)
    ok = family.feasible(loc, scale)
    log_lik = np.full((loc.size, data.n_tests), -np.inf)
    if ok.any():
        log_lik[ok] = log_test_likelihoods(data, family, loc[ok], scale[ok], prepared)
    log_hyper_prior = _half_cauchy_logpdf(scale, hyper_scale) + log_scale
    total = log_lik.sum(axis=1)
    log_post = np.where(ok & np.isfinite(total), log_hyper_prior + total + np.log(dloc * dls), -np.inf)
    return {"loc": loc, "log_scale": log_scale, "scale": scale, "dloc": dloc, "dls": dls, "row": row,
            "log_lik": log_lik, "log_post": log_post}


def _rectangular_grid(data, family, prepared, hyper_scale, box, n):
    locs = np.linspace(box[0], box[1], n)
    log_scales = np.linspace(box[2], box[3], n)
    loc, log_scale = (a.ravel() for a in np.meshgrid(locs, log_scales, indexing="ij"))
    row = np.tile(np.arange(n), n)
    dloc = np.full(loc.size, (box[1] - box[0]) / (n - 1))
    return _evaluate_points(data, family, prepared, hyper_scale, loc, log_scale, dloc,
                            (box[3] - box[2]) / (n - 1), row)


def _occupied(g):
    """Cells within e^−20 of the maximum of the full or of any leave-one-test-out hyper-posterior."""
    ok = np.isfinite(g["log_post"])
    keep = np.zeros(ok.shape, dtype=bool)
    lp = g["log_post"][ok]
    loo = lp[:, None] - g["log_lik"][ok]
    keep[ok] = (lp > lp.max() - _GRID_THRESHOLD) | np.any(loo > loo.max(axis=0) - _GRID_THRESHOLD, axis=1)
    return keep


def _sheared_grid(data, family, prepared, hyper_scale, g, loc_box, log_floor, n):
    """A finer grid with its own location range in every log σ row.

    Hierarchical hyper-posteriors are funnels: the location is known to a
    width ∝ σ + (the tests' own widths), so one rectangle resolves either the
    narrow neck or the wide mouth, not both. Each row of ``g``'s occupied cells
    gives a location interval (padded by that row's cell); the n new rows
    (uniform in log σ over the occupied rows, padded by one) take the union of
    the intervals of the two source rows around them, with n cells each.
    """
    keep = _occupied(g)
    rows = np.unique(g["row"][keep])
    ls_rows = np.array([g["log_scale"][g["row"] == r][0] for r in rows])
    lo_rows = np.array([np.min(g["loc"][keep & (g["row"] == r)] - g["dloc"][keep & (g["row"] == r)])
                        for r in rows])
    hi_rows = np.array([np.max(g["loc"][keep & (g["row"] == r)] + g["dloc"][keep & (g["row"] == r)])
                        for r in rows])
    ls_lo, ls_hi = max(ls_rows.min() - g["dls"], log_floor), ls_rows.max() + g["dls"]
    new_ls = np.linspace(ls_lo, ls_hi, n)
    # source rows bracketing each new row (the nearest at the ends)
    j1 = np.clip(np.searchsorted(ls_rows, new_ls), 0, rows.size - 1)
    j0 = np.clip(j1 - 1, 0, rows.size - 1)
    lo = np.maximum(np.minimum(lo_rows[j0], lo_rows[j1]), loc_box[0])
    hi = np.minimum(np.maximum(hi_rows[j0], hi_rows[j1]), loc_box[1])
    frac = np.linspace(0.0, 1.0, n)
    loc = (lo[:, None] + (hi - lo)[:, None] * frac[None, :]).ravel()
    log_scale = np.repeat(new_ls, n)
    dloc = np.repeat((hi - lo) / (n - 1), n)
    row = np.repeat(np.arange(n), n)
    return _evaluate_points(data, family, prepared, hyper_scale, loc, log_scale, dloc, new_ls[1] - new_ls[0], row)


def _grid_hyper_posterior(data, family, prepared, hyper_scale, floor=0.0, coarse=28, fine=40, max_expansions=5):
    """Coarse rectangular grid grown until it holds the mass, then two sheared refinements.

    "Occupied" cells are those within e^−20 of the maximum of the full
    hyper-posterior *or of any leave-one-test-out one* (log post − log L_i), so
    that the final grid also holds each p(λ | d_−i) the LOO criterion
    integrates over (with few tests they can sit far from p(λ | d)). The
    coarse grid grows (by its own width) on any side where an occupied cell
    touches the edge — up to the location prior's box, and not on the
    small-scale side, where the half-Cauchy prior times the log-grid Jacobian σ
    makes the mass vanish. Then :func:`_sheared_grid` twice (the second pass
    sharpens the row intervals the coarse cells could only bracket).
    """
    box, loc_box = _initial_box(data, family, floor)
    log_floor = box[2]
    notes = []
    for attempt in range(max_expansions + 1):
        g = _rectangular_grid(data, family, prepared, hyper_scale, box, coarse)
        if not np.isfinite(g["log_post"]).any():
            raise ValueError(f"the {family.name} population has zero likelihood everywhere on the grid")
        il, js = np.nonzero(_occupied(g).reshape(coarse, coarse))
        width_loc, width_ls = box[1] - box[0], box[3] - box[2]
        grow = False
        if il.min() == 0 and box[0] > loc_box[0]:
            box[0], grow = max(box[0] - width_loc, loc_box[0]), True
        if il.max() == coarse - 1 and box[1] < loc_box[1]:
            box[1], grow = min(box[1] + width_loc, loc_box[1]), True
        if js.max() == coarse - 1:
            box[3], grow = box[3] + 0.5 * width_ls, True
        if not grow:
            break
        if attempt == max_expansions:
            notes.append(f"{family.name}: hyper-posterior of the scale still reaches the grid edge after "
                         f"{max_expansions} expansions (weakly identified)")
    for _ in range(2):
        g = _sheared_grid(data, family, prepared, hyper_scale, g, loc_box, log_floor, fine)
    g["box"] = [float(np.min(g["loc"])), float(np.max(g["loc"])), float(np.min(g["log_scale"])),
                float(np.max(g["log_scale"]))]
    g["loc_prior_box"] = loc_box
    g["log_floor"] = log_floor
    return g, notes


def _grid_loo(log_post, log_lik):
    """Exact leave-one-test-out elpd on the grid: log Σ post − log Σ post/L_i, per test."""
    ok = np.isfinite(log_post)
    lp, ll = log_post[ok], log_lik[ok]
    return special.logsumexp(lp) - special.logsumexp(lp[:, None] - ll, axis=0)


def _draw_from_grid(g, family, n, rng):
    """Cells drawn by posterior mass, each draw jittered uniformly within its cell."""
    ok = np.isfinite(g["log_post"])
    idx = np.flatnonzero(ok)
    p = np.exp(g["log_post"][idx] - np.max(g["log_post"][idx]))
    pick = idx[rng.choice(idx.size, size=n, p=p / p.sum())]
    loc = g["loc"][pick] + g["dloc"][pick] * (rng.uniform(size=n) - 0.5)
    loc = np.clip(loc, *g.get("loc_prior_box", (-np.inf, np.inf)))
    scale = np.exp(np.maximum(g["log_scale"][pick] + g["dls"] * (rng.uniform(size=n) - 0.5),
                              g.get("log_floor", -np.inf)))
    bad = ~family.feasible(loc, scale)
    loc[bad], scale[bad] = g["loc"][pick[bad]], g["scale"][pick[bad]]
    return np.column_stack([loc, scale])


def _hyper_median(family, draws):
    med = np.median(draws, axis=0)
    if family.feasible(med[0], med[1]):
        return med
    return draws[np.argmin(np.sum(((draws - med) / draws.std(axis=0)) ** 2, axis=1))]


def _pool_stacked(data: PerTestDraws, family: Family, rng, hyper_scale=None, n_draws=4000, ess_min=ESS_MIN):
    """Grid hyper-posterior, exact grid LOO, hyper draws, ESS and predictive of one family (see the module doc)."""
    prepared = _prepare(data, family)
    hyper_scale = hyper_scale if hyper_scale is not None else _default_hyper_scale(data, family)
    floor = scale_floor(data, family, ess_min)
    g, notes = _grid_hyper_posterior(data, family, prepared, hyper_scale, floor)
    elpd = _grid_loo(g["log_post"], g["log_lik"])
    hyper = _draw_from_grid(g, family, n_draws, rng)
    med = _hyper_median(family, hyper)
    ess_canopy = effective_sample_sizes(data, family, med[0], med[1])
    low = [f"{t} {c}" for t, cs, es in zip(data.tests, _canopy_labels(data), ess_canopy)
           for c, e in zip(cs, es) if e < ess_min]
    mean, sd = family.moments(hyper[:, 0], hyper[:, 1])
    predictive = family.ppf(rng.uniform(size=n_draws), hyper[:, 0], hyper[:, 1])
    return ParameterPool(family=family, hyper_draws=hyper, hyper_median=med, elpd_loo=float(elpd.sum()),
                         elpd_pointwise=elpd, ess=np.nanmin(ess_canopy, axis=1), low_ess=low,
                         mean_draws=np.asarray(mean, float), sd_draws=np.asarray(sd, float),
                         predictive=np.asarray(predictive, float), tests=list(data.tests), scale_floor=floor,
                         grid=g, notes=notes)


def _canopy_labels(data):
    return data.canopies if data.canopies else [[str(c + 1) for c in range(int(m.sum()))] for m in data.mask]


def pool_parameter(samples_per_test, log_prior_per_test, family, rng, *, bounds=(-math.inf, math.inf),
                   hyper_scale=None, n_draws=4000, max_samples=500, ess_min=ESS_MIN, tests=None) -> ParameterPool:
    """Population of one parameter from per-test posterior draws, under one ``family``.

    ``samples_per_test[i]``: test i's draws, (S,) or (C, S) for C canopies that
    share the draw index; ``log_prior_per_test[i]``: log π_i at those draws.
    ``bounds``: the family's support (truncation of ``truncnormal``, range of
    ``beta``). ``hyper_scale``: s₀ of the half-Cauchy prior on the scale (default:
    twice the spread of the tests' medians plus their typical width).
    Returns a :class:`ParameterPool`; see the module docstring for the method.
    A test whose effective sample size at the inferred population is below
    ``ess_min`` is listed in ``low_ess`` and warned about (:class:`PoolWarning`).
    """
    data = samples_per_test if isinstance(samples_per_test, PerTestDraws) else PerTestDraws.from_arrays(
        samples_per_test, log_prior_per_test, rng, max_samples, tests)
    fam = make_family(family, *bounds)
    pool = _pool_stacked(data, fam, rng, hyper_scale, n_draws, ess_min)
    if pool.low_ess:
        warnings.warn(f"ESS < {ess_min:g} at the inferred {fam.name} population for {', '.join(pool.low_ess)}: "
                      "their reweighting sums are noisy", PoolWarning, stacklevel=2)
    return pool


@dataclass
class FamilySelection:
    """Every candidate family's pool, their elpd_LOO and the chosen family."""

    pools: dict
    criterion: dict          # family name -> elpd_LOO (sum over tests)
    chosen: str

    @property
    def pool(self) -> ParameterPool:
        return self.pools[self.chosen]


def select_family(samples_per_test, log_prior_per_test, families, rng, *, bounds=(-math.inf, math.inf),
                  hyper_scale=None, n_draws=4000, max_samples=500, ess_min=ESS_MIN, tests=None) -> FamilySelection:
    """Pool under each of ``families`` on the same draws; choose the largest leave-one-test-out elpd.

    ``bounds`` and ``hyper_scale`` may be one value for all families or
    {family name: value}. A family that cannot describe the draws (draws
    outside its support) is skipped with a :class:`PoolWarning`.
    """
    data = samples_per_test if isinstance(samples_per_test, PerTestDraws) else PerTestDraws.from_arrays(
        samples_per_test, log_prior_per_test, rng, max_samples, tests)
    pools = {}
    for name in families:
        fam_bounds = bounds.get(name, (-math.inf, math.inf)) if isinstance(bounds, dict) else bounds
        fam = make_family(name, *fam_bounds)
        s0 = hyper_scale.get(fam.name) if isinstance(hyper_scale, dict) else hyper_scale
        try:
            pools[fam.name] = _pool_stacked(data, fam, rng, s0, n_draws, ess_min)
        except ValueError as exc:
            warnings.warn(f"{fam.name} family skipped: {exc}", PoolWarning, stacklevel=2)
    if not pools:
        raise ValueError("no candidate family could describe the draws")
    criterion = {k: p.elpd_loo for k, p in pools.items()}
    chosen = max(criterion, key=criterion.get)
    return FamilySelection(pools, criterion, chosen)


# ---------------------------------------------------------------------------
# the (n_p, expopen) pair: Gaussian copula


@dataclass
class PairPool:
    """Correlated population of two parameters (a Gaussian copula of two chosen marginals)."""

    names: tuple
    families: tuple                 # (Family, Family)
    hyper_draws: np.ndarray         # (M, 5): loc1, scale1, loc2, scale2, rho
    rho_median: float
    rho_interval: tuple             # 5 % and 95 %
    elpd_correlated: float
    elpd_independent: float
    elpd_diff_se: float
    pareto_k: np.ndarray            # (T,) of the correlated model's PSIS-LOO (tests above 0.7 are refitted)
    pareto_k_independent: np.ndarray
    keep: bool
    predictive: np.ndarray          # (N, 2) from the correlated model
    sampler: dict                   # per model: sampler, its diagnostic, tests whose LOO term was refitted
    tests: list

    @property
    def elpd_diff(self):
        return self.elpd_correlated - self.elpd_independent

    def criterion(self):
        """The correlation's part of a memo entry's criterion table."""
        return {"with": "", "rho": self.rho_median, "rho_q05": self.rho_interval[0],
                "rho_q95": self.rho_interval[1], "elpd_correlated": self.elpd_correlated,
                "elpd_independent": self.elpd_independent, "elpd_diff_se": self.elpd_diff_se,
                "kept": bool(self.keep)}


class _PairPosterior:
    """Vectorised log posterior of θ = (loc₁, log s₁, loc₂, log s₂[, atanh ρ])."""

    def __init__(self, data, families, hyper_scales, boxes, correlated):
        self.data, self.families, self.correlated = data, families, correlated
        self.hyper_scales, self.boxes = hyper_scales, boxes
        self.ndim = 5 if correlated else 4
        self.feats = [f.features(data.values[..., j]) for j, f in enumerate(families)]
        base = sum(f.base(data.values[..., j]) for j, f in enumerate(families)) - data.log_prior
        self.base = np.where(data.mask[..., None], base, 0.0)
        if not np.all(np.isfinite(self.base[data.mask])):
            raise ValueError("pair draws outside a marginal family's support")
        self.mask = data.mask[None, :, :, None]
        self.n_canopies = data.mask.sum(axis=1)
        T, C, S = data.values.shape[:3]
        self.batch = max(1, _CHUNK_ELEMENTS // (T * C * S))

    def unpack(self, theta):
        theta = np.atleast_2d(theta)
        rho = np.tanh(theta[:, 4]) if self.correlated else np.zeros(theta.shape[0])
        return theta[:, 0], np.exp(theta[:, 1]), theta[:, 2], np.exp(theta[:, 3]), rho

    def log_prior(self, theta):
        """Flat loc in its box, half-Cauchy scale above its floor (+ log-scale Jacobian), flat ρ on (−1, 1)."""
        theta = np.atleast_2d(theta)
        l1, s1, l2, s2, rho = self.unpack(theta)
        lp = np.zeros(theta.shape[0])
        for (loc, scale, fam, s0, box) in ((l1, s1, self.families[0], self.hyper_scales[0], self.boxes[0]),
                                           (l2, s2, self.families[1], self.hyper_scales[1], self.boxes[1])):
            inside = (loc > box[0]) & (loc < box[1]) & fam.feasible(loc, scale) & (scale >= box[2])
            lp = np.where(inside, lp + _half_cauchy_logpdf(scale, s0) + np.log(scale), -np.inf)
        if self.correlated:
            z = theta[:, 4]
            lp = np.where(np.abs(z) < 5.0, lp + np.log1p(-rho * rho), -np.inf)   # flat in ρ: Jacobian 1 − ρ²
        return lp

    def log_test_likelihoods(self, theta):
        """log L_i − log Z_i of every test (B, T); −inf rows where the prior is zero."""
        theta = np.atleast_2d(theta)
        out = np.full((theta.shape[0], self.data.n_tests), -np.inf)
        ok = np.isfinite(self.log_prior(theta))
        if not ok.any():
            return out
        l1, s1, l2, s2, rho = self.unpack(theta[ok])
        part = np.empty((l1.size, self.data.n_tests))
        f1, f2 = self.families
        x1, x2 = self.data.values[..., 0], self.data.values[..., 1]
        for start in range(0, l1.size, self.batch):
            sl = slice(start, start + self.batch)

            def col(a):
                return a[sl][:, None, None, None]

            lw = f1.kernel(_with_batch_axis(self.feats[0]), col(l1), col(s1))
            lw += f2.kernel(_with_batch_axis(self.feats[1]), col(l2), col(s2))
            if self.correlated:
                r = col(rho)
                q1 = f1.normal_score(x1[None], col(l1), col(s1))
                q2 = f2.normal_score(x2[None], col(l2), col(s2))
                one_minus = 1.0 - r * r
                lw -= 0.5 * np.log(one_minus) + (r * r * (q1 * q1 + q2 * q2) - 2 * r * q1 * q2) / (2 * one_minus)
            lw += self.base[None]
            part[sl] = np.where(self.data.mask[None], _logmeanexp(lw), 0.0).sum(axis=2)
        part += self.n_canopies[None, :] * (f1.normaliser(l1, s1) + f2.normaliser(l2, s2))[:, None]
        out[ok] = part
        return out

    def __call__(self, theta):
        theta = np.atleast_2d(theta)
        ll = self.log_test_likelihoods(theta).sum(axis=1)
        lp = self.log_prior(theta)
        return np.where(np.isfinite(lp) & np.isfinite(ll), lp + ll, -np.inf)


def _fit_generalized_pareto(x):
    """Shape ξ and scale σ of a generalized Pareto fitted to exceedances ``x`` > 0 (sorted ascending).

    Zhang & Stephens (2009): with b = ξ/σ the profile log-likelihood is
    ℓ(b) = n·[log(b/ξ̂(b)) − ξ̂(b) − 1], ξ̂(b) = mean log(1 + b·x); b̂ is the
    posterior mean of b over their grid of m = 30 + ⌊√n⌋ points
    b_j = −1/x_(n) − (1 − √(m/(j − ½)))/(3·x_(⌊n/4 + ½⌋)). The shape is then pulled
    towards ½ as if by 10 prior observations (Vehtari et al. 2024).
    """
    n = x.size
    m = 30 + int(math.sqrt(n))
    quartile = x[max(int(n / 4 + 0.5) - 1, 0)]
    j = np.arange(1, m + 1)
    b = -1.0 / x[-1] - (1.0 - np.sqrt(m / (j - 0.5))) / (3.0 * quartile)
    xi = np.mean(np.log1p(b[:, None] * x[None, :]), axis=1)
    profile = n * (np.log(b / xi) - xi - 1.0)
    weights = np.exp(profile - special.logsumexp(profile))
    b_hat = float(np.sum(weights * b))
    xi_hat = float(np.mean(np.log1p(b_hat * x)))
    sigma = xi_hat / b_hat
    return (n * xi_hat + 10 * 0.5) / (n + 10), sigma


def _psis(log_ratios):
    """Pareto-smoothed importance weights along the last axis: (normalised log weights, k̂).

    The largest M_tail = ⌈min(0.2·M, 3·√M)⌉ weights are replaced by the
    expected order statistics of a generalized Pareto fitted to their excess
    over the next weight (capped at the largest raw weight); k̂ is its shape.
    k̂ < 0.7: the importance estimate is reliable (Vehtari et al. 2024).
    """
    log_ratios = np.asarray(log_ratios, float)
    if log_ratios.ndim > 1:
        pairs = [_psis(row) for row in log_ratios.reshape(-1, log_ratios.shape[-1])]
        lw = np.stack([p[0] for p in pairs]).reshape(log_ratios.shape)
        return lw, np.array([p[1] for p in pairs]).reshape(log_ratios.shape[:-1])
    lw = log_ratios - np.max(log_ratios)
    n = lw.size
    tail = int(math.ceil(min(0.2 * n, 3 * math.sqrt(n))))
    khat = -math.inf
    if tail >= 5:
        order = np.argsort(lw)
        cutoff = lw[order[-tail - 1]]
        top = order[-tail:]
        excess = np.exp(lw[top]) - math.exp(cutoff)
        if excess[-1] > 0 and np.all(np.isfinite(excess)):
            khat, sigma = _fit_generalized_pareto(np.maximum(excess, 0.0))
            p = (np.arange(1, tail + 1) - 0.5) / tail
            if abs(khat) > 1e-12:
                quantiles = sigma / khat * (np.power(1 - p, -khat) - 1)
            else:
                quantiles = -sigma * np.log1p(-p)
            with np.errstate(divide="ignore"):
                lw[top] = np.minimum(np.log(math.exp(cutoff) + quantiles), 0.0)
    return lw - special.logsumexp(lw), float(khat)


def _psis_loo(log_lik, log_weights=None):
    """PSIS-LOO per test from log L_i at hyper-posterior draws (M, T): (elpd_i, k̂_i).

    With importance draws (``log_weights`` of the proposal, M), the leave-one-out
    ratios are the proposal weights divided by L_i.
    """
    base = np.zeros(log_lik.shape[0]) if log_weights is None else log_weights
    lw, khat = _psis(base[None, :] - log_lik.T)
    return special.logsumexp(lw + log_lik.T, axis=-1), khat


def _hessian(fun, x, steps):
    """Central-difference Hessian of a batched scalar function (one batched call)."""
    d = x.size
    e = np.diag(steps)
    rows = [x]
    for i in range(d):
        for j in range(i, d):
            rows += [x + e[i] + e[j], x + e[i] - e[j], x - e[i] + e[j], x - e[i] - e[j]]
    f = fun(np.array(rows))
    h = np.empty((d, d))
    k = 1
    for i in range(d):
        for j in range(i, d):
            pp, pm, mp, mm = f[k:k + 4]
            h[i, j] = h[j, i] = (pp - pm - mp + mm) / (4 * steps[i] * steps[j])
            k += 4
    return h


def _sample_pair_posterior(post, theta0, steps, rng, n_proposal=2000, df=5.0, khat_max=PARETO_K_MAX):
    """Hyper-posterior draws of a pair model: Laplace + importance sampling, emcee if that fails.

    1. the mode (Nelder–Mead from ``theta0``), the Hessian there (``steps``);
    2. ``n_proposal`` draws from a multivariate t (``df``) with 1.2² × the Laplace
       covariance; weights p(θ|d)/q(θ), Pareto-smoothed;
    3. if the weights' k̂ exceeds ``khat_max`` (a posterior too far from the
       Laplace shape), emcee from walkers around the mode instead.

    Returns (draws (M, d) equally weighted, log weights or None, log L_i at the
    draws (M, T), info).
    """
    def negative(th):
        v = post(th[None])[0]
        return -v if np.isfinite(v) else 1e300

    res = optimize.minimize(negative, theta0, method="Nelder-Mead",
                            options={"maxiter": 4000, "xatol": 1e-5, "fatol": 1e-7, "adaptive": True})
    mode = res.x
    hess = -_hessian(post, mode, steps)
    w, v = np.linalg.eigh(0.5 * (hess + hess.T))
    chol = None
    if np.all(np.isfinite(w)) and np.all(w > 0):
        cov = (v / w) @ v.T * 1.2 ** 2
        chol = np.linalg.cholesky(cov)
        d = mode.size
        z = rng.standard_normal((n_proposal, d))
        g = rng.chisquare(df, size=n_proposal) / df
        theta = mode + (z @ chol.T) / np.sqrt(g)[:, None]
        maha = np.sum(np.square(np.linalg.solve(chol, (theta - mode).T)), axis=0)
        log_q = -0.5 * (df + d) * np.log1p(maha / df)        # up to a constant (cancels on normalising)
        log_lik = post.log_test_likelihoods(theta)
        log_p = post.log_prior(theta) + log_lik.sum(axis=1)
        finite = np.isfinite(log_p)
        if finite.sum() > n_proposal // 2:
            theta, log_lik, log_w = theta[finite], log_lik[finite], (log_p - log_q)[finite]
            smoothed, khat = _psis(log_w)
            if khat <= khat_max:
                return theta, smoothed, log_lik, {"method": "laplace-importance", "pareto_k": float(khat),
                                                  "proposals": int(n_proposal)}
    # fallback: emcee around the mode
    import emcee

    n_walkers = 4 * mode.size
    noise = rng.standard_normal((n_walkers, mode.size))
    init = mode + (0.5 * noise @ chol.T if chol is not None else 20 * steps[None, :] * noise)
    bad = ~np.isfinite(post(init))
    init[bad] = mode + 1e-3 * noise[bad] * steps
    sampler = emcee.EnsembleSampler(n_walkers, mode.size, post, vectorize=True)
    sampler.random_state = np.random.RandomState(int(rng.integers(2**31 - 1))).get_state()
    state, n_steps, tau = init, 0, np.full(mode.size, np.inf)
    while n_steps < 8000:
        state = sampler.run_mcmc(state, 500, progress=False)
        n_steps += 500
        tau = emcee.autocorr.integrated_time(sampler.get_chain(), tol=0)
        if n_steps > 50 * np.max(tau):
            break
    burn = int(min(n_steps // 2, math.ceil(2 * np.max(tau))))
    chain = sampler.get_chain(discard=burn, thin=max(1, int(0.5 * np.min(tau))), flat=True)
    chain = chain[np.linspace(0, chain.shape[0] - 1, min(chain.shape[0], n_proposal)).astype(int)]
    return chain, None, post.log_test_likelihoods(chain), {
        "method": "emcee", "tau_max": float(np.max(tau)), "steps": int(n_steps),
        "acceptance": float(np.mean(sampler.acceptance_fraction))}


def pool_pair(data: PerTestDraws, marginals, rng, *, names=PAIR, hyper_scales=None, n_draws=4000) -> PairPool:
    """Correlated population of a pair under a Gaussian copula of two marginal pools.

    ``data``: joint draws (T, C, S, 2) with the pair's joint log prior.
    ``marginals``: the two :class:`ParameterPool` (chosen families) of the
    parameters alone; they fix the families, give the starting point and step
    sizes and bound the location boxes. The correlated (5 hyper-parameters)
    and the independent (ρ = 0, 4) model are fitted to the same joint draws
    (Laplace approximation + Pareto-smoothed importance sampling, emcee when
    k̂ > 0.7) and compared by PSIS-LOO over tests.
    """
    fams = tuple(m.family for m in marginals)
    scales = hyper_scales or tuple(_default_hyper_scale(_component_draws(data, j), f) for j, f in enumerate(fams))
    boxes, start, steps = [], [], []
    for m in marginals:
        loc_box = m.grid.get("loc_prior_box", (-np.inf, np.inf))
        boxes.append((loc_box[0], loc_box[1], m.scale_floor))
        start += [m.hyper_median[0], math.log(m.hyper_median[1])]
        steps += [0.05 * np.std(m.hyper_draws[:, 0]), 0.05 * np.std(np.log(m.hyper_draws[:, 1]))]
    results = {}
    for correlated in (True, False):
        post = _PairPosterior(data, fams, scales, boxes, correlated)
        theta0 = np.array(start + ([math.atanh(float(np.clip(_median_correlation(data, fams), -0.9, 0.9)))]
                                   if correlated else []))
        h = np.array(steps + ([0.02] if correlated else []))
        draws, log_w, log_lik, info = _sample_pair_posterior(post, theta0, h, rng)
        elpd, khat = _psis_loo(log_lik, log_w)
        # PSIS cannot stand in for p(λ | d_−i) where k̂ > 0.7 (few tests, an influential one): refit without it
        refits = []
        for i in np.flatnonzero(khat > PARETO_K_MAX):
            rest = _PairPosterior(data.select(np.arange(data.n_tests) != i), fams, scales, boxes, correlated)
            d_i, lw_i, _, _ = _sample_pair_posterior(rest, draws[np.argmax(log_lik.sum(axis=1))], h, rng)
            log_li = post.log_test_likelihoods(d_i)[:, i]
            weights = lw_i if lw_i is not None else np.full(d_i.shape[0], -math.log(d_i.shape[0]))
            elpd[i] = special.logsumexp(weights + log_li)
            refits.append(data.tests[i])
        info["loo_refits"] = refits
        results[correlated] = (post, draws, log_w, elpd, khat, info)
    post, draws, log_w, elpd_c, k_c, info_c = results[True]
    _, _, _, elpd_i, k_i, info_i = results[False]
    if log_w is not None:       # resample the importance draws to equal weights
        draws = draws[rng.choice(draws.shape[0], size=n_draws, p=np.exp(log_w - special.logsumexp(log_w)))]
    l1, s1, l2, s2, rho = post.unpack(draws)
    hyper = np.column_stack([l1, s1, l2, s2, rho])
    h = hyper[rng.integers(0, hyper.shape[0], size=n_draws)]
    z1 = rng.standard_normal(n_draws)
    z2 = h[:, 4] * z1 + np.sqrt(1 - h[:, 4] ** 2) * rng.standard_normal(n_draws)
    u1, u2 = (np.clip(special.ndtr(z), 1e-15, 1 - 1e-15) for z in (z1, z2))
    predictive = np.column_stack([fams[0].ppf(u1, h[:, 0], h[:, 1]), fams[1].ppf(u2, h[:, 2], h[:, 3])])
    diff = elpd_c - elpd_i
    se = float(math.sqrt(diff.size) * np.std(diff)) if diff.size > 1 else float("nan")
    q = np.quantile(rho, [0.05, 0.5, 0.95])
    return PairPool(names=tuple(names), families=fams, hyper_draws=hyper, rho_median=float(q[1]),
                    rho_interval=(float(q[0]), float(q[2])), elpd_correlated=float(elpd_c.sum()),
                    elpd_independent=float(elpd_i.sum()), elpd_diff_se=se, pareto_k=k_c, pareto_k_independent=k_i,
                    keep=bool(elpd_c.sum() > elpd_i.sum()), predictive=predictive,
                    sampler={"correlated": info_c, "independent": info_i}, tests=list(data.tests))


def _component_draws(data, j):
    return PerTestDraws(data.values[..., j], data.log_prior, data.mask, data.tests, data.canopies)


def _median_correlation(data, fams):
    """Correlation of the canopies' posterior medians in the families' coordinates (a starting value)."""
    z = [f.coordinate(data.values[..., j])[data.mask] for j, f in enumerate(fams)]
    m1, m2 = (np.median(a, axis=-1) for a in z)
    if m1.size < 3 or np.std(m1) == 0 or np.std(m2) == 0:
        return 0.0
    return float(np.corrcoef(m1, m2)[0, 1])


# ---------------------------------------------------------------------------
# fits -> population


@dataclass
class EntryPool:
    """The pooled population of one (kind, stage, parameter)."""

    kind: str
    stage: str
    parameter: str
    selection: FamilySelection
    per_canopy: pd.DataFrame       # test, canopy, median, q05, q95 (posterior, natural units)
    n_tests: int
    bounds: tuple                  # support written to the memo
    predictive: np.ndarray = None  # the memo column (the pair's when the correlation is kept)
    memo_params: dict = None
    quantiles: dict = None
    correlation: dict | None = None

    @property
    def family(self):
        return self.selection.chosen

    @property
    def pool(self) -> ParameterPool:
        return self.selection.pool

    @property
    def criterion(self):
        return self.selection.criterion

    def population(self, level=0.90):
        """{'mean': (lo, med, hi), 'sd': (...)} of the hyper-posterior."""
        return {"mean": self.pool.interval("mean", level), "sd": self.pool.interval("sd", level)}


@dataclass
class PeakFillTimes:
    """t_fp of one kind and stage: per-canopy posterior medians (s) and their range."""

    kind: str
    stage: str
    per_canopy: pd.DataFrame      # test, canopy, median, q05, q95
    n_tests: int

    @property
    def range(self):
        m = self.per_canopy["median"].to_numpy()
        return float(m.min()), float(m.max())


@dataclass
class PoolResult:
    """Everything pooling found: entries, correlated pairs, peak fill times, draws, provenance."""

    entries: dict                 # (kind, stage, parameter) -> EntryPool
    pairs: dict                   # (kind, stage) -> PairPool
    peak_fill: dict               # (kind, stage) -> PeakFillTimes
    draws: pd.DataFrame           # memo_draws.csv
    tests: list
    seeds: list
    folders: list
    warnings: list
    skipped: list
    method: str = METHOD

    def ess_table(self):
        """Per test and entry: ESS at the inferred population (chosen family)."""
        rows = []
        for (kind, stage, param), e in sorted(self.entries.items()):
            for t, ess in zip(e.pool.tests, e.pool.ess):
                rows.append({"kind": kind, "stage": stage, "parameter": param, "test": t, "ess": float(ess)})
        return pd.DataFrame(rows)

    def summary_table(self):
        """One row per memo entry: family, parameters, population quantiles, hyper-posterior of mean and sd."""
        rows = []
        for (kind, stage, param), e in sorted(self.entries.items()):
            pop = e.population()
            rows.append({"kind": kind, "stage": stage, "parameter": param, "family": e.family,
                         "params": e.memo_params, **e.quantiles, "n_tests": e.n_tests,
                         "mean_q05": pop["mean"][0], "mean_q50": pop["mean"][1], "mean_q95": pop["mean"][2],
                         "sd_q05": pop["sd"][0], "sd_q50": pop["sd"][1], "sd_q95": pop["sd"][2],
                         "criterion": dict(e.criterion), "min_ess": float(np.min(e.pool.ess))})
        for (kind, stage), p in sorted(self.peak_fill.items()):
            m = p.per_canopy["median"].to_numpy()
            q = np.quantile(m, list(QUANTILE_LEVELS.values()))
            rows.append({"kind": kind, "stage": stage, "parameter": "t_fp", "family": "uniform",
                         "params": {"low": p.range[0], "high": p.range[1]},
                         **dict(zip(QUANTILE_LEVELS, map(float, q))), "n_tests": p.n_tests})
        return pd.DataFrame(rows)

    def to_memo(self, provenance=None) -> Memo:
        """The :class:`~cpas_bayes.population.memo.Memo` (entries, joint draws, provenance)."""
        from cpas_bayes import __version__

        prov = {"package_version": __version__,
                "created": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "tests": list(self.tests), "seeds": [int(s) for s in self.seeds], "method": self.method}
        if self.warnings:
            prov["warnings"] = list(self.warnings)
        prov.update(provenance or {})
        entries = {}
        for key, e in self.entries.items():
            crit = {"name": CRITERION_NAME, "values": {k: float(v) for k, v in e.criterion.items()}}
            if e.correlation is not None:
                crit["correlation"] = e.correlation
            entries[key] = MemoEntry(e.kind, e.stage, e.parameter, e.family, dict(e.memo_params),
                                     tuple(float(b) for b in e.bounds), dict(e.quantiles), int(e.n_tests), crit)
        for (kind, stage), p in self.peak_fill.items():
            m = p.per_canopy["median"].to_numpy()
            lo, hi = p.range
            q = np.quantile(m, list(QUANTILE_LEVELS.values()))
            entries[(kind, stage, "t_fp")] = MemoEntry(
                kind, stage, "t_fp", "uniform", {"low": lo, "high": hi}, (lo, hi),
                dict(zip(QUANTILE_LEVELS, map(float, q))), int(p.n_tests),
                {"name": "per-canopy posterior medians (bounds: their range; quantiles: theirs)",
                 "values": {f"{r.test} {r.canopy}": float(r.median) for r in p.per_canopy.itertuples()}})
        return Memo(entries, self.draws.copy(), prov)


def _quantiles(x):
    q = np.quantile(x, list(QUANTILE_LEVELS.values()))
    return {k: float(v) for k, v in zip(QUANTILE_LEVELS, q)}


def _describe(x):
    q = np.quantile(x, [0.05, 0.5, 0.95])
    return float(q[1]), float(q[0]), float(q[2])


def _prior_width(prior, family):
    """sd of the prior in the family's coordinate (from its quantile function): the half-Cauchy s₀."""
    if prior is None:
        return None
    x = prior.ppf(np.linspace(0.005, 0.995, 199))
    z = family.coordinate(x)
    z = z[np.isfinite(z)]
    width = float(np.std(z)) if z.size > 1 else 0.0
    return width if width > 0 else None


def _families_for(parameter):
    return FAMILY_NAMES if parameter == "eps" else ("normal", "truncnormal", "lognormal")


@dataclass
class _Unit:
    """One canopy's draws of one parameter (subsampled indices of its record applied)."""

    test: str
    canopy: str
    values: np.ndarray
    log_prior: np.ndarray
    full: np.ndarray          # all draws, for the per-canopy summary
    prior: object             # the prior in natural units (for the support and s₀), or None
    support: tuple


def _gather(records, rng, max_samples):
    """{(kind, stage, parameter): {test: [_Unit]}} plus t_fp medians; draws aligned per record."""
    groups, tfp = {}, {}
    s_common = min(min(v.size for v in r.draws.values()) for r in records)
    s_common = min(s_common, max_samples)
    for r in records:
        n = min(v.size for v in r.draws.values())
        pick = np.sort(rng.choice(n, size=s_common, replace=False)) if n > s_common else np.arange(n)
        where = r.folder / "posterior.nc"
        for pid, kind, _inflation, diameter, keys in r.parachutes():
            area = math.pi / 4 * float(diameter) ** 2

            def add(stage, param, full, log_prior_full, prior, support, name):
                if not np.all(np.isfinite(full)):
                    raise InputError(where, f"variable '{name}'", "non-finite posterior draws", "rerun the fit")
                if not np.all(np.isfinite(log_prior_full)):
                    raise InputError(where, f"variable '{name}'", "posterior draws outside the fit's prior support",
                                     "rerun the fit with this version of cpas_bayes (summary.json priors must be "
                                     "those the fit used)")
                unit = _Unit(r.test, pid, full[pick], log_prior_full[pick], full, prior, support)
                groups.setdefault((kind, stage, param), {}).setdefault(r.test, []).append(unit)

            name = f"{pid}.cds_o"
            if name in r.draws and name in r.priors:
                prior = r.priors[name].scaled(1.0 / area)
                cd = r.draws[name] / area
                add(PARACHUTE_STAGE, "cd_o", cd, r.priors[name].logpdf(cd * area) + math.log(area), prior,
                    prior.support, name)
            for k, key in enumerate(keys):
                pre = f"{pid}.s{k + 1}"
                for param in STAGE_PARAMETERS:
                    name = f"{pre}.{param}"
                    if name not in r.draws:
                        continue
                    if param == "n":
                        np_name = f"{pre}.n_p"
                        if np_name not in r.priors or np_name not in r.draws:
                            continue
                        n_p, n_ = r.draws[np_name], r.draws[name]
                        if np.any(n_ <= 0) or np.any(n_p <= 0):
                            raise InputError(where, f"variable '{name}'", "non-positive fill constant draws",
                                             "rerun the fit")
                        prior = r.priors[np_name]
                        lp = prior.logpdf(n_p) + np.log(n_p) - np.log(n_)   # π(n | o) = π(n_p)·n_p/n
                        add(key, "n", n_, lp, prior, (0.0, prior.support[1]), name)
                    elif name in r.priors:
                        prior = r.priors[name]
                        add(key, param, r.draws[name], prior.logpdf(r.draws[name]), prior, prior.support, name)
                t_name = f"{pre}.t_fp"
                if t_name in r.draws:
                    tfp.setdefault((kind, key), []).append((r.test, pid, r.draws[t_name]))
    return groups, tfp


def _stack(by_test, tests_order):
    tests = [t for t in tests_order if t in by_test]
    values = [np.stack([u.values for u in by_test[t]]) for t in tests]
    log_prior = [np.stack([u.log_prior for u in by_test[t]]) for t in tests]
    data = PerTestDraws.from_arrays(values, log_prior, None, None, tests)
    data.canopies = [[u.canopy for u in by_test[t]] for t in tests]
    return data


def _per_canopy_table(by_test, tests_order):
    rows = []
    for t in tests_order:
        for u in by_test.get(t, []):
            med, lo, hi = _describe(u.full)
            rows.append({"test": t, "canopy": u.canopy, "median": med, "q05": lo, "q95": hi})
    return pd.DataFrame(rows)


def _support_union(units):
    lo = min(u.support[0] for u in units)
    hi = max(u.support[1] for u in units)
    return float(lo), float(hi)


def _clip_to(x, bounds):
    return np.clip(x, bounds[0], bounds[1])


def pool_fits(records, rng, *, n_draws=10000, max_samples=500, ess_min=ESS_MIN, min_tests=2, correlate=True,
              families=None) -> PoolResult:
    """Pool fitted tests (:class:`~cpas_bayes.inference.fit_folder.FitRecord`) into population distributions.

    Per parachute kind and stage key: n_p, n, expopen, ck, tk, eps (where the
    fits sampled them) and per canopy cd_o, each with the family chosen by
    leave-one-test-out elpd among ``families`` (default: normal, truncnormal,
    lognormal; beta too for eps); (n_p, expopen) as a Gaussian-copula pair when
    ``correlate``; t_fp medians and range. ``max_samples`` draws per test
    enter the reweighting sums; ``n_draws`` population-predictive draws per
    kind become memo_draws.csv rows. Entries with fewer than ``min_tests``
    tests are skipped (listed in ``skipped``, with a warning).
    """
    records = list(records)
    if not records:
        raise InputError("(no folders)", "", "no fits to pool", "pass at least two fit folders")
    seen = {}
    for r in records:
        if r.test in seen:
            raise InputError(r.folder, "summary.json key 'test'",
                             f"test '{r.test}' is already pooled from {seen[r.test]}",
                             "pool each test once (one fit folder per test)")
        seen[r.test] = r.folder
    tests_order = [r.test for r in records]
    seeds = [int(r.summary.get("sampler", {}).get("seed", -1)) for r in records]
    groups, tfp = _gather(records, rng, max_samples)
    notes, skipped = [], []
    entries, pairs, peak = {}, {}, {}
    for key in sorted(groups):
        kind, stage, param = key
        by_test = groups[key]
        if len(by_test) < min_tests:
            skipped.append(f"{kind}.{stage}.{param}: {len(by_test)} test(s), need {min_tests}")
            continue
        units = [u for us in by_test.values() for u in us]
        support = _support_union(units)
        data = _stack(by_test, tests_order)
        cands = families or _families_for(param)
        fam_bounds = {name: (0.0, 1.0) if name == "beta" else support for name in cands}
        s0 = {name: _prior_width(units[0].prior, make_family(name, *fam_bounds[name])) for name in cands}
        selection = select_family(data, None, cands, rng, bounds=fam_bounds, hyper_scale=s0, n_draws=n_draws,
                                  ess_min=ess_min)
        chosen = selection.pool
        label = f"{kind}.{stage}.{param}"
        if chosen.low_ess:
            msg = (f"{label}: ESS < {ess_min:g} at the inferred {chosen.family.name} population for "
                   f"{', '.join(chosen.low_ess)} (smallest {np.min(chosen.ess):.0f}); their reweighting sums are noisy")
            notes.append(msg)
            warnings.warn(msg, PoolWarning, stacklevel=2)
        for note in chosen.notes:
            notes.append(f"{label}: {note}")
            warnings.warn(f"{label}: {note}", PoolWarning, stacklevel=2)
        bounds = (chosen.family.low, chosen.family.high) if chosen.family.name in ("truncnormal", "beta") \
            else support
        entries[key] = EntryPool(kind, stage, param, selection, _per_canopy_table(by_test, tests_order),
                                 len(by_test), bounds)
    for msg in skipped:
        warnings.warn(f"skipped {msg}", PoolWarning, stacklevel=2)

    # correlated pairs
    if correlate:
        for (kind, stage) in sorted({(k, s) for k, s, _ in entries}):
            k1, k2 = (kind, stage, PAIR[0]), (kind, stage, PAIR[1])
            if k1 not in entries or k2 not in entries:
                continue
            g1, g2 = groups[k1], groups[k2]
            tests = [t for t in tests_order if t in g1 and t in g2
                     and [u.canopy for u in g1[t]] == [u.canopy for u in g2[t]]]
            if len(tests) < max(min_tests, 3):
                continue
            values = [np.stack([np.stack([a.values, b.values], axis=-1) for a, b in zip(g1[t], g2[t])])
                      for t in tests]
            log_prior = [np.stack([a.log_prior + b.log_prior for a, b in zip(g1[t], g2[t])]) for t in tests]
            data = PerTestDraws.from_arrays(values, log_prior, None, None, tests)
            marg = (entries[k1].pool, entries[k2].pool)
            s0 = tuple(_prior_width(g[tests[0]][0].prior, m.family)
                       or _default_hyper_scale(_component_draws(data, j), m.family)
                       for j, (g, m) in enumerate(((g1, marg[0]), (g2, marg[1]))))
            pair = pool_pair(data, marg, rng, hyper_scales=s0, n_draws=n_draws)
            pairs[(kind, stage)] = pair
            for model, info in pair.sampler.items():
                if info["method"] != "laplace-importance":
                    msg = (f"{kind}.{stage}.(n_p, expopen), {model} model: the Laplace importance sampler failed "
                           f"(k̂ > {PARETO_K_MAX}); sampled with emcee instead")
                    notes.append(msg)
                    warnings.warn(msg, PoolWarning, stacklevel=2)

    # predictive columns, memo params and quantiles
    columns = {}
    for key, e in sorted(entries.items()):
        kind, stage, param = key
        pair = pairs.get((kind, stage))
        if pair is not None and pair.keep and param in PAIR:
            j = PAIR.index(param)
            x = pair.predictive[:, j]
        else:
            x = e.pool.predictive
        x = _clip_to(x, e.bounds)
        e.predictive = x
        loc, scale = e.pool.family.fit(x, loc_range=e.pool.grid.get("loc_prior_box", (-math.inf, math.inf)))
        e.memo_params = e.pool.family.memo_params(loc, scale)
        e.quantiles = _quantiles(x)
        if pair is not None and param in PAIR:
            corr = pair.criterion()
            corr["with"] = PAIR[1 - PAIR.index(param)]
            e.correlation = corr
        if param in DRAWN_PARAMETERS or param == "cd_o":
            columns.setdefault(kind, {})[f"{stage}.{param}"] = x
    frames = []
    for kind in sorted(columns):
        cols = columns[kind]
        n = min(len(v) for v in cols.values())
        frame = pd.DataFrame({"kind": [kind] * n, **{c: v[:n] for c, v in sorted(cols.items())}})
        frames.append(frame)
    draws = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame({"kind": []})

    for (kind, stage), items in sorted(tfp.items()):
        by_test = {}
        for test, pid, d in items:
            by_test.setdefault(test, []).append(_Unit(test, pid, d, d, d, None, (0, math.inf)))
        if len(by_test) < min_tests:
            continue
        peak[(kind, stage)] = PeakFillTimes(kind, stage, _per_canopy_table(by_test, tests_order), len(by_test))
    if not entries:
        raise InputError(records[0].folder, "", f"nothing to pool: every parameter has fewer than {min_tests} tests",
                         f"pass at least {min_tests} fits of the same parachute kind")
    return PoolResult(entries, pairs, peak, draws, tests_order, seeds, [r.folder for r in records], notes, skipped)


# ---------------------------------------------------------------------------
# folders in, memo folder out


def pool_folders(folders, seed=0, **kwargs) -> PoolResult:
    """Load fit folders (refusing clearly any that is not one) and pool them."""
    from cpas_bayes.inference.fit_folder import load_fit

    records = [load_fit(Path(f)) for f in folders]
    return pool_fits(records, np.random.default_rng(seed), **kwargs)


def memo_markdown(result: PoolResult, provenance=None) -> str:
    """memo.md: one table row per entry, then criteria, correlations, ESS warnings and provenance."""

    def fmt(v):
        return f"{v:.4g}" if isinstance(v, (int, float, np.floating)) else str(v)

    lines = ["# Model memo: population dispersions", "",
             f"Pooled {len(result.tests)} tests: {', '.join(result.tests)}.", "",
             "Population-predictive quantiles (hyper-parameter uncertainty included). "
             "Parameters are the family fitted to the predictive draws.", "",
             "| kind | stage | parameter | family | parameters | 5 % | 50 % | 95 % | n_tests |",
             "|---|---|---|---|---|---|---|---|---|"]
    table = result.summary_table()
    for _, row in table.iterrows():
        params = ", ".join(f"{k} = {fmt(v)}" for k, v in row["params"].items())
        lines.append(f"| {row['kind']} | {row['stage']} | {row['parameter']} | {row['family']} | {params} | "
                     f"{fmt(row['q05'])} | {fmt(row['q50'])} | {fmt(row['q95'])} | {row['n_tests']} |")
    lines += ["", "## Hyper-posterior of the population mean and sd (5 / 50 / 95 %)", "",
              "| kind | stage | parameter | mean | sd | min ESS |", "|---|---|---|---|---|---|"]
    for (kind, stage, param), e in sorted(result.entries.items()):
        pop = e.population()
        lines.append(f"| {kind} | {stage} | {param} | " + " / ".join(fmt(v) for v in pop["mean"]) + " | "
                     + " / ".join(fmt(v) for v in pop["sd"]) + f" | {np.min(e.pool.ess):.0f} |")
    lines += ["", "## Family choice: leave-one-test-out elpd (larger is better)", "",
              "| kind | stage | parameter | " + " | ".join(FAMILY_NAMES) + " | chosen |",
              "|---|---|---|" + "---|" * len(FAMILY_NAMES) + "---|"]
    for (kind, stage, param), e in sorted(result.entries.items()):
        vals = " | ".join(fmt(e.criterion[f]) if f in e.criterion else "–" for f in FAMILY_NAMES)
        lines.append(f"| {kind} | {stage} | {param} | {vals} | {e.family} |")
    if result.pairs:
        lines += ["", "## Correlation of n_p and expopen (Gaussian copula)", "",
                  "| kind | stage | rho median | rho 90 % | elpd correlated | elpd rho = 0 | difference ± se | kept |",
                  "|---|---|---|---|---|---|---|---|"]
        for (kind, stage), p in sorted(result.pairs.items()):
            lines.append(f"| {kind} | {stage} | {p.rho_median:.3f} | [{p.rho_interval[0]:.3f}, "
                         f"{p.rho_interval[1]:.3f}] | {p.elpd_correlated:.2f} | {p.elpd_independent:.2f} | "
                         f"{p.elpd_diff:.2f} ± {p.elpd_diff_se:.2f} | {'yes' if p.keep else 'no'} |")
    if result.peak_fill:
        lines += ["", "## Peak fill time t_fp seen in the tests (posterior medians, s)", ""]
        for (kind, stage), p in sorted(result.peak_fill.items()):
            meds = ", ".join(f"{r.test}/{r.canopy} {r.median:.3f}" for r in p.per_canopy.itertuples())
            lines.append(f"- {kind} {stage}: range {p.range[0]:.3f}–{p.range[1]:.3f} s ({meds})")
    if result.warnings or result.skipped:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in result.warnings] + \
                 [f"- skipped {s}" for s in result.skipped]
    prov = provenance or {}
    lines += ["", "## Provenance", "",
              f"- tests: {', '.join(result.tests)}",
              f"- fit seeds: {', '.join(str(s) for s in result.seeds)}",
              f"- method: {result.method}"]
    lines += [f"- {k}: {v}" for k, v in prov.items() if k not in ("tests", "seeds", "method")]
    return "\n".join(lines) + "\n"


def write_pool(result: PoolResult, out, provenance=None):
    """Write memo.toml, memo_draws.csv, memo.md and the forest plots into ``out``; return the paths."""
    from cpas_bayes.core.files import write_text
    from cpas_bayes.outputs.plots.pool import write_pool_figures

    out = Path(out)
    memo = result.to_memo(provenance)
    memo_path = memo.write(out)
    md = out / "memo.md"
    write_text(md, memo_markdown(result, memo.provenance))
    figures = write_pool_figures(result, out)
    return {"memo": memo_path, "draws": out / "memo_draws.csv", "markdown": md, "figures": figures}

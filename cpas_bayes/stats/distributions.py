"""One-dimensional distribution families: the one place their mathematics lives.

Priors (:mod:`cpas_bayes.stats.priors`), the population families of pooling
(:mod:`cpas_bayes.population.families`) and the model memo's entries
(:mod:`cpas_bayes.population.memo`) all use these densities, distribution
functions and quantile functions. Families and their numbers (the keys of a
TOML table, ``describe()``'s output):

===============  =====================================  ==================================================
family           numbers                                density
===============  =====================================  ==================================================
``uniform``      ``low, high``                          1/(high − low) on [low, high]
``normal``       ``mu, sigma``                          N(x; mu, sigma²)
``truncnormal``  ``mu, sigma, low, high``               N(x; mu, sigma²) / (Φ(β) − Φ(α)) on [low, high]
``lognormal``    ``median, sigma_log`` [``low, high``]  N(log x; log median, sigma_log²) / x, optionally
                                                        cut to [low, high] (then / (Φ(β) − Φ(α)))
``beta``         ``a, b`` [``low, high``]               u^(a−1) (1 − u)^(b−1) / (B(a, b)·(high − low)),
                                                        u = (x − low)/(high − low); default [0, 1]
===============  =====================================  ==================================================

with α, β = (low − mu)/sigma, (high − mu)/sigma (in log x for the lognormal).
Truncated quantiles are F⁻¹(F(α) + u·(F(β) − F(α))), so inverse-transform
draws ``ppf(rng.uniform(size))`` (what :meth:`Distribution.sample` does)
reproduce from any Generator seed.

Two forms of the same objects:

* frozen :class:`Distribution` objects (``Normal(1.0, 0.2)``) with
  ``logpdf``, ``cdf``, ``ppf``, ``sample``, ``describe`` (the TOML table),
  ``scaled`` and ``support``; :func:`from_table` is ``describe``'s inverse;
* functions of arrays of parameters (``truncnormal_ppf(u, mu, sigma, low,
  high)``; the lognormal's in μ = log median), which broadcast over many
  parameter values at once — the population families evaluate them at
  thousands of hyper-parameter draws. The frozen objects' ``cdf`` and
  ``ppf`` are these functions.

The truncated normal's mass log(Φ(β) − Φ(α)) is computed two ways.
:func:`log_normal_mass` (differences of log Φ) stays finite far in the tails,
where population families are evaluated (a location many σ outside the
truncation). Frozen distributions take log(Φ(β) − Φ(α)) directly: the two
agree to ~1e-16 on every shipped prior, but a prior's constant enters every
seeded fit, and a change of one ulp there changes the fit's chains (the MAP
search and the sampler amplify it), so priors keep their form bit for bit.
For the same reason frozen distributions take logarithms of their numbers with
``math.log`` and the array functions with ``np.log`` (they differ in the last
bit for a few arguments).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special, stats

LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


# ---------------------------------------------------------------------------
# the standard normal's mass between two points


def log_normal_mass(alpha, beta):
    """log(Φ(β) − Φ(α)) for α < β, elementwise and stable in both tails."""
    alpha, beta = np.broadcast_arrays(np.asarray(alpha, float), np.asarray(beta, float))
    upper = alpha > 0
    lo = np.where(upper, -beta, alpha)
    hi = np.where(upper, -alpha, beta)
    log_hi, log_lo = special.log_ndtr(hi), special.log_ndtr(lo)
    with np.errstate(divide="ignore", invalid="ignore"):
        return log_hi + np.log1p(-np.exp(log_lo - log_hi))


def _log_normal_mass_direct(a, b):
    """log(Φ(b) − Φ(a)) for scalars a < b, the upper tail by symmetry (frozen distributions; see the module doc)."""
    if a > 0:
        a, b = -b, -a
    return float(np.log(special.ndtr(b) - special.ndtr(a)))


def log_positive(x):
    """log x where x > 0, −inf elsewhere (the lognormal's coordinate)."""
    x = np.asarray(x, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(x > 0, np.log(np.where(x > 0, x, 1.0)), -np.inf)


# ---------------------------------------------------------------------------
# array functions (parameters broadcast with x or u)


def normal_cdf(x, mu, sigma):
    return special.ndtr((np.asarray(x, float) - mu) / sigma)


def normal_ppf(u, mu, sigma):
    return mu + sigma * special.ndtri(np.asarray(u, float))


def truncnormal_cdf(x, mu, sigma, low, high):
    a, b = (low - mu) / sigma, (high - mu) / sigma
    return stats.truncnorm.cdf(x, a, b, loc=mu, scale=sigma)


def truncnormal_ppf(u, mu, sigma, low, high):
    a, b = (low - mu) / sigma, (high - mu) / sigma
    return stats.truncnorm.ppf(np.asarray(u, float), a, b, loc=mu, scale=sigma)


def truncnormal_moments(mu, sigma, low, high):
    """Mean μ + σ·(φ(α) − φ(β))/Z and sd σ·√[1 + (αφ(α) − βφ(β))/Z − ((φ(α) − φ(β))/Z)²],
    Z = Φ(β) − Φ(α), with the ratios φ/Z formed in logs (stable in the tails)."""
    mu, sigma = np.asarray(mu, float), np.asarray(sigma, float)
    alpha, beta = (low - mu) / sigma, (high - mu) / sigma
    log_mass = log_normal_mass(alpha, beta)

    def ratio(t):   # φ(t)/Z and t·φ(t)/Z, 0 at t = ±inf
        finite = np.isfinite(t)
        safe = np.where(finite, t, 0.0)
        r = np.where(finite, np.exp(-0.5 * safe * safe - LOG_SQRT_2PI - log_mass), 0.0)
        return r, r * safe

    ra, ta = ratio(alpha)
    rb, tb = ratio(beta)
    shift = ra - rb
    var = np.maximum(1.0 + ta - tb - shift * shift, 0.0)
    return mu + sigma * shift, sigma * np.sqrt(var)


def _log_limits(mu_log, sigma_log, low, high):
    """(α, β) of a lognormal cut to [low, high], in the normal coordinate (−inf, inf when uncut)."""
    a = -np.inf if low <= 0 else (math.log(low) - mu_log) / sigma_log
    b = np.inf if math.isinf(high) else (math.log(high) - mu_log) / sigma_log
    return a, b


def lognormal_cdf(x, mu_log, sigma_log, low=0.0, high=math.inf):
    p = special.ndtr((log_positive(x) - mu_log) / sigma_log)
    if low <= 0 and math.isinf(high):
        return p
    a, b = _log_limits(mu_log, sigma_log, low, high)
    lo, hi = special.ndtr(a), special.ndtr(b)
    return np.clip((p - lo) / (hi - lo), 0.0, 1.0)


def lognormal_ppf(u, mu_log, sigma_log, low=0.0, high=math.inf):
    a, b = _log_limits(mu_log, sigma_log, low, high)
    lo, hi = special.ndtr(a), special.ndtr(b)
    z = special.ndtri(lo + (hi - lo) * np.asarray(u, float))
    return np.exp(mu_log + sigma_log * z)


def lognormal_moments(mu_log, sigma_log):
    """Mean e^(μ + σ²/2) and sd mean·√(e^(σ²) − 1) of the uncut lognormal."""
    mean = np.exp(mu_log + 0.5 * np.square(sigma_log))
    return mean, mean * np.sqrt(np.expm1(np.square(sigma_log)))


def beta_shapes(mean, sd, low=0.0, high=1.0):
    """Shapes (a, b) of the beta on [low, high] with this mean and sd:
    a = m'ν, b = (1 − m')ν, ν = m'(1 − m')/s'² − 1 (m', s' the mean and sd on [0, 1])."""
    width = high - low
    m = (np.asarray(mean, float) - low) / width
    s = np.asarray(sd, float) / width
    with np.errstate(divide="ignore", invalid="ignore"):
        nu = m * (1 - m) / (s * s) - 1.0
    return m * nu, (1 - m) * nu


def beta_moments(a, b, low=0.0, high=1.0):
    """Mean and sd of the beta (a, b) on [low, high]."""
    mean = a / (a + b)
    sd = np.sqrt(a * b / ((a + b) ** 2 * (a + b + 1)))
    width = high - low
    return low + width * mean, width * sd


def beta_cdf(x, a, b, low=0.0, high=1.0):
    return special.betainc(a, b, np.clip((np.asarray(x, float) - low) / (high - low), 0.0, 1.0))


def beta_ppf(u, a, b, low=0.0, high=1.0):
    return low + (high - low) * special.betaincinv(a, b, u)


# ---------------------------------------------------------------------------
# frozen distributions


@dataclass(frozen=True)
class Distribution:
    """A one-dimensional distribution with fixed numbers; every method is vectorised over x or u."""

    # True when the density is (truncated) normal in log x: a posterior the data leave near such a prior is
    # then near-normal in log x, the coordinates a sampler's Gaussian proposal should use
    log_scale = False

    @property
    def support(self):
        return (-np.inf, np.inf)

    def _in_support(self, x):
        low, high = self.support
        return (x >= low) & (x <= high)

    def logpdf(self, x):
        raise NotImplementedError

    def cdf(self, x):
        raise NotImplementedError

    def ppf(self, u):
        raise NotImplementedError

    def sample(self, rng, size=None):
        """Draws by inverse transform, so any Generator seed reproduces them."""
        return self.ppf(rng.uniform(size=size))

    def log_normaliser(self):
        """The x-independent part of log p(x) inside the support."""
        raise NotImplementedError

    def describe(self):
        """The TOML-table form: ``{"family": ..., <numbers>}`` (see :func:`from_table`)."""
        raise NotImplementedError

    def scaled(self, factor):
        """The distribution of ``factor · x`` (factor > 0), e.g. CDS_o = C_D,o · S_o."""
        raise NotImplementedError


@dataclass(frozen=True)
class Uniform(Distribution):
    low: float
    high: float

    @property
    def support(self):
        return (self.low, self.high)

    def logpdf(self, x):
        x = np.asarray(x, float)
        return np.where(self._in_support(x), -math.log(self.high - self.low), -np.inf)

    def cdf(self, x):
        return np.clip((np.asarray(x, float) - self.low) / (self.high - self.low), 0.0, 1.0)

    def ppf(self, u):
        return self.low + (self.high - self.low) * np.asarray(u, float)

    def log_normaliser(self):
        return -math.log(self.high - self.low)

    def describe(self):
        return {"family": "uniform", "low": self.low, "high": self.high}

    def scaled(self, factor):
        return Uniform(self.low * factor, self.high * factor)


@dataclass(frozen=True)
class Normal(Distribution):
    mu: float
    sigma: float

    def logpdf(self, x):
        z = (np.asarray(x, float) - self.mu) / self.sigma
        return -0.5 * z * z - math.log(self.sigma) - LOG_SQRT_2PI

    def cdf(self, x):
        return normal_cdf(x, self.mu, self.sigma)

    def ppf(self, u):
        return normal_ppf(u, self.mu, self.sigma)

    def log_normaliser(self):
        return -math.log(self.sigma) - LOG_SQRT_2PI

    def describe(self):
        return {"family": "normal", "mu": self.mu, "sigma": self.sigma}

    def scaled(self, factor):
        return Normal(self.mu * factor, self.sigma * factor)


@dataclass(frozen=True)
class TruncNormal(Distribution):
    mu: float
    sigma: float
    low: float
    high: float

    @property
    def support(self):
        return (self.low, self.high)

    @property
    def log_mass(self):
        """log(Φ(β) − Φ(α)): the parent normal's mass on [low, high]."""
        return _log_normal_mass_direct((self.low - self.mu) / self.sigma, (self.high - self.mu) / self.sigma)

    def logpdf(self, x):
        x = np.asarray(x, float)
        z = (x - self.mu) / self.sigma
        inside = -0.5 * z * z - math.log(self.sigma) - LOG_SQRT_2PI - self.log_mass
        return np.where(self._in_support(x), inside, -np.inf)

    def cdf(self, x):
        return truncnormal_cdf(x, self.mu, self.sigma, self.low, self.high)

    def ppf(self, u):
        return truncnormal_ppf(u, self.mu, self.sigma, self.low, self.high)

    def moments(self):
        """Mean and standard deviation."""
        return truncnormal_moments(self.mu, self.sigma, self.low, self.high)

    def log_normaliser(self):
        return -math.log(self.sigma) - LOG_SQRT_2PI - self.log_mass

    def describe(self):
        return {"family": "truncnormal", "mu": self.mu, "sigma": self.sigma, "low": self.low, "high": self.high}

    def scaled(self, factor):
        return TruncNormal(self.mu * factor, self.sigma * factor, self.low * factor, self.high * factor)


@dataclass(frozen=True)
class LogNormal(Distribution):
    median: float
    sigma_log: float
    low: float = 0.0
    high: float = math.inf

    log_scale = True

    @property
    def support(self):
        return (self.low, self.high)

    @property
    def log_mass(self):
        """log(Φ(β) − Φ(α)) of log x on [log low, log high] (0 when uncut)."""
        return _log_normal_mass_direct(*_log_limits(math.log(self.median), self.sigma_log, self.low, self.high))

    def logpdf(self, x):
        x = np.asarray(x, float)
        inside = self._in_support(x) & (x > 0)
        safe = np.where(inside, x, 1.0)
        z = (np.log(safe) - math.log(self.median)) / self.sigma_log
        value = -0.5 * z * z - np.log(safe) - math.log(self.sigma_log) - LOG_SQRT_2PI - self.log_mass
        return np.where(inside, value, -np.inf)

    def cdf(self, x):
        return lognormal_cdf(x, math.log(self.median), self.sigma_log, self.low, self.high)

    def ppf(self, u):
        return lognormal_ppf(u, math.log(self.median), self.sigma_log, self.low, self.high)

    def log_normaliser(self):
        return -math.log(self.sigma_log) - LOG_SQRT_2PI - self.log_mass

    def describe(self):
        out = {"family": "lognormal", "median": self.median, "sigma_log": self.sigma_log}
        if self.low > 0:
            out["low"] = self.low
        if not math.isinf(self.high):
            out["high"] = self.high
        return out

    def scaled(self, factor):
        return LogNormal(self.median * factor, self.sigma_log, self.low * factor, self.high * factor)


@dataclass(frozen=True)
class Beta(Distribution):
    a: float
    b: float
    low: float = 0.0
    high: float = 1.0

    @property
    def support(self):
        return (self.low, self.high)

    def logpdf(self, x):
        u = (np.asarray(x, float) - self.low) / (self.high - self.low)
        inside = (u > 0) & (u < 1)
        safe = np.where(inside, u, 0.5)
        value = (self.a - 1) * np.log(safe) + (self.b - 1) * np.log1p(-safe) + self.log_normaliser()
        return np.where(inside, value, -np.inf)

    def cdf(self, x):
        return beta_cdf(x, self.a, self.b, self.low, self.high)

    def ppf(self, u):
        return beta_ppf(u, self.a, self.b, self.low, self.high)

    def moments(self):
        """Mean and standard deviation."""
        return beta_moments(self.a, self.b, self.low, self.high)

    def log_normaliser(self):
        return -float(special.betaln(self.a, self.b)) - math.log(self.high - self.low)

    def describe(self):
        return {"family": "beta", "a": self.a, "b": self.b, "low": self.low, "high": self.high}

    def scaled(self, factor):
        return Beta(self.a, self.b, self.low * factor, self.high * factor)


# family -> (class, required numbers, optional numbers) of its table
TABLE_FORMS = {
    "uniform": (Uniform, ("low", "high"), ()),
    "normal": (Normal, ("mu", "sigma"), ()),
    "truncnormal": (TruncNormal, ("mu", "sigma", "low", "high"), ()),
    "lognormal": (LogNormal, ("median", "sigma_log"), ("low", "high")),
    "beta": (Beta, ("a", "b"), ("low", "high")),
}
FAMILIES = tuple(TABLE_FORMS)


def from_table(table) -> Distribution:
    """The distribution a table ``{"family": ..., <numbers>}`` describes (:meth:`Distribution.describe`'s inverse).

    The numbers are not checked here; :func:`cpas_bayes.stats.priors.prior_from_table`
    checks a user's file before it builds a prior this way.
    """
    family = table.get("family")
    if family not in TABLE_FORMS:
        raise ValueError(f"unknown family {family!r}; use one of {', '.join(FAMILIES)}")
    cls, required, optional = TABLE_FORMS[family]
    return cls(**{name: float(table[name]) for name in required + optional if name in table})

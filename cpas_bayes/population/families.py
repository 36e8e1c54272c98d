"""Population families: two-parameter distributions of one parameter across the parachutes of a kind.

Each family's mathematics (densities, distribution and quantile functions,
moments) is that of :mod:`cpas_bayes.stats.distributions`; a family adds the
hyper-parameters λ = (loc, scale) pooling infers, the coordinate ``loc`` lives
in, and the split of its log density that makes the reweighting sums cheap.

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
eps on (0, 1). A family's ``distribution(loc, scale)`` is the frozen
distribution at one λ; its table without the bounds is a memo entry's
``params`` (the memo keeps the bounds apart).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import optimize, special, stats

from cpas_bayes.stats.distributions import (LOG_SQRT_2PI, Beta, LogNormal, Normal, TruncNormal, beta_cdf,
                                            beta_moments, beta_ppf, beta_shapes, log_normal_mass, log_positive,
                                            lognormal_cdf, lognormal_moments, lognormal_ppf, normal_cdf, normal_ppf,
                                            truncnormal_cdf, truncnormal_moments, truncnormal_ppf)


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
    def distribution(self, loc, scale):
        """The population at one λ as a frozen :class:`~cpas_bayes.stats.distributions.Distribution`."""
        raise NotImplementedError

    def memo_params(self, loc, scale):
        """A memo entry's ``params``: the table of :meth:`distribution` without family and bounds."""
        return {k: v for k, v in self.distribution(loc, scale).describe().items() if k not in ("family", "low", "high")}

    def fit(self, x, loc_range=(-math.inf, math.inf)):
        """(loc, scale) by maximum likelihood to draws ``x`` (``loc`` kept in ``loc_range``)."""
        raise NotImplementedError


class NormalFamily(Family):
    name = "normal"
    hyper_names = ("mu", "sigma")

    def kernel(self, z, loc, scale):
        return _gauss_kernel(z, loc, scale)

    def normaliser(self, loc, scale):
        return -np.log(scale) - LOG_SQRT_2PI

    def normal_score(self, x, loc, scale):
        return (np.asarray(x, float) - loc) / scale

    def cdf(self, x, loc, scale):
        return normal_cdf(x, loc, scale)

    def ppf(self, u, loc, scale):
        return normal_ppf(u, loc, scale)

    def moments(self, loc, scale):
        return np.asarray(loc, float), np.asarray(scale, float)

    def distribution(self, loc, scale):
        return Normal(float(loc), float(scale))

    def fit(self, x, loc_range=(-math.inf, math.inf)):
        return float(np.clip(np.mean(x), *loc_range)), float(np.std(x))


class TruncNormalFamily(Family):
    name = "truncnormal"
    hyper_names = ("mu", "sigma")

    def kernel(self, z, loc, scale):
        return _gauss_kernel(z, loc, scale)

    def normaliser(self, loc, scale):
        alpha, beta = (self.low - loc) / scale, (self.high - loc) / scale
        return -np.log(scale) - LOG_SQRT_2PI - log_normal_mass(alpha, beta)

    def cdf(self, x, loc, scale):
        return truncnormal_cdf(x, loc, scale, self.low, self.high)

    def ppf(self, u, loc, scale):
        return truncnormal_ppf(u, loc, scale, self.low, self.high)

    def moments(self, loc, scale):
        return truncnormal_moments(loc, scale, self.low, self.high)

    def distribution(self, loc, scale):
        return TruncNormal(float(loc), float(scale), self.low, self.high)

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
        return log_positive(x)

    def features(self, x):
        return self.coordinate(x)

    def base(self, x):
        x = np.asarray(x, float)
        ok = x > 0
        return np.where(ok, -np.log(np.where(ok, x, 1.0)), -np.inf)

    def kernel(self, z, loc, scale):
        return _gauss_kernel(z, loc, scale)

    def normaliser(self, loc, scale):
        return -np.log(scale) - LOG_SQRT_2PI

    def normal_score(self, x, loc, scale):
        return (self.coordinate(x) - loc) / scale

    def cdf(self, x, loc, scale):
        return lognormal_cdf(x, loc, scale)

    def ppf(self, u, loc, scale):
        return lognormal_ppf(u, loc, scale)

    def moments(self, loc, scale):
        return lognormal_moments(loc, scale)

    def distribution(self, loc, scale):
        return LogNormal(float(math.exp(loc)), float(scale))

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

    def shapes(self, loc, scale):
        """Beta shapes (a, b) from mean and sd."""
        return beta_shapes(loc, scale, self.low, self.high)

    def feasible(self, loc, scale):
        a, b = self.shapes(loc, scale)
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
        a, b = self.shapes(loc, scale)
        return (a - 1) * features[0] + (b - 1) * features[1]

    def normaliser(self, loc, scale):
        a, b = self.shapes(loc, scale)
        return -special.betaln(a, b)

    def cdf(self, x, loc, scale):
        a, b = self.shapes(loc, scale)
        return beta_cdf(x, a, b, self.low, self.high)

    def ppf(self, u, loc, scale):
        a, b = self.shapes(loc, scale)
        return beta_ppf(u, a, b, self.low, self.high)

    def moments(self, loc, scale):
        return np.asarray(loc, float), np.asarray(scale, float)

    def distribution(self, loc, scale):
        a, b = self.shapes(loc, scale)
        return Beta(float(a), float(b), self.low, self.high)

    def fit(self, x, loc_range=(-math.inf, math.inf)):
        u = np.clip((np.asarray(x, float) - self.low) / self.width, 1e-12, 1 - 1e-12)
        a, b, _, _ = stats.beta.fit(u, floc=0.0, fscale=1.0)
        return beta_moments(a, b, self.low, self.high)


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

"""Per-test posterior draws and the population likelihood estimated by reweighting them.

Hierarchical model and likelihood
---------------------------------
Test i flew C_i canopies of the kind. Its fit returned S draws
x_{i,c,s} of a parameter from p(x | d_i) ∝ L_i(x)·π_i(x), π_i being the fit's
own prior. The population is a family p(x | λ) (λ: two hyper-parameters,
:mod:`cpas_bayes.population.families`), and each canopy's value is one draw
from it. The likelihood of λ is that of the data with the population in place
of the fit's prior, estimated by reweighting the stored draws (Thrane & Talbot
2019, Eq. 34)::

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
leave-one-test-out criterion on the grid
(:mod:`cpas_bayes.population.hyper_posterior`).

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import special

from cpas_bayes.population.families import Family

ESS_MIN = 20.0
CHUNK_ELEMENTS = 2_000_000  # batch size of the reweighting sums (floats per temporary)


class PoolWarning(UserWarning):
    """A pooled estimate to look at: low effective sample size, high Pareto k, grid edge."""


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

    def component(self, j):
        """The draws of the pair's ``j``-th parameter alone (with the pair's joint log prior)."""
        return PerTestDraws(self.values[..., j], self.log_prior, self.mask, self.tests, self.canopies)

    def canopy_labels(self):
        """Per test: the labels of its canopies."""
        return self.canopies if self.canopies else [[str(c + 1) for c in range(int(m.sum()))] for m in self.mask]

    def summaries(self, family):
        """Per-canopy posterior median and sd in the family's coordinate (for grid ranges)."""
        z = family.coordinate(self.values)
        z = z[self.mask]                                    # (units, S)
        return np.median(z, axis=-1), np.std(z, axis=-1)


# ---------------------------------------------------------------------------
# reweighting sums


def prepare_reweighting(data: PerTestDraws, family: Family):
    """Features of the draws and the λ-independent part of log p(x|λ)/π(x), masked."""
    feats = family.features(data.values)
    base = family.base(data.values) - data.log_prior
    base = np.where(data.mask[..., None], base, 0.0)
    if not np.all(np.isfinite(base[data.mask])):
        bad = np.argwhere(~np.isfinite(base) & data.mask[..., None])[0]
        raise ValueError(f"test {data.tests[bad[0]]}: a posterior draw lies outside the {family.name} family's "
                         "support or has zero prior density")
    return feats, base


def log_mean_exp(a):
    """log mean exp along the last axis (−inf where every term is −inf); overwrites ``a``."""
    m = np.max(a, axis=-1, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    a -= m
    np.exp(a, out=a)
    with np.errstate(divide="ignore"):
        return np.log(np.mean(a, axis=-1)) + m[..., 0]


def with_batch_axis(features):
    """Features (T, C, S) — or (k, T, C, S) for a family with k feature arrays — with a λ-batch axis."""
    return features[None] if features.ndim == 3 else features[:, None]


def log_test_likelihoods(data: PerTestDraws, family: Family, loc, scale, prepared=None):
    """log L_i(λ) − log Z_i for every λ = (loc[b], scale[b]) and test i: array (B, T).

    L_i(λ)/Z_i = Π_c (1/S) Σ_s p(x_{i,c,s} | λ)/π_i(x_{i,c,s}) (canopies reweighted
    separately, see the module docstring); the family's normaliser, the same
    for every draw, is added after the sums.
    """
    feats, base = prepared if prepared is not None else prepare_reweighting(data, family)
    feats = with_batch_axis(feats)
    loc = np.atleast_1d(np.asarray(loc, float))
    scale = np.atleast_1d(np.asarray(scale, float))
    T, C, S = data.values.shape[:3]
    n_canopies = data.mask.sum(axis=1)
    out = np.empty((loc.size, T))
    batch = max(1, CHUNK_ELEMENTS // (T * C * S))
    for start in range(0, loc.size, batch):
        sl = slice(start, start + batch)
        lw = family.kernel(feats, loc[sl][:, None, None, None], scale[sl][:, None, None, None])
        lw += base
        per_canopy = log_mean_exp(lw)                                          # (b, T, C)
        out[sl] = np.where(data.mask[None], per_canopy, 0.0).sum(axis=2)
    return out + n_canopies[None, :] * family.normaliser(loc, scale)[:, None]


def _ess_from_log_weights(lw):
    """(Σ w)²/Σ w² along the last axis, from log weights."""
    return np.exp(2 * special.logsumexp(lw, axis=-1) - special.logsumexp(2 * lw, axis=-1))


def effective_sample_sizes(data: PerTestDraws, family: Family, loc, scale):
    """ESS (T, C) of each canopy's weights w_s = p(x_s|λ)/π(x_s) at one λ (NaN where no canopy)."""
    feats, base = prepare_reweighting(data, family)
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

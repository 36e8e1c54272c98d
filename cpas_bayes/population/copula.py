"""The (n_p, expopen) pair: a correlated population by a Gaussian copula of the two chosen marginals.

For each kind and stage a bivariate population with the chosen marginal
families F₁, F₂ (:mod:`cpas_bayes.population.hyper_posterior`) joined by a
Gaussian copula of correlation ρ (for normal or lognormal marginals this *is*
the bivariate (log-)normal)::

    p(x₁, x₂ | λ₁, λ₂, ρ) = f₁(x₁) f₂(x₂) c_ρ(q₁, q₂),   q_j = Φ⁻¹(F_j(x_j))
    log c_ρ = −½ log(1 − ρ²) − (ρ²(q₁² + q₂²) − 2ρ q₁ q₂) / (2(1 − ρ²))

reweights each canopy's *joint* (n_p, expopen) draws (prior π(n_p)·π(expopen)),
as :mod:`cpas_bayes.population.reweighting` does for one parameter.
Five hyper-parameters (flat ρ on (−1, 1), the marginals' hyper-priors) are
too many for a grid: the hyper-posterior is sampled by importance sampling
from a multivariate t around its Laplace approximation (Pareto-smoothed,
:mod:`cpas_bayes.stats.psis`), or by emcee when the smoothed weights' k̂
exceeds 0.7. The ρ = 0 model is fitted the same way to the same joint draws,
and PSIS leave-one-test-out elpd compares the two (a test whose PSIS k̂
exceeds 0.7 — few tests, an influential one — gets its LOO term from a refit
without it). The correlation is kept when the correlated model predicts the
left-out tests better (Δelpd > 0); ρ's median and 90 % interval are reported
either way. Predictive draws: λ from the hyper-posterior, then (x₁, x₂) jointly
through the copula.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize, special

from cpas_bayes.population.hyper_posterior import default_hyper_scale, half_cauchy_logpdf
from cpas_bayes.stats.psis import PARETO_K_MAX, psis_log_weights, psis_loo
from cpas_bayes.population.reweighting import CHUNK_ELEMENTS, PerTestDraws, log_mean_exp, with_batch_axis

PAIR = ("n_p", "expopen")


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
        self.batch = max(1, CHUNK_ELEMENTS // (T * C * S))

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
            lp = np.where(inside, lp + half_cauchy_logpdf(scale, s0) + np.log(scale), -np.inf)
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

            lw = f1.kernel(with_batch_axis(self.feats[0]), col(l1), col(s1))
            lw += f2.kernel(with_batch_axis(self.feats[1]), col(l2), col(s2))
            if self.correlated:
                r = col(rho)
                q1 = f1.normal_score(x1[None], col(l1), col(s1))
                q2 = f2.normal_score(x2[None], col(l2), col(s2))
                one_minus = 1.0 - r * r
                lw -= 0.5 * np.log(one_minus) + (r * r * (q1 * q1 + q2 * q2) - 2 * r * q1 * q2) / (2 * one_minus)
            lw += self.base[None]
            part[sl] = np.where(self.data.mask[None], log_mean_exp(lw), 0.0).sum(axis=2)
        part += self.n_canopies[None, :] * (f1.normaliser(l1, s1) + f2.normaliser(l2, s2))[:, None]
        out[ok] = part
        return out

    def __call__(self, theta):
        theta = np.atleast_2d(theta)
        ll = self.log_test_likelihoods(theta).sum(axis=1)
        lp = self.log_prior(theta)
        return np.where(np.isfinite(lp) & np.isfinite(ll), lp + ll, -np.inf)


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
            smoothed, khat = psis_log_weights(log_w)
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
    ``marginals``: the two :class:`~cpas_bayes.population.hyper_posterior.ParameterPool` (chosen families) of the
    parameters alone; they fix the families, give the starting point and step
    sizes and bound the location boxes. The correlated (5 hyper-parameters)
    and the independent (ρ = 0, 4) model are fitted to the same joint draws
    (Laplace approximation + Pareto-smoothed importance sampling, emcee when
    k̂ > 0.7) and compared by PSIS-LOO over tests.
    """
    fams = tuple(m.family for m in marginals)
    scales = hyper_scales or tuple(default_hyper_scale(data.component(j), f) for j, f in enumerate(fams))
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
        elpd, khat = psis_loo(log_lik, log_w)
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


def _median_correlation(data, fams):
    """Correlation of the canopies' posterior medians in the families' coordinates (a starting value)."""
    z = [f.coordinate(data.values[..., j])[data.mask] for j, f in enumerate(fams)]
    m1, m2 = (np.median(a, axis=-1) for a in z)
    if m1.size < 3 or np.std(m1) == 0 or np.std(m2) == 0:
        return 0.0
    return float(np.corrcoef(m1, m2)[0, 1])

"""The vectorised differential-evolution move: the same chain law as emcee's DEMove, measured.

Target: a 12-dimensional Gaussian with correlations up to 0.8 and scales over
three decades (as the fits' parameters are). 40 walkers × 4,000 steps after
1,000 of burn-in; τ ≈ 37 steps (both moves, three seeds: 36.5–38.5), so each
parameter has an ESS of about 40·4000/37 ≈ 4,000 and the standard error of a
mean is ≈ σ/65. The bands: means within 5 standard errors, variances within
15 % (the sampling sd of a variance at ESS 4,000 is ≈ 2 %), acceptance and τ
within 15 % and 25 % of emcee's own DEMove on the same target (measured:
acceptance 0.258–0.260 for both, τ within 4 %). A move that drew pairs with a == b, scaled γ wrongly or skipped the
Metropolis test fails these by far.
"""

import emcee
import numpy as np
import pytest

from cpas_bayes.inference.moves import VectorisedDEMove
from cpas_bayes.inference.stopping import integrated_time

D = 12


def _target():
    rng = np.random.default_rng(7)
    a = rng.normal(size=(D, D))
    s = a @ a.T + 0.3 * np.eye(D)
    corr = s / np.sqrt(np.outer(np.diag(s), np.diag(s)))
    scale = np.logspace(-2, 1, D)
    cov = corr * np.outer(scale, scale)
    mean = rng.normal(size=D) * scale
    prec = np.linalg.inv(cov)

    def log_prob(x):
        d = np.atleast_2d(x) - mean
        return -0.5 * np.einsum("ij,jk,ik->i", d, prec, d)

    return mean, cov, log_prob


def _run(move, seed):
    mean, cov, log_prob = _target()
    rng = np.random.default_rng(seed)
    init = rng.multivariate_normal(mean, 0.01 * cov, size=40)
    sampler = emcee.EnsembleSampler(40, D, log_prob, vectorize=True, moves=[(move, 1.0)])
    sampler.random_state = np.random.RandomState(seed).get_state()
    sampler.run_mcmc(init, 5000, progress=False)
    chain = sampler.get_chain(discard=1000)
    return chain, float(np.mean(sampler.acceptance_fraction)), integrated_time(chain, 1)


@pytest.mark.parametrize("seed", [1, 2])
def test_the_move_samples_a_correlated_gaussian(seed):
    mean, cov, _ = _target()
    chain, acceptance, tau = _run(VectorisedDEMove(), seed)
    flat = chain.reshape(-1, D)
    ess = chain.shape[0] * chain.shape[1] / tau
    se = np.sqrt(np.diag(cov) / ess)
    assert np.all(np.abs(flat.mean(axis=0) - mean) < 5 * se)
    np.testing.assert_allclose(flat.var(axis=0) / np.diag(cov), 1, atol=0.15)
    assert 0.1 < acceptance < 0.5


def test_the_move_matches_emcees_demove():
    _, acc_ours, tau_ours = _run(VectorisedDEMove(), 3)
    _, acc_emcee, tau_emcee = _run(emcee.moves.DEMove(), 3)
    assert acc_ours == pytest.approx(acc_emcee, rel=0.15)
    assert np.mean(tau_ours) == pytest.approx(np.mean(tau_emcee), rel=0.25)


def test_pairs_are_distinct_and_uniform():
    move = VectorisedDEMove()
    move.setup(np.zeros((2, D)))
    random = np.random.RandomState(0)
    c = np.arange(6, dtype=float)[:, None] * np.ones((1, 1))      # walker k sits at k
    s = np.zeros((60000, 1))
    q, factors = move.get_proposal(s, [c], random)
    diff = np.round(q[:, 0] / move.g0).astype(int)                  # c_b − c_a: never 0
    assert np.all(diff != 0) and np.all(factors == 0)
    counts = np.bincount(diff + 5, minlength=11)
    # ordered pairs of 6 walkers with difference k: 6 − |k|, of 30
    expected = np.array([6 - abs(k) for k in range(-5, 6)], float) / 30 * s.shape[0]
    expected[5] = 1.0
    assert counts[5] == 0
    mask = np.arange(11) != 5
    chi2 = np.sum((counts[mask] - expected[mask]) ** 2 / expected[mask])
    assert chi2 < 30                                                  # 9 degrees of freedom: p ≈ 4e-4


def test_integrated_time_matches_emcees_estimator():
    rng = np.random.default_rng(4)
    for n in (7, 300):
        x = np.cumsum(rng.normal(size=(n, 16, 5)), axis=0) * 0.05 + rng.normal(size=(n, 16, 5))
        np.testing.assert_allclose(integrated_time(x, 5), 5 * emcee.autocorr.integrated_time(x, tol=0), rtol=1e-10)


def test_a_walker_that_never_moved_lengthens_tau_instead_of_making_it_nan():
    """A walker whose every proposal was rejected for a whole window (seen in a calibration replica: the fit
    crashed on a NaN burn-in) counts as perfectly correlated: τ stays finite and grows."""
    from cpas_bayes.inference.stopping import ess_check

    rng = np.random.default_rng(5)
    x = rng.normal(size=(200, 40, 3))
    free = integrated_time(x, 5)
    x[:, 7, :] = 0.3                               # stuck from the window's first step
    stuck = integrated_time(x, 5)
    assert np.all(np.isfinite(stuck)) and np.all(stuck > free)
    check = ess_check([x, rng.normal(size=(200, 40, 3))], 5)
    assert np.all(np.isfinite(np.concatenate(check.taus))) and check.statistics is not None


# ---------------------------------------------------------------------------
# the independence move: valid whatever its proposal, fast when the proposal fits

def _run_independence(mean_q, cov_q, seed, steps=3000, share=1.0):
    from cpas_bayes.inference.moves import IndependenceMove

    mean, cov, log_prob = _target()
    rng = np.random.default_rng(seed)
    init = rng.multivariate_normal(mean, 0.01 * cov, size=40)
    move = IndependenceMove(mean_q, np.linalg.cholesky(cov_q))
    moves = [(move, 1.0)] if share == 1.0 else [(VectorisedDEMove(), 1 - share), (move, share)]
    sampler = emcee.EnsembleSampler(40, D, log_prob, vectorize=True, moves=moves)
    sampler.random_state = np.random.RandomState(seed).get_state()
    sampler.run_mcmc(init, steps, progress=False)
    chain = sampler.get_chain(discard=500)
    return chain, float(np.mean(sampler.acceptance_fraction)), integrated_time(chain, 1)


def _assert_recovers(chain, tau):
    mean, cov, _ = _target()
    flat = chain.reshape(-1, D)
    ess = chain.shape[0] * chain.shape[1] / np.maximum(tau, 1)
    se = np.sqrt(np.diag(cov) / ess)
    assert np.all(np.abs(flat.mean(axis=0) - mean) < 5 * se)
    np.testing.assert_allclose(flat.var(axis=0) / np.diag(cov), 1, atol=0.15)


def test_a_matched_independence_proposal_gives_nearly_independent_draws():
    """q = the target's own moments: acceptance near 1 (t against normal tails), τ of a few steps where the
    differential-evolution move needs ~37."""
    mean, cov, _ = _target()
    chain, acceptance, tau = _run_independence(mean, cov, 4)
    _assert_recovers(chain, tau)
    assert acceptance > 0.8 and np.max(tau) < 3


def test_a_wrong_proposal_still_samples_the_target():
    """Shifted by half a standard deviation and 1.5× too wide, in a mixture with DE as the fits use it:
    slower, but the Hastings factor keeps the target exact. (Without q(x)/q(x') in the ratio, measured: the
    means shift by 0.10–0.14 sd toward q's centre, the variances come out 16–21 % too small, and this fails.)"""
    mean, cov, _ = _target()
    sd = np.sqrt(np.diag(cov))
    chain, acceptance, tau = _run_independence(mean + 0.5 * sd, 2.25 * cov, 5, steps=5000, share=0.7)
    _assert_recovers(chain, tau)
    assert 0.02 < acceptance < 0.6


def test_fit_proposal_recovers_moments_and_declines_what_cannot_define_one():
    from cpas_bayes.inference.moves import fit_proposal

    mean, cov, _ = _target()
    draws = np.random.default_rng(6).multivariate_normal(mean, cov, size=20000)
    mu, chol, log_columns = fit_proposal(draws)
    assert not log_columns.any()
    sd = np.sqrt(np.diag(cov))
    assert np.all(np.abs(mu - mean) < 0.05 * sd)
    np.testing.assert_allclose((chol @ chol.T) / np.outer(sd, sd), cov / np.outer(sd, sd), atol=0.03)
    assert fit_proposal(draws[: D]) is None                    # fewer than 2·D draws
    stuck = draws.copy()
    stuck[:, 3] = 1.0
    assert fit_proposal(stuck) is None                         # a parameter that never moved


# ---------------------------------------------------------------------------
# log coordinates: a parameter left at its lognormal prior

SIGMA_LOG = np.array([0.6, 0.7, 0.5, 0.6])      # the Main priors' n_p, tk, expopen: skewed in θ
LOG_COLUMNS = np.array([True, True, True, True, False, False])


def _lognormal_target():
    """Four lognormal parameters (the data silent about them) and two normal ones, all independent."""
    def log_prob(theta):
        theta = np.atleast_2d(theta)
        pos = theta[:, :4]
        with np.errstate(divide="ignore", invalid="ignore"):
            logs = np.log(np.where(pos > 0, pos, np.nan))
        out = -0.5 * np.sum((logs / SIGMA_LOG) ** 2, axis=1) - np.sum(logs, axis=1) \
            - 0.5 * np.sum(theta[:, 4:] ** 2, axis=1)
        return np.where(np.isnan(out), -np.inf, out)

    def draw(rng, n):
        return np.column_stack([np.exp(rng.normal(size=(n, 4)) * SIGMA_LOG), rng.normal(size=(n, 2))])

    return log_prob, draw


def _run_fitted(log_columns, seed, steps=3000, walkers=24):
    from cpas_bayes.inference.moves import IndependenceMove, fit_proposal

    log_prob, draw = _lognormal_target()
    rng = np.random.default_rng(seed)
    proposal = fit_proposal(draw(rng, 4000), log_columns)
    sampler = emcee.EnsembleSampler(walkers, 6, log_prob, vectorize=True,
                                    moves=[(VectorisedDEMove(), 0.3), (IndependenceMove(*proposal), 0.7)])
    sampler.random_state = np.random.RandomState(seed).get_state()
    sampler.run_mcmc(draw(rng, walkers), steps, progress=False)
    chain = sampler.get_chain(discard=300)
    return chain, integrated_time(chain, 1)


def test_log_coordinates_sample_a_lognormal_target_exactly():
    """u = log θ with the Jacobian in q's density: log θ comes out N(0, σ²), θ's 95 % quantile matches the
    lognormal's and the normal parameters stay N(0, 1) (without the Jacobian term the proposal's density is
    wrong by Π θ_j, and this test fails: checked)."""
    chain, tau = _run_fitted(LOG_COLUMNS, 7)
    flat = chain.reshape(-1, 6)
    ess = chain.shape[0] * chain.shape[1] / np.maximum(tau, 1)
    logs = np.log(flat[:, :4])
    assert np.all(np.abs(logs.mean(axis=0)) < 5 * SIGMA_LOG / np.sqrt(ess[:4]))
    np.testing.assert_allclose(logs.std(axis=0) / SIGMA_LOG, 1, atol=0.05)
    np.testing.assert_allclose(np.quantile(flat[:, :4], 0.95, axis=0), np.exp(1.645 * SIGMA_LOG), rtol=0.06)
    np.testing.assert_allclose(np.abs(flat[:, 4:]).mean(axis=0), np.sqrt(2 / np.pi), rtol=0.05)


def test_log_coordinates_mix_where_a_symmetric_proposal_in_theta_sticks():
    """The same proposal fitted in θ: a symmetric t is too thin in the lognormal's right tail, walkers that
    reach it stay (measured over three seeds: τ 12–30 steps against 2 in log θ)."""
    _, tau_log = _run_fitted(LOG_COLUMNS, 8)
    _, tau_theta = _run_fitted(np.zeros(6, bool), 8)
    assert np.max(tau_log) < 3
    assert np.max(tau_theta[:4]) > 4 * np.max(tau_log)


def test_a_log_column_that_is_not_positive_gives_no_proposal():
    from cpas_bayes.inference.moves import fit_proposal

    _, draw = _lognormal_target()
    draws = draw(np.random.default_rng(9), 200)
    draws[5, 0] = -0.1
    assert fit_proposal(draws, LOG_COLUMNS) is None
    assert fit_proposal(draws, np.zeros(6, bool)) is not None


def test_a_continued_chunk_is_not_refused_for_walkers_drawn_together():
    """emcee refuses a start whose walkers are linearly dependent; the lockstep chunks refuse it for a fresh
    start only, not for a chain continued from its last state (which raised mid-run on a Main SBC replica)."""
    import cpas_bayes.inference.fit as fit

    def log_prob(x):
        return -0.5 * np.sum(np.atleast_2d(x) ** 2, axis=1)

    x = np.random.default_rng(0).normal(size=(8, 1))
    together = np.hstack([x, 2.0 * x])          # the second column a multiple of the first
    state = np.random.RandomState(1).get_state()
    with pytest.raises(ValueError, match="condition number"):
        fit._chunk_task((log_prob, (together, None, state), 5, 1, None, ()))
    chain, lp, _, _ = fit._chunk_task((log_prob, (together, log_prob(together), state), 5, 1, None, ()))
    assert chain.shape == (5, 8, 2) and np.all(np.isfinite(lp))


def test_starting_walkers_the_density_rules_out_are_replaced_by_nudged_allowed_ones():
    import cpas_bayes.inference.fit as fit
    from emcee.ensemble import walkers_independent

    rng = np.random.default_rng(2)
    u = rng.normal(size=(16, 3))
    u[[2, 5], 1] = np.nan                               # where the coordinates are undefined

    def density(x):
        return np.where(np.all(np.isfinite(x), axis=1), 0.0, -np.inf)

    out = fit._inside_coordinates(u, density, np.random.default_rng(3))
    assert np.all(np.isfinite(out)) and walkers_independent(out) and not walkers_independent(u)
    keep = np.setdiff1d(np.arange(16), [2, 5])
    np.testing.assert_array_equal(out[keep], u[keep])   # the allowed walkers are kept as they were
    near = np.min(np.abs(out[[2, 5]][:, None, :] - u[keep][None]).max(axis=2), axis=1)
    assert np.all(near < 0.01) and np.all(near > 0)       # each a nudged copy of an allowed walker

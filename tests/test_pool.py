"""Pooling per-test posteriors into population dispersions (cpas_bayes.population) and ``cpas-bayes pool``.

Recovery checks draw campaigns from a KNOWN population and ask the pooled
hyper-posterior to find it again:

* with synthetic per-test posteriors (fast): each canopy's true value is drawn
  from the population, "measured" with a realistic posterior width, and its
  posterior is the measurement likelihood times the fit prior (priors/drogue.toml),
  drawn exactly by rejection;
* with real fits of simulated flight tests (slow): the first-stage n_p,
  expopen (correlated) and C_k of every canopy are drawn from the population
  and the tests are simulated and fitted with :func:`cpas_bayes.inference.fit.fit_test`.

Tolerances are stated where they are used.
"""

from __future__ import annotations

import math
import shutil
import warnings
from pathlib import Path
from dataclasses import replace

import numpy as np
import pytest
from scipy import integrate

from cpas_bayes.app.cli import main
from cpas_bayes.core.errors import InputError
from cpas_bayes.inference.fit_folder import FitRecord, load_fit
from cpas_bayes.population.copula import pool_pair
from cpas_bayes.population.families import make_family
from cpas_bayes.population.hyper_posterior import pool_parameter, select_family
from cpas_bayes.population.memo import MemoEntry, load_memo
from cpas_bayes.population.pool import pool_fits
from cpas_bayes.stats.psis import psis_log_weights
from cpas_bayes.population.reweighting import PerTestDraws, PoolWarning
from cpas_bayes.stats.distributions import LogNormal, Normal, TruncNormal, Uniform

# The fit priors of a Drogue's first stage (priors/drogue.toml).
PRIOR_N_P = LogNormal(10.0, 0.5, 2.0, 50.0)
PRIOR_EXPOPEN = LogNormal(2.0, 0.5, 0.3, 8.0)
PRIOR_CK = TruncNormal(1.25, 0.25, 1.0, 2.5)
PRIOR_EPS = Uniform(0.10, 0.90)


# ---------------------------------------------------------------------------
# synthetic per-test posteriors


def posterior_draws(rng, true_value, width, prior, coordinate="linear", n=600):
    """Draws of one canopy's posterior: likelihood N(g(x); y, width²) with y = g(true) + noise, times ``prior``.

    g is the identity or log. Proposals g ~ N(y, width²) have density
    N(g(x); y, width²)·g'(x) in x, so accepting with probability ∝ π(x)/g'(x)
    leaves exact posterior draws.
    """
    g, g_inv, log_jac = {"linear": (lambda x: x, lambda z: z, lambda x: 0.0 * x),
                         "log": (np.log, np.exp, lambda x: -np.log(x))}[coordinate]
    y = g(true_value) + width * rng.standard_normal()
    out = np.empty(0)
    while out.size < n:
        x = g_inv(y + width * rng.standard_normal(8 * n))
        inside = (x > prior.support[0]) & (x < prior.support[1])
        x = x[inside]
        log_w = prior.logpdf(x) - log_jac(x)
        keep = np.log(rng.uniform(size=x.size)) < log_w - np.max(log_w)
        out = np.concatenate([out, x[keep]])
    return out[:n]


def campaign(rng, draw_truth, width, prior, coordinate="linear", n_tests=8, canopies=2, n=600):
    """Per-test draws (C, S), log prior (C, S) and the true values (T, C) of a synthetic campaign."""
    truths = draw_truth(rng, (n_tests, canopies))
    widths = width * rng.uniform(0.5, 2.0, size=truths.shape)   # tests are not equally well measured
    draws, log_prior = [], []
    for t in range(n_tests):
        x = np.stack([posterior_draws(rng, truths[t, c], widths[t, c], prior, coordinate, n)
                      for c in range(canopies)])
        draws.append(x)
        log_prior.append(prior.logpdf(x))
    return draws, log_prior, truths


# Populations of the synthetic campaigns: (family, bounds, true mean, true sd, truth sampler, posterior
# width and coordinate, fit prior). Widths are those real Drogue fits show, a little generous
# (n_p 1-4 %, expopen 0.04-0.16, C_k 0.005-0.02, eps 0.0004 → 0.004).
LOGNORMAL_N_P = ("lognormal", (2.0, 50.0), 10.0 * math.exp(0.15**2 / 2),
                 10.0 * math.exp(0.15**2 / 2) * math.sqrt(math.expm1(0.15**2)),
                 lambda rng, size: 10.0 * np.exp(0.15 * rng.standard_normal(size)), 0.02, "log", PRIOR_N_P)
NORMAL_EXPOPEN = ("normal", (0.3, 8.0), 2.2, 0.25, lambda rng, size: rng.normal(2.2, 0.25, size), 0.08,
                  "linear", PRIOR_EXPOPEN)
NORMAL_CK = ("truncnormal", (1.0, 2.5), 1.30, 0.08, lambda rng, size: rng.normal(1.30, 0.08, size), 0.01,
             "linear", PRIOR_CK)
BETA_EPS = ("beta", (0.0, 1.0), 0.44, 0.03, lambda rng, size: rng.beta(0.44 * 272.8, 0.56 * 272.8, size), 0.002,
            "linear", PRIOR_EPS)
POPULATIONS = {"n_p": LOGNORMAL_N_P, "expopen": NORMAL_EXPOPEN, "ck": NORMAL_CK, "eps": BETA_EPS}


# ---------------------------------------------------------------------------
# families, PSIS and the grid LOO


@pytest.mark.parametrize("name,bounds,loc,scale", [("normal", (-math.inf, math.inf), 2.2, 0.3),
                                                   ("truncnormal", (1.0, 2.5), 1.1, 0.2),
                                                   ("lognormal", (0.0, math.inf), math.log(10.0), 0.2),
                                                   ("beta", (0.0, 1.0), 0.44, 0.05)])
def test_family_density_moments_quantiles_and_memo_form_agree(name, bounds, loc, scale):
    """Each family integrates to one, its moments and ppf/cdf agree with the density, and the memo's
    scipy distribution built from ``memo_params`` is the same distribution."""
    fam = make_family(name, *bounds)
    lo, hi = fam.ppf(1e-9, loc, scale), fam.ppf(1 - 1e-9, loc, scale)
    mass = integrate.quad(lambda x: math.exp(fam.logpdf(x, loc, scale)), lo, hi, limit=200)[0]
    assert mass == pytest.approx(1.0, abs=1e-6)
    mean, sd = fam.moments(loc, scale)
    m1 = integrate.quad(lambda x: x * math.exp(fam.logpdf(x, loc, scale)), lo, hi, limit=200)[0]
    m2 = integrate.quad(lambda x: (x - m1) ** 2 * math.exp(fam.logpdf(x, loc, scale)), lo, hi, limit=200)[0]
    assert float(mean) == pytest.approx(m1, rel=1e-6)
    assert float(sd) == pytest.approx(math.sqrt(m2), rel=1e-5)
    u = np.array([0.01, 0.3, 0.5, 0.9, 0.99])
    np.testing.assert_allclose(fam.cdf(fam.ppf(u, loc, scale), loc, scale), u, atol=1e-9)
    entry = MemoEntry("k", "s", "p", name, fam.memo_params(loc, scale), bounds)
    x = fam.ppf(u, loc, scale)
    np.testing.assert_allclose(entry.distribution().logpdf(x), fam.logpdf(x, loc, scale), rtol=1e-9)
    # maximum-likelihood fit to many draws returns the parameters
    draws = fam.ppf(np.random.default_rng(0).uniform(size=40000), loc, scale)
    np.testing.assert_allclose(fam.fit(draws), (loc, scale), rtol=0.03, atol=0.01 * scale)


def test_psis_smoothing_keeps_benign_weights_and_flags_heavy_tails():
    """Log-normal importance ratios: k̂ is small for sd 0.5 and above 0.7 for sd 3 (the textbook cases);
    normalised weights sum to one and only the tail is changed."""
    rng = np.random.default_rng(0)
    light = rng.normal(0.0, 0.5, 4000)
    lw, k = psis_log_weights(light)
    assert k < 0.3
    assert np.exp(lw).sum() == pytest.approx(1.0)
    order = np.argsort(light)[:3000]
    np.testing.assert_allclose(lw[order] - lw[order[0]], light[order] - light[order[0]], atol=1e-12)
    _, k_heavy = psis_log_weights(rng.normal(0.0, 3.0, 4000))
    assert k_heavy > 0.7


def test_grid_loo_equals_refitting_without_each_test():
    """The leave-one-test-out elpd read off the full grid equals p(d_i | d_−i) computed from a hyper-posterior
    fitted without test i (a finer grid), to 0.01 — with only four wide-posterior tests, where p(λ | d_−i)
    differs most from p(λ | d)."""
    from cpas_bayes.population.hyper_posterior import grid_hyper_posterior
    from cpas_bayes.population.reweighting import log_test_likelihoods, prepare_reweighting
    from scipy.special import logsumexp

    rng = np.random.default_rng(4)
    family, bounds, _, _, draw, width, coord, prior = NORMAL_EXPOPEN
    draws, log_prior, _ = campaign(rng, draw, 3 * width, prior, coord, n_tests=4, n=400)
    data = PerTestDraws.from_arrays(draws, log_prior, rng)
    fam = make_family(family, *bounds)
    pool = pool_parameter(data, None, fam, rng, hyper_scale=0.5, n_draws=500)
    for i in range(data.n_tests):
        rest = data.select(np.arange(data.n_tests) != i)
        g, _ = grid_hyper_posterior(rest, fam, prepare_reweighting(rest, fam), 0.5, pool.scale_floor, coarse=40,
                                    fine=120)
        log_li = log_test_likelihoods(data.select([i]), fam, g["loc"], g["scale"])[:, 0]
        ok = np.isfinite(g["log_post"])
        direct = logsumexp(g["log_post"][ok] + log_li[ok]) - logsumexp(g["log_post"][ok])
        assert pool.elpd_pointwise[i] == pytest.approx(direct, abs=0.01)


# ---------------------------------------------------------------------------
# recovery from synthetic per-test posteriors


def _recovery(name, seeds, n_tests=8):
    family, bounds, mean, sd, draw, width, coord, prior = POPULATIONS[name]
    inside, sd_ratio = 0, []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        draws, log_prior, _ = campaign(rng, draw, width, prior, coord, n_tests=n_tests)
        pool = pool_parameter(draws, log_prior, family, rng, bounds=bounds, n_draws=2000, max_samples=300)
        lo, _, hi = pool.interval("mean", 0.90)
        inside += lo <= mean <= hi
        sd_ratio.append(pool.interval("sd")[1] / sd)
    return inside, np.array(sd_ratio)


@pytest.mark.parametrize("name", sorted(POPULATIONS))
def test_population_is_recovered_from_synthetic_per_test_posteriors(name):
    """Ten campaigns of 8 tests (16 canopies) from a known population, pooled with the true family.

    Mean: the 90 % hyper-posterior interval should hold the true mean in ~9 of 10; requiring ≥ 7/10
    fails by bad luck with probability 1.3 % (binomial), so passing is evidence of calibration.
    Sd: the posterior median of the population sd within 0.5–2× the truth in ≥ 9/10. With 16 draws the
    sample sd alone scatters by ±18 % (1/√(2·15)); a factor 2 is ~4 such sds, so a miss means a bias,
    not bad luck; the posterior widths (a few % of the spread) add little.
    """
    inside, ratio = _recovery(name, range(10))
    assert inside >= 7, f"{name}: true mean inside the 90 % interval in {inside}/10"
    assert np.sum((ratio > 0.5) & (ratio < 2.0)) >= 9, f"{name}: sd ratios {np.round(ratio, 2)}"


def test_the_per_test_prior_is_divided_out():
    """Posteriors shrunk by an informative prior N(8, 1) towards 8, of canopies from N(10, 0.5²) measured to
    ±0.6: the posterior medians average near 9.3, but the pooled population mean must find 10 (90 %
    interval) and exclude the naive average."""
    rng = np.random.default_rng(11)
    prior = Normal(8.0, 1.0)
    draws, log_prior, _ = campaign(rng, lambda r, size: r.normal(10.0, 0.5, size), 0.6, prior, n_tests=12,
                                   canopies=1)
    naive = float(np.mean([np.median(d) for d in draws]))
    pool = pool_parameter(draws, log_prior, "normal", rng, n_draws=2000)
    lo, _, hi = pool.interval("mean")
    assert naive < 9.6
    assert lo <= 10.0 <= hi
    assert not lo <= naive <= hi


def test_family_choice_prefers_the_true_skewed_family():
    """A clearly skewed population (lognormal, σ_log 0.45; 20 tests) is told from a normal one by the
    leave-one-test-out criterion in at least 2 of 3 campaigns; all values are reported."""
    wins = 0
    for seed in range(3):
        rng = np.random.default_rng(100 + seed)
        draws, log_prior, _ = campaign(rng, lambda r, size: 10.0 * np.exp(0.45 * r.standard_normal(size)), 0.03,
                                       PRIOR_N_P, "log", n_tests=20, canopies=1, n=300)
        sel = select_family(draws, log_prior, ["normal", "lognormal"], rng, bounds=(2.0, 50.0), n_draws=500)
        assert set(sel.criterion) == {"normal", "lognormal"}
        wins += sel.chosen == "lognormal"
    assert wins >= 2


def test_low_effective_sample_size_is_warned_and_reported():
    """Seven well-measured tests near 10 and one poorly measured test (posterior N(13, 1)) that reaches the
    inferred population only in its tail: its reweighting sum rests on a few draws, and PoolWarning names it."""
    rng = np.random.default_rng(5)
    draws = [10.0 + 0.3 * rng.standard_normal() + 0.05 * rng.standard_normal(400) for _ in range(7)]
    draws.append(13.0 + 1.0 * rng.standard_normal(400))
    log_prior = [np.zeros(400) for _ in draws]
    with pytest.warns(PoolWarning, match="ESS < 20 .* T7 1"):
        pool = pool_parameter(draws, log_prior, "normal", rng, n_draws=500, tests=[f"T{i}" for i in range(8)])
    assert pool.low_ess == ["T7 1"]
    assert pool.ess[7] < 20 and np.all(pool.ess[:7] > 300)


# ---------------------------------------------------------------------------
# the correlated pair


def pair_campaign(rng, rho, n_tests=10, canopies=2, n=400):
    """(log n_p, expopen) bivariate normal population (median 10, σ_log 0.15; 2.2 ± 0.25; correlation ρ);
    each canopy's posterior correlated −0.5 within the test (a longer fill with a fuller profile fits alike)."""
    cov = np.array([[0.15**2, rho * 0.15 * 0.25], [rho * 0.15 * 0.25, 0.25**2]])
    values, log_prior = [], []
    for _ in range(n_tests):
        per = []
        truth = rng.multivariate_normal([math.log(10.0), 2.2], cov, size=canopies)
        for c in range(canopies):
            sd = np.array([0.02, 0.08]) * rng.uniform(0.5, 2.0, 2)
            like = np.array([[sd[0] ** 2, -0.5 * sd[0] * sd[1]], [-0.5 * sd[0] * sd[1], sd[1] ** 2]])
            y = rng.multivariate_normal(truth[c], like)
            out = np.empty((0, 2))
            while out.shape[0] < n:
                z = rng.multivariate_normal(y, like, size=8 * n)
                x = np.column_stack([np.exp(z[:, 0]), z[:, 1]])
                x = x[(x[:, 1] > 0.3) & (x[:, 1] < 8.0) & (x[:, 0] > 2.0) & (x[:, 0] < 50.0)]
                log_w = PRIOR_N_P.logpdf(x[:, 0]) + np.log(x[:, 0]) + PRIOR_EXPOPEN.logpdf(x[:, 1])
                out = np.concatenate([out, x[np.log(rng.uniform(size=len(x))) < log_w - log_w.max()]])
            per.append(out[:n])
        x = np.stack(per)
        values.append(x)
        log_prior.append(PRIOR_N_P.logpdf(x[..., 0]) + PRIOR_EXPOPEN.logpdf(x[..., 1]))
    return PerTestDraws.from_arrays(values, log_prior, rng)


def _pair(rng, data):
    m1 = pool_parameter(PerTestDraws(data.values[..., 0], PRIOR_N_P.logpdf(data.values[..., 0]), data.mask,
                                     data.tests), None, "lognormal", rng, bounds=(2.0, 50.0), n_draws=2000)
    m2 = pool_parameter(PerTestDraws(data.values[..., 1], PRIOR_EXPOPEN.logpdf(data.values[..., 1]), data.mask,
                                     data.tests), None, "normal", rng, bounds=(0.3, 8.0), n_draws=2000)
    return pool_pair(data, (m1, m2), rng, n_draws=2000)


def test_pair_recovers_a_population_correlation():
    """ρ = 0.6 between log n_p and expopen over 10 tests × 2 canopies. With 20 canopies ρ̂ scatters by about
    (1 − ρ²)/√20 ≈ 0.14, so its 90 % interval should hold 0.6 in ≥ 4 of 5 campaigns (P(≤ 3 | 0.9) = 8 %)
    and exclude 0 in ≥ 4 of 5; the criterion should keep the correlation in ≥ 3 of 5."""
    covered = excludes_zero = kept = 0
    for seed in range(5):
        rng = np.random.default_rng(200 + seed)
        pair = _pair(rng, pair_campaign(rng, 0.6))
        lo, hi = pair.rho_interval
        covered += lo <= 0.6 <= hi
        excludes_zero += lo > 0
        kept += pair.keep
        assert -1 < lo < pair.rho_median < hi < 1
        assert pair.predictive.shape == (2000, 2)
    assert covered >= 4 and excludes_zero >= 4 and kept >= 3


def test_pair_without_correlation_covers_zero():
    """ρ = 0: the 90 % interval holds 0 in ≥ 2 of 3 campaigns (P(≤ 1 | 0.9) = 2.8 %)."""
    covered = 0
    for seed in range(3):
        rng = np.random.default_rng(300 + seed)
        pair = _pair(rng, pair_campaign(rng, 0.0))
        covered += pair.rho_interval[0] <= 0.0 <= pair.rho_interval[1]
    assert covered >= 2


# ---------------------------------------------------------------------------
# fit folders, pool_fits and the command line


def write_fit_folder(folder, model, rng, name, seed, n_draws=800):
    """A fit folder written by the package's own writers (posterior.nc, summary.json) whose posterior is a
    narrow Gaussian around a per-test truth drawn from the fit priors' central range — what
    ``cpas-bayes fit`` leaves, without the minutes of sampling."""
    import arviz as az

    from cpas_bayes.inference.fit import SamplerOptions
    from cpas_bayes.inference.fit_folder import POSTERIOR_NAME, build_summary, save_datatree, write_summary

    truth, width = [], []
    for p in model.parameters:
        lo, hi = p.prior.support
        if p.name.endswith(".start"):
            value, sd = p.prior.ppf(0.5), 0.005
        elif p.group == "inflation":
            value = float(p.prior.ppf(np.clip(0.5 + 0.12 * rng.standard_normal(), 0.05, 0.95)))
            sd = 0.01 * abs(value)
        else:
            value, sd = float(p.prior.ppf(0.5)), 1e-3 * abs(float(p.prior.ppf(0.5)))
        truth.append(value)
        width.append(sd)
        assert lo < value < hi
    theta = np.array(truth) + np.array(width) * rng.standard_normal((n_draws, len(truth)))
    low = [lo + 1e-9 * (1 + abs(lo)) if math.isfinite(lo) else -math.inf
           for lo in (p.prior.support[0] for p in model.parameters)]
    high = [hi - 1e-9 * (1 + abs(hi)) if math.isfinite(hi) else math.inf
            for hi in (p.prior.support[1] for p in model.parameters)]
    theta = np.clip(theta, low, high)
    assert np.all(np.isfinite(model.log_prior(theta)))
    posterior = {n: theta[:, i].reshape(2, -1) for i, n in enumerate(model.names)}
    for n, v in model.derived(theta).items():
        posterior.setdefault(n, v.reshape(2, -1))
    tree = az.from_dict({"posterior": posterior}, check_conventions=False)
    tree.attrs["test"] = name          # as the fit's own DataTree names its test
    folder.mkdir(parents=True)
    save_datatree(tree, folder / POSTERIOR_NAME)
    summary = build_summary(model, tree, {"converged": True}, SamplerOptions(seed=seed))
    summary["test"] = name
    write_summary(folder, summary)
    return folder


@pytest.fixture(scope="module")
def fit_folders(tmp_path_factory):
    from cpas_bayes.data.bundle import EXAMPLES_DIR, read_bundle
    from cpas_bayes.inference.fit import prepare_model

    from cpas_bayes.data.reduction import reduce_test

    test = read_bundle(EXAMPLES_DIR / "drogue-clean")
    model = prepare_model(test, reduce_test(test))
    root = tmp_path_factory.mktemp("fits")
    rng = np.random.default_rng(7)
    return [write_fit_folder(root / f"fit{i}", model, rng, f"EX-drogue-{i}", seed=10 + i) for i in range(3)]


@pytest.fixture(scope="module")
def pooled(fit_folders, tmp_path_factory):
    """``cpas-bayes pool`` over the three folders: (exit status, output folder)."""
    out = tmp_path_factory.mktemp("memo") / "memo"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoolWarning)
        status = main(["pool", *map(str, fit_folders), "--out", str(out), "--seed", "3"])
    return status, out


def test_cli_pool_writes_a_memo_that_loads(pooled, fit_folders):
    status, out = pooled
    assert status == 0
    memo = load_memo(out)
    assert memo.provenance["tests"] == ["EX-drogue-0", "EX-drogue-1", "EX-drogue-2"]
    assert memo.provenance["seeds"] == [10, 11, 12]
    assert "reweighted" in memo.provenance["method"]
    stage_params = {"n_p", "n", "expopen", "ck", "tk", "t_fp"}
    assert {p for k, s, p in memo.entries if s == "first"} == stage_params | {"eps"}
    assert {p for k, s, p in memo.entries if s == "full_open"} == stage_params
    assert memo.entry("drogue", "parachute", "cd_o").n_tests == 3
    for e in memo.entries.values():
        q = [e.quantiles[k] for k in ("q01", "q05", "q50", "q95", "q99")]
        assert np.all(np.diff(q) >= 0) and e.bounds[0] <= q[0] and q[-1] <= e.bounds[1]
        if e.parameter != "t_fp":
            assert set(e.criterion["values"]) >= {"normal", "truncnormal", "lognormal"}
            assert e.family == max(e.criterion["values"], key=e.criterion["values"].get)
    t_fp = memo.entry("drogue", "first", "t_fp")
    assert t_fp.family == "uniform" and t_fp.bounds == (t_fp.params["low"], t_fp.params["high"])
    # the pair's correlation travels with n_p and expopen
    corr = memo.entry("drogue", "first", "n_p").criterion["correlation"]
    assert corr["with"] == "expopen" and corr["rho_q05"] <= corr["rho"] <= corr["rho_q95"]
    # joint draws: one row per parachute, the drawn (not the derived) parameters
    draws = memo.draws
    assert set(draws["kind"]) == {"drogue"} and len(draws) == 10000
    assert "first.n_p" in draws and "parachute.cd_o" in draws
    assert "first.n" not in draws and "first.t_fp" not in draws and "full_open.eps" not in draws
    rows = memo.sample("drogue", 5, np.random.default_rng(0))
    assert rows.shape == (5, len(draws.columns) - 1)
    # the memo's quantiles are those of its draws
    e = memo.entry("drogue", "first", "ck")
    assert e.quantiles["q50"] == pytest.approx(float(np.median(draws["first.ck"])), rel=1e-9)


def test_cli_pool_writes_the_table_and_forest_plots(pooled):
    _, out = pooled
    md = (out / "memo.md").read_text()
    assert "| kind | stage | parameter | family | parameters | 5 % | 50 % | 95 % | n_tests |" in md
    assert "| drogue | first | n_p |" in md and "leave-one-test-out" in md and "rho" in md
    for name in ("pool_drogue_first.png", "pool_drogue_full_open.png", "pool_drogue_parachute.png",
                 "pair_drogue_first.png"):
        assert (out / name).stat().st_size > 10_000


def test_cli_pool_refuses_a_folder_that_is_not_a_fit(fit_folders, tmp_path, capsys):
    stray = tmp_path / "not-a-fit"
    stray.mkdir()
    out = tmp_path / "memo"
    status = main(["pool", str(fit_folders[0]), str(stray), "--out", str(out)])
    err = capsys.readouterr().err
    assert status == 2
    assert str(stray) in err and "not a fit folder" in err and "Traceback" not in err
    assert not out.exists()


def test_a_fit_folder_holding_another_tests_posterior_is_refused(fit_folders, tmp_path):
    """posterior.nc names its test; a file copied in from another fit would pool that test twice."""
    mixed = Path(shutil.copytree(fit_folders[0], tmp_path / "mixed"))
    shutil.copy(Path(fit_folders[1]) / "posterior.nc", mixed / "posterior.nc")
    other = load_fit(fit_folders[1]).summary["test"]
    with pytest.raises(InputError, match=f"the posterior is of test '{other}', but summary.json is of"):
        load_fit(mixed)


def test_pool_fits_refuses_the_same_test_twice(fit_folders):
    records = [load_fit(fit_folders[0]), load_fit(fit_folders[0])]
    with pytest.raises(InputError, match="already pooled"):
        pool_fits(records, np.random.default_rng(0))


def test_pool_fits_uses_each_parameters_own_per_test_prior(fit_folders):
    """cd_o is pooled with the kind's cd_o prior (the fit's CDS_o prior unscaled), n with the induced
    π(n | o) = π(n_p)·n_p/n: the pooled median of cd_o sits among the canopies' cd_o = CDS_o/S_o."""
    records = [load_fit(f) for f in fit_folders[:2]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoolWarning)
        result = pool_fits(records, np.random.default_rng(1), n_draws=2000, correlate=False, families=["normal"])
    cd = result.entries[("drogue", "parachute", "cd_o")]
    area = math.pi / 4 * records[0].summary["parachutes"]["D3"]["diameter_m"] ** 2
    medians = [np.median(r.draws[f"{pid}.cds_o"]) / area for r in records for pid in ("D3", "D6")]
    np.testing.assert_allclose(sorted(cd.per_canopy["median"]), sorted(medians), rtol=1e-3)
    assert min(medians) - 0.05 < cd.quantiles["q50"] < max(medians) + 0.05
    n = result.entries[("drogue", "first", "n")]
    assert np.all(n.per_canopy["median"] < result.entries[("drogue", "first", "n_p")].per_canopy["median"])
    assert result.pairs == {} and len(result.ess_table()) == 2 * len(result.entries)


def test_pooling_fits_in_memory_gives_the_memo_of_pooling_their_folders(tmp_path):
    """A notebook's route: ``fit_model`` results pooled without reading folders. Two small real fits (one
    ensemble, 1000 steps) of the example Drogue test under two names, each also written to a folder by the
    same call: the in-memory records hold what ``load_fit`` reads back, and pooling them (one as a
    ``FitRecord.from_fit``, one as the bare ``Fit``) gives byte for byte the memo.toml, memo_draws.csv and
    memo.md of pooling the folders with the same seed."""
    from cpas_bayes.data.bundle import EXAMPLES_DIR, read_bundle
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit import SamplerOptions, fit_model, prepare_model
    from cpas_bayes.outputs.memo import memo_markdown

    test = read_bundle(EXAMPLES_DIR / "drogue-clean")
    reduction = reduce_test(test)
    fits, folders = [], []
    for i in range(2):
        model = prepare_model(replace(test, name=f"MEM-drogue-{i}"), reduction)
        options = SamplerOptions(seed=i, n_ensembles=1, max_steps=1000, check_every=500, map_starts=2, workers=1,
                                 progress=False)
        fits.append(fit_model(model, options, out=tmp_path / f"fit{i}"))
        folders.append(tmp_path / f"fit{i}")
    for fit, folder in zip(fits, folders):
        in_memory, on_disk = FitRecord.from_fit(fit), load_fit(folder)
        assert in_memory.folder is None and in_memory.summary == on_disk.summary
        assert in_memory.priors == on_disk.priors and in_memory.draws.keys() == on_disk.draws.keys()
        assert all(np.array_equal(in_memory.draws[k], on_disk.draws[k]) for k in on_disk.draws)
    results = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoolWarning)
        for route, records in (("memory", [FitRecord.from_fit(fits[0]), fits[1]]),
                               ("folders", [load_fit(f) for f in folders])):
            results[route] = pool_fits(records, np.random.default_rng(3), n_draws=2000)
    assert results["memory"].folders == [None, None] and results["folders"].folders == folders
    provenance = {"created": "2026-01-01T00:00:00Z"}
    for route, result in results.items():
        memo = result.to_memo(provenance)
        memo.write(tmp_path / route)
        (tmp_path / route / "memo.md").write_text(memo_markdown(result, memo.provenance))
    for name in ("memo.toml", "memo_draws.csv", "memo.md"):
        assert (tmp_path / "memory" / name).read_bytes() == (tmp_path / "folders" / name).read_bytes(), name
    assert load_memo(tmp_path / "memory").entry("drogue", "first", "n_p").n_tests == 2


# ---------------------------------------------------------------------------
# end to end on real fits (slow)

POPULATION = {"n_p": (10.5, 0.12), "expopen": (2.2, 0.20), "ck": (1.30, 0.06), "rho": 0.5}


def campaign_test(seed, population_rng):
    """A two-Drogue test whose first-stage n_p, expopen (Gaussian copula, ρ = 0.5 between log n_p and
    expopen) and C_k are drawn from POPULATION; everything else as ``synthesize("drogue", "none", seed)``."""
    from cpas_bayes.data.synth import draw_truth, random_streams, simulate_test

    truth_rng, _, noise_rng = random_streams(seed)
    truth = draw_truth("drogue", truth_rng)
    rho = POPULATION["rho"]
    chutes = []
    for chute in truth.chutes:
        z = population_rng.multivariate_normal([0.0, 0.0], [[1.0, rho], [rho, 1.0]])
        first = replace(chute.stages[0],
                        n_p=float(POPULATION["n_p"][0] * math.exp(POPULATION["n_p"][1] * z[0])),
                        expopen=float(POPULATION["expopen"][0] + POPULATION["expopen"][1] * z[1]),
                        ck=float(population_rng.normal(*POPULATION["ck"])))
        chutes.append(replace(chute, stages=(first,) + chute.stages[1:]))
    truth = replace(truth, chutes=tuple(chutes))
    test, _ = simulate_test(truth, "none", {}, noise_rng, name=f"POP-drogue-{seed}")
    return test, truth


@pytest.mark.slow
def test_population_is_recovered_from_real_fits_of_a_synthetic_campaign(tmp_path):
    """Eight two-Drogue tests (16 canopies) simulated from POPULATION, fitted (2 ensembles, ≤ 2000 steps),
    pooled. One campaign cannot show calibration (the synthetic-posterior tests do that over many);
    here the checks are that the fits and the pooling together find the population:

    * the 90 % hyper-posterior interval of the population mean holds the mean of the 16 true values
      (the realised campaign: only fit and pooling errors can move it out), and the true population mean
      lies in the 99 % interval;
    * the population sd's posterior median is within 0.5–2× the truth (16 draws: the realised sd alone
      scatters ±18 %);
    * the (n_p, expopen) correlation's 90 % interval holds the realised correlation of the true values.
    """
    from cpas_bayes.inference.fit import SamplerOptions, fit_test

    population_rng = np.random.default_rng(2024)
    truths, folders = [], []
    for seed in range(8):
        test, truth = campaign_test(seed, population_rng)
        folder = tmp_path / f"fit{seed}"
        fit_test(test, SamplerOptions(seed=seed, n_ensembles=2, max_steps=2000, progress=False, workers=1),
                 out=folder)
        truths.append(truth)
        folders.append(folder)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoolWarning)
        result = pool_fits([load_fit(f) for f in folders], np.random.default_rng(0), n_draws=4000)
    true_values = {p: np.array([getattr(c.stages[0], p) for t in truths for c in t.chutes])
                   for p in ("n_p", "expopen", "ck")}
    pop_mean = {"n_p": 10.5 * math.exp(0.12**2 / 2), "expopen": 2.2, "ck": 1.30}
    pop_sd = {"n_p": pop_mean["n_p"] * math.sqrt(math.expm1(0.12**2)), "expopen": 0.20, "ck": 0.06}
    report = {}
    for p in ("n_p", "expopen", "ck"):
        pool = result.entries[("drogue", "first", p)].pool
        lo90, med, hi90 = pool.interval("mean", 0.90)
        lo99, _, hi99 = pool.interval("mean", 0.99)
        sd_med = pool.interval("sd")[1]
        report[p] = (lo90, med, hi90, float(true_values[p].mean()), sd_med, pop_sd[p])
        assert lo90 <= true_values[p].mean() <= hi90, report
        assert lo99 <= pop_mean[p] <= hi99, report
        assert 0.5 < sd_med / pop_sd[p] < 2.0, report
    pair = result.pairs[("drogue", "first")]
    realised = np.corrcoef(np.log(true_values["n_p"]), true_values["expopen"])[0, 1]
    assert pair.rho_interval[0] <= realised <= pair.rho_interval[1], (pair.rho_interval, realised)
    out = tmp_path / "memo"
    assert main(["pool", *map(str, folders), "--out", str(out)]) == 0
    assert load_memo(out).entry("drogue", "first", "n_p").n_tests == 8


def test_a_composite_fit_is_pooled_as_one_canopy_per_group(tmp_path):
    """In the composite form a cluster's like canopies share one set of parameters, and each member's
    variables repeat the group's draws: the pool takes the group once per test (not zero times, as when it
    looked for the members' own priors, nor twice)."""
    from cpas_bayes.data.bundle import EXAMPLES_DIR, read_bundle
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit import prepare_model

    test = read_bundle(EXAMPLES_DIR / "drogue-clean")
    model = prepare_model(test, reduce_test(test), cluster="composite")
    rng = np.random.default_rng(11)
    records = [load_fit(write_fit_folder(tmp_path / f"fit{i}", model, rng, f"EX-c{i}", seed=20 + i))
               for i in range(3)]
    assert records[0].parameter_prefix("D3") == records[0].parameter_prefix("D6") == "cluster.drogue"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoolWarning)
        result = pool_fits(records, np.random.default_rng(2), n_draws=2000, correlate=False, families=["normal"])
    for key in (("drogue", "parachute", "cd_o"), ("drogue", "first", "n_p"), ("drogue", "first", "n"),
                ("drogue", "first", "eps"), ("drogue", "full_open", "expopen")):
        table = result.entries[key].per_canopy
        assert len(table) == 3, key
    area = math.pi / 4 * records[0].summary["parachutes"]["D3"]["diameter_m"] ** 2
    medians = sorted(np.median(r.draws["cluster.drogue.cds_o"]) / area for r in records)
    np.testing.assert_allclose(sorted(result.entries[("drogue", "parachute", "cd_o")].per_canopy["median"]),
                               medians, rtol=1e-3)


@pytest.mark.parametrize("kind, problem", [("missing", "not found"), ("file", "is a file, not a fit folder"),
                                           ("broken link", "is a link to nothing (a broken symbolic link")])
def test_read_summary_says_what_stands_in_place_of_a_fit_folder(tmp_path, kind, problem):
    from cpas_bayes.inference.fit_folder import read_summary

    path = tmp_path / "fit"
    if kind == "file":
        path.write_text("x")
    elif kind == "broken link":
        path.symlink_to(tmp_path / "gone")
    with pytest.raises(InputError) as err:
        read_summary(path)
    assert err.value.problem.startswith(problem), str(err.value)

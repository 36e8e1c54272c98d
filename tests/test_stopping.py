"""The ESS stopping rule: its statistics on chains of known ESS, its decision, resume, and recovery.

Tolerances. For a Gaussian AR(1) chain with coefficient φ the ESS of the mean
is N·(1 − φ)/(1 + φ) and τ = (1 + φ)/(1 − φ); the tail ESS (indicators of the
5 % and 95 % quantiles) is N/(1 + 2 Σ_k ρ_k) with ρ_k the correlation of
I(x_t ≤ q) and I(x_{t+k} ≤ q), a bivariate-normal orthant probability at
correlation φ^k. With 8 chains × 2000 draws the estimators scatter by about
5 % (bulk, τ) and 8 % (tail) over seeds; the bands below are about ±3 sd, wide
enough for chance and narrow enough to catch an estimator off by a factor
such as (1 + φ) or one that ignores the autocorrelation (a factor 3 at φ = 0.5).
"""

import json

import emcee
import numpy as np
import pytest
from scipy.stats import multivariate_normal, norm

from cpas_bayes.data.bundle import example_bundles, read_bundle
from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.data.synth import truth_parameter_values
from cpas_bayes.inference.fit import SamplerOptions, fit_model, prepare_model, run_ensemble, run_ensembles
from cpas_bayes.inference.stopping import (KEPT_DRAWS, TAIL_QUANTILES, burn_and_thin, chain_statistics, ess_check,
                                           integrated_time, pool_kept)

PHI = 0.5


def _ar1(rng, phi, chains, draws, params):
    x = np.empty((chains, draws, params))
    x[:, 0] = rng.standard_normal((chains, params))
    noise = rng.standard_normal((chains, draws, params)) * np.sqrt(1 - phi**2)
    for t in range(1, draws):
        x[:, t] = phi * x[:, t - 1] + noise[:, t]
    return x


def _tail_ess_per_draw(phi, p=0.05):
    q, s = norm.ppf(p), 0.0
    for k in range(1, 200):
        r = phi**k
        if r < 1e-10:
            break
        joint = multivariate_normal(mean=[0, 0], cov=[[1, r], [r, 1]]).cdf([q, q])
        s += (joint - p * p) / (p * (1 - p))
    return 1 / (1 + 2 * s)


def test_ess_and_tau_of_ar1_chains_match_their_analytic_values():
    x = _ar1(np.random.default_rng(0), PHI, 8, 2000, 4)
    n = x.shape[0] * x.shape[1]
    stats = chain_statistics(x, np.repeat(np.arange(4), 2))
    np.testing.assert_allclose(stats.ess_bulk / (n * (1 - PHI) / (1 + PHI)), 1, atol=0.15)
    np.testing.assert_allclose(stats.ess_tail / (n * _tail_ess_per_draw(PHI)), 1, atol=0.25)
    assert np.all(stats.rhat < 1.01)
    tau = integrated_time(np.swapaxes(x, 0, 1), store_every=5)   # (S, W, D); τ in steps of 5
    np.testing.assert_allclose(tau / (5 * (1 + PHI) / (1 - PHI)), 1, atol=0.2)


def test_nested_rhat_sees_an_ensemble_that_sits_elsewhere():
    x = _ar1(np.random.default_rng(1), PHI, 8, 1000, 2)
    ensemble = np.repeat(np.arange(4), 2)
    assert chain_statistics(x, ensemble).meets(1000, 1.01)
    x[ensemble == 3, :, 1] += 0.3            # one ensemble 0.3 sd off in the second parameter
    stats = chain_statistics(x, ensemble)
    assert stats.rhat[0] < 1.01 < stats.rhat[1]
    assert not stats.meets(1000, 1.01)
    assert not stats.meets(1e6, 2.0)         # and an unreachable ESS is not met either


def test_burn_in_is_half_the_chain_under_the_ess_rule_and_two_tau_under_the_tau_rule():
    tau = np.array([40.0, 100.0])
    assert burn_and_thin(tau, 5) == (40, 4)
    assert burn_and_thin(tau, 5, n_stored=1000) == (500, 4)
    assert burn_and_thin(tau, 5, n_stored=60) == (40, 4)
    # the cap on kept draws: 500 kept steps of 60 walkers would be 7,500 draws per ensemble
    burn, thin = burn_and_thin(tau, 5, n_stored=1000, walkers=60)
    assert burn == 500 and thin > 4
    assert len(range(burn, 1000, thin)) * 60 <= KEPT_DRAWS < len(range(burn, 1000, thin - 1)) * 60
    assert burn_and_thin(tau, 5, n_stored=60, walkers=60) == (40, 4)   # few draws: τ's thinning only
    # too short to say anything: not met, no statistics
    assert not ess_check([np.zeros((6, 4, 2)) + np.arange(6)[:, None, None]] * 2, 5).met


def test_the_rule_uses_the_statistics_the_summary_reports():
    import arviz as az

    x = _ar1(np.random.default_rng(2), 0.3, 8, 300, 3)
    ensemble = np.repeat(np.arange(4), 2)
    tree = az.from_dict({"posterior": {f"p{i}": x[:, :, i] for i in range(3)}})
    names = ["p0", "p1", "p2"]
    stats = chain_statistics(x, ensemble)
    ours = [stats.ess_bulk, stats.ess_tail, stats.rhat]
    theirs = [az.ess(tree, var_names=names, method="bulk"),
              az.ess(tree, var_names=names, method="tail", prob=TAIL_QUANTILES),
              az.rhat_nested(tree, var_names=names, superchain_ids=ensemble)]
    for a, b in zip(ours, theirs):
        np.testing.assert_allclose(a, [float(b[n]) for n in names], rtol=1e-12)


class Correlated:
    """A correlated 3-D Gaussian log density, vectorised as emcee calls it (a pickle-able model)."""

    names = ["a", "b", "c"]

    def __init__(self):
        self.precision = np.linalg.inv(np.array([[1, 0.8, 0], [0.8, 1, 0.3], [0, 0.3, 1.0]]))

    def __call__(self, theta):
        return -0.5 * np.einsum("ni,ij,nj->n", theta, self.precision, theta)


def _toy(n_ensembles=4, walkers=8):
    rng = np.random.default_rng(0)
    inits = [rng.normal(size=(walkers, 3)) for _ in range(n_ensembles)]
    return Correlated(), inits, list(range(1, n_ensembles + 1))


def _ess_options(target, proposal="de", **kw):
    """The ESS rule's mechanics on DE alone (chunks of one kernel), unless a test asks for the adaptive proposal."""
    return SamplerOptions(stop="ess", ess_target=target, check_every=100, store_every=1, max_steps=20000,
                          proposal=proposal, **kw)


def test_an_easy_target_stops_earlier_than_a_hard_one():
    model, inits, seeds = _toy()
    easy, seen_easy = run_ensembles(model, inits, seeds, _ess_options(300))
    hard, seen_hard = run_ensembles(model, inits, seeds, _ess_options(3000))
    assert easy[0].steps < hard[0].steps < 20000
    assert all(r.steps == easy[0].steps and r.converged for r in easy)
    for seen, target in ((seen_easy, 300), (seen_hard, 3000)):
        assert seen["ess_bulk_min"] >= target and seen["ess_tail_min"] >= target and seen["rhat_max"] <= 1.01
    # τ is still estimated and reported; the kept draws are the second half of the chain
    assert all(np.all(r.tau > 1) for r in hard)
    assert hard[0].burn == hard[0].steps // 2
    # a target out of reach runs to the step limit and says it did not converge
    capped, _ = run_ensembles(model, inits, seeds, SamplerOptions(stop="ess", ess_target=10**6, check_every=100,
                                                                  store_every=1, max_steps=500, proposal="de"))
    assert capped[0].steps == 500 and not capped[0].converged


def test_the_ess_rule_draws_the_tau_rules_chain(tmp_path):
    """Lockstep chunks run in separate tasks continue the chain exactly as one sampler does."""
    import h5py

    model, inits, seeds = _toy()
    runs, _ = run_ensembles(model, inits, seeds, _ess_options(400),
                            checkpoints=[tmp_path / f"ensemble_{e}.h5" for e in range(4)])
    run_ensemble(model, inits[0], seeds[0], SamplerOptions(check_every=100, store_every=1, tau_factor=1e9,
                                                           max_steps=runs[0].steps), checkpoint=tmp_path / "tau.h5")
    with h5py.File(tmp_path / "ensemble_0.h5") as a, h5py.File(tmp_path / "tau.h5") as b:
        np.testing.assert_array_equal(a["mcmc"]["chain"][...], b["mcmc"]["chain"][...])


@pytest.mark.parametrize("proposal", ["de", "adaptive", "pooled"])
def test_an_interrupted_ess_run_resumes_to_the_same_draws(tmp_path, proposal):
    """A kill mid-round leaves ensembles at different chunks; the rerun catches up, replays the checks (and
    refits the adaptive proposal from the same stored draws) and ends with the draws of an uninterrupted run."""
    model, inits, seeds = _toy()
    # targets the rule reaches after the 300-step interruption (800 steps adaptive): one beyond the kept-draws
    # cap (stopping.KEPT_DRAWS per ensemble) would run both fits to max_steps, minutes for nothing
    options = _ess_options(1500 if proposal == "de" else 4000, proposal=proposal)
    uninterrupted, seen = run_ensembles(model, inits, seeds, options)
    ckpts = [tmp_path / f"ensemble_{e}.h5" for e in range(4)]
    part = SamplerOptions(stop="ess", ess_target=options.ess_target, check_every=100, store_every=1, max_steps=300,
                          proposal=proposal)
    run_ensembles(model, inits, seeds, part, checkpoints=ckpts)
    shorter = tmp_path / "shorter"
    shorter.mkdir()
    run_ensembles(model, inits[:2], seeds[:2], SamplerOptions(stop="ess", check_every=100, store_every=1,
                                                               max_steps=50, proposal=proposal),
                  checkpoints=[shorter / "a.h5", shorter / "b.h5"])
    (shorter / "b.h5").replace(ckpts[1])      # ensemble 1 one chunk behind the others, as a kill leaves it
    resumed, seen_resumed = run_ensembles(model, inits, seeds, options, checkpoints=ckpts)
    assert uninterrupted[0].steps > 300
    assert seen_resumed == seen
    for a, b in zip(uninterrupted, resumed):
        assert a.steps == b.steps
        np.testing.assert_array_equal(a.draws, b.draws)
        np.testing.assert_array_equal(a.tau, b.tau)


def test_the_adaptive_proposal_cuts_tau_and_samples_the_same_target():
    """After its warm-up (one DE chunk, adaptation chunks until the acceptance stops rising) the independence
    proposal fitted to each ensemble's own draws leaves τ at a few steps where DE alone needs about twelve; the
    kept draws come after the warm-up and recover the target's covariance; a run too short for the warm-up uses
    DE alone."""
    model, inits, seeds = _toy(walkers=12)
    de, _ = run_ensembles(model, inits, seeds, _ess_options(2000))
    adaptive, seen = run_ensembles(model, inits, seeds, _ess_options(2000, proposal="adaptive"))
    assert np.max([r.tau for r in adaptive]) < np.min([np.max(r.tau) for r in de]) / 3
    assert seen["proposal"] == "adaptive" and seen["ess_bulk_min"] >= 2000 and seen["rhat_max"] <= 1.01
    assert all(r.burn >= 100 for r in adaptive)                  # warm-up of at least 50 + 2·25 steps dropped
    flat = np.concatenate([r.draws.reshape(-1, 3) for r in adaptive])
    truth = np.linalg.inv(model.precision)
    np.testing.assert_allclose(np.cov(flat.T), truth, atol=0.08)
    assert np.all(np.abs(flat.mean(axis=0)) < 0.06)
    short, _ = run_ensembles(model, inits, seeds, SamplerOptions(stop="ess", ess_target=10**6, check_every=100,
                                                                 store_every=1, max_steps=100, proposal="adaptive"))
    plain, _ = run_ensembles(model, inits, seeds, SamplerOptions(stop="ess", ess_target=10**6, check_every=100,
                                                                 store_every=1, max_steps=100, proposal="de"))
    np.testing.assert_array_equal(short[0].draws, plain[0].draws)


def test_the_pooled_proposal_is_one_fit_to_every_ensembles_window_and_samples_the_same_target():
    """proposal="pooled": every ensemble gets the proposal fitted to all ensembles' warm-up windows (one
    that has not crossed a slow direction reaches where the others are); the kept draws still recover
    the target."""
    from types import SimpleNamespace

    from cpas_bayes.inference import warm_up
    from cpas_bayes.inference.moves import fit_proposal

    rng = np.random.default_rng(3)
    chains = [rng.normal(loc, 1.0, size=(40, 8, 3)) for loc in (0.0, 2.0)]   # (steps, walkers, D), apart
    stores = [SimpleNamespace(model=None, sampler=SimpleNamespace(
        ndim=3, backend=SimpleNamespace(get_chain=lambda discard=0, c=c: c[discard:]))) for c in chains]
    pooled = warm_up.fit_proposals(stores, (10, 40), pooled=True)
    own = warm_up.fit_proposals(stores, (10, 40))
    both = fit_proposal(np.concatenate([c[10:40].reshape(-1, 3) for c in chains]))
    assert pooled[0] is pooled[1]
    np.testing.assert_allclose(pooled[0][0], both[0])
    np.testing.assert_allclose(pooled[0][1], both[1])
    np.testing.assert_allclose(own[1][0], chains[1][10:40].reshape(-1, 3).mean(axis=0))

    model, inits, seeds = _toy(walkers=12)
    runs, seen = run_ensembles(model, inits, seeds, _ess_options(2000, proposal="pooled"))
    assert seen["proposal"] == "pooled" and seen["ess_bulk_min"] >= 2000 and seen["rhat_max"] <= 1.01
    flat = np.concatenate([r.draws.reshape(-1, 3) for r in runs])
    np.testing.assert_allclose(np.cov(flat.T), np.linalg.inv(model.precision), atol=0.08)
    assert np.all(np.abs(flat.mean(axis=0)) < 0.06)


def test_options_refuse_an_unknown_rule_or_target():
    with pytest.raises(ValueError, match="proposal must be one of"):
        SamplerOptions(proposal="hmc")
    with pytest.raises(ValueError, match="stop must be one of"):
        SamplerOptions(stop="rhat")
    with pytest.raises(ValueError, match="ess_target"):
        SamplerOptions(stop="ess", ess_target=0)


def test_a_fit_stopped_by_ess_covers_the_truth_and_reports_what_it_stopped_on(tmp_path):
    """The drogue example under stop="ess": the summary's ESS and R-hat meet the targets (same draws, same
    statistics), the steps are far fewer than the τ rule's ~5,000, and the 90 % intervals cover the known truth
    (29 parameters, about 10 effectively independent: coverage below 0.7 is a 2.5-sd miss)."""
    path = next(p for p in example_bundles() if p.name.startswith("drogue"))
    test = read_bundle(path)
    truth = truth_parameter_values(test, json.loads((path / "truth.json").read_text()))
    model = prepare_model(test, reduce_test(test))
    options = SamplerOptions(seed=0, stop="ess", ess_target=400, workers=2, progress=False)
    fit = fit_model(model, options, out=tmp_path / "fit")
    d = fit.summary["diagnostics"]
    assert d["ess_bulk_min"] >= 400 and d["ess_tail_min"] >= 400 and d["rhat_max"] <= 1.01, d
    assert d["converged"] and max(d["steps"]) < 3000
    assert fit.summary["sampler"]["stop"] == "ess"
    post = fit.tree["posterior"]
    inside, z = [], []
    for name in model.names:
        if name in truth:
            x = np.asarray(post[name].values).ravel()
            lo, hi = np.quantile(x, [0.05, 0.95])
            inside.append(lo <= truth[name] <= hi)
            z.append((truth[name] - x.mean()) / x.std())
    assert np.mean(inside) >= 0.7, np.mean(inside)
    assert np.sqrt(np.mean(np.square(z))) < 1.5


def test_the_ess_rule_waits_for_a_growing_tau_but_not_for_a_falling_one():
    """τ̂ that grew by more than tau_rtol since the last check is the start-up transient's sign; one that
    fell (the half-chain burn-in dropped an early stretch) or moved within its noise is not."""
    rng = np.random.default_rng(5)
    chains = [np.moveaxis(_ar1(rng, 0.5, 20, 400, 2), 0, 1) for _ in range(4)]   # (S, W, D) per ensemble
    first = ess_check(chains, 5, ess_target=200)
    assert not first.met and first.statistics.meets(200, 1.01)                # no previous τ: not yet
    tau_max = max(float(np.max(t)) for t in first.taus)

    def met(previous_tau_max):
        return ess_check(chains, 5, ess_target=200, tau_prev=[np.full(2, previous_tau_max)]).met

    assert met(1.5 * tau_max)                 # fell by a third: settled
    assert met(tau_max / 1.04)                # grew by 4 %: within tau_rtol
    assert not met(tau_max / 1.10)            # grew by 10 %: still growing


def test_the_ess_rule_can_ask_only_the_parameters_a_question_reads():
    """``columns``: a parameter the question does not read (here one whose ensembles sit 1 sd apart, R-hat
    well above 1.01) holds back the whole-model rule but not one asked only of the well-mixed parameter; the
    statistics reported are still every parameter's."""
    rng = np.random.default_rng(8)
    chains = [np.moveaxis(_ar1(rng, 0.5, 20, 400, 2), 0, 1) for _ in range(4)]   # (S, W, D) per ensemble
    for e, c in enumerate(chains):
        c[:, :, 1] += 1.0 * (e % 2)                      # parameter 1: two ensembles elsewhere
    first = ess_check(chains, 5, ess_target=200)
    settled = [np.full(2, 2 * max(float(np.max(t)) for t in first.taus))]
    whole = ess_check(chains, 5, ess_target=200, tau_prev=settled)
    asked = ess_check(chains, 5, ess_target=200, tau_prev=settled, columns=np.array([0]))
    assert not whole.met and asked.met
    assert asked.statistics.rhat[1] > 1.1 and asked.statistics.worst() == whole.statistics.worst()
    assert not ess_check(chains, 5, ess_target=200, tau_prev=settled, columns=np.array([1])).met


def test_stop_on_names_a_parameter_of_the_model_or_is_refused():
    """A run asked only of 'c' (the least correlated) meets that parameter's targets, and stops no later than
    the whole rule; a name the model lacks is refused before any step."""
    model, inits, seeds = _toy()
    whole, _ = run_ensembles(model, inits, seeds, _ess_options(1500))
    asked, seen = run_ensembles(model, inits, seeds, _ess_options(1500, stop_on=("c",)))
    assert asked[0].converged and asked[0].steps <= whole[0].steps < 20000
    c = chain_statistics(*pool_kept([np.swapaxes(r.draws, 0, 1) for r in asked]))   # as the rule pooled them
    assert c.ess_bulk[2] >= 1500 and c.ess_tail[2] >= 1500 and c.rhat[2] <= 1.01
    assert seen["ess_bulk_min"] == pytest.approx(float(np.min(c.ess_bulk)))     # reported: every parameter's
    with pytest.raises(ValueError, match="stop_on names 'nope', not a parameter of the model"):
        run_ensembles(model, inits, seeds, _ess_options(300, stop_on=("nope",)))


def test_the_warm_up_schedules():
    """Plateau (the default): chunks of a quarter check_every, at least 25 stored steps, a DE chunk of two; fixed
    (the diagnosis's fits): the DE chunk of check_every and exactly two adaptation chunks of half."""
    from cpas_bayes.inference.candidate_fits import DIAGNOSIS_SAMPLER
    from cpas_bayes.inference.warm_up import warm_up_schedule as _schedule

    plateau = _schedule(SamplerOptions())
    assert (plateau.de, plateau.step) == (50, 25) and plateau.adaptations[0] >= 2 < plateau.adaptations[1]
    assert (_schedule(SamplerOptions(check_every=250)).step, _schedule(SamplerOptions(check_every=2000)).step) == (25, 100)
    fixed = _schedule(DIAGNOSIS_SAMPLER)
    assert DIAGNOSIS_SAMPLER.warm_up == "fixed" and (fixed.de, fixed.step, fixed.adaptations) == (40, 20, (2, 2))
    assert _schedule(SamplerOptions(proposal="de")).de == 0
    with pytest.raises(ValueError, match="warm_up must be one of"):
        SamplerOptions(warm_up="long")


def test_the_acceptance_read_from_the_chain_is_emcees_own():
    """The plateau rule reads each chunk's acceptance from the stored chain (a resumed run has no per-chunk
    counts): with every step stored it is emcee's count of accepted moves."""
    from types import SimpleNamespace

    from cpas_bayes.inference.warm_up import chain_acceptance as _acceptance

    model, inits, seeds = _toy(n_ensembles=1, walkers=12)
    sampler = emcee.EnsembleSampler(12, 3, model, vectorize=True)
    sampler.random_state = np.random.RandomState(5).get_state()
    sampler.run_mcmc(inits[0], 2000, progress=False)
    emcees = np.mean(sampler.backend.accepted) / 2000
    assert _acceptance([SimpleNamespace(sampler=sampler)], 1, 2000, 1) == pytest.approx(emcees, abs=1e-3)
    # the same chain stored every fifth step: five moves between stored steps, so the share that moved is
    # 1 − (1 − a)^5, solved for a. Rejections come in runs (a walker in the tail refuses several proposals), so
    # the reading is a little low: a monotone measure, which is all a rule on its rise needs
    every_fifth = SimpleNamespace(backend=SimpleNamespace(get_chain=lambda: sampler.backend.get_chain()[4::5]))
    assert 0.8 < _acceptance([SimpleNamespace(sampler=every_fifth)], 1, 400, 5) / emcees < 1.0


def test_the_plateau_warm_up_stops_when_the_acceptance_stops_rising():
    """The warm-up ends at the first adaptation chunk (after the second) whose acceptance rose less than 10 %
    over the chunk before's, and the run reports its length; a proposal that keeps improving keeps it going."""
    from cpas_bayes.inference import warm_up

    model, inits, seeds = _toy(walkers=12)
    original, read = warm_up.chain_acceptance, []

    def recorded(stores, lo, hi, store_every):
        read.append(original(stores, lo, hi, store_every))
        return read[-1]

    def rising(stores, lo, hi, store_every):   # a proposal that keeps improving by 20 % a chunk, then stops
        read.append(min(0.1 * 1.2 ** (len(read) + 1), 0.3))
        return read[-1]

    try:
        warm_up.chain_acceptance = recorded
        runs, seen = run_ensembles(model, inits, seeds, _ess_options(2000, proposal="adaptive"))
        assert seen["warm_up_steps"] == 50 + 25 * len(read) and len(read) >= 2
        assert read[-1] < 1.1 * read[-2] and all(b >= 1.1 * a for a, b in zip(read[:-2], read[1:-1]))
        assert all(r.burn >= seen["warm_up_steps"] for r in runs)
        read.clear()
        warm_up.chain_acceptance = rising
        runs, seen = run_ensembles(model, inits, seeds, _ess_options(2000, proposal="adaptive"))
    finally:
        warm_up.chain_acceptance = original
    # 0.12, 0.144, 0.173, 0.207, 0.249, 0.299, 0.3: the seventh chunk rose < 10 %
    assert seen["warm_up_steps"] == 50 + 7 * 25 and len(read) == 7

"""Mode jumps between the pairings of like canopies (``inference.mode_jumps``, ``moves.ModeJumpMove``).

A label exchange lands on the other pairing's peak only where the data see nothing but the cluster's sum.
Where they see more, the other peak sits away from the exchanged point, and the plain exchange is refused;
the jump adds the offset between the exchanged MAP and the other pairing's optimum. Checked here: the law of
the move on a target whose mode weights are known and which the plain exchange cannot cross, the map's
involution and Jacobian in the sampler's coordinates of a real logger model, and the search for the other
pairing's optimum.
"""

import emcee
import numpy as np
import pytest

from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.data.synth_logger import synthesize_logger
from cpas_bayes.inference.coordinates import SamplerTarget, sampling_coordinates
from cpas_bayes.inference.fit import prepare_model
from cpas_bayes.inference.mode_jumps import ModeJump, mode_jumps, other_pairings, pairing_of
from cpas_bayes.inference.start import laplace_covariance
from cpas_bayes.inference.moves import ModeJumpMove, ensemble_moves
from cpas_bayes.stats.cluster_form import Exchange
from cpas_bayes.stats.distributions import Normal

SWAP = Exchange(("a", "b"), 0, np.array([0]), np.array([1]), *[np.empty(0, int)] * 4, np.empty(0), order=(0, 1))
SD_A, SD_B, WEIGHT = 0.2, 0.35, 0.7


def two_shifted_modes(x):
    """Modes at (1, 6, 0) and (6, 1, 3), weights 0.7 / 0.3, sds 0.2 / 0.35: the swap of the first two
    coordinates maps one onto the other only up to a shift of 3 in the third, 9–15 sds."""
    x = np.atleast_2d(x)
    a = (-0.5 * ((x[:, 0] - 1) ** 2 + (x[:, 1] - 6) ** 2 + x[:, 2] ** 2) / SD_A**2 + np.log(WEIGHT)
         - 3 * np.log(SD_A))
    b = (-0.5 * ((x[:, 0] - 6) ** 2 + (x[:, 1] - 1) ** 2 + (x[:, 2] - 3) ** 2) / SD_B**2 + np.log(1 - WEIGHT)
         - 3 * np.log(SD_B))
    return np.logaddexp(a, b)


class ShiftedModes:
    """:func:`two_shifted_modes` as a model: parameters with priors, vectorised log density, one exchange."""

    parameters = [type("P", (), {"prior": Normal(3.5, 10.0)})() for _ in range(3)]
    names = ["x0", "x1", "x2"]

    def __call__(self, x):
        return two_shifted_modes(x) + sum(p.prior.logpdf(np.atleast_2d(x)[:, i]) for i, p in enumerate(self.parameters))

    def exchanges(self):
        return [SWAP]


@pytest.mark.slow
def test_the_jump_weighs_two_modes_that_the_plain_exchange_cannot_cross():
    """All walkers start in the lighter mode. The plain exchange lands 9–15 sds from the other peak and is
    refused: no draw crosses. With the jump (from each mode's Gaussian onto the other's) the share of draws
    in the first mode is the target's 0.7 and each mode keeps its own width. 32 walkers × 3,000 kept
    steps; the share's standard error is below 0.01, so ±0.04 is four of them; a jump that skipped the
    Metropolis test or the refusal of a non-crossing map would move it."""
    jump = ModeJump((0, 1), True, np.array([1.0, 6.0, 0.0]), SD_A * np.eye(3), np.array([6.0, 1.0, 3.0]),
                    SD_B * np.eye(3), 0.0)
    rng = np.random.default_rng(5)
    start = np.array([6.0, 1.0, 3.0]) + 0.05 * rng.normal(size=(32, 3))
    results = {}
    for name, jumps in (("exchange", ()), ("jump", (jump,))):
        sampler = emcee.EnsembleSampler(32, 3, two_shifted_modes, vectorize=True,
                                        moves=ensemble_moves(None, (SWAP,), jumps))
        sampler.random_state = np.random.RandomState(11).get_state()
        sampler.run_mcmc(start, 3500, progress=False)
        draws = sampler.get_chain(discard=500, flat=True)
        first = draws[:, 0] < draws[:, 1]
        results[name] = (first.mean(), draws[first, 2].std() if first.any() else np.nan, draws[~first, 2].std())
    assert results["exchange"][0] == 0.0
    share, width_a, width_b = results["jump"]
    assert abs(share - WEIGHT) < 0.04, results
    assert abs(width_a / SD_A - 1) < 0.12 and abs(width_b / SD_B - 1) < 0.12, results


@pytest.fixture(scope="module")
def drogue_pair_target():
    test, _ = synthesize_logger("logger-drogue", 1)
    model = prepare_model(test, reduce_test(test))
    lo = np.array([p.prior.ppf(0.3) for p in model.parameters])
    hi = np.array([p.prior.ppf(0.7) for p in model.parameters])
    theta = lo + (hi - lo) * np.random.default_rng(2).uniform(size=(6, lo.size))
    coords = sampling_coordinates(model, "grown", theta[0])
    return SamplerTarget(model, coords), coords.to_sampler(theta)


def test_in_the_samplers_coordinates_the_jump_is_an_involution_with_inverse_jacobians(drogue_pair_target):
    """On a two-Drogue logger model in the sampler's (grown) coordinates, with a jump between two Laplace
    approximations (means and shapes of the walkers, the second's first start moved later): each walker
    the jump takes across comes back where it was, the log Jacobian factors of the two ways cancel (so the
    reverse move's Metropolis ratio is the inverse), and a walker it leaves in its own pairing is refused."""
    target, u = drogue_pair_target
    e = next(e for e in target.exchanges() if e.exchange.stage == 0)
    rng = np.random.default_rng(4)
    mean_a = u.mean(axis=0)
    mean_b = mean_a.copy()
    mean_b[e.order[0]], mean_b[e.order[1]] = mean_a[e.order[1]], mean_a[e.order[0]]
    chol_a = np.diag(u.std(axis=0) + 1e-3)
    chol_b = np.linalg.cholesky(chol_a @ chol_a.T + np.diag(rng.uniform(0, 1e-2, u.shape[1])))
    jump = ModeJump(e.order, bool(pairing_of(mean_a, e.order)[0]), mean_a, chol_a, mean_b, chol_b, 0.0)
    q, crossed, factor = jump.apply(u)
    back, crossed_back, factor_back = jump.apply(q)
    assert crossed.any() and np.ptp(np.abs(factor)) == 0 and factor[0] != 0   # ±log|det L_B / det L_A|
    np.testing.assert_allclose(back[crossed], u[crossed], rtol=1e-9, atol=1e-9)
    assert crossed_back[crossed].all()
    np.testing.assert_allclose(factor_back[crossed], -factor[crossed], atol=1e-12)
    move = ModeJumpMove([jump])
    state = emcee.State(u, log_prob=target(u))
    model = type("M", (), {"random": np.random.RandomState(0), "log_prob_fn": staticmethod(target)})()
    moved, accepted = move.propose(model, state)
    assert not accepted[~crossed].any()


def test_the_other_pairings_optimum_is_found_and_its_offset_is_the_jump():
    """From the MAP (1, 6, 0) the search started at its exchange (6, 1, 0) ends at the other mode's peak,
    (6, 1, 3), ln(0.7/0.3) + 3·ln(0.35/0.2) lower less the prior's 0.06 in its favour (N(3.5, 10²) each: the
    two peaks' squared distances from 3.5 sum to 24.75 and 12.75), and the jump's offset
    goes from N((1, 6, 0), 0.2²) to N((6, 1, 3), 0.35²); a MAP started in the lighter mode is replaced by
    the heavier."""
    model = ShiftedModes()
    theta_map, lp_map, optima = other_pairings(model, np.array([1.0, 6.0, 0.0]), float(model([1.0, 6.0, 0.0])[0]))
    (i, theta, lp, _), = optima
    assert i == 0
    np.testing.assert_allclose(theta, [6.0, 1.0, 3.0], atol=0.02)
    assert lp_map - lp == pytest.approx(np.log(0.7 / 0.3) + 3 * np.log(0.35 / 0.2) - 0.06, abs=0.01)
    cov_map = laplace_covariance(model, theta_map)
    (jump,) = mode_jumps(model, np.asarray, theta_map, lp_map, cov_map, optima)
    np.testing.assert_allclose(jump.mean_b, [6.0, 1.0, 3.0], atol=0.02)
    # the Laplace shapes: each mode's sd (the wide prior shrinks them by under 0.1 %)
    np.testing.assert_allclose(np.diag(jump.chol_a), SD_A, rtol=0.01)
    np.testing.assert_allclose(np.diag(jump.chol_b), SD_B, rtol=0.01)
    assert jump.side and jump.order == (0, 1)
    lighter = np.array([6.0, 1.0, 3.0])
    theta_map, _, optima = other_pairings(model, lighter, float(model(lighter)[0]))
    np.testing.assert_allclose(theta_map, [1.0, 6.0, 0.0], atol=0.02)
    assert len(optima) == 1 and optima[0][2] < float(model(theta_map)[0])


def _toy_jump_run(max_steps, checkpoints=None):
    """The ESS rule's lockstep chunks on :class:`ShiftedModes`: the jumps found from a MAP in the lighter
    mode, every walker starting there, 3 ensembles of 16 walkers."""
    from cpas_bayes.inference.fit import SamplerOptions, run_ensembles

    model = ShiftedModes()
    lighter = np.array([6.0, 1.0, 3.0])
    theta_map, lp_map, optima = other_pairings(model, lighter, float(model(lighter)[0]))
    jumps = mode_jumps(model, np.asarray, theta_map, lp_map, laplace_covariance(model, theta_map), optima)
    rng = np.random.default_rng(3)
    inits = [lighter + 0.05 * rng.normal(size=(16, 3)) for _ in range(3)]
    options = SamplerOptions(stop="ess", ess_target=1500, check_every=100, store_every=1, max_steps=max_steps,
                             proposal="de")
    return run_ensembles(model, inits, [1, 2, 3], options, checkpoints, jumps=jumps)


@pytest.mark.slow
def test_the_fit_warms_up_the_jumps_on_one_chunk_then_samples_both_pairings_and_resumes_alike(tmp_path):
    """Under the ESS rule the first chunk (100 steps) is the jumps' warm-up and is dropped; the jumps are
    then refitted to its draws in each pairing and frozen. The kept draws hold the heavier mode's 0.7
    (±0.05: 48 walkers, the ESS rule's 1,500 draws), though every walker started in the lighter; and a run
    stopped after 200 steps and resumed from its checkpoints ends with the uninterrupted run's draws."""
    runs, seen = _toy_jump_run(20000)
    assert seen["warm_up_steps"] == 100 and seen["ess_bulk_min"] >= 1500
    draws = np.concatenate([r.draws.reshape(-1, 3) for r in runs])
    share = np.mean(draws[:, 0] < draws[:, 1])
    assert abs(share - WEIGHT) < 0.05, share
    ckpts = [tmp_path / f"ensemble_{e}.h5" for e in range(3)]
    _toy_jump_run(200, ckpts)
    resumed, seen_resumed = _toy_jump_run(20000, ckpts)
    assert seen_resumed == seen
    for a, b in zip(runs, resumed):
        np.testing.assert_array_equal(a.draws, b.draws)


def test_a_map_on_the_edge_of_the_samplers_domain_still_gets_its_jump_and_a_map_outside_gets_none():
    """Where a difference step leaves the sampler map's domain (a bound at the MAP), the other side's step
    gives the Jacobian; where neither does, that pairing gets no jump, and the fit goes on without it
    instead of failing."""
    model = ShiftedModes()
    start = np.array([1.0, 6.0, 0.0])
    theta_map, lp_map, optima = other_pairings(model, start, float(model(start)[0]))
    cov_map = laplace_covariance(model, theta_map)
    edge = theta_map[0]

    def bounded(x):      # NaN just above the MAP's first coordinate: its forward step is outside
        x = np.atleast_2d(np.asarray(x, float))
        return np.where((x[:, :1] > edge + 1e-12) & (x[:, :1] < edge + 1), np.nan, x)

    (jump,) = mode_jumps(model, bounded, theta_map, lp_map, cov_map, optima)
    np.testing.assert_allclose(np.diag(jump.chol_a), SD_A, rtol=0.01)

    def nowhere(x):      # defined at the points themselves only
        x = np.atleast_2d(np.asarray(x, float))
        exact = np.isin(x[:, 2], [theta_map[2], optima[0][1][2]])
        return np.where(exact[:, None], x, np.nan)

    assert mode_jumps(model, nowhere, theta_map, lp_map, cov_map, optima) == []


def test_the_fit_commands_pairing_note_names_the_exchanges_and_the_jumps_gaps():
    """What ``cpas-bayes fit`` prints under its stage table for like canopies without a load cell; nothing
    where there are none (and for a summary written before the exchanges)."""
    from cpas_bayes.inference.fit_folder import pairing_note

    summary = {"sampler": {"label_exchanges": ["D1<->D2 s1", "D1<->D2 s2"]},
               "diagnostics": {"mode_jump_gaps": [0.7753]}}
    note = pairing_note(summary)
    assert "D1<->D2 s1, D1<->D2 s2" in note and "mode jumps to 1 other pairing, whose optimum lies 0.775 below" in note
    summary["diagnostics"]["mode_jump_gaps"] = [1.36, 15.0]
    assert "mode jumps to 2 other pairings, whose optima lie 1.36, 15 below" in pairing_note(summary)
    summary["diagnostics"]["mode_jump_gaps"] = []
    assert "no other pairing's optimum within reach" in pairing_note(summary)
    assert pairing_note({"sampler": {"label_exchanges": []}, "diagnostics": {}}) is None
    assert pairing_note({"sampler": {}, "diagnostics": {}}) is None

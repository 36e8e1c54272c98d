"""Label exchanges of like canopies that no channel tells apart (``cluster_form.stage_exchanges``,
``moves.ExchangeMove``).

Without a load cell per canopy the data see only the cluster's sum, so which canopy opened first at a stage
is not known. The posterior then has one mode per pairing; differential evolution stays in the one it
starts in. The exchange is an involution of θ with unit Jacobian, so Metropolis with the posterior ratio is
exact. Checked here: the algebra on a real logger model, and the law of the move on a two-mode target whose
mode weights are known.
"""

import emcee
import numpy as np
import pytest

from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.data.synth_logger import synthesize_logger
from cpas_bayes.inference.fit import prepare_model
from cpas_bayes.inference.moves import ensemble_moves
from cpas_bayes.stats.cluster_form import Exchange


@pytest.fixture(scope="module")
def drogue_pair():
    test, truth = synthesize_logger("logger-drogue", 1)
    return prepare_model(test, reduce_test(test))


def _theta(model, rng):
    lo = np.array([p.prior.ppf(0.2) for p in model.parameters])
    hi = np.array([p.prior.ppf(0.8) for p in model.parameters])
    return lo + (hi - lo) * rng.uniform(size=(3, lo.size))


def test_a_logger_pair_has_one_exchange_per_stage_and_each_is_an_involution_with_unit_jacobian(drogue_pair):
    m = drogue_pair
    exchanges = m.exchanges()
    assert [(e.pair, e.stage) for e in exchanges] == [(("D1", "D2"), 0), (("D1", "D2"), 1)]
    theta = _theta(m, np.random.default_rng(0))
    for e in exchanges:
        swapped = e.apply(theta)
        np.testing.assert_allclose(e.apply(swapped), theta, rtol=1e-12)
        # the Jacobian by central differences, at each row
        for row in theta:
            h = 1e-6 * np.maximum(np.abs(row), 1e-3)
            jac = np.stack([(e.apply((row + h * u)[None]) - e.apply((row - h * u)[None]))[0] / (2 * h[k])
                            for k, u in enumerate(np.eye(row.size))], axis=1)
            assert abs(abs(np.linalg.det(jac)) - 1.0) < 1e-5
    # the exchanged stage's drag area eps·CDS_o and its timing change hands; the other stage's stay
    col = m.index
    reefed, full = exchanges
    t = reefed.apply(theta)
    for a, b in (("D1", "D2"), ("D2", "D1")):
        np.testing.assert_allclose(t[:, col[f"{a}.s1.eps"]] * t[:, col[f"{a}.cds_o"]],
                                   theta[:, col[f"{b}.s1.eps"]] * theta[:, col[f"{b}.cds_o"]])
        np.testing.assert_array_equal(t[:, col[f"{a}.s1.start"]], theta[:, col[f"{b}.s1.start"]])
        np.testing.assert_array_equal(t[:, col[f"{a}.cds_o"]], theta[:, col[f"{a}.cds_o"]])
        np.testing.assert_array_equal(t[:, col[f"{a}.s2.n_p"]], theta[:, col[f"{a}.s2.n_p"]])
    t = full.apply(theta)
    for a, b in (("D1", "D2"), ("D2", "D1")):
        np.testing.assert_array_equal(t[:, col[f"{a}.cds_o"]], theta[:, col[f"{b}.cds_o"]])
        np.testing.assert_allclose(t[:, col[f"{a}.s1.eps"]] * t[:, col[f"{a}.cds_o"]],
                                   theta[:, col[f"{a}.s1.eps"]] * theta[:, col[f"{a}.cds_o"]])


def test_the_exchanged_pairing_predicts_the_same_total_before_either_disreef(drogue_pair):
    """What makes the move worth having: swapping the reefed stage leaves the cluster's drag area unchanged
    while both canopies are in it, so both pairings fit the accelerometer."""
    m = drogue_pair
    theta = _theta(m, np.random.default_rng(1))
    reefed = m.exchanges()[0]
    stage = m.gather_stages(theta)
    disreef = stage["start"][:, :, 1].min()
    t = np.linspace(0.0, disreef - 0.05, 400)
    before = m.drag_areas(m.gather_stages(theta), t)[0].sum(axis=1)
    after = m.drag_areas(m.gather_stages(reefed.apply(theta)), t)[0].sum(axis=1)
    np.testing.assert_allclose(after, before, rtol=1e-9, atol=1e-9)


def test_the_last_stages_exchange_leaves_each_canopys_reefed_curve_where_it_was(drogue_pair):
    """The last stage's exchange swaps CDS_o and the full-open stage; each canopy keeps its reefed stage,
    so its drag area is unchanged until either disreef, fill time included (t_f ∝ n·sqrt(ΔCDS/CDS_o): n_p
    is rescaled with CDS_o; without that the reefed fills ran 2–5 % faster or slower, and on a two-Drogue
    logger test the exchange cost 190 log-units at the median walker against 143 with it). Together the
    two exchanges are then a plain relabelling: every parameter of one canopy to the other."""
    m = drogue_pair
    theta = _theta(m, np.random.default_rng(2))
    reefed, full = m.exchanges()
    stage = m.gather_stages(theta)
    t = np.linspace(0.0, stage["start"][:, :, 1].min() - 0.05, 400)
    before = m.drag_areas(m.gather_stages(theta), t)[0]
    after = m.drag_areas(m.gather_stages(full.apply(theta)), t)[0]
    np.testing.assert_allclose(after, before, rtol=1e-9, atol=1e-9)
    both = full.apply(reefed.apply(theta))
    col = m.index
    for field in ("cds_o", "s1.start", "s1.n_p", "s1.eps", "s1.ck", "s2.start", "s2.n_p", "s2.tk"):
        np.testing.assert_allclose(both[:, col[f"D1.{field}"]], theta[:, col[f"D2.{field}"]], rtol=1e-12)
        np.testing.assert_allclose(both[:, col[f"D2.{field}"]], theta[:, col[f"D1.{field}"]], rtol=1e-12)


def test_no_exchange_where_a_load_cell_or_the_composite_form_tells_the_canopies_apart():
    from cpas_bayes.data.synth import synthesize

    test, _ = synthesize("drogue", "none", 3)
    assert prepare_model(test, reduce_test(test)).exchanges() == []
    logger, _ = synthesize_logger("logger-drogue", 1)
    assert prepare_model(logger, reduce_test(logger), cluster="composite").exchanges() == []


def test_the_moves_weigh_two_modes_of_unequal_widths_as_the_target_does():
    """Two narrow modes at (1, 6) and (6, 1), sd 0.2 and 0.35, weights 0.7 and 0.3, 7 units apart:
    differential evolution alone keeps every walker in the mode it started in; with the exchange and the
    aligned differential evolution the share of draws in the first mode is 0.7 and each mode keeps its own
    width. 32 walkers × 3,000 steps; an exchange is accepted at rate ~0.3–1, so the share's standard error
    is below 0.01 and the band ±0.04 is four of them. A move that skipped the Metropolis test would give
    0.5, one that never crossed 1.0; an alignment that broke the proposal's symmetry would bend the widths
    (band ±12 %, the sd of an sd estimate at this length being ~3 %)."""
    sd_a, sd_b, w = 0.2, 0.35, 0.7

    def log_prob(x):
        x = np.atleast_2d(x)
        a = -0.5 * ((x[:, 0] - 1) ** 2 + (x[:, 1] - 6) ** 2) / sd_a**2 + np.log(w) - 2 * np.log(sd_a)
        b = -0.5 * ((x[:, 0] - 6) ** 2 + (x[:, 1] - 1) ** 2) / sd_b**2 + np.log(1 - w) - 2 * np.log(sd_b)
        return np.logaddexp(a, b)

    swap = Exchange(("a", "b"), 0, np.array([0]), np.array([1]), *[np.empty(0, int)] * 4, np.empty(0),
                    order=(0, 1))
    rng = np.random.default_rng(5)
    start = np.array([6.0, 1.0]) + 0.05 * rng.normal(size=(32, 2))     # all in the lighter mode
    shares = {}
    for name, exchanges in (("de", ()), ("exchange", (swap,))):
        sampler = emcee.EnsembleSampler(32, 2, log_prob, vectorize=True, moves=ensemble_moves(None, exchanges))
        sampler.random_state = np.random.RandomState(11).get_state()
        sampler.run_mcmc(start, 3500, progress=False)
        draws = sampler.get_chain(discard=500, flat=True)
        shares[name] = float(np.mean(draws[:, 0] < draws[:, 1]))
        if name == "exchange":
            first = draws[:, 0] < draws[:, 1]
            widths = (draws[first, 0].std(), draws[~first, 0].std())
    assert shares["de"] < 0.01
    assert abs(shares["exchange"] - w) < 0.04, shares
    assert abs(widths[0] / sd_a - 1) < 0.12 and abs(widths[1] / sd_b - 1) < 0.12, widths


def test_aligned_differential_evolution_is_exact_where_the_pairings_meet():
    """A single Gaussian across the boundary x0 = x1 between two pairings, not symmetric about it
    (means 0 and 0.6, sds 1 and 0.5): half the walkers' pairs are aligned by an exchange, and a proposal
    that lands in the other pairing must be refused for the proposal to stay symmetric. Means within 0.05
    and sds within 6 % (32 walkers × 6,000 steps, τ ≈ 10: standard errors ≈ 0.01 and 1 %); dropping the
    refusal moves them by more."""
    mean, sd = np.array([0.0, 0.6]), np.array([1.0, 0.5])

    def log_prob(x):
        return -0.5 * np.sum(((np.atleast_2d(x) - mean) / sd) ** 2, axis=1)

    swap = Exchange(("a", "b"), 0, np.array([0]), np.array([1]), *[np.empty(0, int)] * 4, np.empty(0),
                    order=(0, 1))
    rng = np.random.default_rng(8)
    sampler = emcee.EnsembleSampler(32, 2, log_prob, vectorize=True, moves=ensemble_moves(None, (swap,)))
    sampler.random_state = np.random.RandomState(3).get_state()
    sampler.run_mcmc(mean + sd * rng.normal(size=(32, 2)), 6500, progress=False)
    draws = sampler.get_chain(discard=500, flat=True)
    np.testing.assert_allclose(draws.mean(axis=0), mean, atol=0.05)
    np.testing.assert_allclose(draws.std(axis=0), sd, rtol=0.06)


def test_in_the_samplers_drag_area_coordinates_an_exchange_stays_exact_and_swaps_the_drag_areas(drogue_pair):
    """The fit samples u (reefed drag areas R = eps·CDS_o in place of eps): each exchange carried into u is
    still an involution, its Metropolis ratio is still the posterior ratio alone (unit Jacobian in u), and at
    a reefed stage it is a plain swap of the two canopies' R."""
    from cpas_bayes.inference.coordinates import SamplerTarget, sampling_coordinates

    m = drogue_pair
    coords = sampling_coordinates(m)
    target = SamplerTarget(m, coords)
    theta = _theta(m, np.random.default_rng(4))
    u = coords.to_sampler(theta)
    col = {n: i for i, n in enumerate(target.names)}
    for e_theta, e_u in zip(m.exchanges(), target.exchanges()):
        assert e_u.order == e_theta.order
        swapped = e_u.apply(u)
        np.testing.assert_allclose(e_u.apply(swapped), u, rtol=1e-12)
        np.testing.assert_allclose(coords.to_model(swapped), e_theta.apply(theta), rtol=1e-12)
        # the u-density ratio equals the θ-posterior ratio: the Jacobian terms cancel
        np.testing.assert_allclose(target(swapped) - target(u), m(e_theta.apply(theta)) - m(theta), atol=1e-8)
    reefed = target.exchanges()[0].apply(u)
    np.testing.assert_allclose(reefed[:, col["D1.s1.cds_reefed"]], u[:, col["D2.s1.cds_reefed"]], rtol=1e-12)
    np.testing.assert_allclose(reefed[:, col["D2.s1.cds_reefed"]], u[:, col["D1.s1.cds_reefed"]], rtol=1e-12)


@pytest.mark.parametrize("one_cut_short", [False, True])
def test_in_peak_time_coordinates_an_exchange_carries_its_jacobian_factor(drogue_pair, one_cut_short):
    """In peak-time coordinates |∂u/∂θ| = Π s (each stage's seconds to peak per unit n_p) need not be the same
    at θ and at its exchange, so the exchange carried into u is accepted on the u-density ratio times
    |∂u′/∂u|: with that factor (``log_factor``) the ratio is the θ-posterior ratio again, without it not.
    Also where one canopy's reefed stage moves in its grown drag area and the other's in its time to peak."""
    from cpas_bayes.inference.coordinates import SamplerTarget, sampling_coordinates

    m = drogue_pair
    theta = _theta(m, np.random.default_rng(5))
    reference = theta[0].copy()
    if one_cut_short:
        reference[m.index["D1.s1.n_p"]] *= 50.0      # D1's reefed stage peaks after its disreef
    coords = sampling_coordinates(m, "grown" if one_cut_short else "peak_time", reference)
    assert ("D1.s1.cds_grown" in coords.names) == one_cut_short and "D2.s1.t_peak" in coords.names
    target = SamplerTarget(m, coords)
    if one_cut_short:    # keep the points where both pairings have a grown drag area (a start before T_ref)
        ok = np.all(np.isfinite([target(coords.to_sampler(e.apply(theta))) for e in m.exchanges()]), axis=0)
        theta = theta[ok & np.isfinite(target(coords.to_sampler(theta)))]
        assert len(theta) >= 2
    u = coords.to_sampler(theta)
    unequal = 0
    for e_theta, e_u in zip(m.exchanges(), target.exchanges()):
        swapped = e_u.apply(u)
        np.testing.assert_allclose(e_u.apply(swapped), u, rtol=1e-10)
        np.testing.assert_allclose(coords.to_model(swapped), e_theta.apply(theta), rtol=1e-10)
        factor = e_u.log_factor(u, swapped)
        np.testing.assert_allclose(target(swapped) - target(u) + factor, m(e_theta.apply(theta)) - m(theta),
                                   atol=1e-6)
        unequal += int(np.any(np.abs(factor) > 1e-6))
    assert unequal > 0     # the factor is not always 1: leaving it out would bias the sampler

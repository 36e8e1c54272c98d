"""The sampler's coordinates (reefed drag areas in place of reefing ratios) change the path, not the
posterior: the map is a bijection, its Jacobian is the determinant's, and a sampler moving in u with the
Jacobian draws θ from the target law (and without it, from another)."""

import emcee
import numpy as np
import pytest
from scipy import stats

from cpas_bayes.inference.coordinates import DragAreaCoordinates, SamplerTarget, sampling_coordinates


class _TwoCanopyModel:
    """Two parachutes' CDS_o and reefing ratios with independent known laws (a stand-in for a posterior)."""

    chute_prefix = ["A", "B"]
    names = ["A.cds_o", "A.s1.eps", "A.s2.eps", "A.s1.n_p", "B.cds_o", "B.s1.eps", "noise_acc"]
    index = {n: i for i, n in enumerate(names)}
    log_scale = np.zeros(len(names), bool)
    laws = [stats.lognorm(0.25, scale=50.0), stats.norm(0.3, 0.04), stats.norm(0.6, 0.05), stats.norm(8, 1),
            stats.lognorm(0.2, scale=20.0), stats.norm(0.2, 0.03), stats.norm(1, 0.1)]

    def __call__(self, theta):
        theta = np.atleast_2d(theta)
        return sum(law.logpdf(theta[:, j]) for j, law in enumerate(self.laws))

    def draw(self, rng, n):
        return np.column_stack([law.rvs(size=n, random_state=rng) for law in self.laws])


def test_the_map_is_a_bijection_with_the_determinants_jacobian():
    model = _TwoCanopyModel()
    coords = DragAreaCoordinates(model)
    assert coords.names[1] == "A.s1.cds_reefed" and coords.names[5] == "B.s1.cds_reefed"
    assert list(coords.eps_columns) == [1, 2, 5] and list(coords.cds_columns) == [0, 0, 4]
    theta = model.draw(np.random.default_rng(0), 5)
    u = coords.to_sampler(theta)
    np.testing.assert_allclose(u[:, 1], theta[:, 1] * theta[:, 0])
    np.testing.assert_allclose(coords.to_model(u), theta, rtol=1e-14)
    for row in u:
        h = 1e-6 * np.maximum(np.abs(row), 1.0)
        jac = np.column_stack([(coords.to_model(row + h[j] * np.eye(7)[j]) - coords.to_model(row - h[j] * np.eye(7)[j]))
                               / (2 * h[j]) for j in range(7)])
        assert coords.log_jacobian(row) == pytest.approx(np.log(abs(np.linalg.det(jac))), abs=1e-6)
    assert coords.log_jacobian(np.array([-1.0, 1, 1, 1, 1, 1, 1])) == -np.inf


def test_no_reefed_stage_or_the_model_choice_means_theta_itself():
    class OneStage(_TwoCanopyModel):
        names = ["A.cds_o", "A.s1.n_p", "B.cds_o", "noise_acc"]
        index = {n: i for i, n in enumerate(names)}

    assert sampling_coordinates(OneStage()) is None
    assert sampling_coordinates(_TwoCanopyModel(), "model") is None
    assert sampling_coordinates(lambda x: x) is None            # a bare log density
    with pytest.raises(ValueError, match="coordinates must be one of"):
        sampling_coordinates(_TwoCanopyModel(), "log")


@pytest.mark.parametrize("with_jacobian", [True, False])
def test_sampling_in_drag_areas_draws_the_target_law_only_with_the_jacobian(with_jacobian):
    model = _TwoCanopyModel()
    coords = DragAreaCoordinates(model)
    target = SamplerTarget(model, coords)
    density = target if with_jacobian else (lambda u: model(coords.to_model(u)))
    rng = np.random.default_rng(1)
    start = coords.to_sampler(model.draw(rng, 32))
    sampler = emcee.EnsembleSampler(32, 7, density, vectorize=True, moves=emcee.moves.DEMove())
    sampler.random_state = np.random.RandomState(2).get_state()
    sampler.run_mcmc(start, 3000, progress=False)
    theta = coords.to_model(sampler.get_chain(discard=500, thin=10, flat=True))
    # log CDS_o of A: the target's mean log 50; without the Jacobian the law is tilted by CDS_o² (two reefed
    # stages), which moves the mean of log CDS_o by 2·0.25² = 0.125, many standard errors (~0.005)
    shift = np.mean(np.log(theta[:, 0])) - np.log(50.0)
    if with_jacobian:
        assert abs(shift) < 0.03
        for j in (1, 2, 5):
            law = model.laws[j]
            assert abs(np.mean(theta[:, j]) - law.mean()) < 0.2 * law.std()
            assert np.std(theta[:, j]) == pytest.approx(law.std(), rel=0.12)
    else:
        assert shift > 0.08


def test_a_fit_in_drag_area_coordinates_hands_back_draws_and_log_posterior_in_theta():
    """After sampling in u, every kept draw is a θ of the model (its reefing ratios, not drag areas) and its
    stored log density is the model's log posterior there, not u's."""
    from pathlib import Path

    from cpas_bayes.data.bundle import read_bundle
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit import SamplerOptions, prepare_model, sample_posterior

    test = read_bundle(Path(__file__).resolve().parents[1] / "cpas_bayes" / "data" / "examples" / "drogue-clean")
    model = prepare_model(test, reduce_test(test))
    options = SamplerOptions(seed=3, n_ensembles=2, workers=1, max_steps=600, check_every=200, progress=False,
                             coordinates="drag_area")
    result = sample_posterior(model, options)
    eps = [j for j, n in enumerate(model.names) if n.endswith(".eps")]
    assert eps and result.names == model.names
    for run in result.runs:
        draws = run.draws.reshape(-1, model.ndim)
        assert np.all((draws[:, eps] > 0) & (draws[:, eps] < 1))
        np.testing.assert_allclose(run.log_prob.ravel(), model(draws), rtol=1e-9, atol=1e-6)

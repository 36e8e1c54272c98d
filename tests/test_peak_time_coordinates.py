"""The sampler's peak-time coordinates (each stage's time from its start to its peak in place of n_p)
change the path, not the posterior: the map is a triangular bijection whose Jacobian is −Σ log s, a fit in
them hands back θ, and sampling in them with the Jacobian draws θ from the target law (without it, not)."""

from pathlib import Path

import emcee
import numpy as np
import pytest
from scipy import stats

from cpas_bayes.data.bundle import read_bundle
from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.inference.coordinates import PeakTimeCoordinates, SamplerTarget, sampling_coordinates
from cpas_bayes.inference.fit import SamplerOptions, prepare_model, sample_posterior
from cpas_bayes.physics.inflation import cluster_drag_area, peak_time_scales

EXAMPLES = Path(__file__).resolve().parents[1] / "cpas_bayes" / "data" / "examples"


@pytest.fixture(scope="module")
def drogue_model():
    test = read_bundle(EXAMPLES / "drogue-clean")
    return prepare_model(test, reduce_test(test))


def _near_prior_median(model, rng, n):
    lo = np.array([p.prior.ppf(0.35) for p in model.parameters])
    hi = np.array([p.prior.ppf(0.65) for p in model.parameters])
    return lo + (hi - lo) * rng.uniform(size=(n, lo.size))


def test_peak_time_scales_give_the_laws_time_to_peak_and_invert():
    rng = np.random.default_rng(3)
    B, P, K = 4, 2, 3
    args = dict(start=np.cumsum(rng.uniform(0.5, 2.0, (B, P, K)), axis=2),
                cds_stage=np.sort(rng.uniform(5.0, 80.0, (B, P, K)), axis=2), cds_o=rng.uniform(80.0, 90.0, (B, P)),
                diameter=np.array([10.0, 10.5]), expopen=rng.uniform(0.8, 3.0, (B, P, K)),
                ck=rng.uniform(1.0, 1.4, (B, P, K)), t_k=rng.uniform(0.1, 0.5, (B, P, K)),
                v_start=rng.uniform(40.0, 90.0, (B, P, K)))
    n_p = rng.uniform(2.0, 12.0, (B, P, K))
    _, timing = cluster_drag_area(np.array([0.0]), n_fill=n_p, **args)
    out_n_p, scale = peak_time_scales(fill=n_p, n_stages=[K, K], **args)
    np.testing.assert_array_equal(out_n_p, n_p)
    grows = timing.t_f > 0     # a stage starting below the drag area held (an overshoot) does not grow
    assert grows.mean() > 0.8
    np.testing.assert_allclose((n_p * scale)[grows], timing.t_fp[grows], rtol=1e-12)   # t_fp = n_p·s
    back, same_scale = peak_time_scales(fill=n_p * scale, n_stages=[K, K], fill_is_peak_time=True, **args)
    np.testing.assert_allclose(back, n_p, rtol=1e-12)
    np.testing.assert_allclose(same_scale, scale, rtol=1e-12)


def test_the_map_is_a_bijection_with_the_determinants_jacobian(drogue_model):
    m = drogue_model
    coords = sampling_coordinates(m, "peak_time")
    assert isinstance(coords, PeakTimeCoordinates)
    assert [coords.names[j] for j in coords.columns] == [m.names[j].replace(".n_p", ".t_peak") for j in coords.columns]
    assert all(m.names[j].endswith(".n_p") for j in coords.columns) and coords.columns.size >= 2
    theta = _near_prior_median(m, np.random.default_rng(0), 4)
    u = coords.to_sampler(theta)
    back, log_jac = coords.inverse(u)
    np.testing.assert_allclose(back, theta, rtol=1e-12)
    assert u.shape == theta.shape and coords.inverse(u.reshape(2, 2, -1))[1].shape == (2, 2)
    d = theta.shape[1]
    for row, lj in zip(u[:2], log_jac[:2]):
        h = 1e-6 * np.maximum(np.abs(row), 1.0)
        jac = np.column_stack([(coords.to_model(row + h[j] * np.eye(d)[j]) - coords.to_model(row - h[j] * np.eye(d)[j]))
                               / (2 * h[j]) for j in range(d)])
        assert lj == pytest.approx(np.linalg.slogdet(jac)[1], abs=1e-5)
    assert sampling_coordinates(m, "model") is None


class _StageModel:
    """One parachute, two stages: independent known laws of (start, n_p, expopen) per stage, its drag areas
    fixed and its airspeed V = 80·e^(−t) at a stage's start; ``fill_scales`` from the package's law (a
    stand-in for a posterior with the real map)."""

    chute_prefix = ["A"]
    names = ["A.s1.start", "A.s1.n_p", "A.s1.expopen", "A.s2.start", "A.s2.n_p", "A.s2.expopen"]
    index = {n: i for i, n in enumerate(names)}
    stages_per_chute = np.array([2])
    log_scale = np.array([False, True, True, False, True, True])
    laws = [stats.norm(1.0, 0.3), stats.lognorm(0.2, scale=6.0), stats.lognorm(0.3, scale=1.5),
            stats.norm(3.0, 0.3), stats.lognorm(0.25, scale=8.0), stats.lognorm(0.2, scale=2.0)]

    def __call__(self, theta):
        theta = np.atleast_2d(theta)
        return sum(law.logpdf(theta[:, j]) for j, law in enumerate(self.laws))

    def fill_scales(self, theta, peak_times=False):
        theta = np.atleast_2d(theta)
        stage = lambda cols: theta[:, cols][:, None, :]   # noqa: E731
        B = theta.shape[0]
        return peak_time_scales(stage([0, 3]), np.broadcast_to([20.0, 70.0], (B, 1, 2)), np.full((B, 1), 70.0),
                                np.array([9.0]), stage([1, 4]), stage([2, 5]), np.full((B, 1, 2), 1.2),
                                np.full((B, 1, 2), 0.3), 80.0 * np.exp(-stage([0, 3])), [2],
                                fill_is_peak_time=peak_times)


@pytest.mark.parametrize("with_jacobian", [True, False])
def test_sampling_in_peak_times_draws_the_target_law_only_with_the_jacobian(with_jacobian):
    model = _StageModel()
    coords = PeakTimeCoordinates(model)
    target = SamplerTarget(model, coords)
    density = target if with_jacobian else (lambda u: model(coords.to_model(u)))
    rng = np.random.default_rng(1)
    start = coords.to_sampler(np.column_stack([law.rvs(size=32, random_state=rng) for law in model.laws]))
    sampler = emcee.EnsembleSampler(32, 6, density, vectorize=True, moves=emcee.moves.DEMove())
    sampler.random_state = np.random.RandomState(2).get_state()
    sampler.run_mcmc(start, 3000, progress=False)
    theta = coords.to_model(sampler.get_chain(discard=500, thin=10, flat=True))
    # without the Jacobian the law is tilted by Π s ∝ Π e^(start): each start's mean moves by its variance
    # (0.09), many standard errors (~0.01)
    shifts = [np.mean(theta[:, j]) - model.laws[j].mean() for j in (0, 3)]
    if with_jacobian:
        assert max(abs(s) for s in shifts) < 0.04
        for j, law in enumerate(model.laws):
            assert abs(np.mean(theta[:, j]) - law.mean()) < 0.2 * law.std()
            assert np.std(theta[:, j]) == pytest.approx(law.std(), rel=0.15)
    else:
        assert min(shifts) > 0.06


def test_a_fit_in_peak_time_coordinates_hands_back_draws_and_log_posterior_in_theta(drogue_model):
    m = drogue_model
    options = SamplerOptions(seed=3, n_ensembles=2, workers=1, max_steps=600, check_every=200, progress=False,
                             coordinates="peak_time")
    result = sample_posterior(m, options)
    cols = [j for j, n in enumerate(m.names) if n.endswith(".n_p")]
    assert cols and result.names == m.names
    for run in result.runs:
        draws = run.draws.reshape(-1, m.ndim)
        np.testing.assert_allclose(run.log_prob.ravel(), m(draws), rtol=1e-9, atol=1e-6)
        # n_p (tens), not seconds to peak (under a second to a few): the draws are θ
        assert np.median(draws[:, cols]) > 2.0

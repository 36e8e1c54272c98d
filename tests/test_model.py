"""The test model: compiled stage law, likelihood identities, batching, consistency with data."""

import json

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from cpas_bayes.bundle import example_bundles, read_bundle
from cpas_bayes.fit import first_guess, prepare_model
from cpas_bayes.inflation import cluster_drag_area, parachute_drag_area
from cpas_bayes.model import Extension, TestModel
from cpas_bayes.synth import truth_parameter_values


@pytest.fixture(scope="module")
def examples():
    out = {}
    for path in example_bundles():
        test = read_bundle(path)
        truth = json.loads((path / "truth.json").read_text())
        out[path.name] = (test, prepare_model(test), truth_parameter_values(test, truth))
    return out


def _theta(model, values, rest=1.0):
    return np.array([values.get(n, rest) for n in model.names])


@pytest.mark.parametrize("decay", ["linear", "exponential"])
@pytest.mark.parametrize("fill_constant", ["n_p", "n"])
def test_compiled_kernel_equals_numpy_stage_law(decay, fill_constant):
    rng = np.random.default_rng(4)
    B, P, K = 7, 3, 3
    start = np.sort(rng.uniform(0.5, 20.0, (B, P, K)), axis=-1)
    cds_o = rng.uniform(20.0, 500.0, (B, P))
    eps = np.concatenate([np.sort(rng.uniform(0.05, 0.9, (B, P, K - 1)), axis=-1), np.ones((B, P, 1))], axis=-1)
    args = dict(start=start, cds_stage=eps * cds_o[..., None], cds_o=cds_o, diameter=np.array([7.0, 20.0, 35.0]),
                n_fill=rng.uniform(3, 20, (B, P, K)), expopen=rng.uniform(0.5, 3.0, (B, P, K)),
                ck=rng.uniform(1.0, 1.6, (B, P, K)), t_k=rng.uniform(0.0, 1.0, (B, P, K)),
                v_start=rng.uniform(20, 150, (B, P, K)))
    t = np.linspace(0.0, 25.0, 3001)
    fast, fast_timing = cluster_drag_area(t, decay=decay, fill_constant=fill_constant, **args)
    reference, ref_timing = parachute_drag_area(t, *(args[k] for k in ("start", "cds_stage")),
                                                args["cds_o"], args["diameter"][None, :],
                                                *(args[k] for k in ("n_fill", "expopen", "ck", "t_k", "v_start")),
                                                decay=decay, fill_constant=fill_constant)
    np.testing.assert_allclose(fast, reference, rtol=1e-12, atol=1e-9)
    for field in ("t_f", "t_fp", "n", "n_p", "cds_start"):
        np.testing.assert_allclose(getattr(fast_timing, field), getattr(ref_timing, field), rtol=1e-12, atol=1e-12)
    # One time base per row (a shifted sensor) gives row-by-row the same law.
    shifted, _ = cluster_drag_area(t[None, :] - 0.05 * np.arange(B)[:, None], decay=decay,
                                   fill_constant=fill_constant, **args)
    for b in (0, 3, 6):
        row, _ = cluster_drag_area(t - 0.05 * b, decay=decay, fill_constant=fill_constant,
                                   **{k: (v[b:b + 1] if k != "diameter" else v) for k, v in args.items()})
        np.testing.assert_allclose(shifted[b], row[0], rtol=1e-12)


@pytest.mark.parametrize("name", ["drogue-clean", "main-clean"])
def test_data_of_the_independent_simulator_fit_the_model_at_truth(examples, name):
    """At the true parameters the normalised residuals of every channel have unit variance."""
    test, model, truth = examples[name]
    theta = _theta(model, truth)[None]
    pred = model.predict(theta)
    obs = model.obs
    r_acc = (obs.acc - pred.acc[0]) / np.hypot(obs.acc_sigma, obs.acc_qbar)
    r_lc = (obs.lc - pred.lc[0]) / np.hypot(obs.lc_sigma, obs.lc_qbar)
    assert 0.85 < np.mean(r_acc**2) < 1.2
    for row in r_lc:
        assert 0.85 < np.mean(row**2) < 1.2
        assert abs(np.mean(row)) < 0.25


def test_joint_likelihood_equals_dense_multivariate_normal(examples):
    test, model, truth = examples["main-clean"]
    theta = _theta(model, truth)[None].repeat(3, axis=0)
    theta[:, model.index["noise_acc"]] = [1.0, 1.3, 0.8]
    theta[:, model.index["noise_lc"]] = [1.0, 0.7, 1.6]
    theta[1, model.index["M2.s2.n_p"]] *= 1.05
    pointwise = model.pointwise_log_likelihood(theta)
    np.testing.assert_allclose(model.log_likelihood(theta), pointwise.sum(axis=1), rtol=1e-12)
    pred, obs = model.predict(theta), model.obs
    for b, t in [(0, 10), (1, 200), (2, obs.n_bins - 1)]:
        lam = np.r_[theta[b, model.index["noise_acc"]], np.full(obs.lc.shape[0], theta[b, model.index["noise_lc"]])]
        u = np.r_[obs.acc_qbar[t], obs.lc_qbar[:, t]]
        cov = np.outer(lam, lam) * (np.diag(np.r_[obs.acc_sigma[t], obs.lc_sigma[:, t]] ** 2) + np.outer(u, u))
        y = np.r_[obs.acc[t], obs.lc[:, t]]
        mean = np.r_[pred.acc[b, t], pred.lc[b, :, t]]
        assert pointwise[b, t] == pytest.approx(multivariate_normal(mean, cov).logpdf(y), rel=1e-10)


def test_any_batch_size_gives_the_same_rows(examples):
    _, model, _ = examples["drogue-clean"]
    rng = np.random.default_rng(2)
    theta = first_guess(model) * (1 + 1e-3 * rng.standard_normal((64, model.ndim)))
    full = model(theta)
    assert np.isfinite(full).all()
    pieces = np.concatenate([model(theta[i:i + n]) for i, n in zip((0, 1, 8, 37), (1, 7, 29, 27))])
    np.testing.assert_array_equal(full, pieces)
    assert model(theta[5]) == pytest.approx(full[5], rel=0, abs=0)


def test_posterior_is_minus_inf_outside_the_prior_never_nan(examples):
    _, model, _ = examples["main-clean"]
    rng = np.random.default_rng(3)
    draws = model.sample_prior(rng, 200)
    lp = model(draws)
    assert not np.isnan(lp).any()
    bad = draws[:3].copy()
    bad[0, model.index["M1.s1.eps"]] = 1.5                          # outside its uniform prior
    bad[1, model.index["M1.s2.start"]] = bad[1, model.index["M1.s1.start"]] - 0.1   # stages out of order
    bad[2, model.index["noise_acc"]] = -1.0
    assert (model(bad) == -np.inf).all()


def test_a_hookless_extension_leaves_the_model_unchanged(examples):
    test, model, truth = examples["drogue-clean"]
    extended = TestModel(test, model.obs, model.kind_priors, model.nuisance_priors, extensions=[Extension()])
    theta = _theta(model, truth)[None]
    assert extended.names == model.names
    assert extended.log_posterior(theta)[0] == pytest.approx(model.log_posterior(theta)[0], rel=1e-14)


def test_derived_n_matches_the_truth_files(examples):
    """n from the sampled n_p by Eq. 18, with the retained drag area, equals the simulator's n."""
    for test, model, truth in examples.values():
        derived = model.derived(_theta(model, truth)[None])
        for name, value in truth.items():
            if name.endswith(".n"):
                assert derived[name][0] == pytest.approx(value, rel=1e-6)

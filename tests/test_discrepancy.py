"""The generic discrepancy: its marginal likelihood and leave-one-bin-out values against brute force."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.data.synth import synthesize, truth_parameter_values
from cpas_bayes.inference.fit import prepare_model
from cpas_bayes.stats.discrepancy import Discrepancy, discrepancy_shape


@pytest.fixture(scope="module")
def models():
    test, truth_doc = synthesize("drogue", "sensor_lag", 3, magnitude=0.06)
    reduction = reduce_test(test)
    base = prepare_model(test, reduction)
    with_d = prepare_model(test, reduction, extensions=[Discrepancy(knot_bins=12)])
    truth = truth_parameter_values(test, truth_doc)
    theta = np.array([truth.get(n, 1.0) for n in base.names])   # the truth; error multipliers 1
    return base, with_d, theta


def _dense(model, theta_d):
    """The whitened residuals and the dense covariance I + σ²·Φ̃Φ̃ᵀ of one draw."""
    term = model.extensions[0]
    pred = model.predict(theta_d[None])
    z, log_det = model.whitened_residuals(theta_d[None], pred)
    white = term._white_t.toarray()                       # (M, C·N)
    sigma = math.exp(theta_d[model.index["discrepancy_log_scale"]])
    cov = np.eye(white.shape[1]) + sigma**2 * white.T @ white
    return z[0].reshape(-1), cov, log_det[0]


@pytest.mark.parametrize("log_scale", [math.log(1e-4), math.log(0.3), math.log(2.0)])
def test_the_marginal_likelihood_is_the_dense_gaussian(models, log_scale):
    base, with_d, theta = models
    theta_d = np.append(theta, log_scale)
    z, cov, log_det = _dense(with_d, theta_d)
    exact = stats.multivariate_normal(np.zeros(z.size), cov).logpdf(z) - 0.5 * log_det.sum()
    assert with_d.log_likelihood(theta_d[None])[0] == pytest.approx(exact, rel=1e-9, abs=1e-6)


def test_the_pointwise_values_are_the_leave_one_bin_out_conditionals(models):
    base, with_d, theta = models
    theta_d = np.append(theta, math.log(0.5))
    z, cov, log_det = _dense(with_d, theta_d)
    n_bins = with_d.obs.n_bins
    channels = z.size // n_bins
    pointwise = with_d.pointwise_log_likelihood(theta_d[None])[0]
    for i in (0, n_bins // 3, n_bins // 2, n_bins - 1):
        idx = np.arange(channels) * n_bins + i              # the channels of bin i
        rest = np.setdiff1d(np.arange(z.size), idx)
        gain = cov[np.ix_(idx, rest)] @ np.linalg.inv(cov[np.ix_(rest, rest)])
        mean = gain @ z[rest]
        var = cov[np.ix_(idx, idx)] - gain @ cov[np.ix_(rest, idx)]
        exact = stats.multivariate_normal(mean, var).logpdf(z[idx]) - 0.5 * log_det[i]
        assert pointwise[i] == pytest.approx(exact, rel=1e-8, abs=1e-8)


def test_a_vanishing_discrepancy_is_the_baseline_bin_by_bin(models):
    base, with_d, theta = models
    theta_d = np.append(theta, math.log(1e-8))   # far below the prior's floor: the limit itself
    assert with_d.pointwise_log_likelihood(theta_d[None])[0] == pytest.approx(
        base.pointwise_log_likelihood(theta[None])[0], abs=1e-5)


def test_the_fitted_shape_finds_the_missing_structure_in_time(models):
    """With the lag left out of the model, the discrepancy sits in the load cells around the fills."""
    base, with_d, theta = models
    theta_d = np.append(theta, math.log(3.0))
    mean, sd = discrepancy_shape(with_d, theta_d[None])
    obs = with_d.obs
    starts = [s.start for p in with_d.parachutes for s in p.stages]
    near = np.zeros(obs.n_bins, bool)
    for s in starts:
        near |= (obs.time > s - 0.2) & (obs.time < s + 1.5)
    load_cells = np.abs(mean[1:])
    assert load_cells[:, near].mean() > 3 * load_cells[:, ~near].mean()

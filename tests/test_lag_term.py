"""The load-cell lag term predicts the effect a lag has on the data, not the noise of the flight condition.

A test simulated twice from one seed, without and with a load-cell lag, has the same truth and the same
noise (the accelerometer channel is identical); the difference of the load-cell channels is then the lag's
effect alone, as the simulator applies it (the riser force delayed, reduced with the q̄ and G of the moment).
The term's predicted effect at the true parameters must follow it. With q̄ and G read as 5-sample means, the
difference of two noisy samples dominated a Main's prediction (least-squares ratio 0.05–0.12), the fitted lag
read 15–20 % short, and the generic discrepancy explained the lag better than the term: the diagnosis' Main
lag misses at 0.04 s.
"""

import numpy as np
import pytest

from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.data.synth import synthesize, truth_parameter_values
from cpas_bayes.inference.fit import prepare_model
from cpas_bayes.inference.start import find_map
from cpas_bayes.stats.model_terms import make_extension
from cpas_bayes.stats.observations import smooth_flight_condition

LAG = 0.04   # s


def _twins(scenario, seed):
    clean, _ = synthesize(scenario, "none", seed)
    lagged, truth = synthesize(scenario, "sensor_lag", seed, magnitude=LAG)
    return clean, lagged, truth


def _values(model, truth, lag):
    known = {"noise_acc": 1.0, "noise_lc": 1.0, "lag": lag, "lag_response": 0.0}   # a pure delay, as simulated
    return np.array([truth.get(n, known.get(n, np.nan)) for n in model.names])


@pytest.mark.parametrize("scenario, seed", [("main", 40008), ("main", 40001), ("drogue", 40001)])
def test_the_predicted_lag_effect_follows_the_simulated_one(scenario, seed):
    clean, lagged, truth_doc = _twins(scenario, seed)
    model = prepare_model(lagged, reduce_test(lagged), extensions=[make_extension("sensor_lag")])
    clean_model = prepare_model(clean, reduce_test(clean), extensions=[make_extension("sensor_lag")])
    np.testing.assert_array_equal(model.obs.acc, clean_model.obs.acc)   # same noise: the twins differ by the lag
    truth = truth_parameter_values(lagged, truth_doc)
    theta = _values(model, truth, LAG)
    assert np.isfinite(theta).all(), [n for n, v in zip(model.names, theta) if not np.isfinite(v)]
    predicted = (model.predict(theta[None]).lc - model.predict(_values(model, truth, 0.0)[None]).lc)[0]
    simulated = model.obs.lc - clean_model.obs.lc
    for p, s in zip(predicted, simulated):
        ratio = np.dot(p, s) / np.dot(p, p)
        left = np.std(s - p) / np.std(s)
        # measured at 1 s smoothing: Main ratio 0.89–0.96 and 39–59 % left; Drogue 0.99–1.00 and 2–3 % left
        assert 0.8 < ratio < 1.2 and left < 0.7, (ratio, left)


@pytest.mark.slow
def test_a_mains_lag_is_found_at_its_size_and_raises_the_fit_far_above_the_baseline():
    """Main, 0.04 s lag (seed 40008, a diagnosis miss before): the lag-only MAP reads the lag within 10 %
    (0.034 s before) and rises +301 in log p over the baseline's (the generic discrepancy's MAP: +206)."""
    _, lagged, truth_doc = _twins("main", 40008)
    reduction = reduce_test(lagged)
    base = prepare_model(lagged, reduction)
    _, base_log_post = find_map(base, np.random.default_rng(0), 4)
    model = prepare_model(lagged, reduction, extensions=[make_extension("sensor_lag")])
    start = _values(model, truth_parameter_values(lagged, truth_doc), 0.0)   # no lag at the start
    theta, log_post = find_map(model, np.random.default_rng(1), 3, [start])
    lag = theta[model.index["lag"]]
    assert abs(lag - LAG) < 0.1 * LAG, lag
    assert log_post - base_log_post > 200, log_post - base_log_post


def test_the_smoothing_keeps_a_quadratic_and_cuts_white_noise():
    t = np.arange(0.0, 20.0, 0.01)
    truth = 1000.0 - 30.0 * t + 0.8 * t**2
    noisy = truth + np.random.default_rng(3).normal(0.0, 10.0, t.size)
    smooth = smooth_flight_condition(t, noisy)
    np.testing.assert_allclose(smooth_flight_condition(t, truth), truth, rtol=0, atol=1e-8)
    # a difference 4 samples apart: noise √2·10 = 14 raw, a 101-point quadratic cuts it over tenfold
    raw, kept = np.std(np.diff(noisy[::4])), np.std(np.diff(smooth[::4]) - np.diff(truth[::4]))
    assert kept < raw / 10, (kept, raw)
    short = np.array([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(smooth_flight_condition(np.arange(3.0), short), short)

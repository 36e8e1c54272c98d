"""The model of logger bundles (no measured q̄): inflation and air data fitted to raw accelerometer and GNSS samples.

Every test here reads data from :mod:`cpas_bayes.data.synth_logger`, an
independent 3-D simulator with a sheared wind, a box-car averaging
accelerometer and a late receiver; the model shares only the stage law with it.
"""

from dataclasses import replace

import numpy as np
import pytest

from cpas_bayes.data.air_reconstruction import AIR_PARAMETERS
from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.data.synth_logger import (draw_logger_truth, logger_streams, simulate_logger_test,
                                          simulate_logger_trajectory, synthesize_logger)
from cpas_bayes.data.synth_logger_truth import logger_truth_parameters
from cpas_bayes.inference.fit import SamplerOptions, fit_model, prepare_model
from cpas_bayes.stats.logger_model import LoggerModel


def _truth_theta(model, truth_doc):
    values = logger_truth_parameters(truth_doc)
    values.update(noise_acc=1.0, noise_gnss=1.0)
    return np.array([values[n] for n in model.names])


def test_a_logger_bundle_gets_the_logger_model_with_the_air_parameters():
    test, _ = synthesize_logger("logger-drop", 2)
    model = prepare_model(test, reduce_test(test))
    assert isinstance(model, LoggerModel)
    assert set(AIR_PARAMETERS) <= set(model.names)
    assert "load_scale" not in model.names and "qbar" not in test.data
    groups = {p.name: p.group for p in model.parameters}
    assert all(groups[n] == "air data" for n in AIR_PARAMETERS)
    from cpas_bayes.stats.model_terms import make_extension

    for term in ("sensor_lag", "friction_drift"):
        with pytest.raises(ValueError, match=f"the {term} term needs the load cells"):
            prepare_model(test, reduce_test(test), extensions=(make_extension(term),))
    # the added mass reads each walker's reconstructed air data in place of measured channels
    assert "k_a" in prepare_model(test, reduce_test(test), extensions=(make_extension("added_mass"),)).names


def test_the_receivers_error_multiplier_scales_its_residuals_alone():
    """noise_gnss (λ_R) scales the receiver's part of the joint Gaussian, noise_acc the bins' given the receiver:
    the bins' log-likelihood does not move with λ_R, and the total moves as −S/(2λ_R²) − k·log λ_R with k the
    number of receiver values (3 per velocity sample, 1 per altitude), solved here from three values of λ_R."""
    test, doc = synthesize_logger("logger-drop", 2)
    model = prepare_model(test, reduce_test(test))
    assert model.parameters[model.index["noise_gnss"]].group == "nuisance"
    theta = np.repeat(_truth_theta(model, doc)[None], 3, axis=0)
    lam = np.array([1.0, 2.0, 4.0])
    theta[:, model.index["noise_gnss"]] = lam
    bins = model.pointwise_log_likelihood(theta).sum(axis=1)
    assert np.allclose(bins, bins[0], rtol=0, atol=1e-9)
    f = model.log_likelihood(theta) - bins
    # f(λ) = c − S/(2λ²) − k·log λ: two differences, two unknowns
    a = np.array([[-0.5 * (1 / lam[1] ** 2 - 1), -np.log(lam[1])], [-0.5 * (1 / lam[2] ** 2 - 1), -np.log(lam[2])]])
    S, k = np.linalg.solve(a, f[1:] - f[0])
    ch = model.channels
    assert k == pytest.approx(3 * ch.gnss_time.size + ch.altitude_time.size, rel=1e-9)
    assert 0.5 * k < S < 2.0 * k   # at the truth the receiver's whitened residuals have unit variance


@pytest.mark.parametrize("seed", [3, 6])
def test_predicted_readings_at_the_truth_match_the_simulators_averaged_load_factor(seed):
    """At the true parameters, the model's averaged reading (Gauss–Legendre over each 20–200 Hz interval, q̄ from
    the reconstruction) equals the simulator's noise-free box-car reading to 1 % of the peak."""
    truth_rng, noise_rng = logger_streams(seed)
    truth = draw_logger_truth("logger-drop", truth_rng)
    truth = replace(truth, accel_sigma=1e-6, gnss_sigma_horizontal=1e-3, gnss_sigma_up=1e-3, altitude_sigma=1e-2)
    test, doc = simulate_logger_test(truth, noise_rng)
    model = prepare_model(test, reduce_test(test))
    theta = _truth_theta(model, doc)
    theta[model.index["vehicle_weight"]] = truth.vehicle_weight
    theta[model.index["vehicle_cds"]] = truth.vehicle_cds
    pred = model.predict(theta[None])
    obs, bins = model.obs, model.bins
    # back from drag-area units to readings: acc = W·mean reading/q̄_ref − CDS_V (the model's fixed affine map)
    reading = (pred.acc[0] + obs.stated_vehicle_cds) * bins.q_ref / model.stated_total_weight
    sim = simulate_logger_trajectory(truth)
    t = model.channels.accel_time
    per_reading = truth.accel_scale * sim.mean_load_factor(t, 1.0 / truth.accel_rate) + truth.accel_bias
    expected = np.add.reduceat(per_reading, bins.first_reading) / bins.readings
    error = np.abs(reading - expected)
    assert error.max() < 0.01 * expected.max(), (error.max(), expected.max(), truth.accel_rate)
    # the instant value at each reading's time misses a 20 Hz peak by more than the model's average does
    if truth.accel_rate <= 50:
        instant = truth.accel_scale * np.interp(t, sim.time, sim.load_factor) + truth.accel_bias
        assert np.abs(instant - per_reading).max() > 3 * error.max()


def test_the_posterior_is_higher_at_the_truth_than_at_a_shifted_air_state():
    test, doc = synthesize_logger("logger-drop", 2)
    model = prepare_model(test, reduce_test(test))
    theta = _truth_theta(model, doc)
    base = model(theta[None])[0]
    assert np.isfinite(base)
    for name, delta in (("gnss_latency", 0.15), ("airspeed_0", 3.0), ("wind_north", 1.0)):
        moved = theta.copy()
        moved[model.index[name]] += delta
        assert model(moved[None])[0] < base - 20.0, name


@pytest.mark.slow
def test_logger_fits_cover_the_true_inflation_and_air_parameters():
    """Seeded single-canopy logger drops (20–200 Hz accelerometer, 2–10 Hz late GNSS, sheared wind, no q̄, no
    load cells), fitted as a user would: the 90 % intervals of the inflation parameters, vehicle drag area and
    the nine air-data terms cover the truth in 80–100 % of cases, every fit converged."""
    inside = total = 0
    misses = []
    for seed in (1, 2, 3):
        test, doc = synthesize_logger("logger-drop", seed)
        model = prepare_model(test, reduce_test(test))
        fit = fit_model(model, SamplerOptions(seed=seed, n_ensembles=2, ess_target=400, progress=False))
        assert fit.summary["diagnostics"]["converged"], seed
        truth = logger_truth_parameters(doc)
        post = fit.tree["posterior"]
        for name in model.names:
            if name not in truth or name == "vehicle_weight":   # the weight's posterior is its stated prior
                continue
            lo, hi = np.quantile(post[name].values.ravel(), [0.05, 0.95])
            ok = lo <= truth[name] <= hi
            inside += ok
            total += 1
            if not ok:
                misses.append((seed, name, truth[name], lo, hi))
    assert total >= 40
    print(f"logger coverage {inside}/{total}; misses {misses}")
    assert inside / total >= 0.80, misses


def test_a_slow_logger_is_warned_about_in_words_that_fit_the_averaging_model():
    from cpas_bayes.inference import fit_health

    test, _ = synthesize_logger("logger-drop", 2)
    model = prepare_model(test, reduce_test(test))
    draws = {"M1.s1.t_fp": np.full(100, 0.2)}
    (w,) = fit_health.sample_rate_warnings(model, draws, sample_interval=0.05)     # 4 readings at 20 Hz
    assert w["code"] == "sample_rate" and "averages over each reading's interval" in w["message"]
    assert fit_health.sample_rate_warnings(model, draws, sample_interval=0.005) == []


@pytest.mark.slow
def test_a_campaign_of_logger_drops_fits_pools_and_runs_the_monte_carlo(tmp_path):
    """Two seeded drops in one campaign: each is reduced and fitted, and both enter the memo and the Monte
    Carlo of their configuration. The diagnosis is off here (it runs by default): a logger diagnosis is
    tests/test_logger_extensions.py's, and with it this test took 565 s instead of about 150."""
    import json

    from cpas_bayes.app.cli import main
    from cpas_bayes.data.synth_logger import write_logger_synthetic

    folder = tmp_path / "tests"
    for seed in (3, 4):
        write_logger_synthetic("logger-drop", seed, folder / f"drop{seed}")
    config = tmp_path / "campaign.toml"
    config.write_text('workers = 1\n[fit]\nensembles = 1\nmax_steps = 1000\nstop = "tau"\ntau_factor = 10\n'
                      "[diagnose]\nmode = \"off\"\n[montecarlo]\nruns = 400\n[compare]\nruns = 200\n"
                      "[pool]\ndraws = 1000\n")
    out = tmp_path / "out"
    assert main(["campaign", str(folder), "--out", str(out), "--config", str(config)]) == 0
    manifest = json.loads((out / "campaign.json").read_text())
    assert len(manifest["tests"]) == 2 and all(c is None for c in manifest["causes"].values())
    steps = {s["name"]: s["status"] for s in manifest["steps"]}
    assert not any(name.endswith("diagnosis") for name in steps)
    for name in manifest["tests"]:
        assert steps[f"{name} fit"] == "ran"
        assert (out / "tests" / name / "fit" / "posterior.nc").stat().st_size > 0
    assert (out / "memo" / "memo.toml").is_file()

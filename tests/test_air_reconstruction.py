"""Flight-path reconstruction of logger bundles (no measured q̄), checked against an independent simulator.

The data come from :mod:`cpas_bayes.data.synth_logger`, whose own 3-D
integrator flies the vehicle through a sheared wind and samples a box-car
averaging accelerometer and a late GNSS receiver; the reconstruction
(:mod:`cpas_bayes.physics.flight_path`, :mod:`cpas_bayes.data.air_reconstruction`)
shares none of that code.
"""

from dataclasses import replace

import numpy as np
import pytest

from cpas_bayes.data import air_reconstruction as air
from cpas_bayes.data.synth_logger import draw_logger_truth, logger_streams, simulate_logger_test, synthesize_logger
from cpas_bayes.data.synth_logger_truth import logger_truth_parameters


def _noise_free(scenario, seed, **changes):
    truth_rng, noise_rng = logger_streams(seed)
    truth = draw_logger_truth(scenario, truth_rng)
    truth = replace(truth, accel_sigma=1e-7, gnss_sigma_horizontal=1e-4, gnss_sigma_up=1e-4, altitude_sigma=1e-3,
                    **changes)
    return simulate_logger_test(truth, noise_rng)


@pytest.mark.parametrize("scenario,seed", [("logger-drop", 4), ("logger-drogue", 2)])
def test_reconstruction_from_the_true_state_follows_the_independent_simulator(scenario, seed):
    """From the true state at the first reading, with the true sensor terms, the kinematics driven by the
    averaged readings land on the simulator's receiver samples (wind shear, latency and all)."""
    test, truth = _noise_free(scenario, seed)
    ch = air.logger_channels(test)
    phi = np.array([logger_truth_parameters(truth)[n] for n in air.AIR_PARAMETERS])
    dv, dh = air.gnss_misfit(ch, air.track(ch, phi[None]))
    speed = np.linalg.norm(ch.velocity, axis=1).max()
    assert np.abs(dv).max() < 2e-3 * speed, np.abs(dv).max()
    assert np.abs(dh).max() < 0.5, np.abs(dh).max()
    # and a wrong latency (0.2 s) or heading (5°) is visible at that scale
    for name, delta in (("gnss_latency", 0.2), ("heading_0", 5.0)):
        wrong = phi.copy()
        wrong[air.AIR_PARAMETERS.index(name)] += delta
        dv_wrong, _ = air.gnss_misfit(ch, air.track(ch, wrong[None]))
        assert np.abs(dv_wrong).max() > 10 * np.abs(dv).max(), name


def test_best_estimate_covers_the_true_air_parameters():
    """Over seeded logger tests of both scenarios, the best estimate's ±1.645 sd intervals cover the true
    initial state, wind offsets, sensor scale, bias and latency about 90 % of the time (80 % floor)."""
    inside = total = 0
    worst = []
    for scenario, seed in [("logger-drop", s) for s in range(1, 7)] + [("logger-drogue", s) for s in range(1, 4)]:
        test, truth = synthesize_logger(scenario, seed)
        estimate = air.best_estimate_trajectory(test)
        values = logger_truth_parameters(truth)
        z = (estimate.phi - np.array([values[n] for n in air.AIR_PARAMETERS])) / estimate.sigma
        inside += int((np.abs(z) <= 1.645).sum())
        total += z.size
        worst.append(float(np.abs(z).max()))
        assert 0.7 < estimate.rms_whitened < 1.3, (scenario, seed, estimate.rms_whitened)
    assert inside / total >= 0.80, (inside, total, worst)
    assert max(worst) < 5.0, worst


def test_counting_the_integrated_accelerometer_noise_as_independent_would_be_overconfident():
    """The random walk of the integrated readings correlates the receiver's residuals: its covariance has a
    smaller determinant per sample than its own diagonal would (it is not white)."""
    test, _ = synthesize_logger("logger-drop", 1)
    estimate = air.best_estimate_trajectory(test)
    cov = estimate.errors.chol @ estimate.errors.chol.T
    diagonal_log_det = float(np.log(np.diag(cov)).sum())
    assert estimate.errors.log_det < diagonal_log_det - 5.0
    # and the walk is a real share of the variance late in the record (velocity rows)
    ch = air.logger_channels(test)
    stated = ch.velocity_sigma.ravel() ** 2
    assert (np.diag(cov)[:stated.size] / stated).max() > 1.5


def test_best_estimate_q_bar_matches_the_simulated_one():
    """The reduction's q̄ (from the best estimate) agrees with the simulator's within its stated 1-sigma."""
    from cpas_bayes.data.synth_logger import simulate_logger_trajectory

    truth_rng, noise_rng = logger_streams(5)
    truth = draw_logger_truth("logger-drop", truth_rng)
    test, _ = simulate_logger_test(truth, noise_rng)
    estimate = air.best_estimate_trajectory(test)
    trajectory = simulate_logger_trajectory(truth)
    f = estimate.frame
    q_true = np.interp(f["time"], trajectory.time, trajectory.qbar)
    z = (f["qbar"] - q_true) / f["qbar_sigma"]
    # One set of air parameters moves every sample together, so z is one number in effect: within 2 sd.
    assert np.median(np.abs(z)) < 2.0, np.median(np.abs(z))
    assert np.abs((f["qbar"] - q_true) / q_true).max() < 0.10


def test_a_record_whose_receiver_starts_too_late_is_refused_clearly():
    test, _ = synthesize_logger("logger-drop", 1)
    d = test.data.copy()
    late = d["time"] < d["time"].iloc[-1] - 0.3   # the receiver only in the last 0.3 s
    for c in ("v_north", "v_east", "v_up", "v_north_sigma", "v_east_sigma", "v_up_sigma"):
        d.loc[late, c] = np.nan
    with pytest.raises(Exception, match="receiver sample"):
        air.logger_channels(replace(test, data=d))


def test_readings_before_a_release_are_not_read_as_drag():
    """A record that starts 3 s before release, hanging under the carrier at 1 g and moving with it, is
    reconstructed from the release on: the same air terms as the record cut at release."""
    import pandas as pd

    test, truth = synthesize_logger("logger-drop", 2)
    d = test.data
    dt = float(np.median(np.diff(air.channel_samples(d, "G")[0])))
    hang_t = np.arange(-3.0, 0.0, dt)
    rng = np.random.default_rng(0)
    hanging = pd.DataFrame({"time": hang_t, "G": 1.0 + rng.normal(0.0, 0.01, hang_t.size),
                            "G_sigma": np.full(hang_t.size, float(d["G_sigma"].dropna().iloc[0]))})
    longer = replace(test, data=pd.concat([hanging, d], ignore_index=True))
    ch = air.logger_channels(longer)
    assert ch.accel_time[0] > -0.1          # starts at the release, not 3 s before it
    cut = air.best_estimate_trajectory(test)
    whole = air.best_estimate_trajectory(longer)
    assert np.all(np.abs(whole.phi - cut.phi) < 2.0 * cut.sigma + 1e-9)


# ---------------------------------------------------------------------------
# careless logger bundles (a fuzzing pass): refused by name, or warned about, never a crash or silent nonsense


def _with(test, **columns):
    d = test.data.copy()
    for name, values in columns.items():
        d[name] = values
    return replace(test, data=d)


def test_a_density_column_that_cannot_be_read_against_altitude_or_is_in_another_unit_is_refused():
    from cpas_bayes.core.errors import BundleError

    test, _ = synthesize_logger("logger-drop", 1)
    has_h = np.isfinite(test.data["altitude"].to_numpy(float))
    off_rows = np.where(has_h, np.nan, 1.0)                   # density only where the altitude is not
    with pytest.raises(BundleError, match="column 'density': 0 row.s. hold both a density and an altitude"):
        air.logger_channels(_with(test, density=off_rows))
    slug = np.where(has_h, 0.00197, np.nan)                   # slug/ft³ read as kg/m³ at ~1.9 km
    with pytest.raises(BundleError, match=r"the density is 0.00\d+× the standard atmosphere's"):
        air.logger_channels(_with(test, density=slug))
    moist = np.where(has_h, 0.9, np.nan)                      # a plausible measured density is used
    assert np.allclose(air.logger_channels(_with(test, density=moist)).density_table, 0.9)


def test_a_release_at_the_end_of_the_record_is_refused_not_read_as_the_whole_record():
    from cpas_bayes.core.errors import BundleError

    test, _ = synthesize_logger("logger-drop", 1)
    t = test.data["time"].to_numpy(float)
    g = test.data["G"].to_numpy(float)
    hanging = np.where(np.isfinite(g), np.where(t < t[-1] - 0.15, 1.0, 0.3), np.nan)   # lifted, then a drop
    with pytest.raises(BundleError, match="release is found at .* leaving [0-9] readings after it"):
        air.logger_channels(_with(test, G=hanging))


def test_a_trajectory_that_misses_its_receiver_is_warned_about():
    """v_up of a receiver that counts down: the reduction warns (its whitened misfit ≫ 1); the clean test not."""
    from cpas_bayes.core.errors import BundleError
    from cpas_bayes.data.reduction import reduce_test

    test, _ = synthesize_logger("logger-drop", 1)
    assert reduce_test(test).warnings == []
    flipped = reduce_test(_with(test, v_up=-test.data["v_up"]))
    assert len(flipped.warnings) == 1 and "sign of v_up" in flipped.warnings[0]
    assert flipped.to_json()["warnings"] == flipped.warnings
    assert flipped.air_estimate.rms_whitened > air.MISFIT_RMS
    # a declared G rate 10× the samples' own is refused, not warned of (read_bundle refuses it too)
    rates = replace(test.air_data, rates={"G": 10.0 / float(np.median(np.diff(
        test.data["time"].to_numpy(float)[np.isfinite(test.data["G"].to_numpy(float))])))})
    with pytest.raises(BundleError, match=r"key 'rate.G': \[rate\] G = "):
        reduce_test(replace(test, air_data=rates))


def test_a_record_reaching_above_the_standard_atmosphere_is_reduced_not_crashed():
    """The density table spans where the flight could go, clipped to the 1976 layers (a long record's span
    reached 95 km and the atmosphere raised)."""
    test, _ = synthesize_logger("logger-drop", 1)
    high = air.logger_channels(_with(test, altitude=test.data["altitude"] + 80_000.0))
    assert high.density_altitude.max() <= air.TOP_GEOPOTENTIAL_ALTITUDE
    assert np.all(np.isfinite(high.density_table))


@pytest.mark.parametrize("limit, value, place", [("MAX_READINGS", 300, "column 'G'"),
                                                 ("MAX_RECEIVER_SAMPLES", 50, "column(s) 'v_north, v_east, v_up'")])
def test_a_record_the_error_model_cannot_hold_is_refused_before_any_work(monkeypatch, limit, value, place):
    """The error model's dense matrices grow as receiver samples × readings (a 1 kHz receiver over 30 s asked
    for 104 GiB and ended in a MemoryError): beyond the limits the record is refused, naming the channel and
    the fix. The 20 Hz drop (400 readings, 200 receiver samples) is refused under limits set below it."""
    from cpas_bayes.core.errors import BundleError

    test, _ = synthesize_logger("logger-drop", 1)
    air.logger_channels(test)
    monkeypatch.setattr(air, limit, value)
    with pytest.raises(BundleError) as err:
        air.logger_channels(test)
    assert err.value.where == place and f"more than the {value:,}" in err.value.problem, str(err.value)
    assert "cut the record to the parachute phase" in err.value.fix


def test_an_atmosphere_profile_off_by_a_unit_is_refused_as_a_density_column_is():
    """[atmosphere] densities in slug/ft³ read as kg/m³ (0.0024 at sea level): q̄ 0.7 Pa and a 20,918 m² drag
    area came out with no word (found by a fuzzing pass); now refused as a density column is, by its ratio to
    the standard atmosphere; a real sounding (±20 %) passes."""
    from cpas_bayes.core.errors import BundleError
    from cpas_bayes.data.air_data import DensityProfile
    from cpas_bayes.physics.atmosphere import standard_density

    test, _ = synthesize_logger("logger-drop", 1)
    h = np.array([0.0, 3000.0, 6000.0])
    with_profile = lambda rho: replace(test, air_data=replace(test.air_data, atmosphere=DensityProfile(h, rho)))  # noqa: E731
    air.logger_channels(with_profile(1.15 * standard_density(h)))
    with pytest.raises(BundleError) as err:
        air.logger_channels(with_profile(standard_density(h) / 515.379))
    assert err.value.where == "key 'atmosphere.density'" and "0.00194× the standard" in err.value.problem


def test_air_data_csv_is_in_the_bundles_units(tmp_path):
    """A US logger bundle's air_data.csv holds ft/s, ft, slug/ft³ and psf, as its reduced.csv holds lbf and
    ft² (it was SI with nothing saying so, found by a fuzzing pass); γ in degrees either way."""
    import pandas as pd

    from cpas_bayes.core.units import unit_system
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.outputs.reduction import write_reduction

    test, _ = synthesize_logger("logger-drop", 1)
    red = reduce_test(replace(test, units=unit_system("US")))
    written = pd.read_csv(write_reduction(red, tmp_path / "red")["air_csv"])
    si = red.air_estimate.frame
    np.testing.assert_allclose(written["qbar"], si["qbar"] / 47.88025898, rtol=1e-8)
    np.testing.assert_allclose(written["airspeed"], si["airspeed"] / 0.3048, rtol=1e-8)
    np.testing.assert_allclose(written["altitude"], si["altitude"] / 0.3048, rtol=1e-8)
    np.testing.assert_allclose(written["gamma"], si["gamma"], rtol=1e-8)

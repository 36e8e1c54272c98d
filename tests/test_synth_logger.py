"""Synthetic logger tests (data/synth_logger.py): the integrator, the loggers' sampling and the truth."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from cpas_bayes.core.units import STANDARD_GRAVITY
from cpas_bayes.data.air_data import WindProfile
from cpas_bayes.data.bundle import read_bundle
from cpas_bayes.data.synth import SyntheticTruth, n_p_consistency
from cpas_bayes.data.synth_logger import (LOGGER_SCENARIOS, draw_logger_truth, logger_streams, sample_times,
                                          simulate_logger_test, simulate_logger_trajectory, synthesize_logger,
                                          write_logger_synthetic)
from cpas_bayes.data.synth_logger_truth import AIR_DATA_KEYS, logger_truth_parameters
from cpas_bayes.physics.atmosphere import standard_density
from cpas_bayes.physics.inflation import parachute_drag_area, stage_role
from cpas_bayes.physics.trajectory import SimulationOptions, simulate
from cpas_bayes.stats.priors import load_kind_priors

SEED = 11
TINY = 1e-7   # noise sigmas of the "noise-free" loggers
VELOCITY = ("v_north", "v_east", "v_up")


def _quiet(truth, **changes):
    """``truth`` with ideal loggers (unit scale, no bias, tiny noise) and ``changes``."""
    fields = dict(accel_scale=1.0, accel_bias=0.0, accel_sigma=TINY, gnss_sigma_horizontal=TINY,
                  gnss_sigma_up=TINY, altitude_sigma=TINY)
    return replace(truth, **{**fields, **changes})


def _truth(scenario, seed=SEED):
    return draw_logger_truth(scenario, logger_streams(seed)[0])


def _record(truth, seed=SEED):
    return simulate_logger_test(truth, np.random.default_rng(seed))


@pytest.fixture(scope="module")
def drop():
    """An ideal-logger single-canopy drop, 200 Hz / 10 Hz, latency 0.3 s, a known wind offset."""
    truth = _quiet(_truth("logger-drop"), accel_rate=200.0, gnss_rate=10.0, gnss_latency=0.3,
                   wind_north=3.0, wind_east=-2.5)
    test, doc = _record(truth)
    return truth, simulate_logger_trajectory(truth), test, doc


def _rows(test, column):
    data = test.data
    keep = np.isfinite(data[column].to_numpy())
    return data["time"].to_numpy()[keep], data[column].to_numpy()[keep]


def _independent_qbar(truth, trajectory, t):
    """q̄ at times t from the state alone: the 1976 density and the true wind at the vehicle's altitude."""
    position, velocity = trajectory.state_at(t)
    w_n, w_e = truth.true_wind().at(position[:, 2])
    air = velocity - np.column_stack([w_n, w_e, np.zeros(len(t))])
    return 0.5 * standard_density(position[:, 2]) * np.sum(air**2, axis=1)


def test_steady_descent_reads_one_g_and_free_fall_reads_the_vehicle_drag(drop):
    truth, trajectory, test, _ = drop
    t, g = _rows(test, "G")
    steady = t > truth.duration - 3.0
    assert np.abs(g[steady] - 1.0).max() < 0.01
    # Before the canopy starts only CDS_V pulls: G = q̄·CDS_V/W_T (q̄ from the state, 5 ms box-car ≈ midpoint).
    start = truth.chutes[0].stages[0].start
    free = t < start - 0.01
    expected = _independent_qbar(truth, trajectory, t[free] - 0.0025) * truth.vehicle_cds / truth.total_weight
    assert free.sum() > 50 and expected.min() > 0.05
    np.testing.assert_allclose(g[free], expected, rtol=2e-3)
    assert g.max() > 2 * expected.max()   # and the canopy's pull is far above it


def test_gnss_reports_the_state_one_latency_earlier(drop):
    truth, trajectory, test, _ = drop
    t, _ = _rows(test, "v_north")
    v = np.column_stack([_rows(test, c)[1] for c in VELOCITY])
    lagged = t - truth.gnss_latency
    # |v_a + w| of the simulator's state at t − L (air velocity and wind interpolated on the 1 ms grid).
    air = np.column_stack([np.interp(lagged, trajectory.time, trajectory.air_velocity[:, i]) for i in range(3)])
    h = np.interp(lagged, trajectory.time, trajectory.position[:, 2])
    w_n, w_e = truth.true_wind().at(h)
    ground = np.linalg.norm(air + np.column_stack([w_n, w_e, np.zeros(len(t))]), axis=1)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), ground, atol=2e-3)
    np.testing.assert_allclose(_rows(test, "altitude")[1], h, atol=1e-3)

    # Against a run without latency: the 0.3 s late receiver shows at t_k what the prompt one showed at t_k − 0.3.
    prompt, _ = _record(replace(truth, gnss_latency=0.0))
    t0, _ = _rows(prompt, "v_north")
    v0 = np.column_stack([_rows(prompt, c)[1] for c in VELOCITY])
    earlier = np.searchsorted(np.round(t0 * 1e6), np.round(lagged * 1e6))
    assert np.array_equal(np.round(t0[earlier], 6), np.round(lagged, 6))
    np.testing.assert_allclose(v, v0[earlier], atol=1e-5)
    same = np.searchsorted(np.round(t0 * 1e6), np.round(t * 1e6))
    filling = (t > truth.chutes[0].stages[0].start) & (t < truth.chutes[0].stages[0].start + 2.0)
    speed, speed0 = np.linalg.norm(v, axis=1), np.linalg.norm(v0[same], axis=1)
    assert np.all(speed[filling] > speed0[filling] + 1.0)   # decelerating: the late receiver reports faster


def test_vertical_descent_drifts_with_the_true_wind(drop):
    truth, _, test, _ = drop
    t, _ = _rows(test, "v_north")
    late = t > truth.duration - 3.0
    h = _rows(test, "altitude")[1][late]
    true_n, true_e = truth.true_wind().at(h)
    stated_n, stated_e = truth.wind.at(h)
    v_n, v_e = _rows(test, "v_north")[1][late], _rows(test, "v_east")[1][late]
    # Within a relaxation time (V/g ≈ 1 s) of shear at most 10 m/s per km at ≈ 10 m/s descent: < 0.1 m/s.
    np.testing.assert_allclose(v_n, true_n, atol=0.15)
    np.testing.assert_allclose(v_e, true_e, atol=0.15)
    assert np.all(np.hypot(v_n - stated_n, v_e - stated_e) > 3.0)   # the offset is flown, not the stated wind
    assert np.all(_rows(test, "v_up")[1][late] < -4.0)


def test_box_car_averaging_lowers_a_slow_loggers_peak():
    truth = _quiet(_truth("logger-drogue"), accel_rate=200.0)
    fast, _ = _record(truth)
    slow_truth = replace(truth, accel_rate=20.0)
    slow, _ = _record(slow_truth)
    trajectory = simulate_logger_trajectory(slow_truth)
    assert trajectory.time[1] - trajectory.time[0] == pytest.approx(1e-3)
    t, g = _rows(slow, "G")
    assert g.max() < _rows(fast, "G")[1].max()
    # Each 20 Hz sample is the 1 ms G averaged over the 0.05 s before it.
    averages = []
    for tj in t:
        inside = (trajectory.time >= tj - 0.05 - 1e-9) & (trajectory.time <= tj + 1e-9)
        averages.append(np.trapezoid(trajectory.load_factor[inside], trajectory.time[inside]) / 0.05)
    np.testing.assert_allclose(g, averages, rtol=5e-3)
    assert np.abs(g / np.array(averages) - 1).max() < 5e-3


def test_halving_the_step_changes_the_peak_g_by_less_than_a_thousandth():
    truth = _quiet(_truth("logger-drogue"), accel_rate=200.0)
    coarse = simulate_logger_trajectory(truth, step=1e-3)
    fine = simulate_logger_trajectory(truth, step=5e-4)
    assert fine.time[1] - fine.time[0] == pytest.approx(5e-4)
    common = fine.load_factor[::2]
    assert len(common) == len(coarse.load_factor)
    peak = coarse.load_factor.max()
    assert np.abs(common - coarse.load_factor).max() < 1e-3 * peak
    t_acc, _ = sample_times(truth)
    boxcar = [run.mean_load_factor(t_acc, 1 / truth.accel_rate).max() for run in (coarse, fine)]
    assert boxcar[1] == pytest.approx(boxcar[0], rel=1e-3)
    np.testing.assert_allclose(coarse.stage_airspeed, fine.stage_airspeed, rtol=1e-6)


def test_the_integrated_drag_areas_are_the_stage_law_with_the_airspeed_at_each_start():
    truth = _quiet(_truth("logger-main"))
    trajectory = simulate_logger_trajectory(truth)
    air_speed = np.linalg.norm(trajectory.air_velocity, axis=1)
    for p, c in enumerate(truth.chutes):
        stages = c.stages
        law, _ = parachute_drag_area(
            trajectory.time, [s.start for s in stages], [s.eps * c.cds_o for s in stages], c.cds_o, c.diameter,
            [s.n_p for s in stages], [s.expopen for s in stages], [s.ck for s in stages], [s.tk for s in stages],
            trajectory.stage_airspeed[p])
        np.testing.assert_allclose(trajectory.cds[p], law, atol=1e-9 * c.cds_o)
        at_start = np.interp([s.start for s in stages], trajectory.time, air_speed)
        np.testing.assert_allclose(trajectory.stage_airspeed[p], at_start, rtol=1e-5)
    # G_true is q̄·(Σ CDS_i + CDS_V)/W_T with q̄ from the state alone.
    qbar = _independent_qbar(truth, trajectory, trajectory.time[1:-1])
    expected = qbar * (trajectory.cds.sum(axis=0)[1:-1] + truth.vehicle_cds) / truth.total_weight
    np.testing.assert_allclose(trajectory.load_factor[1:-1], expected, rtol=1e-6)
    # And the acceleration balances drag and gravity: |a + g ẑ| = G·g0.
    specific = trajectory.acceleration + np.array([0.0, 0.0, STANDARD_GRAVITY])
    np.testing.assert_allclose(np.linalg.norm(specific, axis=1), trajectory.load_factor * STANDARD_GRAVITY,
                               rtol=1e-9)


def test_without_wind_the_3d_integrator_agrees_with_the_planar_simulator():
    truth = _truth("logger-drop")
    calm = WindProfile(truth.wind.altitude, 0 * truth.wind.north, 0 * truth.wind.east, truth.wind.sigma)
    truth = replace(truth, duration=4.0, wind=calm, wind_north=0.0, wind_east=0.0)
    trajectory = simulate_logger_trajectory(truth)
    planar = SyntheticTruth(truth.scenario, truth.duration, truth.airspeed_0, math.radians(truth.flight_path_angle_0),
                            truth.altitude_0, truth.vehicle_weight, truth.vehicle_cds, 1.0, truth.chutes)
    result = simulate(planar.initial_state(), planar.vehicle(), planar.cluster(), truth.duration,
                      SimulationOptions(dt=0.01, substeps=5))
    assert result.load_factor.max() > 3.0   # the canopy has pulled
    np.testing.assert_allclose(np.interp(result.time, trajectory.time, trajectory.load_factor), result.load_factor[0],
                               rtol=1e-5)
    np.testing.assert_allclose(trajectory.stage_airspeed, result.stage_airspeed[0], rtol=1e-6)
    speed = np.linalg.norm(trajectory.velocity, axis=1)
    np.testing.assert_allclose(np.interp(result.time, trajectory.time, speed), result.airspeed[0], rtol=1e-6)


def test_rows_are_the_union_of_the_two_loggers_with_blanks_between():
    truth = replace(_truth("logger-drop"), accel_rate=50.0, gnss_rate=5.0, gnss_latency=0.27)
    test, _ = _record(truth)
    data = test.data
    t_acc, t_gnss = sample_times(truth)
    assert t_gnss[0] == pytest.approx(0.4) and t_acc[0] == pytest.approx(0.02)
    assert list(data.columns) == ["time", "G", "G_sigma", "v_north", "v_east", "v_up", "v_north_sigma",
                                  "v_east_sigma", "v_up_sigma", "altitude", "altitude_sigma"]
    time = data["time"].to_numpy()
    assert np.all(np.diff(time) > 0)
    np.testing.assert_allclose(time, np.union1d(np.round(t_acc, 9), np.round(t_gnss, 9)), atol=1e-9)
    on_acc = np.isin(np.round(time, 6), np.round(t_acc, 6))
    on_gnss = np.isin(np.round(time, 6), np.round(t_gnss, 6))
    assert (on_acc & on_gnss).sum() == len(t_gnss)   # every GNSS time is also an accelerometer time here
    for column in ("G", "G_sigma"):
        assert np.array_equal(np.isfinite(data[column].to_numpy()), on_acc)
    for column in VELOCITY + ("altitude",):
        for c in (column, f"{column}_sigma"):
            assert np.array_equal(np.isfinite(data[c].to_numpy()), on_gnss)
    assert test.units.name == "SI" and not test.measured_qbar
    assert all(p.load_cell is None for p in test.parachutes)
    assert test.air_data.rates == {"G": 50.0}   # the receiver's samples are instantaneous: no rate
    assert test.air_data.wind is truth.wind and test.air_data.atmosphere is None


@pytest.mark.parametrize("scenario", LOGGER_SCENARIOS)
def test_scenarios_draw_inside_their_ranges_and_the_priors(scenario):
    test, doc = synthesize_logger(scenario, SEED)
    truth = draw_logger_truth(scenario, logger_streams(SEED)[0])
    again = draw_logger_truth(scenario, logger_streams(SEED)[0])   # seeded
    assert replace(truth, wind=None) == replace(again, wind=None)
    assert all(np.array_equal(getattr(truth.wind, f), getattr(again.wind, f)) for f in ("altitude", "north", "east"))
    trajectory = simulate_logger_trajectory(truth)
    wind = truth.wind
    assert 3 <= len(wind.altitude) <= 6 and 0.5 <= wind.sigma <= 3.0
    assert np.abs(np.concatenate([wind.north, wind.east])).max() <= 15.0
    shear = np.hypot(*(np.diff(v) / np.diff(wind.altitude) for v in (wind.north, wind.east)))
    assert shear.max() <= 0.010 * math.sqrt(2)
    assert wind.altitude[0] < trajectory.position[:, 2].min() and wind.altitude[-1] > truth.altitude_0
    assert 0.0 <= truth.gnss_latency <= 0.6 and truth.accel_rate in (20, 50, 100, 200)
    assert truth.gnss_rate in (1, 2, 5, 10)
    for c in truth.chutes:
        assert 0.5 <= c.stages[0].start <= 3.0
        priors = load_kind_priors(c.kind)
        assert np.isfinite(priors.parachute["cd_o"].logpdf(c.cds_o / (math.pi * c.diameter**2 / 4)))
        for k, s in enumerate(c.stages):
            role = stage_role(k, len(c.stages))
            names = ("n_p", "expopen") + (("eps",) if role != "full_open" else ()) + (
                ("ck", "tk") if c.inflation == "infinite" else ())
            for name in names:
                assert np.isfinite(priors.for_stage(role, name).logpdf(getattr(s, name))), (c.id, k, name)
    # The last canopy is fully open and the descent near steady by the end.
    assert abs(trajectory.load_factor[-1] - 1.0) < 0.06   # Drogues sinking into denser air at 70 m/s: ≈ 1.03–1.05
    assert test.phase == scenario and len(test.parachutes) == len(truth.chutes)
    json.dumps(doc)   # serialisable
    assert n_p_consistency(doc) < 1e-9


def test_truth_parameters_name_the_air_data_and_the_stages():
    test, doc = synthesize_logger("logger-drogue", SEED)
    truth = draw_logger_truth("logger-drogue", logger_streams(SEED)[0])
    values = logger_truth_parameters(json.loads(json.dumps(doc)))
    # The initial state is the one at the first accelerometer reading (where the fit defines it), the rest
    # the drawn truth.
    first = doc["air_data"]["first_reading"]
    assert first["time"] == pytest.approx(1.0 / truth.accel_rate)
    for key in AIR_DATA_KEYS:
        if key in ("airspeed_0", "flight_path_angle_0", "heading_0", "altitude_0"):
            assert values[key] == pytest.approx(first[key[:-2]])
            change = values[key] - getattr(truth, key)
            if key == "heading_0":
                change = (change + 180.0) % 360.0 - 180.0   # the same direction, in (−180, 180]
            assert abs(change) < 0.05 * abs(getattr(truth, key)) + 1.0, key
        else:
            assert values[key] == pytest.approx(getattr(truth, key))
    assert values["D2.cds_o"] == pytest.approx(truth.chutes[1].cds_o)
    assert values["D1.s2.start"] == pytest.approx(truth.chutes[0].stages[1].start)
    assert values["D1.s1.eps"] == pytest.approx(truth.chutes[0].stages[0].eps) and values["D1.s2.eps"] == 1.0
    assert values["vehicle_weight"] == pytest.approx(truth.vehicle_weight)
    assert {k.split(".")[-1] for k in values if k.startswith("D1.s1.")} == {"start", "n_p", "expopen", "ck", "tk",
                                                                            "eps"}
    # The stated metadata are the truth plus errors of their stated sigmas.
    assert abs(test.vehicle.weight - truth.vehicle_weight) < 5 * test.vehicle.weight_sigma
    stated = [s.start for s in test.parachutes[0].stages]
    assert np.all(np.abs(np.subtract(stated, [s.start for s in truth.chutes[0].stages])) < 0.5)


def test_write_logger_synthetic_puts_truth_json_beside_the_bundle(tmp_path):
    folder = write_logger_synthetic("logger-drop", SEED, tmp_path / "drop")
    test, doc = synthesize_logger("logger-drop", SEED)
    assert json.loads((folder / "truth.json").read_text(encoding="utf-8")) == json.loads(json.dumps(doc))
    header = (folder / "data.csv").read_text(encoding="utf-8").splitlines()[0].split(",")
    assert header == list(test.data.columns) and (folder / "test.toml").is_file()
    back = read_bundle(folder)   # and it reads back: same record, wind and rates
    np.testing.assert_allclose(back.data.to_numpy(float), test.data.to_numpy(float), rtol=1e-12)
    assert back.air_data.rates == test.air_data.rates and back.air_data.wind.sigma == test.air_data.wind.sigma
    np.testing.assert_allclose(back.air_data.wind.north, test.air_data.wind.north, rtol=1e-12)
    assert [s.start for s in back.parachutes[0].stages] == [s.start for s in test.parachutes[0].stages]

"""Synthetic flight tests: valid bundles, reproducible, truthful, each effect in its own channels."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cpas_bayes.data.bundle import EXAMPLES_DIR, read_bundle
from cpas_bayes.data.bundle_write import write_bundle
from cpas_bayes.app.cli import main
from cpas_bayes.outputs.figures import save_figure
from cpas_bayes.data.synth import (EFFECT_MAGNITUDE_RANGE, EFFECTS, draw_effect_params, draw_truth,
                              load_cell_readings, n_p_consistency, noise_free_drag_areas, random_streams,
                              simulate_test, simulate_truth, synthesize, truth_from_bundle, write_synthetic)
from cpas_bayes.physics.trajectory import simulate

SEED = 20240611
IMU_CHANNELS = ["G", "G_sigma", "qbar", "qbar_sigma", "airspeed", "gamma", "density", "altitude"]


def load_cell_columns(test):
    return [c for p in test.parachutes for c in (p.load_column, f"{p.load_column}_sigma")]


@pytest.fixture(scope="module")
def drogue_tests():
    """The drogue scenario of one seed, with every effect at a fixed, mid-range magnitude."""
    sizes = {"added_mass": 0.6, "friction_drift": 0.05, "sensor_lag": 0.05, "canopy_breathing": 0.06}
    return {effect: synthesize("drogue", effect, SEED, magnitude=sizes.get(effect)) for effect in EFFECTS}


@pytest.fixture(scope="module")
def main_bundle(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synth") / "main"
    write_synthetic("main", "none", SEED, folder)
    return folder


def test_bundle_validates_and_has_every_channel(main_bundle):
    test = read_bundle(main_bundle)
    assert test.units.name == "US" and test.phase == "main"
    assert len(test.parachutes) == 3 and all(len(p.stages) == 3 for p in test.parachutes)
    assert test.duration == pytest.approx(40.0) and test.sample_rate == pytest.approx(100.0)
    header = (main_bundle / "data.csv").read_text(encoding="utf-8").partition("\n")[0].split(",")
    for p in test.parachutes:
        assert p.kind == "main" and p.inflation == "finite"
        assert p.diameter == pytest.approx(116 * 0.3048)
        for col in (p.load_cell, f"{p.load_cell}_sigma", p.flyout_angle, f"{p.flyout_angle}_sigma"):
            assert col in header
        theta = test.data[p.angle_column].to_numpy()
        pulling = theta > 0
        assert theta[0] == 0.0 and pulling[-1] and np.all(np.diff(pulling.astype(int)) >= 0)
        assert 3.0 < np.median(theta[pulling]) < 25.0
    for col in ("G_sigma", "qbar_sigma"):
        assert col in header


def test_noise_levels_follow_the_measurement_model(main_bundle):
    test = read_bundle(main_bundle)
    truth_doc = json.loads((main_bundle / "truth.json").read_text(encoding="utf-8"))
    truth = truth_from_bundle(test, truth_doc)
    # the first row's airspeed carries noise; the rest of the state is exact
    r = simulate(truth.initial_state(), truth.vehicle(), truth.cluster(), test.duration)
    d, u = test.data, test.units
    np.testing.assert_allclose(d["G_sigma"], 0.03)
    np.testing.assert_allclose(d["qbar_sigma"], 0.01 * d["qbar"], rtol=1e-12)
    z_g = (d["G"] - r.load_factor[0]) / d["G_sigma"]
    z_q = (d["qbar"] - r.qbar[0]) / d["qbar_sigma"]
    dv = u.from_si(d["airspeed"] - r.airspeed[0], "speed")
    for z in (z_g, z_q):
        assert abs(z.mean()) < 0.15 and 0.9 < z.std() < 1.1
    assert 0.4 < dv.std() < 0.7
    for j, p in enumerate(test.parachutes):
        reading = r.tension[0, j] / (truth.load_scale * np.cos(np.radians(d[p.angle_column])))
        sigma_lbf = u.from_si(d[f"{p.load_column}_sigma"], "force")
        np.testing.assert_allclose(sigma_lbf, 60.0 + 0.01 * np.abs(u.from_si(reading, "force")), rtol=0.02)
        z = (d[p.load_column] - reading) / d[f"{p.load_column}_sigma"]
        assert abs(z.mean()) < 0.15 and 0.9 < z.std() < 1.15


def test_truth_json_layout_matches_the_examples(main_bundle):
    truth_doc = json.loads((main_bundle / "truth.json").read_text(encoding="utf-8"))
    example = json.loads((EXAMPLES_DIR / "main-clean" / "truth.json").read_text(encoding="utf-8"))
    assert set(truth_doc) == set(example)
    assert set(truth_doc["chutes"][0]) == set(example["chutes"][0])
    assert set(truth_doc["chutes"][0]["stages"][0]) == set(example["chutes"][0]["stages"][0])
    assert truth_doc["effect"] == "none" and truth_doc["effect_params"] == {}


def test_truth_is_consistent_and_stated_values_are_noisy_truth(main_bundle):
    test = read_bundle(main_bundle)
    truth_doc = json.loads((main_bundle / "truth.json").read_text(encoding="utf-8"))
    u = test.units
    assert n_p_consistency(truth_doc) < 1e-9
    for chute, p in zip(truth_doc["chutes"], test.parachutes):
        stages = chute["stages"]
        for s, stated in zip(stages, p.stages):
            assert s["cds_end"] == pytest.approx(s["eps"] * chute["cds_o"])
            assert s["ck"] == 1.0 and s["tk"] == 0.0 and s["n"] == pytest.approx(s["n_p"])
            assert abs(stated.start - s["start"]) < 5 * stated.start_sigma + 1e-3
        assert [s["eps"] for s in stages] == sorted(s["eps"] for s in stages) and stages[-1]["eps"] == 1.0
        assert 0 < chute["peak_load"] < truth_doc["peak_total_load"]
    assert abs(u.from_si(test.vehicle.weight, "force") - truth_doc["vehicle_weight"]) < 5 * 100.0
    assert abs(u.from_si(test.vehicle.cds, "area") - truth_doc["vehicle_cds"]) < 5 * 2.0
    assert 1.0 < truth_doc["load_scale"] < 1.2


def test_drogue_truth_has_over_inflation_and_n_p_relation(drogue_tests):
    _, truth_doc = drogue_tests["none"]
    assert n_p_consistency(truth_doc) < 1e-9
    for chute in truth_doc["chutes"]:
        for s in chute["stages"]:
            assert s["ck"] > 1.0 and s["n_p"] > s["n"] and s["tk"] > 0


def test_same_seed_same_bundle_other_seed_other_bundle(tmp_path, drogue_tests):
    a = write_synthetic("drogue", "none", SEED, tmp_path / "a")
    b = write_synthetic("drogue", "none", SEED, tmp_path / "b")
    for name in ("test.toml", "data.csv", "truth.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes()
    test, truth_doc = drogue_tests["none"]
    other_test, other_truth = synthesize("drogue", "none", SEED + 1)
    assert other_truth["chutes"][0]["cds_o"] != truth_doc["chutes"][0]["cds_o"]
    assert not np.allclose(other_test.data["G"], test.data["G"])


def test_load_cell_effects_leave_the_imu_channels_untouched(drogue_tests):
    base, _ = drogue_tests["none"]
    for effect in ("friction_drift", "sensor_lag"):
        test, truth_doc = drogue_tests[effect]
        assert truth_doc["effect"] == effect
        for col in IMU_CHANNELS:
            np.testing.assert_array_equal(test.data[col], base.data[col], err_msg=f"{effect}: {col}")
        for col in load_cell_columns(test):
            assert not np.allclose(test.data[col], base.data[col]), f"{effect}: {col} unchanged"
        assert truth_doc["peak_total_load"] == drogue_tests["none"][1]["peak_total_load"]


def test_dynamic_effects_change_both_channels(drogue_tests):
    base, base_truth = drogue_tests["none"]
    for effect in ("added_mass", "canopy_breathing"):
        test, truth_doc = drogue_tests[effect]
        assert not np.allclose(test.data["G"], base.data["G"], atol=0.01), effect
        for col in load_cell_columns(test)[::2]:
            assert not np.allclose(test.data[col], base.data[col], atol=50.0), f"{effect}: {col}"
        assert truth_doc["peak_total_load"] > base_truth["peak_total_load"]
        # the truth itself (stage parameters, weights) is the same draw
        assert truth_doc["chutes"][0]["stages"] == base_truth["chutes"][0]["stages"]


def test_friction_drift_is_the_seed_like_ramp(drogue_tests):
    test, truth_doc = drogue_tests["friction_drift"]
    params = truth_doc["effect_params"]
    assert params["scale_start"] - params["scale_end"] == pytest.approx(0.05)
    assert truth_doc["load_scale"] == params["scale_end"]
    assert params["t_start"] < params["t_end"] < test.duration
    base, _ = drogue_tests["none"]
    # early the cells read low by scale_end/scale_start; late they read as without the drift
    early = test.data["time"].between(2.5, params["t_start"])
    late = test.data["time"] > params["t_end"]
    for p in test.parachutes:
        ratio_early = (test.data.loc[early, p.load_column].mean() / base.data.loc[early, p.load_column].mean())
        assert ratio_early == pytest.approx(params["scale_end"] / params["scale_start"], rel=5e-3)
        ratio_late = test.data.loc[late, p.load_column].mean() / base.data.loc[late, p.load_column].mean()
        assert ratio_late == pytest.approx(1.0, abs=5e-3)


def test_sensor_lag_delays_the_load_cells():
    truth = draw_truth("drogue", random_streams(3)[0])
    result = simulate_truth(truth)
    base = load_cell_readings(truth, result, "none", {}, 0.0)
    delayed = load_cell_readings(truth, result, "sensor_lag", {"magnitude": 0.05, "lag": 0.05}, 0.0)
    np.testing.assert_allclose(delayed[:, 5:], base[:, :-5], rtol=1e-9, atol=1e-9)   # 50 ms = 5 samples
    np.testing.assert_allclose(delayed[:, :5], base[:, :1] * np.ones((1, 5)))
    shown = noise_free_drag_areas(truth, "sensor_lag", {"magnitude": 0.05, "lag": 0.05}, result=result)
    np.testing.assert_array_equal(shown.accelerometer, noise_free_drag_areas(truth, "none", {}, result).accelerometer)


def test_noise_free_channels_show_the_true_drag_area_without_effects():
    truth = draw_truth("main", random_streams(5)[0])
    shown = noise_free_drag_areas(truth, "none", {})
    np.testing.assert_allclose(shown.accelerometer, shown.true_cds.sum(axis=0), rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(shown.load_cells, shown.true_cds, rtol=1e-9, atol=1e-6)


def test_drawn_effect_sizes_stay_in_their_ranges():
    rng = np.random.default_rng(0)
    for effect, (low, high) in EFFECT_MAGNITUDE_RANGE.items():
        for scenario in ("drogue", "main"):
            params = draw_effect_params(effect, scenario, rng)
            assert low <= params["magnitude"] <= high
    breathing = [draw_effect_params("canopy_breathing", "main", rng) for _ in range(20)]
    assert all(0.2 <= b["frequency_hz"] <= 0.6 and 0.05 <= b["damping_ratio"] <= 0.3 for b in breathing)
    assert draw_effect_params("sensor_lag", "drogue", rng, magnitude=0.07)["lag"] == 0.07
    with pytest.raises(ValueError):
        draw_effect_params("gremlins", "drogue", rng)
    with pytest.raises(ValueError):
        draw_truth("pilot", rng)


def test_simulate_test_round_trips_through_a_bundle(tmp_path, drogue_tests, same_test):
    test, truth_doc = drogue_tests["canopy_breathing"]
    folder = write_bundle(test, tmp_path / "b", extra_files={"truth.json": json.dumps(truth_doc)})
    back = read_bundle(folder)
    # the reader puts columns in its canonical order; data.csv keeps the examples' order
    same_test(back, replace(test, data=test.data[list(back.data.columns)]), rtol=1e-9)
    assert json.loads((folder / "truth.json").read_text())["effect_params"]["amplitude"] == 0.06


def test_cli_synth_writes_a_bundle_and_refuses_bad_sizes(tmp_path, capsys):
    out = tmp_path / "cli"
    assert main(["synth", "--scenario", "drogue", "--effect", "sensor_lag", "--magnitude", "0.03",
                 "--seed", "5", "--out", str(out)]) == 0
    assert "truth.json" in capsys.readouterr().out
    truth_doc = json.loads((out / "truth.json").read_text())
    assert truth_doc["effect"] == "sensor_lag" and truth_doc["effect_params"]["lag"] == 0.03
    read_bundle(out)
    assert main(["synth", "--scenario", "drogue", "--effect", "sensor_lag", "--magnitude", "-0.1",
                 "--seed", "5", "--out", str(tmp_path / "bad")]) == 2
    assert not (tmp_path / "bad").exists()


def test_simulate_test_is_one_function_of_truth_effect_and_noise():
    truth_rng, _, noise_rng = random_streams(9)
    truth = draw_truth("drogue", truth_rng)
    test, truth_doc = simulate_test(truth, "added_mass", {"magnitude": 0.3, "k_a": 0.3}, noise_rng, name="X")
    assert test.name == "X" and truth_doc["effect_params"]["k_a"] == 0.3
    noise_free = simulate_truth(truth, "added_mass", {"k_a": 0.3})
    z = (test.data["G"] - noise_free.load_factor[0]) / 0.03
    assert abs(z.mean()) < 0.15 and 0.9 < z.std() < 1.1


def test_figures_are_drawn(tmp_path, drogue_tests):
    from cpas_bayes.outputs.plots.simulation import plot_effect_comparison, plot_simulated_test

    test, _ = drogue_tests["none"]
    truth = draw_truth("drogue", random_streams(SEED)[0])
    result = simulate_truth(truth)
    fig = plot_simulated_test(result, [c.id for c in truth.chutes], test.units, test=test)
    assert len(fig.axes) == 3 and all(ax.get_ylabel() for ax in fig.axes)
    save_figure(fig, tmp_path / "sim.png")
    fig = plot_effect_comparison("drogue", seed=SEED, magnitudes={"sensor_lag": 0.05})
    assert len(fig.axes) == 4 and all(ax.get_title() and ax.get_legend() for ax in fig.axes)
    save_figure(fig, tmp_path / "effects.png")
    assert (tmp_path / "sim.png").stat().st_size > 10_000 and (tmp_path / "effects.png").stat().st_size > 10_000

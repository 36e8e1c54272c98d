"""Synthetic effects outside the catalogue, the added-mass form variant and pairs: each in its own channels."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cpas_bayes.app.cli import main
from cpas_bayes.data.bundle import read_bundle
from cpas_bayes.data.synth import (EFFECTS, draw_effect_params, draw_truth, load_cell_readings, magnitude_problem,
                                   noise_free_drag_areas, random_streams, simulate_test, simulate_truth,
                                   simulation_options, synthesize, write_synthetic)
from cpas_bayes.data.synth_effects import (ALL_EFFECTS, CATALOGUED_EFFECTS, FORM_VARIANTS, HIDDEN_EFFECTS,
                                           HIDDEN_MAGNITUDE_LIMITS, HIDDEN_MAGNITUDE_RANGE, OUT_OF_CATALOGUE,
                                           cause_of, effect_components)
from cpas_bayes.physics.effects import first_order_lag, lagged, load_path_ringing

SEED = 20240611
AIR_DATA = ["qbar", "qbar_sigma", "airspeed"]
SIZES = {"pitot_lag": 0.2, "accelerometer_clipping": 0.2, "riser_ringing": 0.2, "load_cell_tare_shift": 0.08,
         "added_mass_form": 0.6, "friction_drift_form": 0.05, "sensor_lag_form": 0.05}


def load_cells(test, ids=None):
    return [c for p in test.parachutes if ids is None or p.id in ids for c in (p.load_column, f"{p.load_column}_sigma")]


def changed_columns(test, base):
    return {c for c in base.data.columns
            if not np.array_equal(test.data[c].to_numpy(), base.data[c].to_numpy())}


@pytest.fixture(scope="module")
def drogue():
    """The drogue scenario of one seed: clean, and with every new effect at a fixed size."""
    cases = {effect: synthesize("drogue", effect, SEED, magnitude=SIZES[effect]) for effect in HIDDEN_EFFECTS}
    cases["none"] = synthesize("drogue", "none", SEED)
    return cases


@pytest.fixture(scope="module")
def drogue_truth():
    truth = draw_truth("drogue", random_streams(SEED)[0])
    return truth, simulate_truth(truth)


def test_catalogue_and_the_rest_are_told_apart():
    assert EFFECTS == ("none",) + CATALOGUED_EFFECTS
    assert set(ALL_EFFECTS) == set(EFFECTS) | set(HIDDEN_EFFECTS) and len(ALL_EFFECTS) == len(set(ALL_EFFECTS))
    assert not set(HIDDEN_EFFECTS) & set(EFFECTS) and len(OUT_OF_CATALOGUE) >= 3
    assert set(HIDDEN_MAGNITUDE_RANGE) == set(HIDDEN_MAGNITUDE_LIMITS) == set(HIDDEN_EFFECTS)
    assert {cause_of(e) for e in OUT_OF_CATALOGUE} == {"unexplained"}
    assert FORM_VARIANTS == {"added_mass_form": "added_mass", "friction_drift_form": "friction_drift",
                             "sensor_lag_form": "sensor_lag"}
    assert all(cause_of(e) == c for e, c in FORM_VARIANTS.items())
    assert [cause_of(e) for e in EFFECTS] == list(EFFECTS)


@pytest.mark.parametrize("effect, expected", [
    ("pitot_lag", AIR_DATA),
    ("accelerometer_clipping", ["G"]),
    ("riser_ringing", None),                  # every load cell and its sigma
    ("load_cell_tare_shift", "one cell"),
    ("friction_drift_form", None),
    ("sensor_lag_form", None),
])
def test_each_instrument_effect_changes_only_its_channels(drogue, effect, expected):
    base, base_truth = drogue["none"]
    test, truth_doc = drogue[effect]
    if expected is None:
        expected = load_cells(test)
    elif expected == "one cell":
        expected = load_cells(test, [truth_doc["effects"][effect]["cell"]])
    assert changed_columns(test, base) == set(expected)
    # the truth is the same draw and the dynamics untouched
    assert truth_doc["chutes"] == base_truth["chutes"] and truth_doc["load_scale"] == base_truth["load_scale"]
    assert truth_doc["peak_total_load"] == base_truth["peak_total_load"]
    assert truth_doc["effect"] == effect and truth_doc["cause"] == cause_of(effect)
    assert truth_doc["causes"] == [cause_of(effect)] and truth_doc["effects"] == {effect: truth_doc["effect_params"]}
    assert truth_doc["effect_params"]["magnitude"] == SIZES[effect]


def test_pitot_lag_is_a_first_order_lag_of_the_air_data(drogue, drogue_truth):
    base, _ = drogue["none"]
    test, truth_doc = drogue["pitot_lag"]
    _, result = drogue_truth
    tau = truth_doc["effect_params"]["tau"]
    lagged_qbar = first_order_lag(result.time, result.qbar[0], tau)
    # the same noise multiplies the lagged q̄
    np.testing.assert_allclose(test.data["qbar"] / base.data["qbar"], lagged_qbar / result.qbar[0], rtol=1e-12)
    lag_speed = np.sqrt(2 * lagged_qbar / result.density[0]) - result.airspeed[0]
    np.testing.assert_allclose(test.data["airspeed"] - base.data["airspeed"], lag_speed, atol=1e-9)
    assert np.abs(lag_speed).max() > 10 * 0.5 * 0.3048                     # ≫ the 0.5 ft/s noise
    # both reduction channels divide by the lagged q̄
    shown = noise_free_drag_areas(drogue_truth[0], "pitot_lag", truth_doc["effect_params"],
                                  result=result)
    clean = noise_free_drag_areas(drogue_truth[0], "none", {}, result=result)
    assert not np.allclose(shown.accelerometer, clean.accelerometer, rtol=1e-3)
    assert not np.allclose(shown.load_cells, clean.load_cells, rtol=1e-3)


def test_accelerometer_clipping_makes_flat_tops(drogue, drogue_truth):
    base, _ = drogue["none"]
    test, truth_doc = drogue["accelerometer_clipping"]
    params = truth_doc["effect_params"]
    assert params["ceiling_g"] == pytest.approx(0.8 * drogue_truth[1].load_factor.max())
    g, g_base = test.data["G"].to_numpy(), base.data["G"].to_numpy()
    assert g.max() == params["ceiling_g"] and (g == params["ceiling_g"]).sum() >= 10
    below = g_base < params["ceiling_g"]
    np.testing.assert_array_equal(g[below], g_base[below])
    assert (g_base - g).max() > 10 * 0.03


def test_riser_ringing_rings_after_each_stage_start(drogue, drogue_truth):
    truth, result = drogue_truth
    _, truth_doc = drogue["riser_ringing"]
    params = truth_doc["effect_params"]
    clean = load_cell_readings(truth, result, "none", {}, 0.0)
    ringing = load_cell_readings(truth, result, "riser_ringing", params, 0.0)
    starts = np.array([[s.start for s in c.stages] for c in truth.chutes])
    expected = load_path_ringing(result.time, starts, params["amplitude"], params["frequency_hz"],
                                 params["damping_ratio"])
    np.testing.assert_allclose(ringing, clean * expected, rtol=1e-12)
    ratio = expected - 1.0
    before = result.time < starts.min()
    assert np.all(ratio[:, before] == 0) and 0.5 * params["amplitude"] < np.abs(ratio).max() <= params["amplitude"]
    # frequency: zero crossings of the first ring, half a damped period apart
    after = (result.time > starts[0, 0]) & (result.time < starts[0, 0] + 2.5 / params["frequency_hz"])
    crossings = np.flatnonzero(np.diff(np.sign(ratio[0, after])) != 0)
    omega_d = params["frequency_hz"] * np.sqrt(1 - params["damping_ratio"] ** 2)
    assert np.median(np.diff(crossings)) * 0.01 == pytest.approx(0.5 / omega_d, abs=0.015)
    # the accelerometer channel does not see it
    shown = noise_free_drag_areas(truth, "riser_ringing", params, result=result)
    np.testing.assert_array_equal(shown.accelerometer, noise_free_drag_areas(truth, "none", {}, result).accelerometer)


def test_tare_shift_is_a_step_in_one_cell(drogue):
    base, _ = drogue["none"]
    test, truth_doc = drogue["load_cell_tare_shift"]
    params = truth_doc["effect_params"]
    column = test.parachute(params["cell"]).load_column
    diff = (test.data[column] - base.data[column]).to_numpy()
    time = test.data["time"].to_numpy()
    assert np.all(diff[time < params["time"]] == 0)
    shift_n = params["shift_lbf"] * 4.4482216152605
    np.testing.assert_allclose(np.median(diff[time >= params["time"]]), shift_n, rtol=0.02)
    peak_lbf = [c["peak_load"] for c in truth_doc["chutes"] if c["id"] == params["cell"]][0]
    assert abs(params["shift_lbf"]) == pytest.approx(0.08 * peak_lbf / truth_doc["load_scale"], rel=1e-9)
    assert params["stage_index"] >= 1


def test_magnitude_limits_are_refused_plainly():
    rng = np.random.default_rng(0)
    for effect, (low, high, low_in, high_in, what) in HIDDEN_MAGNITUDE_LIMITS.items():
        for bad in ([] if low_in else [low]) + [low - 1.0, high * 2 + 1.0, float("nan"), float("inf")]:
            with pytest.raises(ValueError, match=f"{effect} magnitude .*must be in"):
                draw_effect_params(effect, "drogue", rng, magnitude=bad)
            assert what in magnitude_problem(effect, bad)
        assert magnitude_problem(effect, high if high_in else 0.99 * high) is None
        assert "number" in magnitude_problem(effect, "ten")
    assert "two values" in magnitude_problem("sensor_lag+pitot_lag", 0.1)
    assert "pitot_lag magnitude" in magnitude_problem("sensor_lag+pitot_lag", (None, -1.0))
    assert magnitude_problem("sensor_lag+pitot_lag", (0.05, None)) is None


def test_drawn_sizes_and_forms_stay_in_their_ranges():
    rng = np.random.default_rng(1)
    for effect, (low, high) in HIDDEN_MAGNITUDE_RANGE.items():
        for scenario in ("drogue", "main"):
            for _ in range(10):
                params = draw_effect_params(effect, scenario, rng)
                assert low <= params["magnitude"] <= high
    for _ in range(20):
        form = draw_effect_params("added_mass_form", "main", rng)
        assert 1.25 <= form["exponent"] <= 1.75 and 0.05 <= form["mass_lag"] <= 0.2
        ringing = draw_effect_params("riser_ringing", "drogue", rng)
        assert 3 <= ringing["frequency_hz"] <= 8 and 0.03 <= ringing["damping_ratio"] <= 0.1
        tare = draw_effect_params("load_cell_tare_shift", "main", rng)
        assert tare["cell_index"] in (0, 1, 2) and tare["stage_index"] in (1, 2) and tare["sign"] in (-1, 1)


def test_the_form_variant_at_exponent_1_5_without_lag_is_plain_added_mass():
    truth_rng, _, _ = random_streams(4)
    truth = draw_truth("drogue", truth_rng)
    plain, plain_doc = simulate_test(truth, "added_mass", {"magnitude": 0.6, "k_a": 0.6}, random_streams(4)[2])
    form, form_doc = simulate_test(truth, "added_mass_form",
                                   {"magnitude": 0.6, "k_a": 0.6, "exponent": 1.5, "mass_lag": 0.0},
                                   random_streams(4)[2])
    for column in plain.data.columns:
        np.testing.assert_array_equal(form.data[column], plain.data[column], err_msg=column)
    assert form_doc["peak_total_load"] == plain_doc["peak_total_load"]
    assert form_doc["cause"] == plain_doc["cause"] == "added_mass" and form_doc["causes"] == ["added_mass"]


def test_the_drawn_form_differs_from_plain_added_mass(drogue):
    base, _ = drogue["none"]
    test, truth_doc = drogue["added_mass_form"]
    params = truth_doc["effect_params"]
    assert truth_doc["cause"] == "added_mass" and params["k_a"] == 0.6
    plain, _ = synthesize("drogue", "added_mass", SEED, magnitude=0.6)
    assert not np.allclose(test.data["G"], plain.data["G"], atol=0.02)
    assert not np.allclose(test.data["G"], base.data["G"], atol=0.02)
    options = simulation_options("added_mass_form", params)
    assert (options.added_mass_k, options.added_mass_exponent, options.added_mass_lag) == (
        0.6, params["exponent"], params["mass_lag"])


def test_pairs_carry_each_signature(drogue):
    base, _ = drogue["none"]
    test, truth_doc = synthesize("drogue", "pitot_lag+accelerometer_clipping", SEED, magnitude=(0.2, 0.2))
    assert truth_doc["effect"] == "pitot_lag+accelerometer_clipping"
    assert list(truth_doc["effects"]) == ["pitot_lag", "accelerometer_clipping"]
    assert truth_doc["effect_params"] == truth_doc["effects"] and truth_doc["causes"] == ["unexplained"] * 2
    assert changed_columns(test, base) == set(AIR_DATA) | {"G"}
    for effect, columns in (("pitot_lag", AIR_DATA), ("accelerometer_clipping", ["G"])):
        single = drogue[effect][0]
        for column in columns:
            np.testing.assert_array_equal(test.data[column], single.data[column], err_msg=column)


def test_a_pair_of_a_sensor_and_a_dynamic_effect():
    truth = draw_truth("drogue", random_streams(SEED)[0])
    params = {"sensor_lag": {"magnitude": 0.05, "lag": 0.05},
              "canopy_breathing": {"magnitude": 0.06, "amplitude": 0.06, "frequency_hz": 1.2, "damping_ratio": 0.1}}
    options = simulation_options("sensor_lag+canopy_breathing", params)
    assert options.breathing is not None and options.added_mass_k is None
    result = simulate_truth(truth, "sensor_lag+canopy_breathing", params)
    breathing_only = load_cell_readings(truth, result, "canopy_breathing", params["canopy_breathing"], 0.0)
    both = load_cell_readings(truth, result, "sensor_lag+canopy_breathing", params, 0.0)
    np.testing.assert_array_equal(both, lagged(result.time, breathing_only, 0.05))
    _, doc = synthesize("drogue", "sensor_lag+canopy_breathing", SEED, magnitude=(0.05, None))
    assert doc["effects"]["sensor_lag"]["lag"] == 0.05 and 0.03 <= doc["effects"]["canopy_breathing"]["amplitude"] <= 0.1
    assert doc["cause"] == "sensor_lag+canopy_breathing" and doc["causes"] == ["sensor_lag", "canopy_breathing"]
    # two dynamic effects go into the dynamics together
    both_dynamic = simulation_options("added_mass_form+canopy_breathing",
                                      {"added_mass_form": {"k_a": 0.4, "exponent": 1.3, "mass_lag": 0.1},
                                       "canopy_breathing": params["canopy_breathing"]})
    assert both_dynamic.breathing is not None and both_dynamic.added_mass_k == 0.4
    drawn = draw_effect_params("riser_ringing+added_mass", "main", np.random.default_rng(2))
    assert set(drawn) == {"riser_ringing", "added_mass"}


@pytest.mark.parametrize("effect", ["none+sensor_lag", "sensor_lag+sensor_lag", "added_mass+added_mass_form",
                                    "friction_drift_form+friction_drift", "sensor_lag+sensor_lag_form",
                                    "pitot_lag+sensor_lag+added_mass", "gremlins", "pitot_lag+gremlins"])
def test_impossible_effects_are_refused(effect):
    with pytest.raises(ValueError):
        effect_components(effect)
    with pytest.raises(ValueError):
        draw_effect_params(effect, "drogue", np.random.default_rng(0))


@pytest.mark.parametrize("effect", list(HIDDEN_EFFECTS) + ["friction_drift+load_cell_tare_shift"])
def test_written_bundles_read_back(tmp_path, effect):
    folder = write_synthetic("drogue", effect, 3, tmp_path / "b")
    test = read_bundle(folder)
    truth_doc = json.loads((folder / "truth.json").read_text(encoding="utf-8"))
    assert truth_doc["effect"] == effect and set(truth_doc["effects"]) == set(effect.split("+"))
    assert len(test.parachutes) == 2 and test.duration == pytest.approx(16.0)
    assert {"effect", "effect_params", "effects", "cause", "causes", "load_scale"} <= set(truth_doc)


def test_cli_synth_takes_the_new_names_and_pairs(tmp_path, capsys):
    out = tmp_path / "one"
    assert main(["synth", "--scenario", "drogue", "--effect", "riser_ringing", "--magnitude", "0.2",
                 "--seed", "5", "--out", str(out)]) == 0
    assert json.loads((out / "truth.json").read_text())["effect_params"]["amplitude"] == 0.2
    read_bundle(out)
    pair = tmp_path / "pair"
    assert main(["synth", "--scenario", "drogue", "--effect", "pitot_lag+sensor_lag", "--magnitude", "0.3",
                 "--magnitude", "0.04", "--seed", "5", "--out", str(pair)]) == 0
    effects = json.loads((pair / "truth.json").read_text())["effects"]
    assert effects["pitot_lag"]["tau"] == 0.3 and effects["sensor_lag"]["lag"] == 0.04
    capsys.readouterr()
    for argv in (["--effect", "pitot_lag", "--magnitude", "5"],
                 ["--effect", "pitot_lag+sensor_lag", "--magnitude", "0.3"],
                 ["--effect", "gremlins"],
                 ["--effect", "none+pitot_lag"]):
        bad = tmp_path / "bad"
        assert main(["synth", "--scenario", "drogue", "--seed", "5", "--out", str(bad)] + argv) == 2, argv
        assert not bad.exists()
    assert "pitot_lag" in capsys.readouterr().err

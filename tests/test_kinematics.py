"""The accelerometer against the airspeed's rate (data.kinematics) and what the diagnosis does with it.

Sound readings of two simulators pass; an accelerometer whose zero drifts, a lagging pitot line and a
saturated accelerometer fail, in the windows where they act; a diagnosis does not try the load-cell terms
against a failing accelerometer and says `unexplained`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cpas_bayes.data.bundle import read_bundle
from cpas_bayes.data.bundle_notes import reading_notes
from cpas_bayes.data.kinematics import FLOOR_G, accelerometer_kinematics, kinematic_warning
from cpas_bayes.data.synth import synthesize
from cpas_bayes.inference.candidate_fits import DiagnoseOptions
from cpas_bayes.inference.diagnosis_rule import adequacy, kinematic_findings, terms_to_try

CANDIDATES = ("added_mass", "friction_drift", "sensor_lag", "canopy_breathing")

EXAMPLES = Path(__file__).parent.parent / "cpas_bayes" / "data" / "examples"


def _with_g(test, extra):
    """``test`` with ``extra`` (an array over its readings, in g) added to G."""
    data = test.data.copy()
    data["G"] = data["G"] + extra
    return dataclasses.replace(test, data=data)


def _zero_drift(test, size=0.05):
    """An accelerometer zero drifting linearly from the first stage start to ``size`` g at the record's end."""
    t = test.data["time"].to_numpy()
    first = min(p.stages[0].start for p in test.parachutes)
    return _with_g(test, np.where(t > first, size * (t - first) / (t[-1] - first), 0.0))


@pytest.mark.parametrize("name", ["drogue-clean", "main-clean"])
def test_the_independent_simulators_readings_agree(name):
    check = accelerometer_kinematics(read_bundle(EXAMPLES / name))
    assert not check.fails
    assert np.abs(check.windows[:, 2]).max() < 0.4 * FLOOR_G
    assert check.p_value > 0.01


@pytest.mark.parametrize("scenario", ["drogue", "main"])
@pytest.mark.parametrize("effect", ["none", "added_mass", "canopy_breathing", "friction_drift"])
def test_synthetic_readings_agree_whatever_the_canopy_does(scenario, effect):
    # an added mass or a breathing canopy changes the drag, not the balance of the accelerometer and the airspeed
    test, _ = synthesize(scenario, effect, 10_001)
    check = accelerometer_kinematics(test)
    assert not check.fails
    assert np.abs(check.windows[:, 2]).max() < 0.4 * FLOOR_G


def test_a_drifting_zero_fails_where_it_has_grown_and_is_named():
    test = _zero_drift(read_bundle(EXAMPLES / "main-clean"))
    check = accelerometer_kinematics(test)
    assert check.fails and check.p_value < 1e-50
    a, b, m, s, allowed = check.worst
    assert 0.035 < m < 0.05 and b > 30.0          # reads high, most at the end
    assert FLOOR_G <= allowed < FLOOR_G + 0.002     # a Main's slow descent: next to no room for wind shear
    bad = check.failing_windows()
    assert bad and min(t0 for t0, _, _ in bad) > 8.0   # not where the drift is still small
    text = kinematic_warning(test, check)
    assert "data.csv G" in text and "airspeed" in text and "drifting zero" in text
    assert ("accelerometer_kinematics", "G") in [(code, column) for code, column, _ in reading_notes(test)]
    # a drift of 0.01 g by the end stays under the floor in every window: not said
    assert not accelerometer_kinematics(_zero_drift(read_bundle(EXAMPLES / "main-clean"), 0.01)).fails


@pytest.mark.parametrize("scenario,seed", [("drogue", 10_001), ("main", 10_001)])
def test_a_lagging_pitot_line_fails(scenario, seed):
    test, _ = synthesize(scenario, "pitot_lag", seed)
    check = accelerometer_kinematics(test)
    assert check.fails and abs(check.worst[2]) > check.worst[4] > FLOOR_G


def test_a_drogues_fast_descent_leaves_room_for_wind_shear():
    # 5 m/s per km of altitude at a Drogue's ~90 m/s descent, cos γ ~0.7: about 0.02 g more than the floor, so
    # a zero drift of 0.05 g over its 16 s (0.031 g) is not said there, where the Main's is
    drifted = _zero_drift(read_bundle(EXAMPLES / "drogue-clean"))
    check = accelerometer_kinematics(drifted)
    assert check.windows[:, 4].min() > FLOOR_G + 0.015
    assert check.p_value < 1e-4 and not check.fails


def test_a_logger_bundle_is_not_checked():
    test = read_bundle(Path(__file__).parent.parent / "docs" / "examples" / "logger-drop")
    assert accelerometer_kinematics(test) is None and kinematic_warning(test) is None


def test_the_diagnosis_does_not_try_load_cell_terms_against_a_failing_accelerometer():
    test = _zero_drift(read_bundle(EXAMPLES / "main-clean"))
    failures, where = kinematic_findings(test)
    assert len(failures) == 1 and "airspeed's rate" in failures[0]
    assert where and all(w["channel"] == "accelerometer" and w["t_start"] > 8.0 for w in where)
    # before the check, that test was named friction_drift and sensor_lag: terms of the load cells read
    # against the accelerometer; terms of the drag itself are still tried
    terms, said = terms_to_try(CANDIDATES, test, failures)
    assert terms == ["added_mass", "canopy_breathing"]
    assert len(said) == 1 and "friction_drift, sensor_lag" in said[0] and "read against the accelerometer" in said[0]
    # readings that agree change nothing
    sound = read_bundle(EXAMPLES / "main-clean")
    assert kinematic_findings(sound) == ([], [])
    assert terms_to_try(CANDIDATES, sound, ()) == (list(CANDIDATES), [])


def test_a_failing_accelerometer_makes_the_baseline_inadequate():
    class Checks:   # a baseline whose own checks all pass
        class residuals:
            noise = {"acc": {"mean": 1.0}}
            table = pd.DataFrame({"ljung_box_p": [0.5], "channel": ["acc"], "phase": ["all"],
                                                    "acf1": [0.0]})

        class ppc:
            table = pd.DataFrame({"p_value": [0.5]})

        class loo_pit:
            table = pd.DataFrame({"ks_p_value": [0.5], "channel": ["acc"]})

    assert adequacy(Checks, DiagnoseOptions()) == (True, [])
    adequate, failures = adequacy(Checks, DiagnoseOptions(), ["the accelerometer disagrees"])
    assert not adequate and failures == ["the accelerometer disagrees"]

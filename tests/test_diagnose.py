"""Diagnosis: the naming rule, the frequency guess, and end-to-end naming of hidden effects.

The end-to-end tests hide one effect (the seed draws its magnitude uniformly
from the simulator's range, :data:`cpas_bayes.data.synth.EFFECT_MAGNITUDE_RANGE`) or
none in a synthetic test and require ``diagnose_test`` to name exactly it:
every physical effect in a Drogue test, one in a Main test, and three clean
tests. With five possible answers, guessing passes one case in five; all eight
would pass by luck with probability (1/5)^8 ≈ 3e-6.
"""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import xarray as xr

from cpas_bayes.inference import candidate_fits as cf
from cpas_bayes.inference import diagnose as dg
from cpas_bayes.inference import diagnosis_rule as rule
from cpas_bayes.app.cli import main
from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.inference.fit import prepare_model
from cpas_bayes.data.synth import synthesize, truth_parameter_values, write_synthetic

# -- the rule, on constructed pointwise elpd values ----------------------------


SIZES = {"added_mass": ("k_a", 0.4), "friction_drift": ("load_scale_change", 0.05), "sensor_lag": ("lag", 0.04),
         "canopy_breathing": ("breathing_amplitude", 0.06), "correlated_noise": ("ar_time", 0.05)}


def _candidate(name, elpd_i, size=None):
    """A stand-in for a fitted candidate: pointwise elpd and the posterior of the term's size."""
    elpd_i = np.asarray(elpd_i, float)
    loo = SimpleNamespace(elpd_i=xr.DataArray(elpd_i), pareto_k=xr.DataArray(np.zeros_like(elpd_i)),
                          elpd=float(elpd_i.sum()), p=1.0, se=1.0)
    params, posterior = [], {}
    if name in SIZES:
        param, typical = SIZES[name]
        value = typical if size is None else size
        params = [SimpleNamespace(name=param, group=name, unit="")]
        posterior = {param: xr.DataArray(value + 0.01 * value * np.random.default_rng(0).standard_normal((2, 50)))}
    fit = SimpleNamespace(summary={"diagnostics": {"converged": True, "rhat_max": 1.0}},
                          model=SimpleNamespace(parameters=params), tree={"posterior": posterior})
    return cf.CandidateFit(name=name, fit=fit, loo=loo, seconds=0.0)


def _field(gains, n=400, seed=0, jitter=0.01):
    """Baseline and candidates whose pointwise elpd exceeds the baseline's by ``gains[name]`` spread
    over 40 bins (a localized effect), plus noise of sd ``jitter`` per bin."""
    rng = np.random.default_rng(seed)
    base = rng.normal(-1.0, 0.3, n)
    cands = {}
    for name, g in gains.items():
        bump = np.zeros(n)
        bump[100:140] = g / 40
        cands[name] = _candidate(name, base + bump + rng.normal(0, jitter, n))
    return _candidate(cf.BASELINE, base), cands


OPTIONS = cf.DiagnoseOptions()


def _gains(**kw):
    g = {"added_mass": 0.0, "friction_drift": 0.0, "sensor_lag": 0.0, "canopy_breathing": 0.0,
         "correlated_noise": 0.0}
    g.update(kw)
    return g


def test_a_clear_physical_gain_is_named():
    base, cands = _field(_gains(sensor_lag=60.0, correlated_noise=15.0))
    cause, reasons = rule.name_cause(base, cands, OPTIONS)
    assert cause == "sensor_lag"
    assert "beats AR(1)" in " ".join(reasons)


def test_a_small_gain_names_nothing():
    base, cands = _field(_gains(sensor_lag=6.0))
    assert rule.name_cause(base, cands, OPTIONS)[0] == "none"


def test_a_term_that_does_not_beat_ar1_names_nothing():
    base, cands = _field(_gains(added_mass=40.0, correlated_noise=55.0))
    cause, reasons = rule.name_cause(base, cands, OPTIONS)
    assert cause == "none"
    assert any("does not beat AR(1)" in r for r in reasons)


def test_two_physical_terms_that_explain_alike_name_nothing():
    # the same bins, explained alike up to bin-to-bin scatter
    base, cands = _field(_gains(added_mass=40.0, canopy_breathing=38.0), jitter=0.2)
    cause, reasons = rule.name_cause(base, cands, OPTIONS)
    assert cause == "none"
    assert any("not clearly ahead" in r for r in reasons)


def test_a_negligible_fitted_size_names_nothing():
    """A real elpd gain from a lag of 2 ms (one 100 Hz sample is the floor) is not a cause."""
    base, cands = _field(_gains(sensor_lag=30.0))
    cands["sensor_lag"] = _candidate("sensor_lag", cands["sensor_lag"].pointwise_elpd, size=-0.002)
    cause, reasons = rule.name_cause(base, cands, OPTIONS)
    assert cause == "none"
    assert any("practical floor" in r for r in reasons)


def test_paired_difference_se_is_the_arviz_formula():
    base, cands = _field(_gains(sensor_lag=60.0))
    diff, se = rule.paired_difference(cands["sensor_lag"], base)
    d = cands["sensor_lag"].pointwise_elpd - base.pointwise_elpd
    assert diff == pytest.approx(d.sum())
    assert se == pytest.approx(np.sqrt(d.size * d.var(ddof=1)))


# -- the breathing frequency guess ---------------------------------------------


@pytest.mark.parametrize("scenario,seed", [("drogue", 3), ("main", 4)])
def test_breathing_frequency_is_read_off_the_baseline_residuals(scenario, seed):
    test, truth_doc = synthesize(scenario, "canopy_breathing", seed, magnitude=0.08)
    model = prepare_model(test, reduce_test(test))
    truth = truth_parameter_values(test, truth_doc)
    theta = np.array([truth.get(n, 1.0) for n in model.names])
    guess = cf.breathing_frequency_guess(model, theta)
    true_f = truth_doc["effect_params"]["frequency_hz"]
    assert guess == pytest.approx(true_f, rel=0.15)


# -- end to end ----------------------------------------------------------------

QUICK = replace(cf.DIAGNOSIS_SAMPLER, workers=1, progress=False)

# (scenario, hidden effect, seed, mode): each seed draws its own truth and effect magnitude. Mode
# "screen" (what a campaign runs) keeps the suite's time; one case and the CLI test run the full comparison.
NAMING_CASES = [
    ("drogue", "none", 101, "screen"), ("drogue", "none", 102, "screen"),
    ("drogue", "added_mass", 103, "screen"), ("drogue", "friction_drift", 104, "screen"),
    ("drogue", "sensor_lag", 105, "full"), ("drogue", "canopy_breathing", 106, "screen"),
    # Mains cost ~3× a Drogue; the other Main effects are in the README's study
    ("main", "none", 201, "screen"), ("main", "canopy_breathing", 206, "screen"),
]


@pytest.mark.slow
@pytest.mark.parametrize("scenario,effect,seed,mode", NAMING_CASES)
def test_diagnose_names_the_hidden_effect(scenario, effect, seed, mode):
    test, truth = synthesize(scenario, effect, seed)
    diagnosis = dg.diagnose_test(test, cf.DiagnoseOptions(seed=seed, sampler=QUICK, mode=mode))
    table = diagnosis.versus_baseline.set_index("name")
    screen = {n: round(r.map_gain, 1) for n, r in diagnosis.screen.items()}
    assert diagnosis.cause == effect, (truth["effect_params"], table[["elpd_diff", "elpd_diff_se"]], screen,
                                       diagnosis.reasons)
    if effect != "none":
        # the named term's own parameter is recovered: its 90 % interval holds the truth
        params = cf.extension_parameters(diagnosis.candidates[effect])
        key, true = {"added_mass": ("k_a", truth["effect_params"].get("k_a")),
                     "sensor_lag": ("lag", truth["effect_params"].get("lag")),
                     "canopy_breathing": ("breathing_frequency", truth["effect_params"].get("frequency_hz")),
                     "friction_drift": (None, None)}[effect]
        if key is not None:
            assert params[key]["q05"] * 0.8 <= true <= params[key]["q95"] * 1.2, (key, true, params[key])


@pytest.mark.slow
def test_diagnose_command_writes_the_documented_outputs(tmp_path):
    bundle = write_synthetic("drogue", "sensor_lag", 7, tmp_path / "bundle", magnitude=0.05)
    out = tmp_path / "diag"
    code = main(["diagnose", str(bundle), "--out", str(out), "--workers", "1",
                 "--candidates", "sensor_lag,added_mass,correlated_noise"])
    assert code == 0
    doc = json.loads((out / "diagnosis.json").read_text())
    assert doc["cause"] == "sensor_lag"
    assert {c["name"] for c in doc["candidates"]} == {"sensor_lag", "added_mass", "correlated_noise"}
    for c in doc["candidates"]:
        assert {"name", "elpd_diff", "elpd_diff_se", "params"} <= set(c)
    lag = next(c for c in doc["candidates"] if c["name"] == "sensor_lag")["params"]["lag"]
    assert lag["q05"] < 0.05 < lag["q95"]
    gain = doc["gain"]
    assert gain["extension"] == "sensor_lag" and gain["elpd_gain"] > 10
    assert set(gain["channels"]) == {"accelerometer", "load cell D1", "load cell D2"}
    for name, channel in gain["channels"].items():
        # RMSE over the whole record is dominated by steady noise: the term must not make it worse
        assert channel["rmse_m2"]["extended"] < 1.05 * channel["rmse_m2"]["baseline"], name
        assert 0 <= channel["coverage_90"]["extended"] <= 1
    assert {"residuals", "error_multipliers", "ppc_flags", "loo_pit", "pareto_k"} <= set(doc["evidence"])
    for name in ("diagnosis.md", "elpd.png", "residuals.png", "comparison.png", "candidates.csv",
                 "baseline/residuals.png", "baseline/ppc.png", "baseline/loo_pit.png"):
        assert (out / name).stat().st_size > 0, name
    assert "sensor_lag" in (out / "diagnosis.md").read_text()


def test_diagnose_command_refuses_an_unknown_candidate(tmp_path, capsys):
    bundle = write_synthetic("drogue", "none", 1, tmp_path / "b")
    code = main(["diagnose", str(bundle), "--out", str(tmp_path / "o"), "--candidates", "wake_prf"])
    assert code == 2
    assert "unknown extension" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()

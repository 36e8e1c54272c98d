"""Fit health warnings (issue 17): each check on draws whose answer is known, then two real fits —
a prior bound below the truth warns naming the parameter and the bound; the clean fit has no warning."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from cpas_bayes.inference import fit_health
from cpas_bayes.stats.distributions import LogNormal, Normal, TruncNormal, Uniform


def _model(*params):
    return SimpleNamespace(parameters=[SimpleNamespace(name=n, prior=p) for n, p in params])


RNG = np.random.default_rng(5)


def test_a_posterior_cut_by_a_prior_bound_warns_and_one_inside_does_not():
    prior = TruncNormal(0.6, 0.1, 0.3, 0.45)
    model = _model(("D1.cds_o", prior))
    piled = np.minimum(0.45, 0.45 - np.abs(RNG.normal(0, 0.01, 4000)))     # a half-normal against 0.45
    inside = RNG.normal(0.40, 0.01, 4000)                                  # 5 sd inside the bound
    w = fit_health.prior_bound_warnings(model, {"D1.cds_o": piled})
    assert [x["code"] for x in w] == ["prior_bound"] and w[0]["parameter"] == "D1.cds_o"
    assert "upper bound 0.45" in w[0]["message"] and "--priors" in w[0]["message"]
    assert fit_health.prior_bound_warnings(model, {"D1.cds_o": inside}) == []


def test_a_posterior_that_repeats_a_flat_prior_or_sits_at_a_physical_limit_is_not_piled():
    flat = RNG.uniform(0.1, 0.9, 4000)          # the data say nothing: not a bound problem
    assert fit_health.prior_bound_warnings(_model(("D1.s1.eps", Uniform(0.1, 0.9))), {"D1.s1.eps": flat}) == []
    no_overshoot = 1.0 + np.abs(RNG.normal(0, 0.005, 4000))   # C_k at 1: a finding, not a prior's cut
    ck = TruncNormal(1.25, 0.25, 1.0, 2.5)
    assert fit_health.prior_bound_warnings(_model(("D1.s1.ck", ck)), {"D1.s1.ck": no_overshoot}) == []
    # the same pile against a non-physical lower bound of n_p does warn
    n_p = LogNormal(10.0, 0.5, 2.0, 50.0)
    w = fit_health.prior_bound_warnings(_model(("D1.s1.n_p", n_p)), {"D1.s1.n_p": 2.0 + np.abs(RNG.normal(0, .05, 4000))})
    assert len(w) == 1 and "lower bound 2" in w[0]["message"]


def test_bundle_priors_point_to_the_bundle_not_a_priors_file():
    prior = TruncNormal(3.0, 0.05, 0.0, 3.5)
    w = fit_health.prior_bound_warnings(_model(("vehicle_cds", prior)),
                                        {"vehicle_cds": 3.5 - np.abs(RNG.normal(0, 0.005, 4000))})
    assert len(w) == 1 and "test.toml" in w[0]["message"]


def test_a_start_or_vehicle_value_the_data_place_far_from_the_bundle_warns():
    start = Normal(9.0, 0.05)          # the bundle's stage start ± its start_sigma
    model = _model(("D3.s2.start", start), ("vehicle_weight", Normal(20000.0, 100.0)))
    w = fit_health.stated_value_warnings(model, {"D3.s2.start": RNG.normal(9.48, 0.01, 4000)})
    assert [(x["code"], x["parameter"]) for x in w] == [("stated_value", "D3.s2.start")]
    assert "D3 stage 2 starts at 9.48" in w[0]["message"] and "9.6 stated sigmas after" in w[0]["message"]
    assert "test.toml" in w[0]["message"]
    heavy = fit_health.stated_value_warnings(model, {"vehicle_weight": RNG.normal(19500.0, 20.0, 4000)})
    assert len(heavy) == 1 and "5.0 stated sigmas below" in heavy[0]["message"]
    # within 4 stated sigmas, or where the data leave the value to the bundle's prior: nothing to say
    assert fit_health.stated_value_warnings(model, {"D3.s2.start": RNG.normal(9.15, 0.01, 4000)}) == []
    assert fit_health.stated_value_warnings(model, {"D3.s2.start": RNG.normal(9.48, 0.03, 4000)}) == []
    # a start within half its stage's fill time of the stated one: an opening's own shape may put it there
    within_fill = {"D3.s2.start": RNG.normal(9.48, 0.01, 4000), "D3.s2.t_fp": np.full(4000, 1.2)}
    assert fit_health.stated_value_warnings(model, within_fill) == []
    within_fill["D3.s2.t_fp"] = np.full(4000, 0.8)
    assert len(fit_health.stated_value_warnings(model, within_fill)) == 1
    # a parameter that is not the bundle's stated value is not judged against its prior here
    assert fit_health.stated_value_warnings(_model(("D3.s2.n_p", LogNormal(8.0, 0.7, 0.5, 60.0))),
                                            {"D3.s2.n_p": RNG.normal(40.0, 0.5, 4000)}) == []


def test_error_multipliers_above_two_warn_by_channel():
    w = fit_health.multiplier_warnings({"noise_acc": np.full(100, 3.1), "noise_lc": np.full(100, 1.2)})
    assert [(x["code"], x["parameter"]) for x in w] == [("error_multiplier", "noise_acc")]
    assert "3.1x" in w[0]["message"]
    assert fit_health.multiplier_warnings({"noise_acc": np.full(100, 1.9)}) == []


def _ppc(p_values, observed=None):
    n = len(p_values)
    return pd.DataFrame({"parachute": "D1", "stage": 1, "statistic": [f"s{i}" for i in range(n)],
                         "p_value": p_values, "observed": observed if observed is not None else np.zeros(n),
                         "replicated_mean": 0.0, "replicated_q05": -1.645, "replicated_q95": 1.645})


def test_ppc_warns_on_three_flags_or_one_statistic_far_outside():
    calm = [0.5, 0.2, 0.8, 0.997, 0.03]          # one beyond 0.995: what a calibrated fit shows
    assert fit_health.ppc_warnings(_ppc(calm)) == []
    assert fit_health.ppc_warnings(_ppc([0.5, 0.0, 0.4], observed=[0.0, 2.2, 0.0])) == []   # a clean Main's p = 0
    assert fit_health.ppc_warnings(_ppc([0.5, 0.0, 0.4], observed=[0.0, 7.5, 0.0]))[0]["code"] == "ppc"
    assert fit_health.ppc_warnings(_ppc([0.5, 0.004, 0.997, 0.003]))[0]["code"] == "ppc"
    assert fit_health.ppc_warnings(_ppc([0.5, 0.004, 0.997])) == []


def test_a_peak_after_the_data_end_warns_naming_the_stage():
    model = SimpleNamespace(parachutes=[SimpleNamespace(id="R1", stages=[object()])])
    late = {"R1.s1.start": np.full(50, 1.0), "R1.s1.t_fp": np.full(50, 3.5), "R1.s1.tk": np.full(50, 0.5)}
    w = fit_health.timing_warnings(model, late, data_end=4.0)
    assert len(w) == 1 and "peak at 4.50 s is after the data end (4.00 s)" in w[0]["message"]
    decay = {**late, "R1.s1.t_fp": np.full(50, 2.8)}
    assert "decay ends at 4.30 s" in fit_health.timing_warnings(model, decay, data_end=4.0)[0]["message"]
    assert fit_health.timing_warnings(model, late, data_end=6.0) == []


def test_convergence_shortfalls_warn():
    per = {"a": {"rhat": 1.002, "ess_bulk": 2000}, "b": {"rhat": 1.03, "ess_bulk": 2000},
           "c": {"rhat": 1.001, "ess_bulk": 150}}
    w = fit_health.convergence_warnings({"per_parameter": per, "ensembles_converged": [True]})
    assert [x["parameter"] for x in w] == ["b", "c"]
    clean = {"per_parameter": {"a": per["a"]}, "ensembles_converged": [True, False]}   # a step limit alone
    assert fit_health.convergence_warnings(clean) == []


# ---------------------------------------------------------------------------
# real fits of the two-Drogue example


@pytest.fixture(scope="module")
def drogue():
    from cpas_bayes.data.bundle import EXAMPLES_DIR, read_bundle
    from cpas_bayes.data.reduction import reduce_test

    test = read_bundle(EXAMPLES_DIR / "drogue-clean")
    return test, reduce_test(test)


def _fit_with_checks(test, reduction, priors=None):
    from cpas_bayes.inference.candidate_fits import DIAGNOSIS_SAMPLER
    from cpas_bayes.inference.fit import fit_model, prepare_model
    from cpas_bayes.inference.fit_folder import record_checks
    from cpas_bayes.inference.predictive_checks import run_checks

    fit = fit_model(prepare_model(test, reduction, priors=priors),
                    replace(DIAGNOSIS_SAMPLER, workers=1, progress=False))
    return fit, record_checks(fit, run_checks(fit, rng=0))


def test_a_prior_bound_below_the_truth_warns_naming_parameter_and_bound(drogue, tmp_path):
    # The example's full-open C_D is ≈ 0.6; this prior stops it at 0.45.
    low = tmp_path / "low.toml"
    low.write_text('kind = "drogue"\n[parachute]\n'
                   'cd_o = { family = "truncnormal", mu = 0.45, sigma = 0.10, low = 0.30, high = 0.45 }\n')
    fit, warnings = _fit_with_checks(*drogue, priors=low)
    bound = [w for w in warnings if w["code"] == "prior_bound" and w["parameter"].endswith(".cds_o")]
    assert bound, warnings
    area_bound = fit.model.parameters[fit.model.index[bound[0]["parameter"]]].prior.support[1]
    assert f"upper bound {area_bound:g} m², i.e. cd_o = 0.45 on S_o" in bound[0]["message"]   # as the file says
    assert {"error_multiplier", "ppc"} <= {w["code"] for w in warnings}   # the misfit shows too
    assert fit.summary["warnings"] == warnings


def test_a_stage_start_stated_half_a_second_early_is_said_and_the_fit_still_finds_it(drogue, clean_fit):
    from cpas_bayes.data.reduction import reduce_test

    test, _ = drogue
    d3 = test.parachutes[0]
    early = replace(d3.stages[1], start=d3.stages[1].start - 0.48)      # 9.6 of its 0.05 s sigma early
    test = replace(test, parachutes=(replace(d3, stages=(d3.stages[0], early)),) + test.parachutes[1:])
    fit, warnings = _fit_with_checks(test, reduce_test(test))
    said = [w for w in warnings if w["code"] == "stated_value"]
    assert [w["parameter"] for w in said] == ["D3.s2.start"], warnings
    assert "D3 stage 2 (full open) starts at" in said[0]["message"] and "after the bundle's" in said[0]["message"]
    # the data, not the bundle, place the start: where the fit of the bundle as written puts it
    start = fit.summary["parachutes"]["D3"]["stages"][1]["start"]
    clean = clean_fit[0].summary["parachutes"]["D3"]["stages"][1]["start"]
    assert abs(start["q50"] - clean["q50"]) < 3 * np.hypot(start["sd"], clean["sd"])


@pytest.fixture(scope="module")
def clean_fit(drogue):
    return _fit_with_checks(*drogue)


def test_the_clean_example_fit_has_no_warning(clean_fit):
    fit, warnings = clean_fit
    assert warnings == []
    stage = fit.summary["parachutes"]["D3"]["stages"][0]
    assert 0.1 < stage["t_f"]["q50"] < stage["t_fp"]["q50"] < 1.0     # fill times in seconds beside n and n_p


def test_a_fill_spanning_few_samples_warns_about_the_logger_rate():
    model = SimpleNamespace(parachutes=[SimpleNamespace(id="R1", stages=[object(), object()])])
    draws = {"R1.s1.t_fp": np.full(50, 0.3), "R1.s2.t_fp": np.full(50, 1.2)}
    w = fit_health.sample_rate_warnings(model, draws, sample_interval=0.05)        # 20 Hz
    assert [x["parameter"] for x in w] == ["R1.s1.n_p"] and "6.0 samples at 20 Hz" in w[0]["message"]
    assert fit_health.sample_rate_warnings(model, draws, sample_interval=0.005) == []   # 200 Hz

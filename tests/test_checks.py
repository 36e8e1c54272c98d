"""Posterior predictive checks, residual diagnostics and fit figures (cpas_bayes.inference.predictive_checks,
inference.residuals, outputs.plots.fit).

One short fit of the clean two-Drogue example is shared by the module (the
model is correct there); the wrong-model cases edit its observations after the
fit, so the same posterior meets data it does not describe. Tests that need the
fit are marked slow; the hand-built cases run without it.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import warnings

import numpy as np
import pytest
from scipy import stats

from cpas_bayes.inference import predictive_checks as checks
from cpas_bayes.inference import residuals as resid
from cpas_bayes.data.bundle import example_bundles, read_bundle
from cpas_bayes.inference.fit import SamplerOptions, fit_test

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SEED = 7
N_DRAWS = 400   # replicated data sets: Monte Carlo sd of a p-value near 0.03 is ≈ 0.009


@pytest.fixture(scope="module")
def drogue_fit():
    test = read_bundle(next(p for p in example_bundles() if p.name == "drogue-clean"))
    # differential evolution, as this fixture ran before the warm-up could fit in 1,000 steps: thinned by ½ τ,
    # its draws have no repeats. The adaptive proposal's thinner chains repeat draws (a walker that refused
    # five moves), and tied log ratios leave PSIS free to order them: ArviZ's order and ours then give the same
    # PSIS-LOO but LOO-PIT values 1e-5 apart (test_fit_loo_and_loo_pit_equal_arviz_own)
    return fit_test(test, SamplerOptions(seed=1, n_ensembles=2, max_steps=1000, check_every=500, map_starts=2,
                                         progress=False, proposal="de"))


@pytest.fixture(scope="module")
def drogue_checks(drogue_fit):
    return checks.run_checks(drogue_fit, n_draws=N_DRAWS, rng=SEED)


def _with_obs(fit, **changes):
    """The same posterior with edited observations (no refit)."""
    model = copy.copy(fit.model)
    model.obs = dataclasses.replace(fit.model.obs, **changes)
    return dataclasses.replace(fit, model=model)


# ---------------------------------------------------------------------------
# posterior predictive p-values


@pytest.mark.slow
def test_ppc_table_covers_every_series_stage_and_statistic(drogue_checks):
    table = drogue_checks.ppc.table
    # 2 load cells × 2 stages + total × 2 stages, five statistics each
    assert len(table) == 6 * len(checks.STATISTICS)
    assert set(table["parachute"]) == {"D3", "D6", "total"}
    assert set(table["statistic"]) == set(checks.STATISTICS)
    p = table["p_value"].to_numpy()
    assert np.all(np.isfinite(p)) and np.all((p >= 0) & (p <= 1))
    assert drogue_checks.ppc.replicated.shape == (len(table), N_DRAWS)


@pytest.mark.slow
def test_clean_example_has_no_extreme_p_values(drogue_checks):
    # Tolerance: a correct model should put every stage statistic inside
    # [0.01, 0.99]; posterior predictive p-values concentrate towards 0.5, so
    # with 30 statistics a chance excursion beyond 0.01 is already unlikely.
    # The lowest on this bundle is D6's full-open peak drag area, p ≈ 0.03
    # (0.005–0.05 over check seeds; its parameters cover the truth), so the
    # seeds are fixed and N_DRAWS keeps the Monte Carlo error near 0.009.
    table = drogue_checks.ppc.table
    extreme = table[(table["p_value"] < 0.01) | (table["p_value"] > 0.99)]
    assert extreme.empty, extreme.to_string()


@pytest.mark.slow
def test_ppc_statistics_on_the_observed_series_are_physical(drogue_checks):
    t = drogue_checks.ppc.table.set_index(["parachute", "stage", "statistic"])["observed"]
    for pid in ("D3", "D6"):
        for stage in (1, 2):
            # infinite mass: over-inflation peak above the steady value, peak after the fill
            assert t[(pid, stage, "peak_drag_area")] > t[(pid, stage, "stage_mean_drag_area")]
            assert 0 < t[(pid, stage, "fill_time")] < t[(pid, stage, "time_to_peak")] < 2.0
    # reefed Drogue about 0.44 of full open; total ≈ sum of the two canopies (m²)
    ratio = t[("D3", 1, "stage_mean_drag_area")] / t[("D3", 2, "stage_mean_drag_area")]
    assert 0.40 < ratio < 0.48
    both = t[("D3", 2, "stage_mean_drag_area")] + t[("D6", 2, "stage_mean_drag_area")]
    assert t[("total", 2, "stage_mean_drag_area")] == pytest.approx(both, rel=0.02)


@pytest.mark.slow
def test_shifted_load_cells_are_flagged_by_the_stage_means(drogue_fit):
    obs = drogue_fit.model.obs
    shifted = _with_obs(drogue_fit, lc=obs.lc * 1.02)
    table = checks.ppc_statistics(shifted, n_draws=200, rng=SEED)
    clean = checks.ppc_statistics(drogue_fit, n_draws=200, rng=SEED)
    cells = table[(table["parachute"] != "total") & (table["statistic"] == "stage_mean_drag_area")]
    # data 2 % above every replicate: P(T_rep ≥ T_obs) collapses to 0
    assert (cells["p_value"] < 0.01).all(), cells.to_string()
    # the accelerometer was not touched: its rows are unchanged (same seed, same replicates)
    total_new = table[table["parachute"] == "total"]["p_value"].to_numpy()
    total_old = clean[clean["parachute"] == "total"]["p_value"].to_numpy()
    np.testing.assert_allclose(total_new, total_old)
    # and the standardised residuals of the load cells turn positive in the steady phases
    report = resid.residuals(shifted)
    rows = report.table[report.table["channel"].str.startswith("load cell")
                        & report.table["phase"].isin(["steady", "full_open"])]
    assert (rows["mean"] > 1.0).all(), rows.to_string()


@pytest.mark.slow
def test_injected_oscillation_shows_in_the_residual_autocorrelation(drogue_fit, drogue_checks):
    obs = drogue_fit.model.obs
    wave = 3.0 * np.hypot(obs.acc_sigma, getattr(obs, "acc_qbar", 0.0)) * np.sin(2 * np.pi * 0.8 * obs.time)
    wavy = _with_obs(drogue_fit, acc=obs.acc + wave)
    report = resid.residuals(wavy)

    def row(table, channel, phase):
        return table[(table["channel"] == channel) & (table["phase"] == phase)].iloc[0]

    clean = drogue_checks.residuals.table
    for phase in ("steady", "full_open"):
        before = row(clean, "accelerometer", phase)
        after = row(report.table, "accelerometer", phase)
        assert before.acf1 < 0.3 and after.acf1 > 0.6
        assert after.ljung_box_p < 1e-6 < before.ljung_box_p
    # the load cells were not touched
    pd_clean = row(clean, "load cell D3", "steady")
    pd_new = row(report.table, "load cell D3", "steady")
    assert pd_new.acf1 == pytest.approx(pd_clean.acf1, abs=0.05)


# ---------------------------------------------------------------------------
# residual machinery on hand-built cases


def test_phase_classification_of_a_tiny_case():
    time = np.arange(0.0, 10.0, 0.5)
    starts, t_fp, t_k = np.array([2.0, 6.0]), np.array([1.0, 1.5]), np.array([1.0, 0.5])
    got = resid.classify_phases(time, starts, t_fp, t_k, infinite=True)
    expected = (["pre_deploy"] * 4                 # 0.0 .. 1.5
                + ["fill"] * 2                     # 2.0, 2.5   (< 2 + 1)
                + ["overinflation"] * 2            # 3.0, 3.5   (< 2 + 1 + 1)
                + ["steady"] * 4                   # 4.0 .. 5.5 (reefed stage)
                + ["fill"] * 3                     # 6.0, 6.5, 7.0 (< 6 + 1.5)
                + ["overinflation"]                # 7.5        (< 6 + 1.5 + 0.5)
                + ["full_open"] * 4)               # 8.0 .. 9.5
    assert list(got) == expected
    finite = resid.classify_phases(time, starts, t_fp, t_k, infinite=False)
    assert "overinflation" not in set(finite)
    assert list(finite[6:8]) == ["steady", "steady"]

    other = resid.classify_phases(time, np.array([2.5, 7.0]), np.array([0.5, 0.5]), np.array([0.0, 0.0]))
    cluster = resid.cluster_phases(np.array([got, other]))
    # pre_deploy only while both are; the most dynamic phase wins elsewhere
    assert list(cluster[:4]) == ["pre_deploy"] * 4
    assert cluster[list(time).index(2.5)] == "fill"
    assert cluster[list(time).index(7.5)] == "overinflation"
    assert cluster[list(time).index(7.0)] == "fill"
    assert list(cluster[-4:]) == ["full_open"] * 4


def test_ljung_box_matches_hand_computation():
    # Alternating series: mean 0, r_1 = −(n − 1)/n exactly.
    n = 10
    x = (-1.0) ** np.arange(n)
    q, p, h = resid.ljung_box(x, lags=1)
    r1 = -(n - 1) / n
    assert h == 1
    assert q == pytest.approx(n * (n + 2) * r1**2 / (n - 1))        # = 10.8
    assert q == pytest.approx(10.8)
    assert p == pytest.approx(stats.chi2.sf(10.8, 1))

    # A fixed series against the textbook sums, three lags.
    y = np.array([0.3, -1.2, 0.8, 1.9, -0.4, 0.1, -0.7, 1.1, 0.6, -1.5, 0.2, 0.9])
    d = y - y.mean()
    r = [np.sum(d[:-k] * d[k:]) / np.sum(d * d) for k in (1, 2, 3)]
    m = y.size
    q_hand = m * (m + 2) * sum(r[k - 1] ** 2 / (m - k) for k in (1, 2, 3))
    q, p, h = resid.ljung_box(y, lags=3)
    assert (q, h) == (pytest.approx(q_hand), 3)
    assert p == pytest.approx(stats.chi2.sf(q_hand, 3))
    np.testing.assert_allclose(resid.autocorrelation(y, 3), r)


def test_masked_autocorrelation_counts_only_pairs_inside_the_mask():
    x = np.array([5.0, 1.0, -1.0, 1.0, -1.0, 50.0, 1.0, -1.0])
    mask = np.array([False, True, True, True, True, False, True, True])
    r1 = resid.autocorrelation(x, 1, mask)[0]
    vals = x[mask]
    d = vals - vals.mean()
    # in-mask adjacent pairs: (1,2), (2,3), (3,4), (6,7)
    pairs = [(1, 2), (2, 3), (3, 4), (6, 7)]
    num = sum((x[i] - vals.mean()) * (x[j] - vals.mean()) for i, j in pairs)
    assert r1 == pytest.approx(num / np.sum(d * d))


def test_stage_statistics_on_a_noise_free_curve():
    # 0 before 1 s, linear growth 30/s to a peak of 12 at 1.4 s, linear decay to 10 at 1.8 s, then steady.
    time = np.arange(0.0, 5.0, 0.02) + 0.01
    cds = np.interp(time, [0.0, 1.0, 1.4, 1.8, 5.0], [0.0, 0.0, 12.0, 10.0, 10.0])
    qbar, weight, g = 500.0, 100.0, 1.5
    load = qbar * cds - weight * g
    window = checks.StageWindow("x", 1, "stage", t0=1.0, t1=5.1, t_steady=3.0)
    got = checks.stage_statistics(time, np.array([cds]), np.array([load]), window)
    assert got["stage_mean_drag_area"][0] == pytest.approx(10.0)
    # the threshold 0.95·10 is crossed on the straight part, which the quadratic filter keeps
    assert got["fill_time"][0] == pytest.approx(9.5 / 30.0, abs=1e-9)
    # the filter rounds the corner a little: peak slightly low, its time near 1.4 s
    assert 11.3 < got["peak_drag_area"][0] <= 12.0
    assert got["time_to_peak"][0] == pytest.approx(0.4, abs=0.02)
    assert got["peak_load"][0] == pytest.approx(qbar * got["peak_drag_area"][0] - weight * g, rel=1e-9)


def test_bayesian_p_value_counts_ties_half_and_drops_nan():
    assert checks.bayesian_p_value([1.0, 2.0, 3.0, np.nan], 2.0) == pytest.approx(0.5)
    assert checks.bayesian_p_value([1.0, 1.0], 5.0) == 0.0
    assert np.isnan(checks.bayesian_p_value([1.0], np.nan))


# ---------------------------------------------------------------------------
# LOO-PIT, Pareto k, report


@pytest.mark.slow
def test_loo_pit_and_pareto_k(drogue_fit, drogue_checks):
    pit = drogue_checks.loo_pit
    assert set(pit.values) == {"accelerometer", "load cell D3", "load cell D6"}
    n = drogue_fit.model.obs.n_bins
    for u in pit.values.values():
        assert u.shape == (n,) and np.all((u >= 0) & (u <= 1))
    # calibrated model: KS distance inside the DKW band, PIT sd near 1/√12
    assert (pit.table["ks_distance"] < pit.table["dkw_band"]).all()
    assert np.allclose(pit.table["pit_sd"], 1 / np.sqrt(12), atol=0.03)
    res = drogue_checks.residuals
    assert res.pareto_k.shape == (n,)
    assert res.elpd_loo["n_high_pareto_k"] == int(np.sum(res.pareto_k > resid.PARETO_K_LIMIT))
    assert res.elpd_loo["n_high_pareto_k"] <= 0.02 * n
    for name in ("noise_acc", "noise_lc"):
        s = res.noise[name]
        assert s["q05"] < s["mean"] < s["q95"] and 0.8 < s["mean"] < 1.2


@pytest.mark.slow
def test_check_report_is_json(drogue_fit, drogue_checks):
    report = checks.check_report(drogue_fit, checks=drogue_checks)
    text = json.dumps(report, allow_nan=False)
    back = json.loads(text)
    assert {"ppc", "ppc_flags", "loo_pit", "residuals", "pareto_k", "noise", "definitions"} <= set(back)
    assert len(back["ppc"]) == len(drogue_checks.ppc.table)
    assert back["ppc_flags"] == []


# ---------------------------------------------------------------------------
# figures


@pytest.mark.slow
def test_write_fit_figures_writes_valid_pngs(drogue_fit, drogue_checks, tmp_path):
    from cpas_bayes.core.executor import Executor
    from cpas_bayes.outputs.fit_figures import start_corner_figures, write_fit_figures

    paths = write_fit_figures(drogue_fit, tmp_path / "figures", checks=drogue_checks, n_draws=150)
    names = {p.name for p in paths}
    expected = {"bands.png", "loads.png", "trace.png", "ppc.png", "loo_pit.png", "residuals.png",
                "corner_D3_s1.png", "corner_D3_s2.png", "corner_D6_s1.png", "corner_D6_s2.png"}
    assert names == expected
    for p in paths:
        data = p.read_bytes()
        assert data[:8] == PNG_MAGIC, p.name
        assert len(data) > 20_000, p.name
    assert not list((tmp_path / "figures").glob(".*tmp"))    # atomic writes left no temporaries
    # the fit command starts the corners from the sampled draws, before the DataTree: the same files
    started = start_corner_figures(drogue_fit.model, drogue_fit.sampling, tmp_path / "early", Executor())
    early = write_fit_figures(drogue_fit, tmp_path / "early", n_draws=150, parts=("draws",), started=started)
    assert {p.name for p in early} == expected - {"ppc.png", "loo_pit.png", "residuals.png"}
    for p in early:
        assert p.read_bytes() == (tmp_path / "figures" / p.name).read_bytes(), p.name


def test_fit_loo_and_loo_pit_equal_arviz_own(drogue_fit):
    """The weights smoothed here in one pass give ArviZ's own PSIS-LOO and LOO-PIT on a real fit's check tree."""
    import arviz as az

    from cpas_bayes.inference.loo import loo_pit, psis_loo

    tree = checks.check_tree(drogue_fit, rng=checks.as_rng(SEED))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = az.loo(tree, var_name="total", pointwise=True)
        pit_ref = az.loo_pit(tree, var_names=["acc", "lc"])
    ours = psis_loo(tree, "total")
    assert ours.elpd == pytest.approx(ref.elpd, abs=1e-9) and ours.se == pytest.approx(ref.se, abs=1e-9)
    assert ours.p == pytest.approx(ref.p, abs=1e-9)
    np.testing.assert_allclose(ours.elpd_i.values, ref.elpd_i.values, atol=1e-9)
    np.testing.assert_allclose(ours.pareto_k.values, ref.pareto_k.values, atol=1e-9)
    pit = loo_pit(tree, ["acc", "lc"])
    for var in ("acc", "lc"):
        np.testing.assert_allclose(pit[var].values, pit_ref[var].values, atol=1e-9)

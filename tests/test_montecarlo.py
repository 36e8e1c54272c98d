"""Monte Carlo loads from a memo, the seed's n_p claim, and measured-vs-predicted load comparison.

Memos here are built by hand (uniform families, population draws sampled
from them), so every expectation follows from the numbers in this file.
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from cpas_bayes.data.bundle import EXAMPLES_DIR, read_bundle
from cpas_bayes.app.cli import main
from cpas_bayes.loads.compare import (exceedance_probability, measurement_percentile, stage_comparisons)
from cpas_bayes.core.errors import InputError
from cpas_bayes.population.memo import Memo, MemoEntry
from cpas_bayes.loads.fill_time import compare_fill_time_dispersion
from cpas_bayes.loads.montecarlo import ClusterLayout, draw_run_inputs, run_monte_carlo, simulate_runs
from cpas_bayes.data.peaks import Peak, StageInterval, StagePeaks
from cpas_bayes.physics.trajectory import SimulationOptions, VehicleProperties, VehicleState0, simulate

DROGUE = EXAMPLES_DIR / "drogue-clean"
MAIN = EXAMPLES_DIR / "main-clean"
SEED = 20261121


def uniform(kind, stage, parameter, low, high):
    return MemoEntry(kind, stage, parameter, "uniform", {"low": low, "high": high}, (low, high))


def hand_memo(spec, n_draws=4000, seed=1):
    """Memo from {kind: {stage: {parameter: (low, high)}}}; population draws sampled independently."""
    rng = np.random.default_rng(seed)
    entries, frames = {}, []
    for kind, stages in spec.items():
        cols = {}
        for stage, params in stages.items():
            for parameter, (low, high) in params.items():
                entry = uniform(kind, stage, parameter, low, high)
                entries[(kind, stage, parameter)] = entry
                cols[f"{stage}.{parameter}"] = entry.sample(rng, n_draws)
        frame = pd.DataFrame(cols)
        frame.insert(0, "kind", kind)
        frames.append(frame)
    return Memo(entries, pd.concat(frames, ignore_index=True), {"method": "hand-built for tests"})


# Drogue population: the example bundle's truth lies inside these ranges.
N_P = {"first": (9.0, 13.0), "full_open": (8.5, 12.0)}
EPS_FIRST = (0.43, 0.45)


def drogue_spec(n_p=N_P, ck=((1.2, 1.45), (1.1, 1.3)), expopen=((2.0, 2.5), (1.9, 2.5)), n=None, t_fp=None):
    stages = {}
    for j, key in enumerate(("first", "full_open")):
        stages[key] = {"n_p": n_p[key], "expopen": expopen[j], "ck": ck[j], "tk": (0.35, 0.7)}
        stages[key]["n"] = n[key] if n else n_p[key]
        if t_fp:
            stages[key]["t_fp"] = t_fp[key]
    stages["first"]["eps"] = EPS_FIRST
    stages["parachute"] = {"cd_o": (0.58, 0.62)}
    return {"drogue": stages}


MAIN_SPEC = {"main": {
    "parachute": {"cd_o": (0.50, 0.54)},
    "first": {"n_p": (14.0, 21.0), "n": (14.0, 21.0), "expopen": (1.6, 2.9), "eps": (0.05, 0.07), "t_fp": (1, 9)},
    "reefed1": {"n_p": (8.0, 13.0), "n": (8.0, 13.0), "expopen": (1.6, 2.9), "eps": (0.18, 0.20), "t_fp": (1, 9)},
    "full_open": {"n_p": (6.0, 7.5), "n": (6.0, 7.5), "expopen": (1.4, 1.8), "t_fp": (1, 12)},
}}


@pytest.fixture(scope="module")
def drogue():
    return read_bundle(DROGUE)


@pytest.fixture(scope="module")
def main_test():
    return read_bundle(MAIN)


def airspeed_range(test, stage_index, margin=0.03):
    """Measured airspeed around the nominal starts of a stage (±3 start sigmas), widened by ``margin``."""
    t, v = test.time, test.data["airspeed"].to_numpy()
    lo, hi = math.inf, -math.inf
    for p in test.parachutes:
        st = p.stages[stage_index]
        m = (t >= st.start - 3 * st.start_sigma) & (t <= st.start + 3 * st.start_sigma)
        lo, hi = min(lo, v[m].min()), max(hi, v[m].max())
    return lo * (1 - margin), hi * (1 + margin)


def closed_form_t_fp_range(test, n_p_bounds):
    """t_fp = n_p·D_o·sqrt(Δε)/V_i (Eq. 16–17) over the n_p, ε and V_i ranges, per memo stage."""
    D = test.parachutes[0].diameter
    d_eps = {"first": EPS_FIRST, "full_open": (1 - EPS_FIRST[1], 1 - EPS_FIRST[0])}
    out = {}
    for k, key in enumerate(("first", "full_open")):
        v_lo, v_hi = airspeed_range(test, k)
        out[key] = (n_p_bounds[key][0] * D * math.sqrt(d_eps[key][0]) / v_hi,
                    n_p_bounds[key][1] * D * math.sqrt(d_eps[key][1]) / v_lo)
    return out


# ---------------------------------------------------------------------------
# the n_p re-parameterisation


def test_narrow_n_p_gives_the_closed_form_peak_fill_times(drogue):
    narrow = {"first": (9.9, 10.1), "full_open": (10.4, 10.6)}
    memo = hand_memo(drogue_spec(n_p=narrow))
    result = run_monte_carlo(memo, drogue, 300, np.random.default_rng(SEED), mode="n_p", joint=False)
    o, x = result.outputs, result.inputs
    D = drogue.parachutes[0].diameter
    # Per run, Eq. 16–17 with the simulated V_i: the first stage fills from 0, full open from the reefed area.
    np.testing.assert_allclose(o.t_fp[:, :, 0], x.n_fill[:, :, 0] * D * np.sqrt(x.eps[:, :, 0]) / o.v_i[:, :, 0],
                               rtol=1e-12)
    np.testing.assert_allclose(o.t_fp[:, :, 1],
                               x.n_fill[:, :, 1] * D * np.sqrt(1 - x.eps[:, :, 0]) / o.v_i[:, :, 1], rtol=1e-9)
    # Over the population: inside the range the narrow n_p allows at this test's airspeeds.
    expected = closed_form_t_fp_range(drogue, narrow)
    for k, key in enumerate(("first", "full_open")):
        lo, hi = expected[key]
        assert lo <= o.t_fp[:, :, k].min() and o.t_fp[:, :, k].max() <= hi
        assert hi / lo < 1.2   # the range is indeed narrow: n_p fixes t_fp whatever C_k and expopen are
    # n differs from n_p by S^(-1/expopen) (Eq. 18), which varies with the independent C_k and expopen.
    assert np.ptp(o.n[:, :, 0] / o.n_p[:, :, 0]) > 0.02


def wide_shape_setup(test):
    """The seed §V.D setup: narrow-ish n_p population, C_k 1.1–1.8, expopen 0.6–3.0 (wide), n as tests show it.

    The n population is what the tests would show for these n_p, C_k and expopen (Eq. 18, held area 0 for
    the first stage, ε·CDS_o for full open): its 1–99 % range. The tested t_fp range is the closed form
    over n_p at this test's airspeeds.
    """
    ck, expopen = ((1.1, 1.8), (1.1, 1.8)), ((0.6, 3.0), (0.6, 3.0))
    rng = np.random.default_rng(7)
    n_range = {}
    for j, key in enumerate(("first", "full_open")):
        n_p = rng.uniform(*N_P[key], 50_000)
        c, e = rng.uniform(*ck[j], 50_000), rng.uniform(*expopen[j], 50_000)
        eps = np.mean(EPS_FIRST)
        ratio = c if key == "first" else (c - eps) / (1 - eps)
        n_range[key] = tuple(np.quantile(n_p * ratio ** (-1 / e), [0.01, 0.99]))
    t_fp = closed_form_t_fp_range(test, N_P)
    return hand_memo(drogue_spec(ck=ck, expopen=expopen, n=n_range, t_fp=t_fp))


def test_dispersing_n_leaves_the_tested_fill_time_range_more_than_n_p(drogue):
    memo = wide_shape_setup(drogue)
    comparison = compare_fill_time_dispersion(memo, drogue, 400, np.random.default_rng(SEED))
    assert {(g.kind, g.stage) for g in comparison.groups} == {("drogue", "first"), ("drogue", "full_open")}
    for g in comparison.groups:
        f_np, f_n = g.fraction_outside("n_p"), g.fraction_outside("n")
        assert f_np == 0.0                       # n_p dispersed: never outside what the tests showed
        assert f_n > f_np + 0.3                  # n dispersed with independent C_k, expopen: often outside
        assert g.fraction_above("n") > 0.1       # ... mostly as long fills (seed Fig. 21–22)
    # Same draws in both modes except the fill constant.
    a, b = comparison.results["n_p"].inputs, comparison.results["n"].inputs
    for name in ("start", "expopen", "ck", "tk", "eps", "cds_o"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    doc = comparison.to_json()
    assert doc["groups"][0]["n"]["fraction_outside"] == comparison.groups[0].fraction_outside("n")


# ---------------------------------------------------------------------------
# batches against single simulations


def test_batch_equals_single_simulations(main_test):
    memo = hand_memo(MAIN_SPEC)
    result = run_monte_carlo(memo, main_test, 6, np.random.default_rng(SEED), history_runs=6, batch=4)
    lay, o = result.layout, result.outputs
    reference = run_monte_carlo(memo, main_test, 6, np.random.default_rng(SEED), engine="trajectory", history_runs=6)
    r = reference.outputs
    np.testing.assert_allclose(o.history, r.history, rtol=0, atol=1e-7 * np.abs(r.history).max())
    for name in ("t_fp", "t_f", "n", "n_p", "v_i"):
        np.testing.assert_allclose(getattr(o, name), getattr(r, name), rtol=1e-9)
    # Compiled peaks also see the drag-area peak instants between samples: never below the sampled peaks.
    assert np.all(o.stage_peak_load >= r.stage_peak_load * (1 - 1e-9))
    assert np.all(o.stage_peak_load <= r.stage_peak_load * 1.01)
    for i in (0, 3, 5):   # per-run single simulations, batch of one
        single = simulate(VehicleState0(lay.airspeed0, lay.gamma0, lay.altitude0),
                          VehicleProperties(lay.vehicle_weight, lay.vehicle_cds), result.single_run_cluster(i),
                          lay.duration, SimulationOptions(), t0=lay.t0, refine_peaks=40)
        np.testing.assert_allclose(o.history[i], single.tension[0].sum(axis=0), rtol=0,
                                   atol=1e-7 * np.abs(single.tension).max())
        np.testing.assert_allclose(o.t_fp[i], single.timing.t_fp[0], rtol=1e-9)
        np.testing.assert_allclose(np.nanmax(o.chute_peak_load[i], axis=-1), single.peak_tension[0], rtol=1e-3)
        np.testing.assert_allclose(np.nanmax(o.stage_peak_load[i]), single.peak_total_tension[0], rtol=1e-3)


def test_trajectory_engine_batch_equals_its_single_runs(drogue):
    memo = hand_memo(drogue_spec())
    layout = ClusterLayout.from_test(drogue)
    inputs = draw_run_inputs(memo, layout, 3, np.random.default_rng(SEED))
    batch = simulate_runs(layout, inputs, engine="trajectory", history_runs=3)
    for i in range(3):
        one = simulate_runs(layout, inputs.take(slice(i, i + 1)), engine="trajectory", history_runs=1)
        np.testing.assert_allclose(batch.history[i], one.history[0], rtol=1e-12)
        np.testing.assert_allclose(batch.stage_peak_load[i], one.stage_peak_load[0], rtol=1e-12)


def test_reproducible_with_a_seed_and_independent_of_batching(drogue):
    memo = hand_memo(drogue_spec())
    a = run_monte_carlo(memo, drogue, 50, np.random.default_rng(3), batch=50).frame()
    b = run_monte_carlo(memo, drogue, 50, np.random.default_rng(3), batch=7).frame()
    c = run_monte_carlo(memo, drogue, 50, np.random.default_rng(4)).frame()
    pd.testing.assert_frame_equal(a, b)
    assert not np.allclose(a["s1.peak_load"], c["s1.peak_load"])
    # Load share at the stage peak sums to one; peaks are positive and in the stage's interval.
    shares = a[[c for c in a.columns if c.startswith("s1.share.")]].sum(axis=1)
    np.testing.assert_allclose(shares, 1.0, rtol=1e-12)
    assert (a["s1.peak_load"] > 0).all() and (a["s2.peak_time"] > a["s1.peak_time"]).all()


def test_finite_mass_canopies_take_ck_one_and_no_decay(main_test):
    memo = hand_memo(MAIN_SPEC)
    result = run_monte_carlo(memo, main_test, 20, np.random.default_rng(SEED), mode="n")
    x, o = result.inputs, result.outputs
    assert np.all(x.ck == 1.0) and np.all(x.tk == 0.0) and np.all(x.eps[:, :, -1] == 1.0)
    np.testing.assert_allclose(o.n, o.n_p, rtol=1e-12)   # S = 1: n = n_p (Eq. 18)
    cd_o = x.cds_o / (math.pi / 4 * np.array([p.diameter for p in main_test.parachutes]) ** 2)
    assert cd_o.min() >= 0.50 and cd_o.max() <= 0.54


def test_a_memo_lacking_a_stage_is_refused_by_name(drogue, tmp_path):
    spec = drogue_spec()
    del spec["drogue"]["full_open"]
    memo = hand_memo(spec)
    with pytest.raises(InputError, match="full_open.n_p.*D3"):
        run_monte_carlo(memo, drogue, 5, np.random.default_rng(0))
    with pytest.raises(InputError, match="drogue.full_open.n_p"):
        run_monte_carlo(memo, drogue, 5, np.random.default_rng(0), joint=False)
    with pytest.raises(InputError, match="kind 'drogue'"):
        run_monte_carlo(hand_memo(MAIN_SPEC), drogue, 5, np.random.default_rng(0))
    memo = hand_memo(drogue_spec())
    with pytest.raises(InputError, match="t_fp"):   # the n_p claim needs the tested t_fp range
        compare_fill_time_dispersion(memo, drogue, 5, np.random.default_rng(0))


# ---------------------------------------------------------------------------
# measured against predicted


def test_percentile_is_half_at_the_median_and_moves_with_a_shift():
    draws = np.random.default_rng(0).normal(100_000.0, 5_000.0, 200_000)
    median = float(np.median(draws))
    for sigma in (0.0, 2_000.0, 5_000.0):
        assert measurement_percentile(draws, median, sigma) == pytest.approx(50.0, abs=0.3)
    # Shifted by one predicted sd: Φ(1/sqrt(1 + (σ/sd)²)) for the convolved distribution.
    for sigma, expected in ((0.0, 84.13), (5_000.0, 76.02)):
        assert measurement_percentile(draws, median + 5_000.0, sigma) == pytest.approx(expected, abs=0.3)
        assert measurement_percentile(draws, median - 5_000.0, sigma) == pytest.approx(100 - expected, abs=0.3)
    assert exceedance_probability(draws, median + 5_000.0, 5_000.0) == pytest.approx(0.2398, abs=0.003)
    assert measurement_percentile(draws, median + 1e6, 1.0) == pytest.approx(100.0)


def test_stage_comparisons_place_hand_built_measurements():
    predicted = np.random.default_rng(1).normal([30_000.0, 45_000.0], [1_500.0, 2_000.0], size=(50_000, 2))
    result = SimpleNamespace(outputs=SimpleNamespace(stage_peak_load=predicted))
    medians = np.median(predicted, axis=0)

    def peaks(shift):
        return [StagePeaks(StageInterval(k, label, 1.0 + 9 * k, 9.5 + 9 * k),
                           Peak(medians[k] + shift[k], 600.0, 1.5 + 9 * k),
                           Peak(medians[k] + shift[k] - 300.0, 400.0, 1.5 + 9 * k), {})
                for k, label in enumerate(("reefed", "full open"))]

    at_median = {(c.stage_index, c.channel): c for c in stage_comparisons({"population": result}, peaks([0, 0]))}
    assert at_median[(0, "accelerometer")].percentile == pytest.approx(50.0, abs=0.5)
    assert at_median[(1, "accelerometer")].p_exceed == pytest.approx(0.5, abs=0.005)
    assert at_median[(0, "load_cells")].percentile < 50.0           # 300 N below the median
    high = {(c.stage_index, c.channel): c for c in stage_comparisons({"population": result},
                                                                     peaks([3_000.0, -4_000.0]))}
    assert high[(0, "accelerometer")].percentile == pytest.approx(
        100 * 0.5 * math.erfc(-3_000.0 / math.hypot(1_500.0, 600.0) / math.sqrt(2)), abs=0.5)
    assert high[(1, "accelerometer")].percentile < 5.0 and high[(1, "accelerometer")].p_exceed > 0.95


# ---------------------------------------------------------------------------
# command line


def test_cli_montecarlo_and_compare_write_their_files(drogue, tmp_path):
    memo_dir = tmp_path / "memo"
    wide_shape_setup(drogue).write(memo_dir)
    out = tmp_path / "mc"
    assert main(["montecarlo", "--memo", str(memo_dir / "memo.toml"), "--like", str(DROGUE), "--runs", "60",
                 "--out", str(out), "--seed", "5", "--compare-np"]) == 0
    for name in ("runs.csv", "summary.json", "peak_loads.png", "fill_times.png", "np_vs_n.json",
                 "fill_time_np_vs_n.png"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert {"stages", "runtime_s", "runs_per_s", "runs", "mode", "joint", "units", "seed"} <= set(summary)
    stage = summary["stages"][0]
    assert {"q01", "q05", "q50", "q95", "q99", "mean", "sd"} <= set(stage["peak_load"])
    assert {"peak_load", "t_fp", "share_at_stage_peak"} <= set(stage["parachutes"]["D3"])
    assert summary["units"]["force"] == "lbf" and summary["runs"] == 60
    runs = pd.read_csv(out / "runs.csv")
    assert len(runs) == 60 and {"s1.peak_load", "D3.s1.t_fp", "s2.share.D6"} <= set(runs.columns)
    # US bundle: loads in lbf (tens of thousands for a pair of Drogues), not N.
    assert 15_000 < runs["s2.peak_load"].median() < 80_000
    np_vs_n = json.loads((out / "np_vs_n.json").read_text())
    assert {g["stage"] for g in np_vs_n["groups"]} == {"first", "full_open"}
    assert all({"fraction_outside", "t_fp_s"} <= set(g["n"]) for g in np_vs_n["groups"])

    cmp_out = tmp_path / "cmp"
    assert main(["compare", str(DROGUE), "--memo", str(memo_dir), "--out", str(cmp_out), "--runs", "60"]) == 0
    doc = json.loads((cmp_out / "compare.json").read_text())
    assert (cmp_out / "compare.png").is_file()
    assert [s["stage"] for s in doc["stages"]] == ["reefed 1", "full open"]
    acc = doc["stages"][1]["comparisons"]["population"]["accelerometer"]
    assert {"measured", "sigma", "percentile", "p_exceed", "percentile_without_sigma"} <= set(acc)
    assert 0 <= acc["percentile"] <= 100 and acc["p_exceed"] == pytest.approx(1 - acc["percentile"] / 100)


def test_cli_refusals(tmp_path):
    assert main(["compare", str(DROGUE), "--out", str(tmp_path / "x")]) != 0
    assert main(["montecarlo", "--memo", str(tmp_path / "nowhere"), "--like", str(DROGUE), "--out",
                 str(tmp_path / "y")]) == 2
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


@pytest.mark.slow
def test_posterior_predictive_of_a_quick_fit(drogue, tmp_path):
    from cpas_bayes.loads.compare import compare_loads
    from cpas_bayes.inference.fit import SamplerOptions, fit_test
    from cpas_bayes.inference.fit_folder import load_fit

    fit_test(drogue, SamplerOptions(seed=1, n_ensembles=2, max_steps=1500, progress=False, workers=1),
             out=tmp_path / "fit")
    fit = load_fit(tmp_path / "fit")
    comparison = compare_loads(drogue, fit=fit, runs=200, rng=np.random.default_rng(SEED), history_runs=50)
    posterior = comparison.predictions["posterior"]
    # The test's own posterior predicts its own peaks: the measurement sits inside the predicted spread.
    for c in comparison.comparisons:
        assert 0.5 < c.percentile < 99.5, (c.stage_label, c.channel, c.percentile)
    assert posterior.inputs.vehicle_weight.std() > 0            # nuisance draws are used
    assert posterior.source["posterior_draws_available"] >= 200

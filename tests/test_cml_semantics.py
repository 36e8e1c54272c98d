"""NASA CML peer semantics of the stage law: ``decay="cml_linear"`` and ``below_previous="hold"``.

Two differences from this package's law, each checked on explicit numbers
against the numpy reference (:mod:`cpas_bayes.physics.inflation`):

(a) CML's linear mode grows to CDS_i at t_f, JUMPS to C_k·CDS_i there and
    ramps linearly to CDS_i over t_k (ours grows on to the peak at t_fp);
(b) a stage whose drag area is below the held one HOLDS the held area in CML
    (ours drops to the stage's own value).

Then every other implementation of the stage law is held to the numpy
reference under every combination of the options, as tests/test_model.py
does for the decay shapes: the compiled drag-area kernel, the Monte Carlo
engine's kernel (through a flight), and the fused likelihood (through the
model's prediction).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from click.testing import CliRunner

from cpas_bayes.app.campaign_config import load_config
from cpas_bayes.app.cli import cli
from cpas_bayes.core.errors import InputError
from cpas_bayes.data.bundle import EXAMPLES_DIR, read_bundle
from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.inference.fit import prepare_model
from cpas_bayes.inference.start import first_guess
from cpas_bayes.physics.engine import simulate_peaks
from cpas_bayes.physics.inflation import (BELOW_PREVIOUS_RULES, DECAY_SHAPES, cluster_drag_area,
                                          parachute_drag_area, stage_drag_area)
from cpas_bayes.physics.trajectory import (ClusterParameters, SimulationOptions, VehicleProperties, VehicleState0,
                                           simulate)

OPTIONS = list(itertools.product(DECAY_SHAPES, BELOW_PREVIOUS_RULES))

# One stage from rest: CDS_i = 100 m², t_f = 1 s, expopen 2, C_k = 1.5, t_k = 0.5 s.
STAGE = dict(cds_start=0.0, cds_i=100.0, t_f=1.0, expopen=2.0, ck=1.5, t_k=0.5)
T_FP_OURS = 1.5 ** 0.5      # t_f·S^(1/expopen), S = C_k from rest


def _stage(tau, decay, **changes):
    s = {**STAGE, **changes}
    return stage_drag_area(np.asarray(tau, float), s["cds_start"], s["cds_i"], s["t_f"], s["expopen"], s["ck"],
                           s["t_k"], decay=decay)


# ---------------------------------------------------------------------------
# (a) CML's linear mode: growth stops at t_f, jump to the peak, ramp over t_k


def test_cml_linear_jumps_to_the_peak_at_t_f_and_ramps_down_over_t_k():
    tau = [0.5, 0.999, 1.001, 1.25, 1.5, 3.0]
    cml = _stage(tau, "cml_linear")
    # 100·0.5² = 25; just below t_f 100·0.999² = 99.80 (CDS_i·(1 − 0.2 %)); just above, the peak
    # 150 less 1/500 of the ramp = 149.9; halfway 125; CDS_i at t_f + t_k = 1.5 s and after.
    np.testing.assert_allclose(cml, [25.0, 99.8001, 149.9, 125.0, 100.0, 100.0], rtol=1e-12)
    assert _stage(1.0, "cml_linear") == pytest.approx(150.0, rel=1e-12)   # the peak instant is t_f itself


def test_ours_grows_on_to_the_peak_at_t_fp():
    tau = [0.5, 0.999, 1.001, T_FP_OURS, T_FP_OURS + 0.25, T_FP_OURS + 0.5]
    ours = _stage(tau, "linear")
    # The same growth up to t_f, then on through t_f (100.2 at 1.001 s) to the peak 150 at
    # t_fp = 1.2247 s, and the ramp to CDS_i ends at t_fp + t_k = 1.7247 s, not at 1.5 s.
    np.testing.assert_allclose(ours, [25.0, 99.8001, 100.2001, 150.0, 125.0, 100.0], rtol=1e-12)
    assert _stage(1.5, "linear") == pytest.approx(150.0 - 50.0 * (1.5 - T_FP_OURS) / 0.5, rel=1e-12)
    assert _stage(1.5, "linear") > 110.0 > _stage(1.5, "cml_linear")


def test_cml_linear_time_to_peak_is_t_f_and_n_p_equals_n():
    """One stage from rest, D_o = 10 m, V_i = 50 m/s, CDS_i = CDS_o, sampled n_p = 8.

    n_p is the fill distance to the peak under both laws: both peak at
    n_p·D_o/V_i = 1.6 s. Ours reaches CDS_i earlier, at 1.6/√1.5 = 1.306 s
    (n = n_p·S^(−1/2) = 6.53); CML's growth ends at the peak, so n = n_p = 8
    and t_f = t_fp = 1.6 s.
    """
    args = (np.array([0.0]), np.array([100.0]), 100.0, 10.0, np.array([8.0]), np.array([2.0]),
            np.array([1.5]), np.array([0.5]), np.array([50.0]))
    t = np.array([1.4, 1.59, 1.6, 2.1])
    cml, cml_timing = parachute_drag_area(t, *args, decay="cml_linear")
    ours, our_timing = parachute_drag_area(t, *args, decay="linear")
    assert cml_timing.t_f[0] == pytest.approx(1.6) and cml_timing.t_fp[0] == pytest.approx(1.6)
    assert cml_timing.n[0] == cml_timing.n_p[0] == 8.0
    assert our_timing.t_fp[0] == pytest.approx(1.6) and our_timing.t_f[0] == pytest.approx(1.6 / 1.5 ** 0.5)
    assert our_timing.n[0] == pytest.approx(8.0 / 1.5 ** 0.5)
    # CML: 100·(1.4/1.6)² = 76.6 and 100·(1.59/1.6)² = 98.75 before the jump, 150 at it, CDS_i at 1.6 + 0.5 s.
    np.testing.assert_allclose(cml, [100 * (1.4 / 1.6) ** 2, 100 * (1.59 / 1.6) ** 2, 150.0, 100.0], rtol=1e-12)
    # Ours: already above CDS_i at 1.4 s (114.8), at the peak 150 at 1.6 s, also settled at 2.1 s.
    assert ours[0] > 100.0 and ours[2] == pytest.approx(150.0) and ours[3] == pytest.approx(100.0)
    # n given instead of n_p: under cml_linear the two parameterisations coincide.
    by_n, n_timing = parachute_drag_area(t, *args, decay="cml_linear", fill_constant="n")
    np.testing.assert_array_equal(by_n, cml)
    assert n_timing.n_p[0] == 8.0


def test_finite_mass_stage_is_the_same_under_every_decay():
    """C_k = 1: no peak above CDS_i, so cml_linear is the growth law to t_f and CDS_i after."""
    tau = np.linspace(0.0, 3.0, 31)
    reference = _stage(tau, "linear", ck=1.0)
    for decay in DECAY_SHAPES:
        np.testing.assert_allclose(_stage(tau, decay, ck=1.0), reference, rtol=1e-14)


# ---------------------------------------------------------------------------
# (b) a stage below the held drag area: CML holds, ours drops


def _three_stages(below_previous, second=80.0, second_start=5.0):
    """Stage 1: 100 m² at 0 s (C_k 1.5, settled by 5 s); stage 2: ``second`` m²; stage 3: 200 m² at 8 s.

    D_o = 10 m, CDS_o = 200 m², V_i = 50 m/s, stage 3 has C_k = 1 so its n = n_p = 10.
    """
    t = np.array([4.9, second_start, second_start + 0.5, 7.99, 8.0])
    return parachute_drag_area(
        t, np.array([0.0, second_start, 8.0]), np.array([100.0, second, 200.0]), 200.0, 10.0,
        np.array([8.0, 8.0, 10.0]), np.array([2.0, 2.0, 2.0]), np.array([1.5, 1.5, 1.0]),
        np.array([0.5, 0.5, 0.5]), np.array([50.0, 50.0, 50.0]), below_previous=below_previous)


def test_stage_below_the_held_area_holds_it_or_drops_to_its_own():
    held, hold_timing = _three_stages("hold")
    dropped, drop_timing = _three_stages("drop")
    # Stage 2 (80 m²) starts holding 100 m²: nothing to fill (t_f = 0) under both rules...
    assert hold_timing.t_f[1] == drop_timing.t_f[1] == 0.0
    assert hold_timing.cds_start[1] == drop_timing.cds_start[1] == pytest.approx(100.0)
    # ... CML keeps 100 m² through the stage, ours shows 80 m² from its start.
    np.testing.assert_allclose(held[:4], [100.0, 100.0, 100.0, 100.0], rtol=1e-12)
    np.testing.assert_allclose(dropped[:4], [100.0, 80.0, 80.0, 80.0], rtol=1e-12)
    # Stage 3 then fills from what stage 2 held: 100 m² (hold) or 80 m² (drop), so its fill time
    # t_f = n·D_o·√((200 − held)/200)/V_i is 10·10·√0.5/50 = 1.414 s or 10·10·√0.6/50 = 1.549 s.
    assert hold_timing.cds_start[2] == pytest.approx(100.0) and drop_timing.cds_start[2] == pytest.approx(80.0)
    assert hold_timing.t_f[2] == pytest.approx(2.0 * np.sqrt(0.5)) and drop_timing.t_f[2] == pytest.approx(
        2.0 * np.sqrt(0.6))
    assert held[4] == pytest.approx(100.0) and dropped[4] == pytest.approx(80.0)   # each fill starts from it


def test_stage_cut_during_the_overshoot_holds_the_overshoot():
    """Stage 2 (110 m²) at 1.4 s, inside stage 1's ramp down: stage 1 peaks at t_fp = n_p·D_o·√(100/200)/V_i
    = 8·10·√0.5/50 = 1.131 s, so at 1.4 s it holds 150 − 50·(1.4 − 1.131)/0.5 = 123.1 m², above 110 m²."""
    held, timing = _three_stages("hold", second=110.0, second_start=1.4)
    dropped, _ = _three_stages("drop", second=110.0, second_start=1.4)
    expected = 150.0 - 50.0 * (1.4 - 8 * 10 * np.sqrt(0.5) / 50) / 0.5
    assert expected == pytest.approx(123.14, abs=0.01)
    assert timing.cds_start[1] == pytest.approx(expected, rel=1e-12) and timing.t_f[1] == 0.0
    assert held[1] == pytest.approx(expected, rel=1e-12) and dropped[1] == pytest.approx(110.0)


def test_a_stage_above_the_held_area_is_the_same_under_both_rules():
    held, hold_timing = _three_stages("hold", second=150.0)
    dropped, drop_timing = _three_stages("drop", second=150.0)
    np.testing.assert_array_equal(held, dropped)
    np.testing.assert_array_equal(hold_timing.t_f, drop_timing.t_f)


@pytest.mark.parametrize("bad", [dict(decay="cml"), dict(below_previous="keep")])
def test_unknown_options_are_refused_by_every_entry(bad):
    with pytest.raises(ValueError, match="must be one of"):
        stage_drag_area(1.0, 0.0, 100.0, 1.0, 2.0, 1.5, 0.5, **bad)
    with pytest.raises(ValueError, match="must be one of"):
        cluster_drag_area(np.zeros(3), np.zeros((1, 1, 1)), 1.0, np.ones((1, 1)), np.ones(1), 1.0, 1.0, 1.0, 0.5,
                          1.0, **bad)
    with pytest.raises(ValueError, match="must be one of"):
        simulate(STATE0, VEHICLE, _cluster(), 1.0, SimulationOptions(**bad))


# ---------------------------------------------------------------------------
# each implementation against the numpy reference, under every option


def _random_cluster_stages(rng, B=7, P=3, K=3):
    """Stage arrays (B, P, K) where later stages are often *below* the held area and disreefs may cut
    overshoots short (unsorted eps; gaps from 0.3 s, inside some fills, to 6 s, after most), so both
    new rules are exercised."""
    start = np.cumsum(rng.uniform(0.3, 6.0, (B, P, K)), axis=-1)
    cds_o = rng.uniform(20.0, 500.0, (B, P))
    eps = np.concatenate([rng.uniform(0.05, 1.0, (B, P, K - 1)), np.ones((B, P, 1))], axis=-1)
    return dict(start=start, cds_stage=eps * cds_o[..., None], cds_o=cds_o, diameter=np.array([7.0, 20.0, 35.0]),
                n_fill=rng.uniform(3, 20, (B, P, K)), expopen=rng.uniform(0.5, 3.0, (B, P, K)),
                ck=rng.uniform(1.05, 1.6, (B, P, K)), t_k=rng.uniform(0.0, 1.0, (B, P, K)),
                v_start=rng.uniform(60, 150, (B, P, K)))


@pytest.mark.parametrize("decay, below_previous", OPTIONS)
@pytest.mark.parametrize("fill_constant", ["n_p", "n"])
def test_compiled_drag_area_kernel_equals_numpy_reference(decay, below_previous, fill_constant):
    args = _random_cluster_stages(np.random.default_rng(31))
    t = np.linspace(0.0, 20.0, 4001)
    law = dict(decay=decay, below_previous=below_previous, fill_constant=fill_constant)
    fast, fast_timing = cluster_drag_area(t, **law, **args)
    reference, ref_timing = parachute_drag_area(t, *(args[k] for k in ("start", "cds_stage")), args["cds_o"],
                                                args["diameter"][None, :],
                                                *(args[k] for k in ("n_fill", "expopen", "ck", "t_k", "v_start")),
                                                **law)
    np.testing.assert_allclose(fast, reference, rtol=1e-12, atol=1e-9)
    for field in ("t_f", "t_fp", "n", "n_p", "cds_start"):
        np.testing.assert_allclose(getattr(fast_timing, field), getattr(ref_timing, field), rtol=1e-12, atol=1e-12)
    # The draw does exercise the rules: stages with nothing to fill, and cml_linear's peak at t_f.
    nothing_to_fill = ref_timing.cds_start >= args["cds_stage"]
    assert nothing_to_fill.sum() >= 5
    if decay == "cml_linear":
        np.testing.assert_array_equal(ref_timing.t_fp, ref_timing.t_f)


@pytest.mark.parametrize("decay", ["linear", "exponential"])
def test_compiled_drag_area_kernel_gives_the_same_values_for_times_in_any_order(decay):
    # Ascending times take the kernel's path that visits each stage's own bins only; others the full scan.
    args = _random_cluster_stages(np.random.default_rng(32))
    t = np.linspace(0.0, 20.0, 2001)
    order = np.random.default_rng(33).permutation(t.size)
    ascending, _ = cluster_drag_area(t, decay=decay, **args)
    shuffled, _ = cluster_drag_area(t[order], decay=decay, **args)
    np.testing.assert_array_equal(shuffled, ascending[..., order])
    per_row = np.repeat(t[None, :], args["start"].shape[0], axis=0)
    per_row[1] = per_row[1, order]          # one time base per row, one of them unsorted
    rows, _ = cluster_drag_area(per_row, decay=decay, **args)
    np.testing.assert_array_equal(rows[1], ascending[1][..., order])
    np.testing.assert_array_equal(rows[0], ascending[0])


# A Drogue-like pair, stage 2 of canopy 0 below what stage 1 holds (SI).
STATE0 = VehicleState0(125.0, np.radians(-47.0), 7000.0)
VEHICLE = VehicleProperties(89_000.0, 1.6)


def _cluster(batch=1):
    rng = np.random.default_rng(5)
    start = np.array([[1.0, 4.0, 7.5], [1.1, 4.2, 7.0]]) + rng.uniform(-0.1, 0.1, (batch, 2, 3))
    cds_o = 23.0
    eps = np.array([[0.5, 0.4, 1.0], [0.4, 0.6, 1.0]])      # canopy 0: stage 2 below stage 1
    return ClusterParameters(start=start, cds_stage=eps * cds_o, n_fill=rng.uniform(8, 12, (batch, 2, 3)),
                             expopen=np.array([2.2, 2.0, 2.1]), ck=np.array([1.4, 1.3, 1.2]),
                             tk=np.array([0.5, 0.4, 0.6]), cds_o=cds_o, diameter=7.0, weight=356.0)


@pytest.mark.parametrize("decay, below_previous", OPTIONS)
def test_engine_kernel_flies_the_numpy_reference_law(decay, below_previous):
    """The compiled Monte Carlo engine against the trajectory engine (which evaluates the numpy
    reference inside the same RK4 scheme): load histories and every stage's timing."""
    cluster = _cluster(batch=3)
    options = SimulationOptions(decay=decay, below_previous=below_previous)
    stages = np.array([3, 3])
    compiled = simulate_peaks(STATE0, VEHICLE, cluster, stages, 10.0, options, engine="compiled", history_runs=3)
    reference = simulate_peaks(STATE0, VEHICLE, cluster, stages, 10.0, options, engine="trajectory", history_runs=3)
    np.testing.assert_allclose(compiled.history, reference.history, rtol=0,
                               atol=1e-7 * np.abs(reference.history).max())
    for name in ("t_f", "t_fp", "n", "n_p", "v_i"):
        np.testing.assert_allclose(getattr(compiled, name), getattr(reference, name), rtol=1e-9, err_msg=name)
    # The engine's timing is the numpy reference's at the engine's own V_i.
    _, timing = parachute_drag_area(np.zeros(1), cluster.start, cluster.cds_stage, cluster.cds_o, cluster.diameter,
                                    cluster.n_fill, cluster.expopen, cluster.ck, cluster.tk, compiled.v_i,
                                    decay=decay, below_previous=below_previous)
    for name in ("t_f", "t_fp", "n", "n_p"):
        np.testing.assert_allclose(getattr(compiled, name), getattr(timing, name), rtol=1e-12, err_msg=name)
    assert (timing.t_f[:, 0, 1] == 0).all()      # the stage below the held area is in every run


def test_engine_sees_each_option():
    """Hold keeps canopy 0's stage-2 drag area (11.5 m², not 9.2 m²) from its start at 3.99 s, so the
    load is higher just after it and the same before; cml_linear peaks at t_f."""
    cluster = _cluster()
    stages = np.array([3, 3])
    runs = {law: simulate_peaks(STATE0, VEHICLE, cluster, stages, 10.0,
                                SimulationOptions(decay=law[0], below_previous=law[1]), engine="compiled",
                                history_runs=1)
            for law in (("linear", "drop"), ("linear", "hold"), ("cml_linear", "drop"))}
    time = runs["linear", "drop"].history_time
    second = cluster.start[0, 0, 1]
    before, after = time < second, (time > second) & (time < second + 0.3)
    drop, hold = runs["linear", "drop"].history[0], runs["linear", "hold"].history[0]
    np.testing.assert_array_equal(hold[before], drop[before])
    assert after.sum() >= 20 and (hold[after] > drop[after]).all()
    cml = runs["cml_linear", "drop"]
    np.testing.assert_array_equal(cml.t_fp, cml.t_f)
    assert (runs["linear", "drop"].t_fp[:, :, 0] > runs["linear", "drop"].t_f[:, :, 0]).all()


@pytest.fixture(scope="module")
def drogue():
    test = read_bundle(EXAMPLES_DIR / "drogue-clean")
    return test, reduce_test(test)


def _rows(model, n=12):
    """Rows near the first guess; in row 0 every canopy's stage 1 opens to full open over-inflated
    (eps 1, C_k 1.4) and still ramping down at the disreef (t_k 30 s), so stage 2 starts below the
    held area; in row 1 no decay time."""
    x = first_guess(model)
    rows = x + 1e-3 * np.random.default_rng(17).standard_normal((n, model.ndim)) * np.abs(x + 1e-3)
    for name in model.names:
        if name.endswith(".s1.eps"):
            rows[0, model.index[name]] = 1.0
        if name.endswith(".s1.ck"):
            rows[0, model.index[name]] = 1.4
        if name.endswith(".tk"):
            rows[1, model.index[name]] = 0.0
        if name.endswith(".s1.tk"):
            rows[0, model.index[name]] = 30.0
    return rows


@pytest.mark.parametrize("decay, below_previous", OPTIONS)
def test_likelihood_kernel_equals_the_model_prediction_of_the_numpy_reference(drogue, decay, below_previous):
    test, reduction = drogue
    model = prepare_model(test, reduction, decay=decay, below_previous=below_previous)
    assert (model.decay, model.below_previous) == (decay, below_previous)
    rows = _rows(model)
    # The model's prediction is the numpy reference law at the bin times, V_i the measured airspeed.
    stage = model.gather_stages(rows)
    reference, ref_timing = parachute_drag_area(
        model.obs.time, stage["start"], stage["cds_stage"], stage["cds_o"], model.diameter, stage["n_p"],
        stage["expopen"], stage["ck"], stage["tk"], model.obs.airspeed_at(stage["start"]),
        decay=decay, below_previous=below_previous)
    pred = model.predict(rows)
    np.testing.assert_allclose(pred.cds, reference, rtol=1e-12, atol=1e-9)
    assert (ref_timing.t_f[0, :, 1] == 0).all()           # row 0 has the stage below the held area
    # The fused likelihood kernel equals the likelihood of that prediction.
    fused = model.log_likelihood(rows)
    numpy_pipeline = model.pointwise_log_likelihood(rows, pred).sum(axis=1)
    np.testing.assert_allclose(fused, numpy_pipeline, rtol=1e-10)


def test_likelihood_kernel_sees_each_option(drogue):
    test, reduction = drogue
    models = {law: prepare_model(test, reduction, decay=law[0], below_previous=law[1])
              for law in (("linear", "drop"), ("linear", "hold"), ("cml_linear", "drop"))}
    rows = _rows(models["linear", "drop"])
    ll = {law: m.log_likelihood(rows) for law, m in models.items()}
    # Hold changes only the row with a stage below the held area; cml_linear changes every row.
    assert ll["linear", "hold"][0] != ll["linear", "drop"][0]
    np.testing.assert_array_equal(ll["linear", "hold"][1:], ll["linear", "drop"][1:])
    assert (ll["cml_linear", "drop"] != ll["linear", "drop"]).all()


def test_defaults_are_linear_and_drop(drogue):
    test, reduction = drogue
    default, explicit = prepare_model(test, reduction), prepare_model(test, reduction, decay="linear",
                                                                      below_previous="drop")
    rows = _rows(default)
    np.testing.assert_array_equal(default.log_likelihood(rows), explicit.log_likelihood(rows))
    assert SimulationOptions().below_previous == "drop" and SimulationOptions().decay == "linear"


# ---------------------------------------------------------------------------
# the options where a user sets them


def test_campaign_config_takes_the_cml_options_and_refuses_others(tmp_path):
    path = tmp_path / "campaign.toml"
    path.write_text('decay = "cml_linear"\nbelow_previous = "hold"\n')
    config = load_config(path)
    assert (config.decay, config.below_previous) == ("cml_linear", "hold")
    path.write_text('below_previous = "holds"\n')
    with pytest.raises(InputError, match="did you mean 'hold'"):
        load_config(path)
    path.write_text('decay = "cml-linear"\n')
    with pytest.raises(InputError, match="cml_linear"):
        load_config(path)


def test_fit_command_offers_the_cml_options():
    result = CliRunner().invoke(cli, ["fit", "--help"])
    assert result.exit_code == 0
    assert "cml_linear" in result.output and "--below-previous" in result.output and "hold" in result.output



@pytest.mark.parametrize("decay, below_previous", OPTIONS)
def test_the_compiled_drag_area_rate_is_the_laws_central_difference_and_continuous(decay, below_previous):
    # The added mass reads dCDS/dt from the kernel's one pass: the law's difference over ±RATE_STEP (what two
    # more evaluations gave), close to its derivative where the law is smooth, and continuous in the
    # parameters as a kink (t_fp) crosses a bin — a one-sided derivative jumped there, and the likelihood
    # with it.
    from cpas_bayes.physics.inflation import RATE_STEP

    args = _random_cluster_stages(np.random.default_rng(34))
    t = np.linspace(0.0, 20.0, 4001)
    law = dict(decay=decay, below_previous=below_previous)
    cds, rate, timing = cluster_drag_area(t, with_rate=True, **law, **args)
    plain, plain_timing = cluster_drag_area(t, **law, **args)
    np.testing.assert_array_equal(cds, plain)
    np.testing.assert_array_equal(timing.t_fp, plain_timing.t_fp)
    ahead, _ = cluster_drag_area(t + RATE_STEP, **law, **args)
    behind, _ = cluster_drag_area(t - RATE_STEP, **law, **args)
    np.testing.assert_allclose(rate, (ahead - behind) / (2 * RATE_STEP), rtol=1e-9, atol=1e-9)
    assert np.all(rate[..., t < args["start"][..., :1].min() - RATE_STEP] == 0.0)
    # bins settled over ±RATE_STEP (skipped by the kernel) are exactly 0, as the difference is; many are
    settled = ahead == behind
    assert settled.mean() > 0.2 and np.all(rate[settled] == 0.0)
    assert (rate > 1e-3).sum() > 100 and (rate < -1e-3).sum() > 100     # growth and decay exercised

    if decay == "cml_linear":
        return      # its drag area itself jumps at t_f = t_fp: a difference cannot be continuous there
    # one bin, a reefed stage's drag area stepped so that its t_fp sweeps across the bin
    one = dict(start=np.array([[[0.0, 2.0, 5.0]]]), cds_stage=np.array([[[10.0, 40.0, 100.0]]]),
               cds_o=np.array([[100.0]]), diameter=np.array([20.0]), n_fill=np.full((1, 1, 3), 10.0),
               expopen=np.full((1, 1, 3), 2.0), ck=np.full((1, 1, 3), 1.3), t_k=np.full((1, 1, 3), 0.5),
               v_start=np.full((1, 1, 3), 100.0))
    _, timing_one = cluster_drag_area(t, **law, **one)
    bin_time = float(one["start"][0, 0, 1] + timing_one.t_fp[0, 0, 1])
    rates = []
    for c in 1.0 + np.linspace(-0.02, 0.02, 801):
        stepped = dict(one, cds_stage=one["cds_stage"] * np.array([1.0, c, 1.0]))
        rates.append(cluster_drag_area(np.array([bin_time]), with_rate=True, **law, **stepped)[1][0, 0, 0])
    rates = np.array(rates)
    assert rates.max() > 0 > rates.min()          # from growth to decay across the sweep
    assert np.max(np.abs(np.diff(rates))) < 0.02 * np.ptp(rates)


def test_the_rate_over_each_bins_own_half_width_is_the_bins_mean_rate():
    """A model of bin means reads dCDS/dt over each bin's own span: per time, the law's difference across
    ±half-width, which is the mean of the rate over the bin (the law's values at the bin edges). Bad widths
    are refused."""
    args = _random_cluster_stages(np.random.default_rng(35))
    t = np.linspace(0.0, 20.0, 801)
    half = np.where(np.arange(t.size) % 3 == 0, 0.05, 0.01)
    cds, rate, _ = cluster_drag_area(t, with_rate=True, rate_half_width=half, **args)
    ahead, _ = cluster_drag_area(t + half, **args)
    behind, _ = cluster_drag_area(t - half, **args)
    np.testing.assert_allclose(rate, (ahead - behind) / (2 * half), rtol=1e-9, atol=1e-9)
    fine = np.linspace(-1.0, 1.0, 2001)
    i = int(np.argmax(np.abs(rate[0, 0])))                 # the bin where the law moves fastest
    dense, _ = cluster_drag_area(t[i] + half[i] * fine, **args)
    mean_rate = np.trapezoid(np.gradient(dense[0, 0], t[i] + half[i] * fine), dx=half[i] * 1e-3) / (2 * half[i])
    assert rate[0, 0, i] == pytest.approx(mean_rate, rel=0.02)
    for bad in (np.full(5, 0.01), -half):
        with pytest.raises(ValueError, match="rate_half_width"):
            cluster_drag_area(t, with_rate=True, rate_half_width=bad, **args)


def test_a_model_reads_the_added_mass_rate_over_its_bins_spans():
    from pathlib import Path

    from cpas_bayes.data.bundle import read_bundle
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit import prepare_model

    test = read_bundle(Path(__file__).resolve().parents[1] / "cpas_bayes" / "data" / "examples" / "drogue-clean")
    model = prepare_model(test, reduce_test(test))
    step = float(np.median(np.diff(test.time)))
    np.testing.assert_allclose(model.rate_half_width, 0.5 * model.obs.samples_per_bin * step)
    assert model.rate_half_width.min() < model.rate_half_width.max()     # transient bins and steady ones

"""Tests of cpas_bayes.data.reduction (with data.friction and data.peaks): each equation by
hand, Monte Carlo checks of the propagated sigmas, recovery of the example bundles' truth,
and the ``reduce`` command.

truth.json is read here only, never by the package.
"""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pandas as pd
import pytest
from scipy.signal import lfilter, savgol_coeffs, savgol_filter

from cpas_bayes.data import reduction as red
from cpas_bayes.data.bundle import FlightTest, Parachute, Stage, Vehicle, example_bundles, read_bundle
from cpas_bayes.app.cli import main
from cpas_bayes.core.errors import InputError
from cpas_bayes.data.friction import ScaleFactor, window_ratio
from cpas_bayes.data.peaks import peak_filter, peak_filter_width
from cpas_bayes.physics.inflation import parachute_drag_area
from cpas_bayes.core.units import unit_system

EXAMPLES = {p.name: p for p in example_bundles()}
N_DRAWS = 40_000


# ---------------------------------------------------------------------------
# fixtures and helpers


def _truth_drag_areas(test, truth):
    """True drag area of each parachute (SI) with its true stage starts and settled times."""
    u = test.units
    time = test.time
    airspeed = test.data["airspeed"].to_numpy()
    out = {}
    for p, chute in zip(test.parachutes, truth["chutes"]):
        assert p.id == chute["id"]
        st = chute["stages"]
        starts = np.array([s["start"] for s in st])
        tk = np.array([s["tk"] for s in st])
        cds_o = u.si(chute["cds_o"], "area")
        cds, timing = parachute_drag_area(
            time, starts, np.array([s["eps"] for s in st]) * cds_o, cds_o, p.diameter,
            np.array([s["n_p"] for s in st]), np.array([s["expopen"] for s in st]),
            np.array([s["ck"] for s in st]), tk, np.interp(starts, time, airspeed),
            decay="linear", fill_constant="n_p")
        out[p.id] = {"cds": cds, "starts": starts, "settled": starts + timing.t_fp + tk,
                     "peak": starts + timing.t_fp}
    return out


def _steady_mask(test, truth_cds, margin=0.2):
    """Samples after every canopy's true inflation transient and before the next true stage start."""
    time = test.time
    mask = np.zeros(time.size, bool)
    n_stages = len(next(iter(truth_cds.values()))["starts"])
    for k in range(n_stages):
        lo = max(v["settled"][k] for v in truth_cds.values()) + margin
        hi = min((v["starts"][k + 1] for v in truth_cds.values()), default=np.inf) if k + 1 < n_stages else np.inf
        mask |= (time >= lo) & (time < hi)
    return mask


@pytest.fixture(scope="module")
def examples():
    """name -> (test, truth, truth drag areas, constant-mode reduction, linear-mode reduction)."""
    out = {}
    for name, path in EXAMPLES.items():
        test = read_bundle(path)
        truth = json.loads((path / "truth.json").read_text())
        out[name] = (test, truth, _truth_drag_areas(test, truth),
                     red.reduce_test(test, scale="constant"), red.reduce_test(test, scale="linear"))
    return out


def _synthetic_test(loads, time, W_V=10_000.0, cds_V=2.0, qbar=500.0, weights=(50.0, 50.0),
                    G_sigma=0.0, qbar_sigma=0.0, F_sigma=0.0, stage_start=0.5):
    """A noise-free FlightTest (SI) whose accelerometer agrees exactly with the load cells."""
    W_p = sum(weights)
    total = sum(loads.values())
    # Eq. 6 solved for G so that the accelerometer total equals the sum of the riser loads.
    G = (total + qbar * cds_V) / W_V
    n = time.size
    data = {"time": time, "G": G, "G_sigma": np.full(n, G_sigma), "qbar": np.full(n, qbar),
            "qbar_sigma": np.full(n, qbar_sigma), "airspeed": np.full(n, 100.0), "gamma": np.full(n, -60.0)}
    chutes = []
    for (pid, F), w in zip(loads.items(), weights):
        data[f"F_{pid}"] = F
        data[f"F_{pid}_sigma"] = np.full(n, F_sigma)
        chutes.append(Parachute(id=pid, kind="drogue", inflation="infinite", diameter=7.0, weight=w,
                                weight_sigma=0.0, stages=(Stage("full open", stage_start, 0.0),),
                                load_cell=f"F_{pid}"))
    assert W_p > 0
    return FlightTest(name="synthetic", phase="test", units=unit_system("SI"),
                      vehicle=Vehicle(W_V, 0.0, cds_V, 0.0), parachutes=tuple(chutes), data=pd.DataFrame(data))


# ---------------------------------------------------------------------------
# equations by hand


def test_accelerometer_load_eq6_eq7_by_hand():
    # W_V = 1000, G = 2, q̄ = 50, (CDS)_V = 4:  F = 1000·2 − 50·4 = 1800.
    assert red.accelerometer_load(2.0, 50.0, 1000.0, 4.0) == pytest.approx(1800.0)
    # ΔW_V = 10, ΔG = 0.1, Δq̄ = 1, Δ(CDS)_V = 0.5; terms 10·2 = 20, 0.1·1000 = 100, 1·4 = 4, 0.5·50 = 25.
    s = red.accelerometer_load_sigma(2.0, 50.0, 1000.0, 4.0, 0.1, 1.0, 10.0, 0.5)
    assert float(s.random) == pytest.approx(math.sqrt(100**2 + 4**2))        # 100.0800
    assert float(s.systematic) == pytest.approx(math.sqrt(20**2 + 25**2))    # 32.0156
    assert float(s.total) == pytest.approx(math.sqrt(11041.0))               # 105.0762


def test_accelerometer_drag_area_eq8_eq9_by_hand():
    # W_T = 1100, G = 2, q̄ = 50, (CDS)_V = 4:  1100·2/50 − 4 = 40.
    assert red.accelerometer_drag_area(2.0, 50.0, 1100.0, 4.0) == pytest.approx(40.0)
    # ΔW_T = 11: 11·2/50 = 0.44; ΔG = 0.1: 0.1·1100/50 = 2.2; Δq̄ = 1: 1·1100·2/50² = 0.88; Δ(CDS)_V = 0.5.
    s = red.accelerometer_drag_area_sigma(2.0, 50.0, 1100.0, 0.1, 1.0, 11.0, 0.5)
    assert float(s.random) == pytest.approx(math.hypot(2.2, 0.88))
    assert float(s.systematic) == pytest.approx(math.hypot(0.44, 0.5))
    assert float(s.total) == pytest.approx(math.sqrt(0.1936 + 4.84 + 0.7744 + 0.25))   # 2.46130


def test_load_cell_drag_area_eq11_and_corrected_eq12_by_hand():
    # F = 900, W_p = 50, G = 2, q̄ = 50:  (900 + 50·2)/50 = 20.
    assert red.load_cell_drag_area(900.0, 2.0, 50.0, 50.0) == pytest.approx(20.0)
    # ΔF = 20: 0.4; ΔW_p = 5: 5·2/50 = 0.2; ΔG = 0.1: 0.1·50/50 = 0.1 (the printed Eq. 12 would
    # give 0.1·0.1·50/50 = 0.01); Δq̄ = 1: 1·1000/50² = 0.4.  RSS = √0.37 = 0.60828.
    s = red.load_cell_drag_area_sigma(900.0, 2.0, 50.0, 50.0, 20.0, 0.1, 1.0, 5.0)
    assert float(s.total) == pytest.approx(math.sqrt(0.37))
    assert float(s.random) == pytest.approx(math.sqrt(0.16 + 0.01 + 0.16))
    assert float(s.systematic) == pytest.approx(0.2)
    # A systematic load part (the scale factor's) adds ΔF_sys/q̄: 10/50 = 0.2.
    s2 = red.load_cell_drag_area_sigma(900.0, 2.0, 50.0, 50.0, 20.0, 0.1, 1.0, 5.0, F_sigma_systematic=10.0)
    assert float(s2.systematic) == pytest.approx(math.hypot(0.2, 0.2))


def test_axial_load_eq13_by_hand():
    # F = 1000 at θ = 60°: 500.  ΔF = 10: 10·cos 60° = 5; Δθ = 2°: 1000·sin 60°·2π/180 = 30.2300.
    assert red.axial_load(1000.0, 60.0) == pytest.approx(500.0)
    expected = math.hypot(5.0, 1000.0 * math.sin(math.radians(60.0)) * math.radians(2.0))
    assert red.axial_load_sigma(1000.0, 60.0, 10.0, 2.0) == pytest.approx(expected)   # 30.6407
    assert red.axial_load_sigma(1000.0, 0.0, 10.0, 2.0) == pytest.approx(10.0)        # no sin θ term at 0°


def test_window_ratio_by_hand():
    # A = 2·L exactly: R = 2 with no scatter.
    ratio, se = window_ratio([2.0, 4.0, 6.0], [1.0, 2.0, 3.0])
    assert ratio == pytest.approx(2.0) and se == pytest.approx(0.0)
    # A = [3, 4, 5], L = 2: R = 4/2 = 2; e = A − 2L = [−1, 0, 1], var = 1, lag-1 ρ = 0,
    # SE = √(1/3)/2 = 0.288675.
    ratio, se = window_ratio([3.0, 4.0, 5.0], [2.0, 2.0, 2.0])
    assert ratio == pytest.approx(2.0)
    assert se == pytest.approx(math.sqrt(1 / 3) / 2)


def _two_window_factor(mode):
    return ScaleFactor(mode=mode, windows=((0.0, 2.0), (4.0, 6.0)), values=np.array([1.1, 1.2]),
                           sigma_random=np.array([0.01, 0.02]),
                           systematic_terms=np.array([[0.003, 0.004], [0.006, 0.008]]),
                           systematic_names=("a", "b"), source="user")


def test_constant_scale_factor_by_hand():
    sf = _two_window_factor("constant")
    # Weights 1/σ²: 10000 and 2500 -> 0.8, 0.2: 0.8·1.1 + 0.2·1.2 = 1.12 at any time.
    assert sf.at([-5.0, 3.0, 50.0]) == pytest.approx([1.12, 1.12, 1.12])
    # Birge ratio: χ² = (0.02/0.01)² + (0.08/0.02)² = 4 + 16 = 20 over 1 dof -> √20;
    # random σ = (1/12500)^½·√20 = 0.04.
    assert sf.birge_ratio == pytest.approx(math.sqrt(20.0))
    random, systematic = sf.sigma_parts([1.0])
    assert random[0] == pytest.approx(0.04)
    # Systematic parts add linearly (same W, CDS_V in both windows): 0.8·[0.003, 0.004] + 0.2·[0.006, 0.008]
    # = [0.0036, 0.0048] -> 0.006, not the RSS 0.00447.
    assert systematic[0] == pytest.approx(0.006)
    assert sf.factor == pytest.approx(1.12)
    assert sf.sigma_systematic == pytest.approx([0.005, 0.01])


def test_linear_scale_factor_by_hand():
    sf = _two_window_factor("linear")
    # Midpoints 1 and 5: straight line between, held constant outside.
    assert sf.at([0.0, 1.0, 3.0, 5.0, 9.0]) == pytest.approx([1.1, 1.1, 1.15, 1.2, 1.2])
    random, systematic = sf.sigma_parts([3.0])
    assert random[0] == pytest.approx(math.sqrt(0.25 * 0.01**2 + 0.25 * 0.02**2))   # 0.01118
    assert systematic[0] == pytest.approx(math.hypot(0.0045, 0.006))                 # 0.0075
    assert sf.factor is None


def test_load_share_and_peaks_by_hand():
    time = np.round(np.arange(0.0, 4.0 + 1e-9, 0.01), 10)
    tri = lambda t0, half: np.clip(1.0 - np.abs(time - t0) / half, 0.0, None)  # noqa: E731
    # A: 1000 + a 1000 N triangle at 1 s; B: 1000 + a 500 N triangle at 2 s.
    loads = {"A": 1000.0 + 1000.0 * tri(1.0, 0.25), "B": 1000.0 + 500.0 * tri(2.0, 0.25)}
    r = red.reduce_test(_synthetic_test(loads, time), peak_smoothing=0.0)
    assert r.scale.factor == pytest.approx(1.0)       # the accelerometer was built to agree
    (peaks,) = r.peaks
    # Sum peaks at 1 s: 2000 + 1000 = 3000 N, on both channels.
    assert peaks.accelerometer.load == pytest.approx(3000.0) and peaks.accelerometer.time == pytest.approx(1.0)
    assert peaks.load_cells.load == pytest.approx(3000.0) and peaks.load_cells.time == pytest.approx(1.0)
    assert peaks.parachutes["B"].time == pytest.approx(2.0) and peaks.parachutes["B"].load == pytest.approx(1500.0)
    (share,) = r.load_share
    assert share.at_global_peak["A"] == pytest.approx(2 / 3)
    assert share.at_parachute_peak["A"]["A"] == pytest.approx(2 / 3)
    assert share.at_parachute_peak["B"]["A"] == pytest.approx(1000 / 2500)          # 0.4
    # Over [0.5, 4] s: ∫A = 3.5·1000 + ½·0.5·1000 = 3750, ∫B = 3500 + ½·0.5·500 = 3625.
    assert share.time_independent["A"] == pytest.approx(3750 / 7375)
    assert share.mean["A"] == pytest.approx((2 / 3 + 2 / 3 + 0.4 + 3750 / 7375) / 4)
    assert sum(share.mean.values()) == pytest.approx(1.0)


def test_peak_filter_keeps_sharp_peak_and_reports_its_noise():
    rng = np.random.default_rng(7)
    width = peak_filter_width(0.1, 100.0)
    assert width == 11
    # The filtered noise sd equals the reported random sigma (interior samples).
    noise = rng.normal(0.0, 3.0, size=(N_DRAWS, 41))
    smooth = savgol_filter(noise, width, 2, axis=1)
    _, sigma = peak_filter(noise[0], np.full(41, 3.0), width)
    assert smooth[:, 20].std() == pytest.approx(sigma[20], rel=0.05)
    assert sigma[20] == pytest.approx(3.0 * math.sqrt((savgol_coeffs(width, 2) ** 2).sum()))
    # A noise-free parabola is kept exactly by the quadratic filter.
    x = np.linspace(-1, 1, 41)
    assert peak_filter(10 - x**2, np.zeros(41), width)[0][20] == pytest.approx(10.0)


# ---------------------------------------------------------------------------
# Monte Carlo propagation: empirical sd of each output against its formula


def _mc_sd(func, nominal, sigmas, rng):
    # Scalars are drawn as (N, 1) columns so that they broadcast against the per-point arrays.
    draws = {k: v + sigmas.get(k, 0.0) * rng.standard_normal((N_DRAWS,) + (np.shape(v) or (1,)))
             for k, v in nominal.items()}
    return func(**draws).std(axis=0)


def test_monte_carlo_eq7_accelerometer_load():
    rng = np.random.default_rng(1)
    nom = {"G": np.array([1.2, 2.5, 4.0]), "qbar": np.array([80.0, 120.0, 60.0]),
           "W_V": np.array(20000.0), "cds_V": np.array(20.0)}
    sig = {"G": 0.03, "qbar": np.array([0.8, 1.2, 0.6]), "W_V": 100.0, "cds_V": 2.0}
    sd = _mc_sd(lambda G, qbar, W_V, cds_V: red.accelerometer_load(G, qbar, W_V, cds_V), nom, sig, rng)
    formula = red.accelerometer_load_sigma(nom["G"], nom["qbar"], 20000.0, 20.0, 0.03, sig["qbar"], 100.0, 2.0)
    np.testing.assert_allclose(sd, formula.total, rtol=0.05)


def test_monte_carlo_eq9_accelerometer_drag_area():
    rng = np.random.default_rng(2)
    nom = {"G": np.array([1.2, 2.5, 4.0]), "qbar": np.array([80.0, 120.0, 60.0]),
           "W_T": np.array(20200.0), "cds_V": np.array(20.0)}
    sig = {"G": 0.03, "qbar": np.array([0.8, 1.2, 0.6]), "W_T": 100.0, "cds_V": 2.0}
    sd = _mc_sd(lambda G, qbar, W_T, cds_V: red.accelerometer_drag_area(G, qbar, W_T, cds_V), nom, sig, rng)
    formula = red.accelerometer_drag_area_sigma(nom["G"], nom["qbar"], 20200.0, 0.03, sig["qbar"], 100.0, 2.0)
    np.testing.assert_allclose(sd, formula.total, rtol=0.05)


def test_monte_carlo_eq12_corrected_load_cell_drag_area():
    rng = np.random.default_rng(3)
    # A heavy Main canopy (W_p ~5 % of W_T) and large ΔG make the G term, the one the typo hid, matter.
    nom = {"F": np.array([9000.0, 20000.0, 3000.0]), "G": np.array([1.5, 2.0, 3.0]),
           "qbar": np.array([30.0, 60.0, 20.0]), "W_p": np.array(1000.0)}
    sig = {"F": np.array([90.0, 200.0, 30.0]), "G": 0.2, "qbar": np.array([0.3, 0.6, 0.2]), "W_p": 20.0}
    sd = _mc_sd(lambda F, G, qbar, W_p: red.load_cell_drag_area(F, G, qbar, W_p), nom, sig, rng)
    formula = red.load_cell_drag_area_sigma(nom["F"], nom["G"], nom["qbar"], 1000.0, sig["F"], 0.2,
                                            sig["qbar"], 20.0)
    np.testing.assert_allclose(sd, formula.total, rtol=0.05)
    # The printed Eq. 12 (|ΔG|² in the G term) would be off by far more than 5 % here.
    typo = np.sqrt(formula.total**2 - (0.2 * 1000.0 / nom["qbar"]) ** 2 + (0.2 * 0.2 * 1000.0 / nom["qbar"]) ** 2)
    assert np.all(np.abs(typo / sd - 1) > 0.05)


def test_monte_carlo_eq13_flyout_angle():
    rng = np.random.default_rng(4)
    nom = {"F": np.array([20000.0, 15000.0, 8000.0]), "theta": np.array([5.0, 15.0, 30.0])}
    sig = {"F": np.array([200.0, 150.0, 80.0]), "theta": 2.0}
    sd = _mc_sd(lambda F, theta: red.axial_load(F, theta), nom, sig, rng)
    np.testing.assert_allclose(sd, red.axial_load_sigma(nom["F"], nom["theta"], sig["F"], 2.0), rtol=0.05)


def test_monte_carlo_scaled_drag_area_with_angle_and_scale_factor():
    """The chain used for cds_<id>: s·F·cos θ through Eq. 11, every input perturbed."""
    rng = np.random.default_rng(5)
    nom = {"F": np.array([9000.0, 20000.0]), "theta": np.array([10.0, 20.0]), "s": np.array(1.06),
           "G": np.array([1.5, 2.5]), "qbar": np.array([30.0, 60.0]), "W_p": np.array(300.0)}
    sig = {"F": np.array([90.0, 200.0]), "theta": 3.0, "s": 0.01, "G": 0.05, "qbar": np.array([0.3, 0.6]),
           "W_p": 5.0}

    def chain(F, theta, s, G, qbar, W_p):
        return red.load_cell_drag_area(s * red.axial_load(F, theta), G, qbar, W_p)

    sd = _mc_sd(chain, nom, sig, rng)
    axial = red.axial_load(nom["F"], nom["theta"])
    formula = red.load_cell_drag_area_sigma(
        1.06 * axial, nom["G"], nom["qbar"], 300.0,
        1.06 * red.axial_load_sigma(nom["F"], nom["theta"], sig["F"], 3.0), 0.05, sig["qbar"], 5.0,
        F_sigma_systematic=np.abs(axial) * 0.01)
    np.testing.assert_allclose(sd, formula.total, rtol=0.05)


@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_monte_carlo_window_ratio_standard_error(rho):
    """The scatter-based standard error of a window ratio matches the spread over repeated windows."""
    rng = np.random.default_rng(6)
    n, reps, true_ratio = 400, 3000, 1.07
    level = 200.0 + 20.0 * np.sin(np.linspace(0, 6, n))   # a breathing canopy, common to both channels
    # AR(1) noise on the accelerometer channel, unit variance scaled to sd 8.
    noise = lfilter([math.sqrt(1 - rho**2)], [1.0, -rho], rng.normal(0.0, 8.0, (reps, n)), axis=1)
    A = true_ratio * level + noise
    L = level + rng.normal(0.0, 2.0, (reps, n))
    ratios, errors = np.array([window_ratio(a, b) for a, b in zip(A, L)]).T
    assert np.mean(ratios) == pytest.approx(true_ratio, abs=3 * np.std(ratios) / math.sqrt(reps))
    assert np.std(ratios) == pytest.approx(np.mean(errors), rel=0.05 if rho == 0 else 0.10)


# ---------------------------------------------------------------------------
# the example bundles against their truth


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_examples_scaled_drag_areas_normalised_residuals(examples, name):
    test, _, truth_cds, r, _ = examples[name]
    mask = _steady_mask(test, truth_cds)
    assert mask.sum() > 500
    for p in test.parachutes:
        z = (r.frame[f"cds_{p.id}"].to_numpy() - truth_cds[p.id]["cds"]) / r.frame[f"cds_{p.id}_sigma"].to_numpy()
        sd = float(z[mask].std())
        assert 0.8 <= sd <= 1.25, f"{name} {p.id}: sd of normalised residuals {sd:.3f}"
        assert abs(float(z[mask].mean())) < 0.5, f"{name} {p.id}: mean normalised residual {z[mask].mean():.3f}"


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_examples_constant_scale_factor_recovers_truth(examples, name):
    """Within 3 sigma: one realisation is compared, so a 1-sigma band would miss ~1 time in 3 by design,
    and the factor inherits the stated W_V/(CDS)_V offsets, which are themselves ~1-sigma draws."""
    _, truth, _, r, _ = examples[name]
    sf = r.scale
    assert sf.mode == "constant" and sf.source == "automatic"
    assert abs(sf.factor - truth["load_scale"]) < 3 * sf.factor_sigma
    assert sf.factor_sigma < 0.02           # informative: better than 2 %
    # Every window agrees with the truth too (the examples have one friction factor).
    assert np.all(np.abs(sf.values - truth["load_scale"]) < 3 * sf.sigma)


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_examples_linear_mode_goes_through_the_window_ratios(examples, name):
    _, truth, _, _, r = examples[name]
    sf = r.scale
    assert sf.at(sf.midpoints) == pytest.approx(sf.values)
    t = r.frame["time"].to_numpy()
    assert r.frame["scale"].to_numpy()[t < sf.midpoints[0]] == pytest.approx(sf.values[0])
    assert np.all(np.abs(r.frame["scale"] - truth["load_scale"]) < 3 * r.frame["scale_sigma"])


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_examples_peak_totals_agree(examples, name):
    """Accelerometer and scaled load-cell peaks agree within their combined sigma (2 sigma per stage for a
    single realisation; the normalised differences over all stages have an RMS ≤ 1.25)."""
    test, truth, _, r, _ = examples[name]
    z = []
    for pk in r.peaks:
        assert abs(pk.accelerometer.time - pk.load_cells.time) < 1.0
        z.append(pk.agreement)
        assert abs(pk.agreement) < 2.0, f"{name} {pk.stage.label}: {pk.agreement:.2f} sigma"
    assert math.sqrt(np.mean(np.square(z))) <= 1.25
    # The largest stage peak of the summed load-cell loads recovers the simulator's peak total load.
    best = max(r.peaks, key=lambda pk: pk.load_cells.load)
    truth_peak = test.units.si(truth["peak_total_load"], "force")
    assert abs(best.load_cells.load - truth_peak) < 3 * best.load_cells.sigma


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_examples_automatic_windows_follow_the_rule(examples, name):
    test, _, truth_cds, r, _ = examples[name]
    sf = r.scale
    assert len(sf.windows) == len(test.parachutes[0].stages)
    for k, (t0, t1) in enumerate(sf.windows):
        # Past every canopy's over-inflation peak, not far past its settling, before any next stage.
        assert t0 > max(v["peak"][k] for v in truth_cds.values())
        assert t0 < max(v["settled"][k] for v in truth_cds.values()) + 1.0
        if k + 1 < len(sf.windows):
            assert t1 < min(v["starts"][k + 1] for v in truth_cds.values())


def test_example_frame_columns_and_sigma_split(examples):
    test, _, _, r, _ = examples["main-clean"]
    f = r.frame
    for col in r.csv_columns:
        assert col in f.columns
    d = test.data
    for p in test.parachutes:
        # Fly-out correction: raw axial load is F·cos θ; scaled load is s·F·cos θ.
        axial = d[p.load_column] * np.cos(np.deg2rad(d[p.angle_column]))
        np.testing.assert_allclose(f[f"load_{p.id}_raw"], axial)
        np.testing.assert_allclose(f[f"load_{p.id}"], f["scale"] * axial)
        for q in (f"cds_{p.id}", f"load_{p.id}", f"cds_{p.id}_raw"):
            np.testing.assert_allclose(f[f"{q}_sigma"], np.hypot(f[f"{q}_sigma_random"], f[f"{q}_sigma_systematic"]))
        # The raw random part is load-cell, G and q̄ noise only (Eq. 12 with ΔW_p = 0).
        axial_sigma = red.axial_load_sigma(d[p.load_column], d[p.angle_column], d[f"{p.load_column}_sigma"],
                                           d[f"{p.angle_column}_sigma"])
        only_noise = red.load_cell_drag_area_sigma(axial, d["G"], d["qbar"], p.weight, axial_sigma,
                                                   d["G_sigma"], d["qbar_sigma"], 0.0)
        np.testing.assert_allclose(f[f"cds_{p.id}_raw_sigma_random"], only_noise.total)
    for q in ("load_total", "cds_total", "load_cells", "cds_cells"):
        np.testing.assert_allclose(f[f"{q}_sigma"], np.hypot(f[f"{q}_sigma_random"], f[f"{q}_sigma_systematic"]))
    np.testing.assert_allclose(f["cds_cells"], sum(f[f"cds_{p.id}"] for p in test.parachutes))
    # Bundle units: US lbf and ft².
    b = r.to_bundle_units()
    assert b["load_total"].to_numpy() == pytest.approx(test.units.from_si(f["load_total"].to_numpy(), "force"))
    assert b["cds_M1"].to_numpy() == pytest.approx(test.units.from_si(f["cds_M1"].to_numpy(), "area"))
    assert b["scale"].to_numpy() == pytest.approx(f["scale"].to_numpy())


def test_load_share_on_examples_sums_to_one(examples):
    _, _, _, r, _ = examples["drogue-clean"]
    assert len(r.load_share) == 2
    for share in r.load_share:
        for method in (share.at_global_peak, share.time_independent, share.mean, *share.at_parachute_peak.values()):
            assert sum(method.values()) == pytest.approx(1.0)
            assert all(0.2 < v < 0.8 for v in method.values())


# ---------------------------------------------------------------------------
# options and refusals


def test_user_windows_replace_the_automatic_ones(examples):
    test = examples["drogue-clean"][0]
    r = red.reduce_test(test, windows=[(11.0, 15.0), (3.0, 9.0)])
    assert r.scale.source == "user"
    assert r.scale.windows == ((3.0, 9.0), (11.0, 15.0))


@pytest.mark.parametrize("kwargs, where, words", [
    ({"scale": "quadratic"}, "option --scale", "linear"),
    ({"windows": [(3.0, 90.0)]}, "option --window", "within"),
    ({"windows": [(-1.0, 3.0)]}, "option --window", "within"),
    ({"windows": [(3.001, 3.004)]}, "option --window", "widen"),
    ({"windows": [(5.0, 3.0)]}, "option --window", "T0 < T1"),
    ({"windows": [(3.0, 6.0), (5.0, 8.0)]}, "option --window", "do not overlap"),
    ({"windows": [(0.0, 0.5)]}, "option --window", "inflated"),
])
def test_bad_options_raise_input_error(examples, kwargs, where, words):
    test = examples["drogue-clean"][0]
    with pytest.raises(InputError) as exc:
        red.reduce_test(test, **kwargs)
    assert where in exc.value.where
    assert words in exc.value.fix


@pytest.mark.parametrize("column, factor, words", [
    ("F_D3", 0.0, "too far from 1 to be riser friction"),        # cells that read nothing
    ("F_D3", 4.448, "too far from 1 to be riser friction"),      # newtons read as pounds-force
    ("G", 0.0, "drag area (W_T·G/q̄ − CDS_V) there is not positive"),
])
def test_a_friction_factor_that_friction_cannot_explain_is_refused(examples, column, factor, words):
    import dataclasses

    test = examples["drogue-clean"][0]
    data = test.data.copy()
    cells = [c for c in data.columns if c.startswith("F_")] if column.startswith("F_") else [column]
    for c in cells:
        data[c] = data[c] * factor
    with pytest.raises(InputError) as exc:
        red.reduce_test(dataclasses.replace(test, data=data))
    assert "window" in exc.value.where and words in exc.value.problem
    assert "units" in exc.value.fix or "G and qbar" in exc.value.fix
    # the same windows given by hand are refused alike
    with pytest.raises(InputError, match="option --window 3:8"):
        red.reduce_test(dataclasses.replace(test, data=data), windows=[(3.0, 8.0)])


def test_parse_window():
    assert red.parse_window("3.5:9") == (3.5, 9.0)
    with pytest.raises(InputError, match="--window"):
        red.parse_window("3.5-9")


def test_without_load_cells_only_the_accelerometer_is_reduced(examples):
    import dataclasses

    test = examples["drogue-clean"][0]
    bare = dataclasses.replace(test, parachutes=tuple(dataclasses.replace(p, load_cell=None)
                                                      for p in test.parachutes))
    r = red.reduce_test(bare)
    assert r.scale is None and r.load_share == ()
    assert r.csv_columns == ["time", "load_total", "load_total_sigma", "cds_total", "cds_total_sigma"]
    assert all(pk.load_cells is None for pk in r.peaks)
    partial = dataclasses.replace(test, parachutes=(dataclasses.replace(test.parachutes[0], load_cell=None),
                                                    test.parachutes[1]))
    with pytest.raises(InputError, match="load cell"):
        red.reduce_test(partial)


# ---------------------------------------------------------------------------
# the command


def _required_columns(test):
    cols = ["time", "load_total", "load_total_sigma", "cds_total", "cds_total_sigma"]
    for p in test.parachutes:
        cols += [f"load_{p.id}", f"load_{p.id}_sigma", f"cds_{p.id}_raw", f"cds_{p.id}", f"cds_{p.id}_sigma"]
    return cols


@pytest.mark.parametrize("name, extra", [("main-clean", []),
                                         ("drogue-clean", ["--scale", "linear", "--window", "3:9",
                                                           "--window", "11:15.5"])])
def test_cli_reduce_writes_outputs(tmp_path, capsys, examples, name, extra):
    out = tmp_path / "out"
    assert main(["reduce", str(EXAMPLES[name]), "--out", str(out), *extra]) == 0
    printed = capsys.readouterr().out
    assert "scale factor" in printed and "peak load" in printed and str(out / "reduced.csv") in printed
    test, *_ = examples[name]
    table = pd.read_csv(out / "reduced.csv")
    assert list(table.columns) == _required_columns(test)
    assert np.isfinite(table.to_numpy()).all()
    summary = json.loads((out / "reduction.json").read_text())
    assert summary["units"]["force"] == "lbf" and summary["units"]["area"] == "ft²"
    assert set(summary["scale_factor"]) >= {"mode", "windows", "values", "sigma"}
    assert summary["scale_factor"]["mode"] == ("linear" if extra else "constant")
    assert len(summary["peaks"]) == len(summary["load_share"]) == len(test.parachutes[0].stages)
    # JSON peaks are in the bundle's units (lbf), like the CSV.
    stage1 = summary["peaks"][0]["accelerometer"]
    row = table.loc[np.argmin(np.abs(table["time"] - stage1["time"]))]
    assert stage1["load"] == pytest.approx(row["load_total"], rel=0.1)
    assert (out / "reduction.png").stat().st_size > 10_000


def test_cli_bad_bundle_writes_nothing(tmp_path, capsys):
    bundle = tmp_path / "broken"
    shutil.copytree(EXAMPLES["drogue-clean"], bundle)
    (bundle / "truth.json").unlink()
    lines = (bundle / "data.csv").read_text().splitlines()
    lines[5] = lines[5].replace(lines[5].split(",")[1], "oops", 1)
    (bundle / "data.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    assert main(["reduce", str(bundle), "--out", str(out)]) != 0
    err = capsys.readouterr().err
    assert "row 6" in err and "Fix:" in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("args", [["--scale", "cubic"], ["--window", "2:99"], ["--window", "nonsense"]])
def test_cli_bad_option_writes_nothing(tmp_path, capsys, args):
    out = tmp_path / "out"
    assert main(["reduce", str(EXAMPLES["drogue-clean"]), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert "--scale" in err or "--window" in err
    assert not out.exists()


@pytest.mark.parametrize("scenario,seed", [("drogue", 5), ("main", 6)])
def test_synthetic_bundles_reduce_to_their_true_drag_areas(tmp_path, scenario, seed):
    """Our own simulator's bundles, through the file format: scaled drag areas match truth within sigma."""
    from cpas_bayes.data.synth import write_synthetic

    folder = write_synthetic(scenario, "none", seed, tmp_path / scenario)
    test = read_bundle(folder)
    truth = json.loads((folder / "truth.json").read_text())
    truth_cds = _truth_drag_areas(test, truth)
    r = red.reduce_test(test)
    mask = _steady_mask(test, truth_cds)
    assert mask.sum() > 500
    for p in test.parachutes:
        z = (r.frame[f"cds_{p.id}"].to_numpy() - truth_cds[p.id]["cds"]) / r.frame[f"cds_{p.id}_sigma"].to_numpy()
        assert 0.8 <= float(z[mask].std()) <= 1.25, f"{scenario} {p.id}: sd {z[mask].std():.3f}"
        assert abs(float(z[mask].mean())) < 0.5
    assert abs(r.scale.factor - truth["load_scale"]) < 3 * r.scale.factor_sigma

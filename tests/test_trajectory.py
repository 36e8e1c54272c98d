"""Atmosphere, effects and the batched trajectory: closed forms, identities, and the example bundles.

The example bundles come from an independent simulator; given their truth
(truth.json, the first data row as initial state) this package's simulator
must reproduce their channels within the measurement noise.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from cpas_bayes.physics.atmosphere import geopotential_altitude, standard_atmosphere
from cpas_bayes.data.bundle import EXAMPLES_DIR, read_bundle
from cpas_bayes.physics.effects import (added_mass, breathing_drag_area, breathing_factor, friction_scale,
                                        friction_settle, lagged, riser_tension, sensed_load_factor)
from cpas_bayes.data.synth import truth_from_bundle
from cpas_bayes.physics.trajectory import (BreathingParameters, ClusterParameters, SimulationOptions, VehicleProperties,
                                   VehicleState0, composite_cluster, simulate, single_run)
from cpas_bayes.core.units import STANDARD_GRAVITY as G0

# ---------------------------------------------------------------------------
# atmosphere


@pytest.mark.parametrize("h, density, pressure, temperature", [
    # U.S. Standard Atmosphere 1976, by geopotential altitude (m, kg/m³, Pa, K)
    (0.0, 1.2250, 101_325.0, 288.15),
    (5_000.0, 0.73612, 54_019.9, 255.65),
    (11_000.0, 0.36392, 22_632.1, 216.65),
    (20_000.0, 0.088035, 5_474.89, 216.65),
    (32_000.0, 0.013225, 868.019, 228.65),
    (47_000.0, 0.0014275, 110.906, 270.65),
    (51_000.0, 0.00086160, 66.9389, 270.65),
    (71_000.0, 0.000064211, 3.95642, 214.65),
])
def test_standard_atmosphere_tables(h, density, pressure, temperature):
    rho, p, T = standard_atmosphere(h)
    assert rho == pytest.approx(density, rel=2e-4)
    assert p == pytest.approx(pressure, rel=2e-5)
    assert T == pytest.approx(temperature, abs=1e-9)


@pytest.mark.parametrize("z, density", [(11_000.0, 0.36480), (20_000.0, 0.088910), (32_000.0, 0.013555)])
def test_geometric_altitude_tables(z, density):
    assert standard_atmosphere(z, geopotential=False)[0] == pytest.approx(density, rel=2e-4)
    assert geopotential_altitude(z) < z


def test_troposphere_formula_and_vectorisation():
    h = np.linspace(-500.0, 10_999.0, 36).reshape(3, 12)
    rho, p, T = standard_atmosphere(h)
    assert rho.shape == h.shape
    T_expected = 288.15 - 0.0065 * h
    p_expected = 101_325.0 * (T_expected / 288.15) ** 5.25588
    np.testing.assert_allclose(T, T_expected, rtol=1e-12)
    np.testing.assert_allclose(p, p_expected, rtol=2e-6)
    np.testing.assert_allclose(rho, p_expected / (287.05287 * T_expected), rtol=2e-6)


def test_atmosphere_is_continuous_across_layers_and_refuses_space():
    for base in (11_000.0, 20_000.0, 32_000.0, 47_000.0, 51_000.0, 71_000.0):
        below, above = standard_atmosphere(np.array([base - 1e-6, base + 1e-6]))[0]
        assert below == pytest.approx(above, rel=1e-8)
    mixed = np.array([1_000.0, 15_000.0, 40_000.0])
    np.testing.assert_allclose(standard_atmosphere(mixed)[0], [standard_atmosphere(h)[0] for h in mixed])
    with pytest.raises(ValueError):
        standard_atmosphere(90_000.0)


# ---------------------------------------------------------------------------
# effects


def test_added_mass_scales_with_volume():
    assert added_mass(100.0, 1.0, 0.5) == pytest.approx(0.5 * 1000.0)
    np.testing.assert_allclose(added_mass(np.array([[4.0], [9.0]]), 1.2, np.array([1.0, 0.5])),
                               [[9.6, 4.8], [32.4, 16.2]])
    assert added_mass(-1.0, 1.0, 1.0) == 0.0


def test_breathing_factor_starts_at_one_and_dies_out():
    tau = np.array([-1.0, 0.0, 0.25, 30.0])
    b = breathing_factor(tau, 0.08, 1.0, 0.2)
    assert b[0] == 1.0 and b[1] == pytest.approx(1.0)
    # quarter period of the damped oscillation: near its first crest
    expected = 1 + 0.08 * np.exp(-0.2 * 2 * np.pi * 0.25) * np.sin(2 * np.pi * np.sqrt(1 - 0.04) * 0.25)
    assert b[2] == pytest.approx(expected)
    assert abs(b[3] - 1.0) < 1e-6
    with pytest.raises(ValueError):
        breathing_factor(tau, 0.05, 1.0, 1.0)


def _breathing_by_numpy(cds, t, start, peak, amplitude, frequency, damping, phase=None, share=None):
    """The active stage found with numpy (the count of starts passed, less one) and breathing_factor; with a
    phase (B, P) and a reefed share (B,), the ring A_k·e^(−ζωτ)·[sin(ω_d·τ + φ) − sin φ] written out."""
    tt = t if np.ndim(t) == 3 else np.asarray(t)[None, None, :]
    active = (start[..., :, None] <= tt[..., None, :]).sum(axis=-2) - 1
    tau = np.where(active >= 0, tt - np.take_along_axis(peak, np.clip(active, 0, None), axis=-1), -1.0)
    if phase is None:
        return cds * breathing_factor(tau, amplitude[:, None, None], frequency[:, None, None],
                                      damping[:, None, None])
    last = np.isfinite(start).sum(axis=-1)[..., None] - 1                        # (B, P, 1)
    a = amplitude[:, None, None] * np.where(active == last, 1.0, share[:, None, None])
    omega, zeta, after = 2 * np.pi * frequency[:, None, None], damping[:, None, None], np.clip(tau, 0.0, None)
    x = omega * np.sqrt(1 - zeta ** 2) * after
    ring = np.exp(-zeta * omega * after) * (np.sin(x + phase[..., None]) - np.sin(phase[..., None]))
    with np.errstate(invalid="ignore"):
        return cds * np.where(tau >= 0, 1.0 + a * ring, 1.0)


@pytest.mark.parametrize("per_walker_time", [False, True])
def test_breathing_drag_area_is_the_active_stages_factor(per_walker_time):
    """The compiled pass against the numpy statement of the same law, with a walker whose stage is undefined
    (NaN start and peak: factor 1 from there), times before the first start, and a lagged time base."""
    rng = np.random.default_rng(3)
    b, p, k, n = 5, 3, 3, 400
    start = np.sort(rng.uniform(0.0, 20.0, (b, p, k)), axis=-1)
    peak = start + rng.uniform(0.2, 3.0, (b, p, k))
    start[1, 2, 1] = peak[1, 2, 1] = np.nan
    cds = rng.uniform(5.0, 500.0, (b, p, n))
    t = np.sort(rng.uniform(-1.0, 30.0, n))
    if per_walker_time:
        t = t[None, None, :] - rng.uniform(0.0, 0.1, (b, 1, 1))
    amplitude, frequency, damping = rng.uniform(0, 0.25, b), rng.uniform(0.1, 3.0, b), rng.uniform(0.0, 0.4, b)
    got = breathing_drag_area(cds, t, start, peak, amplitude, frequency, damping)
    np.testing.assert_allclose(got, _breathing_by_numpy(cds, t, start, peak, amplitude, frequency, damping),
                               rtol=1e-13, atol=0)
    # a phase per canopy and a share of the ring in the stages before the last: the same law written out,
    # and at φ = 0, share 1 the ring above to the last bits
    phase, share = rng.uniform(-np.pi, np.pi, (b, p)), rng.uniform(0.0, 2.0, b)
    shaped = breathing_drag_area(cds, t, start, peak, amplitude, frequency, damping, phase, share)
    np.testing.assert_allclose(shaped, _breathing_by_numpy(cds, t, start, peak, amplitude, frequency, damping,
                                                           phase, share), rtol=1e-12, atol=0)
    assert not np.allclose(shaped, got)
    np.testing.assert_allclose(breathing_drag_area(cds, t, start, peak, amplitude, frequency, damping,
                                                   np.zeros((b, p)), np.ones(b)), got, rtol=1e-15, atol=0)
    if not per_walker_time:     # before the first stage starts: no ring
        before = t < np.nanmin(start)
        assert before.any() and np.all(got[..., before] == cds[..., before])
    assert not np.allclose(got, cds)     # it rings
    with pytest.raises(ValueError, match="damping_ratio"):
        breathing_drag_area(cds, t, start, peak, amplitude, frequency, np.full(b, 1.0))


def test_friction_settle_holds_then_decays_exponentially():
    t = np.array([0.0, 5.0, 7.0, 9.0, 1e3])
    np.testing.assert_allclose(friction_settle(t, 1.16, 1.10, 5.0, 2.0),
                               [1.16, 1.16, 1.10 + 0.06 / np.e, 1.10 + 0.06 / np.e**2, 1.10])
    with pytest.raises(ValueError, match="tau > 0"):
        friction_settle(t, 1.16, 1.10, 5.0, 0.0)


def test_friction_scale_ramps_linearly_and_holds_outside():
    t = np.array([0.0, 5.0, 7.5, 10.0, 20.0])
    np.testing.assert_allclose(friction_scale(t, 1.16, 1.10, 5.0, 10.0), [1.16, 1.16, 1.13, 1.10, 1.10])
    batch = friction_scale(t, np.array([1.2, 1.1]), 1.0, 5.0, 10.0)
    assert batch.shape == (2, 5)
    np.testing.assert_allclose(batch[:, 2], [1.1, 1.05])


def test_lagged_delays_by_interpolation_and_holds_the_first_value():
    t = np.arange(0.0, 1.0, 0.01)
    values = np.vstack([3.0 * t + 1.0, np.sin(2 * np.pi * t)])
    out = lagged(t, values, np.array([0.035, 0.0]))
    np.testing.assert_allclose(out[0, 4:], 3.0 * (t[4:] - 0.035) + 1.0, rtol=1e-12)
    np.testing.assert_allclose(out[0, :4], 1.0)
    np.testing.assert_allclose(out[1], values[1])
    with pytest.raises(ValueError):
        lagged(t, values, -0.01)


def test_sensed_load_factor_and_tension_signs():
    # falling straight down: free fall (speeding up at g) senses nothing, terminal speed senses 1 g
    assert sensed_load_factor(G0, -np.pi / 2, G0) == pytest.approx(0.0)
    assert sensed_load_factor(0.0, -np.pi / 2, G0) == pytest.approx(1.0)
    assert riser_tension(100.0, 2.0, 50.0, 1.0) == pytest.approx(150.0)


# ---------------------------------------------------------------------------
# trajectory

FT = 0.3048
LBF = 4.4482216152605


def drogue_like(batch=1, rng=None, **overrides):
    """Two Drogue-like canopies, reefed then full open, SI."""
    rng = rng or np.random.default_rng(0)
    start = np.stack([np.array([[1.0, 9.5], [1.1, 10.0]]) + rng.uniform(-0.1, 0.1, (2, 2)) for _ in range(batch)])
    cds_o = 250.0 * FT**2
    fields = dict(start=start, cds_stage=np.array([0.44, 1.0]) * cds_o, n_fill=np.array([10.0, 10.0]),
                  expopen=np.array([2.2, 2.1]), ck=np.array([1.3, 1.2]), tk=np.array([0.5, 0.5]),
                  cds_o=cds_o, diameter=23 * FT, weight=80 * LBF)
    fields.update(overrides)
    return ClusterParameters(**fields)


STATE0 = VehicleState0(412 * FT, np.radians(-47.0), 22_800 * FT)
VEHICLE = VehicleProperties(20_000 * LBF, 17 * FT**2)


def test_zero_drag_follows_the_ballistic_closed_form():
    cluster = drogue_like(cds_stage=np.zeros(2))
    vehicle = VehicleProperties(20_000 * LBF, 0.0)
    r = simulate(STATE0, vehicle, cluster, 6.0)
    t = r.time
    v0, g0 = STATE0.airspeed, STATE0.flight_path_angle
    horizontal = v0 * np.cos(g0)
    vertical = v0 * np.sin(g0) - G0 * t
    np.testing.assert_allclose(r.airspeed[0], np.hypot(horizontal, vertical), rtol=1e-9)
    np.testing.assert_allclose(r.flight_path_angle[0], np.arctan2(vertical, horizontal), atol=1e-9)
    np.testing.assert_allclose(r.altitude[0], STATE0.altitude + v0 * np.sin(g0) * t - 0.5 * G0 * t**2,
                               atol=1e-6)
    np.testing.assert_allclose(r.load_factor, 0.0, atol=1e-12)
    np.testing.assert_allclose(r.tension, 0.0, atol=1e-9)


@pytest.fixture(scope="module")
def drogue_batch():
    rng = np.random.default_rng(11)
    cluster = drogue_like(batch=3, rng=rng, n_fill=rng.uniform(9, 13, (3, 2, 2)))
    state0 = VehicleState0(np.array([400, 412, 430]) * FT, np.radians([-45.0, -47.0, -52.0]),
                           np.array([22_000, 22_800, 24_000]) * FT)
    vehicle = VehicleProperties(np.array([19_500, 20_000, 21_000]) * LBF, np.array([15, 17, 20]) * FT**2)
    return state0, vehicle, cluster, simulate(state0, vehicle, cluster, 12.0)


def test_load_factor_and_tensions_satisfy_eq_3_6_10(drogue_batch):
    _, vehicle, cluster, r = drogue_batch
    W_T = r.total_weight[:, None]
    cds_total = r.cds.sum(axis=1)
    # Eq. 3 / 8: W_T·G = q̄·(PRF·ΣCDS + CDS_V)
    np.testing.assert_allclose(W_T * r.load_factor, r.qbar * (cds_total + r.vehicle_cds[:, None]),
                               rtol=1e-10, atol=1e-6)
    # Eq. 10: F_i = PRF·q̄·CDS_i − W_p,i·G
    np.testing.assert_allclose(r.tension, r.qbar[:, None] * r.cds - r.parachute_weight[..., None]
                               * r.load_factor[:, None], rtol=1e-10, atol=1e-6)
    # Eq. 6: W_V·G = ΣF_i + q̄·CDS_V (the vehicle alone)
    W_V = np.asarray(vehicle.weight)[:, None]
    np.testing.assert_allclose(W_V * r.load_factor, r.tension.sum(axis=1) + r.qbar * r.vehicle_cds[:, None],
                               rtol=1e-10, atol=1e-6)
    # kinematics: dh/dt = V·sin γ, dγ/dt = −g·cos γ/V (central differences)
    dt = r.time[1] - r.time[0]
    dh = np.gradient(r.altitude, dt, axis=-1)[:, 1:-1]
    np.testing.assert_allclose(dh, (r.airspeed * np.sin(r.flight_path_angle))[:, 1:-1], rtol=1e-4, atol=1e-3)
    dgamma = np.gradient(r.flight_path_angle, dt, axis=-1)[:, 1:-1]
    np.testing.assert_allclose(dgamma, (-G0 * np.cos(r.flight_path_angle) / r.airspeed)[:, 1:-1],
                               rtol=1e-3, atol=1e-5)


def test_energy_lost_equals_drag_work(drogue_batch):
    _, _, _, r = drogue_batch
    mass = r.total_weight[:, None] / G0
    energy = 0.5 * mass * r.airspeed**2 + mass * G0 * r.altitude
    drag_power = r.qbar * (r.cds.sum(axis=1) + r.vehicle_cds[:, None]) * r.airspeed
    dt = r.time[1] - r.time[0]
    work = np.concatenate([np.zeros((3, 1)), np.cumsum(0.5 * (drag_power[:, 1:] + drag_power[:, :-1]) * dt,
                                                       axis=-1)], axis=-1)
    loss = energy[:, :1] - energy
    np.testing.assert_allclose(loss[:, -1], work[:, -1], rtol=2e-4)


def test_batch_equals_single_runs(drogue_batch):
    state0, vehicle, cluster, r = drogue_batch
    for b in range(3):
        one = simulate(VehicleState0(state0.airspeed[b], state0.flight_path_angle[b], state0.altitude[b]),
                       VehicleProperties(vehicle.weight[b], vehicle.cds[b]),
                       ClusterParameters(**{**cluster.__dict__, "start": cluster.start[b],
                                            "n_fill": cluster.n_fill[b]}), 12.0)
        ref = single_run(r, b)
        for name in ("airspeed", "flight_path_angle", "altitude", "qbar", "load_factor", "cds", "tension",
                     "stage_airspeed", "peak_tension", "peak_total_tension"):
            np.testing.assert_allclose(getattr(one, name), getattr(ref, name), rtol=1e-12, atol=1e-9,
                                       err_msg=name)


def test_stage_airspeed_is_the_airspeed_at_each_own_start(drogue_batch):
    _, _, cluster, r = drogue_batch
    for b in range(3):
        for p in range(2):
            for k in range(2):
                expected = np.interp(cluster.start[b, p, k], r.time, r.airspeed[b])
                assert r.stage_airspeed[b, p, k] == pytest.approx(expected, rel=2e-5)


def test_finer_steps_agree(drogue_batch):
    state0, vehicle, cluster, r = drogue_batch
    fine = simulate(state0, vehicle, cluster, 12.0, SimulationOptions(substeps=4))
    np.testing.assert_allclose(fine.airspeed, r.airspeed, rtol=1e-5)
    np.testing.assert_allclose(fine.tension, r.tension, rtol=1e-3, atol=5.0)
    np.testing.assert_allclose(fine.peak_tension, r.peak_tension, rtol=2e-3)


def test_refined_peaks_are_at_least_the_sampled_peaks(drogue_batch):
    _, _, _, r = drogue_batch
    assert np.all(r.peak_tension >= r.tension.max(axis=-1))
    assert np.all(r.peak_tension <= r.tension.max(axis=-1) * 1.05)
    assert np.all(r.peak_total_tension >= r.tension.sum(axis=1).max(axis=-1))


def test_added_mass_identities_and_momentum():
    cluster = drogue_like()
    opts = SimulationOptions(added_mass_k=0.6)
    r = simulate(STATE0, VEHICLE, cluster, 12.0, opts)
    base = simulate(STATE0, VEHICLE, cluster, 12.0)
    momentum = r.momentum_rate
    # W_T·G = q̄·(ΣCDS + CDS_V) + Σ d(m_a V)/dt (A4), and Eq. 6 still holds for the vehicle
    np.testing.assert_allclose(r.total_weight[:, None] * r.load_factor,
                               r.qbar * (r.cds.sum(axis=1) + r.vehicle_cds[:, None]) + momentum.sum(axis=1),
                               rtol=1e-9, atol=1e-3)
    np.testing.assert_allclose(VEHICLE.weight * r.load_factor,
                               r.tension.sum(axis=1) + r.qbar * r.vehicle_cds[:, None], rtol=1e-9, atol=1e-3)
    # load-cell drag area (Eq. 11) = CDS_i + d(m_a V)/dt / q̄
    lc = (r.tension + r.parachute_weight[..., None] * r.load_factor[:, None]) / r.qbar[:, None]
    np.testing.assert_allclose(lc, r.cds + momentum / r.qbar[:, None], rtol=1e-9, atol=1e-9)
    # m_a = k_a·ρ·CDS^1.5; capturing air while filling pulls harder
    np.testing.assert_allclose(r.added_mass, 0.6 * r.density[:, None] * r.cds**1.5, rtol=1e-12)
    first_start, first_peak = cluster.start[0, :, 0], base.peak_time[0, :, 0]
    for p in range(2):
        filling = (r.time > first_start[p] + 0.05) & (r.time < first_peak[p] - 0.02)
        assert np.all(momentum[0, p, filling] > 0)
    assert r.peak_total_tension[0] > base.peak_total_tension[0]
    # the momentum term integrates to m_a·V (finely sampled: d(m_a V)/dt jumps at each peak)
    fine = simulate(STATE0, VEHICLE, cluster, 2.5, SimulationOptions(added_mass_k=0.6, dt=0.001))
    rate = fine.momentum_rate[0]
    integral = np.sum(0.5 * (rate[:, 1:] + rate[:, :-1]), axis=-1) * 0.001
    np.testing.assert_allclose(integral, fine.added_mass[0, :, -1] * fine.airspeed[0, -1], rtol=1e-2)


def test_breathing_rings_after_each_peak_and_keeps_the_drag_area_continuous():
    cluster = drogue_like()
    breathing = BreathingParameters(0.08, 1.5, 0.1)
    r = simulate(STATE0, VEHICLE, cluster, 12.0, SimulationOptions(breathing=breathing))
    base = simulate(STATE0, VEHICLE, cluster, 12.0)
    peak_time = base.peak_time[0]          # (P, K)
    before = base.time < peak_time[:, :1].min()
    np.testing.assert_allclose(r.cds[..., before], base.cds[..., before], rtol=1e-12)
    after = (base.time > peak_time[:, 0].max()) & (base.time < peak_time[:, 0].max() + 2.0)
    ratio = r.cds[0][:, after] / base.cds[0][:, after]   # the 2 s after the first peaks
    assert np.ptp(ratio) > 0.08
    assert np.max(np.abs(np.diff(r.cds[0], axis=-1))) < 1.5 * np.max(np.abs(np.diff(base.cds[0], axis=-1)))
    assert not np.allclose(r.load_factor, base.load_factor)


def test_flight_path_angle_turns_down_to_vertical_and_stays():
    cluster = drogue_like(start=np.array([[0.2, 1.0], [0.2, 1.1]]))
    state0 = VehicleState0(np.array([60.0, 60.0]), np.radians([-80.0, -90.0]), 3000.0)
    r = simulate(state0, VEHICLE, cluster, 20.0)
    assert r.flight_path_angle.min() >= -np.pi / 2
    assert np.all(np.diff(r.flight_path_angle[0]) <= 0)
    # γ + 90° decays like exp(−g·t/V) near vertical
    assert r.flight_path_angle[0, -1] == pytest.approx(-np.pi / 2, abs=2e-2)
    np.testing.assert_array_equal(r.flight_path_angle[1], -np.pi / 2)
    assert np.all(np.isfinite(r.airspeed))


def test_composite_parachute_equals_identical_simultaneous_canopies_and_overshoots_staggered_ones():
    together = drogue_like(start=np.array([[1.0, 9.5], [1.0, 9.5]]))
    r = simulate(STATE0, VEHICLE, together, 12.0)
    c = simulate(STATE0, VEHICLE, composite_cluster(together), 12.0)
    np.testing.assert_allclose(c.cds[:, 0], r.cds.sum(axis=1), rtol=1e-10)
    np.testing.assert_allclose(c.tension[:, 0], r.tension.sum(axis=1), rtol=1e-9, atol=1e-6)
    staggered = drogue_like(start=np.array([[0.9, 9.3], [1.3, 9.9]]))
    s = simulate(STATE0, VEHICLE, staggered, 12.0)
    sc = simulate(STATE0, VEHICLE, composite_cluster(staggered), 12.0)
    assert sc.peak_total_tension[0] > s.peak_total_tension[0]


def test_bad_options_are_refused():
    with pytest.raises(ValueError):
        simulate(STATE0, VEHICLE, drogue_like(), 1.0, SimulationOptions(decay="cubic"))
    with pytest.raises(ValueError):
        simulate(STATE0, VEHICLE, drogue_like(), -1.0)


# ---------------------------------------------------------------------------
# reproduction of the independent simulator's example bundles


def reproduce(example):
    folder = EXAMPLES_DIR / example
    test = read_bundle(folder)
    truth_doc = json.loads((folder / "truth.json").read_text(encoding="utf-8"))
    truth = truth_from_bundle(test, truth_doc)
    r = simulate(truth.initial_state(), truth.vehicle(), truth.cluster(), test.duration)
    return test, truth_doc, r


@pytest.fixture(scope="module", params=["drogue-clean", "main-clean"])
def example_run(request):
    return reproduce(request.param)


def test_examples_reproduce_within_noise(example_run):
    """Measured: airspeed residual mean 0.11 / 0.01 ft/s, sd 0.51 ft/s (the 0.5 ft/s noise);
    normalised residuals of G, q̄ and every load-cell drag area: |mean| ≤ 0.07, sd 0.98–1.02."""
    test, truth_doc, r = example_run
    d, u = test.data, test.units
    assert np.allclose(d["time"], r.time)

    dv = u.from_si(r.airspeed[0] - d["airspeed"].to_numpy(), "speed")
    assert abs(dv.mean()) < 0.3 and dv.std() < 0.7 and np.abs(dv).max() < 3.0
    np.testing.assert_allclose(r.density[0], d["density"], rtol=2e-4)
    np.testing.assert_allclose(np.degrees(r.flight_path_angle[0]), d["gamma"], atol=0.05)

    def check(z, what):
        assert abs(z.mean()) < 0.2 and z.std() < 1.5, f"{what}: mean {z.mean():.3f}, sd {z.std():.3f}"

    check((d["G"] - r.load_factor[0]) / d["G_sigma"], "G")
    check((d["qbar"] - r.qbar[0]) / d["qbar_sigma"], "qbar")
    scale = truth_doc["load_scale"]
    G, q = d["G"].to_numpy(), d["qbar"].to_numpy()
    for j, p in enumerate(test.parachutes):
        cos_theta = np.cos(np.radians(d[p.angle_column])) if p.angle_column else 1.0
        load = d[p.load_column].to_numpy() * scale * cos_theta
        # Eq. 11 and its uncertainty (Eq. 12) from the load cell, G and q̄
        cds_cells = (load + p.weight * G) / q
        sigma = np.sqrt((scale * cos_theta * d[f"{p.load_column}_sigma"] / q) ** 2
                        + (p.weight * d["G_sigma"] / q) ** 2 + (d["qbar_sigma"] * cds_cells / q) ** 2)
        check((cds_cells - r.cds[0, j]) / sigma, f"load-cell drag area {p.id}")


def test_examples_peak_loads_match_truth(example_run):
    test, truth_doc, r = example_run
    u = test.units
    for j, chute in enumerate(truth_doc["chutes"]):
        assert u.from_si(r.peak_tension[0, j], "force") == pytest.approx(chute["peak_load"], rel=3e-3)
    assert u.from_si(r.peak_total_tension[0], "force") == pytest.approx(truth_doc["peak_total_load"], rel=3e-3)


def test_examples_fill_constants_match_truth(example_run):
    _, truth_doc, r = example_run
    for j, chute in enumerate(truth_doc["chutes"]):
        np.testing.assert_allclose(r.timing.n[0, j], [s["n"] for s in chute["stages"]], rtol=1e-3)


def test_added_mass_and_its_rate_together_equal_the_two_formulas():
    """The likelihood's fused form (one power of the area ratio) gives Eq. A1' and its rate as
    ``added_mass`` and ``added_mass_rate`` do, at every exponent the prior allows and at a zero area."""
    from cpas_bayes.physics.effects import added_mass, added_mass_and_rate, added_mass_rate

    rng = np.random.default_rng(5)
    shape = (6, 3, 40)
    cds = rng.uniform(0.0, 80.0, shape)
    cds[:, :, :5] = 0.0                               # before a stage starts
    cds_rate = rng.normal(0.0, 50.0, shape)
    rho = rng.uniform(0.4, 1.2, (1, 1, 40))
    rho_rate = rng.normal(0.0, 1e-3, (1, 1, 40))
    k_a = rng.uniform(0.0, 1.0, (6, 1, 1))
    exponent = np.array([1.0, 1.2, 1.5, 1.5, 2.0, 2.25])[:, None, None]
    cds_o = rng.uniform(50.0, 90.0, (6, 3, 1))
    mass, rate = added_mass_and_rate(cds, cds_rate, rho, rho_rate, k_a, exponent, cds_o)
    np.testing.assert_allclose(mass, added_mass(cds, rho, k_a, exponent, cds_o), rtol=1e-12, atol=0)
    np.testing.assert_allclose(rate, added_mass_rate(cds, cds_rate, rho, rho_rate, k_a, exponent, cds_o),
                               rtol=1e-12, atol=1e-300)


def test_the_compiled_lagged_added_mass_equals_its_two_formulas():
    """``lagged_added_mass`` (one compiled pass, the likelihood's) gives what ``added_mass_and_rate`` then
    ``lagged_mass_rate`` give: mass = target + τ_m·g, rate = −g, with plateaus of equal drag area (where
    it reuses the power), zero areas and a zero lag among the rows."""
    from cpas_bayes.physics.effects import added_mass_and_rate, lagged_added_mass, lagged_mass_rate

    rng = np.random.default_rng(6)
    B, P, N = 6, 3, 60
    t = np.cumsum(rng.uniform(0.005, 0.03, N))
    cds = np.sort(rng.uniform(0.0, 80.0, (B, P, N)), axis=-1)
    cds[:, :, :5] = 0.0                                # before a stage starts
    cds[:, :, 30:45] = cds[:, :, 30:31]                # a settled stage
    cds_rate = rng.normal(0.0, 50.0, (B, P, N))
    cds_rate[:, :, 30:45] = 0.0
    rho = rng.uniform(0.4, 1.2, (1, N))
    rho_rate = rng.normal(0.0, 1e-3, (1, N))
    k_a = rng.uniform(0.0, 1.0, B)
    exponent = np.array([1.0, 1.2, 1.5, 1.5, 2.0, 2.25])
    lag = np.array([0.0, 0.01, 0.05, 0.2, 0.0, 0.1])
    cds_o = rng.uniform(50.0, 90.0, (B, P))
    mass, rate = lagged_added_mass(cds, cds_rate, rho, rho_rate, k_a, exponent, cds_o, t, lag)
    target, target_rate = added_mass_and_rate(cds, cds_rate, rho[:, None], rho_rate[:, None], k_a[:, None, None],
                                              exponent[:, None, None], cds_o[..., None])
    g = lagged_mass_rate(target_rate, t, lag)
    np.testing.assert_allclose(mass, target + lag[:, None, None] * g, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rate, -g, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="lag"):
        lagged_added_mass(cds, cds_rate, rho, rho_rate, k_a, exponent, cds_o, t, -lag - 0.1)

"""Synthetic logger-like drop tests with known truth: an accelerometer and a GNSS receiver, no q̄, no load cells.

A logger test is what a small drop-test team records: a box-car averaging
accelerometer (20–200 Hz) and a GNSS receiver (1–10 Hz, with latency), the
wind from a sounding, no dynamic-pressure channel and no load cells. This
module simulates such tests with its own 3-D point-mass integrator (it does
not call :func:`cpas_bayes.physics.trajectory.simulate`, so the two check each
other); it shares only the stage law
(:func:`cpas_bayes.physics.inflation.parachute_stage_law`, the compiled
:func:`~cpas_bayes.physics.inflation.parachute_drag_area`) and the 1976
atmosphere. Package code never reads a truth.json; tests and recovery
studies do.

Dynamics (SI; earth axes north, east, up; state: position (n, e, h), ground
velocity v_g)::

    w(h)  = (w_n(h), w_e(h), 0)        stated profile (linear in h) + one true offset per component
    v_a   = v_g − w(h),   q̄ = ½·ρ(h)·|v_a|²
    m·dv_g/dt = −q̄·(Σ_i CDS_i(t) + CDS_V)·v_a/|v_a| − m·g0·ẑ,   m = W_T/g0,  W_T = W_V + Σ W_p,i

so the wind shear enters through w(h(t)). ρ is the 1976 standard atmosphere
(:func:`~cpas_bayes.physics.atmosphere.standard_density`) or a scenario's
:class:`~cpas_bayes.data.air_data.DensityProfile`, tabulated every metre and
interpolated log-linearly (error < 1e-9). CDS_i(t) is the stage law with the
n_p form of the fill constant, decay "linear", below_previous "drop" (the
defaults of :mod:`cpas_bayes.data.synth`), V_i = |v_a| at each stage start:
a step that contains a start is split there so V_i is the integrated state
at the start. Classical RK4, step ≤ 1 ms throughout (``step``), on a grid on
which the accelerometer's sample times fall.

Measurement model::

    G_true(t) = q̄·(Σ CDS_i + CDS_V)/W_T                      specific force magnitude, g
    G_j       = accel_scale·(1/T_a)·∫_{t_j−T_a}^{t_j} G_true dt + accel_bias + N(0, σ_G),   T_a = 1/r_a
    v_k       = v_g(t_k − L) + N(0, diag(σ_vh², σ_vh², σ_vv²)),   h_k = h(t_k − L) + N(0, σ_h²)

The box-car integral is a seventh state (∫G_true dt), so averages are as
exact as the integration. Accelerometer rows at t_j = j/r_a (j ≥ 1), GNSS
rows at t_k = k/r_g with t_k ≥ L (the state before release is not simulated);
rows are the union of both (sorted), NaN where a channel has no sample.
Time 0 is release, at airspeed V0, air-relative flight-path angle γ0 and
heading ψ0 (deg from north toward east).

With no wind it reproduces the planar simulator to ~1e-9 (a test holds it).

Scenarios (``SCENARIOS``, uniform draws): ``logger-drop`` one unreefed Main
(D_o 5–15 m, W_V 500–5,000 N, V0 40–90 m/s, γ0 −30–0°, one stage at 0.5–2 s,
20 s), ``logger-drogue`` two reefed Drogues as synth's ``drogue`` but at
100–150 m/s (25 s), ``logger-main`` three Mains as synth's ``main`` (45 s),
``logger-attitude`` logger-drop logged as body axes with attitude and a swing
(:mod:`cpas_bayes.data.synth_attitude`).
Common to all: wind profile of 3–6 levels spanning the flown altitudes, each
component within ±15 m/s, shear ≤ 10 m/s per km, stated sigma U(0.5, 3) m/s
and true offsets N(0, sigma); accel_scale 1 + N(0, 0.01), accel_bias
N(0, 0.02) g, σ_G U(0.01, 0.05) g, r_a from {20, 50, 100, 200} Hz, r_g from
{1, 2, 5, 10} Hz, σ_vh U(0.05, 0.3), σ_vv U(0.1, 0.5) m/s, σ_h U(2, 5) m,
latency L U(0, 0.6) s. Stated stage starts, vehicle weight and CDS_V are the
truth plus normal errors of their stated sigmas, as in synth.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numba
import numpy as np
import pandas as pd

from cpas_bayes.core.units import STANDARD_GRAVITY, unit_system
from cpas_bayes.data.air_data import AirDataSpec, DensityProfile, WindProfile
from cpas_bayes.data.bundle import FlightTest, Parachute, Stage, Vehicle
from cpas_bayes.data.bundle_write import write_bundle
from cpas_bayes.data.synth import FIRST_START_SIGMA, LATER_START_SIGMA, ChuteTruth, StageTruth
from cpas_bayes.data.synth_attitude import AttitudeTruth, draw_attitude_truth, write_body_axes
from cpas_bayes.data.synth_logger_effects import draw_added_mass, draw_breathing, effect_stream
from cpas_bayes.data.synth_logger_scenarios import (ACCEL_BIAS_SIGMA, ACCEL_NOISE, ACCEL_RATES, ACCEL_SCALE_SIGMA,
                                                    ALTITUDE_SIGMA, DENSITY_GRID, GNSS_RATES, GNSS_SIGMA_H,
                                                    GNSS_SIGMA_V, LATENCY, SCENARIOS, WIND_LEVELS, WIND_LIMIT,
                                                    WIND_SHEAR, WIND_SIGMA)
from cpas_bayes.data.synth_logger_truth import logger_truth_document, sample_times
from cpas_bayes.physics.atmosphere import standard_density
from cpas_bayes.physics.inflation import below_previous_code, decay_code, parachute_drag_area, parachute_stage_law

LOGGER_SCENARIOS = ("logger-drop", "logger-drogue", "logger-main", "logger-attitude")
SI = unit_system("SI")
G0 = STANDARD_GRAVITY
DECAY, BELOW_PREVIOUS = "linear", "drop"   # the stage-law options synth.py simulates with
ADDED_MASS_STEP = 1e-4                     # s, half the span of dCDS/dt's central difference (added mass)
MAX_STEP = 1e-3                            # s, RK4 step bound (halving it moves the peak G by < 0.1 %)


@dataclass(frozen=True)
class LoggerTruth:
    """Everything a logger test is simulated from, SI; angles in degrees, accelerations in g."""

    scenario: str
    duration: float              # s simulated after release
    vehicle_weight: float        # W_V, N
    vehicle_cds: float           # CDS_V, m²
    chutes: tuple[ChuteTruth, ...]
    airspeed_0: float            # |v_a| at release, m/s
    flight_path_angle_0: float   # air-relative γ0, deg (negative below the horizon)
    heading_0: float             # air-relative ψ0, deg from north toward east
    altitude_0: float            # m
    wind: WindProfile            # the stated profile (what the bundle says)
    wind_north: float            # true − stated, m/s (one offset for the whole profile)
    wind_east: float
    accel_scale: float
    accel_bias: float            # g
    accel_sigma: float           # σ_G, g
    accel_rate: float            # r_a, Hz
    gnss_rate: float             # r_g, Hz
    gnss_latency: float          # L, s
    gnss_sigma_horizontal: float  # σ_vh, m/s
    gnss_sigma_up: float         # σ_vv, m/s
    altitude_sigma: float        # σ_h, m
    vehicle_weight_sigma: float  # the stated sigmas of the bundle's metadata
    vehicle_cds_sigma: float
    parachute_weight_sigma: float
    atmosphere: DensityProfile | None = field(default=None)   # None: the 1976 standard atmosphere
    attitude: AttitudeTruth | None = field(default=None)      # given: body axes with attitude in place of G
    # Canopy breathing after each stage's peak (effects.breathing_factor): amplitude, Hz, damping ratio;
    # amplitude 0 is none.
    breathing: tuple[float, float, float] = (0.0, 1.0, 0.0)
    added_mass: float = 0.0      # k_a of Eq. A1 flown in the dynamics (synth_logger_effects); 0 is none

    @property
    def total_weight(self):
        return self.vehicle_weight + sum(c.weight for c in self.chutes)

    def true_wind(self) -> WindProfile:
        """The wind the simulation flies through: the stated profile shifted by the offsets."""
        w = self.wind
        return WindProfile(np.asarray(w.altitude, float), np.asarray(w.north, float) + self.wind_north,
                           np.asarray(w.east, float) + self.wind_east, w.sigma)


def _scenario(name):
    if name not in SCENARIOS:
        raise ValueError(f"unknown logger scenario {name!r}; use one of {', '.join(LOGGER_SCENARIOS)}")
    return SCENARIOS[name]


def _draw_wind(altitude0, drop, rng):
    """A stated profile over [altitude0 − drop, altitude0 + 100 m]: bounded components, bounded shear."""
    levels = np.linspace(max(altitude0 - drop, 0.0), altitude0 + 100.0, int(rng.integers(WIND_LEVELS[0],
                                                                                          WIND_LEVELS[1] + 1)))
    gap = levels[1] - levels[0]
    components = []
    for _ in range(2):
        v = np.empty(len(levels))
        v[-1] = rng.uniform(-WIND_LIMIT, WIND_LIMIT)
        for i in range(len(levels) - 2, -1, -1):   # clipping is 1-Lipschitz: the shear bound survives it
            v[i] = np.clip(v[i + 1] + rng.uniform(-1.0, 1.0) * WIND_SHEAR * gap, -WIND_LIMIT, WIND_LIMIT)
        components.append(v)
    return WindProfile(levels, components[0], components[1], float(rng.uniform(*WIND_SIGMA)))


def draw_logger_truth(scenario: str, rng: np.random.Generator) -> LoggerTruth:
    """Draw a logger test's true parameters for ``scenario`` (one of :data:`LOGGER_SCENARIOS`)."""
    spec = _scenario(scenario)

    def uniform(bounds):
        return float(rng.uniform(*bounds))

    airspeed0, gamma0, heading0 = uniform(spec["airspeed0"]), uniform(spec["gamma0_deg"]), uniform((0.0, 360.0))
    altitude0 = uniform(spec["altitude0"])
    diameter = uniform(spec["diameter"])
    area = math.pi * diameter**2 / 4
    cds_o = [uniform(spec["cd_o"]) * area for _ in spec["ids"]]
    weights = [uniform(spec["canopy_loading"]) * area for _ in spec["ids"]]
    low, high = spec["vehicle_weight"]
    if spec["descent"] is not None:   # W ≈ ½ρ0·v_d²·Σ CDS_o, within the scenario's range
        drag = 0.5 * float(standard_density(0.0)) * sum(cds_o)
        low, high = max(low, drag * spec["descent"][0] ** 2), min(high, drag * spec["descent"][1] ** 2)
        low = min(low, high)
    vehicle_weight = float(rng.uniform(low, high))
    vehicle_cds = (uniform(spec["vehicle_cds"]) if spec["vehicle_cds"] is not None
                   else vehicle_weight / uniform(spec["vehicle_loading"]))
    first = uniform(spec["first"])
    chutes = []
    for pid, cds, weight in zip(spec["ids"], cds_o, weights):
        t1 = first + float(rng.uniform(0.0, spec["jitter"]))
        stages = []
        for k, label in enumerate(spec["labels"]):
            finite = spec["ck"][k] is None
            stages.append(StageTruth(
                label=label, eps=1.0 if spec["eps"][k] is None else uniform(spec["eps"][k]),
                start=t1 if k == 0 else t1 + uniform(spec["after"][k - 1]), n_p=uniform(spec["n_p"][k]),
                expopen=uniform(spec["expopen"][k]), ck=1.0 if finite else uniform(spec["ck"][k]),
                tk=0.0 if finite else uniform(spec["tk"][k])))
        chutes.append(ChuteTruth(id=pid, kind=spec["kind"], inflation=spec["inflation"], diameter=diameter,
                                 weight=weight, cds_o=cds, stages=tuple(stages)))
    wind = _draw_wind(altitude0, spec["drop"], rng)
    truth = LoggerTruth(
        scenario=scenario, duration=spec["duration"], vehicle_weight=vehicle_weight, vehicle_cds=vehicle_cds,
        chutes=tuple(chutes), airspeed_0=airspeed0, flight_path_angle_0=gamma0, heading_0=heading0,
        altitude_0=altitude0, wind=wind, wind_north=float(rng.normal(0.0, wind.sigma)),
        wind_east=float(rng.normal(0.0, wind.sigma)), accel_scale=1.0 + float(rng.normal(0.0, ACCEL_SCALE_SIGMA)),
        accel_bias=float(rng.normal(0.0, ACCEL_BIAS_SIGMA)), accel_sigma=uniform(ACCEL_NOISE),
        accel_rate=float(rng.choice(ACCEL_RATES)), gnss_rate=float(rng.choice(GNSS_RATES)),
        gnss_latency=uniform(LATENCY), gnss_sigma_horizontal=uniform(GNSS_SIGMA_H),
        gnss_sigma_up=uniform(GNSS_SIGMA_V), altitude_sigma=uniform(ALTITUDE_SIGMA),
        vehicle_weight_sigma=spec["weight_sigma"], vehicle_cds_sigma=spec["cds_sigma"],
        parachute_weight_sigma=spec["parachute_weight_sigma"])
    # drawn last: the other scenarios' draws stay as they were
    return replace(truth, attitude=draw_attitude_truth(spec["attitude"], rng)) if "attitude" in spec else truth


# ---------------------------------------------------------------------------
# the integrator (compiled: 20–45 s at 1 ms is 10⁵ right-hand sides)

@numba.njit(cache=True)
def _drag(t, y, v_start, law, body, dy, cds, scratch):
    """Fill ``dy`` (7,) with dy/dt and ``cds`` (P,) with the canopies' drag areas at (t, y); returns G_true.

    ``law`` = (stage_par (6, P, K), chute_par (2, P), n_stages (P,), option codes (2,)) as made by
    :func:`_stage_arrays`; ``body`` = (log ρ every DENSITY_GRID m, wind table (3, L), [h of the first
    log ρ, mass, CDS_V, breathing amplitude, Hz and damping ratio, added-mass k_a]).
    """
    stage_par, chute_par, n_stages, codes = law
    log_rho, wind, constants = body
    rho_base, mass, cds_v = constants[0], constants[1], constants[2]
    amplitude, omega, damping = constants[3], 2.0 * math.pi * constants[4], constants[5]
    k_a = constants[6]
    total = cds_v
    x = min(max((y[2] - rho_base) / DENSITY_GRID, 0.0), log_rho.shape[0] - 1.000001)
    i = int(x)
    rho = math.exp(log_rho[i] + (x - i) * (log_rho[i + 1] - log_rho[i]))
    rho_rate = rho * (log_rho[i + 1] - log_rho[i]) / DENSITY_GRID * y[5]   # dρ/dh · dh/dt
    m_a, m_a_rate = 0.0, 0.0
    for p in range(cds.shape[0]):
        points = 1 if k_a == 0.0 else 3    # with added mass also t ∓ δ: dCDS/dt by central difference
        scratch[0, 0] = t
        if points == 3:
            scratch[0, 0], scratch[0, 1], scratch[0, 2] = t - ADDED_MASS_STEP, t, t + ADDED_MASS_STEP
        scratch[1, :points] = 0.0   # the stage law writes only bins inside a stage
        parachute_stage_law(scratch[0, :points], stage_par[0, p], stage_par[1, p], chute_par[0, p],
                            chute_par[1, p], stage_par[2, p], stage_par[3, p], stage_par[4, p], stage_par[5, p],
                            v_start[p], n_stages[p], codes[0], codes[1], True, True, scratch[1, :points],
                            scratch[2], scratch[3], scratch[4], scratch[5])
        if points == 1:
            cds[p] = scratch[1, 0]
        else:
            area = max(scratch[1, 1], 0.0)
            cds[p] = scratch[1, 1]
            rate = (scratch[1, 2] - scratch[1, 0]) / (2.0 * ADDED_MASS_STEP)
            m_a += k_a * rho * area**1.5
            m_a_rate += k_a * (rho_rate * area**1.5 + 1.5 * rho * math.sqrt(area) * rate)
        if amplitude != 0.0:   # breathing: τ from the peak (start + t_fp, scratch[3]) of the active stage
            active = -1
            for k in range(n_stages[p]):
                if stage_par[0, p, k] <= t:
                    active = k
            if active >= 0:
                tau = t - stage_par[0, p, active] - scratch[3, active]
                if tau >= 0.0:
                    cds[p] *= 1.0 + amplitude * math.exp(-damping * omega * tau) * math.sin(
                        omega * math.sqrt(1.0 - damping * damping) * tau)
        total += cds[p]
    van = y[3] - np.interp(y[2], wind[0], wind[1])
    vae = y[4] - np.interp(y[2], wind[0], wind[2])
    vau = y[5]
    speed = math.sqrt(van * van + vae * vae + vau * vau)
    drag = 0.5 * rho * speed * speed * total
    per_speed = drag / (mass * speed) if speed > 0.0 else 0.0
    dy[0], dy[1], dy[2] = y[3], y[4], y[5]
    dy[3] = -per_speed * van
    dy[4] = -per_speed * vae
    dy[5] = -per_speed * vau - G0
    dy[6] = drag / (mass * G0)
    if m_a > 0.0 and speed > 0.0:
        # Eq. A3 along the air velocity; the sensed force gains the momentum term d(m_a·V)/dt
        sin_gamma = vau / speed
        along = (-drag - mass * G0 * sin_gamma - speed * m_a_rate) / (mass + m_a)
        change = along - (-drag / mass - G0 * sin_gamma)
        dy[3] += change * van / speed
        dy[4] += change * vae / speed
        dy[5] += change * vau / speed
        dy[6] = (drag + speed * m_a_rate + m_a * along) / (mass * G0)
    return dy[6]


@numba.njit(cache=True)
def _airspeed(y, wind):
    van = y[3] - np.interp(y[2], wind[0], wind[1])
    vae = y[4] - np.interp(y[2], wind[0], wind[2])
    return math.sqrt(van * van + vae * vae + y[5] * y[5])


@numba.njit(cache=True)
def _integrate(h, n_steps, y0, v_start, law, body):
    """RK4 from t = 0 to n_steps·h; returns the states, their derivatives, G_true and CDS_i on the grid.

    ``v_start`` (P, K) is filled with |v_a| at each stage start as the integration passes it (a step
    holding a start is split there); starts at or before 0 take |v_a(0)|.
    """
    stage_par, n_stages, wind = law[0], law[2], body[1]
    P, K = stage_par.shape[1], stage_par.shape[2]
    states, rates = np.empty((n_steps + 1, 7)), np.empty((n_steps + 1, 7))
    load, drag_areas = np.empty(n_steps + 1), np.empty((n_steps + 1, P))
    recorded = np.zeros((P, K), dtype=np.bool_)
    for p in range(P):
        for k in range(n_stages[p]):
            v_start[p, k] = _airspeed(y0, wind)   # placeholder until recorded: never 0 (t_f divides by it)
            recorded[p, k] = stage_par[0, p, k] <= 0.0
    y, dy, cds, scratch = y0.copy(), np.empty(7), np.empty(P), np.zeros((6, max(K, 3)))
    k1, k2, k3, k4, tmp = np.empty(7), np.empty(7), np.empty(7), np.empty(7), np.empty(7)
    for n in range(n_steps + 1):
        t = n * h
        load[n] = _drag(t, y, v_start, law, body, dy, cds, scratch)
        states[n, :] = y
        rates[n, :] = dy
        drag_areas[n, :] = cds
        if n == n_steps:
            break
        t_end = (n + 1) * h
        while t < t_end:
            stop = t_end   # the earliest stage start still to come in (t, t_end]
            for p in range(P):
                for k in range(n_stages[p]):
                    if not recorded[p, k] and t < stage_par[0, p, k] < stop:
                        stop = stage_par[0, p, k]
            dt = stop - t
            if t == n * h:   # the grid point's derivative is k1 (stage starts are recorded only after a step)
                k1[:] = dy
            else:
                _drag(t, y, v_start, law, body, k1, cds, scratch)
            for i in range(7):
                tmp[i] = y[i] + 0.5 * dt * k1[i]
            _drag(t + 0.5 * dt, tmp, v_start, law, body, k2, cds, scratch)
            for i in range(7):
                tmp[i] = y[i] + 0.5 * dt * k2[i]
            _drag(t + 0.5 * dt, tmp, v_start, law, body, k3, cds, scratch)
            for i in range(7):
                tmp[i] = y[i] + dt * k3[i]
            _drag(stop, tmp, v_start, law, body, k4, cds, scratch)
            for i in range(7):
                y[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
            t = stop
            for p in range(P):
                for k in range(n_stages[p]):
                    if not recorded[p, k] and stage_par[0, p, k] <= t:
                        v_start[p, k] = _airspeed(y, wind)
                        recorded[p, k] = True
    return states, rates, load, drag_areas


@dataclass(frozen=True)
class LoggerTrajectory:
    """Noise-free histories on the integration grid, SI; ``state_at`` interpolates between grid points."""

    time: np.ndarray            # (N,) s
    position: np.ndarray        # (N, 3) north, east, up (altitude), m
    velocity: np.ndarray        # (N, 3) ground velocity, m/s
    acceleration: np.ndarray    # (N, 3) m/s²
    load_factor: np.ndarray     # (N,) G_true, g
    load_integral: np.ndarray   # (N,) ∫ G_true dt, g·s
    cds: np.ndarray             # (P, N) each canopy's drag area, m²
    wind: np.ndarray            # (N, 2) true wind (north, east) at the vehicle, m/s
    density: np.ndarray         # (N,) kg/m³
    stage_airspeed: np.ndarray  # (P, K) V_i, m/s
    timing: tuple               # per canopy, the stage law's StageTiming with the recorded V_i
    total_weight: float         # W_T, N

    @property
    def air_velocity(self):
        return self.velocity - np.column_stack([self.wind, np.zeros(len(self.time))])

    @property
    def qbar(self):
        return 0.5 * self.density * np.sum(self.air_velocity**2, axis=1)

    def state_at(self, t):
        """(position (n, 3), velocity (n, 3)) at times ``t`` (n,), cubic Hermite on the grid."""
        return (_hermite(t, self.time, self.position, self.velocity),
                _hermite(t, self.time, self.velocity, self.acceleration))

    def mean_load_factor(self, t, window):
        """Box-car average of G_true over [t − window, t] (exact up to the integration error)."""
        integral = self.load_integral[:, None]
        rate = self.load_factor[:, None]
        t = np.asarray(t, float)
        return ((_hermite(t, self.time, integral, rate) - _hermite(t - window, self.time, integral, rate))[:, 0]
                / window)


def _hermite(t, grid, y, dy):
    """Cubic Hermite interpolation of y (N, m) with slopes dy at times t (n,) inside the uniform grid."""
    t = np.asarray(t, float)
    h = grid[1] - grid[0]
    i = np.clip(np.floor((t - grid[0]) / h).astype(int), 0, len(grid) - 2)
    s = ((t - grid[i]) / h)[:, None]
    return ((2 * s**3 - 3 * s**2 + 1) * y[i] + (s**3 - 2 * s**2 + s) * h * dy[i]
            + (-2 * s**3 + 3 * s**2) * y[i + 1] + (s**3 - s**2) * h * dy[i + 1])


def _stage_arrays(truth):
    """(6, P, K) start, CDS_i, n_p, expopen, C_k, t_k; (2, P) CDS_o, D_o; (P,) stage counts."""
    P, K = len(truth.chutes), max(len(c.stages) for c in truth.chutes)
    stage_par = np.zeros((6, P, K))
    stage_par[3] = stage_par[4] = 1.0   # unused slots of a canopy with fewer stages: harmless values
    for p, c in enumerate(truth.chutes):
        for k, s in enumerate(c.stages):
            stage_par[:, p, k] = (s.start, s.eps * c.cds_o, s.n_p, s.expopen, s.ck, s.tk)
    chute_par = np.array([[c.cds_o for c in truth.chutes], [c.diameter for c in truth.chutes]])
    return stage_par, chute_par, np.array([len(c.stages) for c in truth.chutes], dtype=np.int64)


def integration_step(truth: LoggerTruth, step: float = MAX_STEP) -> float:
    """The RK4 step: the largest ≤ ``step`` that divides the accelerometer's sample interval."""
    period = 1.0 / truth.accel_rate
    return period / math.ceil(period / step - 1e-9)


def simulate_logger_trajectory(truth: LoggerTruth, step: float = MAX_STEP) -> LoggerTrajectory:
    """Integrate ``truth`` from release for ``truth.duration`` s with RK4 steps ≤ ``step``."""
    h = integration_step(truth, step)
    n_steps = int(math.ceil(truth.duration / h - 1e-9))
    wind = truth.true_wind()
    wind_table = np.ascontiguousarray([wind.altitude, wind.north, wind.east], dtype=float)
    gamma, psi = math.radians(truth.flight_path_angle_0), math.radians(truth.heading_0)
    w_n, w_e = (float(v) for v in wind.at(truth.altitude_0))
    v_air = truth.airspeed_0 * np.array([math.cos(gamma) * math.cos(psi), math.cos(gamma) * math.sin(psi),
                                          math.sin(gamma)])
    y0 = np.array([0.0, 0.0, truth.altitude_0, v_air[0] + w_n, v_air[1] + w_e, v_air[2], 0.0])
    # Density table from well below anything flown to above the release.
    heights = np.arange(-1_000.0, truth.altitude_0 + 1_000.0, DENSITY_GRID)
    rho = truth.atmosphere(heights) if truth.atmosphere is not None else standard_density(heights)
    stage_par, chute_par, n_stages = _stage_arrays(truth)
    v_start = np.zeros(stage_par.shape[1:])
    codes = np.array([decay_code(DECAY), below_previous_code(BELOW_PREVIOUS)], dtype=np.int64)
    mass = truth.total_weight / G0
    body = (np.log(rho), wind_table, np.array([heights[0], mass, truth.vehicle_cds, *truth.breathing,
                                               truth.added_mass]))
    states, rates, load, drag_areas = _integrate(h, n_steps, y0, v_start, (stage_par, chute_par, n_stages, codes),
                                                 body)
    time = h * np.arange(n_steps + 1)
    timing = tuple(parachute_drag_area(time[-1:], *(stage_par[j, p, :n] for j in range(2)), chute_par[0, p],
                                       chute_par[1, p], *(stage_par[j, p, :n] for j in range(2, 6)),
                                       v_start[p, :n], decay=DECAY, below_previous=BELOW_PREVIOUS)[1]
                   for p, n in enumerate(n_stages))
    altitude = states[:, 2]
    return LoggerTrajectory(
        time=time, position=states[:, :3], velocity=states[:, 3:6], acceleration=rates[:, 3:6],
        load_factor=load, load_integral=states[:, 6], cds=drag_areas.T.copy(),
        wind=np.column_stack(wind.at(altitude)), density=np.exp(np.interp(altitude, heights, np.log(rho))),
        stage_airspeed=v_start, timing=timing, total_weight=truth.total_weight)


# ---------------------------------------------------------------------------
# the logged record

def _stated_stages(chute, rng, first_row, last_row):
    stages, previous = [], -math.inf
    for k, s in enumerate(chute.stages):
        sigma = FIRST_START_SIGMA if k == 0 else LATER_START_SIGMA
        start = round(float(np.clip(s.start + rng.normal(0.0, sigma), first_row, last_row)), 3)
        start = max(start, previous + 0.01)   # noise must not reorder the stated stages (a reader refuses that)
        stages.append(Stage(label=s.label, start=start, start_sigma=sigma))
        previous = start
    return tuple(stages)


def simulate_logger_test(truth: LoggerTruth, rng: np.random.Generator, name: str | None = None,
                         step: float = MAX_STEP) -> tuple[FlightTest, dict]:
    """Simulate ``truth`` and its loggers; return the test (SI) and truth.json's dict.

    ``rng`` supplies every draw, in a fixed order: stated vehicle weight and CDS_V, stated stage
    starts, accelerometer noise, GNSS velocity noise (north, east, up per sample), altitude noise, and with
    attitude the three axes' noise per reading.
    """
    trajectory = simulate_logger_trajectory(truth, step)
    t_acc, t_gnss = sample_times(truth)
    # Rows: the union of both sample grids, matched on integer microseconds (exact for these rates).
    key_acc, key_gnss = np.round(t_acc * 1e6).astype(np.int64), np.round(t_gnss * 1e6).astype(np.int64)
    keys = np.union1d(key_acc, key_gnss)
    rows_acc, rows_gnss = np.searchsorted(keys, key_acc), np.searchsorted(keys, key_gnss)
    time = keys / 1e6

    stated_weight = truth.vehicle_weight + float(rng.normal(0.0, truth.vehicle_weight_sigma))
    stated_cds = max(truth.vehicle_cds + float(rng.normal(0.0, truth.vehicle_cds_sigma)), 0.0)
    stated_stages = [_stated_stages(c, rng, time[0], time[-1]) for c in truth.chutes]
    g_noise = rng.normal(0.0, truth.accel_sigma, size=len(t_acc))
    v_noise = rng.normal(0.0, 1.0, size=(len(t_gnss), 3)) * np.array(
        [truth.gnss_sigma_horizontal, truth.gnss_sigma_horizontal, truth.gnss_sigma_up])
    h_noise = rng.normal(0.0, truth.altitude_sigma, size=len(t_gnss))

    def blank():
        return np.full(len(time), np.nan)

    data = {"time": time}
    columns = ("G", "G_sigma", "v_north", "v_east", "v_up", "v_north_sigma", "v_east_sigma", "v_up_sigma",
               "altitude", "altitude_sigma")
    data.update({c: blank() for c in columns})
    averaged = trajectory.mean_load_factor(t_acc, 1.0 / truth.accel_rate)
    data["G"][rows_acc] = truth.accel_scale * averaged + truth.accel_bias + g_noise
    data["G_sigma"][rows_acc] = truth.accel_sigma
    position, velocity = trajectory.state_at(t_gnss - truth.gnss_latency)
    sigmas = (truth.gnss_sigma_horizontal, truth.gnss_sigma_horizontal, truth.gnss_sigma_up)
    for i, (c, sigma) in enumerate(zip(("v_north", "v_east", "v_up"), sigmas)):
        data[c][rows_gnss] = velocity[:, i] + v_noise[:, i]
        data[f"{c}_sigma"][rows_gnss] = sigma
    data["altitude"][rows_gnss] = position[:, 2] + h_noise
    data["altitude_sigma"][rows_gnss] = truth.altitude_sigma
    if truth.attitude is not None:
        write_body_axes(data, truth, trajectory, t_acc, rows_acc, rng.normal(0.0, truth.accel_sigma, (len(t_acc), 3)))

    parachutes = tuple(Parachute(id=c.id, kind=c.kind, inflation=c.inflation, diameter=c.diameter, weight=c.weight,
                                 weight_sigma=truth.parachute_weight_sigma, stages=stages)
                       for c, stages in zip(truth.chutes, stated_stages))
    vehicle = Vehicle(weight=stated_weight, weight_sigma=truth.vehicle_weight_sigma, cds=stated_cds,
                      cds_sigma=truth.vehicle_cds_sigma)
    # only the accelerometer's rate: the model takes the receiver's samples as instantaneous (data.air_data)
    air_data = AirDataSpec(wind=truth.wind, atmosphere=truth.atmosphere, rates={"G": truth.accel_rate})
    test = FlightTest(name=name or f"SYN-{truth.scenario}", phase=truth.scenario, units=SI, vehicle=vehicle,
                      parachutes=parachutes, data=pd.DataFrame(data), air_data=air_data)
    return test, logger_truth_document(truth, trajectory)


def logger_streams(seed: int):
    """Independent generators for the truth and for the stated metadata and noise of one seed."""
    truth_seq, noise_seq = np.random.SeedSequence(seed).spawn(2)
    return np.random.default_rng(truth_seq), np.random.default_rng(noise_seq)


def synthesize_logger(scenario: str, seed: int, name: str | None = None, effect: str = "none", magnitude=None):
    """Draw and simulate one logger test from a seed, with a hidden ``effect`` (:mod:`cpas_bayes.data.
    synth_logger_effects`): (FlightTest, truth dict)."""
    truth_rng, noise_rng = logger_streams(seed)
    truth = draw_logger_truth(scenario, truth_rng)
    breathing = draw_breathing(effect, scenario, truth.chutes[0].diameter, effect_stream(seed), magnitude)
    truth = replace(truth, breathing=breathing, added_mass=draw_added_mass(effect, effect_stream(seed), magnitude))
    suffix = "" if effect == "none" else f"-{effect}"
    return simulate_logger_test(truth, noise_rng, name=name or f"SYN-{scenario}-{seed}{suffix}")


def write_logger_synthetic(scenario: str, seed: int, out, effect: str = "none", magnitude=None) -> Path:
    """Simulate a logger test and write it as a bundle with its truth.json beside it; returns the folder."""
    test, truth = synthesize_logger(scenario, seed, effect=effect, magnitude=magnitude)
    return write_bundle(test, Path(out), extra_files={"truth.json": json.dumps(truth, indent=1) + "\n"})

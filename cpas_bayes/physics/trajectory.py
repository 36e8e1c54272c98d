"""Planar point-mass descent under a cluster of inflating parachutes, batched.

Integrates B parameter sets at once (Monte Carlo runs, posterior draws) with a
fixed-step classical Runge–Kutta scheme; numpy arrays carry the batch, the
only Python loop is over time steps. Everything is SI; angles in radians.

Dynamics (seed Eq. 1–3 with the parachutes moving with the vehicle; no wind,
so airspeed = inertial speed)::

    m_T·dV/dt = −q̄·(PRF·Σ CDS_i + CDS_V) − W_T·sin γ        m_T = W_T/g
    dγ/dt     = −g·cos γ / V
    dh/dt     = V·sin γ
    W_T       = W_V + Σ W_p,i,   q̄ = ½·ρ(h)·V²

γ is negative below the horizon; it turns down towards −90° and never passes
it (cos γ is clipped at 0, γ at −π/2), so a long Main phase ends hanging
straight down as in the example bundles, and a run started vertical stays so.

Outputs per sample: the sensed load factor (Eq. 5)
G = −(dV/dt + g·sin γ)/g, which equals q̄·(PRF·Σ CDS_i + CDS_V)/W_T (Eq. 3)
without added mass, and the riser tension of each parachute (Eq. 10)
F_i = PRF·q̄·CDS_i − W_p,i·G.

Drag areas come from :func:`cpas_bayes.physics.inflation.parachute_drag_area`,
evaluated inside the integration: the airspeed V_i that sets each stage's fill
time (Eq. 14) is the simulated airspeed at that run's own stage start,
recorded as the integration passes it (starts differ per run and parachute).

Optional extensions (see :mod:`cpas_bayes.physics.effects` for the equations):
``added_mass_k`` adds the enclosed/apparent air mass m_a = k_a·ρ·CDS^(3/2)
and its momentum term to the dynamics and to G and F_i (Eq. A2–A4);
``added_mass_exponent`` and ``added_mass_lag`` change its form (Eq. A1', the
carried mass as an extra state lagging A1'; defaults give Eq. A1 exactly);
``breathing`` multiplies every canopy's drag area by a damped oscillation
excited at each stage's peak drag area (superposed, so the drag area stays
continuous across disreefs).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from cpas_bayes.physics.atmosphere import standard_density
from cpas_bayes.physics.effects import (added_mass, added_mass_acceleration, added_mass_momentum_rate, added_mass_rate,
                      breathing_factor, riser_tension, sensed_load_factor)
from cpas_bayes.physics.inflation import StageTiming, below_previous_code, decay_code, parachute_drag_area
from cpas_bayes.core.units import STANDARD_GRAVITY

# Half-width of the central differences that give dCDS/dt and dρ/dh for the
# added-mass rate: small against any fill time, large against round-off.
_TIME_DIFFERENCE = 1e-5  # s
_ALTITUDE_DIFFERENCE = 0.5  # m


@dataclass(frozen=True)
class VehicleState0:
    """Initial state of each run, arrays (B,) or scalars."""

    airspeed: np.ndarray           # V0, m/s
    flight_path_angle: np.ndarray  # γ0, rad, negative below the horizon
    altitude: np.ndarray           # h0, m


@dataclass(frozen=True)
class VehicleProperties:
    """The suspended vehicle without canopies, arrays (B,) or scalars."""

    weight: np.ndarray  # W_V, N
    cds: np.ndarray     # (C_D S)_V, m²


@dataclass(frozen=True)
class ClusterParameters:
    """Every parachute's inflation parameters.

    Per stage arrays broadcast to (B, P, K) (P parachutes, K stages each, in
    time order); per parachute arrays to (B, P). A batch axis may be left out
    where a value is shared by all runs. ``fill_constant`` says whether
    ``n_fill`` holds n_p (Eq. 17, the default) or n (Eq. 14).
    """

    start: np.ndarray       # stage start times t_i, s
    cds_stage: np.ndarray   # steady drag area of each stage CDS_i = eps_i·CDS_o, m²
    n_fill: np.ndarray      # n_p (or n), dimensionless
    expopen: np.ndarray     # growth shape exponent
    ck: np.ndarray          # over-inflation factor C_k (1 for finite mass)
    tk: np.ndarray          # decay time after the peak t_k, s
    cds_o: np.ndarray       # full-open drag area, m²
    diameter: np.ndarray    # nominal diameter D_o, m
    weight: np.ndarray      # W_p,i, N
    fill_constant: str = "n_p"
    ids: tuple[str, ...] | None = None

    @property
    def n_parachutes(self):
        return np.shape(self.start)[-2]

    @property
    def n_stages(self):
        return np.shape(self.start)[-1]


@dataclass(frozen=True)
class BreathingParameters:
    """Canopy breathing (effects.breathing_factor); arrays broadcast to (B, P).

    A per-run value needs its parachute axis: ``amplitude[:, None]``.
    """

    amplitude: np.ndarray
    frequency_hz: np.ndarray
    damping_ratio: np.ndarray


@dataclass(frozen=True)
class SimulationOptions:
    """How to integrate and which extensions to switch on."""

    dt: float = 0.01                 # output sample interval, s
    substeps: int = 1                # RK4 steps per sample
    decay: str = "linear"            # post-peak decay shape of the stage law (inflation.DECAY_SHAPES)
    below_previous: str = "drop"     # a stage not above the held drag area: "drop" to its own, "hold" it (CML)
    prf: float = 1.0                 # pressure recovery fraction on the canopies
    added_mass_k: object = None      # k_a, scalar or (B,) or (B, P); None = off
    added_mass_exponent: float = 1.5  # p of m_a ∝ CDS^p (effects Eq. A1'); 1.5 = Eq. A1
    added_mass_lag: float = 0.0      # τ_m, s: m_a follows A1' through a first-order lag; 0 = at once
    breathing: BreathingParameters | None = None
    gravity: float = STANDARD_GRAVITY
    density: Callable = field(default=standard_density)  # ρ(h) in kg/m³, vectorised


@dataclass(frozen=True)
class TrajectoryResult:
    """Simulated histories, SI. Time last; B runs, P parachutes, K stages."""

    time: np.ndarray               # (T,) s
    airspeed: np.ndarray           # (B, T) m/s
    flight_path_angle: np.ndarray  # (B, T) rad
    altitude: np.ndarray           # (B, T) m
    density: np.ndarray            # (B, T) kg/m³
    qbar: np.ndarray               # (B, T) Pa
    acceleration: np.ndarray       # (B, T) dV/dt, m/s²
    load_factor: np.ndarray        # (B, T) G, dimensionless (in g)
    cds: np.ndarray                # (B, P, T) each canopy's drag area (breathing included, PRF not), m²
    tension: np.ndarray            # (B, P, T) riser tension F_i along the flight path, N
    added_mass: np.ndarray         # (B, P, T) m_a,i, kg (zeros when off)
    momentum_rate: np.ndarray      # (B, P, T) d(m_a,i·V)/dt, N (zeros when off)
    stage_airspeed: np.ndarray     # (B, P, K) V_i used for each stage's fill time, m/s
    timing: StageTiming            # (B, P, K) fields: t_f, t_fp, n, n_p, cds_start
    total_weight: np.ndarray       # (B,) W_T, N
    vehicle_cds: np.ndarray        # (B,) CDS_V, m²
    parachute_weight: np.ndarray   # (B, P) W_p,i, N
    stage_start: np.ndarray        # (B, P, K) the stage starts t_i that were simulated, s
    peak_tension: np.ndarray       # (B, P) max F_i, located between samples (simulate's refine_peaks), N
    peak_total_tension: np.ndarray  # (B,) max Σ F_i, likewise, N
    prf: float = 1.0

    @property
    def cds_total(self):
        """Σ CDS_i (B, T), m²."""
        return self.cds.sum(axis=1)

    @property
    def total_tension(self):
        """Σ F_i (B, T), N."""
        return self.tension.sum(axis=1)

    @property
    def peak_time(self):
        """Absolute time of each stage's peak drag area t_i + t_fp (B, P, K), s."""
        return self.stage_start + self.timing.t_fp


def _as_batched(value, trailing_ndim, batch):
    """Broadcast ``value`` to batch + its trailing shape."""
    value = np.asarray(value, float)
    trailing = value.shape[value.ndim - trailing_ndim:] if trailing_ndim else ()
    return np.broadcast_to(value, batch + trailing).astype(float, copy=True)


def _batch_shape(state0, vehicle, cluster):
    shapes = [np.shape(state0.airspeed), np.shape(state0.flight_path_angle), np.shape(state0.altitude),
              np.shape(vehicle.weight), np.shape(vehicle.cds)]
    for name in ("start", "cds_stage", "n_fill", "expopen", "ck", "tk"):
        shapes.append(np.shape(getattr(cluster, name))[:-2])
    for name in ("cds_o", "diameter", "weight"):
        shape = np.shape(getattr(cluster, name))
        shapes.append(shape[:-1] if len(shape) >= 1 else ())
    batch = np.broadcast_shapes(*shapes)
    if len(batch) > 1:
        raise ValueError(f"one batch axis at most, got batch shape {batch}")
    return batch if batch else (1,)


class _Cluster:
    """The cluster's parameters broadcast to (B, P, K) / (B, P) and its drag-area law."""

    def __init__(self, cluster, batch, options):
        self.start = _as_batched(cluster.start, 2, batch)
        shape = self.start.shape
        self.stage = {name: np.broadcast_to(np.asarray(getattr(cluster, name), float), shape).copy()
                      for name in ("cds_stage", "n_fill", "expopen", "ck", "tk")}
        per_chute = shape[:-1]
        self.cds_o = np.broadcast_to(np.asarray(cluster.cds_o, float), per_chute).copy()
        self.diameter = np.broadcast_to(np.asarray(cluster.diameter, float), per_chute).copy()
        self.weight = np.broadcast_to(np.asarray(cluster.weight, float), per_chute).copy()
        self.fill_constant = cluster.fill_constant
        self.decay = options.decay
        self.below_previous = options.below_previous
        self.breathing = None
        if options.breathing is not None:
            b = options.breathing
            # (B, P, 1, 1): broadcast against (B, P, K, n_times)
            self.breathing = tuple(np.broadcast_to(np.asarray(v, float), per_chute).copy()[..., None, None]
                                   for v in (b.amplitude, b.frequency_hz, b.damping_ratio))

    def drag_area(self, times, stage_airspeed):
        """CDS_i at ``times`` ((n,) or (B, 1, n)) given the recorded V_i: (B, P, n) and the timing."""
        cds, timing = parachute_drag_area(
            times, self.start, self.stage["cds_stage"], self.cds_o, self.diameter, self.stage["n_fill"],
            self.stage["expopen"], self.stage["ck"], self.stage["tk"], stage_airspeed,
            decay=self.decay, fill_constant=self.fill_constant, below_previous=self.below_previous)
        if self.breathing is not None:
            peak = (self.start + timing.t_fp)[..., None]                  # (B, P, K, 1)
            ringing = breathing_factor(np.asarray(times)[..., None, :] - peak, *self.breathing) - 1.0  # (B, P, K, n)
            cds = cds * (1.0 + ringing.sum(axis=-2))
        return cds, timing


def _air_state(density_of, altitude, climb_rate, with_rate):
    rho = density_of(altitude)
    if not with_rate:
        return rho, None
    gradient = (density_of(altitude + _ALTITUDE_DIFFERENCE)
                - density_of(altitude - _ALTITUDE_DIFFERENCE)) / (2 * _ALTITUDE_DIFFERENCE)
    return rho, gradient * climb_rate


class _Dynamics:
    """Right-hand side of the equations of motion and the derived channels."""

    def __init__(self, vehicle_weight, vehicle_cds, parachute_weight, options, cds_o):
        self.vehicle_cds = vehicle_cds
        self.cds_o = cds_o
        self.parachute_weight = parachute_weight
        self.total_weight = vehicle_weight + parachute_weight.sum(axis=-1)
        self.options = options
        self.k_a = None
        if options.added_mass_k is not None:
            k = np.asarray(options.added_mass_k, float)
            # (B,) per run or (B, P) per parachute
            self.k_a = np.broadcast_to(k[..., None] if k.ndim == 1 else k, parachute_weight.shape)
        if options.added_mass_lag < 0 or options.added_mass_exponent <= 0:
            raise ValueError("need added_mass_lag ≥ 0 and added_mass_exponent > 0")
        # With a lag the carried mass m_a (B, P) is a state of the integration.
        self.lagged = self.k_a is not None and options.added_mass_lag > 0

    def target_mass(self, cds, rho):
        """Eq. A1 / A1' at the current drag areas (B, P), kg."""
        return added_mass(cds, rho[:, None], self.k_a, self.options.added_mass_exponent, self.cds_o)

    def initial_mass(self, altitude, cds):
        """The carried mass at the start when it is a state (settled at A1'), else None."""
        return self.target_mass(cds, self.options.density(altitude)) if self.lagged else None

    def evaluate(self, airspeed, gamma, altitude, cds, cds_rate, mass=None):
        """Derivatives and channels at one time for all runs; cds (B, P); ``mass`` the lagged m_a state."""
        g = self.options.gravity
        climb = airspeed * np.sin(gamma)
        rho, rho_rate = _air_state(self.options.density, altitude, climb, self.k_a is not None)
        qbar = 0.5 * rho * airspeed**2
        drag_area = self.options.prf * cds.sum(axis=-1)
        if self.k_a is None:
            m_a = mass_rate = np.zeros_like(cds)
        elif self.lagged:
            m_a = mass
            mass_rate = (self.target_mass(cds, rho) - mass) / self.options.added_mass_lag
        else:
            m_a = self.target_mass(cds, rho)
            mass_rate = added_mass_rate(cds, cds_rate, rho[:, None], rho_rate[:, None], self.k_a,
                                        self.options.added_mass_exponent, self.cds_o)
        accel = added_mass_acceleration(qbar, drag_area, self.vehicle_cds, self.total_weight, gamma, airspeed,
                                        m_a.sum(axis=-1), mass_rate.sum(axis=-1), g)
        gamma_rate = -g * np.clip(np.cos(gamma), 0.0, None) / airspeed
        rates = (accel, gamma_rate, climb) + ((mass_rate,) if self.lagged else ())
        return rates, dict(density=rho, qbar=qbar, acceleration=accel, added_mass=m_a,
                                                mass_rate=mass_rate)

    def channels(self, airspeed, gamma, cds, aux):
        """G (Eq. 5) and F_i (Eq. 10 / A2) from the evaluated derivatives."""
        load_factor = sensed_load_factor(aux["acceleration"], gamma, self.options.gravity)
        momentum = added_mass_momentum_rate(aux["added_mass"], aux["mass_rate"], airspeed[:, None],
                                            aux["acceleration"][:, None])
        tension = riser_tension(aux["qbar"][:, None], cds, self.parachute_weight, load_factor[:, None],
                                prf=self.options.prf, momentum_rate=momentum)
        return load_factor, tension, momentum


def _drag_and_rate(chutes, times, stage_airspeed, with_rate):
    """CDS (B, P, n) at ``times`` ((n,) or (B, 1, n)); with the central-difference rate when needed."""
    if not with_rate:
        cds, timing = chutes.drag_area(times, stage_airspeed)
        return cds, None, timing
    n = np.shape(times)[-1]
    stacked = np.concatenate([times, times - _TIME_DIFFERENCE, times + _TIME_DIFFERENCE], axis=-1)
    values, timing = chutes.drag_area(stacked, stage_airspeed)
    cds, before, after = values[..., :n], values[..., n:2 * n], values[..., 2 * n:]
    return cds, (after - before) / (2 * _TIME_DIFFERENCE), timing


def _recording_steps(start, t0, h):
    """Step n during which each stage starts: start in (t_n, t_n + h]; −1 if at or before t0."""
    steps = np.ceil((start - t0) / h).astype(np.int64) - 1
    return np.where(start > t0, steps, -1)


class _DragAreaBlocks:
    """CDS at the RK4 midpoints and step ends, evaluated a block of steps at a time.

    Between stage starts the drag-area law depends on time only, so whole
    blocks of steps go through one call of ``parachute_drag_area``; a block
    ends where some run records a new stage airspeed V_i.
    """

    BLOCK_STEPS = 200

    def __init__(self, chutes, with_rate, t0, h, n_steps, record_steps):
        self.chutes, self.with_rate = chutes, with_rate
        self.t0, self.h, self.n_steps = t0, h, n_steps
        self.events = np.unique(record_steps[record_steps >= 0])
        self.first = self.stop = 0
        self.mid = self.end = self.mid_rate = self.end_rate = None

    def refresh(self, n, stage_airspeed):
        """Evaluate steps n… up to the next recording step (exclusive) or the block size."""
        later = self.events[self.events > n]
        stop = min(n + self.BLOCK_STEPS, self.n_steps, int(later[0]) if later.size else self.n_steps)
        steps = np.arange(n, stop)
        times = self.t0 + self.h * np.concatenate([steps + 0.5, steps + 1.0])
        cds, rate, _ = _drag_and_rate(self.chutes, times, stage_airspeed, self.with_rate)
        m = len(steps)
        self.mid, self.end = cds[..., :m], cds[..., m:]
        if rate is not None:
            self.mid_rate, self.end_rate = rate[..., :m], rate[..., m:]
        self.first, self.stop = n, stop

    def at(self, n, which):
        """CDS and its rate (or None) at step n's midpoint or end."""
        j = n - self.first
        values, rates = (self.mid, self.mid_rate) if which == "mid" else (self.end, self.end_rate)
        return values[..., j], (None if rates is None else rates[..., j])


def simulate(state0: VehicleState0, vehicle: VehicleProperties, cluster: ClusterParameters, duration: float,
             options: SimulationOptions = SimulationOptions(), t0: float = 0.0,
             refine_peaks: int = 10) -> TrajectoryResult:
    """Integrate B descents from ``t0`` for ``duration`` seconds.

    Samples every ``options.dt`` (T = round(duration/dt) + 1 samples),
    integrating with ``options.substeps`` RK4 steps per sample. A stage that
    starts at or before ``t0`` takes V0 as its V_i; one that starts inside a
    step takes the airspeed at its start, extrapolated from the step's start
    along dV/dt (error ~ h²·d²V/dt²).

    ``refine_peaks`` > 0 locates each peak tension between samples (the
    Drogue peaks are sharp corners that a 100 Hz record misses by up to a few
    per cent): the drag areas are re-evaluated exactly on a grid ``refine_peaks``
    times finer around the sampled maximum, with the state interpolated
    (cubic Hermite) between samples. Results in ``peak_tension``,
    ``peak_total_tension``.
    """
    decay_code(options.decay), below_previous_code(options.below_previous)  # refuse a bad option before any work
    if options.dt <= 0 or options.substeps < 1 or duration <= 0:
        raise ValueError("need dt > 0, substeps ≥ 1 and duration > 0")
    batch = _batch_shape(state0, vehicle, cluster)
    chutes = _Cluster(cluster, batch, options)
    dynamics = _Dynamics(_as_batched(vehicle.weight, 0, batch), _as_batched(vehicle.cds, 0, batch),
                         chutes.weight, options, chutes.cds_o)
    with_rate = dynamics.k_a is not None

    n_samples = int(round(duration / options.dt)) + 1
    time = t0 + options.dt * np.arange(n_samples)
    h = options.dt / options.substeps
    n_steps = (n_samples - 1) * options.substeps
    if dynamics.lagged and options.added_mass_lag < h:  # RK4 would go unstable on the stiff lag
        raise ValueError(f"added_mass_lag must be 0 or at least the RK4 step {h:g} s (more substeps)")

    airspeed = _as_batched(state0.airspeed, 0, batch)
    gamma = _as_batched(state0.flight_path_angle, 0, batch)
    altitude = _as_batched(state0.altitude, 0, batch)
    if np.any(airspeed <= 0):
        raise ValueError("initial airspeed must be positive")
    # Placeholder V_i for stages not reached yet: a stage is inactive before
    # its start, when the recorded airspeed replaces the placeholder.
    stage_airspeed = np.broadcast_to(airspeed[:, None, None], chutes.start.shape).copy()
    record_step = _recording_steps(chutes.start, t0, h)
    blocks = _DragAreaBlocks(chutes, with_rate, t0, h, n_steps, record_step)

    n_batch, n_chutes = chutes.weight.shape
    out = {name: np.empty((n_batch, n_samples)) for name in
           ("airspeed", "flight_path_angle", "altitude", "density", "qbar", "acceleration", "load_factor")}
    out.update({name: np.empty((n_batch, n_chutes, n_samples)) for name in
                ("cds", "tension", "added_mass", "momentum_rate")})

    def record(i, v, gam, alt, cds, aux):
        load_factor, tension, momentum = dynamics.channels(v, gam, cds, aux)
        for name, value in (("airspeed", v), ("flight_path_angle", gam), ("altitude", alt),
                            ("density", aux["density"]), ("qbar", aux["qbar"]),
                            ("acceleration", aux["acceleration"]), ("load_factor", load_factor)):
            out[name][:, i] = value
        for name, value in (("cds", cds), ("tension", tension), ("added_mass", aux["added_mass"]),
                            ("momentum_rate", momentum)):
            out[name][:, :, i] = value

    cds_now, rate_now, _ = _drag_and_rate(chutes, np.array([t0]), stage_airspeed, with_rate)
    cds_now = cds_now[..., 0]
    rate_now = None if rate_now is None else rate_now[..., 0]
    mass = dynamics.initial_mass(altitude, cds_now)

    def mass_at(step, k):
        return None if mass is None else mass + step * k[3]

    for n in range(n_steps + 1):
        k1, aux = dynamics.evaluate(airspeed, gamma, altitude, cds_now, rate_now, mass)
        if n % options.substeps == 0:
            record(n // options.substeps, airspeed, gamma, altitude, cds_now, aux)
        if n == n_steps:
            break
        t_now = t0 + n * h
        starting = record_step == n
        if starting.any():
            v_at_start = airspeed[:, None, None] + (chutes.start - t_now) * k1[0][:, None, None]
            stage_airspeed = np.where(starting, v_at_start, stage_airspeed)
        if n >= blocks.stop or starting.any():
            blocks.refresh(n, stage_airspeed)
        cds_mid, rate_mid = blocks.at(n, "mid")
        cds_end, rate_end = blocks.at(n, "end")
        k2 = dynamics.evaluate(airspeed + h / 2 * k1[0], gamma + h / 2 * k1[1], altitude + h / 2 * k1[2],
                               cds_mid, rate_mid, mass_at(h / 2, k1))[0]
        k3 = dynamics.evaluate(airspeed + h / 2 * k2[0], gamma + h / 2 * k2[1], altitude + h / 2 * k2[2],
                               cds_mid, rate_mid, mass_at(h / 2, k2))[0]
        k4 = dynamics.evaluate(airspeed + h * k3[0], gamma + h * k3[1], altitude + h * k3[2],
                               cds_end, rate_end, mass_at(h, k3))[0]
        airspeed = airspeed + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        gamma = np.clip(gamma + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]), -np.pi / 2, np.pi / 2)
        altitude = altitude + h / 6 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
        if mass is not None:
            mass = mass + h / 6 * (k1[3] + 2 * k2[3] + 2 * k3[3] + k4[3])
        cds_now, rate_now = cds_end, rate_end

    # Stages that never started in the record keep the placeholder V_i.
    _, timing = chutes.drag_area(np.array([time[-1]]), stage_airspeed)
    if refine_peaks > 0:
        peak_tension, peak_total = _refined_peaks(out, time, chutes, dynamics, stage_airspeed, with_rate,
                                                  refine_peaks, options.gravity)
    else:
        peak_tension, peak_total = out["tension"].max(axis=-1), out["tension"].sum(axis=1).max(axis=-1)
    return TrajectoryResult(
        time=time, stage_airspeed=stage_airspeed, timing=timing, total_weight=dynamics.total_weight,
        vehicle_cds=dynamics.vehicle_cds, parachute_weight=chutes.weight, prf=options.prf,
        stage_start=chutes.start, peak_tension=peak_tension, peak_total_tension=peak_total, **out)


def _hermite(t, t_left, dt, y_left, y_right, slope_left, slope_right):
    """Cubic Hermite interpolation on [t_left, t_left + dt]."""
    s = (t - t_left) / dt
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    return h00 * y_left + h10 * dt * slope_left + h01 * y_right + h11 * dt * slope_right


def _refined_peaks(out, time, chutes, dynamics, stage_airspeed, with_rate, factor, gravity):
    """Peak F_i (B, P) and peak Σ F_i (B,) on a grid ``factor`` times finer than the samples."""
    n_batch, n_chutes, n_samples = out["tension"].shape
    rows = np.arange(n_batch)
    v, gam, alt, accel = out["airspeed"], out["flight_path_angle"], out["altitude"], out["acceleration"]
    gamma_rate = -gravity * np.clip(np.cos(gam), 0.0, None) / v
    climb = v * np.sin(gam)
    dt = time[1] - time[0] if n_samples > 1 else 1.0

    def channels_at(t):
        """Tension (B, P) at per-run times t (B,) inside the record."""
        i = np.clip(np.searchsorted(time, t, side="right") - 1, 0, n_samples - 2)
        j = i + 1
        state = [_hermite(t, time[i], dt, y[rows, i], y[rows, j], dy[rows, i], dy[rows, j])
                 for y, dy in ((v, accel), (gam, gamma_rate), (alt, climb))]
        cds, rate, _ = _drag_and_rate(chutes, t[:, None, None], stage_airspeed, with_rate)
        cds = cds[..., 0]
        rate = None if rate is None else rate[..., 0]
        mass = None
        if dynamics.lagged:  # the carried-mass state, linear between samples
            weight = np.clip((t - time[i]) / dt, 0.0, 1.0)[:, None]
            mass = (1 - weight) * out["added_mass"][rows, :, i] + weight * out["added_mass"][rows, :, j]
        _, aux = dynamics.evaluate(*state, cds, rate, mass)
        return dynamics.channels(state[0], state[1], cds, aux)[1]

    def window(index):
        centre = time[index]
        lo = np.maximum(centre - dt, time[0])
        hi = np.minimum(centre + dt, time[-1])
        return [lo + (hi - lo) * k / (2 * factor) for k in range(2 * factor + 1)]

    if n_samples < 3:
        return out["tension"].max(axis=-1), out["tension"].sum(axis=1).max(axis=-1)
    peak = out["tension"].max(axis=-1).copy()
    for p in range(n_chutes):
        for t in window(out["tension"][:, p].argmax(axis=-1)):
            peak[:, p] = np.maximum(peak[:, p], channels_at(t)[:, p])
    total = out["tension"].sum(axis=1)
    peak_total = total.max(axis=-1).copy()
    for t in window(total.argmax(axis=-1)):
        peak_total = np.maximum(peak_total, channels_at(t).sum(axis=-1))
    return peak, peak_total


def composite_cluster(cluster: ClusterParameters) -> ClusterParameters:
    """The cluster as one "composite parachute" (seed §IV–V), for comparison.

    Drag areas and weights are summed over the canopies; each stage starts
    at the canopies' mean start, with their mean n, expopen, C_k and t_k. The
    diameter stays the single canopy's D_o: every canopy's reefing ratio
    CDS_i/CDS_o is unchanged by the sum, so a composite fills in the same
    time as one canopy with the same fill constant (Eq. 14). Arrays keep a
    parachute axis of length 1. Composite and individual runs agree exactly
    for identical canopies that open together, and differ when they stagger
    (the composite's peak is the higher one, seed Fig. 14 and 19).
    """
    start = np.asarray(cluster.start, float)

    def mean(values):
        return np.broadcast_to(np.asarray(values, float), start.shape).mean(axis=-2, keepdims=True)

    per_chute = start.shape[:-1]
    diameter = np.broadcast_to(np.asarray(cluster.diameter, float), per_chute)
    return ClusterParameters(
        start=mean(cluster.start), n_fill=mean(cluster.n_fill), expopen=mean(cluster.expopen), ck=mean(cluster.ck),
        tk=mean(cluster.tk),
        cds_stage=np.broadcast_to(np.asarray(cluster.cds_stage, float), start.shape).sum(axis=-2, keepdims=True),
        cds_o=np.broadcast_to(np.asarray(cluster.cds_o, float), per_chute).sum(axis=-1, keepdims=True),
        diameter=diameter.mean(axis=-1, keepdims=True),
        weight=np.broadcast_to(np.asarray(cluster.weight, float), per_chute).sum(axis=-1, keepdims=True),
        fill_constant=cluster.fill_constant, ids=("composite",))


def single_run(result: TrajectoryResult, index: int) -> TrajectoryResult:
    """Run ``index`` of a batched result as a batch of one (for plots and tests)."""
    def take(value):
        return value[index:index + 1]

    timing = StageTiming(**{name: take(getattr(result.timing, name))
                            for name in ("cds_start", "t_f", "t_fp", "n", "n_p")})
    fields = {name: take(getattr(result, name)) for name in
              ("airspeed", "flight_path_angle", "altitude", "density", "qbar", "acceleration", "load_factor",
               "cds", "tension", "added_mass", "momentum_rate", "stage_airspeed", "total_weight",
               "vehicle_cds", "parachute_weight", "stage_start", "peak_tension", "peak_total_tension")}
    return TrajectoryResult(time=result.time, timing=timing, prf=result.prf, **fields)

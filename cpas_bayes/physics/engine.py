"""Batch flight of Monte Carlo runs, down to each run's peak loads and stage timing (seed §V.D).

:func:`simulate_peaks` flies B runs, each with its own initial state, vehicle
and cluster parameter set (the arrays :func:`cpas_bayes.physics.trajectory.simulate`
takes), and keeps per run only what a Monte Carlo reports
(:class:`RunOutputs`), plus the total-load histories of the first H runs.
Stage arrays may hold padding slots after a canopy's last real stage
(``stages_per_chute`` says how many are real); they must start after the
simulated duration, so they are never active. How the parameter sets are
drawn is :mod:`cpas_bayes.loads.montecarlo`'s business.

Dynamics and loads (as :mod:`cpas_bayes.physics.trajectory`)
-------------------------------------------------------------
Planar point mass, no wind (seed Eq. 1–3)::

    (W_T/g)·dV/dt = −q̄·(PRF·Σ CDS_i + CDS_V) − W_T·sin γ,   dγ/dt = −g·cos γ/V,   dh/dt = V·sin γ
    G   = −(dV/dt + g·sin γ)/g                                            (Eq. 5)
    F_i = PRF·q̄·CDS_i − W_p,i·G                                           (Eq. 10)

and Σ F_i = W_V·G − q̄·CDS_V, the accelerometer total load of Eq. 6, so the
simulated total is directly comparable with a reduced test.

What is reported per run
------------------------
Cluster stage k runs from the earliest start of stage k among the canopies to
the earliest start of stage k+1 (the rule of :func:`cpas_bayes.data.peaks.stage_intervals`,
applied to the run's own dispersed starts). Per cluster stage: the peak of
Σ F_i, its time and the load share F_i/Σ F_i at that instant. Per canopy and
own stage (from its start to its next start): the peak of F_i and its time,
and the stage timing t_f, t_fp, n, n_p, V_i (Eq. 14–18, with n_p or n
dispersed as the cluster's ``fill_constant`` says). A stage that never
started within the simulated duration reports NaN.

Engines
-------
``"trajectory"`` runs :func:`cpas_bayes.physics.trajectory.simulate` on the batch
and takes the peaks from its samples. ``"compiled"`` integrates the same
equations with the same fixed-step RK4 scheme and the same rules (V_i
extrapolated inside the step along dV/dt, drag areas at the step midpoint
and end, γ clipped to ±90°) in one compiled loop per run, evaluating the
drag areas with :mod:`cpas_bayes.physics.inflation`'s compiled stage law and the
density from a 1 m table of ``options.density`` (linear interpolation,
relative error ~1e-9). It keeps no full histories, so a batch costs memory
for its outputs only. It also takes each canopy's drag-area peak instant
t_i + t_fp as an extra evaluation point (a partial RK4 step from the last
step), so the sharp corner of an infinite-mass peak is not missed between
samples (under ``decay="cml_linear"`` that instant is t_f, where the drag area
jumps to its peak). The stage law's options (``options.decay``,
``options.below_previous``) reach the compiled loop as the integer codes of
:mod:`cpas_bayes.physics.inflation`. ``"auto"`` (default) uses the compiled
engine unless added mass or breathing is switched on in ``options``. Tests
hold the two engines equal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from cpas_bayes.physics.inflation import (DECAY_LINEAR, BELOW_PREVIOUS_DROP, below_previous_code,
                                          compiled_peak_exponent, compiled_stage_drag_area, decay_code)
from cpas_bayes.physics.trajectory import (ClusterParameters, SimulationOptions, VehicleProperties, VehicleState0,
                                           simulate)

ENGINES = ("auto", "compiled", "trajectory")
DENSITY_TABLE_STEP = 1.0      # m


# ---------------------------------------------------------------------------
# run outputs


@dataclass(frozen=True)
class RunOutputs:
    """Per-run results, SI. S = K cluster stages; NaN where a stage did not happen."""

    stage_peak_load: np.ndarray      # (B, S) peak of Σ F_i in cluster stage k, N
    stage_peak_time: np.ndarray      # (B, S) s
    stage_peak_tension: np.ndarray   # (B, S, P) each F_i at that instant, N
    chute_peak_load: np.ndarray      # (B, P, K) peak of F_i in its own stage k, N
    chute_peak_time: np.ndarray      # (B, P, K) s
    t_f: np.ndarray                  # (B, P, K) fill time (Eq. 14), s
    t_fp: np.ndarray                 # (B, P, K) peak fill time (Eq. 15), s
    n: np.ndarray                    # (B, P, K) fill constant (Eq. 18)
    n_p: np.ndarray                  # (B, P, K) fill distance to peak (Eq. 17)
    v_i: np.ndarray                  # (B, P, K) airspeed at the stage start, m/s
    history_time: np.ndarray         # (T,) s
    history: np.ndarray              # (H, T) Σ F_i of the first H runs, N

    @property
    def stage_share(self):
        """(B, S, P) load share F_i/Σ F_i at each cluster stage's peak (NaN where that peak is not positive)."""
        total = self.stage_peak_load[..., None]
        positive = total > 0
        return np.divide(self.stage_peak_tension, np.where(positive, total, 1.0),
                         out=np.full(self.stage_peak_tension.shape, np.nan), where=positive)

    @staticmethod
    def concatenate(parts):
        """The runs of ``parts`` (batches of one configuration) in order, as one RunOutputs."""
        first = parts[0]
        fields = {}
        for name in first.__dataclass_fields__:
            if name == "history_time":
                fields[name] = first.history_time
            else:
                fields[name] = np.concatenate([getattr(p, name) for p in parts], axis=0)
        return RunOutputs(**fields)


def real_stages(stages_per_chute, n_slots):
    """(P, K) mask of real stage slots among ``n_slots`` K (the rest are padding)."""
    return np.arange(n_slots)[None, :] < np.asarray(stages_per_chute)[:, None]


def cluster_stage_starts(start, stages_per_chute):
    """(B, K) earliest start of each cluster stage among the canopies having it; ``start`` (B, P, K)."""
    masked = np.where(real_stages(stages_per_chute, start.shape[-1])[None], start, np.inf)
    return masked.min(axis=1)


# ---------------------------------------------------------------------------
# compiled engine
#
# Per-run inputs are packed into a few arrays so that the compiled helpers
# take few arguments (a numba array argument is passed as a dozen words, and
# calls with many arrays cost more than the arithmetic they wrap).

# fields of the stage-parameter array (B, P, K, 7)
_START, _CDS, _FILL, _EXPOPEN, _CK, _TK, _CDS_O = range(7)
# fields of the stage-timing array (B, P, K, 6)
_HELD, _T_F, _T_FP, _N, _N_P, _V_I = range(6)
# fields of the run array (B, 5)
_V0, _GAMMA0, _ALT0, _W_V, _CDS_V = range(5)


@numba.njit(cache=True, inline="always")
def _density(alt, base, step, table):
    """Linear interpolation in the density table (clamped at its ends)."""
    x = (alt - base) / step
    last = table.shape[0] - 1
    if x < 0.0:
        x = 0.0
    elif x > last:
        x = float(last)
    i = min(int(x), last - 1)
    f = x - i
    return table[i] + f * (table[i + 1] - table[i])


@numba.njit(cache=True, inline="always")
def _derivatives(v, gamma, alt, cds_sum, total_weight, vehicle_cds, prf, gravity, base, step, table):
    """dV/dt (Eq. 3), dγ/dt, dh/dt, q̄ and sin γ: the trajectory module's equations without added mass."""
    rho = _density(alt, base, step, table)
    qbar = 0.5 * rho * v**2
    drag = qbar * (prf * cds_sum + vehicle_cds)
    sin_gamma = math.sin(gamma)
    accel = (-drag - total_weight * sin_gamma) / (total_weight / gravity)
    gamma_rate = -gravity * max(math.cos(gamma), 0.0) / v
    return accel, gamma_rate, v * sin_gamma, qbar, sin_gamma


@numba.njit(cache=True)
def _cluster_cds(t, b, par, timing, n_stages, decay, below_previous, out):
    """Each canopy's drag area at time t into ``out`` (the active stage's law, 0 before the first start); Σ."""
    total = 0.0
    for p in range(out.shape[0]):
        m = n_stages[p]
        k = m - 1
        while k >= 0 and t < par[b, p, k, _START]:
            k -= 1
        value = 0.0
        if k >= 0:
            value = compiled_stage_drag_area(t - par[b, p, k, _START], timing[b, p, k, _HELD], par[b, p, k, _CDS],
                                             timing[b, p, k, _T_F], timing[b, p, k, _T_FP], par[b, p, k, _EXPOPEN],
                                             par[b, p, k, _CK], par[b, p, k, _TK], decay, below_previous)
        out[p] = value
        total += value
    return total


@numba.njit(cache=True)
def _begin_stage(b, p, k, v_stage, par, timing, diameter, fill_is_np, decay, below_previous):
    """Stage k of canopy p starts at airspeed V_i: held drag area, S, n ↔ n_p (Eq. 17/18), t_f (Eq. 14), t_fp (Eq. 15).

    The same arithmetic as :func:`cpas_bayes.physics.inflation.parachute_drag_area`.
    """
    if k == 0:
        held = 0.0
    else:
        held = compiled_stage_drag_area(par[b, p, k, _START] - par[b, p, k - 1, _START],
                                        timing[b, p, k - 1, _HELD], par[b, p, k - 1, _CDS],
                                        timing[b, p, k - 1, _T_F], timing[b, p, k - 1, _T_FP],
                                        par[b, p, k - 1, _EXPOPEN], par[b, p, k - 1, _CK], par[b, p, k - 1, _TK],
                                        decay, below_previous)
    cds_i = par[b, p, k, _CDS]
    growth = cds_i - held
    ratio = (par[b, p, k, _CK] * cds_i - held) / growth if growth > 0.0 else 1.0
    e = compiled_peak_exponent(par[b, p, k, _EXPOPEN], decay)   # t_fp/t_f = n_p/n = S^e
    if fill_is_np:
        n_p = par[b, p, k, _FILL]
        n = n_p * ratio ** (-e)
    else:
        n = par[b, p, k, _FILL]
        n_p = n * ratio ** e
    t_f = n * diameter[p] * math.sqrt(max(growth, 0.0) / par[b, p, k, _CDS_O]) / v_stage
    timing[b, p, k, _HELD] = held
    timing[b, p, k, _T_F] = t_f
    timing[b, p, k, _T_FP] = t_f * ratio ** e if t_f > 0.0 else 0.0
    timing[b, p, k, _N] = n
    timing[b, p, k, _N_P] = n_p
    timing[b, p, k, _V_I] = v_stage


@numba.njit(cache=True)
def _update_peaks(b, t, tension, total, par, n_stages, cluster_start, stage_peaks, chute_peaks):
    """Raise the running peaks of cluster stage and canopy stage holding time t (B, S, 2 + P) / (B, P, K, 2)."""
    s = cluster_start.shape[1] - 1
    while s >= 0 and t < cluster_start[b, s]:
        s -= 1
    if s >= 0 and total > stage_peaks[b, s, 0]:
        stage_peaks[b, s, 0] = total
        stage_peaks[b, s, 1] = t
        for p in range(tension.shape[0]):
            stage_peaks[b, s, 2 + p] = tension[p]
    for p in range(tension.shape[0]):
        k = n_stages[p] - 1
        while k >= 0 and t < par[b, p, k, _START]:
            k -= 1
        if k >= 0 and tension[p] > chute_peaks[b, p, k, 0]:
            chute_peaks[b, p, k, 0] = tension[p]
            chute_peaks[b, p, k, 1] = t


@numba.njit(cache=True)
def _simulate_run(b, t0, h, n_steps, record_every, runs, chute_weight, diameter, par, n_stages, fill_is_np, decay,
                  below_previous, prf, gravity, base, step, table, cluster_start, timing, stage_peaks, chute_peaks,
                  history, status):
    """Integrate run b (RK4, the trajectory module's step rules) and record its peaks, timing and history."""
    P = par.shape[1]
    K = par.shape[2]
    alt_low = base
    alt_high = base + step * (table.shape[0] - 1)
    chutes_weight = 0.0
    for p in range(P):
        chutes_weight += chute_weight[p]
    total_weight = runs[b, _W_V] + chutes_weight
    cds_v = runs[b, _CDS_V]
    v, gam, alt = runs[b, _V0], runs[b, _GAMMA0], runs[b, _ALT0]
    cds = np.zeros(P)
    cds_mid = np.zeros(P)
    cds_end = np.zeros(P)
    cds_a = np.zeros(P)
    tension = np.zeros(P)
    record_step = np.full((P, K), -2, dtype=np.int64)
    corner = np.full((P, K), np.inf)
    for p in range(P):
        for k in range(n_stages[p]):
            start = par[b, p, k, _START]
            if start > t0:
                record_step[p, k] = int(math.ceil((start - t0) / h)) - 1
            else:
                # Started at or before t0: V_i = V0, as in the trajectory module.
                _begin_stage(b, p, k, v, par, timing, diameter, fill_is_np, decay, below_previous)
                if timing[b, p, k, _T_FP] > 0.0:
                    corner[p, k] = start + timing[b, p, k, _T_FP]
    next_record = n_steps + 1
    for p in range(P):
        for k in range(n_stages[p]):
            if record_step[p, k] >= 0 and record_step[p, k] < next_record:
                next_record = record_step[p, k]
    next_corner = np.inf
    for p in range(P):
        for k in range(n_stages[p]):
            next_corner = min(next_corner, corner[p, k])
    cds_sum = _cluster_cds(t0, b, par, timing, n_stages, decay, below_previous, cds)
    H = history.shape[0]
    for n in range(n_steps + 1):
        t_n = t0 + n * h
        a1, g1, c1, qbar, sin_gamma = _derivatives(v, gam, alt, cds_sum, total_weight, cds_v, prf, gravity, base,
                                                   step, table)
        # Channels at t_n: G (Eq. 5) and F_i (Eq. 10).
        load_factor = -(a1 + gravity * sin_gamma) / gravity
        total = 0.0
        for p in range(P):
            tension[p] = prf * qbar * cds[p] - chute_weight[p] * load_factor
            total += tension[p]
        if b < H and n % record_every == 0:
            history[b, n // record_every] = total
        _update_peaks(b, t_n, tension, total, par, n_stages, cluster_start, stage_peaks, chute_peaks)
        if n == n_steps:
            break
        if n == next_record:
            # Stages starting in (t_n, t_n + h]: V_i extrapolated from t_n along dV/dt.
            next_record = n_steps + 1
            for p in range(P):
                for k in range(n_stages[p]):
                    if record_step[p, k] == n:
                        start = par[b, p, k, _START]
                        _begin_stage(b, p, k, v + (start - t_n) * a1, par, timing, diameter, fill_is_np, decay,
                                     below_previous)
                        if timing[b, p, k, _T_FP] > 0.0:
                            corner[p, k] = start + timing[b, p, k, _T_FP]
                            next_corner = min(next_corner, corner[p, k])
                    elif record_step[p, k] > n and record_step[p, k] < next_record:
                        next_record = record_step[p, k]
        t_end = t0 + h * (n + 1.0)
        sum_mid = _cluster_cds(t0 + h * (n + 0.5), b, par, timing, n_stages, decay, below_previous, cds_mid)
        sum_end = _cluster_cds(t_end, b, par, timing, n_stages, decay, below_previous, cds_end)
        if next_corner < t_end:
            # Drag-area peaks inside this step: a partial RK4 step to each exact instant.
            next_corner = np.inf
            for p in range(P):
                for k in range(n_stages[p]):
                    tc = corner[p, k]
                    if tc >= t_end:
                        next_corner = min(next_corner, tc)
                        continue
                    if not tc > t_n or (k + 1 < n_stages[p] and tc >= par[b, p, k + 1, _START]):
                        continue
                    d = tc - t_n
                    s_a = _cluster_cds(t_n + 0.5 * d, b, par, timing, n_stages, decay, below_previous, cds_a)
                    a2, g2, c2, _, _ = _derivatives(v + d / 2 * a1, gam + d / 2 * g1, alt + d / 2 * c1, s_a,
                                                    total_weight, cds_v, prf, gravity, base, step, table)
                    a3, g3, c3, _, _ = _derivatives(v + d / 2 * a2, gam + d / 2 * g2, alt + d / 2 * c2, s_a,
                                                    total_weight, cds_v, prf, gravity, base, step, table)
                    s_b = _cluster_cds(tc, b, par, timing, n_stages, decay, below_previous, cds_a)
                    a4, g4, c4, _, _ = _derivatives(v + d * a3, gam + d * g3, alt + d * c3, s_b, total_weight,
                                                    cds_v, prf, gravity, base, step, table)
                    vc = v + d / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
                    gc = min(max(gam + d / 6 * (g1 + 2 * g2 + 2 * g3 + g4), -math.pi / 2), math.pi / 2)
                    hc = alt + d / 6 * (c1 + 2 * c2 + 2 * c3 + c4)
                    ac, _, _, qc, sc = _derivatives(vc, gc, hc, s_b, total_weight, cds_v, prf, gravity, base, step,
                                                    table)
                    gc_load = -(ac + gravity * sc) / gravity
                    total_c = 0.0
                    for j in range(P):
                        cds_a[j] = prf * qc * cds_a[j] - chute_weight[j] * gc_load
                        total_c += cds_a[j]
                    _update_peaks(b, tc, cds_a, total_c, par, n_stages, cluster_start, stage_peaks, chute_peaks)
        a2, g2, c2, _, _ = _derivatives(v + h / 2 * a1, gam + h / 2 * g1, alt + h / 2 * c1, sum_mid, total_weight,
                                        cds_v, prf, gravity, base, step, table)
        a3, g3, c3, _, _ = _derivatives(v + h / 2 * a2, gam + h / 2 * g2, alt + h / 2 * c2, sum_mid, total_weight,
                                        cds_v, prf, gravity, base, step, table)
        a4, g4, c4, _, _ = _derivatives(v + h * a3, gam + h * g3, alt + h * c3, sum_end, total_weight, cds_v, prf,
                                        gravity, base, step, table)
        v = v + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
        gam = min(max(gam + h / 6 * (g1 + 2 * g2 + 2 * g3 + g4), -math.pi / 2), math.pi / 2)
        alt = alt + h / 6 * (c1 + 2 * c2 + 2 * c3 + c4)
        if not (alt >= alt_low and alt <= alt_high and v > 0.0):
            status[b] = 1
            return
        for p in range(P):
            cds[p] = cds_end[p]
        cds_sum = sum_end


@numba.njit(cache=True, parallel=True)
def _simulate_batch(t0, h, n_steps, record_every, runs, chute_weight, diameter, par, n_stages, fill_is_np, decay,
                    below_previous, prf, gravity, base, step, table, cluster_start, timing, stage_peaks, chute_peaks,
                    history, status):
    for b in numba.prange(par.shape[0]):
        _simulate_run(b, t0, h, n_steps, record_every, runs, chute_weight, diameter, par, n_stages, fill_is_np,
                      decay, below_previous, prf, gravity, base, step, table, cluster_start, timing, stage_peaks,
                      chute_peaks, history, status)


_ENGINE_READY = False  # per process: the compiled engine has been loaded


def ensure_compiled():
    """Compile (or load from numba's cache) the compiled engine with a one-run, one-step call.

    Called before a Monte Carlo starts its clock, so runtimes measure runs, not compilation,
    and by :func:`simulate_peaks` (a worker's first batch loads it); once per process.
    """
    global _ENGINE_READY
    if _ENGINE_READY:
        return
    par = np.zeros((1, 1, 1, 7))
    par[..., _CDS] = par[..., _CDS_O] = par[..., _FILL] = par[..., _EXPOPEN] = par[..., _CK] = 1.0
    runs = np.array([[1.0, 0.0, 0.0, 1.0, 0.0]])
    _simulate_batch(0.0, 0.01, 1, 1, runs, np.zeros(1), np.ones(1), par, np.ones(1, dtype=np.int64), True,
                    DECAY_LINEAR, BELOW_PREVIOUS_DROP, 1.0, 9.80665, -10.0, 1.0, np.ones(21), np.zeros((1, 1)), np.full((1, 1, 1, 6), np.nan),
                    np.zeros((1, 1, 3)), np.zeros((1, 1, 1, 2)), np.zeros((0, 2)), np.zeros(1, dtype=np.int64))
    _ENGINE_READY = True


def density_table(airspeed0, altitude0, duration, options: SimulationOptions):
    """(base, step, table): ``options.density`` every DENSITY_TABLE_STEP m over every altitude a run can reach.

    Down: the lowest initial altitude minus the larger of twice the initial
    speed and the initial speed plus free-fall gain, times the duration; up:
    the climb V0²/(2g) of an ascending start; 500 m margins (the highest
    initial speed is taken for every run).
    """
    v0, T = float(np.max(airspeed0)), float(duration)
    speed = max(2.0 * v0, v0 + options.gravity * T)
    low = max(float(np.min(altitude0)) - speed * T - 500.0, -4900.0)
    high = float(np.max(altitude0)) + v0**2 / (2.0 * options.gravity) + 500.0
    altitudes = low + DENSITY_TABLE_STEP * np.arange(int(math.ceil((high - low) / DENSITY_TABLE_STEP)) + 1)
    return low, DENSITY_TABLE_STEP, np.ascontiguousarray(options.density(altitudes), dtype=float)


def _fly_compiled(state0: VehicleState0, vehicle: VehicleProperties, cluster: ClusterParameters, stages_per_chute,
                  duration, options: SimulationOptions, t0, n_history):
    start = np.asarray(cluster.start, float)
    B, P, K = start.shape
    time = t0 + options.dt * np.arange(int(round(duration / options.dt)) + 1)
    h = options.dt / options.substeps
    n_steps = (time.size - 1) * options.substeps
    base, step, table = density_table(state0.airspeed, state0.altitude, duration, options)
    par = np.empty((B, P, K, 7))
    for index, values in ((_START, start), (_CDS, cluster.cds_stage), (_FILL, cluster.n_fill),
                          (_EXPOPEN, cluster.expopen), (_CK, cluster.ck), (_TK, cluster.tk),
                          (_CDS_O, np.broadcast_to(np.asarray(cluster.cds_o, float), (B, P))[:, :, None])):
        par[..., index] = values
    runs = np.empty((B, 5))
    runs[:, _V0], runs[:, _GAMMA0], runs[:, _ALT0] = state0.airspeed, state0.flight_path_angle, state0.altitude
    runs[:, _W_V], runs[:, _CDS_V] = vehicle.weight, vehicle.cds
    timing = np.full((B, P, K, 6), np.nan)
    stage_peaks = np.full((B, K, 2 + P), np.nan)
    stage_peaks[:, :, 0] = -np.inf
    chute_peaks = np.full((B, P, K, 2), np.nan)
    chute_peaks[..., 0] = -np.inf
    history = np.zeros((n_history, time.size))
    status = np.zeros(B, dtype=np.int64)
    # The compiled engine shares D_o and W_p,i between runs: (P,), as a configuration fixes them.
    _simulate_batch(float(t0), float(h), int(n_steps), int(options.substeps), runs,
                    np.ascontiguousarray(np.broadcast_to(np.asarray(cluster.weight, float), (P,))),
                    np.ascontiguousarray(np.broadcast_to(np.asarray(cluster.diameter, float), (P,))),
                    par, np.asarray(stages_per_chute, dtype=np.int64), cluster.fill_constant == "n_p",
                    decay_code(options.decay), below_previous_code(options.below_previous), float(options.prf),
                    float(options.gravity), float(base), float(step), table, np.ascontiguousarray(cluster_stage_starts(start, stages_per_chute)), timing, stage_peaks,
                    chute_peaks, history, status)
    if status.any():
        raise ValueError(f"{int(status.sum())} run(s) left the density table or stopped (airspeed ≤ 0); "
                         "check the initial state and the memo's drag areas")
    stage_peaks[:, :, 0][~np.isfinite(stage_peaks[:, :, 0])] = np.nan
    chute_peaks[..., 0][~np.isfinite(chute_peaks[..., 0])] = np.nan
    return RunOutputs(stage_peak_load=stage_peaks[:, :, 0], stage_peak_time=stage_peaks[:, :, 1],
                      stage_peak_tension=stage_peaks[:, :, 2:], chute_peak_load=chute_peaks[..., 0],
                      chute_peak_time=chute_peaks[..., 1], t_f=timing[..., _T_F], t_fp=timing[..., _T_FP],
                      n=timing[..., _N], n_p=timing[..., _N_P], v_i=timing[..., _V_I], history_time=time,
                      history=history)


# ---------------------------------------------------------------------------
# trajectory engine


def _masked_peak(values, mask, time):
    """Max over the last axis where ``mask``; its time; NaN where the mask is empty. Also the argmax."""
    masked = np.where(mask, values, -np.inf)
    index = masked.argmax(axis=-1)
    peak = np.take_along_axis(masked, index[..., None], axis=-1)[..., 0]
    empty = ~mask.any(axis=-1)
    return np.where(empty, np.nan, peak), np.where(empty, np.nan, time[index]), index, empty


def _fly_trajectory(state0: VehicleState0, vehicle: VehicleProperties, cluster: ClusterParameters, stages_per_chute,
                    duration, options: SimulationOptions, t0, n_history):
    start = np.asarray(cluster.start, float)
    B, P, K = start.shape
    result = simulate(state0, vehicle, cluster, duration, options, t0=t0, refine_peaks=0)
    time = result.time
    tension, total = result.tension, result.tension.sum(axis=1)
    bounds = np.concatenate([cluster_stage_starts(start, stages_per_chute), np.full((B, 1), np.inf)], axis=1)
    stage_peak = np.full((B, K), np.nan)
    stage_time = np.full((B, K), np.nan)
    stage_tension = np.full((B, K, P), np.nan)
    rows = np.arange(B)
    for s in range(K):
        mask = (time[None] >= bounds[:, s, None]) & (time[None] < bounds[:, s + 1, None])
        peak, when, index, empty = _masked_peak(total, mask, time)
        stage_peak[:, s], stage_time[:, s] = peak, when
        stage_tension[:, s] = np.where(empty[:, None], np.nan, tension[rows, :, index])
    has = real_stages(stages_per_chute, K)
    ends = np.concatenate([start[:, :, 1:], np.full((B, P, 1), np.inf)], axis=2)
    ends = np.where(np.concatenate([has[:, 1:], np.zeros((P, 1), bool)], axis=1)[None], ends, np.inf)
    chute_peak = np.full((B, P, K), np.nan)
    chute_time = np.full((B, P, K), np.nan)
    for k in range(K):
        mask = (time >= start[:, :, k, None]) & (time < ends[:, :, k, None]) & has[None, :, k, None]
        chute_peak[:, :, k], chute_time[:, :, k], _, _ = _masked_peak(tension, mask, time)
    started = has[None] & (start <= time[-1])
    timing = result.timing

    def keep(a):
        return np.where(started, a, np.nan)

    return RunOutputs(stage_peak_load=stage_peak, stage_peak_time=stage_time, stage_peak_tension=stage_tension,
                      chute_peak_load=chute_peak, chute_peak_time=chute_time, t_f=keep(timing.t_f),
                      t_fp=keep(timing.t_fp), n=keep(timing.n), n_p=keep(timing.n_p),
                      v_i=keep(result.stage_airspeed), history_time=time, history=total[:n_history].copy())


# ---------------------------------------------------------------------------
# the driver


def choose_engine(engine, options: SimulationOptions):
    """The engine ``engine`` resolves to under ``options`` ("auto": compiled unless added mass or breathing)."""
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if engine == "auto":
        return "trajectory" if (options.added_mass_k is not None or options.breathing is not None) else "compiled"
    if engine == "compiled" and (options.added_mass_k is not None or options.breathing is not None):
        raise ValueError("the compiled engine has no added mass or breathing; use engine='trajectory'")
    return engine


def simulate_peaks(state0: VehicleState0, vehicle: VehicleProperties, cluster: ClusterParameters, stages_per_chute,
                   duration, options: SimulationOptions = SimulationOptions(), t0=0.0, engine="auto",
                   history_runs=0) -> RunOutputs:
    """Fly B runs from ``t0`` for ``duration`` s; each run's peaks and stage timing (module notes).

    ``cluster`` stage arrays are (B, P, K) (batch axis required), ``cds_o``
    (B, P), ``diameter`` and ``weight`` (P,); ``state0`` and ``vehicle``
    scalars or (B,). ``stages_per_chute`` (P,) counts each canopy's real
    stages. ``history_runs`` H keeps Σ F_i(t) of the first H runs at the
    sample times (for load bands). Every run is flown on its own, so a batch
    gives each run the result it would get alone.
    """
    engine = choose_engine(engine, options)
    if engine == "compiled":
        ensure_compiled()
        fly = _fly_compiled
    else:
        fly = _fly_trajectory
    return fly(state0, vehicle, cluster, stages_per_chute, duration, options, t0, history_runs)

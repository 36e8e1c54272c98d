"""Flight-path reconstruction with the accelerometer as the input (kinematic, batched over parameter sets).

Without a measured dynamic pressure the airspeed must be rebuilt from what was
logged. Flight-path reconstruction (Jategaonkar, *Flight Vehicle System
Identification*, AIAA 2006, ch. 10) treats the accelerometer as the *input* of
the kinematic equations and the GNSS velocity and altitude as their *outputs*;
the unknowns are few and systematic (initial state, wind, sensor scale, bias,
latency), so they become parameters of the fit instead of per-sample noise.

Equations (earth frame north, east, up; SI)::

    v_a = v_g − w(h) − δw                 air velocity = ground velocity − wind
    dv_a/dt = −a(t)·v_a/|v_a| − g·ẑ − (dw/dh)·v_up
    dh/dt  = v_up
    a(t)   = g0·(G_reading(t) − b)/s      sensed specific force, magnitude

The accelerometer senses the specific force of the aerodynamic drag, which
acts against the air velocity for a point mass without lift; ``s`` and ``b``
are its scale and bias (reading = s·true + b, in g). A logger reading is the
mean over its sample interval, so a(t) is held at each reading's value over
the interval (t_{j−1}, t_j] that precedes it: the integral of a over every
interval is then exact. The wind w(h) is a stated profile plus one unknown
offset δw per horizontal component (the profile's systematic error); its shear
changes the air velocity as the vehicle descends through it. The offset does
not enter the dynamics (a uniform wind does not change air-relative motion).

Integration: midpoint (RK2) sub-steps of at most ``max_step`` inside every
interval, one compiled loop per parameter set. The state at each reading's time
is returned; between readings the model interpolates linearly.

The readings' random noise is integrated too: a white error σ_G per reading
becomes a random walk in the velocity, of variance (g0·σ_G/s)²·Δt·(t − t0);
:class:`cpas_bayes.data.air_reconstruction.ReceiverErrors` carries it.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from cpas_bayes.core.units import STANDARD_GRAVITY

# Columns of the per-run initial state / sensor array (B, 8).
AIRSPEED_0, FLIGHT_PATH_ANGLE_0, HEADING_0, ALTITUDE_0, WIND_NORTH, WIND_EAST, ACCEL_SCALE, ACCEL_BIAS = range(8)
N_STATE = 8
MAX_STEP = 0.01   # s: a fill of 0.3 s sees ≥ 30 sub-steps; the midpoint rule's error is then < 1e-4 of Δv


@numba.njit(cache=True, inline="always")
def _shear(h, alt, north, east):
    """(dw_n/dh, dw_e/dh) of the piecewise-linear profile at h (0 beyond its ends)."""
    n = alt.shape[0]
    if n < 2 or h <= alt[0] or h >= alt[n - 1]:
        return 0.0, 0.0
    i = 0
    while alt[i + 1] < h:
        i += 1
    dh = alt[i + 1] - alt[i]
    return (north[i + 1] - north[i]) / dh, (east[i + 1] - east[i]) / dh


@numba.njit(cache=True, inline="always")
def _rate(vn, ve, vu, h, a, gravity, alt, north, east):
    speed = math.sqrt(vn * vn + ve * ve + vu * vu)
    k = a / speed if speed > 1e-9 else 0.0
    sn, se = _shear(h, alt, north, east)
    return -k * vn - sn * vu, -k * ve - se * vu, -k * vu - gravity


@numba.njit(cache=True)
def _integrate(time, reading, state, gravity, max_step, alt, north, east, out_v, out_h, out_speed):
    B = state.shape[0]
    N = time.shape[0]
    for b in range(B):
        v0 = state[b, AIRSPEED_0]
        gam = state[b, FLIGHT_PATH_ANGLE_0]
        psi = state[b, HEADING_0]
        vn = v0 * math.cos(gam) * math.cos(psi)
        ve = v0 * math.cos(gam) * math.sin(psi)
        vu = v0 * math.sin(gam)
        h = state[b, ALTITUDE_0]
        scale = state[b, ACCEL_SCALE]
        bias = state[b, ACCEL_BIAS]
        out_v[b, 0, 0], out_v[b, 0, 1], out_v[b, 0, 2] = vn, ve, vu
        out_h[b, 0] = h
        out_speed[b, 0] = math.sqrt(vn * vn + ve * ve + vu * vu)
        for j in range(1, N):
            dt_total = time[j] - time[j - 1]
            m = int(math.ceil(dt_total / max_step))
            dt = dt_total / m
            a = gravity * (reading[j] - bias) / scale
            if a < 0.0:
                a = 0.0   # a reading below its bias is noise about zero drag, never thrust
            for _ in range(m):
                r1n, r1e, r1u = _rate(vn, ve, vu, h, a, gravity, alt, north, east)
                mn, me, mu = vn + 0.5 * dt * r1n, ve + 0.5 * dt * r1e, vu + 0.5 * dt * r1u
                r2n, r2e, r2u = _rate(mn, me, mu, h + 0.5 * dt * vu, a, gravity, alt, north, east)
                h += dt * mu
                vn += dt * r2n
                ve += dt * r2e
                vu += dt * r2u
            out_v[b, j, 0], out_v[b, j, 1], out_v[b, j, 2] = vn, ve, vu
            out_h[b, j] = h
            out_speed[b, j] = math.sqrt(vn * vn + ve * ve + vu * vu)


def reconstruct(time, reading, state, wind_altitude=None, wind_north=None, wind_east=None,
                gravity=STANDARD_GRAVITY, max_step=MAX_STEP):
    """Air velocity (B, N, 3), altitude (B, N) and airspeed (B, N) at each reading's time, for B initial states.

    ``time`` (N,) and ``reading`` (N,) are the accelerometer's samples (g);
    ``state`` (B, 8) holds per run the columns named by this module's constants
    (angles in radians: γ0 above the horizon, heading from north toward east).
    The wind profile (altitude, north, east) gives the shear; None: no shear.
    """
    time = np.ascontiguousarray(time, dtype=float)
    reading = np.ascontiguousarray(reading, dtype=float)
    state = np.ascontiguousarray(np.atleast_2d(state), dtype=float)
    if wind_altitude is None:
        wind_altitude = wind_north = wind_east = np.zeros(1)
    B, N = state.shape[0], time.size
    out_v = np.empty((B, N, 3))
    out_h = np.empty((B, N))
    out_speed = np.empty((B, N))
    _integrate(time, reading, state, float(gravity), float(max_step),
               np.ascontiguousarray(wind_altitude, float), np.ascontiguousarray(wind_north, float),
               np.ascontiguousarray(wind_east, float), out_v, out_h, out_speed)
    return out_v, out_h, out_speed


def interpolate_rows(time, values, query, before="hold"):
    """Per row b, ``values`` (B, N, ...) linearly interpolated at ``query`` (B, M) on the common ``time`` (N,).

    Queries after the time base are held at its end; before it, held (``before="hold"``) or extended along
    the first interval's slope (``"linear"``: a velocity at the first reading's acceleration, for receiver
    samples that a latency puts before the first reading).
    """
    time = np.asarray(time, float)
    q = np.clip(query, time[0], time[-1])
    j = np.clip(np.searchsorted(time, q, side="right"), 1, time.size - 1)
    t_lo, t_hi = time[j - 1], time[j]
    if before == "linear":
        q = np.minimum(query, time[-1])   # below time[0] the first interval's line continues
    f = (q - t_lo) / (t_hi - t_lo)
    rows = np.arange(values.shape[0])[:, None]
    lo, hi = values[rows, j - 1], values[rows, j]
    if values.ndim > 2:
        f = f.reshape(f.shape + (1,) * (values.ndim - 2))
    return lo + f * (hi - lo)

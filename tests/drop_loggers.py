"""A simulated drop test seen by two loggers with their own clocks, for tests/test_import.py.

The truth is a point mass in north-east-down axes, integrated at 2 kHz:

    m dv/dt = m g⃗ + S + D + P,   D = −½ ρ(h) |v| v (C_D S)_V,   P = −P(t) v̂

S holds the vehicle under its carrier (S = −(m g⃗ + D), so a = 0) and falls to
zero along a 20 ms ramp centred on the release time; P is the parachute: a
40 ms ramp to the snatch load centred on the line-stretch time, held 0.1 s,
then decaying to the canopy's drag as its drag area grows. The sensed specific
force is f = dv/dt − g⃗. With these ramps the half-level crossings of |f|/g0
are the stated release and line-stretch times (the levels on either side are
constant to well under 1 % over a ramp).

An accelerometer logger samples f in a rotated body frame (three axes, noise
per axis) and a GNSS logger samples velocity (north, east, down) and altitude,
each at its own rate and on its own clock: logger time = true time + its
clock origin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cpas_bayes.core.units import STANDARD_GRAVITY as G0


@dataclass
class DropTruth:
    release: float = 20.0          # true time of release, s
    line_stretch: float = 21.6     # true time of line stretch (half-way up the first rise), s
    duration: float = 80.0         # s of true time simulated
    mass: float = 1500.0           # kg
    cds_vehicle: float = 0.8       # m²
    cds_canopy: float = 40.0       # m², full open
    snatch_g: float = 3.0          # snatch load / weight
    speed: float = 35.0            # carrier's ground speed, north, m/s
    altitude: float = 2500.0       # m at release
    wind_east: float = 0.0         # the air mass's velocity toward east, m/s (drag acts on the air-relative one)


def air_density(h):
    """The 1976 standard troposphere's density at altitude h (m), kg/m³."""
    return 1.225 * (1.0 - 2.25577e-5 * h) ** 4.2559


def simulate(truth: DropTruth, dt=0.001):
    """True time, NED velocity (n, 3), altitude (n,) and specific force (n, 3) in m/s² (explicit Euler)."""
    n = int(truth.duration / dt) + 1
    t = dt * np.arange(n)
    out_v, out_h, out_f = np.zeros((n, 3)), np.zeros(n), np.zeros((n, 3))
    vn, ve, vd, h = truth.speed, 0.0, 0.0, truth.altitude
    m, snatch = truth.mass, truth.snatch_g * truth.mass * G0
    snatch_end = truth.line_stretch + 0.02 + 0.1
    for i in range(n):
        ti = t[i]
        out_v[i], out_h[i] = (vn, ve, vd), h
        ae = ve - truth.wind_east                                # air-relative velocity (vn, ae, vd)
        speed = math.sqrt(vn * vn + ae * ae + vd * vd)
        rho = air_density(h)
        k_drag = 0.5 * rho * speed * truth.cds_vehicle          # drag = −k_drag·v_air
        held = min(max((truth.release + 0.01 - ti) / 0.02, 0.0), 1.0)
        rise = min(max((ti - (truth.line_stretch - 0.02)) / 0.04, 0.0), 1.0)
        if ti < snatch_end:
            pull = snatch * rise
        else:
            opening = min((ti - snatch_end) / 1.5, 1.0)
            pull = max(snatch * math.exp(-(ti - snatch_end) / 0.1), 0.5 * rho * speed ** 2 * truth.cds_canopy * opening)
        k = (k_drag + pull / speed) / m                          # drag and parachute both oppose v_air
        # specific force f = a − g⃗: drag and parachute, plus the carrier's support (which cancels a while held)
        fn, fe, fd = -k * vn, -k * ae, -k * vd
        fn, fe, fd = fn * (1 - held), fe * (1 - held), fd * (1 - held) - G0 * held
        out_f[i] = (fn, fe, fd)
        vn, ve, vd = vn + fn * dt, ve + fe * dt, vd + (fd + G0) * dt
        h -= vd * dt
    return t, out_v, out_h, out_f


def rotation(rng):
    """A random rotation matrix (the accelerometer's mounting)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def accel_logger(sim, rate, clock_origin, noise_g, rng, start=0.5, end=None):
    """Samples of the accelerometer logger: (logger time in s, body-axis specific force in m/s², (n, 3))."""
    t, _, _, f = sim
    end = t[-1] - 0.5 if end is None else end
    true_t = start + rng.uniform(0, 1 / rate) + np.arange(0, end - start, 1 / rate)
    body = rotation(rng)
    values = np.stack([np.interp(true_t, t, f[:, k]) for k in range(3)], axis=1) @ body.T
    values += rng.normal(0.0, noise_g * G0, size=values.shape)
    return true_t + clock_origin, values


def gnss_logger(sim, rate, clock_origin, speed_noise, altitude_noise, rng, start=0.3, end=None, latency=0.0):
    """Samples of the GNSS logger: (logger time in s, velocity NED (n, 3) in m/s, altitude (n,) in m), each
    stamped ``latency`` s after the instant it shows (a receiver's filter delay)."""
    t, v, h, _ = sim
    end = t[-1] - 0.3 if end is None else end
    true_t = start + rng.uniform(0, 1 / rate) + np.arange(0, end - start, 1 / rate)
    vel = np.stack([np.interp(true_t, t, v[:, k]) for k in range(3)], axis=1)
    vel += rng.normal(0.0, speed_noise, size=vel.shape)
    alt = np.interp(true_t, t, h) + rng.normal(0.0, altitude_noise, size=true_t.shape)
    return true_t + latency + clock_origin, vel, alt

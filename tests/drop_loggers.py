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


def _geodetic(north, east, up, lat0, lon0, h0):
    """Latitude, longitude (deg) and height (m) of points north/east/up (m) of (lat0, lon0, h0): through
    Earth-centred coordinates on the WGS-84 ellipsoid (Bowring's iteration back), not the local radii that
    the importer uses, so that a test of its conversion is not the same formula twice."""
    a, e2 = 6378137.0, 6.69437999014e-3
    p0, l0 = math.radians(lat0), math.radians(lon0)
    n0 = a / math.sqrt(1 - e2 * math.sin(p0) ** 2)
    origin = np.array([(n0 + h0) * math.cos(p0) * math.cos(l0), (n0 + h0) * math.cos(p0) * math.sin(l0),
                       (n0 * (1 - e2) + h0) * math.sin(p0)])
    east_axis = np.array([-math.sin(l0), math.cos(l0), 0.0])
    north_axis = np.array([-math.sin(p0) * math.cos(l0), -math.sin(p0) * math.sin(l0), math.cos(p0)])
    up_axis = np.array([math.cos(p0) * math.cos(l0), math.cos(p0) * math.sin(l0), math.sin(p0)])
    x, y, z = (origin[:, None] + np.outer(east_axis, east) + np.outer(north_axis, north)
               + np.outer(up_axis, up))
    lon = np.arctan2(y, x)
    r = np.hypot(x, y)
    lat = np.arctan2(z, r * (1 - e2))
    for _ in range(6):
        n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
        lat = np.arctan2(z + e2 * n * np.sin(lat), r)
    n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    return np.degrees(lat), np.degrees(lon), r / np.cos(lat) - n


def gnss_fixes_logger(sim, rate, clock_origin, position_noise, altitude_noise, rng, latency=0.0,
                      site=(34.9, -117.9), start=0.3, end=None):
    """Fixes of a receiver that logs no velocity: (logger time in s, latitude and longitude in degrees,
    altitude in m), each fix stamped ``latency`` s late; noise per fix: ``position_noise`` m north and east,
    ``altitude_noise`` m up. The drop's track starts at ``site`` (latitude, longitude)."""
    t, v, h, _ = sim
    dt = t[1] - t[0]
    north = np.concatenate([[0.0], np.cumsum(v[:-1, 0]) * dt])     # the explicit Euler of simulate()
    east = np.concatenate([[0.0], np.cumsum(v[:-1, 1]) * dt])
    end = t[-1] - 0.3 if end is None else end
    true_t = start + rng.uniform(0, 1 / rate) + np.arange(0, end - start, 1 / rate)
    n = np.interp(true_t, t, north) + rng.normal(0.0, position_noise, true_t.shape)
    e = np.interp(true_t, t, east) + rng.normal(0.0, position_noise, true_t.shape)
    alt = np.interp(true_t, t, h) + rng.normal(0.0, altitude_noise, true_t.shape)
    lat, lon, _ = _geodetic(n, e, np.zeros_like(n), *site, 0.0)
    return true_t + latency + clock_origin, lat, lon, alt

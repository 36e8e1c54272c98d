"""A receiver's velocity from what it logs, for ``cpas-bayes import`` (docs/import.md, "Channels"): its
velocity as three columns, its track (ground speed, course, vertical speed), or only its fixes (latitude,
longitude, altitude).

**Fixes to velocity.** Latitude φ and longitude λ become north and east metres about the record's mean
latitude φ̄ on the WGS-84 ellipsoid (a drop spans a few kilometres, where this flat map errs by < 0.1 %)::

    north = (φ − φ̄)·M(φ̄),   east = (λ − λ̄)·N(φ̄)·cos φ̄
    M = a(1 − e²)/(1 − e²·sin²φ)^(3/2),   N = a/(1 − e²·sin²φ)^(1/2)

Consecutive fixes are then taken in disjoint pairs (2j, 2j + 1), each pair one row at the mean of its two
time stamps::

    v = (p_(2j+1) − p_(2j)) / Δ_j,   h = (h_(2j) + h_(2j+1)) / 2,   Δ_j = t_(2j+1) − t_(2j)

with 1-sigmas √2·σ_p/Δ_j (north, east), √2·σ_h/Δ_j (up) and σ_h/√2 (altitude), σ_p and σ_h being the
fix-to-fix noise the map states (``[test.sigma] position`` and ``altitude``). Each fix enters one row, and
the sum and the difference of two fixes with independent errors of one variance are independent: the rows'
errors are independent of one another, and the altitude of a row of its velocity, so the likelihood, which
takes the receiver's samples as independent, counts each fix once. (Differences of every consecutive pair
share a fix with their neighbours, a correlation of −½ that the likelihood would count twice; an altitude
beside velocities differenced from it would count the vertical twice.) The difference is the velocity at
the pair's midpoint to O(Δ²·jerk): 10 Hz fixes through a 100 m/s³ snatch err by 0.04 m/s. A pair spanning
more than 1.5 median intervals (a dropped fix) is not formed: its first fix is left out.
"""

from __future__ import annotations

import numpy as np

from cpas_bayes.core.units import STANDARD_GRAVITY

TRACK = {"ground_speed", "course"}
POSITION = "position"
WGS84_A = 6378137.0                  # m, equatorial radius
WGS84_E2 = 6.69437999014e-3          # first eccentricity squared
MAX_PAIR_SPAN = 1.5                  # × the median fix interval: a longer pair straddles a dropped fix


def velocity_from_track(m, where, channels, spec_type):
    """A receiver that logs its track (ground speed, course over ground, vertical speed: ArduPilot's GPS Spd,
    GCrs and VZ with sign = -1, NMEA's speed and course with a climb rate) gives the velocity: its three
    channels become one ``velocity`` channel (north = s·cos c, east = s·sin c, down = −v_up). ``m`` refuses
    (the map being read), ``spec_type`` is the channel class."""
    parts = ("ground_speed", "course", "vertical_speed")
    missing = [p for p in parts if p not in channels]
    if missing:
        m.fail(f"{where}.{missing[0]}", "is missing: ground_speed and course give the velocity with the "
               "vertical speed of the same logger", f"add {missing[0]} = {{ column = \"...\", unit = \"...\" }} "
               "to this logger (vertical_speed positive up: sign = -1 for a column positive down), or map velocity "
               "= { columns = [north, east, down] } instead")
    for other in ("velocity", POSITION):
        if other in channels:
            m.fail(f"{where}.{other}", f"the velocity is mapped twice: as {other} and as ground_speed, course and "
                   "vertical_speed", "keep one of the two")
    specs = tuple(channels.pop(p) for p in parts)
    channels["velocity"] = spec_type("velocity", tuple(s.columns[0] for s in specs),
                                     ", ".join(f"{p} {s.unit}" + (" sign -1" if s.sign < 0 else "")
                                               for p, s in zip(parts, specs)), 1.0, 1.0, "speed",
                                     parts=specs, source="track")
    return channels


def velocity_from_fixes(m, where, channels, spec_type):
    """A receiver that logs only its fixes gives the velocity by differences (the module's docstring): its
    ``position`` (latitude, longitude) and ``altitude`` channels become a ``velocity`` channel and an altitude
    at the pairs' rows. The logger must hold nothing else: its rows are re-timed to the pairs' midpoints."""
    if "velocity" in channels:
        m.fail(f"{where}.{POSITION}", "the velocity is mapped twice: as velocity and from the position",
               "keep one of the two")
    if "altitude" not in channels:
        m.fail(f"{where}.altitude", "is missing: the position gives the velocity with the altitude of the same "
               "logger (its vertical part)", "add altitude = { column = \"...\", unit = \"m\" } to this logger")
    others = sorted(set(channels) - {POSITION, "altitude"})
    if others:
        m.fail(f"{where}.{others[0]}", "shares a logger with a position: that logger's rows become the pairs of "
               "fixes the velocity is differenced from", "map the same file as a second logger for "
               f"{', '.join(others)} (a [logger.NAME] table of its own, with the same file)")
    position, altitude = channels[POSITION], channels["altitude"]
    channels["velocity"] = spec_type("velocity", position.columns + altitude.columns,
                                     f"latitude, longitude {position.unit}; altitude {altitude.unit}", 1.0, 1.0,
                                     "speed", parts=(position, altitude), source="fixes")
    del channels[POSITION]
    return channels


def checked_position_sigma(m, value, needed, prefix):
    """[test.sigma] position (the bundle's length unit), refused by ``m`` unless it is a positive number given exactly
    when ``needed`` (a velocity from fixes in a logger bundle)."""
    where = f"{prefix}sigma.{POSITION}"
    if value is None and needed:
        m.fail(where, "is missing: the velocity is differenced from the receiver's fixes", "add position = <the "
               "fixes' fix-to-fix noise in the bundle's length unit> under [sigma] (e.g. 0.05 m; not the absolute "
               "accuracy, whose slow part cancels in a difference)")
    if value is not None and not needed:
        m.fail(where, "applies to a logger bundle whose velocity is differenced from a receiver's fixes (a position "
               "channel)", "remove it")
    return m.number({POSITION: value}, POSITION, where, positive=True)   # the map's own check of a number


def local_metres(latitude, longitude):
    """North and east (m) of fixes in degrees, about their mean latitude and longitude (WGS-84)."""
    lat0, lon0 = float(np.mean(latitude)), float(np.mean(longitude))
    s2 = np.sin(np.radians(lat0)) ** 2
    meridional = WGS84_A * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s2) ** 1.5
    normal = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s2)
    north = np.radians(latitude - lat0) * meridional
    east = np.radians(longitude - lon0) * normal * np.cos(np.radians(lat0))
    return north, east


def fix_pairs(time):
    """Indices (first fixes) of the disjoint consecutive pairs of fixes: greedy from the start, a pair spanning
    more than :data:`MAX_PAIR_SPAN` median intervals skipped by one fix."""
    step = float(np.median(np.diff(time)))
    firsts, i = [], 0
    while i + 1 < len(time):
        if time[i + 1] - time[i] <= MAX_PAIR_SPAN * step:
            firsts.append(i)
            i += 2
        else:
            i += 1
    return np.asarray(firsts, dtype=int)


def pair_rows(time, latitude, longitude, altitude):
    """The rows of a receiver's fixes (times s, degrees, m): (times, velocity NED (R, 3) m/s, altitude (R,) m,
    span (R,) s), one per pair of :func:`fix_pairs`, by the differences and means of the docstring."""
    north, east = local_metres(np.asarray(latitude, float), np.asarray(longitude, float))
    first = fix_pairs(time)
    second = first + 1
    span = time[second] - time[first]
    velocity = np.column_stack([(north[second] - north[first]) / span, (east[second] - east[first]) / span,
                                -(altitude[second] - altitude[first]) / span])
    return 0.5 * (time[first] + time[second]), velocity, 0.5 * (altitude[first] + altitude[second]), span


def pair_truncation(time, accel, middle, span, latencies=(0.0,)):
    """How far each pair's rows may depart from the instant they show (m/s, m), sized from an accelerometer's
    magnitude ``accel`` (m/s²) at ``time`` (both on the pairs' clock): a pair's difference is its mean
    velocity, whose departure from the velocity at its middle t_m is the mean over the pair of ∫_(t_m)^τ a dt,
    zero for a steady acceleration; with the force along the flight path that is the same mean of the
    magnitude's departure from its pair mean. The mean of two altitudes departs from the middle's by
    Δ²·a_v/8, a_v ≈ |ā − g0| the pair's mean vertical acceleration in a steep descent. The instant a pair
    shows is its stamp less the receiver's latency, which the reconstruction fits later: the largest over
    ``latencies`` (s) is taken."""
    velocity, altitude = np.zeros(len(middle)), np.zeros(len(middle))
    for latency in latencies:
        instant = middle - latency
        lo = np.searchsorted(time, instant - span / 2)
        hi = np.searchsorted(time, instant + span / 2, side="right")
        for i, (a, b) in enumerate(zip(lo, hi)):
            if b - a < 3:
                continue
            t, dev = time[a:b], accel[a:b] - accel[a:b].mean()
            swept = np.concatenate([[0.0], np.cumsum(0.5 * (dev[1:] + dev[:-1]) * np.diff(t))])
            velocity[i] = max(velocity[i], abs(np.mean(swept - np.interp(instant[i], t, swept))))
            altitude[i] = max(altitude[i], span[i] ** 2 * abs(accel[a:b].mean() - STANDARD_GRAVITY) / 8.0)
    return velocity, altitude


def pair_sigmas(span, position_sigma, altitude_sigma, truncation=(0.0, 0.0)):
    """1-sigmas of the pairs' rows: (north and east, up, altitude), each (R,), from the fixes' noise and the
    ``truncation`` of :func:`pair_truncation` (velocity, altitude), added in quadrature: without it the
    likelihood would take a 1 Hz pair's mean velocity through a snatch, metres per second from the
    velocity at its middle, for a misfit."""
    span = np.asarray(span, float)
    truncation_v, truncation_h = truncation
    return (np.hypot(np.sqrt(2.0) * position_sigma / span, truncation_v),
            np.hypot(np.sqrt(2.0) * altitude_sigma / span, truncation_v),
            np.hypot(altitude_sigma / np.sqrt(2.0), truncation_h))

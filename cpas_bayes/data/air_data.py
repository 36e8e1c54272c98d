"""What a logger bundle without measured q̄ says about the air: winds, density and sample rates.

A bundle may omit ``qbar``, ``airspeed`` and ``gamma`` and give instead the
ground velocity of a GNSS receiver (``v_north``, ``v_east``, ``v_up``, blank
between its samples) and an ``altitude`` (docs/test-bundle.md, "Logger
bundles"). Its test.toml may then hold:

``[wind]``
    ``altitude``, ``north``, ``east``: arrays, the air mass's velocity toward
    north and east (meteorology's v and u) at each altitude; ``sigma``: the
    1-sigma of each component, one systematic error for the whole profile.
``[atmosphere]``
    ``altitude``, ``density``: a measured density profile (a balloon sounding)
    used in place of the 1976 standard atmosphere.
``[rate]``
    ``G``: the accelerometer's declared sample rate, Hz. An accelerometer
    logger averages (or low-pass filters) over its sample interval, so the
    model averages its G prediction over 1/rate before each reading. Absent:
    the median interval between G's own (non-blank) readings. A declared rate
    must agree with the readings' own (:func:`own_interval`) within
    :data:`RATE_TOLERANCE`. The receiver's velocity and altitude are modelled
    as instantaneous samples stamped late by a fitted latency (a receiver's
    filter delays, it does not box-average), so a rate of theirs (``v``,
    ``altitude``: :data:`RECEIVER_RATES`) is accepted but not used, and
    ``validate`` says so.

Everything here is SI: m, m/s, kg/m³, Hz. Pure data and interpolation; the
reading and checking live in :mod:`cpas_bayes.data.bundle_air`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Data columns a logger bundle may hold, canonical names (each may have a ``<name>_sigma``).
VELOCITY_COLUMNS = ("v_north", "v_east", "v_up")
RATE_CHANNELS = ("G",)   # the channels whose declared rate the model uses: the accelerometer's averaging
# [rate] keys of the receiver's channels: accepted (bundles written to the earlier format reference hold them) but
# not used, since the model treats them as instantaneous samples; validate warns, so that nobody trusts them
RECEIVER_RATES = ("v", "v_north", "v_east", "v_up", "altitude")
# A declared rate may differ from the rate data.csv's time column shows by this fraction at most. The rate is
# the reciprocal of the interval each reading averages over, and the readings of an averaging logger follow one
# another at that interval: a logger's clock is off by parts per million (a crystal's 100 ppm is 0.01 %), its
# nominal rate from its actual one by tenths of a per cent, and the rate measured from the time column is off
# by at most the stamps' resolution over the readings' span (own_interval averages the rounding: 100 readings
# at 400 Hz stamped in ms, 0.4 %). 5 % leaves room for all of these, while every slip seen (a rate in the wrong
# unit, the logger's nominal rate where the file holds a decimated or resampled record: factors of 2 and more)
# is refused. A window 5 % off moves a 20 Hz logger's averaged peak by under 0.1 % and no reading by more than
# 0.5 % of the peak (synth_logger's logger-drop, seeds 1-3).
RATE_TOLERANCE = 0.05
# The receiver's latency prior (mean, 1-sigma), s: a sample stamped t shows the state at t − latency. Receivers
# stamp velocity late by their filter's delay, up to ~1.5 s. The fit's prior (air_reconstruction.air_priors) and
# the wind projection's best guess (cpas_bayes.data.attitude, kept for comparison) share it.
LATENCY_PRIOR = (0.3, 0.5)
WIND_SIGMA_WITHOUT_PROFILE = 10.0   # m/s per component: the wind prior's 1-sigma when test.toml has no [wind]
# m/s per component: a [wind] profile's 1-sigma when it states none. A sounding's wind is off by 1-3 m/s by the
# time and place of a drop; 0, the default before, claimed it exact and bent the trajectory to a wrong wind.
WIND_SIGMA_DEFAULT = 2.0


@dataclass(frozen=True)
class WindProfile:
    """The air mass's velocity (toward north, toward east) against altitude, with one 1-sigma per component."""

    altitude: np.ndarray   # (L,) m, strictly increasing
    north: np.ndarray      # (L,) m/s
    east: np.ndarray       # (L,) m/s
    sigma: float = 0.0     # m/s, systematic: the whole profile may be off by one unknown offset

    def at(self, altitude):
        """(north, east) at ``altitude`` (any shape): linear, held constant beyond the profile's ends."""
        h = np.asarray(altitude, float)
        return np.interp(h, self.altitude, self.north), np.interp(h, self.altitude, self.east)


@dataclass(frozen=True)
class DensityProfile:
    """A measured density profile: ρ(h), log-linear between levels, held beyond the ends."""

    altitude: np.ndarray   # (L,) m, strictly increasing
    density: np.ndarray    # (L,) kg/m³, > 0

    def __call__(self, altitude):
        h = np.asarray(altitude, float)
        return np.exp(np.interp(h, self.altitude, np.log(self.density)))


@dataclass(frozen=True)
class AirDataSpec:
    """The air-data part of a logger bundle's test.toml (all optional)."""

    wind: WindProfile | None = None
    atmosphere: DensityProfile | None = None
    rates: dict = field(default_factory=dict)   # channel (RATE_CHANNELS) -> declared rate, Hz
    unused_rates: tuple = ()                    # [rate] keys of the receiver's channels: taken, not used


def channel_samples(data, column):
    """(time, values) of a channel's non-blank samples (blank cells are NaN in the test's data)."""
    values = data[column].to_numpy(float)
    keep = np.isfinite(values)
    return data["time"].to_numpy(float)[keep], values[keep]


def sample_interval(data, column, spec: AirDataSpec | None, channel):
    """The channel's sample interval, s: 1/declared rate, else the median interval between its samples."""
    if spec is not None and channel in spec.rates:
        return 1.0 / float(spec.rates[channel])
    t, _ = channel_samples(data, column)
    return float(np.median(np.diff(t))) if t.size > 1 else 0.0


def own_interval(t):
    """The sample interval, s, that time stamps ``t`` (a channel's, increasing) show: the mean of their regular
    intervals, those at most 1.5× the median (a dropped sample's double interval left out), or 0 for fewer than
    two stamps.

    The mean, not the median: stamps rounded to the time column's resolution give intervals that alternate about
    the true one (a 400 Hz logger stamped in milliseconds: 2 and 3 ms, median 2 or 3, 20 % off either way), and
    their mean recovers it."""
    steps = np.diff(np.asarray(t, float))
    if steps.size == 0:
        return 0.0
    regular = steps[steps <= 1.5 * float(np.median(steps))]
    return float(regular.mean())

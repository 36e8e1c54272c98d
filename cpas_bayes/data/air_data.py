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
    ``G``, ``v``, ``altitude``: each channel's declared sample rate, Hz. An
    accelerometer logger averages (or low-pass filters) over its sample
    interval, so the model averages its G prediction over 1/rate before each
    sample. Absent: the median interval between the channel's own (non-blank)
    samples. The receiver's velocity and altitude are modelled as point
    samples stamped late by a fitted latency (a receiver's filter delays, it
    does not box-average), so their rates are only shown and checked
    (:func:`rate_warnings`).

Everything here is SI: m, m/s, kg/m³, Hz. Pure data and interpolation; the
reading and checking live in :mod:`cpas_bayes.data.bundle_air`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Data columns a logger bundle may hold, canonical names (each may have a ``<name>_sigma``).
VELOCITY_COLUMNS = ("v_north", "v_east", "v_up")
RATE_CHANNELS = ("G", "v", "altitude")
RATE_COLUMNS = {"G": "G", "v": "v_north", "altitude": "altitude"}   # the column whose samples a rate describes
RATE_MISMATCH = 2.0   # a declared rate this many times faster or slower than the samples' own is questioned
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


def rate_warnings(data, spec: AirDataSpec | None):
    """Messages for declared rates that disagree with their channel's samples by more than RATE_MISMATCH×.

    Either way round the declaration can be right (a faster logger decimated without averaging; a slower one
    resampled onto a finer grid), so these are warnings, not refusals; but both are more often a slip (a rate
    in the wrong unit, or the logger's nominal rate where the file holds another), and the G rate sets the
    window the accelerometer's prediction is averaged over: on 20 Hz samples a declared 1,000 Hz leaves the
    averaged-away part of a fast peak to the inflation parameters.
    """
    out = []
    for channel, rate in ({} if spec is None else spec.rates).items():
        column = RATE_COLUMNS[channel]
        t, _ = channel_samples(data, column)
        if t.size < 3:
            continue
        spacing = float(np.median(np.diff(t)))
        ratio = float(rate) * spacing          # 1 when the declaration is the samples' own rate
        if 1.0 / RATE_MISMATCH <= ratio <= RATE_MISMATCH:
            continue
        own = f"the '{column}' samples are {spacing * 1e3:.3g} ms apart ({1.0 / spacing:.3g} Hz)"
        if ratio > RATE_MISMATCH:
            why = ("right only if a faster logger's samples were kept without averaging; if the logger averaged "
                   f"over each interval, declare {channel} = {1.0 / spacing:.3g}")
        else:
            why = ("right only if a slower logger's samples were resampled onto a finer grid; otherwise declare "
                   f"{channel} = {1.0 / spacing:.3g}")
        out.append(f"test.toml [rate] {channel} = {float(rate):g} Hz, but {own}: {why}, or remove the entry "
                   "(the samples' own rate is then used)")
    return out

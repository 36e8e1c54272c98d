"""What a bundle's numbers may be: physical plausibility ranges and the size of data.csv.

A number the format can hold is not always one the reduction can use: G = 1e300
overflows, q̄ = 1e-300 divides a load by ~0, a record in milliseconds looks like
a four-hour test sampled every 10 s. Each range below states its reason in one
line (docs/test-bundle.md lists the same table); a value outside its range is
refused by :func:`cpas_bayes.data.bundle.read_bundle` with the value and the
limit in the bundle's own units.

Ranges are in SI (:mod:`cpas_bayes.core.units`), inclusive at both ends; a
quantity of ``None`` means a load factor (g) or an angle (deg), which carry no
unit system. A sigma's range is [0, the upper limit of its value]: a 1-sigma
wider than every plausible value is a unit error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cpas_bayes.core.errors import BundleError

# data.csv, checked before it is parsed: the size of any parachute phase with room to spare, and what
# parsing every cell as text in memory handles (a few GB at the limit).
MAX_CSV_BYTES = 500_000_000      # 500 MB: 2,000,000 rows of ~25 ten-character cells
MAX_CSV_ROWS = 2_000_000         # an hour at 555 Hz, half an hour at 1 kHz
MAX_CSV_COLUMNS = 1_000          # a bundle has 5-9 channels plus 2-4 per parachute
MAX_COLUMN_NAME = 128            # characters of one header name

# The record (time column, s).
MAX_DURATION = 3600.0            # a parachute phase lasts seconds to minutes; an hour-long record is time in ms
MAX_SAMPLE_INTERVAL = 10.0       # an inflation lasts about a second; samples 10 s apart cannot see it (ms again)
MIN_SAMPLE_INTERVAL = 1e-5       # 100 kHz: faster than any flight data system; smaller steps are a unit error
MAX_START_SIGMA = 10.0           # bag strip and cutter times are known to a fraction of a second


@dataclass(frozen=True)
class Plausible:
    """The range a quantity must lie in, in SI, with the reason and a hint on the usual unit error."""

    quantity: str | None   # core.units quantity; None: g or deg
    low: float
    high: float
    reason: str
    unit: str = ""         # shown when quantity is None
    hint: str = "check the value and its unit"

    def sigma(self):
        """The range of this quantity's 1-sigma: [0, high]."""
        return Plausible(self.quantity, 0.0, max(abs(self.low), abs(self.high)),
                         "a 1-sigma cannot exceed the plausible range of the value itself", self.unit, self.hint)

    def limits(self, units):
        """(low, high, unit label) in the bundle's units."""
        if self.quantity is None:
            return self.low, self.high, self.unit
        return units.from_si(self.low, self.quantity), units.from_si(self.high, self.quantity), \
            units.label(self.quantity)


_UNITS_HINT = "US bundles are in lbf, ft, ft², ft/s, lbf/ft², slug/ft³; SI bundles in N, m, m², m/s, Pa, kg/m³"

# Channels the package divides by: a value ≤ 0 is refused before the range check, naming the division.
DIVISORS = {"qbar": "drag areas are computed as load / qbar",
            "airspeed": "fill times are computed as n·D_o / airspeed"}

# data.csv channels, by canonical column ("F" and "theta": every parachute's load cell and fly-out angle).
CHANNELS = {
    "G": Plausible(None, -50.0, 50.0, "parachute deployment loads stay below ~20 g; beyond 50 g it is not a "
                   "load factor", "g", "G is the load factor in g, not an acceleration in m/s² or ft/s²"),
    "qbar": Plausible("pressure", 0.1, 1.0e6, "1e6 Pa is beyond Mach 3 at sea level, faster than any parachute "
                      "deployment; below 0.1 Pa nothing flies and load / q̄ divides noise by ~0", hint=_UNITS_HINT),
    "airspeed": Plausible("speed", 0.0, 1000.0, "an airspeed is ≥ 0, and no parachute deploys faster than "
                          "Mach 3, ~1000 m/s", hint=_UNITS_HINT),
    "gamma": Plausible(None, -90.0, 90.0, "a flight path angle lies between straight down and straight up", "deg",
                       "gamma is in degrees, positive above the horizon"),
    "density": Plausible("density", 1e-6, 2.0, "sea-level air is 1.225 kg/m³; 2 is denser than any air, 1e-6 is "
                         "air at ~95 km", hint="US density is slug/ft³ (sea level 0.00238), not lbm/ft³"),
    "altitude": Plausible("length", -1000.0, 100_000.0, "from below the Dead Sea to 100 km, where the air ends",
                          hint=_UNITS_HINT),
    "F": Plausible("force", -1.0e7, 1.0e7, "1e7 N, 2.2 million lbf, is far beyond any parachute riser; "
                   "a CPAS Main peaks near 1e5 N", hint=_UNITS_HINT),
    "theta": Plausible(None, -180.0, 180.0, "an angle beyond ±180° is not in degrees", "deg",
                       "fly-out angles are in degrees"),
}
CHANNELS.update({axis: CHANNELS["G"] for axis in ("accel_x", "accel_y", "accel_z")})   # body axes, in g
# A logger bundle's GNSS ground velocity, one entry per component (north, east, up).
_VELOCITY = Plausible("speed", -1000.0, 1000.0, "no parachute deploys faster than Mach 3, ~1000 m/s, in any "
                      "direction", hint=_UNITS_HINT)
CHANNELS.update({c: _VELOCITY for c in ("v_north", "v_east", "v_up")})

# A logger bundle's [wind] components and [rate] entries (test.toml).
AIR_DATA = {
    "wind": Plausible("speed", -150.0, 150.0, "jet-stream cores reach ~100 m/s; no parachute test flies in a "
                      "wind of 150 m/s", hint=_UNITS_HINT),
    "rate": Plausible(None, 0.1, 100_000.0, "a channel sampled less often than every 10 s cannot see an "
                      "inflation; 100 kHz is faster than any flight data system", "Hz",
                      "a rate is in Hz (samples per second), not a sample interval"),
}

# test.toml numbers, by key.
VEHICLE = {
    "weight": Plausible("force", 1.0, 1.0e7, "below 1 N, 100 g, there is no test vehicle; 1e7 N is 1,000 t, "
                        "heavier than anything recovered under parachutes", hint=_UNITS_HINT),
    "cds": Plausible("area", 0.0, 1.0e4, "1e4 m² is the drag of a 110 m flat plate; test vehicles are 1-100 m²",
                     hint=_UNITS_HINT),
}
PARACHUTE = {
    "diameter": Plausible("length", 0.1, 300.0, "parachutes range from ~0.5 m pilots to ~100 m cargo canopies",
                          hint=_UNITS_HINT),
    "weight": Plausible("force", 0.0, 1.0e5, "1e5 N, 22,000 lbf, is ten times the heaviest parachute pack",
                        hint=_UNITS_HINT),
}


def _fmt(x):
    return f"{x:.6g}"


def outside_problem(value, spec, units, what):
    """Why ``value`` (in the bundle's units) is implausible for ``spec``, or ``None``."""
    low, high, unit = spec.limits(units)
    if low <= value <= high:
        return None
    unit = f" {unit}" if unit else ""
    return f"{what} = {_fmt(value)}{unit} is outside {_fmt(low)} … {_fmt(high)}{unit} ({spec.reason})"


def check_value(value, spec, units, file, key, what=None):
    """Refuse one test.toml number outside ``spec``; ``key`` is its dotted key."""
    problem = outside_problem(value, spec, units, what or key.rpartition(".")[2])
    if problem:
        raise BundleError(file, f"key '{key}'", problem, spec.hint)
    return value


def check_column(values, spec, units, file, column):
    """Refuse the first cell of a data.csv column outside ``spec`` (values in the bundle's units)."""
    low, high, _ = spec.limits(units)
    bad = (values < low) | (values > high)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise BundleError(file, f"row {i + 2}, column '{column}'",
                          outside_problem(float(values[i]), spec, units, column), spec.hint)
    return values


def check_record(t, file):
    """Refuse a time column whose length or sampling says it is not in seconds (``t`` increasing, ≥ 2 samples)."""
    duration, step = float(t[-1] - t[0]), float(np.median(np.diff(t)))
    last = f"row {len(t) + 1}, column 'time'"
    if duration > MAX_DURATION:
        raise BundleError(file, last, f"the record lasts {_fmt(duration)} s, more than an hour "
                          f"({_fmt(t[0])} to {_fmt(t[-1])}); a parachute phase lasts seconds to minutes",
                          "time is in seconds: if it was written in milliseconds, divide the column by 1000")
    if step > MAX_SAMPLE_INTERVAL:
        raise BundleError(file, "column 'time'", f"the median sample interval is {_fmt(step)} s, more than "
                          f"{_fmt(MAX_SAMPLE_INTERVAL)} s: too coarse to see an inflation",
                          "time is in seconds: if it was written in milliseconds, divide the column by 1000")
    if step < MIN_SAMPLE_INTERVAL:
        raise BundleError(file, "column 'time'", f"the median sample interval is {_fmt(step)} s, faster than "
                          f"{_fmt(1 / MIN_SAMPLE_INTERVAL)} Hz, which no flight data system records",
                          "time is in seconds: convert it if it was written in another unit")


# How many of each a test.toml may list: each parachute and stage adds parameters to every fit (a two-Drogue
# fit samples 29), and a hostile file of 200 parachutes passed every check before these.
COUNTS = {"parachutes": (16, "the largest clusters flown hold 8 canopies (a heavy airdrop's G-11s)",
                         "split the test into bundles of the canopies that share a record"),
          "stages": (8, "a canopy disreefs two or three times (CPAS Mains: two reefed stages, then full open)",
                     "list a stage per reefing line cut, the last full open")}


def check_count(reader, key, items, what):
    """Refuse (through the bundle reader) a list of more ``what`` (a :data:`COUNTS` key) than its limit."""
    most, reason, fix = COUNTS[what]
    if len(items) > most:
        reader.fail(key, f"{len(items)} {what}, more than {most} ({reason})", fix)

"""The column map of ``cpas-bayes import`` (docs/import.md): logger files, columns, units, clocks and metadata.

A map is a TOML file. ``[logger.NAME]`` tables say, for each logger CSV file,
its path (relative to the map's folder), its time column and unit, its clock
offset, and which column feeds which bundle channel, in which unit. ``[test]``
(or a ``template`` test.toml) gives what no logger records: vehicle,
parachutes, stages, constant sigmas. ``[record]`` and ``[events]`` are
optional. :func:`read_import_map` checks all of it, and the logger files'
presence, before any file is read; every refusal is an
:class:`~cpas_bayes.core.errors.InputError` naming the map (or template), the
key and the fix.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace
from pathlib import Path, PurePath

from cpas_bayes.core.errors import BundleError, InputError
from cpas_bayes.core.inputs import check_keys, check_name, nearest, read_toml, shown
from cpas_bayes.core.units import column_factor
from cpas_bayes.data.bundle import parse_test_document
from cpas_bayes.data.bundle_csv import skip_lines
from cpas_bayes.data.import_velocity import (POSITION, TRACK, checked_position_sigma, velocity_from_fixes,
                                             velocity_from_track)
from cpas_bayes.data.limits import MAX_CSV_BYTES, MAX_DURATION, MAX_START_SIGMA

MAP_KEYS = ("reference", "template", "air_data", "record", "events", "logger", "test")
LOGGER_KEYS = ("file", "time", "clock", "offset", "offset_hint", "search", "skip_rows", "delimiter", "channels")
TIME_KEYS = ("column", "unit")
CHANNEL_KEYS = ("column", "columns", "unit", "sign", "ground")
RECORD_KEYS = ("start", "end")
EVENT_KEYS = ("release", "release_sigma", "line_stretch", "line_stretch_sigma", "line_stretch_threshold")
EVENTS = ("release", "line_stretch")
CLOCKS = ("elapsed", "wall")
# What a map with GNSS velocity (and no airspeed or q̄ channel) makes of the air data: "reconstruct" writes a
# logger bundle (the velocity and altitude at the receiver's own samples; q̄ is reconstructed by the package with
# the wind, the receiver's latency and the accelerometer's scale and bias as parameters), "ground_speed" a bundle
# with q̄ = ½ρ|v_ground|² (no wind, the receiver's lag kept). A map with an airspeed or q̄ channel is "measured".
AIR_DATA_MODES = ("reconstruct", "ground_speed")
ISO = "iso"

# Bundle channels a logger column can feed: name -> (quantity, allowed numbers of columns, meaning).
# A parachute's load_cell (force) and flyout_angle (angle) column names are channels too.
CHANNELS = {
    "accel": ("acceleration", (1, 3), "sensed acceleration: one axis with its sign, or three axes (magnitude)"),
    "velocity": ("speed", (3,), "velocity: north, east, down"),
    "ground_speed": ("speed", (1,), "horizontal ground speed (with course and vertical_speed: the velocity)"),
    "course": ("angle", (1,), "course over ground, clockwise from north (with ground_speed and vertical_speed)"),
    "vertical_speed": ("speed", (1,), "vertical speed, positive up"),
    "position": ("angle", (2,), "latitude and longitude of the fixes (the velocity by differences, with altitude)"),
    "airspeed": ("speed", (1,), "airspeed"),
    "gamma": ("angle", (1,), "flight path angle, positive above the horizon"),
    "altitude": ("length", (1,), "altitude above sea level"),
    "density": ("density", (1,), "air density"),
    "qbar": ("pressure", (1,), "dynamic pressure"),
}
_UNIT_EXAMPLES = {"acceleration": "'m/s^2', 'ft/s^2' or 'g'", "speed": "'m/s', 'ft/s', 'km/h' or 'kn'",
                  "angle": "'deg' or 'rad'", "length": "'m' or 'ft'", "density": "'kg/m^3' or 'slug/ft^3'",
                  "pressure": "'Pa', 'kPa', 'psf' or 'psi'", "force": "'N', 'kN' or 'lbf'",
                  "time": "'s', 'ms', 'us' or 'iso'"}

# A clock offset's (and offset_hint's) magnitude, s. The widest legitimate gap is between a wall clock and an
# elapsed one: ISO times are seconds since 1970 (pandas' timestamps end in 2262, 9.2e9 s) and an elapsed clock
# counts from power-on, so an offset reaches ~1.7e9 s today; a day would refuse that. Beyond 1e10 s (317 years)
# it is a typo or a unit error, and would overflow the record's arithmetic into meaningless numbers.
MAX_CLOCK_OFFSET = 1e10


@dataclass(frozen=True)
class ChannelSpec:
    """One bundle channel fed by one or three columns of a logger file."""

    name: str
    columns: tuple
    unit: str
    factor: float      # multiplies the column into SI (angles: degrees)
    sign: float        # +1 or -1 (one column only)
    quantity: str
    parts: tuple = ()  # a velocity from a track (ground_speed, course, vertical_speed) or fixes (position, altitude)
    source: str = "columns"   # a velocity's: "columns", "track" or "fixes" (data/import_velocity.py)
    ground: float = 0.0   # m added to an altitude logged above ground: the site's elevation above sea level


@dataclass(frozen=True)
class LoggerSpec:
    """One logger file: where it is, its time column and clock, and the channels it feeds."""

    name: str
    path: Path
    time_column: str
    time_unit: str            # "iso" or a time unit
    time_factor: float        # seconds per unit (1 for iso)
    clock: str                # "elapsed" or "wall"
    offset: float | None      # s added to its times; None: "auto"
    hint: float | None        # centre of the "auto" search, s
    search: float | None      # half-width of the "auto" search, s
    skip_rows: int
    delimiter: str
    channels: dict

    def has(self, channel):
        return channel in self.channels


@dataclass(frozen=True)
class ImportMap:
    """A checked column map."""

    path: Path
    loggers: tuple
    reference: str            # the logger whose clock the others are aligned to
    g_logger: str             # the logger whose accelerometer gives G, events and the rows
    record_start: float       # s after release
    record_end: float | None  # s after release; None: the end of the common record
    release: float | None     # s on the reference clock; None: detected
    release_sigma: float
    line_stretch: float | None  # s after release; None: detected
    line_stretch_sigma: float
    threshold: float          # g above the free-fall level that marks the first load
    test_doc: dict            # [test] or the template, stage starts as written
    test_path: Path           # the file refusals about test keys name
    test_prefix: str          # "test." for the map's own [test], "" for a template
    air_data: str | None = None   # AIR_DATA_MODES or "measured"; None while the map is being read
    position_sigma: float | None = None   # [test.sigma] position: fix-to-fix noise, bundle length unit

    @property
    def logger_bundle(self):
        """True: the bundle is a logger bundle; False: measured air data; None: not yet known."""
        return None if self.air_data is None else self.air_data == "reconstruct"

    def logger(self, name):
        return next(lg for lg in self.loggers if lg.name == name)

    def feeder(self, channel):
        """The logger feeding ``channel`` (for accel: the G logger), or None."""
        if channel == "accel":
            return self.logger(self.g_logger)
        return next((lg for lg in self.loggers if lg.has(channel)), None)


class _Map:
    """Typed access to the map that refuses with file, key and fix."""

    def __init__(self, path):
        self.path = path

    def fail(self, key, problem, fix):
        raise InputError(self.path, f"key '{key}'" if key else "", problem, fix)

    def keys(self, table, valid, where):
        check_keys(table, valid, self.path, where)

    def table(self, doc, key, where, required=False):
        value = doc.get(key)
        if value is None and not required:
            return {}
        if not isinstance(value, dict):
            self.fail(where, "is missing" if value is None else "is not a table", f"add a [{where}] table "
                      "as in docs/import.md")
        return value

    def string(self, doc, key, where, default=None):
        value = doc.get(key, default)
        if value is None:
            self.fail(where, "is missing", f"add {key} = \"...\"")
        if not isinstance(value, str) or not value.strip():
            self.fail(where, f"must be a non-empty string, got {shown(value)}", f"write {key} = \"...\"")
        return value

    def number(self, doc, key, where, default=None, positive=False, minimum=None):
        value = doc.get(key, default)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.fail(where, f"must be a finite number, got {shown(value)}", f"write a number for {key}")
        if positive and value <= 0:
            self.fail(where, f"must be positive, got {value}", f"give {key} a value > 0")
        if minimum is not None and value < minimum:
            self.fail(where, f"must be ≥ {minimum}, got {value}", f"give {key} a value ≥ {minimum}")
        return float(value)

    def local_file(self, value, where, what):
        """A path relative to the map's folder, inside it (also where its links lead); the file must exist."""
        if not isinstance(value, str) or not value.strip():
            self.fail(where, f"must be a file name, got {shown(value)}", f"write the {what}'s path relative "
                      "to the map's folder")
        rel = PurePath(value)
        if rel.is_absolute() or ".." in rel.parts:
            self.fail(where, f"{shown(value)} is {'absolute' if rel.is_absolute() else 'outside the map folder'}: "
                      "a map reads only files in its own folder and below it",
                      "put the map beside the logger files (or above them) and give paths relative to it")
        path = self.path.parent / rel
        folder, target = self.path.parent.resolve(), path.resolve(strict=False)
        if not target.is_relative_to(folder):   # the text stays inside; a symbolic link on the way leaves
            self.fail(where, f"{shown(value)} is a link leading outside the map folder (to {shown(str(target), 80)}): "
                      "a map reads only files in its own folder and below it",
                      "copy the file into the map's folder (or put the map above both) instead of linking to it")
        if not path.is_file():
            self.fail(where, f"{what} {path} not found" if not path.exists() else f"{path} is not a file",
                      "check the path (relative to the map's folder)")
        return path


def _unit(m, unit, quantity, where):
    if not isinstance(unit, str):
        m.fail(where, f"a unit must be a string, got {shown(unit)}", f"write a unit such as {_UNIT_EXAMPLES[quantity]}")
    try:
        return column_factor(unit, quantity)
    except ValueError as exc:
        m.fail(where, f"unknown unit {shown(unit)} for {quantity}: {exc}",
               f"write a unit of {quantity} such as {_UNIT_EXAMPLES[quantity]}")


def _column_name(m, value, where):
    if not isinstance(value, str) or not value.strip():
        m.fail(where, f"must name a column of the file, got {shown(value)}", "write the column's header name")
    return value.strip()


def _channel(m, name, entry, where, quantities):
    if not isinstance(entry, dict):
        m.fail(where, "is not a table", f"write {name} = {{ column = \"...\", unit = \"...\" }}")
    m.keys(entry, CHANNEL_KEYS, where)
    quantity, counts, meaning = quantities[name]
    if ("column" in entry) == ("columns" in entry):
        m.fail(where, "needs exactly one of 'column' and 'columns'",
               f"{name} ({meaning}) takes " + (" or ".join(f"{n} column{'s' * (n > 1)}" for n in counts)))
    if "column" in entry:
        columns = (_column_name(m, entry["column"], f"{where}.column"),)
    else:
        raw = entry["columns"]
        if not isinstance(raw, list):
            m.fail(f"{where}.columns", f"must be a list of column names, got {shown(raw)}",
                   "write columns = [\"x\", \"y\", \"z\"]")
        columns = tuple(_column_name(m, c, f"{where}.columns") for c in raw)
    if len(columns) not in counts:
        m.fail(where, f"{name} ({meaning}) takes " + " or ".join(map(str, counts)) + f" column(s), got {len(columns)}",
               "list the right columns")
    if "unit" not in entry:
        m.fail(f"{where}.unit", "is missing", f"add unit = ... such as {_UNIT_EXAMPLES[quantity]}")
    factor = _unit(m, entry["unit"], quantity, f"{where}.unit")
    sign = entry.get("sign", 1)
    if sign not in (1, -1) or isinstance(sign, bool):
        m.fail(f"{where}.sign", f"must be 1 or -1, got {shown(sign)}", "write sign = -1 to reverse an axis")
    if sign != 1 and len(columns) != 1:
        if name == "velocity":
            m.fail(f"{where}.sign", "a sign applies to one column; velocity's three are north, east, down",
                   "remove sign; a receiver logging up rather than down: map its track (ground_speed, course and "
                   "vertical_speed, which takes a sign) or negate the column in the file")
        m.fail(f"{where}.sign", "a sign applies to one column (three axes give a magnitude)", "remove sign")
    return ChannelSpec(name, columns, entry["unit"], factor, float(sign), quantity,
                       ground=_ground(m, name, entry, factor, where) if "ground" in entry else 0.0)


GROUND_RANGE = (-500.0, 6000.0)   # m above sea level: the Dead Sea shore to the highest drop zones with margin


def _ground(m, name, entry, factor, where):
    """The site elevation (m) of an altitude logged above ground: the density is the atmosphere's at sea-level
    altitude, and a height above a site at 1,300 m read as sea-level altitude makes q̄ 13 % high."""
    value = entry["ground"]
    if name != "altitude":
        m.fail(f"{where}.ground", "applies to the altitude channel only", "remove ground")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        m.fail(f"{where}.ground", f"must be a number (the site's elevation in {entry['unit']}), got {shown(value)}",
               "write ground = the drop zone's elevation above sea level, in the channel's unit")
    metres = float(value) * factor
    if not GROUND_RANGE[0] <= metres <= GROUND_RANGE[1]:
        given = f"{value:g} m" if factor == 1.0 else f"{value:g} {entry['unit']} = {metres:.0f} m"
        m.fail(f"{where}.ground", f"{given} is not a ground elevation on Earth's drop zones ({GROUND_RANGE[0]:.0f} "
               f"to {GROUND_RANGE[1]:.0f} m)", "write the site's elevation above sea level in the channel's unit")
    return metres


def _logger(m, name, entry, quantities):
    where = f"logger.{name}"
    check_name(name, m.path, f"key '{where}'", "logger name")
    if not isinstance(entry, dict):
        m.fail(where, "is not a table", f"write [{where}] with file, time and channels")
    m.keys(entry, LOGGER_KEYS, where)
    path = m.local_file(entry.get("file"), f"{where}.file", f"logger file of '{name}'")
    time = m.table(entry, "time", f"{where}.time", required=True)
    m.keys(time, TIME_KEYS, f"{where}.time")
    column = _column_name(m, time.get("column"), f"{where}.time.column")
    unit = m.string(time, "unit", f"{where}.time.unit")
    factor = 1.0 if unit == ISO else _unit(m, unit, "time", f"{where}.time.unit")
    clock = m.string(entry, "clock", f"{where}.clock", default="wall" if unit == ISO else "elapsed")
    if clock not in CLOCKS:
        m.fail(f"{where}.clock", f"unknown clock {shown(clock)}", "use \"elapsed\" (time since the logger "
               "started) or \"wall\" (a time of day shared with the other wall-clock loggers)")
    offset = entry.get("offset", "auto")
    if isinstance(offset, str) and offset != "auto":
        m.fail(f"{where}.offset", f"unknown offset {shown(offset)}",
               "give the seconds to add to this logger's time, or \"auto\" (cross-correlation)")
    if offset != "auto":
        offset = _clock_offset(m, entry, "offset", where)
    hint = _clock_offset(m, entry, "offset_hint", where)
    search = m.number(entry, "search", f"{where}.search", positive=True)
    if offset != "auto" and (hint is not None or search is not None):
        m.fail(f"{where}.{'offset_hint' if hint is not None else 'search'}", "applies only to offset = \"auto\"",
               "remove it, or write offset = \"auto\"")
    skip = entry.get("skip_rows", 0)
    if isinstance(skip, bool) or not isinstance(skip, int) or skip < 0:
        m.fail(f"{where}.skip_rows", f"must be a whole number ≥ 0, got {shown(skip)}",
               "give the number of lines before the header row")
    _check_skip_rows(m, path, skip, f"{where}.skip_rows")
    delimiter = m.string(entry, "delimiter", f"{where}.delimiter", default=",")
    if len(delimiter) != 1:
        m.fail(f"{where}.delimiter", f"must be one character, got {shown(delimiter)}", "write delimiter = \",\"")
    raw = m.table(entry, "channels", f"{where}.channels", required=True)
    m.keys(raw, tuple(quantities), f"{where}.channels")
    channels = {key: _channel(m, key, value, f"{where}.channels.{key}", quantities) for key, value in raw.items()}
    if TRACK & set(channels):
        channels = velocity_from_track(m, f"{where}.channels", channels, ChannelSpec)
    elif POSITION in channels:
        channels = velocity_from_fixes(m, f"{where}.channels", channels, ChannelSpec)
    return LoggerSpec(name, path, column, unit, factor, clock, None if offset == "auto" else offset, hint, search,
                      skip, delimiter, channels)


def _clock_offset(m, entry, key, where):
    value = m.number(entry, key, f"{where}.{key}")
    if value is not None and abs(value) > MAX_CLOCK_OFFSET:
        m.fail(f"{where}.{key}", f"{value:.6g} s is more than the {MAX_CLOCK_OFFSET:.0e} s (317 years) two clocks "
               "can differ by, even a wall clock (s since 1970) against an elapsed one",
               "give the seconds to add to this logger's time (t_ref = t_logger + offset), not another unit")
    return value


def _check_skip_rows(m, path, skip, key):
    """Refuse a skip_rows that passes the whole file, before anything parses it (pandas would allocate per row)."""
    if skip == 0 or path.stat().st_size > MAX_CSV_BYTES:   # a larger file is refused by its size before it is read
        return
    with open(path, "rb") as handle:
        offset, seen = skip_lines(handle, skip)
        size = handle.seek(0, 2)
        if seen == skip and offset < size:   # a line follows the skipped ones: the header
            return
        handle.seek(max(size - 1, 0))
        lines = seen + (handle.read(1) not in (b"", b"\n", b"\r"))   # a last line without a line end counts
    m.fail(key, f"skip_rows {skip} is beyond the file's {lines:,} line{'s' * (lines != 1)}: {path.name} has no "
           "header row after them", "give the number of lines before the header row" +
           (f" (at most {lines - 1:,})" if lines else ", or a logger file that is not empty"))


def _test_document(m, doc):
    """([test] or the template's document, the file it came from, its key prefix)."""
    if "template" in doc and "test" in doc:
        m.fail("template", "a map takes either [test] or template, not both", "keep one of them")
    if "template" in doc:
        path = m.local_file(doc["template"], "template", "template test.toml")
        return read_toml(path), path, ""
    return m.table(doc, "test", "test", required=True), m.path, "test."


def _stages(test_doc):
    """(where, stage table) of every stage the document holds, without judging its shape."""
    chutes = test_doc.get("parachute")
    for i, chute in enumerate(chutes if isinstance(chutes, list) else []):
        stages = chute.get("stage") if isinstance(chute, dict) else None
        for k, stage in enumerate(stages if isinstance(stages, list) else []):
            if isinstance(stage, dict):
                yield f"parachute[{i}].stage[{k}]", stage


def resolved_test_document(import_map, events):
    """The test document with event-linked stage starts replaced by numbers.

    ``events`` maps "release" / "line_stretch" to (time after release, 1-sigma),
    or is None: then every event start becomes a placeholder just after the
    previous stage (so the rest of the document can be checked before the logs
    are read). start = event time + delay; start_sigma = √(σ_event² + start_sigma²).
    """
    doc = copy.deepcopy(import_map.test_doc)
    for _, stage in _stages(doc):
        stage.pop("delay", None)
    previous = {}
    for (where, stage), (_, written) in zip(_stages(doc), _stages(import_map.test_doc)):
        chute = where.split(".")[0]
        start = written.get("start")
        if isinstance(start, str):
            delay = written.get("delay", 0.0)
            sigma = written.get("start_sigma", 0.0)
            if events is None:
                stage["start"] = previous.get(chute, 0.0) + 1e-3
            else:
                time, event_sigma = events[start]
                stage["start"] = time + delay
                stage["start_sigma"] = math.hypot(event_sigma, sigma)
        if isinstance(stage.get("start"), (int, float)):
            previous[chute] = stage["start"]
    return doc


def bundle_metadata(import_map, events, folder):
    """The bundle's metadata with event-linked stage starts resolved; refusals name the map's (or template's) key."""
    doc = resolved_test_document(import_map, events)
    try:
        return parse_test_document(doc, import_map.test_path, folder, import_map.logger_bundle)
    except BundleError as exc:
        where = exc.where.replace("key '", f"key '{import_map.test_prefix}", 1)
        raise InputError(import_map.test_path, where, exc.problem, exc.fix) from None


def _check_stage_starts(m, test_doc, prefix):
    """Event-linked stage starts: start = "release" | "line_stretch", delay a number; numbers take no delay."""
    for where, stage in _stages(test_doc):
        where = f"{prefix}{where}"
        start = stage.get("start")
        if isinstance(start, str):
            if start not in EVENTS:
                near = nearest(start, EVENTS)
                m.fail(f"{where}.start", f"unknown event {shown(start)}",
                       (f"did you mean '{near}'? " if near else "") + "use a number (s after release), "
                       "\"release\" or \"line_stretch\"")
            m.number(stage, "delay", f"{where}.delay")
            sigma = m.number(stage, "start_sigma", f"{where}.start_sigma", minimum=0.0)
            if sigma is not None and sigma > MAX_START_SIGMA:
                m.fail(f"{where}.start_sigma", f"start_sigma = {sigma} s, more than {MAX_START_SIGMA:g} s",
                       "give the 1-sigma of the delay after the event, in seconds")
        elif "delay" in stage:
            m.fail(f"{where}.delay", "a delay applies to a stage that starts at an event",
                   "write start = \"line_stretch\" (or \"release\") with the delay, or remove delay")


def _air_data_mode(m, doc, loggers):
    """The map's air_data (AIR_DATA_MODES) or "measured" for a map with an airspeed or q̄ channel."""
    fed = {name for lg in loggers for name in lg.channels}
    given = doc.get("air_data")
    if fed & {"airspeed", "qbar"} or "velocity" not in fed:
        if given is not None and fed & {"airspeed", "qbar"}:   # without either, _check_channels says what is missing
            m.fail("air_data", "applies to a map whose air data come from GNSS velocity, with no airspeed or qbar "
                   "channel", "remove air_data (the mapped airspeed or qbar channel is the air data)")
        return "measured"
    mode = m.string(doc, "air_data", "air_data", default="reconstruct")
    if mode not in AIR_DATA_MODES:
        near = nearest(mode, AIR_DATA_MODES)
        m.fail("air_data", f"unknown air_data {shown(mode)}", (f"did you mean '{near}'? " if near else "") +
               "use \"reconstruct\" (a logger bundle: q̄ reconstructed with the wind and the receiver's latency) "
               "or \"ground_speed\" (q̄ from the ground speed: no wind, the receiver's lag kept)")
    return mode


def _check_channels(m, loggers, test_doc, prefix, meta, mode):
    """Every channel fed once (accel may be in several loggers), and every channel the bundle needs fed."""
    owners = {}
    for lg in loggers:
        for name in lg.channels:
            if name != "accel" and name in owners:
                m.fail(f"logger.{lg.name}.channels.{name}", f"channel '{name}' is already fed by logger "
                       f"'{owners[name]}'", "feed each channel from one logger")
            owners.setdefault(name, lg.name)
    has = owners.__contains__
    if not has("accel"):
        m.fail("logger", "no logger has an accel channel: G, the release and the line stretch come from it",
               "add accel = { column = \"...\", unit = \"m/s^2\" } (or columns = [x, y, z]) to a logger's channels")
    if mode == "reconstruct":   # a logger bundle: the receiver's velocity and an altitude, at their own samples
        unused = [(lg.name, n) for lg in loggers for n in lg.channels if n in ("gamma", "vertical_speed")]
        if unused:
            name, channel = unused[0]
            m.fail(f"logger.{name}.channels.{channel}", f"a logger bundle does not use {channel}: the package "
                   "reconstructs the flight path from G and the receiver's velocity", f"remove {channel}, or write "
                   "air_data = \"ground_speed\" for a bundle with q̄ from the ground speed (which reads it)")
        needs = [("altitude", has("altitude"), "an altitude channel (GNSS or barometric), which a logger bundle "
                  "needs for the density and the wind")]
    else:
        needs = [("airspeed", has("airspeed") or has("velocity"), "an airspeed or a velocity channel"),
                 ("gamma", has("gamma") or has("velocity") or (has("vertical_speed") and has("airspeed")),
                  "a gamma channel, a velocity channel, or vertical_speed with airspeed"),
                 ("qbar", has("qbar") or ((has("airspeed") or has("velocity")) and (has("density") or
                                                                                    has("altitude"))),
                  "a qbar channel, or an airspeed or velocity channel with density or altitude")]
    for channel, ok, what in needs:
        if not ok:
            m.fail("logger", f"the bundle needs '{channel}' and no logger channel gives it",
                   f"map {what} (docs/import.md, 'Channels')")
    for p in meta.parachutes:
        for column, key in ((p.load_cell, "load_cell"), (p.flyout_angle, "flyout_angle")):
            if column and not has(column):
                m.fail(f"{prefix}parachute '{p.id}'.{key}", f"names column '{column}' but no logger has a channel "
                       f"'{column}'", f"add {column} = {{ column = \"...\", unit = \"...\" }} to a logger's channels, "
                       f"or remove {key}")
    sigma = test_doc.get("sigma") if isinstance(test_doc.get("sigma"), dict) else {}
    needed = [("G", "g", "the accelerometer's noise, e.g. 0.03")]
    if mode == "reconstruct":
        if "qbar" in sigma:
            m.fail(f"{prefix}sigma.qbar", "a 1-sigma of qbar, but the map makes a logger bundle, whose q̄ the "
                   "package reconstructs (air_data = \"reconstruct\", the default with GNSS velocity)",
                   f"remove qbar from [{prefix}sigma] and give v_north, v_east, v_up and altitude; or write "
                   "air_data = \"ground_speed\" for q̄ from the ground speed (no wind, the receiver's lag kept)")
        fixes = fixes_feed_velocity(loggers)
        if fixes and (given := [c for c in VELOCITY_SIGMAS if c in sigma]):
            m.fail(f"{prefix}sigma.{given[0]}", "the velocity is differenced from the receiver's fixes, whose 1-sigmas "
                   "follow from position's and altitude's", f"remove {', '.join(given)} from [{prefix}sigma]")
        needed += [(c, "in the bundle's speed unit", "the receiver's velocity accuracy, e.g. 0.1 m/s")
                   for c in VELOCITY_SIGMAS if not fixes]
        needed += [("altitude", "in the bundle's length unit", "e.g. 3 m for GNSS, 1 m for a barometer")]
    else:
        needed += [("qbar", "in the bundle's units", "e.g. 2 % of q̄")]
    needed += [(p.load_cell, "in the bundle's force unit", "the load cell's accuracy") for p in meta.parachutes
               if p.load_cell]
    for key, unit, example in needed:
        if key not in sigma:
            m.fail(f"{prefix}sigma.{key}", f"is missing: the bundle needs a 1-sigma of {key} and the loggers give none",
                   f"add {key} = <1-sigma, {unit}> under [{prefix}sigma] ({example})")
        if sigma[key] == 0 and not isinstance(sigma[key], bool):   # the bundle refuses it; say so at the map's key
            m.fail(f"{prefix}sigma.{key}", f"a 1-sigma of 0 claims an exact {key} (no sensor is), and each sample is "
                   "weighed by 1/sigma", f"give the sensor's 1-sigma, {unit} ({example})")


VELOCITY_SIGMAS = ("v_north", "v_east", "v_up")


def fixes_feed_velocity(loggers):
    """Whether a receiver's velocity is differenced from its fixes (data/import_velocity.py)."""
    return any(lg.has("velocity") and lg.channels["velocity"].source == "fixes" for lg in loggers)


def read_import_map(path, folder) -> ImportMap:
    """Read and check a column map; ``folder`` (the output bundle) names the test when [test] has no name."""
    path = Path(path)
    doc = read_toml(path)
    m = _Map(path)
    m.keys(doc, MAP_KEYS, "")
    test_doc, test_path, prefix = _test_document(m, doc)
    _check_stage_starts(_Map(test_path), test_doc, prefix)
    test_doc = copy.deepcopy(test_doc)   # the fixes' noise is the import's, not a bundle channel's sigma
    position_sigma = test_doc["sigma"].pop(POSITION, None) if isinstance(test_doc.get("sigma"), dict) else None
    # first read as either kind of bundle (the channels, read next, say which), then as the kind they make
    preliminary = ImportMap(path, (), "", "", 0.0, None, None, 0.0, None, 0.0, 0.0, test_doc, test_path, prefix)
    meta = bundle_metadata(preliminary, None, folder)

    quantities = dict(CHANNELS)
    for p in meta.parachutes:
        if p.load_cell:
            quantities[p.load_cell] = ("force", (1,), f"riser tension of parachute '{p.id}'")
        if p.flyout_angle:
            quantities[p.flyout_angle] = ("angle", (1,), f"fly-out angle of parachute '{p.id}'")
    raw = m.table(doc, "logger", "logger", required=True)
    if not raw:
        m.fail("logger", "no logger", "add a [logger.NAME] table per logger file")
    loggers = tuple(_logger(m, name, entry, quantities) for name, entry in raw.items())
    mode = _air_data_mode(m, doc, loggers)
    _check_channels(m, loggers, test_doc, prefix, meta, mode)
    position_sigma = checked_position_sigma(_Map(test_path), position_sigma, fixes_feed_velocity(loggers) and mode == "reconstruct",
                                     prefix)
    bundle_metadata(replace(preliminary, air_data=mode), None, folder)   # what this kind of bundle refuses

    with_accel = [lg.name for lg in loggers if lg.has("accel")]
    reference = m.string(doc, "reference", "reference", default=with_accel[0])
    if reference not in raw:
        near = nearest(reference, list(raw))
        m.fail("reference", f"no logger named {shown(reference)}",
               (f"did you mean '{near}'? " if near else "") + f"use one of {', '.join(raw)}")
    g_logger = reference if reference in with_accel else with_accel[0]
    ref = next(lg for lg in loggers if lg.name == reference)
    if ref.offset not in (None, 0.0) or ref.hint is not None or ref.search is not None:
        m.fail(f"logger.{reference}.offset", "the reference logger's clock is the one the others are aligned to",
               "remove offset, offset_hint and search from the reference logger")
    loggers = tuple(lg if lg.name != reference else _with_offset(lg, 0.0) for lg in loggers)

    record = m.table(doc, "record", "record")
    m.keys(record, RECORD_KEYS, "record")
    start = m.number(record, "start", "record.start", default=0.0)
    end = m.number(record, "end", "record.end")
    if end is not None and not end > start:
        m.fail("record.end", f"must be after record.start ({start:g} s), got {end:g}", "give end > start")
    if end is not None and end - start > MAX_DURATION:
        m.fail("record.end", f"the record would last {end - start:g} s, more than a bundle's {MAX_DURATION:g} s",
               "shorten the record to the parachute phase")

    events = m.table(doc, "events", "events")
    m.keys(events, EVENT_KEYS, "events")
    release = _manual_event(m, events, "release")
    line_stretch = _manual_event(m, events, "line_stretch", positive=True)
    threshold = m.number(events, "line_stretch_threshold", "events.line_stretch_threshold", default=0.5,
                         positive=True)
    return ImportMap(path, loggers, reference, g_logger, start, end, release,
                     m.number(events, "release_sigma", "events.release_sigma", default=0.0, minimum=0.0),
                     line_stretch,
                     m.number(events, "line_stretch_sigma", "events.line_stretch_sigma", default=0.0, minimum=0.0),
                     threshold, test_doc, test_path, prefix, mode, position_sigma)


def _with_offset(spec, offset):
    return LoggerSpec(**{**spec.__dict__, "offset": offset})


def _manual_event(m, events, name, positive=False):
    """An event time the map gives (a number) or None ("auto", the default)."""
    if events.get(name, "auto") == "auto":
        if f"{name}_sigma" in events:
            m.fail(f"events.{name}_sigma", f"applies to a {name} time given in the map", f"remove it, or give {name}")
        return None
    return m.number(events, name, f"events.{name}", positive=positive)

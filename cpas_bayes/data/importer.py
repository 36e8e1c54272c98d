"""Logger CSV files to a flight-test bundle: ``cpas-bayes import MAP.toml --out BUNDLE`` (docs/import.md).

The steps, each refusing bad input with the file, the place and the fix:

1. :func:`~cpas_bayes.data.import_map.read_import_map` checks the column map
   (and that every logger file exists) before any file is read;
2. :func:`read_logger` reads each logger's time column (s, ms, us… or ISO
   timestamps, as seconds) and the columns of its channels, in SI;
3. :func:`~cpas_bayes.data.import_clocks.clock_offsets`: every logger's clock is put on the reference
   logger's, t_ref = t_logger + offset, with the offset given or found by
   cross-correlation (:func:`~cpas_bayes.data.logger_events.align_clocks`);
4. release and line stretch are found in the sensed load factor of the G
   logger (:mod:`cpas_bayes.data.logger_events`), unless the map gives them;
5. the bundle's rows are the G logger's samples from ``record.start`` to
   ``record.end`` seconds after release (within the span every logger feeding
   the bundle covers); **time 0 is the release**. The other loggers' channels
   are interpolated (linearly) onto those rows;
6. derived channels: G = |a|/g0 less its noise bias (three axes) or sign·a/g0
   (one axis). With GNSS velocity and no airspeed or q̄ column (``air_data =
   "reconstruct"``, the default) a logger bundle: velocity (north, east, up) and
   altitude (above sea level: a height above ground plus the map's ``ground``)
   at their own samples, blank between (:func:`_assemble_logger`). Otherwise:
   airspeed = |v| (ground speed, no wind) unless mapped; γ = atan2(−v_down,
   √(v_n² + v_e²)) or asin(v_up/V); ρ = 1976 atmosphere at the altitude; q̄ = ½ρV²;
7. stage starts linked to an event become numbers in the bundle's time
   (start = event + delay, start_sigma = √(σ_event² + start_sigma²)), and the
   bundle is written to a temporary folder, read back with
   :func:`~cpas_bayes.data.bundle.read_bundle`, and only then renamed into
   place, with ``import.json`` (what was detected, from which files).
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.files import jsonable
from cpas_bayes.core.units import STANDARD_GRAVITY as G0
from cpas_bayes.core.inputs import did_you_mean, shown
from cpas_bayes.data.air_data import VELOCITY_COLUMNS
from cpas_bayes.data.air_reconstruction import LATENCY_RANGE
from cpas_bayes.data.bundle import FlightTest, read_bundle
from cpas_bayes.data.bundle_csv import parse_numbers, skip_lines
from cpas_bayes.data.bundle_write import write_bundle
from cpas_bayes.data.import_clocks import clock_offsets, find_events, load_factor
from cpas_bayes.data.import_map import ISO, bundle_metadata, fixes_feed_velocity, read_import_map
from cpas_bayes.data.import_velocity import pair_rows, pair_sigmas, pair_truncation
from cpas_bayes.data.limits import MAX_CSV_BYTES, MAX_DURATION
from cpas_bayes.data.reduction import check_reducible
from cpas_bayes.data.logger_events import Event, sample_interval
from cpas_bayes.physics.atmosphere import standard_density

REPORT_NAME = "import.json"
MIN_ROWS = 10
_EPOCH = pd.Timestamp("1970-01-01", tz="UTC")


@dataclass(frozen=True)
class LoggerRecord:
    """One logger file read: its time (s, its own clock) and its channels in SI (angles in degrees)."""

    spec: object           # its LoggerSpec
    time: np.ndarray
    channels: dict         # name -> (n,) or (n, 3) array
    rows_without_fix: int = 0   # a receiver's rows whose position and altitude were all empty (left out)

    @property
    def rate(self):
        return 1.0 / sample_interval(self.time)


@dataclass(frozen=True)
class ImportResult:
    """What ``cpas-bayes import`` made: the bundle (in memory) and what it detected."""

    test: FlightTest
    import_map: object     # the ImportMap
    records: dict          # logger name -> LoggerRecord
    offsets: dict          # logger name -> ClockOffset
    release: Event         # time on the reference clock
    line_stretch: Event    # time after release
    sources: dict          # bundle channel -> where it came from
    release_given: bool = False
    line_stretch_given: bool = False

    def report(self) -> dict:
        """The content of import.json."""
        imap, ref = self.import_map, self.import_map.logger(self.import_map.reference)
        t = self.test.time
        release = {"time_on_reference_clock_s": self.release.time, "sigma_s": self.release.sigma,
                   "terms_s": self.release.terms, "given_in_map": self.release_given}
        if ref.time_unit == ISO:
            release["utc"] = (_EPOCH + pd.Timedelta(self.release.time, "s")).round("us").isoformat()
        return jsonable({
            "map": str(imap.path), "time_zero": "release", "reference_logger": imap.reference,
            "air_data": imap.air_data,
            "release": release,
            "line_stretch": {"time_after_release_s": self.line_stretch.time, "sigma_s": self.line_stretch.sigma,
                             "terms_s": self.line_stretch.terms, "given_in_map": self.line_stretch_given},
            "loggers": {name: {"file": str(rec.spec.path), "rows": len(rec.time), "rate_hz": rec.rate,
                               **({"rows_are": "pairs of fixes", "rows_without_fix": rec.rows_without_fix}
                                  if "pair_span" in rec.channels else {}),
                               "clock": rec.spec.clock, "offset_s": self.offsets[name].offset,
                               "offset_sigma_s": self.offsets[name].sigma, "offset_method": self.offsets[name].method,
                               **_alignment_fields(self.offsets[name].alignment),
                               **_questioned_fields(self.offsets[name].disagreement)}
                        for name, rec in self.records.items()},
            "record": {"start_s": float(t[0]), "end_s": float(t[-1]), "rows": len(t),
                       "rate_hz": self.test.sample_rate},
            "channels": self.sources,
        })


def _questioned_fields(alignment):
    if alignment is None:
        return {}
    return {"signals_prefer_offset_s": alignment.offset, "signals_prefer_offset_sigma_s": alignment.sigma,
            "signals_prefer_correlation": alignment.correlation}


def _alignment_fields(alignment):
    if alignment is None:
        return {}
    return {"correlation": alignment.correlation, "runner_up_correlation": alignment.runner_up,
            "searched_s": list(alignment.search), "fit_samples": alignment.samples}


# ---------------------------------------------------------------------------
# reading one logger file


def _fail_file(spec, where, problem, fix):
    raise InputError(spec.path, where, problem, fix)


def _at_header(spec):
    """The logger file, binary, at its header row: skip_rows lines passed here, streaming.

    pandas is never given skip_rows: it turns skiprows=N into a set of N row numbers.
    """
    handle = open(spec.path, "rb")
    handle.seek(skip_lines(handle, spec.skip_rows)[0])
    return handle


def _header(spec):
    """The header row's names (stripped), read with the csv module; refused unless every name is unique."""
    where = f"row {spec.skip_rows + 1} (header)"
    with _at_header(spec) as handle:
        try:
            row = next(csv.reader(io.TextIOWrapper(handle, encoding="utf-8-sig", newline=""),
                                  delimiter=spec.delimiter), [])
        except UnicodeDecodeError:
            _fail_file(spec, "", "not UTF-8 text", "save the logger file as UTF-8 CSV")
        except (csv.Error, ValueError) as exc:
            _fail_file(spec, where, f"no readable header ({exc})",
                       "set skip_rows to the number of lines before the header, and delimiter to the file's "
                       "separator")
    header = [name.strip() for name in row]
    if not any(header):
        _fail_file(spec, where, "no header: the line is blank (or the file ends)" if not row else
                   "no header: every name is blank",
                   "set skip_rows to the number of lines before the header row")
    places = {}
    for k, name in enumerate(header, 1):
        if name:   # unnamed columns (a trailing delimiter) cannot be mapped, so they cannot be confused
            places.setdefault(name, []).append(k)
    for name, ks in places.items():
        if len(ks) > 1:   # pandas would rename the second 'ax.1' and the map's 'ax' would silently mean the first
            numbers = ", ".join(map(str, ks[:-1])) + f" and {ks[-1]}"
            _fail_file(spec, where, f"the column name '{shown(name, 60, quote=False)}' is in columns {numbers}",
                       "give each column its own header name (the map names columns by their header)")
    return header


def _cells(spec, needed):
    header = _header(spec)
    for column, key in needed:
        if column not in header:
            listed = ", ".join(shown(h, 30, quote=False) for h in header[:12]) + (", …" if len(header) > 12 else "")
            _fail_file(spec, f"column '{shown(column, 60, quote=False)}'",
                       f"missing column, named by the map ({key})" + did_you_mean(column, header),
                       f"correct the column name in the map (the file's columns: {listed}), or set skip_rows / "
                       "delimiter if the header was misread")
    # columns by position in the header read above: pandas' own names (mangled or not) play no part
    positions = sorted({header.index(c) for c, _ in needed})
    with _at_header(spec) as handle:
        try:
            frame = pd.read_csv(handle, sep=spec.delimiter, dtype=str, encoding="utf-8-sig", index_col=False,
                                keep_default_na=False, skip_blank_lines=False, usecols=positions)
        except UnicodeDecodeError:
            _fail_file(spec, "", "not UTF-8 text", "save the logger file as UTF-8 CSV")
        except (pd.errors.ParserError, ValueError) as exc:
            _fail_file(spec, "", f"not a readable CSV table ({exc})", "make every row have as many cells as the "
                       "header")
    frame.columns = [header[k] for k in positions]
    filled = (frame != "").any(axis=1).to_numpy()
    last = int(np.flatnonzero(filled)[-1]) + 1 if filled.any() else 0
    return frame.iloc[:last]  # blank lines at the end are not samples


def _row(spec, i, frame=None):
    """The file's row of data row ``i`` (of ``frame``, whose index keeps the file's numbering)."""
    return f"row {spec.skip_rows + 2 + (i if frame is None else int(frame.index[i]))}"


def _numbers(spec, frame, column):
    values, i, cell = parse_numbers(frame, column)
    if i is not None:
        _fail_file(spec, f"{_row(spec, i, frame)}, column '{column}'",
                   "the cell is empty" if cell == "" else f"the cell {shown(cell)} is not a finite number",
                   "every cell of a mapped column must hold a number; remove or repair the row")
    return values


def _times(spec, frame):
    column = spec.time_column
    if spec.time_unit != ISO:
        return _numbers(spec, frame, column) * spec.time_factor
    stamps = pd.to_datetime(frame[column].str.strip(), utc=True, format="ISO8601", errors="coerce")
    bad = stamps.isna().to_numpy()
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        _fail_file(spec, f"{_row(spec, i, frame)}, column '{column}'",
                   f"{shown(frame[column].iloc[i])} is not an ISO 8601 timestamp",
                   "write times as 2024-05-14T10:15:02.125Z (a zone-less time is taken as UTC), or give the "
                   "time column's numeric unit")
    return ((stamps - _EPOCH) / pd.Timedelta(1, "s")).to_numpy(dtype=float)


def _check_fixes(spec, position, lat, lon, frame):
    """Latitudes within ±90°, longitudes within ±360°, and fixes that move (a receiver without a fix logs one)."""
    for values, name, bound in ((lat, "latitude", 90.0), (lon, "longitude", 360.0)):
        if np.abs(values).max() > bound:
            i = int(np.argmax(np.abs(values) > bound))
            _fail_file(spec, f"{_row(spec, i, frame)}, column '{position.columns[name == 'longitude']}'",
                       f"{name} {values[i]:.6g}° is beyond ±{bound:g}°", "map [latitude, longitude] in that order, "
                       "in degrees (unit = \"deg\") or radians (\"rad\")")
    if np.ptp(lat) == 0 and np.ptp(lon) == 0:
        _fail_file(spec, f"columns {', '.join(position.columns)}", "every fix is the same point: the receiver had no "
                   "fix, or the columns are not its position", "map the columns of the receiver's latitude and longitude")


def read_logger(spec) -> LoggerRecord:
    """One logger file: strictly increasing time in seconds and each mapped channel in SI."""
    size = spec.path.stat().st_size
    if size > MAX_CSV_BYTES:
        _fail_file(spec, "", f"{size:,} bytes, more than the {MAX_CSV_BYTES:,} a logger file may have",
                   "cut the file to the drop (a few minutes around it)")
    needed = [(spec.time_column, f"logger.{spec.name}.time.column")]
    for ch in spec.channels.values():
        needed += [(c, f"logger.{spec.name}.channels.{ch.name}") for c in ch.columns]
    frame = _cells(spec, needed)
    dropped = 0
    fixes = spec.channels["velocity"] if fixes_feed_velocity((spec,)) else None
    if fixes:   # a row without a fix: the receiver lost it
        no_fix = (frame[[c for c, _ in needed[1:]]].apply(lambda col: col.str.strip()) == "").all(axis=1)
        frame, dropped = frame[~no_fix], int(no_fix.sum())
    if len(frame) < MIN_ROWS:
        _fail_file(spec, "", f"{len(frame)} data rows, fewer than {MIN_ROWS}", "give the logger's full record")
    t = _times(spec, frame)
    steps = np.diff(t)
    if (steps <= 0).any():
        i = int(np.flatnonzero(steps <= 0)[0]) + 1
        _fail_file(spec, f"{_row(spec, i, frame)}, column '{spec.time_column}'",
                   f"time not strictly increasing ({t[i - 1]:.10g} s then {t[i]:.10g} s)",
                   "sort the rows by time and remove repeated samples")
    channels = {}
    if fixes:   # the logger holds nothing else (import_velocity.velocity_from_fixes): its rows become the pairs
        position, altitude = fixes.parts
        lat, lon = (_numbers(spec, frame, c) * position.factor for c in position.columns)
        _check_fixes(spec, position, lat, lon, frame)
        alt = _numbers(spec, frame, altitude.columns[0]) * altitude.factor + altitude.ground
        t, channels["velocity"], channels["altitude"], channels["pair_span"] = pair_rows(t, lat, lon, alt)
        return LoggerRecord(spec, t, channels, dropped)
    for ch in spec.channels.values():
        if ch.parts:   # a track: ground speed, course (deg), vertical speed up → north, east, down
            speed, course, up = (_numbers(spec, frame, p.columns[0]) * p.factor * p.sign for p in ch.parts)
            channels[ch.name] = np.column_stack([speed * np.cos(np.radians(course)),
                                                 speed * np.sin(np.radians(course)), -up])
            continue
        columns = [_numbers(spec, frame, c) * ch.factor * ch.sign for c in ch.columns]
        channels[ch.name] = columns[0] + ch.ground if len(columns) == 1 else np.stack(columns, axis=1)
    return LoggerRecord(spec, t, channels, dropped)


# ---------------------------------------------------------------------------
# the bundle


# Channels a logger bundle keeps at their own logger's samples (blank elsewhere): their loggers do not bound
# the record, so a receiver switched on late leaves blank cells rather than a shorter record.
OWN_SAMPLES = ("velocity", "altitude")


def _feeds_bundle(spec, import_map):
    own = OWN_SAMPLES if import_map.air_data == "reconstruct" else ()
    return spec.name == import_map.g_logger or any(n not in ("accel",) + own for n in spec.channels)


def _rows(import_map, records, offsets, release):
    """The G logger's sample indices in the record window, inside every bundle-feeding logger's span."""
    g_name = import_map.g_logger
    t = records[g_name].time + offsets[g_name].offset
    start = release + import_map.record_start
    spans = [(rec.time[0] + offsets[name].offset, rec.time[-1] + offsets[name].offset)
             for name, rec in records.items() if _feeds_bundle(rec.spec, import_map)]
    first, last = max(s for s, _ in spans), min(e for _, e in spans)
    end = release + import_map.record_end if import_map.record_end is not None else \
        min(last, start + MAX_DURATION)
    idx = np.flatnonzero((t >= max(start, first)) & (t <= min(end, last)))
    if idx.size < MIN_ROWS:
        raise InputError(import_map.path, "key 'record'",
                         f"fewer than {MIN_ROWS} samples of logger '{g_name}' lie between {import_map.record_start:g} "
                         f"and {'the end' if import_map.record_end is None else f'{import_map.record_end:g} s'} after "
                         f"release, where every logger has data ({first - release:.6g} … {last - release:.6g} s "
                         "after release)", "check [record] start and end, and the loggers' offsets")
    return idx, t[idx]


def _interpolated(import_map, records, offsets, channel, times):
    """A channel's values at ``times`` on the reference clock, linear between its logger's samples."""
    spec = import_map.feeder(channel)
    rec, off = records[spec.name], offsets[spec.name].offset
    values = rec.channels[channel]
    if values.ndim == 2:
        return np.stack([np.interp(times, rec.time + off, values[:, k]) for k in range(values.shape[1])], axis=1)
    return np.interp(times, rec.time + off, values)


def _own_samples(import_map, records, offsets, channel, lo, hi, key=None):
    """A channel's own samples from ``lo`` to ``hi`` on the reference clock: (times, values); ``key``: another of
    its logger record's arrays at the same samples (a pair of fixes' span)."""
    spec = import_map.feeder(channel)
    rec = records[spec.name]
    t = rec.time + offsets[spec.name].offset
    keep = (t >= lo) & (t <= hi)
    return t[keep], rec.channels[key or channel][keep]


def _source(import_map, channel, how=""):
    spec = import_map.feeder(channel)
    ch = spec.channels[channel]
    if ch.ground:
        how += f", above ground at {ch.ground:.1f} m above sea level"
    elif channel == "altitude" and import_map.feeder("density") is None and import_map.feeder("qbar") is None:
        how += ", taken as above sea level (a height above ground: give altitude's ground = the site's elevation)"
    return f"{spec.name}: {', '.join(ch.columns)} ({ch.unit}{', sign -1' if ch.sign < 0 else ''}){how}"


# pairs of fixes a second: below it (fixes under 2 Hz) the latency is poorly identified (1 Hz fixes on the import
# tests' windy drop, 6 seeds: latency off by up to 0.33 s, q̄ by up to 17 %, reduce's 1-sigma short in 2 of 6)
MIN_PAIR_RATE = 1.0
SNAP = 1e-6   # s: a receiver sample this close to an accelerometer row shares its row (no near-duplicate times)


def _snapped(times, rows):
    """``times`` moved onto the nearest of ``rows`` (sorted) where within SNAP of it."""
    i = np.clip(np.searchsorted(rows, times), 1, len(rows) - 1)
    nearest = np.where(np.abs(rows[i - 1] - times) <= np.abs(rows[i] - times), rows[i - 1], rows[i])
    return np.where(np.abs(nearest - times) <= SNAP, nearest, times)


def _receiver_sigmas(import_map, records, offsets, meta, t_rows, g_rows):
    """The receiver's 1-sigmas in SI at its samples within the rows ``t_rows``: ((north, east, up), altitude);
    per pair of fixes when its velocity is differenced from them (data/import_velocity.py, with the truncation
    the load factor ``g_rows`` sizes), else the map's constants."""
    u, sigma = meta.units, meta.sigma
    h_sigma = u.si(float(sigma["altitude"]), "length")
    if not fixes_feed_velocity(import_map.loggers):
        return [u.si(float(sigma[c]), "speed") for c in VELOCITY_COLUMNS], h_sigma
    t, span = _own_samples(import_map, records, offsets, "velocity", t_rows[0], t_rows[-1], key="pair_span")
    latencies = np.arange(LATENCY_RANGE[0], LATENCY_RANGE[1] + 1e-9, 0.05)   # the reconstruction's prior range
    truncation = pair_truncation(t_rows, np.asarray(g_rows, float) * G0, t, span, latencies)
    across, up, h_sigma = pair_sigmas(span, u.si(import_map.position_sigma, "length"), h_sigma, truncation)
    return [across, across, up], h_sigma


def _assemble_logger(import_map, records, offsets, meta, t_rows, idx, release):
    """A logger bundle's columns in SI and where each came from: G and the parachute channels at the
    accelerometer's rows, the velocity (north, east, up) and the altitude at their loggers' own samples within
    them, blank elsewhere (docs/test-bundle.md, "Logger bundles"). Nothing is interpolated across the receiver's
    samples, so its latency stays a parameter of the reconstruction instead of being smeared into the rows."""
    lo, hi = t_rows[0], t_rows[-1]
    t_v, velocity = _own_samples(import_map, records, offsets, "velocity", lo, hi)
    t_h, altitude = _own_samples(import_map, records, offsets, "altitude", lo, hi)
    t_v, t_h = _snapped(t_v, t_rows), _snapped(t_h, t_rows)
    times = np.union1d(np.union1d(t_rows, t_v), t_h)

    def placed(at, values):
        out = np.full(len(times), np.nan)
        out[np.searchsorted(times, at)] = values
        return out

    u, sigma = meta.units, meta.sigma
    g_rec = records[import_map.g_logger]
    accel = g_rec.spec.channels["accel"]
    g_rows = load_factor(g_rec.channels["accel"], sigma["G"])[idx]
    columns = {"time": times - release, "G": placed(t_rows, g_rows), "G_sigma": placed(t_rows, float(sigma["G"]))}
    sources = {"time": f"{g_rec.spec.name}: {g_rec.spec.time_column} − release, with the receiver's samples",
               "G": _source(import_map, "accel",
                            " magnitude less its noise bias / g0" if len(accel.columns) == 3 else " / g0")}
    v_sigma, h_sigma = _receiver_sigmas(import_map, records, offsets, meta, t_rows, g_rows)
    for k, column in enumerate(VELOCITY_COLUMNS):   # the map's velocity is north, east, down
        columns[column] = placed(t_v, velocity[:, k] if k < 2 else -velocity[:, 2])
        columns[f"{column}_sigma"] = placed(t_v, v_sigma[k])
    fixes = fixes_feed_velocity(import_map.loggers)
    sources["v_north, v_east, v_up"] = _source(import_map, "velocity", " north, east, −down, at its own samples"
                                               + (" (differences of pairs of fixes)" if fixes else ""))
    columns["altitude"] = placed(t_h, altitude)
    columns["altitude_sigma"] = placed(t_h, h_sigma)
    sources["altitude"] = _source(import_map, "altitude", ", at its own samples" + (" (means of pairs of fixes)"
                                                                                   if fixes else ""))
    if import_map.feeder("density") is not None:
        columns["density"] = placed(t_h, _interpolated(import_map, records, offsets, "density", t_h))
        sources["density"] = _source(import_map, "density", ", at the altitude's samples")
    sources["qbar"] = ("reconstructed by reduce and fit from G, the velocity, the altitude and the wind "
                       "(a logger bundle)")
    for p in meta.parachutes:
        for column, name, key, quantity in ((p.load_cell, p.load_column, "load_cell", "force"),
                                            (p.flyout_angle, p.angle_column, "flyout_angle", None)):
            if column:
                columns[name] = placed(t_rows, _interpolated(import_map, records, offsets, column, t_rows))
                value = float(sigma[column]) if key == "load_cell" else float(sigma.get(column, 0.0))
                columns[f"{name}_sigma"] = placed(t_rows, u.si(value, quantity) if quantity else value)
                sources[column] = _source(import_map, column)
    return pd.DataFrame(columns), sources


def _assemble(import_map, records, offsets, meta, t_rows, idx, release):
    """The bundle's columns in SI, and where each came from."""
    if import_map.air_data == "reconstruct":
        return _assemble_logger(import_map, records, offsets, meta, t_rows, idx, release)

    def at_rows(channel):
        return _interpolated(import_map, records, offsets, channel, t_rows)

    def source(channel, how=""):
        return _source(import_map, channel, how)

    def has(channel):
        return import_map.feeder(channel) is not None

    g_rec = records[import_map.g_logger]
    columns = {"time": t_rows - release, "G": load_factor(g_rec.channels["accel"], meta.sigma["G"])[idx]}
    accel = g_rec.spec.channels["accel"]
    sources = {"time": f"{g_rec.spec.name}: {g_rec.spec.time_column} − release",
               "G": source("accel", " magnitude less its noise bias / g0" if len(accel.columns) == 3 else " / g0")}
    velocity = at_rows("velocity") if has("velocity") else None
    if has("airspeed"):
        columns["airspeed"], sources["airspeed"] = at_rows("airspeed"), source("airspeed")
    else:
        columns["airspeed"] = np.linalg.norm(velocity, axis=1)
        sources["airspeed"] = source("velocity", " |v|: ground speed, no wind")
    if has("gamma"):
        columns["gamma"], sources["gamma"] = at_rows("gamma"), source("gamma")
    elif velocity is not None:
        columns["gamma"] = np.degrees(np.arctan2(-velocity[:, 2], np.hypot(velocity[:, 0], velocity[:, 1])))
        sources["gamma"] = source("velocity", " atan2(-v_down, horizontal speed)")
    else:
        ratio = at_rows("vertical_speed") / np.maximum(columns["airspeed"], 1e-9)
        columns["gamma"] = np.degrees(np.arcsin(np.clip(ratio, -1.0, 1.0)))
        sources["gamma"] = source("vertical_speed", " asin(v_up / airspeed)")
    if has("altitude"):
        columns["altitude"], sources["altitude"] = at_rows("altitude"), source("altitude")
    if has("density"):
        columns["density"], sources["density"] = at_rows("density"), source("density")
    elif "altitude" in columns:
        try:
            columns["density"] = standard_density(columns["altitude"], geopotential=False)
        except ValueError as exc:
            spec = import_map.feeder("altitude")
            raise InputError(spec.path, f"column '{spec.channels['altitude'].columns[0]}'", str(exc),
                             "check the altitude column and its unit in the map") from None
        sources["density"] = "1976 standard atmosphere at the altitude"
    if has("qbar"):
        columns["qbar"], sources["qbar"] = at_rows("qbar"), source("qbar")
    else:
        columns["qbar"] = 0.5 * columns["density"] * columns["airspeed"] ** 2
        sources["qbar"] = "½ ρ airspeed²"
    u, sigma = meta.units, meta.sigma
    columns["G_sigma"] = np.full(len(t_rows), float(sigma["G"]))
    columns["qbar_sigma"] = np.full(len(t_rows), u.si(float(sigma["qbar"]), "pressure"))
    for p in meta.parachutes:
        if p.load_cell:
            columns[p.load_column], sources[p.load_cell] = at_rows(p.load_cell), source(p.load_cell)
            columns[f"{p.load_column}_sigma"] = np.full(len(t_rows), u.si(float(sigma[p.load_cell]), "force"))
        if p.flyout_angle:
            columns[p.angle_column], sources[p.flyout_angle] = at_rows(p.flyout_angle), source(p.flyout_angle)
            columns[f"{p.angle_column}_sigma"] = np.full(len(t_rows), float(sigma.get(p.flyout_angle, 0.0)))
    return pd.DataFrame(columns), sources


def describe(result) -> list:
    """What the import found, one line each: loggers (rows, rate, clock offset ± sigma), events, channel sources."""
    lines = []
    for name, rec in result.records.items():
        off = result.offsets[name]
        clock = {"reference": "reference clock", "given": f"offset {off.offset:+.4f} s (given)"}.get(off.method)
        if clock is None:
            al = off.alignment
            other = "none" if math.isnan(al.runner_up) else f"{al.runner_up:.2f}"
            clock = (f"offset {off.offset:+.4f} ± {off.sigma:.4f} s (auto: correlation {al.correlation:.2f}, "
                     f"next best {other})")
        rows = (f"{len(rec.time):,} pairs of fixes (rows) at {rec.rate:.1f} Hz"
                + (f", {rec.rows_without_fix:,} rows without a fix left out" if rec.rows_without_fix else "")
                if "pair_span" in rec.channels else f"{len(rec.time):,} rows at {rec.rate:.1f} Hz")
        lines.append(f"{name}: {rec.spec.path.name}, {rows}, {clock}")
        if "pair_span" in rec.channels and rec.rate < MIN_PAIR_RATE:
            lines.append(f"warning: logger '{name}': fixes at {2 * rec.rate:.1f} Hz, fewer than {2 * MIN_PAIR_RATE:g}: "
                         "their pairs' velocities are means over more than half a second, which say little of the "
                         "receiver's latency, and reduce's q̄ 1-sigma (linearised about one latency) may understate "
                         "its error near the snatch; the fit, which samples the latency, is the one to read")
        if off.disagreement is not None:
            q = off.disagreement
            lines.append(f"warning: logger '{name}': the signals both loggers see match at offset {q.offset:+.4f} ± "
                         f"{q.sigma:.4f} s (correlation {q.correlation:.2f}), {q.offset - off.offset:+.3f} s from the "
                         f"map's offset; check logger.{name}.offset, or write offset = \"auto\"")
    rel, line = result.release, result.line_stretch
    lines.append(f"release at {rel.time:.4f} ± {rel.sigma:.4f} s on {result.import_map.reference}'s clock"
                 f"{' (given)' if result.release_given else ''}: time 0 of the bundle")
    lines.append(f"line stretch {line.time:.4f} ± {line.sigma:.4f} s after release"
                 f"{' (given)' if result.line_stretch_given else ''}")
    lines += [f"{channel} <- {source}" for channel, source in result.sources.items()]
    return lines


def import_loggers(import_map, folder) -> ImportResult:
    """Read the loggers of a checked map, align them, find the events and assemble the bundle (nothing written).

    ``folder`` (the output bundle) names the test when the map's [test] has no name.
    """
    records = {spec.name: read_logger(spec) for spec in import_map.loggers}
    offsets = clock_offsets(import_map, records)
    g_rec = records[import_map.g_logger]
    release, line = find_events(import_map, g_rec, g_rec.time + offsets[import_map.g_logger].offset)
    meta = bundle_metadata(import_map, {"release": (0.0, 0.0), "line_stretch": (line.time, line.sigma)}, folder)
    idx, t_rows = _rows(import_map, records, offsets, release.time)
    data, sources = _assemble(import_map, records, offsets, meta, t_rows, idx, release.time)
    test = FlightTest(name=meta.name, phase=meta.phase, units=meta.units, vehicle=meta.vehicle,
                      parachutes=meta.parachutes, data=data, priors_files=meta.priors_files,
                      air_data=meta.air_data)
    return ImportResult(test, import_map, records, offsets, release, line, sources,
                        release_given=import_map.release is not None,
                        line_stretch_given=import_map.line_stretch is not None)


def _logger_rows(result, where):
    """Where a refused data.csv row came from: its time, and each logger's nearest sample as its file's row."""
    found = re.match(r"row (\d+)\b", where or "")
    i = int(found.group(1)) - 2 if found else -1     # data.csv's row 2 is the first sample
    if not 0 <= i < len(result.test.data):
        return ""
    t = float(result.test.time[i])
    rows = []
    for name, rec in result.records.items():
        own = t + result.release.time - result.offsets[name].offset       # on the logger's own clock
        rows.append(f"{rec.spec.path.name} {_row(rec.spec, int(np.argmin(np.abs(rec.time - own))))}")
    return f" ({t:.4f} s after release; nearest samples: {', '.join(rows)})"


def write_import(result, out) -> Path:
    """Write the bundle and import.json atomically; the bundle is read back and checked before it is put in place."""
    def verify(tmp):
        try:
            check_reducible(read_bundle(tmp))   # what reduce would refuse before any work, too
        except InputError as exc:
            raise InputError(result.import_map.path, "", f"the bundle made from the loggers would be refused: "
                             f"{Path(exc.file).name}, {exc.where}{_logger_rows(result, exc.where)}: {exc.problem}",
                             f"{exc.fix} (in the map: [record], [test] or a channel's unit)") from None

    text = json.dumps(result.report(), indent=2, allow_nan=False) + "\n"
    return write_bundle(result.test, Path(out), extra_files={REPORT_NAME: text}, check=verify)


def import_bundle(map_path, out) -> ImportResult:
    """``cpas-bayes import``: read the map and the loggers, and write the bundle folder ``out``."""
    import_map = read_import_map(map_path, out)
    result = import_loggers(import_map, out)
    write_import(result, out)
    return replace(result, test=replace(result.test, source=Path(out)))

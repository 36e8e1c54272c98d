"""The import's clocks and events: every logger's clock on the reference logger's, and release and line
stretch in the G logger's sensed load factor (``cpas-bayes import``, docs/import.md).

t_ref = t_logger + offset, the offset given in the map or found by cross-correlating a signal both loggers
see (:func:`~cpas_bayes.data.logger_events.align_clocks`); the events are the half-level crossings of
:mod:`cpas_bayes.data.logger_events`, unless the map gives them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.units import STANDARD_GRAVITY
from cpas_bayes.data.bundle_air import accelerometer_magnitude
from cpas_bayes.data.logger_events import (Event, EventNotFound, align_clocks, detect_line_stretch, detect_release,
                                           from_acceleration, from_velocity, from_vertical_speed)

@dataclass(frozen=True)
class ClockOffset:
    """t_ref = t_logger + offset, s, with its 1-sigma and how it was obtained."""

    offset: float
    sigma: float
    method: str            # "reference", "given" or "auto"
    alignment: object = None  # the Alignment of an "auto" offset
    disagreement: object = None   # a given offset's: the Alignment the signals clearly prefer, when far from it


# A given offset is questioned when the signals both loggers see match clearly elsewhere: r ≥ 0.9 with the next
# best match (> 2 s away) 0.2 lower, more than 1 s and 10 sigma from it. A receiver's latency (tenths of a
# second) stays below that; a clock slip of seconds, a wrong time zone or a typed digit does not.
QUESTION_CORRELATION, QUESTION_MARGIN, QUESTION_SECONDS, QUESTION_SIGMAS = 0.9, 0.2, 1.0, 10.0


def load_factor(accel, sigma=None):
    """Sensed load factor, g: |a|/g0 for three axes, a/g0 for one signed axis (a in m/s²). With ``sigma`` (each
    axis' 1-sigma, g) three axes give the magnitude less its noise bias, the bundle reader's own (:func:`cpas_bayes.
    data.bundle_air.accelerometer_magnitude`). The events are found on the plain magnitude."""
    accel = np.asarray(accel, float) / STANDARD_GRAVITY
    if accel.ndim == 1:
        return accel
    if sigma is None:
        return np.linalg.norm(accel, axis=1)
    return accelerometer_magnitude(accel, np.full(accel.shape, float(sigma)), np.ones(len(accel), bool))["G"]


def shared_signal(record):
    """What ``record`` shows of the motion both loggers saw, in g, or None (accel, then velocity, then v_up)."""
    ch = record.channels
    if "accel" in ch:
        return from_acceleration(record.time, load_factor(ch["accel"]))
    if "velocity" in ch:
        return from_velocity(record.time, *ch["velocity"].T)
    if "vertical_speed" in ch:
        return from_vertical_speed(record.time, ch["vertical_speed"])
    return None


def clock_offsets(import_map, records) -> dict:
    """Every logger's :class:`ClockOffset` to the reference logger's clock."""
    ref_name = import_map.reference
    ref_signal = None
    offsets = {}
    for spec in import_map.loggers:
        where = f"key 'logger.{spec.name}.offset'"
        if spec.name == ref_name:
            offsets[spec.name] = ClockOffset(0.0, 0.0, "reference")
            continue
        ref_signal = ref_signal or shared_signal(records[ref_name])
        signal = shared_signal(records[spec.name])
        if spec.offset is not None:
            offsets[spec.name] = ClockOffset(spec.offset, 0.0, "given",
                                             disagreement=_questioned(spec.offset, ref_signal, signal))
            continue
        for name, sig in ((ref_name, ref_signal), (spec.name, signal)):
            if sig is None:
                raise InputError(import_map.path, where, f"offset = \"auto\" needs a signal both loggers see, and "
                                 f"logger '{name}' has no accel, velocity or vertical_speed channel",
                                 f"give logger '{spec.name}' offset = <seconds to add to its time>")
        hint = spec.hint
        if hint is None and spec.clock == "wall" and import_map.logger(ref_name).clock == "wall":
            hint = 0.0  # wall clocks agree to within the search window
        try:
            found = align_clocks(ref_signal, signal, hint=hint, search=spec.search)
        except EventNotFound as exc:
            raise InputError(import_map.path, where, f"the clock of logger '{spec.name}' could not be aligned to "
                             f"'{ref_name}': {exc}",
                             "give offset_hint = <approximate seconds to add to its time> (and search = <seconds>), "
                             "or offset = <seconds>") from None
        offsets[spec.name] = ClockOffset(found.offset, found.sigma, "auto", found)
    return offsets


def _questioned(given, ref_signal, signal):
    """The Alignment the shared signals clearly prefer over the ``given`` offset, or None (no shared signal, no
    clear match, or a match near it). The import goes on with the given offset; the alignment is reported."""
    if ref_signal is None or signal is None:
        return None
    try:
        found = align_clocks(ref_signal, signal)
    except EventNotFound:
        return None
    clear = found.correlation >= QUESTION_CORRELATION and not found.runner_up > found.correlation - QUESTION_MARGIN
    far = abs(found.offset - given) > max(QUESTION_SECONDS, QUESTION_SIGMAS * found.sigma)
    return found if clear and far else None


def find_events(import_map, record, t):
    """(release on the reference clock, line stretch after release) of the G logger's record."""
    g = load_factor(record.channels["accel"])
    columns = ", ".join(record.spec.channels["accel"].columns)
    fix = ("check the accel column(s), unit and sign (hanging under the carrier reads +1 g), or give "
           "[events] {} in the map")
    if import_map.release is not None:
        release = Event("release", import_map.release, import_map.release_sigma, math.nan, math.nan, 0.0)
    else:
        try:
            release = detect_release(t, g)
        except EventNotFound as exc:
            raise InputError(record.spec.path, f"column(s) {columns}", str(exc),
                             fix.format("release = <time on the reference clock, s>")) from None
    if import_map.line_stretch is not None:
        line = Event("line stretch", import_map.line_stretch, import_map.line_stretch_sigma, math.nan, math.nan, 0.0)
    else:
        try:
            found = detect_line_stretch(t, g, release.time, import_map.threshold)
        except EventNotFound as exc:
            raise InputError(record.spec.path, f"column(s) {columns}", str(exc),
                             fix.format("line_stretch = <s after release>") + ", or lower "
                             "[events] line_stretch_threshold") from None
        line = replace(found, time=found.time - release.time)
    return release, line

"""Reading a logger bundle: GNSS velocity and altitude in place of measured q̄ (docs/test-bundle.md).

A bundle whose data.csv has neither ``qbar`` nor ``airspeed`` but velocity
columns is a logger bundle. Its rows are the union of the accelerometer's and
the receiver's sample times, so ``G``, the velocity components, ``altitude``,
``density`` and the parachute channels may be blank in a row (NaN in the
test's data); the three velocity components are blank together. Three body
axes may replace ``G``, with or without attitude quaternions
(:func:`read_attitude`, :mod:`cpas_bayes.data.attitude`). Its test.toml
may hold ``[wind]``, ``[atmosphere]`` and ``[rate]``
(:class:`~cpas_bayes.data.air_data.AirDataSpec`); a bundle with measured q̄ may not.

:mod:`cpas_bayes.data.bundle` calls these functions; ``reader`` is its
:class:`~cpas_bayes.data.bundle.TomlReader` (``fail``, ``keys``, ``number``,
``table``, ``units``, ``path``), passed in so that this module does not import
the one that imports it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cpas_bayes.core.errors import BundleError
from cpas_bayes.core.inputs import shown
from cpas_bayes.data import limits
from cpas_bayes.data.air_data import RATE_CHANNELS, RATE_TOLERANCE, RECEIVER_RATES, VELOCITY_COLUMNS, \
    WIND_SIGMA_DEFAULT, AirDataSpec, DensityProfile, WindProfile, own_interval, sample_interval
from cpas_bayes.data.attitude import NORM_TOLERANCE, swing_load_factor
from cpas_bayes.data.bundle_csv import TOML_NAME, blank_column
from cpas_bayes.data.limits import check_column, check_value

AIR_TABLES = ("wind", "atmosphere", "rate")
WIND_KEYS = ("altitude", "north", "east", "sigma")
ATMOSPHERE_KEYS = ("altitude", "density")
LOGGER_COLUMNS = VELOCITY_COLUMNS + ("altitude",)   # required in a logger bundle, each with a 1-sigma
ACCEL_AXES = ("accel_x", "accel_y", "accel_z")      # three body axes (g) in place of G: their magnitude is used,
QUATERNION = ("q_w", "q_x", "q_y", "q_z")           # or with attitude their drag component (data/attitude.py)
MEASURED_COLUMNS = ("qbar", "airspeed")
# Unit conversion of a logger bundle's own columns (bundle.COLUMN_QUANTITY holds these too).
LOGGER_QUANTITY = {**{c: "speed" for c in VELOCITY_COLUMNS}, **{f"{c}_sigma": "speed" for c in VELOCITY_COLUMNS},
                   "altitude_sigma": "length"}
MIN_G_SAMPLES = 10          # fewer accelerometer samples cannot resolve an inflation
MIN_VELOCITY_SAMPLES = 3    # a velocity history needs a start, an end and one sample between

EITHER_FIX = ("either give qbar, its sigma, airspeed and gamma (measured air data), or give v_north, v_east, "
              "v_up and altitude with their sigmas (a logger bundle; docs/test-bundle.md, \"Logger bundles\")")


def logger_bundle(names):
    """What data.csv's column ``names`` make of the bundle: True a logger bundle (no ``qbar`` or
    ``airspeed``, a velocity column), False one with measured air data (``qbar`` or ``airspeed``), None
    neither (refused by :func:`check_measured_columns`) or ``names`` unknown (None: data.csv unread)."""
    if names is None:
        return None
    names = set(names)
    if names & set(MEASURED_COLUMNS):
        return False
    return True if names & set(VELOCITY_COLUMNS) else None


def sigma_channels(logger):
    """The vehicle channels [sigma] may name (parachute columns aside), by :func:`logger_bundle`'s answer."""
    measured, gnss = ("G", "qbar"), ("G",) + ACCEL_AXES + LOGGER_COLUMNS
    return measured if logger is False else gnss if logger else measured + LOGGER_COLUMNS


def check_measured_columns(names, path):
    """Refuse a data.csv (``path``) that gives ``qbar`` without ``airspeed`` or the reverse, or no air data."""
    given = [c for c in MEASURED_COLUMNS if c in names]
    if len(given) == 2:
        return
    if given:
        missing = next(c for c in MEASURED_COLUMNS if c not in given)
        raise BundleError(path, f"column '{missing}'", f"missing column '{missing}': data.csv gives '{given[0]}' "
                          f"but not '{missing}' (a bundle with measured air data needs qbar, airspeed and gamma)",
                          EITHER_FIX)
    raise BundleError(path, "columns 'qbar', 'airspeed'", "missing columns: data.csv gives neither qbar and "
                      "airspeed (measured air data) nor v_north, v_east and v_up (GNSS velocity)", EITHER_FIX)


# ---------------------------------------------------------------------------
# test.toml: [wind], [atmosphere], [rate]

def _is_number(value):
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _levels(reader, table, key, where, spec, what, count=None):
    """One array of a profile table, in the bundle's units: finite, plausible, ``count`` long when given."""
    place, values = f"{where}.{key}", table.get(key)
    if values is None:
        reader.fail(place, "is missing", f"add {key} = [<number>, ...], one value per altitude level")
    if not isinstance(values, list) or not values:
        reader.fail(place, f"must be a non-empty array of numbers, got {shown(values)}",
                    f"write {key} = [<number>, ...], one value per altitude level (one level: a constant)")
    for i, v in enumerate(values):
        if not _is_number(v) or not math.isfinite(v):
            reader.fail(f"{place}[{i}]", f"must be a finite number, got {shown(v)}", f"write a number in {key}")
        check_value(v, spec, reader.units, reader.path, f"{place}[{i}]", what)
    if count is not None and len(values) != count:
        reader.fail(place, f"has {len(values)} value(s) but {where}.altitude has {count}",
                    f"give one {key} value per altitude level, in the order of {where}.altitude")
    return np.array(values, dtype=float)


def _altitudes(reader, table, where):
    h = _levels(reader, table, "altitude", where, limits.CHANNELS["altitude"], "altitude")
    bad = np.flatnonzero(np.diff(h) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        reader.fail(f"{where}.altitude[{i}]", f"altitudes not strictly increasing ({h[i - 1]:g} then {h[i]:g})",
                    f"list the levels of [{where}] from the lowest up, each altitude once")
    return h


def _wind(reader, table):
    reader.keys(table, WIND_KEYS, "wind")
    u, spec = reader.units, limits.AIR_DATA["wind"]
    h = _altitudes(reader, table, "wind")
    north = _levels(reader, table, "north", "wind", spec, "wind toward north", len(h))
    east = _levels(reader, table, "east", "wind", spec, "wind toward east", len(h))
    sigma = reader.number(table, "sigma", "wind.", minimum=0, optional=True, plausible=spec.sigma())
    sigma = WIND_SIGMA_DEFAULT if sigma is None else float(u.si(sigma, "speed"))
    return WindProfile(u.si(h, "length"), u.si(north, "speed"), u.si(east, "speed"), sigma)


def _atmosphere(reader, table):
    reader.keys(table, ATMOSPHERE_KEYS, "atmosphere")
    h = _altitudes(reader, table, "atmosphere")
    rho = _levels(reader, table, "density", "atmosphere", limits.CHANNELS["density"], "density", len(h))
    return DensityProfile(reader.units.si(h, "length"), reader.units.si(rho, "density"))


def parse_air_tables(doc, reader, logger):
    """test.toml's [wind], [atmosphere] and [rate] in SI: an :class:`AirDataSpec` unless ``logger`` is False
    (a bundle with measured q̄, which may not hold them: None)."""
    if logger is False:
        return None
    tables = {key: reader.table(doc, key, "") for key in AIR_TABLES if key in doc}
    rates, unused = {}, ()
    if "rate" in tables:
        reader.keys(tables["rate"], RATE_CHANNELS + RECEIVER_RATES, "rate")
        rates = {k: reader.number(tables["rate"], k, "rate.", positive=True, plausible=limits.AIR_DATA["rate"])
                 for k in tables["rate"]}
        unused = tuple(k for k in rates if k in RECEIVER_RATES)
        rates = {k: v for k, v in rates.items() if k not in RECEIVER_RATES}
    return AirDataSpec(wind=_wind(reader, tables["wind"]) if "wind" in tables else None,
                       atmosphere=_atmosphere(reader, tables["atmosphere"]) if "atmosphere" in tables else None,
                       rates=rates, unused_rates=unused)


def receiver_rate_warnings(spec):
    """validate's words on [rate] keys of the receiver's channels: accepted, not used (the model takes the
    receiver's velocity and altitude as instantaneous samples stamped late by a fitted latency)."""
    return [f"test.toml [rate] {key} is not used: the model treats the receiver's velocity and altitude as "
            "instantaneous samples stamped late by a fitted latency; only the accelerometer's averaging ([rate] G) "
            f"is modelled. Remove '{key}' to silence this" for key in (spec.unused_rates if spec else ())]


def check_declared_rate(time, present, rates, toml_path):
    """Refuse a declared ``[rate] G`` (Hz) that disagrees with the readings' own rate by more than RATE_TOLERANCE.

    ``time`` is data.csv's time column (s), ``present`` the rows holding an accelerometer reading, ``rates``
    the declared rates (:class:`AirDataSpec`'s). The rate sets the window the model averages each reading's
    prediction over (1/rate): on 20 Hz readings a declared 1,000 Hz would leave the averaged-away part of a fast
    peak to the inflation parameters, silently."""
    if "G" not in rates:
        return
    t = np.asarray(time, float)[np.asarray(present, bool)]
    interval = own_interval(t)
    if interval <= 0.0:
        return
    declared, shown_rate = float(rates["G"]), 1.0 / interval
    if abs(declared * interval - 1.0) <= RATE_TOLERANCE:
        return
    raise BundleError(toml_path, "key 'rate.G'", f"[rate] G = {declared:g} Hz, but data.csv's time column shows "
                      f"the accelerometer's {t.size} readings {interval * 1e3:.4g} ms apart, {shown_rate:.4g} Hz "
                      f"(more than {RATE_TOLERANCE * 100:g} % off): the model would average each reading over "
                      f"{1e3 / declared:.4g} ms, not the {interval * 1e3:.4g} ms between readings",
                      f"declare G = {shown_rate:.4g}, or remove the entry (the readings' own spacing is then used)")


def refuse_air_tables(doc, reader, logger):
    """Refuse [wind], [atmosphere] or [rate] in a bundle with measured q̄ (``logger`` False)."""
    given = [key for key in AIR_TABLES if key in doc]
    if logger is False and given:
        reader.fail(given[0], f"[{given[0]}] is for a logger bundle, but data.csv has a qbar or airspeed column: a "
                    "bundle with measured qbar already has its airspeed",
                    f"remove the [{given[0]}] table, or drop qbar, airspeed and gamma from data.csv and give v_north, "
                    "v_east, v_up and altitude (a logger bundle)")


# ---------------------------------------------------------------------------
# data.csv

def refuse_conflicts(names, meta, csv_path):
    """Refuse what data.csv (column ``names``) and test.toml (``meta``) both say, where one would silently
    win: a channel's 1-sigma as a ``<column>_sigma`` column and a [sigma] entry; in a logger bundle ``G``
    beside the body axes, a 1-sigma for the accelerometer form data.csv does not give (``G`` beside the axes,
    ``accel_*`` beside ``G``), and a ``density`` column beside an [atmosphere] profile."""
    toml_path = Path(csv_path).parent / TOML_NAME
    names, logger = set(names), logger_bundle(names)
    if logger is None:          # neither kind: check_measured_columns says so first
        return
    for key in meta.sigma:
        if f"{key}_sigma" in names:
            raise BundleError(toml_path, f"key 'sigma.{key}'", f"the 1-sigma of '{key}' is given twice: here and "
                              f"as data.csv's column '{key}_sigma'", f"keep one: remove '{key}' from [sigma] (the "
                              f"column gives each sample its own 1-sigma) or remove the column '{key}_sigma'")
    if not logger:
        return
    axes = [c for c in ACCEL_AXES if c in names]
    if "G" in names and axes:
        raise BundleError(csv_path, f"columns 'G', {', '.join(repr(c) for c in axes)}", "data.csv gives both G "
                          "and accelerometer body axes: two readings of one accelerometer, and one would be "
                          "ignored", "keep G (the sensed load factor, g) or accel_x, accel_y, accel_z (three body "
                          "axes, g), not both")
    # A 1-sigma for the accelerometer form data.csv does not use would be ignored while the other's is used: with
    # the three axes, G is their magnitude (or drag component) and its 1-sigma is propagated from theirs.
    with_axes = "G" not in names and all(c in names for c in ACCEL_AXES)
    if with_axes or "G" in names:       # else logger_columns refuses the missing accelerometer
        form, other = (ACCEL_AXES, ("G",)) if with_axes else (("G",), ACCEL_AXES)
        stated = next((k for k in other if k in meta.sigma), None)
        if stated:
            raise BundleError(toml_path, f"key 'sigma.{stated}'", f"a 1-sigma for '{stated}', but data.csv gives "
                              f"the accelerometer as {', '.join(form)}"
                              + (", from whose 1-sigmas G's is propagated" if with_axes else "")
                              + ": this entry would be ignored", f"remove '{stated}' from [sigma]"
                              + (" and give the axes' 1-sigmas (accel_x = ... there, or accel_x_sigma, ... columns)"
                                 if with_axes else " (G's 1-sigma is [sigma] G or the column 'G_sigma')"))
        if with_axes and "G_sigma" in names:
            raise BundleError(csv_path, "column 'G_sigma'", "a 1-sigma column for G, but data.csv gives the "
                              "accelerometer as accel_x, accel_y, accel_z, from whose 1-sigmas G's is propagated: "
                              "the column would be ignored", "remove the column 'G_sigma' and give the axes' "
                              "1-sigmas (accel_x_sigma, ... columns, or accel_x = ... under [sigma])")
    if "density" in names and meta.air_data is not None and meta.air_data.atmosphere is not None:
        raise BundleError(toml_path, "key 'atmosphere'", "a density profile is given here and as data.csv's column "
                          "'density': two densities for one flight, and one would be ignored",
                          "keep one: remove [atmosphere] (the column gives the density along the record) or the "
                          "column 'density'")


def _channel(raw, column, spec, units, path):
    values = blank_column(raw, column, path)
    return check_column(values, spec, units, path, column) if spec else values


def _sigma(raw, column, values, sigma_table, spec, units, path, required=True):
    """1-sigma of a channel with gaps: its ``<column>_sigma`` column or [sigma] constant where the channel has
    a sample, NaN where it has none; 0 when not ``required`` and not given."""
    name, present = f"{column}_sigma", np.isfinite(values)
    if name in raw.columns:
        sigma = blank_column(raw, name, path)
        negative = np.flatnonzero(sigma < 0)
        if negative.size:
            i = int(negative[0])
            raise BundleError(path, f"row {i + 2}, column '{name}'", f"negative sigma {sigma[i]}",
                              "a 1-sigma is ≥ 0; correct the value")
        check_column(sigma, spec.sigma(), units, path, name)
        gaps = np.flatnonzero(present & np.isnan(sigma))
        if gaps.size:
            raise BundleError(path, f"row {int(gaps[0]) + 2}, column '{name}'",
                              f"the cell is empty, but '{column}' has a sample in this row",
                              f"give the sample's 1-sigma, or leave '{column}' empty too")
    elif column in sigma_table or not required:
        sigma = np.full(len(values), float(sigma_table.get(column, 0.0)))
    else:
        raise BundleError(path, f"column '{name}'", f"no 1-sigma for '{column}' (required in a logger bundle)",
                          f"add a '{name}' column, or '{column} = <sigma>' under [sigma] in test.toml")
    # a required channel's samples are weighed by 1/sigma: zero claims a perfect sensor and breaks the fit
    zero = np.flatnonzero(present & (sigma == 0)) if required else np.array([], int)
    if zero.size:
        in_csv = name in raw.columns
        where = f"row {int(zero[0]) + 2}, column '{name}'" if in_csv else f"key 'sigma.{column}'"
        raise BundleError(path if in_csv else Path(path).parent / TOML_NAME, where,
                          f"a 1-sigma of 0 for a sample of '{column}' (no sensor is exact)",
                          "give the sensor's 1-sigma (its noise, e.g. from the data sheet or a still period)")
    return np.where(present, sigma, np.nan)


def _enough(values, minimum, column, what, path):
    n = int(np.isfinite(values).sum())
    if n < minimum:
        raise BundleError(path, f"column '{column}'", f"{n} {what} sample(s), fewer than {minimum}",
                          f"a logger bundle needs at least {minimum} non-empty '{column}' cells; add the samples")


def parachute_channels(parachutes, names, path):
    """(column, canonical name, limits kind, test.toml key) of each parachute's load cell and fly-out angle;
    refuses one that data.csv (``path``, column ``names``) lacks."""
    for p in parachutes:
        for column, canonical, kind, what in ((p.load_cell, p.load_column, "F", "load_cell"),
                                              (p.flyout_angle, p.angle_column, "theta", "flyout_angle")):
            if not column:
                continue
            if column not in names:
                raise BundleError(path, f"column '{column}'",
                                  f"parachute {p.id!r} names {what} '{column}' but data.csv has no such column",
                                  f"add the column or remove {what} from parachute {p.id!r} in test.toml")
            yield column, canonical, kind, what


def read_axes(raw, sigma_table, units, path):
    """The three body axes ``accel_x, accel_y, accel_z`` (g): values (N, 3), 1-sigmas (N, 3) from
    ``accel_<i>_sigma`` or [sigma], and the rows that hold a reading (N,); refuses a reading missing an axis."""
    spec = limits.CHANNELS["G"]
    parts = [_channel(raw, c, spec, units, path) for c in ACCEL_AXES]
    present = np.all([np.isfinite(p) for p in parts], axis=0)
    split = np.flatnonzero(np.any([np.isfinite(p) for p in parts], axis=0) & ~present)
    if split.size:
        raise BundleError(path, f"row {int(split[0]) + 2}, columns 'accel_x', 'accel_y', 'accel_z'",
                          "an axis is empty where the others are given", "give all three axes of each reading")
    sigmas = [_sigma(raw, c, p, sigma_table, spec, units, path) for c, p in zip(ACCEL_AXES, parts)]
    return np.column_stack(parts), np.column_stack(sigmas), present


def accelerometer_magnitude(axes, sigmas, present):
    """G and G_sigma from :func:`read_axes` without attitude: the magnitude, less its noise bias.

    |a| = √(a_x² + a_y² + a_z²) is the sensed load factor whatever the attitude, but the magnitude of
    noisy axes reads high: the noise across the force adds σ_⊥² = Σσ_i² − σ_∥² to |a|² (σ_∥² = Σ(â_i·σ_i)²,
    the noise along it), by about σ_⊥²/(2|a|) in |a| — most where |a| is small, as in a free fall, where no
    constant accelerometer bias can take it (a simulated drop's scale read 0.952 and its bias 0.05 g, against
    0.984 and 0.015 with it removed). G = √max(|a|² − σ_⊥², 0) is unbiased to first order; its 1-sigma is
    σ_∥ = √Σ(a_i·σ_i)²/|a|.
    """
    axes, sigmas = np.where(present[:, None], axes, 0.0), np.where(present[:, None], sigmas, 0.0)
    squared = np.sum(axes**2, axis=1)
    along = np.sum((axes * sigmas) ** 2, axis=1) / np.maximum(squared, 1e-18)          # σ_∥²
    magnitude = np.sqrt(np.maximum(squared - (np.sum(sigmas**2, axis=1) - along), 0.0))
    sigma = np.sqrt(along)
    # Near zero magnitude the linear rule fails: never below the axes' own mean sigma.
    sigma = np.maximum(sigma, np.sqrt(np.sum(sigmas**2, axis=1) / 3.0))
    return {"G": np.where(present, magnitude, np.nan), "G_sigma": np.where(present, sigma, np.nan)}


def _attitude_fault(path, i, what, fix):
    return BundleError(path, f"row {i + 2}, columns {', '.join(repr(c) for c in QUATERNION)}", what, fix)


def read_attitude(raw, path, present):
    """The readings' attitude quaternions (N, 4), normalised, NaN on rows without a reading (``present``);
    None when data.csv gives none. Refuses a partial quaternion, one without body axes, one whose norm is off
    1 by more than NORM_TOLERANCE, and readings without attitude beside readings with it."""
    given = [c for c in QUATERNION if c in raw.columns]
    if not given:
        return None
    if len(given) < len(QUATERNION):
        missing = next(c for c in QUATERNION if c not in given)
        raise BundleError(path, f"column '{missing}'", f"data.csv gives {', '.join(given)} but not {missing}: an "
                          "attitude quaternion has four components", "add the missing column (q_w, q_x, q_y, q_z, "
                          "scalar first), or remove the quaternion columns (no attitude: the magnitude is used)")
    q = np.column_stack([blank_column(raw, c, path) for c in QUATERNION])
    have = np.isfinite(q)
    full = have.all(axis=1)
    split = np.flatnonzero(have.any(axis=1) & ~full)
    if split.size:
        i = int(split[0])
        blank = ", ".join(c for c, g in zip(QUATERNION, have[i]) if not g)
        raise _attitude_fault(path, i, f"{blank} empty where the other quaternion component(s) are given",
                              "give all four components of the reading's attitude, or leave all four empty")
    orphan = np.flatnonzero(full & ~present)
    if orphan.size:
        i = int(orphan[0])
        what = ("an attitude quaternion, but data.csv gives G: the attitude rotates the body axes accel_x, "
                "accel_y, accel_z, which are used in place of G") if "G" in raw.columns else \
            "an attitude quaternion where accel_x, accel_y, accel_z are empty: the attitude belongs to a reading"
        raise _attitude_fault(path, i, what, "give the quaternion on the rows of the readings it belongs to, with "
                              "accel_x, accel_y, accel_z (and no G column), or remove it")
    if not full.any():
        return None
    bare = np.flatnonzero(present & ~full)
    if bare.size:
        raise _attitude_fault(path, int(bare[0]), "a reading without attitude, while other readings have one: G "
                              "would be the projection on some readings and the magnitude on others",
                              "give the attitude of every reading, remove the readings without it, or remove the "
                              "quaternion columns (no attitude: the magnitude is used)")
    norm = np.linalg.norm(q, axis=1)
    off = np.flatnonzero(full & (np.abs(norm - 1.0) > NORM_TOLERANCE))
    if off.size:
        i = int(off[0])
        raise _attitude_fault(path, i, f"the quaternion's norm is {norm[i]:.6g}, off 1 by {abs(norm[i] - 1.0):.3g} "
                              f"(more than {NORM_TOLERANCE:g}): not a unit quaternion",
                              "normalise each quaternion to unit length; if they are, check the column order: "
                              "q_w, q_x, q_y, q_z hold w, x, y, z, scalar first")
    return q / norm[:, None]


def attitude_load_factor(time, axes, attitude):
    """G and G_sigma with attitude: the specific force along its own time-averaged direction, the drag's
    (:func:`cpas_bayes.data.attitude.swing_load_factor`; neither the wind nor the receiver enters).

    ``time`` is data.csv's (s), ``axes`` :func:`read_axes`'s answer and ``attitude`` :func:`read_attitude`'s.
    """
    a, sigma, present = axes
    g, g_sigma = np.full(len(time), np.nan), np.full(len(time), np.nan)
    g[present], g_sigma[present], _ = swing_load_factor(time[present], attitude[present], a[present], sigma[present])
    return {"G": g, "G_sigma": g_sigma}


def logger_columns(raw, meta, path):
    """A logger bundle's data columns in its own units (time aside), canonical names, NaN where blank.

    ``raw`` is data.csv as cell strings, ``meta`` test.toml's
    :class:`~cpas_bayes.data.bundle.BundleMetadata`. Refuses a missing column,
    a velocity row with one or two blank components, too few samples, a sample
    without its 1-sigma, implausible values and a faulty attitude quaternion,
    naming ``path``, row and column. With attitude, ``G`` is the body axes'
    specific force along the drag direction (:func:`attitude_load_factor`).
    """
    has_axes = "G" not in raw.columns and all(c in raw.columns for c in ACCEL_AXES)
    missing = [c for c in ("G",) + LOGGER_COLUMNS if c not in raw.columns and not (c == "G" and has_axes)]
    if missing:
        listed = ", ".join(f"'{c}'" for c in missing)
        raise BundleError(path, f"column '{missing[0]}'", f"missing column(s) {listed}: a bundle without qbar and "
                          "airspeed is a logger bundle, which needs G (or accel_x, accel_y, accel_z), v_north, "
                          "v_east, v_up and altitude", EITHER_FIX)
    units, sigma_table, channels = meta.units, meta.sigma, limits.CHANNELS
    axes = None
    if has_axes:
        axes = read_axes(raw, sigma_table, units, path)
        out = accelerometer_magnitude(*axes)
        attitude = read_attitude(raw, path, axes[2])
    else:
        out = {"G": _channel(raw, "G", channels["G"], units, path)}
        out["G_sigma"] = _sigma(raw, "G", out["G"], sigma_table, channels["G"], units, path)
        attitude = read_attitude(raw, path, np.zeros(len(raw), bool))   # refuses any quaternion given
    _enough(out["G"], MIN_G_SAMPLES, "G", "accelerometer", path)
    if meta.air_data is not None:
        check_declared_rate(blank_column(raw, "time", path), np.isfinite(out["G"]), meta.air_data.rates,
                            Path(path).parent / TOML_NAME)

    v = {c: _channel(raw, c, channels[c], units, path) for c in VELOCITY_COLUMNS}
    given = np.column_stack([np.isfinite(v[c]) for c in VELOCITY_COLUMNS])
    split = np.flatnonzero(given.any(axis=1) & ~given.all(axis=1))
    if split.size:
        i = int(split[0])
        blank = [c for c, g in zip(VELOCITY_COLUMNS, given[i]) if not g]
        raise BundleError(path, f"row {i + 2}, columns 'v_north', 'v_east', 'v_up'",
                          f"{', '.join(blank)} empty where the other component(s) are given: a GNSS sample gives "
                          "all three components", "fill the empty components, or leave all three empty in this row")
    _enough(v["v_north"], MIN_VELOCITY_SAMPLES, "v_north", "velocity", path)
    out.update(v)
    for c in VELOCITY_COLUMNS:
        out[f"{c}_sigma"] = _sigma(raw, c, v[c], sigma_table, channels[c], units, path)
    out["altitude"] = _channel(raw, "altitude", channels["altitude"], units, path)
    _enough(out["altitude"], 1, "altitude", "altitude", path)
    out["altitude_sigma"] = _sigma(raw, "altitude", out["altitude"], sigma_table, channels["altitude"], units, path)
    if "density" in raw.columns:
        out["density"] = _channel(raw, "density", channels["density"], units, path)
    if attitude is not None:
        out.update(attitude_load_factor(blank_column(raw, "time", path), axes, attitude))

    for column, canonical, kind, _ in parachute_channels(meta.parachutes, raw.columns, path):
        out[canonical] = _channel(raw, column, channels[kind], units, path)
        out[f"{canonical}_sigma"] = _sigma(raw, column, out[canonical], sigma_table, channels[kind], units,
                                           path, required=kind == "F")
    return out


def air_summary(test):
    """A logger bundle's part of ``cpas-bayes validate``'s summary: ``air_data``, one line such as ``"GNSS
    velocity (41 samples at 5 Hz), altitude (41 samples), wind profile (3 levels)"``."""
    spec, data = test.air_data, test.data
    n_v, n_h = (int(np.isfinite(data[c]).sum()) for c in ("v_north", "altitude"))
    step = sample_interval(data, "v_north", None, "v")    # the receiver's own samples: no rate is declared
    parts = [f"GNSS velocity ({n_v} samples at {1 / step:.3g} Hz)" if step > 0 else f"GNSS velocity ({n_v} samples)",
             f"altitude ({n_h} samples)"]
    if spec is not None and spec.wind is not None:
        levels = len(spec.wind.altitude)
        parts.append("constant wind" if levels == 1 else f"wind profile ({levels} levels)")
    if spec is not None and spec.atmosphere is not None:
        parts.append(f"density profile ({len(spec.atmosphere.altitude)} levels)")
    warnings = receiver_rate_warnings(spec)
    return {"air_data": ", ".join(parts), **({"warnings": warnings} if warnings else {})}

"""Flight-test bundles: reading, validating and writing (docs/test-bundle.md).

A bundle is a folder with ``test.toml`` (vehicle, parachutes, stages, units)
and ``data.csv`` (time histories). :func:`read_bundle` returns a
:class:`FlightTest` whose numbers are all SI, with canonical column names:

``time, G, G_sigma, qbar, qbar_sigma, airspeed, gamma`` (deg), optional
``density, altitude``, and per parachute with a load cell ``F_<id>,
F_<id>_sigma``, with a fly-out angle ``theta_<id>, theta_<id>_sigma`` (deg). A logger
bundle has ``v_north, v_east, v_up, altitude`` and their sigmas in place of ``qbar, airspeed,
gamma``, NaN where a channel has no sample, and ``air_data`` (:mod:`cpas_bayes.data.bundle_air`).

Every refusal is a :class:`~cpas_bayes.core.errors.BundleError` naming the file,
the row or key, and the fix, raised while reading, before any work: unknown
keys (with the nearest valid one), unsafe names, implausible values
(:mod:`cpas_bayes.data.limits`), stage starts outside the record, one column
named by two parachutes, and a data.csv beyond its size limits or of the wrong
shape (:mod:`cpas_bayes.data.bundle_csv`). :func:`write_bundle` writes the
format back in the test's own units, atomically.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from cpas_bayes.core.errors import BundleError
from cpas_bayes.core.inputs import MAX_TEXT, check_keys, check_name, check_text, name_problem, nearest, read_toml, shown
from cpas_bayes.core.units import UNIT_SYSTEMS, UnitSystem, unit_system
from cpas_bayes.data import limits
from cpas_bayes.data.air_data import AirDataSpec
from cpas_bayes.data.bundle_air import AIR_TABLES, LOGGER_QUANTITY, check_measured_columns, logger_bundle, \
    logger_columns, parachute_channels, parse_air_tables, refuse_air_tables, refuse_conflicts, sigma_channels
from cpas_bayes.data.bundle_csv import CSV_NAME, TOML_NAME, csv_header, numeric_column, read_csv, sigma_column
from cpas_bayes.data.limits import MAX_COLUMN_NAME, check_column, check_record, check_value

KINDS = ("drogue", "main", "pilot", "fbcp")   # kinds whose priors the package ships; any other needs a priors file
INFLATIONS = ("infinite", "finite")

# Column -> physical quantity, for unit conversion. Angles stay in degrees.
COLUMN_QUANTITY = {"time": "time", "qbar": "pressure", "qbar_sigma": "pressure",
                    "airspeed": "speed", "density": "density", "altitude": "length", **LOGGER_QUANTITY}


@dataclass(frozen=True)
class Stage:
    """One inflation stage: reefed, disreef or full open."""

    label: str
    start: float        # nominal start (bag strip or disreef cutter), s
    start_sigma: float  # its 1-sigma, s


@dataclass(frozen=True)
class Parachute:
    """One canopy of the cluster, in SI (m, N)."""

    id: str
    kind: str
    inflation: str
    diameter: float
    weight: float
    weight_sigma: float
    stages: tuple[Stage, ...]
    load_cell: str | None = None      # column name in the bundle's data.csv
    flyout_angle: str | None = None   # column name in the bundle's data.csv
    diameter_sigma: float = 0.0       # 1-sigma of the nominal diameter, m; > 0 makes D_o a fitted parameter

    @property
    def load_column(self):
        """Canonical column of this riser's tension in :attr:`FlightTest.data`."""
        return f"F_{self.id}" if self.load_cell else None

    @property
    def angle_column(self):
        """Canonical column of this parachute's fly-out angle, deg."""
        return f"theta_{self.id}" if self.flyout_angle else None

    @property
    def stage_starts(self):
        return np.array([s.start for s in self.stages])


@dataclass(frozen=True)
class Vehicle:
    """The suspended test vehicle, canopies excluded, in SI (N, m²)."""

    weight: float
    weight_sigma: float
    cds: float
    cds_sigma: float


@dataclass(frozen=True)
class FlightTest:
    """One flight-test phase: metadata and time histories, all SI."""

    name: str
    phase: str
    units: UnitSystem
    vehicle: Vehicle
    parachutes: tuple[Parachute, ...]
    data: pd.DataFrame = field(repr=False)
    source: Path | None = None
    priors_files: tuple[Path, ...] = ()   # test.toml's own prior files (key ``priors``), resolved
    air_data: AirDataSpec | None = None   # a logger bundle's [wind], [atmosphere], [rate] (data.air_data)

    @property
    def measured_qbar(self):
        """True when data.csv gives q̄ (and airspeed); False for a logger bundle (GNSS velocity and altitude)."""
        return "qbar" in self.data.columns

    @property
    def time(self):
        return self.data["time"].to_numpy()

    @property
    def duration(self):
        t = self.time
        return float(t[-1] - t[0])

    @property
    def sample_rate(self):
        """Median samples per second."""
        return float(1.0 / np.median(np.diff(self.time)))

    @property
    def parachute_weight(self):
        """Sum of the parachutes' dry weights, N."""
        return float(sum(p.weight for p in self.parachutes))

    @property
    def total_weight(self):
        """W_T = W_V + Σ W_p,i, N (Eq. 8)."""
        return self.vehicle.weight + self.parachute_weight

    def parachute(self, pid):
        for p in self.parachutes:
            if p.id == pid:
                return p
        raise KeyError(f"no parachute {pid!r} in test {self.name!r}")

    @property
    def channels(self):
        """Measured channels present, in canonical names (sigmas excluded)."""
        return [c for c in self.data.columns if not c.endswith("_sigma")]

    @property
    def label(self):
        """A short label for messages: the source folder, else the name."""
        return str(self.source) if self.source else self.name

    def kind_keys(self):
        """{kind: (file, key)}: where test.toml names each parachute kind (its first parachute of it)."""
        file = self.source / TOML_NAME if self.source else self.name
        keys = {}
        for p in self.parachutes:
            keys.setdefault(p.kind, (file, f"key 'parachute '{p.id}'.kind'"))
        return keys


# ---------------------------------------------------------------------------
# reading

# Every key test.toml may hold (docs/test-bundle.md); any other is refused with the nearest of these.
TOP_KEYS = ("name", "units", "phase", "priors", "vehicle", "parachute", "sigma")
VEHICLE_KEYS = ("weight", "weight_sigma", "cds", "cds_sigma")
PARACHUTE_KEYS = ("id", "kind", "inflation", "diameter", "diameter_sigma", "weight", "weight_sigma", "load_cell",
                  "flyout_angle", "stage")
STAGE_KEYS = ("label", "start", "start_sigma")
# data.csv columns with a fixed meaning: no parachute's load_cell or flyout_angle may name one of them.
_RESERVED = ("time", "G", "qbar", "airspeed", "gamma", "density", "altitude", "v_north", "v_east", "v_up",
             "accel_x", "accel_y", "accel_z", "q_w", "q_x", "q_y", "q_z")


def _is_number(value):
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class TomlReader:
    """Typed access to test.toml that refuses with file, key and fix."""

    def __init__(self, path, units=None):
        self.path = path
        self.units = units

    def fail(self, key, problem, fix):
        raise BundleError(self.path, f"key '{key}'" if key else "", problem, fix)

    def keys(self, table, valid, where):
        check_keys(table, valid, self.path, where, BundleError)

    def table(self, doc, key, where):
        value = doc.get(key)
        if not isinstance(value, dict):
            self.fail(f"{where}{key}", "the table is missing" if value is None else "is not a table",
                      f"add a [{where}{key}] table as in docs/test-bundle.md")
        return value

    def string(self, doc, key, where, default=None, choices=None):
        value = doc.get(key, default)
        if value is None:
            self.fail(f"{where}{key}", "is missing", f"add {key} = \"...\"")
        if not isinstance(value, str) or not value.strip():
            self.fail(f"{where}{key}", f"must be a non-empty string, got {shown(value)}", f"write {key} = \"...\"")
        if choices and value not in choices:
            near = nearest(value, choices)
            self.fail(f"{where}{key}", f"unknown value {shown(value)}",
                      (f"did you mean '{near}'? " if near else "") + f"use one of {', '.join(map(repr, choices))}")
        return value

    def text(self, doc, key, where, default=None, what=None, max_length=MAX_TEXT):
        """A free-text string that is printed: one printable line."""
        value = self.string(doc, key, where, default=default)
        return check_text(value, self.path, f"key '{where}{key}'", what or key, BundleError, max_length)

    def number(self, doc, key, where, minimum=None, positive=False, optional=False, plausible=None):
        value = doc.get(key)
        if value is None:
            if optional:
                return None
            self.fail(f"{where}{key}", "is missing", f"add {key} = <number>")
        if not _is_number(value) or not math.isfinite(value):
            self.fail(f"{where}{key}", f"must be a finite number, got {shown(value)}", f"write a number for {key}")
        if positive and value <= 0:
            self.fail(f"{where}{key}", f"must be positive, got {value}", f"give {key} a value > 0")
        if minimum is not None and value < minimum:
            what = "a sigma cannot be negative" if key.endswith("sigma") else f"must be ≥ {minimum}"
            self.fail(f"{where}{key}", f"{what}, got {value}", f"give {key} a value ≥ {minimum}")
        if plausible is not None:
            check_value(value, plausible, self.units, self.path, f"{where}{key}", key)
        return float(value)


def _read_toml(path):
    if not (path.exists() or path.is_symlink()):     # a broken link, a folder, a pipe: read_toml says which
        raise BundleError(path, "", "file not found",
                          f"a bundle folder needs {TOML_NAME} and {CSV_NAME} (docs/test-bundle.md)")
    return read_toml(path, error=BundleError, fix_file=f"put the bundle's {TOML_NAME} there as a plain file")


def _column_key(reader, entry, key, where, pid, owners):
    """A parachute's ``load_cell`` / ``flyout_angle`` column name, or None; each column serves one channel."""
    value = entry.get(key)
    if value is None:
        return None
    if not isinstance(value, str) or not value.strip():
        reader.fail(f"{where}{key}", f"must name a data.csv column, got {shown(value)}",
                    f"write {key} = \"<column name>\" or remove the key")
    check_text(value, reader.path, f"key '{where}{key}'", key, BundleError, MAX_COLUMN_NAME)
    if value in _RESERVED or value.endswith("_sigma"):
        reader.fail(f"{where}{key}", f"names column '{value}', which is "
                    + ("a sigma column" if value.endswith("_sigma") else "a channel of the vehicle"),
                    "name the column holding the " + ("riser tension" if key == "load_cell" else "fly-out angle")
                    + f" of parachute {pid!r}")
    if value in owners:
        other, other_key = owners[value]
        share = (" (the reduction would split that one load 50/50 between them)"
                 if key == other_key == "load_cell" else "")
        reader.fail(f"{where}{key}", f"column '{value}' is already the {other_key} of parachute {other!r}{share}",
                    "give each channel of each parachute its own column (a parachute without its own load cell "
                    "has no load_cell key)")
    owners[value] = (pid, key)
    return value


def _parse_parachutes(doc, reader, units):
    chutes = doc.get("parachute")
    if not isinstance(chutes, list) or not chutes:
        reader.fail("parachute", "no [[parachute]] entries", "add one [[parachute]] table per canopy")
    limits.check_count(reader, "parachute", chutes, "parachutes")
    parsed, seen, owners = [], set(), {}
    for i, entry in enumerate(chutes):
        where = f"parachute[{i}]."
        if not isinstance(entry, dict):
            reader.fail(f"parachute[{i}]", "is not a table", "write each parachute as [[parachute]]")
        reader.keys(entry, PARACHUTE_KEYS, f"parachute[{i}]")
        pid = reader.string(entry, "id", where)
        check_name(pid, reader.path, f"key 'parachute[{i}].id'", "parachute id", BundleError)
        if pid == "total" or "_" in pid and pid.rsplit("_", 1)[1] in ("sigma", "raw", "random", "systematic"):
            reader.fail(f"parachute[{i}].id", f"parachute id {pid!r} would give the reduction's columns the "
                        "names of others (load_total, cds_<id>_raw, ..._sigma_random; a sigma column ends with "
                        "'_sigma')", "choose an id that is not 'total' and does not end with '_raw', '_random', "
                        "'_systematic' or '_sigma'")
        where = f"parachute '{pid}'."
        if pid in seen:
            reader.fail(f"parachute[{i}].id", f"duplicate parachute id {pid!r}", "give every parachute a unique id")
        seen.add(pid)
        kind = check_kind(reader.string(entry, "kind", where), reader.path, f"key '{where}kind'", BundleError)
        inflation = reader.string(entry, "inflation", where, choices=INFLATIONS)
        diameter = reader.number(entry, "diameter", where, positive=True, plausible=limits.PARACHUTE["diameter"])
        diameter_sigma = reader.number(entry, "diameter_sigma", where, minimum=0, optional=True) or 0.0
        if diameter_sigma > 0.25 * diameter:
            reader.fail(f"{where}diameter_sigma", f"diameter_sigma = {diameter_sigma} is more than a quarter of "
                        f"the diameter ({diameter})", "give the 1-sigma of the nominal diameter, in the bundle's "
                        "length unit")
        weight_range = limits.PARACHUTE["weight"]
        weight = reader.number(entry, "weight", where, minimum=0, plausible=weight_range)
        weight_sigma = reader.number(entry, "weight_sigma", where, minimum=0, optional=True,
                                     plausible=weight_range.sigma()) or 0.0
        load_cell = _column_key(reader, entry, "load_cell", where, pid, owners)
        flyout = _column_key(reader, entry, "flyout_angle", where, pid, owners)
        stages_raw = entry.get("stage")
        if not isinstance(stages_raw, list) or not stages_raw:
            reader.fail(f"{where}stage", f"parachute {pid!r} has no stages",
                        "add at least one [[parachute.stage]] (the last is full open)")
        limits.check_count(reader, f"{where}stage", stages_raw, "stages")
        stages = []
        for k, st in enumerate(stages_raw):
            swhere = f"{where}stage[{k}]."
            if not isinstance(st, dict):
                reader.fail(f"{where}stage[{k}]", "is not a table", "write each stage as [[parachute.stage]]")
            reader.keys(st, STAGE_KEYS, f"{where}stage[{k}]")
            label = reader.text(st, "label", swhere, default=f"stage {k + 1}", what="stage label")
            start = reader.number(st, "start", swhere)
            start_sigma = reader.number(st, "start_sigma", swhere, minimum=0, optional=True) or 0.0
            if start_sigma > limits.MAX_START_SIGMA:
                reader.fail(f"{swhere}start_sigma", f"start_sigma = {start_sigma} s, more than "
                            f"{limits.MAX_START_SIGMA:g} s (bag strip and cutter times are known to a fraction "
                            "of a second)", "give the 1-sigma of the start time in seconds")
            if stages and start <= stages[-1].start:
                reader.fail(f"{swhere}start",
                            f"stages out of time order: starts at {start} s, not after the previous stage "
                            f"({stages[-1].start} s)", "list stages in time order with increasing start times")
            stages.append(Stage(label, start, start_sigma))
        parsed.append(Parachute(
            id=pid, kind=kind, inflation=inflation,
            diameter=units.si(diameter, "length"), diameter_sigma=units.si(diameter_sigma, "length"),
            weight=units.si(weight, "force"), weight_sigma=units.si(weight_sigma, "force"),
            stages=tuple(stages), load_cell=load_cell, flyout_angle=flyout))
    return tuple(parsed)


PRIORS_SUFFIX = ".toml"
RESERVED_KINDS = ("provenance",)   # memo.toml's own tables sit beside its kinds


def check_kind(kind, file, where, error):
    """A parachute kind: the package's (priors shipped) or the user's own (a safe name whose priors come from
    a file), but never a package kind in other letter case (a typo, not a new kind)."""
    check_name(kind, file, where, "parachute kind", error,
               example=f"{', '.join(repr(k) for k in KINDS)} or a kind of your own with its prior file")
    if kind.lower() in RESERVED_KINDS:
        raise error(file, where, f"{shown(kind)} cannot be a parachute kind: the model memo uses the name for "
                    "its own table", "choose another name for the kind")
    near = next((k for k in KINDS if k == kind.lower() and k != kind), None)
    if near:
        raise error(file, where, f"unknown kind {shown(kind)}", f"did you mean '{near}'? (kinds are lower case)")
    return kind


def _priors_files(doc, reader, folder):
    """test.toml's ``priors``: one relative path or a list, each an existing ``.toml`` file in the bundle's
    folder or its parent (a campaign folder's shared priors), resolved; () when absent."""
    value = doc.get("priors", [])
    items = [value] if isinstance(value, str) else value
    if not isinstance(items, list) or not all(isinstance(v, str) and v.strip() for v in items):
        reader.fail("priors", f"must be a file name or a list of them, got {shown(value)}",
                    'write priors = "rescue.toml" (a file next to test.toml)')
    out = []
    bundle = folder.resolve()
    for i, item in enumerate(items):
        where = "priors" if isinstance(value, str) else f"priors[{i}]"
        if len(item) > 255 or not item.isprintable():
            reader.fail(where, f"{shown(item)} is not a usable file name", "give a short relative path")
        path = Path(item)
        if path.is_absolute():
            reader.fail(where, f"{shown(item)} is an absolute path", "give a path relative to the bundle folder, "
                        "e.g. \"rescue.toml\" or \"../priors/rescue.toml\"")
        if path.suffix != PRIORS_SUFFIX:
            reader.fail(where, f"{shown(item)} is not a .toml file", "name a TOML prior file (see priors/README.md)")
        resolved = (bundle / path).resolve()
        if not (resolved.is_relative_to(bundle) or resolved.is_relative_to(bundle.parent)):
            reader.fail(where, f"{shown(item)} leads outside the bundle's folder and its parent",
                        "keep prior files next to test.toml or in the folder that holds the bundles")
        if not resolved.is_file():
            reader.fail(where, f"prior file {resolved} not found", "create it (template: priors/template.toml) "
                        "or correct the path, which is relative to the bundle folder")
        out.append(resolved)
    return tuple(out)


def _test_name(doc, reader, folder):
    """test.toml's name, else the folder's; either must be a safe name (it becomes a folder of a campaign)."""
    if "name" in doc:
        return check_name(reader.string(doc, "name", ""), reader.path, "key 'name'", "test name", BundleError)
    name = folder.resolve().name
    problem = name_problem(name)
    if problem:
        reader.fail("name", f"no name given, and the folder name {shown(name)} cannot be used: {problem}",
                    "add name = \"...\" to test.toml (1-64 letters, digits, '-', '_', '.', '+' or spaces)")
    return name


def _sigma_table(doc, reader, parachutes, units, logger):
    """The [sigma] table: keys are channels this bundle has, values plausible 1-sigmas in the bundle's units."""
    table = doc.get("sigma", {})
    if not isinstance(table, dict):
        reader.fail("sigma", "is not a table", "write constant sigmas as a [sigma] table")
    specs = {c: limits.CHANNELS[c] for c in sigma_channels(logger)}
    for p in parachutes:
        if p.load_cell:
            specs[p.load_cell] = limits.CHANNELS["F"]
        if p.flyout_angle:
            specs[p.flyout_angle] = limits.CHANNELS["theta"]
    reader.keys(table, tuple(specs), "sigma")
    for key, value in table.items():
        if not _is_number(value) or not math.isfinite(value) or value < 0:
            reader.fail(f"sigma.{key}", f"must be a finite number ≥ 0, got {shown(value)}", "give a 1-sigma ≥ 0")
        check_value(value, specs[key].sigma(), units, reader.path, f"sigma.{key}", f"the 1-sigma of {key}")
    return table


def _check_stages_in_record(parachutes, t, reader, csv_path):
    for p in parachutes:
        for k, st in enumerate(p.stages):
            if not t[0] <= st.start < t[-1]:
                side = "before the record starts" if st.start < t[0] else "at or after the record ends"
                reader.fail(f"parachute '{p.id}'.stage[{k}].start",
                            f"stage {st.label!r} starts at {st.start:g} s, {side} ({csv_path.name} covers "
                            f"{t[0]:g} … {t[-1]:g} s)",
                            "give stage starts in the time base of data.csv, in seconds")


@dataclass(frozen=True)
class BundleMetadata:
    """What test.toml says (SI, as in :class:`FlightTest`), and its constant sigmas in the bundle's units."""

    name: str
    phase: str
    units: UnitSystem
    vehicle: Vehicle
    parachutes: tuple[Parachute, ...]
    sigma: dict
    priors_files: tuple[Path, ...] = ()
    air_data: AirDataSpec | None = None   # a logger bundle's [wind], [atmosphere], [rate], SI


def parse_test_document(doc, path, folder, logger=False) -> BundleMetadata:
    """Check a test.toml document and convert it to SI; raise :class:`BundleError` naming ``path`` and the key.

    ``folder``'s name is the test's name when the document has none. ``logger``: the data.csv beside it makes
    a logger bundle (True), one with measured q̄ (False), or either (None) (:func:`bundle_air.logger_bundle`).
    """
    reader = TomlReader(path)
    refuse_air_tables(doc, reader, logger)
    reader.keys(doc, TOP_KEYS + (AIR_TABLES if logger is not False else ()), "")

    units_name = reader.string(doc, "units", "")
    if units_name not in UNIT_SYSTEMS:
        reader.fail("units", f"unknown units {shown(units_name)}", "use units = \"US\" or units = \"SI\"")
    units = unit_system(units_name)
    reader.units = units
    name = _test_name(doc, reader, Path(folder))
    phase = reader.text(doc, "phase", "", default="unspecified")
    priors_files = _priors_files(doc, reader, Path(folder))

    veh = reader.table(doc, "vehicle", "")
    reader.keys(veh, VEHICLE_KEYS, "vehicle")
    weight, cds = limits.VEHICLE["weight"], limits.VEHICLE["cds"]
    vehicle = Vehicle(
        weight=units.si(reader.number(veh, "weight", "vehicle.", positive=True, plausible=weight), "force"),
        weight_sigma=units.si(reader.number(veh, "weight_sigma", "vehicle.", minimum=0, optional=True,
                                            plausible=weight.sigma()) or 0.0, "force"),
        cds=units.si(reader.number(veh, "cds", "vehicle.", minimum=0, plausible=cds), "area"),
        cds_sigma=units.si(reader.number(veh, "cds_sigma", "vehicle.", minimum=0, optional=True,
                                         plausible=cds.sigma()) or 0.0, "area"),
    )
    parachutes = _parse_parachutes(doc, reader, units)
    sigma_table = _sigma_table(doc, reader, parachutes, units, logger)
    return BundleMetadata(name, phase, units, vehicle, parachutes, sigma_table, priors_files,
                          parse_air_tables(doc, reader, logger))


def read_bundle(folder) -> FlightTest:
    """Read and validate one bundle folder; raise :class:`BundleError` on any fault."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BundleError(folder, "", "not a folder" if folder.exists() else "folder not found",
                          "pass the path of a bundle folder holding test.toml and data.csv")
    toml_path, csv_path = folder / TOML_NAME, folder / CSV_NAME
    # What test.toml may hold depends on the kind of bundle data.csv's columns make (logger or measured q̄).
    meta = parse_test_document(_read_toml(toml_path), toml_path, folder, logger_bundle(csv_header(csv_path)))
    units, parachutes, sigma_table = meta.units, meta.parachutes, meta.sigma
    reader = TomlReader(toml_path, units)

    raw = read_csv(csv_path)
    refuse_conflicts(raw.columns, meta, csv_path)
    columns = {}

    def need(column, why, spec):
        if column not in raw.columns:
            raise BundleError(csv_path, f"column '{column}'", f"missing column ({why})",
                              f"add a '{column}' column to data.csv")
        values = numeric_column(raw, column, csv_path)
        return check_column(values, spec, units, csv_path, column) if spec else values

    def need_sigma(column, canonical, spec, required=True):
        values = sigma_column(raw, column, sigma_table, csv_path)
        if values is None and not required:
            values = np.zeros(len(raw))  # a fly-out angle without a stated sigma: 0
        elif values is None:
            raise BundleError(csv_path, f"column '{column}_sigma'",
                              f"no 1-sigma for '{column}'",
                              f"add a '{column}_sigma' column, or '{column} = <sigma>' under [sigma] in test.toml")
        if f"{column}_sigma" in raw.columns:
            check_column(values, spec.sigma(), units, csv_path, f"{column}_sigma")
        columns[f"{canonical}_sigma"] = values
        return values

    columns["time"] = t = need("time", "required by the bundle format", None)
    if len(t) < 2:
        raise BundleError(csv_path, "column 'time'", "fewer than two samples", "add more rows of data")
    steps = np.diff(t)
    if (steps <= 0).any():
        i = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise BundleError(csv_path, f"row {i + 2}, column 'time'",
                          f"time not strictly increasing ({t[i - 1]} then {t[i]})",
                          "sort the rows by time and remove duplicate samples")
    check_record(t, csv_path)
    _check_stages_in_record(parachutes, t, reader, csv_path)
    if logger_bundle(raw.columns):
        return _flight_test(meta, {**columns, **logger_columns(raw, meta, csv_path)}, folder)
    check_measured_columns(raw.columns, csv_path)
    for col in ("G", "qbar", "airspeed", "gamma"):
        columns[col] = need(col, "required by the bundle format", None)
        if col in limits.DIVISORS and (columns[col] <= 0).any():
            values = columns[col]
            i = int(np.flatnonzero(values <= 0)[0])
            raise BundleError(csv_path, f"row {i + 2}, column '{col}'",
                              f"{col} = {values[i]} ≤ 0, where {limits.DIVISORS[col]}",
                              "trim the rows before the vehicle has airspeed, or repair the value")
        check_column(columns[col], limits.CHANNELS[col], units, csv_path, col)
    for col in ("density", "altitude"):
        if col in raw.columns:
            columns[col] = need(col, "optional", limits.CHANNELS[col])
    need_sigma("G", "G", limits.CHANNELS["G"])
    need_sigma("qbar", "qbar", limits.CHANNELS["qbar"])

    for column, canonical, kind, what in parachute_channels(parachutes, raw.columns, csv_path):
        columns[canonical] = need(column, f"{what} ({canonical})", limits.CHANNELS[kind])
        need_sigma(column, canonical, limits.CHANNELS[kind], required=kind == "F")
    return _flight_test(meta, columns, folder)


def _flight_test(meta, columns, folder):
    """The :class:`FlightTest` of data.csv's ``columns`` (canonical names, the bundle's units) converted to SI."""
    data = pd.DataFrame(columns)
    for col, quantity in COLUMN_QUANTITY.items():
        if col in data:
            data[col] = meta.units.si(data[col].to_numpy(), quantity)
    for p in meta.parachutes:
        if p.load_cell:
            for c in (p.load_column, f"{p.load_column}_sigma"):
                data[c] = meta.units.si(data[c].to_numpy(), "force")
    return FlightTest(name=meta.name, phase=meta.phase, units=meta.units, vehicle=meta.vehicle,
                      parachutes=meta.parachutes, data=data, source=folder, priors_files=meta.priors_files,
                      air_data=meta.air_data)


def with_data(test: FlightTest, data: pd.DataFrame) -> FlightTest:
    """A copy of ``test`` with new time histories (same metadata)."""
    return replace(test, data=data)


def summary(test: FlightTest) -> dict:
    """What ``cpas-bayes validate`` prints: parachutes, stages, duration, rate, channels."""
    from cpas_bayes.data.bundle_notes import summary_notes

    return {
        "name": test.name,
        "phase": test.phase,
        "units": test.units.name,
        "samples": int(len(test.data)),
        "duration_s": test.duration,
        "sample_rate_hz": test.sample_rate,
        "vehicle_weight": test.units.from_si(test.vehicle.weight, "force"),
        "parachutes": [
            {"id": p.id, "kind": p.kind, "inflation": p.inflation,
             "diameter": test.units.from_si(p.diameter, "length"),
             "load_cell": bool(p.load_cell), "flyout_angle": bool(p.flyout_angle),
             "stages": [{"label": s.label, "start": s.start} for s in p.stages]}
            for p in test.parachutes
        ],
        "channels": test.channels,
        **summary_notes(test),
    }


EXAMPLES_DIR = Path(__file__).parent / "examples"


def example_bundles():
    """Paths of the example bundles shipped with the package (from an independent simulator)."""
    return sorted(p for p in EXAMPLES_DIR.iterdir() if (p / TOML_NAME).is_file())

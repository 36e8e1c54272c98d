"""Flight-test bundles: reading, validating and writing (docs/test-bundle.md).

A bundle is a folder with ``test.toml`` (vehicle, parachutes, stages, units)
and ``data.csv`` (time histories). :func:`read_bundle` returns a
:class:`FlightTest` whose numbers are all SI, with canonical column names:

``time, G, G_sigma, qbar, qbar_sigma, airspeed, gamma`` (deg), optional
``density, altitude``, and per parachute with a load cell ``F_<id>,
F_<id>_sigma``, with a fly-out angle ``theta_<id>, theta_<id>_sigma`` (deg).

Every refusal is a :class:`~cpas_bayes.core.errors.BundleError` naming the file,
the row or key, and the fix. :func:`write_bundle` writes the format back in the
test's own units, atomically.
"""

from __future__ import annotations

import io
import math
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd
import tomli_w

from cpas_bayes.core.errors import BundleError
from cpas_bayes.core.files import atomic_directory
from cpas_bayes.core.units import UNIT_SYSTEMS, UnitSystem, unit_system

KINDS = ("drogue", "main", "pilot", "fbcp")
INFLATIONS = ("infinite", "finite")
TOML_NAME = "test.toml"
CSV_NAME = "data.csv"

# Column -> physical quantity, for unit conversion. Angles stay in degrees.
_COLUMN_QUANTITY = {"time": "time", "qbar": "pressure", "qbar_sigma": "pressure",
                    "airspeed": "speed", "density": "density", "altitude": "length"}
_REQUIRED = ("time", "G", "qbar", "airspeed", "gamma")
_OPTIONAL = ("density", "altitude")


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


# ---------------------------------------------------------------------------
# reading


def _is_number(value):
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class _TomlReader:
    """Typed access to test.toml that refuses with file, key and fix."""

    def __init__(self, path):
        self.path = path

    def fail(self, key, problem, fix):
        raise BundleError(self.path, f"key '{key}'" if key else "", problem, fix)

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
            self.fail(f"{where}{key}", f"must be a non-empty string, got {value!r}", f"write {key} = \"...\"")
        if choices and value not in choices:
            self.fail(f"{where}{key}", f"unknown value {value!r}",
                      f"use one of {', '.join(repr(c) for c in choices)}")
        return value

    def number(self, doc, key, where, minimum=None, positive=False, optional=False):
        value = doc.get(key)
        if value is None:
            if optional:
                return None
            self.fail(f"{where}{key}", "is missing", f"add {key} = <number>")
        if not _is_number(value) or not math.isfinite(value):
            self.fail(f"{where}{key}", f"must be a finite number, got {value!r}", f"write a number for {key}")
        if positive and value <= 0:
            self.fail(f"{where}{key}", f"must be positive, got {value}", f"give {key} a value > 0")
        if minimum is not None and value < minimum:
            what = "a sigma cannot be negative" if key.endswith("sigma") else f"must be ≥ {minimum}"
            self.fail(f"{where}{key}", f"{what}, got {value}", f"give {key} a value ≥ {minimum}")
        return float(value)


def _read_toml(path):
    if not path.is_file():
        raise BundleError(path, "", "file not found",
                          f"a bundle folder needs {TOML_NAME} and {CSV_NAME} (docs/test-bundle.md)")
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise BundleError(path, "", f"not valid TOML ({exc})", "correct the TOML syntax at that line") from None
    except UnicodeDecodeError:
        raise BundleError(path, "", "not UTF-8 text", "save the file as UTF-8 TOML") from None


def _parse_parachutes(doc, reader, units):
    chutes = doc.get("parachute")
    if not isinstance(chutes, list) or not chutes:
        reader.fail("parachute", "no [[parachute]] entries", "add one [[parachute]] table per canopy")
    parsed, seen = [], set()
    for i, entry in enumerate(chutes):
        where = f"parachute[{i}]."
        if not isinstance(entry, dict):
            reader.fail(f"parachute[{i}]", "is not a table", "write each parachute as [[parachute]]")
        pid = reader.string(entry, "id", where)
        where = f"parachute '{pid}'."
        if pid in seen:
            reader.fail(f"parachute[{i}].id", f"duplicate parachute id {pid!r}", "give every parachute a unique id")
        seen.add(pid)
        kind = reader.string(entry, "kind", where, choices=KINDS)
        inflation = reader.string(entry, "inflation", where, choices=INFLATIONS)
        diameter = reader.number(entry, "diameter", where, positive=True)
        weight = reader.number(entry, "weight", where, minimum=0)
        weight_sigma = reader.number(entry, "weight_sigma", where, minimum=0, optional=True) or 0.0
        load_cell = entry.get("load_cell")
        flyout = entry.get("flyout_angle")
        for key, value in (("load_cell", load_cell), ("flyout_angle", flyout)):
            if value is not None and (not isinstance(value, str) or not value.strip()):
                reader.fail(f"{where}{key}", f"must name a data.csv column, got {value!r}",
                            f"write {key} = \"<column name>\" or remove the key")
        stages_raw = entry.get("stage")
        if not isinstance(stages_raw, list) or not stages_raw:
            reader.fail(f"{where}stage", f"parachute {pid!r} has no stages",
                        "add at least one [[parachute.stage]] (the last is full open)")
        stages = []
        for k, st in enumerate(stages_raw):
            swhere = f"{where}stage[{k}]."
            if not isinstance(st, dict):
                reader.fail(f"{where}stage[{k}]", "is not a table", "write each stage as [[parachute.stage]]")
            label = reader.string(st, "label", swhere, default=f"stage {k + 1}")
            start = reader.number(st, "start", swhere)
            start_sigma = reader.number(st, "start_sigma", swhere, minimum=0, optional=True) or 0.0
            if stages and start <= stages[-1].start:
                reader.fail(f"{swhere}start",
                            f"stages out of time order: starts at {start} s, not after the previous stage "
                            f"({stages[-1].start} s)", "list stages in time order with increasing start times")
            stages.append(Stage(label, start, start_sigma))
        parsed.append(Parachute(
            id=pid, kind=kind, inflation=inflation,
            diameter=units.si(diameter, "length"),
            weight=units.si(weight, "force"), weight_sigma=units.si(weight_sigma, "force"),
            stages=tuple(stages), load_cell=load_cell, flyout_angle=flyout))
    return tuple(parsed)


def _read_csv(path):
    if not path.is_file():
        raise BundleError(path, "", "file not found",
                          f"a bundle folder needs {TOML_NAME} and {CSV_NAME} (docs/test-bundle.md)")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise BundleError(path, "", "not UTF-8 text", "save data.csv as UTF-8 CSV") from None
    header = text.partition("\n")[0].strip()
    names = [h.strip() for h in header.split(",")]
    if not header or not all(names):
        raise BundleError(path, "row 1 (header)", "the header row is missing or has an empty column name",
                          "start data.csv with a comma-separated header such as time,G,G_sigma,...")
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise BundleError(path, f"column '{dupes[0]}'", "column name appears more than once",
                          "give every column a unique name")
    try:
        # Blank lines stay rows so that row numbers are file lines; only trailing ones are dropped.
        frame = pd.read_csv(io.StringIO(text.rstrip("\n")), dtype=str, skipinitialspace=True,
                            keep_default_na=False, skip_blank_lines=False)
    except (pd.errors.ParserError, ValueError) as exc:
        raise BundleError(path, "", f"not a readable CSV table ({exc})",
                          "make every row have as many comma-separated cells as the header") from None
    frame.columns = [c.strip() for c in frame.columns]
    if frame.empty:
        raise BundleError(path, "", "has a header but no data rows", "add at least two rows of samples")
    return frame


def _numeric_column(frame, column, path):
    raw = frame[column].str.strip()
    values = pd.to_numeric(raw, errors="coerce").to_numpy(dtype=float)
    bad = ~np.isfinite(values)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        cell = raw.iloc[i]
        what = "is empty" if cell == "" else (f"is not a number ({cell!r})" if np.isnan(values[i]) and
                                              cell.lower() not in ("nan", "-nan", "+nan") else
                                              f"is {cell!r}, not a finite number")
        raise BundleError(path, f"row {i + 2}, column '{column}'", f"the cell {what}",
                          "every cell of a used column must hold a finite number; remove or repair the row")
    return values


def _sigma(frame, column, sigma_table, path):
    """Per-sample sigma of ``column``: its ``<column>_sigma`` or the constant [sigma] entry."""
    name = f"{column}_sigma"
    if name in frame.columns:
        values = _numeric_column(frame, name, path)
        if (values < 0).any():
            i = int(np.flatnonzero(values < 0)[0])
            raise BundleError(path, f"row {i + 2}, column '{name}'", f"negative sigma {values[i]}",
                              "a 1-sigma is ≥ 0; correct the value")
        return values
    if column in sigma_table:
        return np.full(len(frame), float(sigma_table[column]))
    return None


def read_bundle(folder) -> FlightTest:
    """Read and validate one bundle folder; raise :class:`BundleError` on any fault."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BundleError(folder, "", "not a folder" if folder.exists() else "folder not found",
                          "pass the path of a bundle folder holding test.toml and data.csv")
    toml_path, csv_path = folder / TOML_NAME, folder / CSV_NAME
    doc = _read_toml(toml_path)
    reader = _TomlReader(toml_path)

    units_name = reader.string(doc, "units", "")
    if units_name not in UNIT_SYSTEMS:
        reader.fail("units", f"unknown units {units_name!r}", "use units = \"US\" or units = \"SI\"")
    units = unit_system(units_name)
    name = reader.string(doc, "name", "", default=folder.name)
    phase = reader.string(doc, "phase", "", default="unspecified")

    veh = reader.table(doc, "vehicle", "")
    vehicle = Vehicle(
        weight=units.si(reader.number(veh, "weight", "vehicle.", positive=True), "force"),
        weight_sigma=units.si(reader.number(veh, "weight_sigma", "vehicle.", minimum=0, optional=True) or 0.0,
                              "force"),
        cds=units.si(reader.number(veh, "cds", "vehicle.", minimum=0), "area"),
        cds_sigma=units.si(reader.number(veh, "cds_sigma", "vehicle.", minimum=0, optional=True) or 0.0, "area"),
    )
    parachutes = _parse_parachutes(doc, reader, units)

    sigma_table = doc.get("sigma", {})
    if not isinstance(sigma_table, dict):
        reader.fail("sigma", "is not a table", "write constant sigmas as a [sigma] table")
    for key, value in sigma_table.items():
        if not _is_number(value) or not math.isfinite(value) or value < 0:
            reader.fail(f"sigma.{key}", f"must be a finite number ≥ 0, got {value!r}", "give a 1-sigma ≥ 0")

    raw = _read_csv(csv_path)
    columns = {}

    def need(column, why):
        if column not in raw.columns:
            raise BundleError(csv_path, f"column '{column}'", f"missing column ({why})",
                              f"add a '{column}' column to data.csv")
        return _numeric_column(raw, column, csv_path)

    def need_sigma(column, canonical):
        values = _sigma(raw, column, sigma_table, csv_path)
        if values is None:
            raise BundleError(csv_path, f"column '{column}_sigma'",
                              f"no 1-sigma for '{column}'",
                              f"add a '{column}_sigma' column, or '{column} = <sigma>' under [sigma] in test.toml")
        columns[f"{canonical}_sigma"] = values

    for col in _REQUIRED:
        columns[col] = need(col, "required by the bundle format")
    for col in _OPTIONAL:
        if col in raw.columns:
            columns[col] = _numeric_column(raw, col, csv_path)
    need_sigma("G", "G")
    need_sigma("qbar", "qbar")

    t = columns["time"]
    if len(t) < 2:
        raise BundleError(csv_path, "column 'time'", "fewer than two samples", "add more rows of data")
    steps = np.diff(t)
    if (steps <= 0).any():
        i = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise BundleError(csv_path, f"row {i + 2}, column 'time'",
                          f"time not strictly increasing ({t[i - 1]} then {t[i]})",
                          "sort the rows by time and remove duplicate samples")
    qbar = columns["qbar"]
    if (qbar <= 0).any():
        i = int(np.flatnonzero(qbar <= 0)[0])
        raise BundleError(csv_path, f"row {i + 2}, column 'qbar'",
                          f"qbar = {qbar[i]} ≤ 0, where drag areas are computed as load / qbar",
                          "trim the rows before the vehicle has airspeed, or repair the value")

    for p in parachutes:
        if p.load_cell:
            if p.load_cell not in raw.columns:
                raise BundleError(csv_path, f"column '{p.load_cell}'",
                                  f"parachute {p.id!r} names load_cell '{p.load_cell}' but data.csv has no such column",
                                  f"add the column or remove load_cell from parachute {p.id!r} in test.toml")
            columns[p.load_column] = need(p.load_cell, f"load cell of {p.id}")
            need_sigma(p.load_cell, p.load_column)
        if p.flyout_angle:
            if p.flyout_angle not in raw.columns:
                raise BundleError(csv_path, f"column '{p.flyout_angle}'",
                                  f"parachute {p.id!r} names flyout_angle '{p.flyout_angle}' but data.csv has no "
                                  "such column",
                                  f"add the column or remove flyout_angle from parachute {p.id!r} in test.toml")
            columns[p.angle_column] = need(p.flyout_angle, f"fly-out angle of {p.id}")
            sig = _sigma(raw, p.flyout_angle, sigma_table, csv_path)
            columns[f"{p.angle_column}_sigma"] = sig if sig is not None else np.zeros(len(t))

    data = pd.DataFrame(columns)
    for col, quantity in _COLUMN_QUANTITY.items():
        if col in data:
            data[col] = units.si(data[col].to_numpy(), quantity)
    for p in parachutes:
        if p.load_cell:
            for c in (p.load_column, f"{p.load_column}_sigma"):
                data[c] = units.si(data[c].to_numpy(), "force")
    return FlightTest(name=name, phase=phase, units=units, vehicle=vehicle, parachutes=parachutes,
                      data=data, source=folder)


# ---------------------------------------------------------------------------
# writing


def _toml_document(test: FlightTest):
    u = test.units
    doc = {"name": test.name, "units": u.name, "phase": test.phase,
           "vehicle": {"weight": u.from_si(test.vehicle.weight, "force"),
                       "weight_sigma": u.from_si(test.vehicle.weight_sigma, "force"),
                       "cds": u.from_si(test.vehicle.cds, "area"),
                       "cds_sigma": u.from_si(test.vehicle.cds_sigma, "area")},
           "parachute": []}
    for p in test.parachutes:
        entry = {"id": p.id, "kind": p.kind, "inflation": p.inflation,
                 "diameter": u.from_si(p.diameter, "length"),
                 "weight": u.from_si(p.weight, "force"), "weight_sigma": u.from_si(p.weight_sigma, "force")}
        if p.load_cell:
            entry["load_cell"] = p.load_cell
        if p.flyout_angle:
            entry["flyout_angle"] = p.flyout_angle
        entry["stage"] = [{"label": s.label, "start": s.start, "start_sigma": s.start_sigma} for s in p.stages]
        doc["parachute"].append(entry)
    return doc


def bundle_frame(test: FlightTest) -> pd.DataFrame:
    """The test's data as they appear in data.csv: the bundle's units and column names."""
    u = test.units
    out = test.data.copy()
    for col, quantity in _COLUMN_QUANTITY.items():
        if col in out:
            out[col] = u.from_si(out[col].to_numpy(), quantity)
    rename = {}
    for p in test.parachutes:
        if p.load_cell:
            for c in (p.load_column, f"{p.load_column}_sigma"):
                out[c] = u.from_si(out[c].to_numpy(), "force")
            rename[p.load_column] = p.load_cell
            rename[f"{p.load_column}_sigma"] = f"{p.load_cell}_sigma"
        if p.flyout_angle:
            rename[p.angle_column] = p.flyout_angle
            rename[f"{p.angle_column}_sigma"] = f"{p.flyout_angle}_sigma"
    return out.rename(columns=rename)


def write_bundle(test: FlightTest, folder, extra_files=None):
    """Write ``test`` as a bundle folder in its own units, atomically.

    ``extra_files`` maps file names to text written beside test.toml (for
    example a synthetic test's ``truth.json``).
    """
    folder = Path(folder)
    with atomic_directory(folder) as tmp:
        (tmp / TOML_NAME).write_bytes(tomli_w.dumps(_toml_document(test)).encode("utf-8"))
        bundle_frame(test).to_csv(tmp / CSV_NAME, index=False, float_format="%.15g")
        for name, text in (extra_files or {}).items():
            (tmp / name).write_text(text, encoding="utf-8")
    return folder


def with_data(test: FlightTest, data: pd.DataFrame) -> FlightTest:
    """A copy of ``test`` with new time histories (same metadata)."""
    return replace(test, data=data)


def summary(test: FlightTest) -> dict:
    """What ``cpas-bayes validate`` prints: parachutes, stages, duration, rate, channels."""
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
    }


EXAMPLES_DIR = Path(__file__).parent / "examples"


def example_bundles():
    """Paths of the example bundles shipped with the package (from an independent simulator)."""
    return sorted(p for p in EXAMPLES_DIR.iterdir() if (p / TOML_NAME).is_file())

"""Writing a flight-test bundle: ``test.toml`` and ``data.csv`` in the test's own units, atomically.

The inverse of :func:`cpas_bayes.data.bundle.read_bundle` (format:
``docs/test-bundle.md``); a written bundle reads back to the same test,
a logger bundle's missing samples as empty cells and its air data as tables.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import tomli_w

from cpas_bayes.core.files import atomic_directory
from cpas_bayes.data.bundle import COLUMN_QUANTITY, CSV_NAME, TOML_NAME, FlightTest


def _toml_document(test: FlightTest):
    u = test.units
    doc = {"name": test.name, "units": u.name, "phase": test.phase,
           "vehicle": {"weight": u.from_si(test.vehicle.weight, "force"),
                       "weight_sigma": u.from_si(test.vehicle.weight_sigma, "force"),
                       "cds": u.from_si(test.vehicle.cds, "area"),
                       "cds_sigma": u.from_si(test.vehicle.cds_sigma, "area")},
           "parachute": []}
    if test.priors_files:   # copied beside test.toml by write_bundle
        doc["priors"] = [f.name for f in test.priors_files]
    for p in test.parachutes:
        entry = {"id": p.id, "kind": p.kind, "inflation": p.inflation,
                 "diameter": u.from_si(p.diameter, "length"),
                 "weight": u.from_si(p.weight, "force"), "weight_sigma": u.from_si(p.weight_sigma, "force")}
        if p.diameter_sigma > 0:
            entry["diameter_sigma"] = u.from_si(p.diameter_sigma, "length")
        if p.load_cell:
            entry["load_cell"] = p.load_cell
        if p.flyout_angle:
            entry["flyout_angle"] = p.flyout_angle
        entry["stage"] = [{"label": s.label, "start": s.start, "start_sigma": s.start_sigma} for s in p.stages]
        doc["parachute"].append(entry)
    doc.update(_air_tables(test))
    return doc


def _air_tables(test: FlightTest):
    """A logger bundle's [wind], [atmosphere] and [rate] in the test's units (none when not given)."""
    air, out = test.air_data, {}

    def levels(values, quantity):
        return test.units.from_si(np.asarray(values, dtype=float), quantity).tolist()

    if air is None:
        return out
    if air.wind is not None:
        out["wind"] = {"altitude": levels(air.wind.altitude, "length"), "north": levels(air.wind.north, "speed"),
                       "east": levels(air.wind.east, "speed"), "sigma": float(levels(air.wind.sigma, "speed"))}
    if air.atmosphere is not None:
        out["atmosphere"] = {"altitude": levels(air.atmosphere.altitude, "length"),
                             "density": levels(air.atmosphere.density, "density")}
    if air.rates:
        out["rate"] = {k: float(v) for k, v in air.rates.items()}
    return out


def bundle_frame(test: FlightTest) -> pd.DataFrame:
    """The test's data as they appear in data.csv: the bundle's units and column names."""
    u = test.units
    out = test.data.copy()
    for col, quantity in COLUMN_QUANTITY.items():
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


def write_bundle(test: FlightTest, folder, extra_files=None, check=None):
    """Write ``test`` as a bundle folder in its own units, atomically.

    ``extra_files`` maps file names to text written beside test.toml (for
    example a synthetic test's ``truth.json``); the test's own prior files are
    copied beside it too. ``check``, if given, is called with the finished
    temporary folder before it is put in place (e.g. :func:`read_bundle`);
    whatever it raises passes through and nothing is installed.
    """
    folder = Path(folder)
    names = [f.name for f in test.priors_files]
    if len(set(names)) < len(names):
        raise ValueError(f"prior files of test {test.name!r} share a file name: {names}")
    extra_files = {**{f.name: Path(f).read_text(encoding="utf-8") for f in test.priors_files}, **(extra_files or {})}
    with atomic_directory(folder) as tmp:
        (tmp / TOML_NAME).write_bytes(tomli_w.dumps(_toml_document(test)).encode("utf-8"))
        # NaN is a logger bundle's missing sample: an empty cell
        bundle_frame(test).to_csv(tmp / CSV_NAME, index=False, float_format="%.15g", na_rep="")
        for name, text in (extra_files or {}).items():
            (tmp / name).write_text(text, encoding="utf-8")
        if check is not None:
            check(tmp)
    return folder

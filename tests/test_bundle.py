"""Bundle I/O on the example bundles: reading, SI conversion, round trips, atomic writes
and every refusal listed in docs/test-bundle.md."""

from __future__ import annotations

import csv
import dataclasses
import tomllib
from pathlib import Path

import numpy as np
import pytest

from cpas_bayes.data import bundle_write as bundle_module
from cpas_bayes.data.bundle import read_bundle
from cpas_bayes.data.bundle_write import write_bundle
from cpas_bayes.core.errors import BundleError
from cpas_bayes.core.units import UNIT_SYSTEMS

DROGUE, MAIN = "drogue-clean", "main-clean"
EXAMPLES = {DROGUE: (("D3", "D6"), 2, 1601), MAIN: (("M1", "M2", "M3"), 3, 4001)}

# Quantity of each data.csv column that carries a unit; the others (G, gamma, theta, sigmas of
# those) are load factors or degrees and pass through unchanged.
COLUMN_QUANTITY = {"qbar": "pressure", "qbar_sigma": "pressure", "airspeed": "speed",
                   "density": "density", "altitude": "length"}


def raw_csv(folder):
    """data.csv as float columns by header name, parsed with the csv module and float()."""
    with (folder / "data.csv").open(newline="") as fh:
        header, *rows = list(csv.reader(fh))
    return {name: np.array([float(row[i]) for row in rows]) for i, name in enumerate(header)}


def raw_toml(folder):
    with (folder / "test.toml").open("rb") as fh:
        return tomllib.load(fh)


# ---------------------------------------------------------------------------
# reading and SI conversion


@pytest.mark.parametrize("name", EXAMPLES)
def test_example_reads(example_dir, name):
    ids, n_stages, n_rows = EXAMPLES[name]
    test = read_bundle(example_dir(name))
    assert [p.id for p in test.parachutes] == list(ids)
    assert [len(p.stages) for p in test.parachutes] == [n_stages] * len(ids)
    assert all(p.stages[-1].label == "full open" for p in test.parachutes)
    assert len(test.data) == n_rows
    assert test.units.name == "US"
    assert test.duration == pytest.approx(0.01 * (n_rows - 1))
    assert test.sample_rate == pytest.approx(100.0)


@pytest.mark.parametrize("name", EXAMPLES)
def test_example_values_are_converted_to_si(example_dir, us_to_si, name):
    folder = example_dir(name)
    test, doc, raw = read_bundle(folder), raw_toml(folder), raw_csv(folder)
    lbf, ft = us_to_si["force"], us_to_si["length"]

    v = test.vehicle
    assert (v.weight, v.weight_sigma) == pytest.approx(
        (doc["vehicle"]["weight"] * lbf, doc["vehicle"]["weight_sigma"] * lbf), rel=1e-12)
    assert (v.cds, v.cds_sigma) == pytest.approx(
        (doc["vehicle"]["cds"] * ft**2, doc["vehicle"]["cds_sigma"] * ft**2), rel=1e-12)
    assert test.total_weight == pytest.approx(
        (doc["vehicle"]["weight"] + sum(e["weight"] for e in doc["parachute"])) * lbf, rel=1e-12)

    expected = {c: raw[c] * us_to_si.get(COLUMN_QUANTITY.get(c), 1.0)
                for c in ("time", "G", "G_sigma", "qbar", "qbar_sigma", "airspeed", "gamma", "density", "altitude")}
    for p, entry in zip(test.parachutes, doc["parachute"]):
        assert (p.diameter, p.weight, p.weight_sigma) == pytest.approx(
            (entry["diameter"] * ft, entry["weight"] * lbf, entry["weight_sigma"] * lbf), rel=1e-12)
        assert [(s.label, s.start, s.start_sigma) for s in p.stages] == \
            [(s["label"], s["start"], s["start_sigma"]) for s in entry["stage"]]
        expected[f"F_{p.id}"] = raw[entry["load_cell"]] * lbf
        expected[f"F_{p.id}_sigma"] = raw[entry["load_cell"] + "_sigma"] * lbf
        if "flyout_angle" in entry:
            expected[f"theta_{p.id}"] = raw[entry["flyout_angle"]]
            expected[f"theta_{p.id}_sigma"] = np.zeros(len(test.data))  # no sigma given: 0
    assert sorted(test.data.columns) == sorted(expected)
    for column, values in expected.items():
        np.testing.assert_allclose(test.data[column], values, rtol=1e-12, atol=0, err_msg=column)


def test_constant_sigma_table_expands_to_columns(example_dir, bundle_files, us_to_si):
    folder = example_dir(MAIN)
    files = bundle_files(folder)
    for column in ("G_sigma", "qbar_sigma", "F_M2_sigma"):
        files.drop_column(column)
    files.set_key("sigma", value={"G": 0.05, "qbar": 0.9, "F_M2": 25.0, "theta_M1": 2.0})
    test = read_bundle(folder)
    n = len(test.data)
    np.testing.assert_array_equal(test.data["G_sigma"], np.full(n, 0.05))
    np.testing.assert_allclose(test.data["qbar_sigma"], np.full(n, 0.9 * us_to_si["pressure"]), rtol=1e-12)
    np.testing.assert_allclose(test.data["F_M2_sigma"], np.full(n, 25.0 * us_to_si["force"]), rtol=1e-12)
    np.testing.assert_array_equal(test.data["theta_M1_sigma"], np.full(n, 2.0))  # degrees, unconverted
    np.testing.assert_array_equal(test.data["theta_M2_sigma"], np.zeros(n))
    # Sigma columns still in data.csv are read from there.
    np.testing.assert_allclose(test.data["F_M1_sigma"], raw_csv(folder)["F_M1_sigma"] * us_to_si["force"],
                               rtol=1e-12)


def test_canonical_column_names_whatever_the_bundle_calls_them(example_dir, bundle_files, tmp_path):
    original = read_bundle(example_dir(MAIN))
    folder = example_dir(MAIN, "renamed")
    files = bundle_files(folder)
    for old, new in (("F_M1", "LC1"), ("F_M1_sigma", "LC1_sigma"), ("theta_M1", "flyout1")):
        files.rename_column(old, new)
    files.set_key("parachute", 0, "load_cell", value="LC1")
    files.set_key("parachute", 0, "flyout_angle", value="flyout1")

    test = read_bundle(folder)
    m1 = test.parachute("M1")
    assert (m1.load_cell, m1.flyout_angle) == ("LC1", "flyout1")
    assert (m1.load_column, m1.angle_column) == ("F_M1", "theta_M1")
    assert list(test.data.columns) == list(original.data.columns)
    assert not {"LC1", "LC1_sigma", "flyout1"} & set(test.data.columns)
    np.testing.assert_array_equal(test.data.to_numpy(), original.data.to_numpy())
    assert "LC1" not in test.channels and {"F_M1", "theta_M1"} <= set(test.channels)

    # Written back under the bundle's own names.
    header = bundle_files(write_bundle(test, tmp_path / "written")).header()
    assert {"LC1", "LC1_sigma", "flyout1", "flyout1_sigma"} <= set(header)
    assert "F_M1" not in header and "theta_M1" not in header


# ---------------------------------------------------------------------------
# writing


@pytest.mark.parametrize("name", EXAMPLES)
def test_round_trip_in_bundle_units(example_dir, same_test, tmp_path, name):
    original = read_bundle(example_dir(name))
    out = write_bundle(original, tmp_path / "out", extra_files={"notes.txt": "written by a test\n"})
    # the files, and the marker that says cpas-bayes wrote them (core.ownership)
    assert sorted(p.name for p in out.iterdir()) == [".cpas-bayes", "data.csv", "notes.txt", "test.toml"]
    assert (out / "notes.txt").read_text(encoding="utf-8") == "written by a test\n"
    assert raw_toml(out)["units"] == "US"
    same_test(read_bundle(out), original, rtol=1e-9)


@pytest.mark.parametrize("name", EXAMPLES)
def test_round_trip_in_si(example_dir, same_test, us_to_si, tmp_path, name):
    folder = example_dir(name)
    si = dataclasses.replace(read_bundle(folder), units=UNIT_SYSTEMS["SI"])
    out = write_bundle(si, tmp_path / "si")

    # On disk the copy really is SI: N, m, Pa.
    doc, raw, us_doc, us_raw = raw_toml(out), raw_csv(out), raw_toml(folder), raw_csv(folder)
    assert doc["units"] == "SI"
    assert doc["vehicle"]["weight"] == pytest.approx(us_doc["vehicle"]["weight"] * us_to_si["force"], rel=1e-12)
    assert doc["parachute"][0]["diameter"] == pytest.approx(
        us_doc["parachute"][0]["diameter"] * us_to_si["length"], rel=1e-12)
    np.testing.assert_allclose(raw["qbar"], us_raw["qbar"] * us_to_si["pressure"], rtol=1e-12)
    load_cell = doc["parachute"][0]["load_cell"]
    np.testing.assert_allclose(raw[load_cell], us_raw[load_cell] * us_to_si["force"], rtol=1e-12)

    again = read_bundle(out)
    same_test(again, si, rtol=1e-9)
    # ... and an SI bundle round-trips as such.
    same_test(read_bundle(write_bundle(again, tmp_path / "si-again")), again, rtol=1e-9)


def _fail_after_test_toml(monkeypatch, parent):
    """Make write_bundle fail between writing test.toml and data.csv; return what existed then."""
    seen = []

    def fail(test):
        seen.extend(p.name for p in parent.rglob("*"))
        raise OSError("disk full")

    monkeypatch.setattr(bundle_module, "bundle_frame", fail)
    return seen


def test_failed_write_leaves_nothing(example_dir, monkeypatch, tmp_path):
    test = read_bundle(example_dir(DROGUE))
    parent = tmp_path / "out"
    parent.mkdir()
    seen = _fail_after_test_toml(monkeypatch, parent)
    with pytest.raises(OSError, match="disk full"):
        write_bundle(test, parent / "bundle")
    assert "test.toml" in seen  # the failure really came midway
    assert list(parent.iterdir()) == []


def test_failed_write_keeps_the_previous_bundle(example_dir, monkeypatch, snapshot, tmp_path):
    test = read_bundle(example_dir(DROGUE))
    parent = tmp_path / "out"
    write_bundle(test, parent / "bundle")
    before = snapshot(parent)
    seen = _fail_after_test_toml(monkeypatch, parent)
    with pytest.raises(OSError, match="disk full"):
        write_bundle(dataclasses.replace(test, name="changed"), parent / "bundle")
    assert "test.toml" in seen
    assert snapshot(parent) == before
    assert read_bundle(parent / "bundle").name == test.name


# ---------------------------------------------------------------------------
# refusals: one defect planted in a copy of the drogue example (parachutes D3, D6; 2 stages each;
# row r of data.csv has time (r - 2) * 0.01 s)


def _drop_sigma_column_and_set_entry(files):
    files.drop_column("G_sigma")
    files.set_key("sigma", "G", value=-0.03)


def _insert_blank_line(files):
    rows = files.read_rows()
    files.write_rows(rows[:3] + [[""]] + rows[3:])


REFUSALS = [
    # id, defect, file named, place named (None: the file itself), problem named
    ("missing test.toml", lambda f: f.toml_path.unlink(), "test.toml", None, "file not found"),
    ("missing data.csv", lambda f: f.csv_path.unlink(), "data.csv", None, "file not found"),
    *[(f"missing column {c}", lambda f, c=c: f.drop_column(c), "data.csv", f"column '{c}'", "missing column")
      for c in ("time", "G", "gamma")],
    # without one of qbar and airspeed the bundle is neither one with measured air data nor a logger bundle
    ("missing column qbar", lambda f: f.drop_column("qbar"), "data.csv", "column 'qbar'",
     "missing column 'qbar': data.csv gives 'airspeed' but not 'qbar'"),
    ("missing column airspeed", lambda f: f.drop_column("airspeed"), "data.csv", "column 'airspeed'",
     "missing column 'airspeed': data.csv gives 'qbar' but not 'airspeed'"),
    ("load cell absent from data.csv", lambda f: f.drop_column("F_D6"), "data.csv", "column 'F_D6'",
     "parachute 'D6' names load_cell 'F_D6' but data.csv has no such column"),
    ("non-numeric cell", lambda f: f.set_cell(5, "airspeed", "fast"), "data.csv", "row 5, column 'airspeed'",
     "the cell is not a number ('fast')"),
    ("empty cell", lambda f: f.set_cell(6, "F_D3_sigma", ""), "data.csv", "row 6, column 'F_D3_sigma'",
     "the cell is empty"),
    ("NaN in qbar", lambda f: f.set_cell(7, "qbar", "NaN"), "data.csv", "row 7, column 'qbar'",
     "is 'NaN', not a finite number"),
    ("inf in G", lambda f: f.set_cell(20, "G", "inf"), "data.csv", "row 20, column 'G'",
     "is 'inf', not a finite number"),
    ("time repeated", lambda f: f.set_cell(50, "time", "0.47"), "data.csv", "row 50, column 'time'",
     "time not strictly increasing (0.47 then 0.47)"),
    ("time decreasing", lambda f: f.set_cell(50, "time", "0.465"), "data.csv", "row 50, column 'time'",
     "time not strictly increasing (0.47 then 0.465)"),
    ("qbar zero", lambda f: f.set_cell(12, "qbar", "0"), "data.csv", "row 12, column 'qbar'", "qbar = 0.0 ≤ 0"),
    ("qbar negative", lambda f: f.set_cell(13, "qbar", "-3.5"), "data.csv", "row 13, column 'qbar'",
     "≤ 0"),
    ("negative sigma column", lambda f: f.set_cell(9, "G_sigma", "-0.03"), "data.csv",
     "row 9, column 'G_sigma'", "negative sigma -0.03"),
    ("negative [sigma] entry", _drop_sigma_column_and_set_entry, "test.toml", "key 'sigma.G'", "≥ 0, got -0.03"),
    ("negative [sigma] entry beside a sigma column", lambda f: f.set_key("sigma", "qbar", value=-1.0),
     "test.toml", "key 'sigma.qbar'", "≥ 0, got -1.0"),
    ("negative sigma key", lambda f: f.set_key("parachute", 1, "weight_sigma", value=-2.0), "test.toml",
     "key 'parachute 'D6'.weight_sigma'", "a sigma cannot be negative"),
    ("unknown units", lambda f: f.set_key("units", value="metric"), "test.toml", "key 'units'",
     "unknown units 'metric'"),
    ("kind not a name", lambda f: f.set_key("parachute", 0, "kind", value="../reserve"), "test.toml",
     "key 'parachute 'D3'.kind'", "parachute kind '../reserve' cannot be used"),
    ("unknown inflation", lambda f: f.set_key("parachute", 1, "inflation", value="partial"), "test.toml",
     "key 'parachute 'D6'.inflation'", "unknown value 'partial'"),
    ("stages out of order", lambda f: f.set_key("parachute", 1, "stage", 1, "start", value=0.5), "test.toml",
     "key 'parachute 'D6'.stage[1].start'", "stages out of time order"),
    ("parachute without stages", lambda f: f.delete_key("parachute", 0, "stage"), "test.toml",
     "key 'parachute 'D3'.stage'", "parachute 'D3' has no stages"),
    ("duplicate parachute id", lambda f: f.set_key("parachute", 1, "id", value="D3"), "test.toml",
     "key 'parachute[1].id'", "duplicate parachute id 'D3'"),
    ("no sigma for G", lambda f: f.drop_column("G_sigma"), "data.csv", "column 'G_sigma'", "no 1-sigma for 'G'"),
    ("blank line among the data", _insert_blank_line, "data.csv", "row 4, column 'time'", "the cell is empty"),
]


# Issue #18: what a careless or adversarial user hands over, refused by name before any work.


def _edit_toml_text(files, old, new):
    text = files.toml_path.read_text(encoding="utf-8")
    assert old in text
    files.toml_path.write_text(text.replace(old, new, 1), encoding="utf-8")


def _scale_time(files, factor, keep=None):
    """Multiply data.csv's time by ``factor`` (keeping only the first ``keep`` data rows if given)."""
    rows = files.read_rows()
    rows = rows[:keep + 1] if keep else rows
    for row in rows[1:]:
        row[0] = repr(float(row[0]) * factor)
    files.write_rows(rows)


def _trailing_comma(files, header=False):
    rows = files.read_rows()
    files.write_rows([row + [""] if header or k else row for k, row in enumerate(rows)])


def _extra_cell(files, row):
    rows = files.read_rows()
    rows[row - 1].append("7")
    files.write_rows(rows)


def _huge_name(files):
    _edit_toml_text(files, 'name = "EX-drogue"', 'name = "' + "x" * 50_000_000 + '"')


ISSUE_18 = [
    # 1. names that become paths or reach a terminal
    ("name climbs out", lambda f: f.set_key("name", value="../../victim"), "test.toml", "key 'name'",
     "test name '../../victim' cannot be used: contains a path separator"),
    ("name too long", lambda f: f.set_key("name", value="x" * 65), "test.toml", "key 'name'",
     "65 characters, more than 64"),
    ("name of 100,000 characters", lambda f: f.set_key("name", value="x" * 100_000), "test.toml", "key 'name'",
     "a string of 100,000 characters"),
    ("name of 50 million characters", _huge_name, "test.toml", None, "bytes, more than the 5,000,000"),
    ("id with a slash", lambda f: f.set_key("parachute", 0, "id", value="D/3"), "test.toml",
     "key 'parachute[0].id'", "parachute id 'D/3' cannot be used: contains a path separator"),
    ("id with a newline", lambda f: f.set_key("parachute", 1, "id", value="D6\nD7"), "test.toml",
     "key 'parachute[1].id'", "parachute id 'D6\\nD7' cannot be used: contains a control character"),
    ("id with an ANSI escape", lambda f: f.set_key("parachute", 0, "id", value="\x1b[31mD3"), "test.toml",
     "key 'parachute[0].id'", "'\\x1b[31mD3' cannot be used: contains a control character"),
    ("id like a sigma column", lambda f: f.set_key("parachute", 1, "id", value="D3_sigma"), "test.toml",
     "key 'parachute[1].id'", "ends with '_sigma'"),
    ("stage label with a newline", lambda f: f.set_key("parachute", 0, "stage", 0, "label", value="reefed\n1"),
     "test.toml", "key 'parachute 'D3'.stage[0].label'", "stage label 'reefed\\n1' cannot be used"),
    ("phase with an escape", lambda f: f.set_key("phase", value="\x1b]0;owned\x07"), "test.toml", "key 'phase'",
     "contains a control character"),
    # 2. TOML that crashed the reader
    ("400-digit integer", lambda f: _edit_toml_text(f, "weight = 20263.7", "weight = " + "9" * 400), "test.toml",
     "key 'vehicle.weight'", "an integer beyond 64 bits"),
    ("100,000-deep array", lambda f: _edit_toml_text(f, 'phase = "drogue"', "phase = " + "[" * 100_000
                                                       + "]" * 100_000), "test.toml", "line 3", "nested more than 16"),
    # 3. misspelt keys and values
    ("misspelt vehicle key", lambda f: f.set_key("vehicle", "weight_sigm", value=100.0), "test.toml",
     "key 'vehicle.weight_sigm'", "unknown key 'weight_sigm'. Fix: did you mean 'weight_sigma'?"),
    ("misspelt top-level key", lambda f: f.set_key("unit", value="SI"), "test.toml", "key 'unit'",
     "did you mean 'units'?"),
    ("misspelt parachute key", lambda f: f.set_key("parachute", 1, "loadcell", value="F_D6"), "test.toml",
     "key 'parachute[1].loadcell'", "did you mean 'load_cell'?"),
    ("misspelt stage key", lambda f: f.set_key("parachute", 0, "stage", 1, "start_sigm", value=0.1), "test.toml",
     "key 'parachute 'D3'.stage[1].start_sigm'", "did you mean 'start_sigma'?"),
    ("[sigma] for a column the bundle does not use", lambda f: f.set_key("sigma", "F_D7", value=40.0), "test.toml",
     "key 'sigma.F_D7'", "unknown key 'F_D7'. Fix: did you mean"),
    ("kind in capitals", lambda f: f.set_key("parachute", 0, "kind", value="Drogue"), "test.toml",
     "key 'parachute 'D3'.kind'", "unknown kind 'Drogue'. Fix: did you mean 'drogue'?"),
    # 4. values the reduction cannot handle
    ("G = 1e300", lambda f: f.set_cell(30, "G", "1e300"), "data.csv", "row 30, column 'G'",
     "G = 1e+300 g is outside -50 … 50 g"),
    ("qbar = 1e-300", lambda f: f.set_cell(31, "qbar", "1e-300"), "data.csv", "row 31, column 'qbar'",
     "qbar = 1e-300 lbf/ft² is outside 0.00208854 … 20885.4 lbf/ft²"),
    ("qbar sigma of 1e300", lambda f: f.set_cell(32, "qbar_sigma", "1e300"), "data.csv",
     "row 32, column 'qbar_sigma'", "a 1-sigma cannot exceed"),
    ("negative airspeed", lambda f: f.set_cell(33, "airspeed", "-412"), "data.csv", "row 33, column 'airspeed'",
     "airspeed = -412.0 ≤ 0, where fill times are computed as n·D_o / airspeed"),
    # a zero airspeed passed the range check and ended the fit's MAP search with a ZeroDivisionError
    ("zero airspeed", lambda f: f.set_cell(33, "airspeed", "0"), "data.csv", "row 33, column 'airspeed'",
     "airspeed = 0.0 ≤ 0, where fill times"),
    ("density in lbm/ft³", lambda f: f.set_cell(34, "density", "0.0765"), "data.csv", "row 34, column 'density'",
     "not lbm/ft³"),
    ("load of 1e300", lambda f: f.set_cell(35, "F_D6", "1e300"), "data.csv", "row 35, column 'F_D6'",
     "F_D6 = 1e+300 lbf is outside"),
    ("time in milliseconds", lambda f: _scale_time(f, 1000.0), "data.csv", "row 1602, column 'time'",
     "the record lasts 16000 s, more than an hour"),
    ("samples 20 s apart", lambda f: _scale_time(f, 2000.0, keep=11), "data.csv", "column 'time'",
     "the median sample interval is 20 s"),
    ("samples a microsecond apart", lambda f: _scale_time(f, 1e-4), "data.csv", "column 'time'",
     "faster than 100000 Hz"),
    ("diameter of 1e300", lambda f: f.set_key("parachute", 0, "diameter", value=1e300), "test.toml",
     "key 'parachute 'D3'.diameter'", "diameter = 1e+300 ft is outside 0.328084 … 984.252 ft"),
    ("vehicle weight of 1e300", lambda f: f.set_key("vehicle", "weight", value=1e300), "test.toml",
     "key 'vehicle.weight'", "weight = 1e+300 lbf is outside"),
    ("vehicle cds of 1e300", lambda f: f.set_key("vehicle", "cds", value=1e300), "test.toml", "key 'vehicle.cds'",
     "cds = 1e+300 ft² is outside"),
    ("infinite diameter", lambda f: _edit_toml_text(f, "diameter = 23.00", "diameter = inf"), "test.toml",
     "key 'parachute 'D3'.diameter'", "must be a finite number, got inf"),
    ("NaN weight sigma", lambda f: _edit_toml_text(f, "weight_sigma = 100.0", "weight_sigma = nan"), "test.toml",
     "key 'vehicle.weight_sigma'", "must be a finite number, got nan"),
    ("start sigma in milliseconds", lambda f: f.set_key("parachute", 0, "stage", 0, "start_sigma", value=100.0),
     "test.toml", "key 'parachute 'D3'.stage[0].start_sigma'", "more than 10 s"),
    ("[sigma] of 1e300", lambda f: (f.drop_column("G_sigma"), f.set_key("sigma", "G", value=1e300)), "test.toml",
     "key 'sigma.G'", "the 1-sigma of G = 1e+300 g is outside 0 … 50 g"),
    # 5. stage times outside the record
    ("stage after the record", lambda f: f.set_key("parachute", 0, "stage", 1, "start", value=500.0), "test.toml",
     "key 'parachute 'D3'.stage[1].start'",
     "starts at 500 s, at or after the record ends (data.csv covers 0 … 16 s)"),
    ("stage before the record", lambda f: f.set_key("parachute", 1, "stage", 0, "start", value=-50.0), "test.toml",
     "key 'parachute 'D6'.stage[0].start'", "starts at -50 s, before the record starts"),
    # 6. one column, two parachutes
    ("two parachutes on one load cell", lambda f: f.set_key("parachute", 1, "load_cell", value="F_D3"), "test.toml",
     "key 'parachute 'D6'.load_cell'", "column 'F_D3' is already the load_cell of parachute 'D3' (the reduction "
     "would split that one load 50/50"),
    ("load cell on the qbar column", lambda f: f.set_key("parachute", 0, "load_cell", value="qbar"), "test.toml",
     "key 'parachute 'D3'.load_cell'", "names column 'qbar', which is a channel of the vehicle"),
    ("fly-out angle on a load-cell column", lambda f: f.set_key("parachute", 1, "flyout_angle", value="F_D6"),
     "test.toml", "key 'parachute 'D6'.flyout_angle'", "already the load_cell of parachute 'D6'"),
    # 7. CSV shape and size
    ("trailing comma on every data row", _trailing_comma, "data.csv", "row 2",
     "the row ends with a comma (every data row does): 1 empty cell(s) beyond the header's 13 columns"),
    ("trailing comma on every line", lambda f: _trailing_comma(f, header=True), "data.csv",
     "row 1 (header), column 14", "the header ends with a comma: an unnamed empty last column"),
    ("one row too long", lambda f: _extra_cell(f, 40), "data.csv", "row 40",
     "14 cells, but the header names 13 columns"),
    ("unnamed column", lambda f: f.rename_column("gamma", ""), "data.csv", "row 1 (header), column 7",
     "a column has no name"),
    ("column name with an escape", lambda f: f.rename_column("altitude", "alt\x1b[2J"), "data.csv",
     "row 1 (header), column 9", "column name 'alt\\x1b[2J': contains a control character"),
]
REFUSALS += ISSUE_18


def _separated_by(files, sep, decimal=None):
    path = files.folder / "data.csv"
    text = path.read_text()
    if decimal:
        text = text.replace(".", decimal)
    path.write_text(text.replace(",", sep))


# hostile and careless inputs found by a fuzzing pass over validate and reduce (2026-11-24)
FUZZED = [
    ("id that is the cluster total's", lambda f: f.set_key("parachute", 1, "id", value="total"), "test.toml",
     "key 'parachute[1].id'", "would give the reduction's columns the names of others"),
    ("id ending in _raw", lambda f: f.set_key("parachute", 1, "id", value="D3_raw"), "test.toml",
     "key 'parachute[1].id'", "does not end with '_raw'"),
    ("id ending in _sigma_random", lambda f: f.set_key("parachute", 1, "id", value="D3_sigma_random"), "test.toml",
     "key 'parachute[1].id'", "would give the reduction's columns the names of others"),
    ("id ending in _sigma", lambda f: f.set_key("parachute", 1, "id", value="D3_sigma"), "test.toml",
     "key 'parachute[1].id'", "does not end with '_raw', '_random', '_systematic' or '_sigma'"),
    # a hostile test.toml of 202 parachutes passed every check, to a fit of 2,000+ parameters (2026-11-30)
    ("17 parachutes", lambda f: f.set_key("parachute", value=[
        {**{k: v for k, v in f.read_toml()["parachute"][1].items() if k != "load_cell"}, "id": f"X{n}"}
        for n in range(17)]),
     "test.toml", "key 'parachute'", "17 parachutes, more than 16 (the largest clusters flown hold 8"),
    ("9 stages", lambda f: f.set_key("parachute", 0, "stage", value=[
        {"label": f"s{k}", "start": 1.0 + k, "start_sigma": 0.05} for k in range(9)]),
     "test.toml", "key 'parachute 'D3'.stage'", "9 stages, more than 8 (a canopy disreefs two or three times"),
    ("kind with a trailing space", lambda f: f.set_key("parachute", 0, "kind", value="drogue "), "test.toml",
     "key 'parachute 'D3'.kind'", "e.g. 'drogue', 'main', 'pilot', 'fbcp' or a kind of your own"),
    ("semicolon-separated CSV", lambda f: _separated_by(f, ";"), "data.csv", "row 1 (header)",
     "the columns are separated by semicolons, not commas"),
    ("semicolons and decimal commas", lambda f: _separated_by(f, ";", decimal=","), "data.csv", "row 1 (header)",
     "separated by semicolons"),
    ("tab-separated CSV", lambda f: _separated_by(f, "\t"), "data.csv", "row 1 (header)", "separated by tabs"),
    ("data.csv a folder", lambda f: ((f.folder / "data.csv").unlink(), (f.folder / "data.csv").mkdir()),
     "data.csv", None, "is a folder, not a file"),
    ("test.toml a folder", lambda f: ((f.folder / "test.toml").unlink(), (f.folder / "test.toml").mkdir()),
     "test.toml", None, "is a folder, not a file"),
    ("test.toml a broken link", lambda f: _replace_by_link(f.folder / "test.toml", f.folder / "gone.toml"),
     "test.toml", None, "is a link to nothing"),
    ("test.toml a loop of links", lambda f: _replace_by_link(f.folder / "test.toml", f.folder / "other.toml",
                                                             loop=True), "test.toml", None, "a loop of links"),
    ("data.csv a loop of links", lambda f: _replace_by_link(f.folder / "data.csv", f.folder / "other.csv",
                                                            loop=True), "data.csv", None, "a loop of links"),
]
REFUSALS += FUZZED


def _replace_by_link(path, target, loop=False):
    """``path`` becomes a symbolic link to ``target``, which is missing or (``loop``) links back to it."""
    path.unlink()
    path.symlink_to(target)
    if loop:
        target.symlink_to(path)


@pytest.mark.parametrize("defect, file, place, problem", [case[1:] for case in REFUSALS],
                         ids=[case[0] for case in REFUSALS])
def test_refusal(example_dir, bundle_files, snapshot, defect, file, place, problem):
    folder = example_dir(DROGUE)
    defect(bundle_files(folder))
    before = snapshot(folder.parent)
    with pytest.raises(BundleError) as info:
        read_bundle(folder)
    message = str(info.value)
    assert message.startswith(f"{folder / file}{', ' + place if place else ''}: "), message
    assert problem in message, message
    assert ". Fix: " in message
    assert message.isprintable() and len(message) < 1000  # no escape, newline or megabyte reaches a terminal
    assert snapshot(folder.parent) == before


def test_trailing_blank_lines_are_not_data(example_dir, bundle_files):
    folder = example_dir(DROGUE)
    with bundle_files(folder).csv_path.open("a", encoding="utf-8") as fh:
        fh.write("\n\n")
    assert len(read_bundle(folder).data) == EXAMPLES[DROGUE][2]


def test_missing_folder_is_refused(tmp_path):
    with pytest.raises(BundleError, match=r"folder not found\. Fix: "):
        read_bundle(tmp_path / "nowhere")


def test_byte_order_marks_are_accepted(example_dir, bundle_files, same_test):
    """Editors that save UTF-8 with a BOM (Notepad, Excel) write valid bundles."""
    folder = example_dir(DROGUE)
    expected = read_bundle(folder)
    files = bundle_files(folder)
    for path in (files.toml_path, files.csv_path):
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    same_test(read_bundle(folder), expected, rtol=0)


def test_the_folder_name_stands_in_for_a_missing_name_only_if_it_is_a_safe_name(example_dir, bundle_files):
    folder = example_dir(DROGUE, "CDT-3-2 drogue")
    bundle_files(folder).delete_key("name")
    assert read_bundle(folder).name == "CDT-3-2 drogue"
    hidden = example_dir(DROGUE, ".hidden")
    bundle_files(hidden).delete_key("name")
    with pytest.raises(BundleError) as info:
        read_bundle(hidden)
    assert str(info.value).startswith(f"{hidden / 'test.toml'}, key 'name': no name given, and the folder name "
                                      "'.hidden' cannot be used: starts with '.'. Fix: add name = ")


@pytest.mark.parametrize("limit, value, problem", [
    ("MAX_CSV_ROWS", 1000, "1,601 data rows, more than 1,000"),
    ("MAX_CSV_BYTES", 100_000, "bytes, more than the 100,000 a data.csv may have"),
    ("MAX_CSV_COLUMNS", 10, "13 columns, more than 10"),
])
def test_data_csv_size_limits_are_checked_before_parsing(example_dir, monkeypatch, limit, value, problem):
    """The limits (2,000,000 rows, 500 MB, 1,000 columns) lowered so that a small file exceeds them."""
    from cpas_bayes.data import bundle_csv

    monkeypatch.setattr(bundle_csv, limit, value)
    monkeypatch.setattr(bundle_csv.pd, "read_csv", None)  # parsing would fail loudly: it must not be reached
    folder = example_dir(DROGUE)
    with pytest.raises(BundleError) as info:
        read_bundle(folder)
    assert str(info.value).startswith(f"{folder / 'data.csv'}")
    assert problem in str(info.value) and ". Fix: " in str(info.value)


def test_stated_limits_are_the_documented_ones():
    from cpas_bayes.data import limits

    assert (limits.MAX_CSV_ROWS, limits.MAX_CSV_BYTES, limits.MAX_DURATION, limits.MAX_SAMPLE_INTERVAL) == \
        (2_000_000, 500_000_000, 3600.0, 10.0)
    doc = (Path(__file__).resolve().parent.parent / "docs" / "test-bundle.md").read_text(encoding="utf-8")
    for spec in list(limits.CHANNELS.values()) + list(limits.VEHICLE.values()) + list(limits.PARACHUTE.values()):
        assert spec.reason in doc, spec.reason


@pytest.mark.skipif(not hasattr(__import__("os"), "mkfifo"), reason="no named pipes on this platform")
@pytest.mark.timeout(30)  # a reader blocked on the pipe fails here, not at the suite's limit
def test_a_pipe_in_place_of_data_csv_is_refused_not_read(example_dir):
    # opening a FIFO for reading blocks until a writer comes: the reader must look before it opens
    import os

    folder = example_dir(DROGUE)
    (folder / "data.csv").unlink()
    os.mkfifo(folder / "data.csv")
    with pytest.raises(BundleError, match="data.csv: not a regular file .a pipe"):
        read_bundle(folder)



def test_unit_factors_are_pints_and_reading_a_bundle_does_not_load_pint():
    """The US factors are written from the 1959 definitions; pint derives the same. pint (0.4 s to import
    and parse per process) loads only for a logger column's free-form unit, not to read a bundle."""
    import subprocess
    import sys

    from cpas_bayes.core.units import pint_factors

    for name, system in UNIT_SYSTEMS.items():
        derived = pint_factors(name)
        assert set(derived) == set(system.to_si)
        for quantity, factor in derived.items():
            assert system.to_si[quantity] == pytest.approx(factor, rel=1e-14), (name, quantity)
    script = ("import sys; from cpas_bayes.data.bundle import read_bundle, example_bundles; "
              "tests = [read_bundle(p) for p in example_bundles()]; print('pint' in sys.modules, tests[0].units.name)")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "US"]

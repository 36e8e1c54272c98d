"""Property-based tests of bundle I/O: generated valid bundles read and round-trip; a generated
bundle with any one defect is refused with a BundleError naming the file, the place and the fix,
and nothing is written."""

from __future__ import annotations

import copy
import math
import string
import tempfile
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cpas_bayes.core.units import UNIT_SYSTEMS
from cpas_bayes.data import limits
from cpas_bayes.core.ownership import MARKER
from cpas_bayes.data.bundle import CSV_NAME as CSV
from cpas_bayes.data.bundle import (INFLATIONS, KINDS, PARACHUTE_KEYS, STAGE_KEYS, TOP_KEYS, VEHICLE_KEYS,
                                    read_bundle)
from cpas_bayes.data.bundle_write import write_bundle
from cpas_bayes.data.bundle import TOML_NAME as TOML
from cpas_bayes.core.errors import BundleError
from cpas_bayes.core.inputs import name_problem

REQUIRED = ("time", "G", "qbar", "airspeed", "gamma")
EXAMPLES_PER_DEFECT = 60
SETTINGS = dict(deadline=None, derandomize=True, database=None)

# Generated channels: canonical column -> (quantity, low, high). Quantity None: no unit (g, deg).
CHANNELS = {"G": (None, -1.0, 12.0), "qbar": ("pressure", 0.5, 900.0), "airspeed": ("speed", 5.0, 900.0),
            "gamma": (None, -90.0, 90.0), "density": ("density", 1e-4, 1e-3), "altitude": ("length", 0.0, 4e4),
            "F": ("force", -500.0, 4e4), "theta": (None, 0.0, 60.0)}


@dataclass
class Plan:
    """A generated valid bundle and what reading it must give."""

    doc: dict          # test.toml
    columns: dict      # data.csv column -> cell strings, in file order
    expected: dict     # canonical column of FlightTest.data -> SI values

    @property
    def n_rows(self):
        return len(self.columns["time"])

    def write(self, files):
        files.folder.mkdir()
        files.write_toml(self.doc)
        names = list(self.columns)
        files.write_rows([names] + [list(cells) for cells in zip(*self.columns.values())])

    def parachute(self, i):
        return self.doc["parachute"][i]


# ---------------------------------------------------------------------------
# valid bundles

def floats(low, high):
    return st.floats(low, high, allow_subnormal=False)


ids = st.text(string.ascii_uppercase + string.digits, min_size=1, max_size=4)
# Any name that can be one path component (core.inputs.name_problem), Unicode included.
names = st.text(min_size=1, max_size=12).filter(lambda s: name_problem(s) is None)
# Names a bundle may give a parachute's columns (the canonical ones, F_<id> and theta_<id>, or others).
COLUMN_NAMES = {"load_cell": ("F_{}", "LC_{}", "riser{}"), "flyout_angle": ("theta_{}", "angle_{}")}


@st.composite
def valid_bundles(draw, us_to_si):
    units = draw(st.sampled_from(["US", "SI"]))
    factor = (lambda q: us_to_si[q] if q else 1.0) if units == "US" else (lambda q: 1.0)
    n = draw(st.integers(5, 30))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    columns, expected, sigma = {}, {}, {}

    t0 = draw(st.sampled_from(["0", "-2.5", "1234.5", "1700000000"]))
    dt = draw(st.sampled_from(["0.001", "0.01", "0.05", "0.1"]))
    columns["time"] = [str(Decimal(t0) + k * Decimal(dt)) for k in range(n)]
    expected["time"] = np.array([float(c) for c in columns["time"]])

    def channel(column, canonical, kind):
        quantity, low, high = CHANNELS[kind]
        cells = [f"{x:.6g}" for x in rng.uniform(low, high, n)]
        columns[column] = cells
        expected[canonical] = np.array([float(c) for c in cells]) * factor(quantity)

    def channel_sigma(column, canonical, kind, optional=False):
        """A sigma column, a constant [sigma] entry, or (if optional) nothing."""
        quantity = CHANNELS[kind][0]
        how = draw(st.sampled_from(["column", "table", "none"] if optional else ["column", "table"]))
        if how == "column":
            cells = [f"{x:.4g}" for x in rng.uniform(0.0, 50.0, n)]
            cells[0] = "0"
            columns[f"{column}_sigma"] = cells
            values = np.array([float(c) for c in cells])
        elif how == "table":
            sigma[column] = draw(floats(0.0, 50.0))
            values = np.full(n, sigma[column])
        else:
            values = np.zeros(n)
        expected[f"{canonical}_sigma"] = values * factor(quantity)

    for column in REQUIRED[1:]:
        channel(column, column, column)
    for column in ("density", "altitude"):
        if draw(st.booleans()):
            channel(column, column, column)
    channel_sigma("G", "G", "G")
    channel_sigma("qbar", "qbar", "qbar")

    parachutes = []
    for pid in draw(st.lists(ids, min_size=1, max_size=4, unique=True)):
        # Stage starts inside the record: half a step after a sample that is not the last.
        starts = [float(Decimal(t0) + (k + Decimal("0.5")) * Decimal(dt))
                  for k in sorted(draw(st.lists(st.integers(0, n - 2), min_size=1, max_size=3, unique=True)))]
        entry = {"id": pid, "kind": draw(st.sampled_from(KINDS)), "inflation": draw(st.sampled_from(INFLATIONS)),
                 "diameter": draw(floats(0.5, 200.0)), "weight": draw(floats(0.0, 500.0))}
        if draw(st.booleans()):
            entry["weight_sigma"] = draw(floats(0.0, 10.0))
        for key, kind in (("load_cell", "F"), ("flyout_angle", "theta")):
            if draw(st.booleans()):
                entry[key] = draw(st.sampled_from(COLUMN_NAMES[key])).format(pid)
                channel(entry[key], f"{kind}_{pid}", kind)
                channel_sigma(entry[key], f"{kind}_{pid}", kind, optional=kind == "theta")
        entry["stage"] = [{"label": f"stage {k + 1}", "start": s, "start_sigma": 0.05}
                          for k, s in enumerate(starts)]
        entry["stage"][-1]["label"] = "full open"
        parachutes.append(entry)

    doc = {"name": draw(names), "units": units, "phase": "drogue",
           "vehicle": {"weight": draw(floats(1.0, 1e5)), "weight_sigma": 100.0, "cds": draw(floats(0.0, 100.0))},
           "parachute": parachutes}
    if sigma:
        doc["sigma"] = sigma
    order = draw(st.permutations(list(columns)))
    return Plan(doc, {c: columns[c] for c in order}, expected)


# ---------------------------------------------------------------------------
# defects: each plants one fault in a written plan's files and returns (file, place, problem);
# place None means the message names the file only.

def rows(draw, plan, lowest=2):
    """A data row's file line (the header is line 1)."""
    return draw(st.integers(lowest, plan.n_rows + 1))


def chute(draw, plan):
    """Index of one of the plan's parachutes."""
    return draw(st.integers(0, len(plan.doc["parachute"]) - 1))


junk_text = st.text(string.ascii_letters + string.digits + " .-+_!?", max_size=8)


def is_finite_number(text):
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def missing_toml(draw, plan, files):
    files.toml_path.unlink()
    return TOML, None, "file not found"


def missing_csv(draw, plan, files):
    files.csv_path.unlink()
    return CSV, None, "file not found"


def missing_required_column(draw, plan, files):
    column = draw(st.sampled_from(REQUIRED))
    files.drop_column(column)
    other = {"qbar": "airspeed", "airspeed": "qbar"}.get(column)   # one without the other: said as such
    return CSV, f"column '{column}'", f"missing column '{column}': data.csv gives '{other}'" if other else \
        "missing column"


def missing_named_column(draw, plan, files):
    i, key = chute(draw, plan), draw(st.sampled_from(["load_cell", "flyout_angle"]))
    entry = plan.parachute(i)
    if key in entry:
        name = entry[key]
        files.drop_column(name)
    else:
        name = f"absent_{entry['id']}"
        files.set_key("parachute", i, key, value=name)
    return CSV, f"column '{name}'", f"parachute '{entry['id']}' names {key} '{name}' but data.csv has no such column"


def non_numeric_cell(draw, plan, files):
    row, column = rows(draw, plan), draw(st.sampled_from(list(plan.columns)))
    files.set_cell(row, column, draw(junk_text.filter(lambda s: not is_finite_number(s))))
    return CSV, f"row {row}, column '{column}'", "the cell "


def non_finite_cell(draw, plan, files):
    row, column = rows(draw, plan), draw(st.sampled_from(list(plan.columns)))
    files.set_cell(row, column, draw(st.sampled_from(["nan", "NaN", "NAN", "inf", "-inf", "Infinity", "1e999"])))
    return CSV, f"row {row}, column '{column}'", "not a finite number"


def time_repeated(draw, plan, files):
    row = rows(draw, plan, lowest=3)
    files.set_cell(row, "time", files.cell(row - 1, "time"))
    return CSV, f"row {row}, column 'time'", "time not strictly increasing"


def time_decreasing(draw, plan, files):
    row = rows(draw, plan, lowest=3)
    earlier = float(files.cell(row - 1, "time")) - draw(floats(1e-3, 1e3))
    files.set_cell(row, "time", repr(earlier))
    return CSV, f"row {row}, column 'time'", "time not strictly increasing"


def qbar_not_positive(draw, plan, files):
    row = rows(draw, plan)
    value = draw(st.sampled_from(["0", "0.0", "-0", "-1e-9"]) | st.floats(max_value=0.0, allow_infinity=False,
                                                                          allow_nan=False).map(repr))
    files.set_cell(row, "qbar", value)
    return CSV, f"row {row}, column 'qbar'", "≤ 0"


def negative_sigma_cell(draw, plan, files):
    sigma_columns = [c for c in plan.columns if c.endswith("_sigma")]
    if not sigma_columns:  # every sigma is a [sigma] constant: give G a column in place of its entry
        lines = files.read_rows()
        files.write_rows([r + [c] for r, c in zip(lines, ["G_sigma"] + ["0.1"] * plan.n_rows)])
        files.delete_key("sigma", "G")   # both at once are refused as given twice
        sigma_columns = ["G_sigma"]
    row, column = rows(draw, plan), draw(st.sampled_from(sigma_columns))
    files.set_cell(row, column, repr(-draw(floats(1e-9, 1e3))))
    return CSV, f"row {row}, column '{column}'", "negative sigma"


def negative_sigma_entry(draw, plan, files):
    channels = ["G", "qbar"] + [e[k] for e in plan.doc["parachute"] for k in ("load_cell", "flyout_angle") if k in e]
    channel = draw(st.sampled_from(channels))
    files.set_key("sigma", channel, value=-draw(floats(1e-9, 1e3)))
    return TOML, f"key 'sigma.{channel}'", "must be a finite number ≥ 0"


def negative_sigma_key(draw, plan, files):
    i = chute(draw, plan)
    pid, n_stages = plan.parachute(i)["id"], len(plan.parachute(i)["stage"])
    path, key = draw(st.sampled_from([(("vehicle", "weight_sigma"), "vehicle.weight_sigma"),
                                      (("vehicle", "cds_sigma"), "vehicle.cds_sigma"),
                                      (("parachute", i, "weight_sigma"), f"parachute '{pid}'.weight_sigma")]
                                     + [(("parachute", i, "stage", k, "start_sigma"),
                                         f"parachute '{pid}'.stage[{k}].start_sigma") for k in range(n_stages)]))
    files.set_key(*path, value=-draw(floats(1e-9, 1e3)))
    return TOML, f"key '{key}'", "a sigma cannot be negative"


def strings_other_than(choices):
    return st.text(min_size=1, max_size=10).filter(lambda s: s.strip() and s not in choices)


def unknown_units(draw, plan, files):
    value = draw(strings_other_than(("US", "SI")))
    files.set_key("units", value=value)
    return TOML, "key 'units'", f"unknown units {value!r}"


def unknown_kind(draw, plan, files):
    """A package kind in other letter case: a typo, refused (any other safe name is a kind of the user's)."""
    i, kind = chute(draw, plan), draw(st.sampled_from(KINDS))
    value = draw(st.sampled_from([kind.upper(), kind.capitalize()]))
    files.set_key("parachute", i, "kind", value=value)
    return TOML, f"key 'parachute '{plan.parachute(i)['id']}'.kind'", f"unknown kind {value!r}"


def unknown_inflation(draw, plan, files):
    return unknown_choice(draw, plan, files, "inflation", INFLATIONS)


def unknown_choice(draw, plan, files, key, choices):
    i, value = chute(draw, plan), draw(strings_other_than(choices))
    files.set_key("parachute", i, key, value=value)
    return TOML, f"key 'parachute '{plan.parachute(i)['id']}'.{key}'", f"unknown value {value!r}"


def stages_out_of_order(draw, plan, files):
    i = chute(draw, plan)
    stages = copy.deepcopy(plan.parachute(i)["stage"])
    if len(stages) == 1:
        stages.append(dict(stages[0], label="full open"))
    k = draw(st.integers(1, len(stages) - 1))
    stages[k]["start"] = stages[k - 1]["start"] - draw(st.sampled_from([0.0, 0.01]) | floats(0.0, 100.0))
    files.set_key("parachute", i, "stage", value=stages)
    return TOML, f"key 'parachute '{plan.parachute(i)['id']}'.stage[{k}].start'", "stages out of time order"


def parachute_without_stages(draw, plan, files):
    i = chute(draw, plan)
    if draw(st.booleans()):
        files.delete_key("parachute", i, "stage")
    else:
        files.set_key("parachute", i, "stage", value=[])
    pid = plan.parachute(i)["id"]
    return TOML, f"key 'parachute '{pid}'.stage'", f"parachute '{pid}' has no stages"


def duplicate_parachute_id(draw, plan, files):
    parachutes = copy.deepcopy(plan.doc["parachute"])
    if len(parachutes) == 1:
        parachutes.append(copy.deepcopy(parachutes[0]))
    j = draw(st.integers(1, len(parachutes) - 1))
    pid = parachutes[draw(st.integers(0, j - 1))]["id"]
    parachutes[j]["id"] = pid
    files.set_key("parachute", value=parachutes)
    return TOML, f"key 'parachute[{j}].id'", f"duplicate parachute id '{pid}'"


def missing_sigma(draw, plan, files):
    channel = draw(st.sampled_from(["G", "qbar"] + [e["load_cell"] for e in plan.doc["parachute"]
                                                     if "load_cell" in e]))
    if f"{channel}_sigma" in plan.columns:
        files.drop_column(f"{channel}_sigma")
    else:
        files.delete_key("sigma", channel)
    return CSV, f"column '{channel}_sigma'", f"no 1-sigma for '{channel}'"


def sigma_given_twice(draw, plan, files):
    """A channel's 1-sigma as a column and as a [sigma] entry: one would be silently ignored."""
    channel = draw(st.sampled_from(["G", "qbar"] + [e["load_cell"] for e in plan.doc["parachute"]
                                                     if "load_cell" in e]))
    if f"{channel}_sigma" in plan.columns:
        files.set_key("sigma", channel, value=0.5)
    else:
        lines = files.read_rows()
        files.write_rows([r + [c] for r, c in zip(lines, [f"{channel}_sigma"] + ["0.5"] * plan.n_rows)])
    return TOML, f"key 'sigma.{channel}'", f"the 1-sigma of '{channel}' is given twice"


# Issue #18: what a careless or adversarial user hands over.

def misspelt(key):
    """Near misses of a valid key: a letter dropped, doubled or capitalised, a plural."""
    return st.sampled_from([key[:-1], key + key[-1], key.upper(), key.capitalize(), key + "s"]).filter(
        lambda k: k and k != key)


def unknown_key(draw, plan, files):
    i = chute(draw, plan)
    entry = plan.parachute(i)
    sigma_keys = ["G", "qbar"] + [e[k] for e in plan.doc["parachute"] for k in ("load_cell", "flyout_angle")
                                  if k in e]
    where = draw(st.sampled_from(["top", "vehicle", "parachute", "stage", "sigma"]))
    path, valid, place = {
        "top": ((), TOP_KEYS, ""),
        "vehicle": (("vehicle",), VEHICLE_KEYS, "vehicle."),
        "parachute": (("parachute", i), PARACHUTE_KEYS, f"parachute[{i}]."),
        "stage": (("parachute", i, "stage", 0), STAGE_KEYS, f"parachute '{entry['id']}'.stage[0]."),
        "sigma": (("sigma",), tuple(sigma_keys), "sigma."),
    }[where]
    key = draw(st.sampled_from(valid).flatmap(misspelt).filter(lambda k: k not in valid))
    files.set_key(*path, key, value=1.0)
    return TOML, f"key '{place}{key}'", f"unknown key {key!r}. Fix: "


bad_names = st.one_of(
    st.builds(lambda a, b, sep: a + sep + b, ids, ids, st.sampled_from(["/", "\\", ":", "/../"])),
    st.builds(lambda a, c: a + c, ids, st.sampled_from(["\n", "\r", "\t", "\x1b[31m", "\x00", "\u202e"])),
    st.builds(lambda a: "." + a, ids), st.just(".."), st.just("../../victim"),
    st.integers(65, 5000).map(lambda n: "x" * n))


def unsafe_name(draw, plan, files):
    value = draw(bad_names)
    if draw(st.booleans()):
        files.set_key("name", value=value)
        return TOML, "key 'name'", "test name "
    i = chute(draw, plan)
    files.set_key("parachute", i, "id", value=value)
    return TOML, f"key 'parachute[{i}].id'", "parachute id "


def implausible_cell(draw, plan, files):
    specs = {c: limits.CHANNELS[c] for c in ("G", "qbar", "airspeed", "gamma", "density", "altitude")
             if c in plan.columns}
    for e in plan.doc["parachute"]:
        specs.update({e[k]: limits.CHANNELS[c] for k, c in (("load_cell", "F"), ("flyout_angle", "theta")) if k in e})
    column, row = draw(st.sampled_from(sorted(specs))), rows(draw, plan)
    low, high, _ = specs[column].limits(UNIT_SYSTEMS[plan.doc["units"]])
    beyond = draw(floats(1.001, 1e12))
    value = high * beyond if high > 0 else high + beyond
    if low < 0 and draw(st.booleans()):
        value = low * beyond
    files.set_cell(row, column, repr(value))
    return CSV, f"row {row}, column '{column}'", "is outside"


def record_beyond_an_hour(draw, plan, files):
    last = plan.n_rows + 1
    files.set_cell(last, "time", repr(float(files.cell(2, "time")) + 3600.0 + draw(floats(0.5, 1e6))))
    return CSV, f"row {last}, column 'time'", "more than an hour"


def stage_outside_record(draw, plan, files):
    i = chute(draw, plan)
    stages = plan.parachute(i)["stage"]
    t0, t1 = float(files.cell(2, "time")), float(files.cell(plan.n_rows + 1, "time"))
    if draw(st.booleans()):
        k, value, side = len(stages) - 1, t1 + draw(st.sampled_from([0.0]) | floats(1e-3, 1e4)), "after"
    else:
        k, value, side = 0, t0 - draw(floats(1e-3, 1e4)), "before"
    files.set_key("parachute", i, "stage", k, "start", value=value)
    return TOML, f"key 'parachute '{plan.parachute(i)['id']}'.stage[{k}].start'", f"{side} the record"


def column_used_twice(draw, plan, files):
    with_cells = [i for i, e in enumerate(plan.doc["parachute"]) if "load_cell" in e]
    n = len(plan.doc["parachute"])
    if n < 2 or not with_cells:  # no second parachute to share with: point a load cell at a vehicle channel
        column = draw(st.sampled_from(REQUIRED))
        files.set_key("parachute", 0, "load_cell", value=column)
        return TOML, f"key 'parachute '{plan.parachute(0)['id']}'.load_cell'", "a channel of the vehicle"
    i = draw(st.sampled_from(with_cells))
    j = draw(st.integers(0, n - 1).filter(lambda j: j != i))
    files.set_key("parachute", j, "load_cell", value=plan.parachute(i)["load_cell"])
    first, second = min(i, j), max(i, j)
    return (TOML, f"key 'parachute '{plan.parachute(second)['id']}'.load_cell'",
            f"is already the load_cell of parachute '{plan.parachute(first)['id']}'")


def trailing_commas(draw, plan, files):
    header = draw(st.booleans())
    lines = files.read_rows()
    files.write_rows([r + [""] if header or k else r for k, r in enumerate(lines)])
    if header:
        return CSV, f"row 1 (header), column {len(lines[0]) + 1}", "the header ends with a comma"
    return CSV, "row 2", "the row ends with a comma (every data row does)"


DEFECTS = [missing_toml, missing_csv, missing_required_column, missing_named_column, non_numeric_cell,
           non_finite_cell, time_repeated, time_decreasing, qbar_not_positive, negative_sigma_cell,
           negative_sigma_entry, negative_sigma_key, unknown_units, unknown_kind, unknown_inflation,
           stages_out_of_order, parachute_without_stages, duplicate_parachute_id, missing_sigma, sigma_given_twice,
           unknown_key, unsafe_name, implausible_cell, record_beyond_an_hour, stage_outside_record,
           column_used_twice, trailing_commas]


# ---------------------------------------------------------------------------
# properties


@pytest.mark.parametrize("defect", DEFECTS, ids=lambda d: d.__name__)
@settings(max_examples=EXAMPLES_PER_DEFECT, **SETTINGS)
@given(data=st.data())
def test_one_defect_is_refused_cleanly(bundle_files, snapshot, us_to_si, defect, data):
    plan = data.draw(valid_bundles(us_to_si), label="bundle")
    with tempfile.TemporaryDirectory() as root:
        files = bundle_files(Path(root) / "bundle")
        plan.write(files)
        file, place, problem = defect(data.draw, plan, files)
        before = snapshot(root)
        with pytest.raises(BundleError) as info:  # any other exception type fails the test
            read_bundle(files.folder)
        message = str(info.value)
        assert message.startswith(f"{files.folder / file}{', ' + place if place else ''}: "), message
        assert problem in message, message
        assert ". Fix: " in message
        assert message.isprintable() and len(message) < 1000, message
        assert snapshot(root) == before


@settings(max_examples=150, **SETTINGS)
@given(data=st.data())
def test_valid_bundles_read_and_round_trip(bundle_files, snapshot, same_test, us_to_si, data):
    plan = data.draw(valid_bundles(us_to_si), label="bundle")
    with tempfile.TemporaryDirectory() as root:
        files = bundle_files(Path(root) / "bundle")
        plan.write(files)
        before = snapshot(root)
        test = read_bundle(files.folder)
        assert snapshot(root) == before

        assert test.units.name == plan.doc["units"]
        to_si = us_to_si if test.units.name == "US" else dict.fromkeys(us_to_si, 1.0)
        assert test.vehicle.weight == pytest.approx(plan.doc["vehicle"]["weight"] * to_si["force"], rel=1e-12)
        assert test.vehicle.cds == pytest.approx(plan.doc["vehicle"]["cds"] * to_si["area"], rel=1e-12)
        assert [p.diameter for p in test.parachutes] == pytest.approx(
            [e["diameter"] * to_si["length"] for e in plan.doc["parachute"]], rel=1e-12)
        assert [p.id for p in test.parachutes] == [e["id"] for e in plan.doc["parachute"]]
        assert [len(p.stages) for p in test.parachutes] == [len(e["stage"]) for e in plan.doc["parachute"]]
        assert sorted(test.data.columns) == sorted(plan.expected)
        for column, values in plan.expected.items():
            np.testing.assert_allclose(test.data[column], values, rtol=1e-12, atol=0, err_msg=column)

        written = write_bundle(test, Path(root) / "copy")
        assert sorted(p.name for p in Path(root).iterdir()) == ["bundle", "copy"]
        assert sorted(p.name for p in written.iterdir()) == sorted([MARKER, CSV, TOML])  # the marker: cpas-bayes wrote it
        same_test(read_bundle(written), test, rtol=1e-9)

"""Logger bundles (no measured q̄): GNSS velocity and altitude with blanks between samples, [wind],
[atmosphere] and [rate]; SI conversion, the write/read round trip and every refusal (docs/test-bundle.md,
"Logger bundles")."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest
from bundle_writer import write_by_hand

from cpas_bayes.core.errors import BundleError
from cpas_bayes.core.units import UNIT_SYSTEMS
from cpas_bayes.data.bundle import read_bundle, summary
from cpas_bayes.data.bundle_write import write_bundle

# 20 Hz accelerometer and load cell (t = 0.05 k, 41 rows) interleaved with a 5 Hz GNSS receiver
# (t = 0.01 + 0.2 k, 10 rows): 51 rows, each with one instrument's cells and the other's blank.
G_TIMES = [round(0.05 * k, 6) for k in range(41)]
GNSS_TIMES = [round(0.01 + 0.2 * k, 6) for k in range(10)]
HEADER = ["time", "G", "v_north", "v_east", "v_up", "altitude", "altitude_sigma", "F_D1"]


def g_row(k):
    return {"time": G_TIMES[k], "G": 1.0 + 0.1 * k, "F_D1": 100.0 + k}


def gnss_row(k):
    return {"time": GNSS_TIMES[k], "v_north": 10.0 + k, "v_east": -2.0, "v_up": -30.0 + k,
            "altitude": 3000.0 - 6.0 * k, "altitude_sigma": 5.0}


ROWS = sorted([g_row(k) for k in range(41)] + [gnss_row(k) for k in range(10)], key=lambda r: r["time"])

DOC = {
    "name": "LOG-1", "units": "SI", "phase": "drogue",
    "vehicle": {"weight": 20000.0, "weight_sigma": 100.0, "cds": 2.0, "cds_sigma": 0.2},
    "parachute": [{"id": "D1", "kind": "drogue", "inflation": "infinite", "diameter": 7.0, "weight": 400.0,
                   "weight_sigma": 5.0, "load_cell": "F_D1",
                   "stage": [{"label": "full open", "start": 0.5, "start_sigma": 0.05}]}],
    "sigma": {"G": 0.03, "v_north": 0.1, "v_east": 0.15, "v_up": 0.2, "F_D1": 10.0},
    "wind": {"altitude": [0.0, 1000.0, 3000.0], "north": [1.0, 2.0, 3.0], "east": [-4.0, -5.0, -6.0], "sigma": 1.5},
    "atmosphere": {"altitude": [0.0, 5000.0], "density": [1.225, 0.736]},
    "rate": {"G": 20.0},
}


def write_logger(folder, doc=None, rows=None, header=None):
    """A logger bundle written by hand: test.toml from ``doc``, data.csv with empty cells for absent keys."""
    return write_by_hand(folder, DOC if doc is None else doc, rows or ROWS, header or HEADER)


def edited(**changes):
    """A deep copy of DOC with top-level tables replaced (None deletes)."""
    doc = {k: (dict(v) if isinstance(v, dict) else v) for k, v in DOC.items()}
    for key, value in changes.items():
        if value is None:
            doc.pop(key, None)
        else:
            doc[key] = value
    return doc


def column(name, rows=ROWS):
    return np.array([r.get(name, np.nan) for r in rows], dtype=float)


# ---------------------------------------------------------------------------
# reading


def test_logger_bundle_reads_with_blanks_as_nan(tmp_path):
    test = read_bundle(write_logger(tmp_path / "log"))
    assert not test.measured_qbar
    assert list(test.data.columns) == ["time", "G", "G_sigma", "v_north", "v_east", "v_up", "v_north_sigma",
                                       "v_east_sigma", "v_up_sigma", "altitude", "altitude_sigma", "F_D1",
                                       "F_D1_sigma"]
    assert len(test.data) == 51
    np.testing.assert_array_equal(test.time, column("time"))
    for name in ("G", "v_north", "v_east", "v_up", "altitude", "altitude_sigma", "F_D1"):
        np.testing.assert_array_equal(test.data[name], column(name), err_msg=name)   # SI: unchanged, NaN blanks
    gnss = np.isin(test.time, GNSS_TIMES)
    assert gnss.sum() == 10 and np.isnan(test.data["G"][gnss]).all() and np.isnan(test.data["v_up"][~gnss]).all()
    # [sigma] constants fill only the rows where the channel has a sample
    np.testing.assert_array_equal(test.data["G_sigma"], np.where(gnss, np.nan, 0.03))
    np.testing.assert_array_equal(test.data["v_east_sigma"], np.where(gnss, 0.15, np.nan))
    np.testing.assert_array_equal(test.data["F_D1_sigma"], np.where(gnss, np.nan, 10.0))

    air = test.air_data
    np.testing.assert_array_equal(air.wind.altitude, [0.0, 1000.0, 3000.0])
    np.testing.assert_array_equal(air.wind.north, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(air.wind.east, [-4.0, -5.0, -6.0])
    assert air.wind.sigma == 1.5
    np.testing.assert_array_equal(air.atmosphere.density, [1.225, 0.736])
    assert air.rates == {"G": 20.0}
    assert test.channels == ["time", "G", "v_north", "v_east", "v_up", "altitude", "F_D1"]


def test_us_logger_bundle_is_converted_to_si(tmp_path, us_to_si):
    doc = edited(units="US", atmosphere={"altitude": [0.0, 16000.0], "density": [0.00238, 0.00108]},
                 wind={"altitude": [0.0, 10000.0], "north": [3.0, 10.0], "east": [-12.0, 0.0], "sigma": 5.0},
                 vehicle={"weight": 4500.0, "weight_sigma": 20.0, "cds": 20.0, "cds_sigma": 2.0},
                 parachute=[{**DOC["parachute"][0], "diameter": 23.0, "weight": 90.0, "weight_sigma": 1.0}])
    test = read_bundle(write_logger(tmp_path / "log", doc))
    ft, fps, lbf = us_to_si["length"], us_to_si["speed"], us_to_si["force"]
    gnss = np.isin(test.time, GNSS_TIMES)
    for name, factor in (("v_north", fps), ("v_up", fps), ("altitude", ft), ("altitude_sigma", ft),
                         ("F_D1", lbf), ("G", 1.0)):
        np.testing.assert_allclose(test.data[name], column(name) * factor, rtol=1e-12, err_msg=name)
    np.testing.assert_allclose(test.data["v_up_sigma"], np.where(gnss, 0.2 * fps, np.nan), rtol=1e-12)
    np.testing.assert_allclose(test.data["F_D1_sigma"], np.where(gnss, np.nan, 10.0 * lbf), rtol=1e-12)
    air = test.air_data
    np.testing.assert_allclose(air.wind.altitude, [0.0, 10000.0 * ft], rtol=1e-12)
    np.testing.assert_allclose(air.wind.north, [3.0 * fps, 10.0 * fps], rtol=1e-12)
    np.testing.assert_allclose(air.wind.east, [-12.0 * fps, 0.0], rtol=1e-12)
    assert air.wind.sigma == pytest.approx(5.0 * fps, rel=1e-12)
    np.testing.assert_allclose(air.atmosphere.altitude, [0.0, 16000.0 * ft], rtol=1e-12)
    np.testing.assert_allclose(air.atmosphere.density, np.array([0.00238, 0.00108]) * us_to_si["density"],
                               rtol=1e-12)
    assert air.atmosphere.density[0] == pytest.approx(1.2266, rel=1e-3)   # slug/ft³ -> kg/m³ at sea level


def test_logger_bundle_without_air_tables_has_an_empty_spec(tmp_path):
    test = read_bundle(write_logger(tmp_path / "log", edited(wind=None, atmosphere=None, rate=None)))
    assert (test.air_data.wind, test.air_data.atmosphere, test.air_data.rates) == (None, None, {})


def test_sigma_columns_and_density_with_blanks(tmp_path):
    header = HEADER + ["G_sigma", "v_north_sigma", "v_east_sigma", "v_up_sigma", "density"]
    rows = [{**r, "G_sigma": 0.02} if "G" in r else
            {**r, "v_north_sigma": 0.3, "v_east_sigma": 0.3, "v_up_sigma": 0.5,
             **({"density": 0.9} if r["time"] < 1 else {})} for r in ROWS]
    doc = edited(sigma={"F_D1": 10.0}, atmosphere=None)
    test = read_bundle(write_logger(tmp_path / "log", doc, rows, header))
    gnss = np.isin(test.time, GNSS_TIMES)
    np.testing.assert_array_equal(test.data["G_sigma"], np.where(gnss, np.nan, 0.02))
    np.testing.assert_array_equal(test.data["v_up_sigma"], np.where(gnss, 0.5, np.nan))
    np.testing.assert_array_equal(test.data["density"], np.where(gnss & (test.time < 1), 0.9, np.nan))
    assert "density" in test.channels


def test_summary_names_the_air_data(tmp_path):
    s = summary(read_bundle(write_logger(tmp_path / "log")))
    assert s["air_data"] == ("GNSS velocity (10 samples at 5 Hz), altitude (10 samples), wind profile (3 levels), "
                             "density profile (2 levels)")
    no_rate = summary(read_bundle(write_logger(tmp_path / "log2", edited(rate=None, wind={
        "altitude": [0.0], "north": [1.0], "east": [2.0]}))))
    assert no_rate["air_data"].startswith("GNSS velocity (10 samples at 5 Hz), altitude (10 samples), constant wind")


def test_summary_of_a_bundle_with_qbar_is_unchanged(example_dir):
    s = summary(read_bundle(example_dir("drogue-clean")))
    assert "air_data" not in s


# ---------------------------------------------------------------------------
# round trip


def assert_same_logger(actual, expected):
    assert list(actual.data.columns) == list(expected.data.columns)
    pd.testing.assert_frame_equal(actual.data, expected.data, check_exact=False, rtol=1e-12, atol=0)
    a, e = actual.air_data, expected.air_data
    for part, fields in (("wind", ("altitude", "north", "east", "sigma")), ("atmosphere", ("altitude", "density"))):
        assert (getattr(a, part) is None) == (getattr(e, part) is None), part
        for f in fields if getattr(e, part) is not None else ():
            np.testing.assert_allclose(getattr(getattr(a, part), f), getattr(getattr(e, part), f), rtol=1e-12)
    assert a.rates == e.rates
    assert actual.vehicle.weight == pytest.approx(expected.vehicle.weight, rel=1e-12)


@pytest.mark.parametrize("units", ["SI", "US"])
def test_round_trip_through_write_bundle(tmp_path, units):
    original = read_bundle(write_logger(tmp_path / "log"))
    original = dataclasses.replace(original, units=UNIT_SYSTEMS[units])   # same SI test, written in `units`
    again = read_bundle(write_bundle(original, tmp_path / f"written-{units}"))
    assert again.units.name == units and not again.measured_qbar
    assert_same_logger(again, original)
    # blanks stay blank: a GNSS row has no G and no load, an accelerometer row no velocity
    lines = (tmp_path / f"written-{units}" / "data.csv").read_text().splitlines()
    header, second = lines[0].split(","), lines[2].split(",")   # t = 0.01: the first GNSS row
    assert second[header.index("time")] == "0.01"
    assert second[header.index("G")] == second[header.index("F_D1")] == ""
    if units == "US":
        assert float(second[header.index("altitude")]) == pytest.approx(3000.0 / 0.3048, rel=1e-12)
        assert float(second[header.index("v_north")]) == pytest.approx(10.0 / 0.3048, rel=1e-12)


def test_round_trip_without_air_tables(tmp_path):
    original = read_bundle(write_logger(tmp_path / "log", edited(wind=None, atmosphere=None, rate=None)))
    again = read_bundle(write_bundle(original, tmp_path / "written"))
    assert_same_logger(again, original)
    assert "wind" not in (tmp_path / "written" / "test.toml").read_text()


# ---------------------------------------------------------------------------
# refusals: the message names the file, the key or column, and a fix


def _half_blank_row(folder):
    rows = [dict(r) for r in ROWS]
    gnss = [r for r in rows if "v_east" in r]
    del gnss[3]["v_east"]                      # GNSS row 4 at t = 0.61 s
    row = rows.index(gnss[3]) + 2
    write_logger(folder, rows=rows)
    return row


def _logger(**changes):
    return lambda folder: write_logger(folder, edited(**changes)) and None


def _no_altitude_sigma(folder):
    rows = [{k: v for k, v in r.items() if k != "altitude_sigma"} for r in ROWS]
    write_logger(folder, rows=rows, header=[c for c in HEADER if c != "altitude_sigma"])


def _velocity_without_sigma_cell(folder):
    header = HEADER + ["v_up_sigma"]
    rows = [{**r, "v_up_sigma": 0.5} if "v_up" in r and r["time"] != GNSS_TIMES[2] else r for r in ROWS]
    write_logger(folder, edited(sigma={"G": 0.03, "v_north": 0.1, "v_east": 0.1, "F_D1": 10.0}), rows, header)
    return ROWS.index(next(r for r in ROWS if r["time"] == GNSS_TIMES[2])) + 2


def _zero_velocity_sigma_cell(folder):
    header = HEADER + ["v_up_sigma"]
    rows = [{**r, "v_up_sigma": 0.0 if r["time"] == GNSS_TIMES[2] else 0.5} if "v_up" in r else r for r in ROWS]
    write_logger(folder, edited(sigma={"G": 0.03, "v_north": 0.1, "v_east": 0.1, "F_D1": 10.0}), rows, header)
    return ROWS.index(next(r for r in ROWS if r["time"] == GNSS_TIMES[2])) + 2


def _few_g(folder):
    rows = [r for r in ROWS if "G" not in r or r["time"] < 0.45]   # 9 accelerometer rows
    write_logger(folder, edited(parachute=[{**DOC["parachute"][0], "stage": [
        {"label": "full open", "start": 0.2, "start_sigma": 0.05}]}]), rows)


def _no_v_up(folder):
    write_logger(folder, edited(sigma={"G": 0.03, "v_north": 0.1, "v_east": 0.1, "F_D1": 10.0}),
                 header=[c for c in HEADER if c != "v_up"])


def _fast_v(folder):
    rows = [{**r, "v_up": -5000.0} if r["time"] == GNSS_TIMES[1] else r for r in ROWS]
    write_logger(folder, rows=rows)
    return ROWS.index(next(r for r in ROWS if r["time"] == GNSS_TIMES[1])) + 2


def _nan_text(folder):
    write_logger(folder)
    path = folder / "data.csv"
    lines = path.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith("0.21,"))
    lines[i] = lines[i].replace(",11.0,", ",nan,", 1)
    path.write_text("\n".join(lines) + "\n")
    return i + 1


def _sigma_twice(folder):
    rows = [{**r, "v_up_sigma": 0.5} if "v_up" in r else r for r in ROWS]
    write_logger(folder, rows=rows, header=HEADER + ["v_up_sigma"])     # DOC's [sigma] also gives v_up


def _g_beside_axes(folder):
    rows = [{**r, "accel_x": 0.0, "accel_y": 0.0, "accel_z": r["G"]} if "G" in r else r for r in ROWS]
    write_logger(folder, rows=rows, header=HEADER + ["accel_x", "accel_y", "accel_z"])


def _density_beside_atmosphere(folder):
    rows = [{**r, "density": 0.9} if "v_up" in r else r for r in ROWS]
    write_logger(folder, rows=rows, header=HEADER + ["density"])         # DOC has an [atmosphere] profile


LOGGER_REFUSALS = [
    # id, defect (returns a row number where the place needs one), file, place, problem, fix
    ("half-blank velocity row", _half_blank_row, "data.csv", "row {row}, columns 'v_north', 'v_east', 'v_up'",
     "v_east empty where the other component(s) are given", "fill the empty components, or leave all three empty"),
    ("wind arrays of unequal length",
     _logger(wind={"altitude": [0.0, 1000.0, 3000.0], "north": [1.0, 2.0, 3.0], "east": [-4.0, -5.0]}),
     "test.toml", "key 'wind.east'", "has 2 value(s) but wind.altitude has 3",
     "give one east value per altitude level"),
    ("wind altitude not increasing",
     _logger(wind={"altitude": [0.0, 1000.0, 1000.0], "north": [1.0, 2.0, 3.0], "east": [1.0, 2.0, 3.0]}),
     "test.toml", "key 'wind.altitude[2]'", "altitudes not strictly increasing (1000 then 1000)",
     "list the levels of [wind] from the lowest up"),
    ("atmosphere altitude decreasing",
     _logger(atmosphere={"altitude": [5000.0, 0.0], "density": [0.736, 1.225]}),
     "test.toml", "key 'atmosphere.altitude[1]'", "altitudes not strictly increasing (5000 then 0)",
     "list the levels of [atmosphere] from the lowest up"),
    ("unknown key in [rate]", _logger(rate={"G": 20.0, "altitde": 5.0}), "test.toml", "key 'rate.altitde'",
     "unknown key 'altitde'", "did you mean 'altitude'? (valid: G, v, v_north, v_east, v_up, altitude)"),
    ("missing altitude sigma", _no_altitude_sigma, "data.csv", "column 'altitude_sigma'",
     "no 1-sigma for 'altitude' (required in a logger bundle)",
     "add a 'altitude_sigma' column, or 'altitude = <sigma>' under [sigma] in test.toml"),
    ("velocity sample without its sigma cell", _velocity_without_sigma_cell, "data.csv", "row {row}, column "
     "'v_up_sigma'", "the cell is empty, but 'v_up' has a sample in this row", "give the sample's 1-sigma"),
    ("wind beyond 150 m/s", _logger(wind={"altitude": [0.0], "north": [200.0], "east": [0.0]}), "test.toml",
     "key 'wind.north[0]'", "wind toward north = 200 m/s is outside -150 … 150 m/s", "SI bundles in"),
    ("rate out of range", _logger(rate={"G": 1e6}), "test.toml", "key 'rate.G'", "G = 1e+06 Hz is outside 0.1 … "
     "100000 Hz", "a rate is in Hz"),
    ("wind as a number", _logger(wind={"altitude": [0.0], "north": 3.0, "east": [0.0]}), "test.toml",
     "key 'wind.north'", "must be a non-empty array of numbers", "write north = [<number>, ...]"),
    ("qbar sigma in a logger bundle", _logger(sigma={"G": 0.03, "qbar": 1.0}), "test.toml", "key 'sigma.qbar'",
     "unknown key 'qbar'", "use one of: G, accel_x, accel_y, accel_z, v_north, v_east, v_up, altitude, F_D1"),
    ("fewer than 10 G samples", _few_g, "data.csv", "column 'G'", "9 accelerometer sample(s), fewer than 10",
     "at least 10 non-empty 'G' cells"),
    ("a velocity column missing", _no_v_up, "data.csv", "column 'v_up'", "missing column(s) 'v_up'",
     "or give v_north, v_east, v_up and altitude with their sigmas"),
    ("implausible velocity", _fast_v, "data.csv", "row {row}, column 'v_up'",
     "v_up = -5000 m/s is outside -1000 … 1000 m/s", "SI bundles in"),
    ("zero velocity sigma cell", _zero_velocity_sigma_cell, "data.csv", "row {row}, column 'v_up_sigma'",
     "a 1-sigma of 0 for a sample of 'v_up' (no sensor is exact)", "give the sensor's 1-sigma"),
    ("zero sigma in [sigma]", _logger(sigma={"G": 0.0, "v_north": 0.1, "v_east": 0.1, "v_up": 0.1, "F_D1": 10.0}),
     "test.toml", "key 'sigma.G'", "a 1-sigma of 0 for a sample of 'G'", "give the sensor's 1-sigma"),
    ("a sigma column beside its [sigma] entry", _sigma_twice, "test.toml", "key 'sigma.v_up'",
     "the 1-sigma of 'v_up' is given twice: here and as data.csv's column 'v_up_sigma'",
     "keep one: remove 'v_up' from [sigma]"),
    ("G beside body axes", _g_beside_axes, "data.csv", "columns 'G', 'accel_x', 'accel_y', 'accel_z'",
     "data.csv gives both G and accelerometer body axes", "keep G (the sensed load factor, g) or accel_x"),
    ("a density column beside [atmosphere]", _density_beside_atmosphere, "test.toml", "key 'atmosphere'",
     "a density profile is given here and as data.csv's column 'density'", "keep one: remove [atmosphere]"),
    ("nan written in a velocity cell", _nan_text, "data.csv", "row {row}, column 'v_north'",
     "the cell is 'nan', not a finite number", "is empty where the channel has no sample"),
]


@pytest.mark.parametrize("defect, file, place, problem, fix", [r[1:] for r in LOGGER_REFUSALS],
                         ids=[r[0] for r in LOGGER_REFUSALS])
def test_logger_refusals(tmp_path, defect, file, place, problem, fix):
    folder = tmp_path / "log"
    folder.mkdir()
    row = defect(folder)
    with pytest.raises(BundleError) as err:
        read_bundle(folder)
    message = str(err.value)
    assert message.startswith(f"{folder / file}, {place.format(row=row)}: "), message
    assert problem in err.value.problem, message
    assert fix in err.value.fix, message


def test_wind_in_a_bundle_with_qbar_is_refused(example_dir, bundle_files):
    folder = example_dir("drogue-clean")
    bundle_files(folder).set_key("wind", value={"altitude": [0.0], "north": [1.0], "east": [0.0]})
    with pytest.raises(BundleError) as err:
        read_bundle(folder)
    assert str(err.value).startswith(f"{folder / 'test.toml'}, key 'wind': "), str(err.value)
    assert "a bundle with measured qbar already has its airspeed" in err.value.problem
    assert "remove the [wind] table" in err.value.fix


@pytest.mark.parametrize("table", ["atmosphere", "rate"])
def test_other_air_tables_in_a_bundle_with_qbar_are_refused(example_dir, bundle_files, table):
    folder = example_dir("drogue-clean")
    bundle_files(folder).set_key(table, value={"G": 100.0} if table == "rate" else DOC["atmosphere"])
    with pytest.raises(BundleError, match=rf"key '{table}': \[{table}\] is for a logger bundle"):
        read_bundle(folder)


@pytest.mark.parametrize("dropped, kept", [("airspeed", "qbar"), ("qbar", "airspeed")])
def test_qbar_without_airspeed_and_the_reverse(example_dir, bundle_files, dropped, kept):
    folder = example_dir("drogue-clean")
    bundle_files(folder).drop_column(dropped)
    with pytest.raises(BundleError) as err:
        read_bundle(folder)
    assert str(err.value).startswith(f"{folder / 'data.csv'}, column '{dropped}': "), str(err.value)
    assert f"data.csv gives '{kept}' but not '{dropped}'" in err.value.problem
    assert err.value.fix.startswith("either give qbar, its sigma, airspeed and gamma")
    assert "or give v_north, v_east, v_up and altitude with their sigmas" in err.value.fix


def test_no_air_data_at_all(example_dir, bundle_files):
    folder = example_dir("drogue-clean")
    files = bundle_files(folder)
    for c in ("qbar", "qbar_sigma", "airspeed"):
        files.drop_column(c)
    files.set_key("sigma", value={"G": 0.03})   # accepted while data.csv could still be either kind
    with pytest.raises(BundleError) as err:
        read_bundle(folder)
    assert str(err.value).startswith(f"{folder / 'data.csv'}, columns 'qbar', 'airspeed': "), str(err.value)
    assert "neither qbar and airspeed (measured air data) nor v_north, v_east and v_up" in err.value.problem
    assert "either give qbar" in err.value.fix


def test_velocity_columns_beside_qbar_are_ignored_as_before(example_dir, bundle_files):
    """A bundle with qbar reads as it always did: extra columns, v_* included, are not channels."""
    folder = example_dir("drogue-clean")
    before = read_bundle(folder)
    files = bundle_files(folder)
    rows = files.read_rows()
    files.write_rows([rows[0] + ["v_north"]] + [r + [""] for r in rows[1:]])
    test = read_bundle(folder)
    assert test.measured_qbar and test.air_data is None
    pd.testing.assert_frame_equal(test.data, before.data)


def test_three_accelerometer_axes_without_attitude_give_their_magnitude(tmp_path):
    """accel_x, accel_y, accel_z (g) in place of G: G is their magnitude, its sigma propagated."""
    from cpas_bayes.data.bundle import read_bundle
    from cpas_bayes.data.bundle_write import write_bundle
    from cpas_bayes.data.synth_logger import synthesize_logger

    test, _ = synthesize_logger("logger-drop", 2)
    folder = write_bundle(test, tmp_path / "g")
    csv = (folder / "data.csv").read_text(encoding="utf-8").splitlines()
    header = csv[0].split(",")
    gi, si = header.index("G"), header.index("G_sigma")
    rows = [["accel_x", "accel_y", "accel_z", "accel_x_sigma", "accel_y_sigma", "accel_z_sigma"]
            + [h for k, h in enumerate(header) if k not in (gi, si)]]
    for line in csv[1:]:
        cells = line.split(",")
        g, sg = cells[gi], cells[si]
        if g:
            # the same magnitude split over three axes: 0.6, 0.8 and 0 of it
            axes = [f"{0.6 * float(g)!r}", f"{0.8 * float(g)!r}", "0.0", sg, sg, sg]
        else:
            axes = ["", "", "", "", "", ""]
        rows.append(axes + [c for k, c in enumerate(cells) if k not in (gi, si)])
    (folder / "data.csv").write_text("\n".join(",".join(r) for r in rows) + "\n", encoding="utf-8")
    back = read_bundle(folder)
    # less the noise across the force (two axes' worth of σ² for equal sigmas): unbiased to first order
    g, sg = test.data["G"].to_numpy(), test.data["G_sigma"].to_numpy()
    np.testing.assert_allclose(back.data["G"].to_numpy(), np.sqrt(np.maximum(g**2 - 2 * sg**2, 0.0)), rtol=1e-9,
                               equal_nan=True)
    np.testing.assert_allclose(back.data["G_sigma"].to_numpy(), sg, rtol=1e-9, equal_nan=True)
    # one axis missing in a reading is refused
    rows[5][1] = ""
    (folder / "data.csv").write_text("\n".join(",".join(r) for r in rows) + "\n", encoding="utf-8")
    with pytest.raises(BundleError, match="an axis is empty"):
        read_bundle(folder)


def test_a_wind_profile_without_sigma_is_uncertain_by_two_metres_a_second(tmp_path):
    """A sounding's wind is off by 1-3 m/s by the drop's time and place; a default of 0 claimed it exact, and a
    wrong wind then bent the reconstructed trajectory (airspeed falling to 0.01 m/s in a steady descent)."""
    folder = tmp_path / "log"
    folder.mkdir()
    write_logger(folder, edited(wind={"altitude": [0.0, 1000.0], "north": [1.0, 2.0], "east": [-4.0, -5.0]}))
    assert read_bundle(folder).air_data.wind.sigma == 2.0          # m/s (SI inside the package)
    write_logger(folder, edited(wind={"altitude": [0.0], "north": [1.0], "east": [-4.0], "sigma": 0.5}))
    assert read_bundle(folder).air_data.wind.sigma == pytest.approx(0.5)      # the base bundle is SI


def test_the_reconstruction_with_an_unstated_wind_sigma_follows_the_stated_one():
    from cpas_bayes.data import air_reconstruction as air
    from cpas_bayes.data.synth_logger import synthesize_logger

    test, _ = synthesize_logger("logger-drop", 1)
    unstated = dataclasses.replace(test, air_data=dataclasses.replace(
        test.air_data, wind=dataclasses.replace(test.air_data.wind, sigma=2.0)))
    estimate = air.best_estimate_trajectory(unstated)
    assert estimate.misfit_warning() is None
    assert estimate.frame["airspeed"].min() > 5.0                  # a steady descent, not a stall to 0.01 m/s


def test_the_magnitude_of_three_noisy_axes_is_unbiased_where_the_naive_one_reads_high():
    """200,000 readings of 0.3 g split over three axes, 0.05 g of noise on each: the naive magnitude reads
    high by about σ²/|a| (8e-3); the reader's, less the noise across the force, within 1e-3 of the truth."""
    from cpas_bayes.data.bundle_air import accelerometer_magnitude

    rng = np.random.default_rng(7)
    n, true_g, sigma = 200_000, 0.3, 0.05
    direction = np.array([0.48, -0.6, 0.64])
    axes = true_g * direction / np.linalg.norm(direction) + rng.normal(0.0, sigma, (n, 3))
    out = accelerometer_magnitude(axes, np.full((n, 3), sigma), np.ones(n, bool))
    assert np.linalg.norm(axes, axis=1).mean() - true_g > 5e-3
    assert abs(out["G"].mean() - true_g) < 1e-3
    np.testing.assert_allclose(out["G_sigma"], sigma, rtol=1e-9)

"""``cpas-bayes import``: logger CSV files with known truth become a bundle that read_bundle accepts.

The loggers are simulated (tests/drop_loggers.py): a vehicle hangs under its
carrier, is released, falls, and is snatched by its parachute. The
accelerometer logger and the GNSS logger each have their own clock, rate and
noise. The tests check the detected release and line stretch, and the
recovered clock offset, against the truth within a small multiple of the
stated 1-sigma (and that the sigma is not vacuously large), the written
bundle's channels and units, and the refusals of bad maps and files.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from datetime import datetime, timedelta, timezone

import numpy as np
import pandas as pd
import pytest
import tomli_w

import cpas_bayes as cb
from cpas_bayes.app.cli import main
from cpas_bayes.core.units import STANDARD_GRAVITY as G0
from cpas_bayes.data import logger_events as le
from cpas_bayes.data.bundle import read_bundle
from cpas_bayes.data.import_map import read_import_map
from cpas_bayes.data.importer import REPORT_NAME, import_loggers

from drop_loggers import DropTruth, accel_logger, air_density, gnss_fixes_logger, gnss_logger, simulate

TRUTH = DropTruth(duration=60.0)
OFFSET_1H15M02S = 3600 + 15 * 60 + 2  # s
K = 3.0  # errors must lie within K stated sigmas


@pytest.fixture(scope="module")
def sim():
    return simulate(TRUTH)


def _csv(path, header, columns, formats):
    lines = [",".join(header)]
    lines += [",".join(f % v if isinstance(f, str) else f(v) for f, v in zip(formats, row)) for row in zip(*columns)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_loggers(folder, sim, seed=0, accel_rate=200.0, gnss_rate=10.0, accel_clock=37.25,
                  gnss_clock=37.25 + OFFSET_1H15M02S + 0.137):
    """imu.csv (time in ms, three axes in m/s²) and gnss.csv (s; velocity NED, m/s; altitude, m).

    Returns the truth on the imu clock: release, line stretch after release, and
    the offset to add to the GNSS clock (t_imu = t_gnss + offset).
    """
    rng = np.random.default_rng(seed)
    ta, fa = accel_logger(sim, accel_rate, accel_clock, 0.05, rng)
    tg, vg, hg = gnss_logger(sim, gnss_rate, gnss_clock, 0.05, 0.3, rng)
    _csv(folder / "imu.csv", ["t_ms", "ax", "ay", "az"], [ta * 1000, *fa.T], ["%.3f", "%.5f", "%.5f", "%.5f"])
    _csv(folder / "gnss.csv", ["time", "vn", "ve", "vd", "alt"], [tg, *vg.T, hg], ["%.4f"] + ["%.4f"] * 4)
    return {"release": TRUTH.release + accel_clock, "line_stretch": TRUTH.line_stretch - TRUTH.release,
            "offset": accel_clock - gnss_clock}


def map_document(air_data="ground_speed", **loggers):
    """A column map for imu.csv + gnss.csv (the logger tables may be replaced or extended). Its q̄ is from
    the ground speed unless ``air_data`` says otherwise (None: the map's default, a logger bundle)."""
    doc = {
        "logger": {
            "imu": {"file": "imu.csv", "time": {"column": "t_ms", "unit": "ms"},
                    "channels": {"accel": {"columns": ["ax", "ay", "az"], "unit": "m/s^2"}}},
            "gnss": {"file": "gnss.csv", "time": {"column": "time", "unit": "s"}, "offset": "auto",
                     "offset_hint": -4500.0,
                     "channels": {"velocity": {"columns": ["vn", "ve", "vd"], "unit": "m/s"},
                                  "altitude": {"column": "alt", "unit": "m"}}},
        },
        "record": {"start": -0.5, "end": 30.0},
        "test": {
            "name": "DT-sim", "units": "SI", "phase": "drogue",
            "vehicle": {"weight": TRUTH.mass * G0, "weight_sigma": 50.0, "cds": TRUTH.cds_vehicle,
                        "cds_sigma": 0.1},
            "parachute": [{"id": "D1", "kind": "drogue", "inflation": "infinite", "diameter": 7.0,
                           "weight": 300.0, "weight_sigma": 10.0,
                           "stage": [{"label": "full open", "start": "line_stretch", "delay": 0.0,
                                      "start_sigma": 0.05}]}],
            "sigma": {"G": 0.05, "qbar": 5.0},
        },
    }
    doc["logger"].update(loggers)
    if air_data is not None:
        doc["air_data"] = air_data
    return doc


def write_map(folder, doc):
    path = folder / "map.toml"
    path.write_text(tomli_w.dumps(doc), encoding="utf-8")
    return path


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_import_recovers_events_and_a_1h15m02s_offset(tmp_path, sim, capsys):
    """200 Hz accelerometer in ms, 10 Hz GNSS in s whose clock is 1 h 15 min 2.137 s ahead; hint -4500 s."""
    truth = write_loggers(tmp_path, sim)
    out = tmp_path / "bundle"
    code, printed, err = run(capsys, "import", write_map(tmp_path, map_document()), "--out", out)
    assert code == 0, err
    assert "release at" in printed and "line stretch" in printed and "offset" in printed

    report = json.loads((out / REPORT_NAME).read_text())
    release, line = report["release"], report["line_stretch"]
    gnss = report["loggers"]["gnss"]
    errors = {"release": (release["time_on_reference_clock_s"] - truth["release"], release["sigma_s"]),
              "line stretch": (line["time_after_release_s"] - truth["line_stretch"], line["sigma_s"]),
              "offset": (gnss["offset_s"] - truth["offset"], gnss["offset_sigma_s"])}
    for what, (error, sigma) in errors.items():
        assert abs(error) <= K * sigma, f"{what}: error {error * 1e3:.2f} ms, sigma {sigma * 1e3:.2f} ms"
    # the sigmas say something: a few sample intervals at most
    assert release["sigma_s"] < 0.02 and line["sigma_s"] < 0.02 and gnss["offset_sigma_s"] < 0.01
    assert gnss["offset_method"] == "auto" and gnss["correlation"] > 0.8

    test = read_bundle(out)  # the package's own reader accepts it
    assert test.name == "DT-sim" and test.units.name == "SI"
    assert set(test.channels) == {"time", "G", "qbar", "airspeed", "gamma", "density", "altitude"}
    t = test.time
    assert t[0] == pytest.approx(-0.5, abs=0.006) and t[-1] == pytest.approx(30.0, abs=0.006)
    assert test.sample_rate == pytest.approx(200.0, rel=1e-3)
    stage = test.parachutes[0].stages[0]
    assert stage.start == pytest.approx(line["time_after_release_s"])
    assert stage.start_sigma == pytest.approx(np.hypot(line["sigma_s"], 0.05))
    # channels against the truth, on the bundle's time (release = 0)
    true_t, v, h, f = sim
    at = t + TRUTH.release
    hanging = t < -0.1
    assert np.allclose(test.data["G"][hanging], 1.0, atol=0.2)
    speed = np.interp(at, true_t, np.linalg.norm(v, axis=1))
    assert np.abs(test.data["airspeed"] - speed).max() < 0.5
    qbar = 0.5 * air_density(np.interp(at, true_t, h)) * speed ** 2
    assert np.allclose(test.data["qbar"], qbar, rtol=0.03)
    assert test.data["gamma"][hanging].abs().max() < 1.0                  # level flight under the carrier
    assert test.data["gamma"].iloc[-1] == pytest.approx(-90.0, abs=5.0)   # straight down under the canopy
    assert np.allclose(test.data["G_sigma"], 0.05) and np.allclose(test.data["qbar_sigma"], 5.0)


def test_offset_without_a_hint_is_found_by_the_full_search(tmp_path, sim):
    """Elapsed clocks and no hint: every lag with enough overlap is searched (the library call, cb.import_bundle)."""
    truth = write_loggers(tmp_path, sim, seed=1)
    doc = map_document()
    del doc["logger"]["gnss"]["offset_hint"]
    result = cb.import_bundle(write_map(tmp_path, doc), tmp_path / "b")
    assert read_bundle(result.test.source).name == "DT-sim"
    off = result.offsets["gnss"]
    assert abs(off.offset - truth["offset"]) <= K * off.sigma
    assert off.alignment.search == (-np.inf, np.inf)
    assert off.alignment.runner_up < 0.6 * off.alignment.correlation   # the match is distinct


@pytest.mark.parametrize("accel_rate", [20.0, 50.0])
def test_low_rate_accelerometer(tmp_path, sim, accel_rate):
    """At 20 and 50 Hz the stated sigmas grow with the sample interval and still hold the truth."""
    truth = write_loggers(tmp_path, sim, seed=2, accel_rate=accel_rate)
    result = import_loggers(read_import_map(write_map(tmp_path, map_document()), tmp_path / "b"), tmp_path / "b")
    dt = 1.0 / accel_rate
    for event, true in ((result.release, truth["release"]), (result.line_stretch, truth["line_stretch"])):
        assert abs(event.time - true) <= K * event.sigma
        assert dt / np.sqrt(12) <= event.sigma < 2 * dt
    off = result.offsets["gnss"]
    assert abs(off.offset - truth["offset"]) <= K * off.sigma


def test_wall_clocks_align_files_started_1h15m02s_apart(tmp_path, sim):
    """ISO timestamps: the GNSS file starts 1 h 15 min 2 s before the accelerometer's, its clock 0.73 s fast."""
    rng = np.random.default_rng(3)
    start = datetime(2024, 5, 14, 11, 15, 2, tzinfo=timezone.utc)   # true time 0: the accelerometer's first sample
    clock_error = 0.73
    ta, fa = accel_logger(sim, 100.0, 0.0, 0.05, rng, start=0.0)
    tg, vg, hg = gnss_logger(sim, 10.0, clock_error, 0.05, 0.3, rng, start=-OFFSET_1H15M02S)

    def iso(seconds):
        return (start + timedelta(seconds=float(seconds))).isoformat(timespec="milliseconds").replace("+00:00", "Z")

    _csv(tmp_path / "imu.csv", ["utc", "ax", "ay", "az"], [ta, *fa.T], [iso, "%.5f", "%.5f", "%.5f"])
    _csv(tmp_path / "gnss.csv", ["utc", "vn", "ve", "vd", "alt"], [tg, *vg.T, hg], [iso] + ["%.4f"] * 4)
    doc = map_document()
    doc["logger"]["imu"]["time"] = {"column": "utc", "unit": "iso"}
    doc["logger"]["gnss"]["time"] = {"column": "utc", "unit": "iso"}
    del doc["logger"]["gnss"]["offset_hint"]  # wall clocks: the search is centred on 0
    out = tmp_path / "bundle"
    result = import_loggers(read_import_map(write_map(tmp_path, doc), out), out)
    gnss = result.records["gnss"]
    assert gnss.time[0] == pytest.approx(start.timestamp() - OFFSET_1H15M02S + clock_error, abs=0.2)
    off = result.offsets["gnss"]
    assert abs(off.offset - (-clock_error)) <= K * off.sigma and off.alignment.search == (-60.0, 60.0)
    assert abs(result.release.time - (start.timestamp() + TRUTH.release)) <= K * result.release.sigma
    utc = datetime.fromisoformat(result.report()["release"]["utc"])
    assert abs((utc - start).total_seconds() - TRUTH.release) <= K * result.release.sigma


def test_second_accelerometer_single_axis_in_g(tmp_path, sim):
    """A 100 Hz logger with one axis (z down, in g, sign -1) and its own clock is aligned by correlation."""
    truth = write_loggers(tmp_path, sim, seed=4)
    rng = np.random.default_rng(5)
    true_t, _, _, f = sim
    t2 = 1.0 + np.arange(0.0, 55.0, 0.01) + rng.uniform(0, 0.01)
    z_down = np.interp(t2, true_t, f[:, 2]) / G0 + rng.normal(0, 0.03, t2.size)
    clock2 = 812.5
    _csv(tmp_path / "box.csv", ["sec", "z"], [t2 + clock2, z_down], ["%.4f", "%.5f"])
    box = {"file": "box.csv", "time": {"column": "sec", "unit": "s"}, "offset": "auto", "offset_hint": -800.0,
           "channels": {"accel": {"column": "z", "unit": "g", "sign": -1}}}
    result = import_loggers(read_import_map(write_map(tmp_path, map_document(box=box)), tmp_path / "b"),
                            tmp_path / "b")
    off = result.offsets["box"]
    true_offset = (truth["release"] - TRUTH.release) - clock2
    assert abs(off.offset - true_offset) <= K * off.sigma < 0.01
    assert result.import_map.g_logger == "imu"  # G still from the reference's three axes


def test_events_on_a_clean_step():
    """detect_release on a noise-free step between two samples: the interval's midpoint, sigma Δt/√12-ish."""
    t = np.arange(0.0, 5.0, 0.01)
    g = np.where(t < 2.0034, 1.0, 0.05)
    event = le.detect_release(t, g)
    assert event.time == pytest.approx(2.005, abs=1e-9)  # half-level crossing between 2.00 and 2.01
    assert abs(event.time - 2.0034) <= event.sigma <= 0.01
    with pytest.raises(le.EventNotFound, match="no line stretch"):
        le.detect_line_stretch(t, g, event.time)


# ---------------------------------------------------------------------------
# refusals: exit status 2, a message naming the file, the place and the fix, nothing written


def _refused(capsys, tmp_path, doc, out=None):
    out = out or tmp_path / "bundle"
    code, _, err = run(capsys, "import", write_map(tmp_path, doc), "--out", out)
    assert code == 2, err
    assert "Fix:" in err and "Traceback" not in err
    return err


def test_missing_column_names_file_column_and_fix(tmp_path, sim, capsys):
    write_loggers(tmp_path, sim)
    doc = map_document()
    doc["logger"]["imu"]["channels"]["accel"]["columns"] = ["ax", "ay", "a_z"]
    err = _refused(capsys, tmp_path, doc)
    assert "imu.csv" in err and "column 'a_z'" in err and "did you mean 'az'" in err
    assert "logger.imu.channels.accel" in err and "correct the column name in the map" in err
    assert not (tmp_path / "bundle").exists()


def test_unknown_unit_is_refused_before_any_file_is_read(tmp_path, capsys):
    (tmp_path / "imu.csv").write_text("not read\n")
    (tmp_path / "gnss.csv").write_text("not read\n")
    doc = map_document()
    doc["logger"]["imu"]["channels"]["accel"]["unit"] = "m/s2"
    err = _refused(capsys, tmp_path, doc)
    assert "map.toml" in err and "logger.imu.channels.accel.unit" in err and "unknown unit 'm/s2'" in err
    assert "'m/s^2', 'ft/s^2' or 'g'" in err
    doc["logger"]["imu"]["channels"]["accel"]["unit"] = "m/s"   # a unit, of the wrong quantity
    assert "is not a unit of acceleration" in _refused(capsys, tmp_path, doc)
    assert not (tmp_path / "bundle").exists()


def test_output_folder_not_ours_is_refused_untouched(tmp_path, sim, capsys):
    write_loggers(tmp_path, sim)
    out = tmp_path / "bundle"
    out.mkdir()
    (out / "notes.txt").write_text("the user's\n")
    map_path = write_map(tmp_path, map_document())
    before = sorted(p.name for p in tmp_path.iterdir())
    code, _, err = run(capsys, "import", map_path, "--out", out)
    assert code == 2 and "Fix:" in err
    assert "notes.txt" in err and "--out" in err
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no temporary folder left beside it


@pytest.mark.parametrize("edit, expected", [
    (lambda d: d["logger"]["gnss"].update(file="/etc/gnss.csv"), "absolute"),
    (lambda d: d["logger"]["gnss"].update(file="../gnss.csv"), "outside the map folder"),
    (lambda d: d["logger"]["gnss"]["time"].update(unit="milis"), "unknown unit 'milis'"),
    (lambda d: d["logger"]["gnss"].update(offset="atuo"), "unknown offset 'atuo'"),
    (lambda d: d["logger"]["gnss"]["channels"].pop("velocity"), "the bundle needs 'airspeed'"),
    (lambda d: d["test"]["parachute"][0]["stage"][0].update(start="line_strech"), "did you mean 'line_stretch'"),
    (lambda d: d["test"]["vehicle"].update(weight_sigm=1.0), "key 'test.vehicle.weight_sigm'"),
    (lambda d: d["test"]["sigma"].pop("G"), "test.sigma.G"),
    (lambda d: d.update(reference="gps"), "no logger named 'gps'"),
    # a skip_rows past the end: pandas made a set of 10**9 row numbers (22 GB) before the file ran out
    (lambda d: d["logger"]["imu"].update(skip_rows=10**9),
     "key 'logger.imu.skip_rows': skip_rows 1000000000 is beyond the file's"),
    (lambda d: (d["logger"]["gnss"].pop("offset_hint"), d["logger"]["gnss"].update(offset=1e300)),
     "key 'logger.gnss.offset': 1e+300 s is more than the 1e+10 s"),
    (lambda d: d["logger"]["gnss"].update(offset_hint=-2e10), "key 'logger.gnss.offset_hint': -2e+10 s"),
])
def test_bad_maps_are_refused_naming_the_key(tmp_path, sim, capsys, monkeypatch, edit, expected):
    write_loggers(tmp_path, sim)
    doc = map_document()
    edit(doc)
    monkeypatch.setattr(pd, "read_csv", None)  # a map is refused before any logger file is parsed
    err = _refused(capsys, tmp_path, doc)
    assert expected in err and "map.toml" in err
    assert not (tmp_path / "bundle").exists()


def test_bad_logger_files_are_refused_naming_the_row(tmp_path, sim, capsys):
    write_loggers(tmp_path, sim)
    lines = (tmp_path / "gnss.csv").read_text().splitlines()
    lines[5], lines[6] = lines[6], lines[5]           # two rows swapped: time goes back at file row 7
    (tmp_path / "gnss.csv").write_text("\n".join(lines) + "\n")
    err = _refused(capsys, tmp_path, map_document())
    assert "gnss.csv, row 7, column 'time'" in err and "not strictly increasing" in err

    write_loggers(tmp_path, sim)
    lines = (tmp_path / "imu.csv").read_text().splitlines()
    lines[3] = lines[3].replace(",", ",n/a", 1)
    (tmp_path / "imu.csv").write_text("\n".join(lines) + "\n")
    err = _refused(capsys, tmp_path, map_document())
    assert "imu.csv, row 4, column 't_ms'" in err or "imu.csv, row 4, column 'ax'" in err


@pytest.mark.parametrize("header, expected", [
    ("t_ms,ax,ay,ax", "the column name 'ax' is in columns 2 and 4"),
    ("t_ms,ax,ax.1,ax", "the column name 'ax' is in columns 2 and 4"),       # pandas would call the last 'ax.2'
    ("t_ms, ax,ay,az,ax ", "the column name 'ax' is in columns 2 and 5"),    # names are compared stripped
])
def test_a_repeated_column_name_is_refused(tmp_path, sim, capsys, header, expected):
    """pandas renames a second 'ax' to 'ax.1' and the map's 'ax' would silently read the first."""
    write_loggers(tmp_path, sim)
    lines = (tmp_path / "imu.csv").read_text().splitlines()
    lines = [header] + [row + ",0.0" * (header.count(",") - 3) for row in lines[1:]]
    (tmp_path / "imu.csv").write_text("\n".join(lines) + "\n")
    err = _refused(capsys, tmp_path, map_document())
    assert "imu.csv, row 1 (header): " + expected in err and "give each column its own header name" in err
    assert not (tmp_path / "bundle").exists()


def test_a_column_named_like_a_pandas_duplicate_is_its_own_column(tmp_path, sim):
    """'ax' and 'ax.1' are two names, not a duplicate: each reads its own column, with the map's skip_rows."""
    write_loggers(tmp_path, sim)
    lines = (tmp_path / "imu.csv").read_text().splitlines()
    lines[0] = "t_ms,ax.1,ax,az"
    (tmp_path / "imu.csv").write_text("logger 7\r\nfirmware 1.2\r\n\r\n" + "\n".join(lines) + "\n")
    doc = map_document()
    doc["logger"]["imu"]["skip_rows"] = 3
    doc["logger"]["imu"]["channels"]["accel"]["columns"] = ["ax", "ax.1", "az"]   # y first, then x: any order
    out = tmp_path / "b"
    record = import_loggers(read_import_map(write_map(tmp_path, doc), out), out).records["imu"]
    cells = np.loadtxt(tmp_path / "imu.csv", delimiter=",", skiprows=4)
    assert np.array_equal(record.channels["accel"], cells[:, [2, 1, 3]])
    assert np.allclose(record.time, cells[:, 0] / 1000, rtol=1e-12, atol=0)


def test_skip_rows_is_bounded_by_the_line_count(tmp_path, sim, capsys, monkeypatch):
    """A skip_rows leaving no header is refused with the file's line count, before pandas parses anything."""
    write_loggers(tmp_path, sim)
    lines = len((tmp_path / "imu.csv").read_text().splitlines())
    monkeypatch.setattr(pd, "read_csv", None)
    for skip in (lines, lines + 1):
        doc = map_document()
        doc["logger"]["imu"]["skip_rows"] = skip
        err = _refused(capsys, tmp_path, doc)
        assert f"map.toml, key 'logger.imu.skip_rows': skip_rows {skip} is beyond the file's {lines:,} lines" in err
        assert f"at most {lines - 1:,}" in err
    (tmp_path / "gnss.csv").write_text("time,vn\n1,2")   # a last line without a line end is a line
    doc = map_document()
    doc["logger"]["gnss"]["skip_rows"] = 2
    assert "skip_rows 2 is beyond the file's 2 lines" in _refused(capsys, tmp_path, doc)


AS_LIMITED = """
import resource, sys
from cpas_bayes.app.cli import main

size = next(int(line.split()[1]) * 1024 for line in open("/proc/self/status") if line.startswith("VmSize:"))
hard = resource.getrlimit(resource.RLIMIT_AS)[1]
limit = size + int(sys.argv[3])
resource.setrlimit(resource.RLIMIT_AS, (limit if hard == resource.RLIM_INFINITY else min(limit, hard), hard))
sys.exit(main(["import", sys.argv[1], "--out", sys.argv[2]]))
"""


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads the address space size from /proc")
def test_a_large_skip_rows_within_the_file_costs_no_memory_per_row(tmp_path, sim):
    """20 million blank lines before the header: skipping them takes no memory per line.

    pandas turns skiprows=N into a set of N row numbers (here ~1.7 GB); the import runs with its address
    space limited to 600 MB above what its imports took (it needs ~250 MB).
    """
    write_loggers(tmp_path, sim)
    skip = 20_000_000
    text = (tmp_path / "imu.csv").read_bytes()
    (tmp_path / "imu.csv").write_bytes(b"\n" * skip + text)
    doc = map_document()
    doc["logger"]["imu"]["skip_rows"] = skip
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", AS_LIMITED, str(write_map(tmp_path, doc)), str(tmp_path / "b"),
                           str(600 * 2**20)], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert read_bundle(tmp_path / "b").name == "DT-sim"


def test_no_release_in_the_record_is_said_with_the_fix(tmp_path, capsys):
    t = np.arange(0.0, 30.0, 0.01)
    rng = np.random.default_rng(6)
    _csv(tmp_path / "imu.csv", ["t_ms", "ax", "ay", "az"],
         [t * 1000, *rng.normal(0, 0.3, (2, t.size)), -G0 + rng.normal(0, 0.3, t.size)],
         ["%.1f", "%.4f", "%.4f", "%.4f"])
    _csv(tmp_path / "gnss.csv", ["time", "vn", "ve", "vd", "alt"], [t[::10], *np.ones((3, t.size // 10)),
         np.full(t.size // 10, 100.0)], ["%.2f"] * 5)
    doc = map_document()
    doc["logger"]["gnss"]["offset"] = 0.0
    del doc["logger"]["gnss"]["offset_hint"]
    err = _refused(capsys, tmp_path, doc)
    assert "imu.csv" in err and "no release" in err and "[events] release" in err


def test_a_logger_file_linked_from_outside_the_map_folder_is_refused(tmp_path, sim, capsys):
    """The path is checked where it leads, not only as text: a symbolic link out of the folder is refused."""
    write_loggers(tmp_path, sim)
    drop = tmp_path / "drop"
    drop.mkdir()
    (tmp_path / "imu.csv").rename(drop / "imu.csv")
    (drop / "gnss.csv").symlink_to(tmp_path / "gnss.csv")
    doc = map_document()
    code, _, err = run(capsys, "import", write_map(drop, doc), "--out", drop / "bundle")
    assert code == 2 and "Fix:" in err
    assert "map.toml, key 'logger.gnss.file': 'gnss.csv' is a link leading outside the map folder" in err
    assert not (drop / "bundle").exists()
    (drop / "gnss.csv").unlink()          # a link that stays inside the folder is a file of the folder
    (tmp_path / "gnss.csv").rename(drop / "gnss-2024.csv")
    (drop / "gnss.csv").symlink_to("gnss-2024.csv")
    assert read_import_map(drop / "map.toml", drop / "bundle").logger("gnss").path == drop / "gnss.csv"


def test_a_clock_offset_leaving_no_common_record_prints_readable_numbers(tmp_path, sim, capsys):
    """An offset within the bound (a wall clock against an elapsed one) but wrong: the span is said in %g."""
    write_loggers(tmp_path, sim)
    doc = map_document()
    del doc["logger"]["gnss"]["offset_hint"]
    doc["logger"]["gnss"]["offset"] = 5e9
    err = _refused(capsys, tmp_path, doc)
    assert "map.toml, key 'record'" in err and "(5e+09 … " in err
    assert not re.search(r"\d{12}", err)


def test_template_and_events_given_in_the_map(tmp_path, sim, capsys):
    """Metadata from a template test.toml; release and line stretch given (not detected) are used as given."""
    truth = write_loggers(tmp_path, sim, seed=7)
    doc = map_document()
    template = dict(doc.pop("test"))
    template["parachute"] = [dict(template["parachute"][0], stage=[{"label": "full open", "start": 1.7,
                                                                   "start_sigma": 0.1}])]
    (tmp_path / "template.toml").write_text(tomli_w.dumps(template), encoding="utf-8")
    doc["template"] = "template.toml"
    doc["events"] = {"release": truth["release"] + 0.004, "release_sigma": 0.01, "line_stretch": 1.65,
                     "line_stretch_sigma": 0.02}
    out = tmp_path / "bundle"
    code, printed, err = run(capsys, "import", write_map(tmp_path, doc), "--out", out)
    assert code == 0, err
    assert "release at" in printed and "(given)" in printed
    report = json.loads((out / REPORT_NAME).read_text())
    assert report["release"]["time_on_reference_clock_s"] == truth["release"] + 0.004
    assert report["release"]["given_in_map"] and report["line_stretch"]["time_after_release_s"] == 1.65
    stage = read_bundle(out).parachutes[0].stages[0]
    assert (stage.start, stage.start_sigma) == (1.7, 0.1)


def test_a_bundle_read_bundle_would_refuse_is_not_written(tmp_path, sim, capsys):
    """A stage starting after the record ends: the written bundle is read back, refused, and not put in place."""
    write_loggers(tmp_path, sim)
    doc = map_document()
    doc["test"]["parachute"][0]["stage"][0]["delay"] = 100.0
    code, printed, err = run(capsys, "import", write_map(tmp_path, doc), "--out", tmp_path / "bundle")
    assert code == 2 and "Fix:" in err and "Traceback" not in err
    assert "map.toml" in err and "would be refused" in err and "stage[0].start" in err
    assert "after the record ends" in err
    assert printed == ""     # no detections reported for a bundle that was not written
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gnss.csv", "imu.csv", "map.toml"]


def test_a_given_clock_offset_the_signals_contradict_is_questioned(tmp_path, sim, capsys):
    """A map's offset 5 s off (a typed digit): the import goes on with it, but says where the signals both
    loggers see match, and import.json keeps it; the right offset, or one 0.4 s off (a receiver's latency), is
    not questioned."""
    truth = write_loggers(tmp_path, sim)
    for shift, questioned in ((-5.0, True), (0.0, False), (0.4, False)):
        doc = map_document()
        doc["logger"]["gnss"]["offset"] = truth["offset"] + shift
        doc["logger"]["gnss"].pop("offset_hint")
        out = tmp_path / f"bundle{shift}"
        code, printed, err = run(capsys, "import", write_map(tmp_path, doc), "--out", out)
        assert code == 0, err
        assert ("warning: logger 'gnss': the signals both loggers see match at offset" in printed) == questioned
        logger = json.loads((out / REPORT_NAME).read_text())["loggers"]["gnss"]
        assert ("signals_prefer_offset_s" in logger) == questioned, logger
        if questioned:
            assert abs(logger["signals_prefer_offset_s"] - truth["offset"]) < 0.05
            said = re.search(r"\(correlation 0\.9\d\), ([+-]\d+\.\d+) s from the map's offset; check "
                             r"logger\.gnss\.offset, or write offset = \"auto\"", printed)
            assert said and abs(float(said.group(1)) + shift) < 0.05, printed


def test_a_read_back_refusal_names_the_logger_rows_behind_the_bundle_row(tmp_path, sim, capsys):
    """A receiver that logged three samples of zero velocity: the ground-speed q̄ is 0 between them, which the
    bundle refuses at a data.csv row the user never sees; the refusal also says the time after release and each
    logger's nearest sample as its file's row (the first zero sample, index k, is gnss.csv's row k + 2)."""
    truth = write_loggers(tmp_path, sim)
    rows = pd.read_csv(tmp_path / "gnss.csv")
    k = int(np.searchsorted(rows["time"], truth["release"] - truth["offset"] + 5.0))   # 5 s after release
    rows.loc[k:k + 2, ["vn", "ve", "vd"]] = 0.0
    rows.to_csv(tmp_path / "gnss.csv", index=False, float_format="%.4f")
    doc = map_document()
    doc["logger"]["gnss"]["offset"] = truth["offset"]
    doc["logger"]["gnss"].pop("offset_hint")
    err = _refused(capsys, tmp_path, doc)
    assert "would be refused: data.csv, row " in err and "column 'qbar'" in err, err
    assert "s after release; nearest samples: imu.csv row " in err and f", gnss.csv row {k + 2})" in err, err


# ---------------------------------------------------------------------------
# GNSS velocity without airspeed: a logger bundle, whose q̄ the package reconstructs

WINDY = DropTruth(duration=60.0, wind_east=8.0)
LATENCY = 0.4   # s: the receiver stamps each sample this late
LOGGER_SIGMA = {"G": 0.05, "v_north": 0.05, "v_east": 0.05, "v_up": 0.05, "altitude": 0.3}


@pytest.fixture(scope="module")
def windy():
    return simulate(WINDY)


def _windy_loggers(folder, sim):
    """imu.csv and gnss.csv of the windy drop, the receiver 0.4 s late; the map's clock offset given exact (an
    automatic one would take the latency into the offset)."""
    rng = np.random.default_rng(3)
    ta, fa = accel_logger(sim, 200.0, 37.25, 0.05, rng)
    tg, vg, hg = gnss_logger(sim, 10.0, 137.25, 0.05, 0.3, rng, latency=LATENCY)
    _csv(folder / "imu.csv", ["t_ms", "ax", "ay", "az"], [ta * 1000, *fa.T], ["%.3f", "%.5f", "%.5f", "%.5f"])
    _csv(folder / "gnss.csv", ["time", "vn", "ve", "vd", "alt"], [tg, *vg.T, hg], ["%.4f"] + ["%.4f"] * 4)
    gnss = {"file": "gnss.csv", "time": {"column": "time", "unit": "s"}, "offset": -100.0,
            "channels": {"velocity": {"columns": ["vn", "ve", "vd"], "unit": "m/s"},
                         "altitude": {"column": "alt", "unit": "m"}}}
    return gnss


def _true_qbar(sim, truth, t):
    """The drop's q̄ at bundle times ``t`` (s after release), from its air-relative velocity."""
    true_t, v, h, _ = sim
    air = np.linalg.norm(v - np.array([0.0, truth.wind_east, 0.0]), axis=1)
    at = t + truth.release
    return 0.5 * air_density(np.interp(at, true_t, h)) * np.interp(at, true_t, air) ** 2


def test_gnss_velocity_makes_a_logger_bundle_whose_qbar_beats_the_ground_speeds(tmp_path, windy, capsys):
    """8 m/s of crosswind and a receiver 0.4 s late, no [wind] table: the default import writes a logger
    bundle (the receiver's samples as they are, blank between), whose reconstruction finds the wind and the
    latency and gives q̄ within 2.5 % of the truth everywhere, its median error within 1 % (over 11 seeds of
    these loggers: 0.7-1.7 % at worst, median 0.0-0.5 %, wind within 0.01 m/s, latency within 5 ms); the
    same loggers read as ground speed (air_data = "ground_speed", the only way before) are 6-9 % off in
    steady flight and 10-23 % around the snatch."""
    from cpas_bayes.data.reduction import reduce_test

    gnss = _windy_loggers(tmp_path, windy)
    doc = map_document(air_data=None, gnss=gnss)
    doc["test"]["sigma"] = dict(LOGGER_SIGMA)
    out = tmp_path / "logger"
    code, printed, err = run(capsys, "import", write_map(tmp_path, doc), "--out", out)
    assert code == 0, err
    assert "qbar <- reconstructed by reduce and fit" in printed
    assert json.loads((out / REPORT_NAME).read_text())["air_data"] == "reconstruct"
    test = read_bundle(out)
    assert not test.measured_qbar
    assert set(test.channels) == {"time", "G", "v_north", "v_east", "v_up", "altitude"}
    g, v = np.isfinite(test.data["G"].to_numpy()), np.isfinite(test.data["v_north"].to_numpy())
    assert g.sum() == pytest.approx(200 * 30.5, abs=3) and v.sum() == pytest.approx(10 * 30.5, abs=2)
    assert np.all(g | v)                  # every row is a reading or a receiver sample

    red = reduce_test(test)
    phi = dict(zip(("airspeed", "gamma", "heading", "altitude", "wind_north", "wind_east", "scale", "bias",
                    "latency"), red.air_estimate.phi))
    assert phi["wind_east"] == pytest.approx(WINDY.wind_east, abs=0.2)
    assert phi["latency"] == pytest.approx(LATENCY, abs=0.02)
    # the receiver's first 0.4 s of samples show the vehicle still held: extrapolated back along the free
    # fall instead, they read the release airspeed 0.15 m/s low and the accelerometer's scale 0.91 (11 seeds
    # now: 0.01-0.03 m/s, scale 0.970-0.987; the rest is the magnitude's noise bias in the free fall)
    assert phi["airspeed"] == pytest.approx(math.hypot(WINDY.speed, WINDY.wind_east), abs=0.1)
    assert phi["scale"] == pytest.approx(1.0, abs=0.05) and abs(phi["bias"]) < 0.05
    t, q = red.test.data["time"].to_numpy(), red.test.data["qbar"].to_numpy()
    error = q / _true_qbar(windy, WINDY, t) - 1.0
    assert np.abs(error).max() < 0.025 and abs(np.median(error)) < 0.01, (np.abs(error).max(), np.median(error))

    doc = map_document(gnss=gnss)   # air_data = "ground_speed"
    code, _, err = run(capsys, "import", write_map(tmp_path, doc), "--out", tmp_path / "ground")
    assert code == 0, err
    ground = read_bundle(tmp_path / "ground")
    t, q = ground.data["time"].to_numpy(), ground.data["qbar"].to_numpy()
    ground_error = np.abs(q / _true_qbar(windy, WINDY, t) - 1.0)
    assert np.median(ground_error[t > 10.0]) > 0.05 and ground_error.max() > 0.1


@pytest.mark.parametrize("edit, expected", [
    (lambda d: d["test"]["sigma"].update(qbar=5.0),
     "key 'test.sigma.qbar': a 1-sigma of qbar, but the map makes a logger bundle"),
    (lambda d: d["test"]["sigma"].pop("v_up"), "key 'test.sigma.v_up': is missing"),
    (lambda d: d.update(air_data="groundspeed"), "unknown air_data 'groundspeed'. Fix: did you mean 'ground_speed'?"),
    (lambda d: d["logger"]["gnss"]["channels"].pop("altitude"), "the bundle needs 'altitude'"),
    (lambda d: (d.update(air_data="reconstruct"),
                d["logger"]["gnss"]["channels"].update(airspeed={"column": "vn", "unit": "m/s"})),
     "key 'air_data': applies to a map whose air data come from GNSS velocity"),
    (lambda d: d["test"].update(wind={"altitude": [0.0], "north": [0.0], "east": [8.0], "sigma": -1.0}),
     "key 'test.wind.sigma'"),
    # what a logger bundle would silently ignore, and a zero sigma said at the map's key (not data.csv's)
    (lambda d: d["logger"]["gnss"]["channels"].update(gamma={"column": "vn", "unit": "deg"}),
     "key 'logger.gnss.channels.gamma': a logger bundle does not use gamma"),
    (lambda d: d["test"]["sigma"].update(v_north=0.0), "key 'test.sigma.v_north': a 1-sigma of 0 claims an exact"),
    (lambda d: d["logger"]["gnss"]["channels"]["velocity"].update(sign=-1),
     "velocity's three are north, east, down. Fix: remove sign; a receiver logging up rather than down: map its "
     "track"),
])
def test_logger_bundle_maps_are_refused_naming_the_key(tmp_path, sim, capsys, monkeypatch, edit, expected):
    write_loggers(tmp_path, sim)
    doc = map_document(air_data=None)
    doc["test"]["sigma"] = dict(LOGGER_SIGMA)
    edit(doc)
    monkeypatch.setattr(pd, "read_csv", None)  # refused before any logger file is parsed
    err = _refused(capsys, tmp_path, doc)
    assert expected in err and "map.toml" in err, err
    assert not (tmp_path / "bundle").exists()


def test_a_ground_speed_map_may_not_hold_a_wind_table(tmp_path, sim, capsys):
    """[test.wind] belongs to a logger bundle: with air_data = "ground_speed" it would be ignored, so it is
    refused, naming the key and both ways out."""
    write_loggers(tmp_path, sim)
    doc = map_document()
    doc["test"]["wind"] = {"altitude": [0.0], "north": [0.0], "east": [8.0]}
    err = _refused(capsys, tmp_path, doc)
    assert "key 'test.wind'" in err and "[wind] is for a logger bundle" in err, err


def test_the_imported_g_of_three_noisy_axes_is_unbiased():
    """0.3 g on three axes with 0.05 g of noise each: |a| reads high by about σ²/|a|; the bundle's G, less the
    noise across the force, within 1e-3 of the truth (the events are still found on the plain magnitude)."""
    from cpas_bayes.data.import_clocks import load_factor

    rng = np.random.default_rng(11)
    axes = (0.3 * np.array([0.0, 0.6, 0.8]) + rng.normal(0.0, 0.05, (200_000, 3))) * G0
    assert load_factor(axes).mean() - 0.3 > 5e-3
    assert abs(load_factor(axes, 0.05).mean() - 0.3) < 1e-3
    np.testing.assert_array_equal(load_factor(axes[:, 0], 0.05), axes[:, 0] / G0)   # one signed axis: as it is


def test_a_receiver_that_logs_its_track_gives_the_same_velocity(tmp_path, windy, capsys):
    """Ground speed (kn), course over ground (deg) and vertical speed positive down (ArduPilot's GPS Spd,
    GCrs, VZ) in place of north, east, down: the same logger bundle to the CSV's rounding."""
    gnss = _windy_loggers(tmp_path, windy)
    doc = map_document(air_data=None, gnss=gnss)
    doc["test"]["sigma"] = dict(LOGGER_SIGMA)
    code, _, err = run(capsys, "import", write_map(tmp_path, doc), "--out", tmp_path / "ned")
    assert code == 0, err
    rows = pd.read_csv(tmp_path / "gnss.csv")
    knots = 1852.0 / 3600.0
    speed = np.hypot(rows["vn"], rows["ve"]) / knots
    course = np.degrees(np.arctan2(rows["ve"], rows["vn"])) % 360.0
    _csv(tmp_path / "track.csv", ["time", "Spd", "GCrs", "VZ", "alt"],
         [rows["time"], speed, course, rows["vd"], rows["alt"]], ["%.4f", "%.6f", "%.6f", "%.4f", "%.4f"])
    track = dict(gnss, file="track.csv", channels={
        "ground_speed": {"column": "Spd", "unit": "kn"}, "course": {"column": "GCrs", "unit": "deg"},
        "vertical_speed": {"column": "VZ", "unit": "m/s", "sign": -1}, "altitude": {"column": "alt", "unit": "m"}})
    doc = map_document(air_data=None, gnss=track)
    doc["test"]["sigma"] = dict(LOGGER_SIGMA)
    code, printed, err = run(capsys, "import", write_map(tmp_path, doc), "--out", tmp_path / "track")
    assert code == 0, err
    assert "v_north, v_east, v_up <- gnss: Spd, GCrs, VZ (ground_speed kn, course deg, vertical_speed m/s sign -1)" \
        in printed
    a, b = read_bundle(tmp_path / "ned").data, read_bundle(tmp_path / "track").data
    np.testing.assert_array_equal(a["time"], b["time"])
    for c in ("v_north", "v_east", "v_up", "altitude", "G"):
        np.testing.assert_allclose(b[c], a[c], atol=1e-4, equal_nan=True, err_msg=c)


def test_a_height_above_ground_with_its_site_elevation_gives_the_sea_level_altitude(tmp_path, windy, capsys):
    """A barometer logging feet above a drop zone at 1,340 m: with ground = 4396.33 ft the bundle's altitude is
    the same as the receiver's sea-level one (to the CSV's rounding); without it, import says the height is
    taken as above sea level and how to say otherwise (read as sea level, q̄ would be ~13 % high)."""
    gnss = _windy_loggers(tmp_path, windy)
    doc = map_document(air_data=None, gnss=gnss)
    doc["test"]["sigma"] = dict(LOGGER_SIGMA)
    code, printed, err = run(capsys, "import", write_map(tmp_path, doc), "--out", tmp_path / "msl")
    assert code == 0, err
    assert "altitude <- gnss: alt (m), at its own samples, taken as above sea level (a height above ground: " \
           "give altitude's ground = the site's elevation)" in printed
    rows = pd.read_csv(tmp_path / "gnss.csv")
    ft, site = 0.3048, 1340.0
    _csv(tmp_path / "agl.csv", ["time", "vn", "ve", "vd", "h_agl"],
         [rows["time"], rows["vn"], rows["ve"], rows["vd"], (rows["alt"] - site) / ft], ["%.4f"] * 4 + ["%.6f"])
    agl = dict(gnss, file="agl.csv", channels={"velocity": gnss["channels"]["velocity"],
                                               "altitude": {"column": "h_agl", "unit": "ft", "ground": site / ft}})
    doc = map_document(air_data=None, gnss=agl)
    doc["test"]["sigma"] = dict(LOGGER_SIGMA)
    code, printed, err = run(capsys, "import", write_map(tmp_path, doc), "--out", tmp_path / "agl")
    assert code == 0, err
    assert "altitude <- gnss: h_agl (ft), at its own samples, above ground at 1340.0 m above sea level" in printed
    a, b = read_bundle(tmp_path / "msl").data, read_bundle(tmp_path / "agl").data
    np.testing.assert_allclose(b["altitude"], a["altitude"], atol=1e-4, equal_nan=True)


@pytest.mark.parametrize("channel, ground, expected", [
    ("altitude", 9000.0, "key 'logger.gnss.channels.altitude.ground': 9000 m is not a ground elevation"),
    ("altitude", "high", "key 'logger.gnss.channels.altitude.ground': must be a number (the site's elevation in m)"),
    ("velocity", 100.0, "key 'logger.gnss.channels.velocity.ground': applies to the altitude channel only"),
])
def test_a_bad_ground_elevation_is_refused_naming_the_key(tmp_path, sim, capsys, monkeypatch, channel, ground,
                                                          expected):
    write_loggers(tmp_path, sim)
    doc = map_document(air_data=None)
    doc["test"]["sigma"] = dict(LOGGER_SIGMA)
    doc["logger"]["gnss"]["channels"][channel]["ground"] = ground
    monkeypatch.setattr(pd, "read_csv", None)  # refused before any logger file is parsed
    assert expected in _refused(capsys, tmp_path, doc)


@pytest.mark.parametrize("edit, expected", [
    (lambda ch: ch.pop("vertical_speed"), "key 'logger.gnss.channels.vertical_speed': is missing: ground_speed "
                                          "and course give the velocity"),
    (lambda ch: ch.pop("course"), "key 'logger.gnss.channels.course': is missing"),
    (lambda ch: ch.update(velocity={"columns": ["vn", "ve", "vd"], "unit": "m/s"}),
     "key 'logger.gnss.channels.velocity': the velocity is mapped twice"),
])
def test_a_track_missing_a_part_or_given_twice_is_refused(tmp_path, sim, capsys, edit, expected):
    write_loggers(tmp_path, sim)
    doc = map_document(air_data=None)
    doc["test"]["sigma"] = dict(LOGGER_SIGMA)
    channels = {"ground_speed": {"column": "vn", "unit": "m/s"}, "course": {"column": "ve", "unit": "deg"},
                "vertical_speed": {"column": "vd", "unit": "m/s"}, "altitude": {"column": "alt", "unit": "m"}}
    edit(channels)
    doc["logger"]["gnss"]["channels"] = channels
    err = _refused(capsys, tmp_path, doc)
    assert expected in err, err


def test_a_receiver_switched_on_late_leaves_blank_cells_not_a_shorter_record(tmp_path, windy, capsys):
    """A logger bundle keeps the receiver's samples where they are: a receiver whose file starts 5 s after
    release no longer clips the record (it was then refused over the stage start, which the clipped record
    no longer held); the reduction still reads the clean snatch peak."""
    from cpas_bayes.data.reduction import reduce_test

    gnss = _windy_loggers(tmp_path, windy)
    rows = pd.read_csv(tmp_path / "gnss.csv")
    late = rows[rows["time"] > 137.25 + WINDY.release + 5.0]      # its clock: true time + 137.25 s
    late.to_csv(tmp_path / "gnss.csv", index=False, float_format="%.4f")
    doc = map_document(air_data=None, gnss=gnss)
    doc["test"]["sigma"] = dict(LOGGER_SIGMA)
    code, _, err = run(capsys, "import", write_map(tmp_path, doc), "--out", tmp_path / "late")
    assert code == 0, err
    test = read_bundle(tmp_path / "late")
    v = np.isfinite(test.data["v_north"].to_numpy())
    assert test.time[0] == pytest.approx(-0.5, abs=0.006) and test.time[v][0] > 4.0
    peak = max(p.accelerometer.load for p in reduce_test(test).peaks)
    assert peak == pytest.approx(WINDY.snatch_g * WINDY.mass * G0, rel=0.05)


# A receiver that logs only its fixes: the velocity by differences of pairs of fixes (data/import_velocity.py)

FIX_NOISE, FIX_ALTITUDE_NOISE = 0.03, 0.05   # m per fix: carrier-smoothed, fix to fix


def _fixes_map(folder, sim, seed=3, rate=10.0):
    """imu.csv and fixes.csv (latitude, longitude in degrees, altitude) of the windy drop, the receiver 0.4 s
    late, and a logger-bundle map of them whose sigmas state the fixes' noise."""
    rng = np.random.default_rng(seed)
    ta, fa = accel_logger(sim, 200.0, 37.25, 0.05, rng)
    tg, lat, lon, alt = gnss_fixes_logger(sim, rate, 137.25, FIX_NOISE, FIX_ALTITUDE_NOISE, rng, latency=LATENCY)
    _csv(folder / "imu.csv", ["t_ms", "ax", "ay", "az"], [ta * 1000, *fa.T], ["%.3f", "%.5f", "%.5f", "%.5f"])
    _csv(folder / "fixes.csv", ["time", "lat", "lon", "alt"], [tg, lat, lon, alt], ["%.4f", "%.9f", "%.9f", "%.3f"])
    fixes = {"file": "fixes.csv", "time": {"column": "time", "unit": "s"}, "offset": -100.0,
             "channels": {"position": {"columns": ["lat", "lon"], "unit": "deg"},
                          "altitude": {"column": "alt", "unit": "m"}}}
    doc = map_document(air_data=None, gnss=fixes)
    doc["test"]["sigma"] = {"G": 0.05, "altitude": FIX_ALTITUDE_NOISE, "position": FIX_NOISE}
    return doc, len(tg)


@pytest.mark.parametrize("rate, sd, lag_one, latency", [(10.0, (0.8, 1.25), 0.15, 0.03),
                                                        (2.0, (0.6, 1.4), 0.5, 0.08)])
def test_a_receiver_that_logs_only_its_fixes_gives_a_logger_bundle_with_honest_velocity_errors(tmp_path, windy,
                                                                                               capsys, rate, sd,
                                                                                               lag_one, latency):
    """Latitude, longitude and altitude (3 cm and 5 cm of noise per fix, the latitudes and longitudes made
    through Earth-centred coordinates, not the importer's local radii): one row per pair of fixes, whose
    velocity and altitude errors over their stated 1-sigmas are independent and about standard normal (at
    10 Hz sd within 0.8-1.25 and correlations within ±0.15 (over 8 seeds: 0.93-1.13 and ±0.16); at 2 Hz, 40
    rows, whose 1-sigmas carry the pairs' truncation through the snatch, sd within 0.6-1.4 and correlations
    within ±0.5, a truncation shared by a pair's velocity and altitude being correlated (over 8 seeds:
    0.79-1.37 and up to ±0.47), every error within 4 sigma), and whose reconstruction finds the wind and the
    latency and q̄ within 3 % of the truth (its median within 1 %)."""
    from cpas_bayes.data.reduction import reduce_test

    doc, n_fixes = _fixes_map(tmp_path, windy, rate=rate)
    doc["record"]["end"] = 39.0                      # the whole descent the loggers hold: 40 pairs at 2 Hz
    out = tmp_path / "logger"
    code, printed, err = run(capsys, "import", write_map(tmp_path, doc), "--out", out)
    assert code == 0, err
    assert "differences of pairs of fixes" in printed and "means of pairs of fixes" in printed
    assert f"pairs of fixes (rows) at {rate / 2:.1f} Hz" in printed and "warning" not in printed
    test = read_bundle(out)
    assert not test.measured_qbar
    d = test.data
    rows = np.isfinite(d["v_north"].to_numpy())
    assert rows.sum() == pytest.approx(rate / 2 * 39.5, abs=2)    # the record's 39.5 s of fixes, in pairs
    # the instants the rows show: bundle time is after the detected release, on the imu clock (37.25 s ahead)
    release = json.loads((out / REPORT_NAME).read_text())["release"]["time_on_reference_clock_s"]
    t = d["time"].to_numpy()[rows] + release - 37.25 - LATENCY
    true_t, v, h, _ = windy
    errors = []
    for column, k, sign in (("v_north", 0, 1), ("v_east", 1, 1), ("v_up", 2, -1)):
        truth = sign * np.interp(t, true_t, v[:, k])
        errors.append((d[column].to_numpy()[rows] - truth) / d[f"{column}_sigma"].to_numpy()[rows])
    errors.append((d["altitude"].to_numpy()[rows] - np.interp(t, true_t, h)) / d["altitude_sigma"].to_numpy()[rows])
    for name, z in zip(("north", "east", "up", "altitude"), errors):
        assert sd[0] < np.std(z) < sd[1] and abs(np.mean(z)) < 0.35 and np.abs(z).max() < 4, (name, np.std(z), z)
        assert abs(np.corrcoef(z[:-1], z[1:])[0, 1]) < lag_one, (name, np.corrcoef(z[:-1], z[1:])[0, 1])
    assert abs(np.corrcoef(errors[2], errors[3])[0, 1]) < lag_one   # the vertical is not counted twice

    red = reduce_test(test)
    phi = dict(zip(("airspeed", "gamma", "heading", "altitude", "wind_north", "wind_east", "scale", "bias",
                    "latency"), red.air_estimate.phi))
    assert phi["wind_east"] == pytest.approx(WINDY.wind_east, abs=0.3)
    assert phi["latency"] == pytest.approx(LATENCY, abs=latency)
    tq, q = red.test.data["time"].to_numpy(), red.test.data["qbar"].to_numpy()
    error = q / _true_qbar(windy, WINDY, tq) - 1.0
    assert np.abs(error).max() < 0.03 and abs(np.median(error)) < 0.01, (np.abs(error).max(), np.median(error))


def test_fixes_at_one_hertz_are_imported_with_a_warning_and_wider_sigmas_through_the_snatch(tmp_path, windy, capsys):
    """1 Hz fixes: a warning that the latency is poorly identified; the pairs' velocity 1-sigmas, which carry
    their truncation, are wider around the snatch (line stretch 1.6 s after release) than in steady descent."""
    doc, _ = _fixes_map(tmp_path, windy, rate=1.0)
    code, printed, err = run(capsys, "import", write_map(tmp_path, doc), "--out", tmp_path / "logger")
    assert code == 0, err
    assert "fixes at 1.0 Hz, fewer than 2" in printed and "the fit, which samples the latency" in printed
    d = read_bundle(tmp_path / "logger").data
    rows = np.isfinite(d["v_north"].to_numpy())
    t, sigma = d["time"].to_numpy()[rows], d["v_north_sigma"].to_numpy()[rows]
    steady = np.median(sigma[t > 15.0])
    assert steady == pytest.approx(np.sqrt(2) * FIX_NOISE / 1.0, rel=0.2)
    assert sigma[(t > 1.0) & (t < 4.0)].max() > 10 * steady


def test_local_metres_match_the_ellipsoids_degree_lengths():
    """At 45° a degree of latitude is 111,131.78 m and of longitude 78,846.81 m (WGS-84, by the usual series
    111,132.954 − 559.822·cos 2φ + 1.175·cos 4φ and 111,412.84·cos φ − 93.5·cos 3φ + 0.118·cos 5φ)."""
    from cpas_bayes.data.import_velocity import local_metres

    north, east = local_metres(np.array([44.995, 45.005]), np.array([9.995, 10.005]))
    assert np.diff(north)[0] / 0.01 == pytest.approx(111131.78, abs=0.5)
    assert np.diff(east)[0] / 0.01 == pytest.approx(78846.81, abs=0.5)


def test_fix_pairs_skip_a_dropped_fix():
    """Pairs are consecutive, disjoint, and never straddle a gap of more than 1.5 intervals."""
    from cpas_bayes.data.import_velocity import fix_pairs

    t = np.array([0.0, 0.1, 0.2, 0.3, 0.6, 0.7, 0.8, 0.9, 1.0])   # a gap after 0.3 s
    assert fix_pairs(t).tolist() == [0, 2, 4, 6]
    t = np.array([0.0, 0.1, 0.2, 0.5, 0.6, 0.7])                  # the gap would split the second pair
    assert fix_pairs(t).tolist() == [0, 3]


@pytest.mark.parametrize("edit, expected", [
    (lambda d: d["test"]["sigma"].pop("position"), "key 'test.sigma.position': is missing"),
    (lambda d: d["test"]["sigma"].update(position=-0.1), "key 'test.sigma.position': must be positive, got -0.1"),
    (lambda d: d["test"]["sigma"].update(v_north=0.1), "key 'test.sigma.v_north': the velocity is differenced"),
    (lambda d: d["logger"]["gnss"]["channels"].pop("altitude"), "key 'logger.gnss.channels.altitude': is missing"),
    (lambda d: d["logger"]["gnss"]["channels"].update(velocity={"columns": ["lat", "lon", "alt"], "unit": "m/s"}),
     "the velocity is mapped twice"),
    (lambda d: d["logger"]["gnss"]["channels"].update(density={"column": "alt", "unit": "kg/m^3"}),
     "key 'logger.gnss.channels.density': shares a logger with a position"),
    (lambda d: d["logger"]["gnss"]["channels"]["position"].update(columns=["lat"]), "takes 2 column(s), got 1"),
])
def test_maps_of_fixes_are_refused_naming_the_key(tmp_path, windy, capsys, monkeypatch, edit, expected):
    doc, _ = _fixes_map(tmp_path, windy)
    edit(doc)
    monkeypatch.setattr(pd, "read_csv", None)  # refused before any logger file is parsed
    err = _refused(capsys, tmp_path, doc)
    assert expected in err and "map.toml" in err, err


def test_fixes_that_are_not_latitude_and_longitude_are_refused_naming_the_cell(tmp_path, windy, capsys):
    doc, _ = _fixes_map(tmp_path, windy)
    doc["logger"]["gnss"]["channels"]["position"]["columns"] = ["lon", "alt"]   # altitude is no latitude
    err = _refused(capsys, tmp_path, doc)
    assert "fixes.csv" in err and "is beyond ±90°" in err and "column 'lon'" in err, err


def test_rows_without_a_fix_are_left_out_and_a_half_empty_one_is_refused_by_its_row(tmp_path, windy, capsys):
    """A receiver that lost its fix logs the time with empty position and altitude: those rows are left out
    (and said); a row with a latitude but no longitude is a broken row, refused by its row in the file."""
    doc, _ = _fixes_map(tmp_path, windy)
    lines = (tmp_path / "fixes.csv").read_text().splitlines()
    for i in range(200, 210):                       # one second without a fix
        lines[i] = lines[i].split(",")[0] + ",,,"
    (tmp_path / "fixes.csv").write_text("\n".join(lines) + "\n")
    code, printed, err = run(capsys, "import", write_map(tmp_path, doc), "--out", tmp_path / "logger")
    assert code == 0, err
    assert "10 rows without a fix left out" in printed
    report = json.loads((tmp_path / "logger" / REPORT_NAME).read_text())["loggers"]["gnss"]
    assert report["rows_are"] == "pairs of fixes" and report["rows_without_fix"] == 10
    lines[300] = ",".join(lines[300].split(",")[:2]) + ",,1000.0"
    (tmp_path / "fixes.csv").write_text("\n".join(lines) + "\n")
    err = _refused(capsys, tmp_path, doc, out=tmp_path / "again")
    assert "fixes.csv" in err and "row 301, column 'lon'" in err and "the cell is empty" in err, err

"""``cpas-bayes validate`` and ``--version``: summaries of good bundles, one clear message and a
non-zero exit for a refused one, never a traceback."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from cpas_bayes import __version__
from cpas_bayes.app.cli import main

DROGUE, MAIN = "drogue-clean", "main-clean"
SUMMARY_LINES = {
    DROGUE: ["EX-drogue  (drogue, US units)",
             "  1601 samples over 16.00 s at 100.0 Hz",
             "  D3: drogue, infinite mass, D_o 23; load cell",
             "      stages: reefed 1 @ 1.038 s, full open @ 9.481 s",
             "  D6: drogue, infinite mass, D_o 23; load cell",
             "      stages: reefed 1 @ 1.113 s, full open @ 10.031 s",
             "  channels: time, G, qbar, airspeed, gamma, density, altitude, F_D3, F_D6"],
    MAIN: ["EX-main  (main, US units)",
           "  4001 samples over 40.00 s at 100.0 Hz",
           "  M1: main, finite mass, D_o 116; load cell, fly-out angle",
           "      stages: reefed 1 @ 1.185 s, reefed 2 @ 10.839 s, full open @ 21.389 s",
           "  M3: main, finite mass, D_o 116; load cell, fly-out angle",
           "  channels: time, G, qbar, airspeed, gamma, density, altitude, F_M1, theta_M1, F_M2, theta_M2, F_M3, "
           "theta_M3"],
}

# The check list, planted in a copy of the drogue example: defect, file and place, problem.
BROKEN = {
    "missing column": (lambda f: f.drop_column("airspeed"), "data.csv, column 'airspeed'",
                       "missing column 'airspeed': data.csv gives 'qbar' but not 'airspeed'"),
    "NaN in qbar": (lambda f: f.set_cell(7, "qbar", "nan"), "data.csv, row 7, column 'qbar'",
                    "the cell is 'nan', not a finite number"),
    "time not increasing": (lambda f: f.set_cell(50, "time", "0.47"), "data.csv, row 50, column 'time'",
                            "time not strictly increasing"),
    "unknown units": (lambda f: f.set_key("units", value="imperial"), "test.toml, key 'units'",
                      "unknown units 'imperial'"),
    "duplicate parachute id": (lambda f: f.set_key("parachute", 1, "id", value="D3"),
                               "test.toml, key 'parachute[1].id'", "duplicate parachute id 'D3'"),
    "stage out of order": (lambda f: f.set_key("parachute", 0, "stage", 1, "start", value=1.0),
                           "test.toml, key 'parachute 'D3'.stage[1].start'", "stages out of time order"),
    # issue #18: refused by validate, so that reduce and fit never meet them
    "name climbs out": (lambda f: f.set_key("name", value="../../victim"), "test.toml, key 'name'",
                        "test name '../../victim' cannot be used"),
    "id with an ANSI escape": (lambda f: f.set_key("parachute", 0, "id", value="\x1b[2J\x1b[31mD3"),
                               "test.toml, key 'parachute[0].id'", "contains a control character"),
    "400-digit integer": (lambda f: f.toml_path.write_text(f.toml_path.read_text().replace(
        "weight = 20263.7", "weight = " + "7" * 400)), "test.toml, key 'vehicle.weight'", "beyond 64 bits"),
    "deep array": (lambda f: f.toml_path.write_text(f.toml_path.read_text() + "x = " + "[" * 100_000
                                                    + "]" * 100_000 + "\n"), "test.toml, line 48", "nested more than 16 deep"),
    "misspelt key": (lambda f: f.set_key("vehicle", "weight_sigm", value=100.0), "test.toml, key 'vehicle.weight_sigm'",
                     "did you mean 'weight_sigma'?"),
    "G of 1e300": (lambda f: f.set_cell(30, "G", "1e300"), "data.csv, row 30, column 'G'", "is outside -50 … 50 g"),
    "time in ms": (lambda f: f.write_rows([r if k == 0 else [repr(float(r[0]) * 1000)] + r[1:]
                                           for k, r in enumerate(f.read_rows())]),
                   "data.csv, row 1602, column 'time'", "divide the column by 1000"),
    "stage after the record": (lambda f: f.set_key("parachute", 0, "stage", 1, "start", value=500.0),
                               "test.toml, key 'parachute 'D3'.stage[1].start'", "at or after the record ends"),
    "shared load cell": (lambda f: f.set_key("parachute", 1, "load_cell", value="F_D3"),
                         "test.toml, key 'parachute 'D6'.load_cell'", "already the load_cell of parachute 'D3'"),
    "trailing commas": (lambda f: f.write_rows([r + [""] if k else r for k, r in enumerate(f.read_rows())]),
                        "data.csv, row 2", "the row ends with a comma (every data row does)"),
    # refused by reduce and fit before, passed by validate (a fuzzing pass, 2026-11-24)
    "a cluster measured in part": (lambda f: f.delete_key("parachute", 1, "load_cell"),
                                   "test.toml, key 'parachute 'D6'.load_cell'", "D6 have no load cell"),
}


@pytest.fixture
def broken(example_dir, bundle_files):
    """``broken(case)``: a copy of the drogue example with the defect ``BROKEN[case]``; returns its folder."""
    def make(case):
        folder = example_dir(DROGUE, case.replace(" ", "-"))
        BROKEN[case][0](bundle_files(folder))
        return folder
    return make


def run(capsys, *args):
    code = main(list(map(str, args)))
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    return code, out, err


def test_examples_are_accepted_and_summarised(example_dir, capsys):
    code, out, err = run(capsys, "validate", example_dir(DROGUE), example_dir(MAIN))
    assert code == 0
    assert err == ""
    lines = out.splitlines()
    for name, expected in SUMMARY_LINES.items():
        assert set(expected) <= set(lines), name
    assert lines.index(SUMMARY_LINES[DROGUE][0]) < lines.index(SUMMARY_LINES[MAIN][0])


def test_json_summary(example_dir, capsys):
    code, out, _ = run(capsys, "validate", "--json", example_dir(MAIN))
    assert code == 0
    (summary,) = json.loads(out)
    assert summary["samples"] == 4001
    assert summary["duration_s"] == pytest.approx(40.0)
    assert summary["sample_rate_hz"] == pytest.approx(100.0)
    assert [p["id"] for p in summary["parachutes"]] == ["M1", "M2", "M3"]
    assert [s["label"] for s in summary["parachutes"][0]["stages"]] == ["reefed 1", "reefed 2", "full open"]
    assert "theta_M2" in summary["channels"]


@pytest.mark.parametrize("case", BROKEN)
def test_broken_bundle_is_refused_with_one_message(broken, capsys, case):
    folder = broken(case)
    _, place, problem = BROKEN[case]
    file, _, where = place.partition(", ")
    code, out, err = run(capsys, "validate", folder)
    assert code == 2
    assert out == ""
    assert err.startswith(f"refused: {folder / file}, {where}: ")
    assert problem in err
    assert ". Fix: " in err
    assert len(err.strip().splitlines()) == 1
    assert "\x1b" not in err.replace("\x1b[31m", "").replace("\x1b[0m", "")  # only click's own colour codes


def test_every_refusal_is_reported_and_good_bundles_still_summarised(example_dir, broken, capsys):
    code, out, err = run(capsys, "validate", broken("unknown units"), example_dir(MAIN), broken("stage out of order"))
    assert code == 2
    assert SUMMARY_LINES[MAIN][0] in out.splitlines()
    assert [line.partition(": ")[0] for line in err.splitlines()] == ["refused"] * 2
    assert "unknown units 'imperial'" in err and "stages out of time order" in err


def test_version(capsys):
    code, out, _ = run(capsys, "--version")
    assert code == 0
    assert out.strip() == f"cpas-bayes, version {__version__}"


def test_missing_argument_is_a_usage_error(capsys):
    code, out, err = run(capsys, "validate")
    assert code == 2
    assert "Missing argument 'BUNDLES...'" in err


def test_as_a_process(example_dir, broken):
    """The real entry point in a fresh interpreter: a good and a refused bundle, no traceback."""
    good, bad = example_dir(DROGUE), broken("NaN in qbar")
    env = {k: v for k, v in os.environ.items() if k != "CPAS_BAYES_DEBUG"}
    proc = subprocess.run([sys.executable, "-m", "cpas_bayes.app.cli", "validate", str(good), str(bad)],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stdout + proc.stderr
    assert SUMMARY_LINES[DROGUE][1] in proc.stdout.splitlines()
    assert f"refused: {bad / 'data.csv'}, row 7, column 'qbar': " in proc.stderr


BAD_PRIORS = {
    "misspelt nuisance": ('[nuisance]\nload_scal = { family = "uniform", low = 1.0, high = 1.3 }\n',
                          "key 'nuisance.load_scal'", "did you mean 'load_scale'?"),
    "kind in capitals": ('kind = "Drogue"\n[first]\nn_p = { family = "normal", mu = 12.0, sigma = 1.0 }\n',
                         "key 'kind'", "unknown kind 'Drogue'"),
    "high = inf": ('[first]\nn_p = { family = "lognormal", median = 10.0, sigma_log = 0.5, low = 2.0, high = inf }\n',
                   "key 'first.n_p.high'", "must be a finite number, got inf"),
    "Latin-1": ("# équipe\n".encode("latin-1"), "line 1 (byte 2)", "not UTF-8 text"),
}


def _prior_file(tmp_path, case):
    text = BAD_PRIORS[case][0]
    path = tmp_path / "my priors.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    return path


@pytest.mark.parametrize("case", BAD_PRIORS)
def test_validate_checks_a_prior_file(example_dir, capsys, tmp_path, case):
    path = _prior_file(tmp_path, case)
    _, place, problem = BAD_PRIORS[case]
    code, out, err = run(capsys, "validate", "--priors", path, example_dir(DROGUE))
    assert code == 2
    assert SUMMARY_LINES[DROGUE][0] in out.splitlines()          # the bundle itself is fine and summarised
    assert err.startswith(f"refused: {path}, {place}: ") and problem in err and ". Fix: " in err
    assert len(err.strip().splitlines()) == 1


def test_validate_accepts_a_good_prior_file(example_dir, capsys, tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('kind = "drogue"\n[first]\nn_p = { family = "normal", mu = 12.0, sigma = 1.0 }\n')
    code, _, err = run(capsys, "validate", "--priors", path, example_dir(DROGUE))
    assert (code, err) == (0, "")


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_fit_and_diagnose_refuse_a_bad_prior_file_before_any_work(example_dir, capsys, tmp_path, monkeypatch,
                                                                  command):
    from cpas_bayes.data import reduction

    def no_work(*args, **kwargs):
        raise AssertionError("the reduction ran before the prior file was checked")

    monkeypatch.setattr(reduction, "reduce_test", no_work)
    path, out = _prior_file(tmp_path, "high = inf"), tmp_path / "out"
    code, _, err = run(capsys, command, example_dir(DROGUE), "--out", out, "--priors", path)
    assert code == 2
    assert err.startswith(f"error: {path}, key 'first.n_p.high': must be a finite number, got inf. Fix: ")
    assert not out.exists()


def test_validate_refuses_a_logger_record_that_reduce_would_refuse(tmp_path, capsys):
    """A logger record cut 0.95 s in holds 6 receiver samples but only 1 that its accelerometer readings span
    at every latency the fit allows: reduce refuses it, and now validate does too, naming data.csv."""
    from dataclasses import replace

    from cpas_bayes.data.bundle_write import write_bundle
    from cpas_bayes.data.synth_logger import synthesize_logger

    test, _ = synthesize_logger("logger-drop", 1)
    t = test.data["time"].to_numpy(float)
    folder = write_bundle(replace(test, data=test.data[t <= 0.95].reset_index(drop=True)), tmp_path / "short")
    code, out, err = run(capsys, "validate", folder)
    assert code == 2 and out == ""
    assert err.startswith(f"refused: {folder / 'data.csv'}, columns 'v_north', 'v_east', 'v_up': the "
                          "accelerometer's record and the receiver's overlap too little"), err
    assert "Fix: supply accelerometer readings until at least" in err

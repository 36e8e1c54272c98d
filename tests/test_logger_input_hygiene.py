"""Careless inputs to logger bundles, found by a fuzzing pass, each refused by name (exit status 2, nothing
written; the receiver's rates, which older bundles hold, are taken with a warning) while the correct bundle
beside it still passes:

1. a ``[rate] G`` that disagrees with the readings' own spacing (``G = 1000`` on a 20 Hz record);
2. ``[rate] v`` / ``[rate] altitude``, which the model does not use, said so by validate (it takes the receiver's samples as
   instantaneous, stamped late by a fitted latency);
3. one thing specified twice, where one would silently win: a ``[sigma]`` entry beside a ``<name>_sigma``
   column, ``G`` beside ``accel_x/y/z`` (and a 1-sigma for the accelerometer form not given), a ``density``
   column beside ``[atmosphere]``;
4. a short record whose receiver samples fall in the latency window: ``validate`` refuses it as ``reduce``
   does, by the same check, saying what is too short and until when readings are needed;
5. an ``--out`` that is, or lies inside, an input bundle folder (symbolic links resolved), for every command
   that takes bundles and ``--out``.

docs/test-bundle.md, "Logger bundles".
"""

from __future__ import annotations

import json
import os
import re
import shutil

import numpy as np
import pytest
from bundle_writer import write_by_hand

from cpas_bayes.app.cli import main
from cpas_bayes.core.errors import BundleError
from cpas_bayes.core.ownership import OutputError
from cpas_bayes.data.bundle import read_bundle

# A 20 Hz accelerometer (t = 0.05 k, 41 readings) and a 5 Hz receiver (t = 0.01 + 0.2 k, 10 samples) on rows
# of their own: the layout of tests/test_bundle_air.py, built here so that each test states its own defect.
G_TIMES = [round(0.05 * k, 6) for k in range(41)]
GNSS_TIMES = [round(0.01 + 0.2 * k, 6) for k in range(10)]
HEADER = ["time", "G", "v_north", "v_east", "v_up", "altitude", "altitude_sigma", "F_D1"]
ROWS = sorted([{"time": t, "G": 1.0 + 0.1 * k, "F_D1": 100.0 + 40.0 * k} for k, t in enumerate(G_TIMES)]
              + [{"time": t, "v_north": 10.0 + k, "v_east": -2.0, "v_up": -30.0 + k, "altitude": 3000.0 - 6.0 * k,
                  "altitude_sigma": 5.0} for k, t in enumerate(GNSS_TIMES)], key=lambda r: r["time"])
DOC = {
    "name": "LOG-H", "units": "SI", "phase": "drogue",
    "vehicle": {"weight": 20000.0, "weight_sigma": 100.0, "cds": 2.0, "cds_sigma": 0.2},
    "parachute": [{"id": "D1", "kind": "drogue", "inflation": "infinite", "diameter": 7.0, "weight": 400.0,
                   "weight_sigma": 5.0, "load_cell": "F_D1",
                   "stage": [{"label": "full open", "start": 0.5, "start_sigma": 0.05}]}],
    "sigma": {"G": 0.03, "v_north": 0.1, "v_east": 0.15, "v_up": 0.2, "F_D1": 10.0},
    "wind": {"altitude": [0.0, 3000.0], "north": [1.0, 3.0], "east": [-4.0, -6.0]},
    "atmosphere": {"altitude": [0.0, 5000.0], "density": [1.225, 0.736]},
    "rate": {"G": 20.0},
}


def doc_with(**changes):
    """A copy of DOC with top-level entries replaced (None deletes)."""
    doc = json.loads(json.dumps(DOC))
    for key, value in changes.items():
        if value is None:
            doc.pop(key, None)
        else:
            doc[key] = value
    return doc


def write_logger(folder, doc=None, rows=None, header=None):
    """test.toml from ``doc`` and data.csv from ``rows`` (empty cells for absent keys); returns the folder."""
    return write_by_hand(folder, DOC if doc is None else doc, rows or ROWS, header or HEADER)


def run(capsys, *args):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err and "internal error" not in err
    return code, out, err


def refusal(folder):
    with pytest.raises(BundleError) as caught:
        read_bundle(folder)
    return caught.value


def assert_refused_everywhere(capsys, snapshot, folder, message_start):
    """``validate`` refuses the bundle and ``reduce`` too, with exit status 2, the same message, and nothing
    written: no --out folder, the bundle's files unchanged."""
    before = snapshot(folder)
    code, out, err = run(capsys, "validate", folder)
    assert code == 2 and out == "", out
    assert err.startswith(f"refused: {message_start}"), err
    out_dir = folder.parent / f"{folder.name}-reduction"
    code, _, err_reduce = run(capsys, "reduce", folder, "--out", out_dir)
    assert code == 2
    assert err_reduce.startswith(f"error: {message_start}"), err_reduce
    assert err_reduce.removeprefix("error: ") == err.removeprefix("refused: ")   # one check, one message
    assert not out_dir.exists()
    assert snapshot(folder) == before


# ---------------------------------------------------------------------------
# 1. a declared rate that disagrees with the readings


@pytest.mark.parametrize("declared", [1000.0, 10.0, 21.5, 18.5])
def test_a_declared_g_rate_off_the_readings_spacing_is_refused(tmp_path, capsys, snapshot, declared):
    folder = write_logger(tmp_path / "log", doc_with(rate={"G": declared}))
    err = refusal(folder)
    assert err.file == str(folder / "test.toml") and err.where == "key 'rate.G'", str(err)
    assert err.problem.startswith(f"[rate] G = {declared:g} Hz, but data.csv's time column shows the "
                                  "accelerometer's 41 readings 50 ms apart, 20 Hz (more than 5 % off)"), err.problem
    assert err.fix == "declare G = 20, or remove the entry (the readings' own spacing is then used)"
    assert_refused_everywhere(capsys, snapshot, folder, f"{folder / 'test.toml'}, key 'rate.G': [rate] G = ")


@pytest.mark.parametrize("declared", [20.0, 20.9, 19.1, None])
def test_a_declared_g_rate_within_five_per_cent_or_none_passes(tmp_path, capsys, declared):
    folder = write_logger(tmp_path / "log", doc_with(rate=None if declared is None else {"G": declared}))
    assert read_bundle(folder).air_data.rates == ({} if declared is None else {"G": declared})
    assert run(capsys, "validate", folder)[0] == 0


def test_the_rate_a_time_column_shows_averages_its_rounding_and_skips_dropouts():
    """400 Hz stamped in milliseconds: intervals of 2 and 3 ms, a median 20 % off either way; the mean of the
    regular intervals is 2.5 ms to 0.5 %, and a dropped reading (a 5 ms interval) is left out."""
    from cpas_bayes.data.air_data import own_interval

    t = np.round(np.arange(200) / 400.0, 3)
    assert abs(float(np.median(np.diff(t))) - 0.0025) / 0.0025 > 0.19
    assert own_interval(t) == pytest.approx(0.0025, rel=0.005)
    assert own_interval(np.delete(t, [50, 120])) == pytest.approx(0.0025, rel=0.005)
    assert own_interval(t[:1]) == 0.0


def test_a_millisecond_stamped_400_hz_logger_keeps_its_true_rate(tmp_path, capsys):
    """Its declared 400 Hz passes (a check on the median interval would refuse it), 350 Hz does not."""
    times = np.round(np.arange(800) / 400.0, 3)
    rows = [{"time": float(t), "G": 1.0 + 0.001 * k, "F_D1": 100.0} for k, t in enumerate(times)]
    for k in range(0, 800, 80):                     # the receiver on every 80th row: 5 Hz
        rows[k].update({"v_north": 10.0, "v_east": -2.0, "v_up": -30.0 + k / 80, "altitude": 3000.0 - k / 10,
                        "altitude_sigma": 5.0})
    ok = write_logger(tmp_path / "ms400", doc_with(rate={"G": 400.0}), rows)
    assert read_bundle(ok).air_data.rates == {"G": 400.0}
    off = write_logger(tmp_path / "ms350", doc_with(rate={"G": 350.0}), rows)
    assert re.search(r"800 readings 2\.50\d* ms apart, (399\.9|400) Hz", refusal(off).problem)


# ---------------------------------------------------------------------------
# 2. [rate] of the receiver's channels


@pytest.mark.parametrize("key", ["v", "altitude", "v_up"])
def test_a_receiver_rate_is_taken_but_said_to_be_unused(tmp_path, capsys, key):
    """Bundles written to the earlier format reference declare the receiver's rates: they still read, the rate
    changes nothing the model uses, and validate says that it is not used."""
    from cpas_bayes.data.bundle import summary

    folder = write_logger(tmp_path / "log", doc_with(rate={"G": 20.0, key: 5.0}))
    test = read_bundle(folder)
    assert test.air_data.rates == {"G": 20.0} and test.air_data.unused_rates == (key,)
    plain = read_bundle(write_logger(tmp_path / "plain", doc_with(rate={"G": 20.0})))
    assert plain.air_data.rates == test.air_data.rates and plain.air_data.unused_rates == ()
    warnings = summary(test)["warnings"]
    assert len(warnings) == 1 and warnings[0].startswith(f"test.toml [rate] {key} is not used: the model treats")
    code, out = run(capsys, "validate", folder)[:2]
    assert code == 0 and f"warning: test.toml [rate] {key} is not used" in out
    assert "warnings" not in summary(plain)


def test_synthetic_and_example_logger_bundles_declare_only_the_accelerometer_rate(tmp_path):
    from pathlib import Path

    from cpas_bayes.data.synth_logger import write_logger_synthetic

    for scenario in ("logger-drop", "logger-attitude"):
        folder = write_logger_synthetic(scenario, 2, tmp_path / scenario)
        assert set(read_bundle(folder).air_data.rates) == {"G"}, scenario
    example = Path(__file__).parent.parent / "docs" / "examples" / "logger-drop"
    assert read_bundle(example).air_data.rates == {"G": 20.0}


def test_the_summary_shows_the_receivers_own_rate_and_no_rate_warnings(tmp_path):
    """With the receiver's rates gone and G's refused when off, validate's summary has nothing to warn of."""
    from cpas_bayes.data.bundle import summary

    s = summary(read_bundle(write_logger(tmp_path / "log")))
    assert s["air_data"].startswith("GNSS velocity (10 samples at 5 Hz), altitude (10 samples)"), s["air_data"]
    assert "warnings" not in s


# ---------------------------------------------------------------------------
# 3. the same thing specified twice


def _sigma_column_and_entry(folder, channel):
    """``channel``'s 1-sigma as a column, and DOC's [sigma] entry for it kept."""
    header = HEADER + [f"{channel}_sigma"]
    rows = [{**r, f"{channel}_sigma": 0.5} if channel in r else r for r in ROWS]
    return write_logger(folder, rows=rows, header=header), rows, header


def _axes_rows():
    return [{**{k: v for k, v in r.items() if k != "G"}, "accel_x": 0.0, "accel_y": 0.6 * r["G"],
             "accel_z": 0.8 * r["G"]} if "G" in r else r for r in ROWS]


AXES_HEADER = [c for c in HEADER if c != "G"] + ["accel_x", "accel_y", "accel_z"]
AXES_SIGMA = {"accel_x": 0.02, "accel_y": 0.02, "accel_z": 0.02, "v_north": 0.1, "v_east": 0.15, "v_up": 0.2,
              "F_D1": 10.0}

CONFLICTS = {
    # case: (write the conflicting bundle, write the fixed one, file, place, problem, fix)
    "sigma column and [sigma] v_up": (
        lambda f: _sigma_column_and_entry(f, "v_up")[0],
        lambda f: write_logger(f, doc_with(sigma={k: v for k, v in DOC["sigma"].items() if k != "v_up"}),
                               *_sigma_column_and_entry(f, "v_up")[1:]),
        "test.toml", "key 'sigma.v_up'", "the 1-sigma of 'v_up' is given twice: here and as data.csv's column "
        "'v_up_sigma'", "keep one: remove 'v_up' from [sigma]"),
    "sigma column and [sigma] G": (
        lambda f: _sigma_column_and_entry(f, "G")[0],
        lambda f: write_logger(f, doc_with(sigma={k: v for k, v in DOC["sigma"].items() if k != "G"}),
                               *_sigma_column_and_entry(f, "G")[1:]),
        "test.toml", "key 'sigma.G'", "the 1-sigma of 'G' is given twice", "or remove the column 'G_sigma'"),
    "sigma column and [sigma] of a load cell": (
        lambda f: _sigma_column_and_entry(f, "F_D1")[0],
        lambda f: write_logger(f, doc_with(sigma={k: v for k, v in DOC["sigma"].items() if k != "F_D1"}),
                               *_sigma_column_and_entry(f, "F_D1")[1:]),
        "test.toml", "key 'sigma.F_D1'", "the 1-sigma of 'F_D1' is given twice", "keep one"),
    "G beside the three axes": (
        lambda f: write_logger(f, doc_with(sigma={**AXES_SIGMA, "G": 0.03}),
                               [{**r, **a} for r, a in zip(ROWS, _axes_rows())], HEADER + AXES_HEADER[-3:]),
        lambda f: write_logger(f, doc_with(sigma=AXES_SIGMA), _axes_rows(), AXES_HEADER),
        "data.csv", "columns 'G', 'accel_x', 'accel_y', 'accel_z'", "data.csv gives both G and accelerometer body "
        "axes", "keep G (the sensed load factor, g) or accel_x, accel_y, accel_z (three body axes, g), not both"),
    "[sigma] G beside the three axes": (
        lambda f: write_logger(f, doc_with(sigma={**AXES_SIGMA, "G": 0.03}), _axes_rows(), AXES_HEADER),
        lambda f: write_logger(f, doc_with(sigma=AXES_SIGMA), _axes_rows(), AXES_HEADER),
        "test.toml", "key 'sigma.G'", "a 1-sigma for 'G', but data.csv gives the accelerometer as accel_x, "
        "accel_y, accel_z, from whose 1-sigmas G's is propagated: this entry would be ignored",
        "remove 'G' from [sigma] and give the axes' 1-sigmas"),
    "a G_sigma column beside the three axes": (
        lambda f: write_logger(f, doc_with(sigma=AXES_SIGMA), [{**r, "G_sigma": 0.03} if "accel_x" in r else r
                                                               for r in _axes_rows()], AXES_HEADER + ["G_sigma"]),
        lambda f: write_logger(f, doc_with(sigma=AXES_SIGMA), _axes_rows(), AXES_HEADER),
        "data.csv", "column 'G_sigma'", "a 1-sigma column for G, but data.csv gives the accelerometer as accel_x, "
        "accel_y, accel_z", "remove the column 'G_sigma'"),
    "[sigma] accel_x beside G": (
        lambda f: write_logger(f, doc_with(sigma={**DOC["sigma"], "accel_x": 0.02})),
        lambda f: write_logger(f),
        "test.toml", "key 'sigma.accel_x'", "a 1-sigma for 'accel_x', but data.csv gives the accelerometer as G: "
        "this entry would be ignored", "remove 'accel_x' from [sigma]"),
    "a density column beside [atmosphere]": (
        lambda f: write_logger(f, rows=[{**r, "density": 0.9} if "v_up" in r else r for r in ROWS],
                               header=HEADER + ["density"]),
        lambda f: write_logger(f, doc_with(atmosphere=None), [{**r, "density": 0.9} if "v_up" in r else r
                                                             for r in ROWS], HEADER + ["density"]),
        "test.toml", "key 'atmosphere'", "a density profile is given here and as data.csv's column 'density': two "
        "densities for one flight, and one would be ignored", "keep one: remove [atmosphere] (the column gives the "
        "density along the record) or the column 'density'"),
}


@pytest.mark.parametrize("case", CONFLICTS)
def test_a_thing_given_twice_is_refused_and_the_bundle_with_one_passes(tmp_path, capsys, snapshot, case):
    conflicting, fixed, file, place, problem, fix = CONFLICTS[case]
    folder = conflicting(tmp_path / "log")
    err = refusal(folder)
    assert str(err).startswith(f"{folder / file}, {place}: "), str(err)
    assert problem in err.problem, err.problem
    assert fix in err.fix, err.fix
    assert_refused_everywhere(capsys, snapshot, folder, f"{folder / file}, {place}: ")
    good = fixed(tmp_path / "fixed")
    read_bundle(good)
    assert run(capsys, "validate", good)[0] == 0


# ---------------------------------------------------------------------------
# 4. a record too short for the receiver's latency window


def _short_record(folder, rows_count):
    """``rows_count`` readings at 20 Hz from 0 s, the receiver on rows 0, 5 and 11 (0, 0.25 and 0.55 s)."""
    rows = []
    for k in range(rows_count):
        row = {"time": round(0.05 * k, 6), "G": 0.3 + 0.5 * k}
        if k in (0, 5, 11):
            row.update({"v_north": 30.0, "v_east": 0.0, "v_up": -30.0 - k, "altitude": 3000.0 - 10.0 * k,
                        "altitude_sigma": 5.0})
        rows.append(row)
    chute = {k: v for k, v in DOC["parachute"][0].items() if k != "load_cell"}
    doc = doc_with(rate=None, atmosphere=None, sigma={"G": 0.03, "v_north": 0.1, "v_east": 0.1, "v_up": 0.1},
                   parachute=[{**chute, "stage": [{"label": "full open", "start": 0.2, "start_sigma": 0.05}]}])
    return write_logger(folder, doc, rows, [c for c in HEADER if c != "F_D1"])


def test_validate_refuses_the_12_row_record_that_reduce_refuses_with_one_plain_message(tmp_path, capsys, snapshot):
    folder = _short_record(tmp_path / "short", 12)
    read_bundle(folder)   # the format is fine: the record is what is too short
    start = f"{folder / 'data.csv'}, columns 'v_north', 'v_east', 'v_up': "
    assert_refused_everywhere(capsys, snapshot, folder, start)
    code, _, err = run(capsys, "validate", folder)
    assert err.strip() == (
        f"refused: {start}the accelerometer's record and the receiver's overlap too little: the readings used run "
        "from 0 s (the first reading) to 0.55 s, and 1 receiver sample is stamped from 0 s to 0.05 s (0.5 s before "
        "the last reading), where at least 3 are needed: the receiver's fitted latency may be as low as -0.5 s (a "
        "sample showing the state 0.5 s after its stamp), so each sample used needs accelerometer readings from "
        "its stamp to 0.5 s past it. Fix: supply accelerometer readings until at least 1.05 s (0.5 s past the "
        "third receiver sample from 0 s on), or receiver samples earlier or more often, at least 3 of them from "
        "0 s to 0.05 s")


def test_the_record_the_message_asks_for_passes(tmp_path, capsys):
    """Readings until 1.05 s, as the fix says, and validate passes; one reading fewer, it still refuses."""
    assert run(capsys, "validate", _short_record(tmp_path / "enough", 22))[0] == 0
    assert run(capsys, "validate", _short_record(tmp_path / "one-short", 21))[0] == 2


def test_validate_and_reduce_share_the_check(monkeypatch, tmp_path, capsys):
    """validate refuses through reduction.check_reducible, which reads the channels as reduce does: replace
    the reconstruction's channel reader and validate's refusal goes with it."""
    from cpas_bayes.data import air_reconstruction

    folder = _short_record(tmp_path / "short", 12)
    assert run(capsys, "validate", folder)[0] == 2
    monkeypatch.setattr(air_reconstruction, "logger_channels", lambda test: None)
    assert run(capsys, "validate", folder)[0] == 0


# ---------------------------------------------------------------------------
# 5. --out inside an input bundle


@pytest.fixture
def no_work(monkeypatch):
    """Every bundle reader raises: a refusal that comes after one would not be 'before any work'."""
    from cpas_bayes.app import campaign, cli
    from cpas_bayes.data import bundle

    def refuse(*args, **kwargs):
        raise AssertionError("a bundle was read before --out was checked")

    for module in (cli, bundle, campaign):
        monkeypatch.setattr(module, "read_bundle", refuse)


def _commands(bundle, tmp_path):
    """(label, command line) of every command that takes a bundle and --out, its --out inside the bundle."""
    return [
        ("reduce", ["reduce", bundle, "--out", bundle / "reduction"]),
        ("fit", ["fit", bundle, "--out", bundle / "fit"]),
        ("fit, --out first", ["fit", "--out", bundle / "fit", bundle]),
        ("fit, deep", ["fit", bundle, "--out", bundle / "a" / "b" / "fit"]),
        ("diagnose", ["diagnose", bundle, "--out", bundle / "diagnosis"]),
        ("compare", ["compare", bundle, "--fit", tmp_path / "no-fit", "--out", bundle / "compare"]),
        ("montecarlo", ["montecarlo", "--memo", tmp_path / "memo.toml", "--like", bundle, "--out", bundle / "mc"]),
        ("campaign of one bundle", ["campaign", bundle, "--out", bundle / "campaign"]),
    ]


@pytest.mark.parametrize("index", range(8))
def test_out_inside_an_input_bundle_is_refused_before_any_work(tmp_path, capsys, snapshot, no_work, index):
    bundle = write_logger(tmp_path / "log")
    label, args = _commands(bundle, tmp_path)[index]
    before = snapshot(tmp_path)
    code, out, err = run(capsys, *args)
    assert code == 2, (label, out, err)
    out_path = args[args.index("--out") + 1]
    assert f"Error: Invalid value for '--out': {out_path}: --out lies inside the bundle folder {bundle}: the " \
           "outputs would be written among the bundle's own files. Fix: give --out a folder outside " \
           f"{bundle}, e.g. {bundle.resolve().parent / ('log-' + out_path.name)}" in err, (label, err)
    assert snapshot(tmp_path) == before, label


def test_a_campaign_out_inside_one_of_its_bundles_is_refused(tmp_path, capsys, snapshot, no_work):
    folder = tmp_path / "tests"
    write_logger(folder / "A")
    write_logger(folder / "B", doc_with(name="LOG-B"))
    before = snapshot(tmp_path)
    code, _, err = run(capsys, "campaign", folder, "--out", folder / "B" / "campaign")
    assert code == 2
    assert f"--out lies inside the bundle folder {folder / 'B'}: " in err, err
    assert snapshot(tmp_path) == before


def test_run_campaign_refuses_it_too(tmp_path, snapshot):
    from cpas_bayes.app.campaign import run_campaign
    from cpas_bayes.core.executor import Executor

    folder = tmp_path / "tests"
    write_logger(folder / "A")
    before = snapshot(tmp_path)
    with pytest.raises(OutputError, match="--out lies inside the bundle folder .*A: "):
        run_campaign(folder, folder / "A" / "out", echo=lambda *a: None, executor=Executor())
    assert snapshot(tmp_path) == before


def test_out_equal_to_the_bundle_is_refused_as_the_bundle(tmp_path, capsys, snapshot):
    bundle = write_logger(tmp_path / "log")
    before = snapshot(tmp_path)
    for command in ("reduce", "fit", "diagnose"):
        code, _, err = run(capsys, command, bundle, "--out", bundle)
        assert code == 2
        assert f"--out is the bundle folder {bundle}: " in err and f"e.g. {bundle.resolve()}-out" in err, err
    assert snapshot(tmp_path) == before


@pytest.mark.skipif(not hasattr(os, "symlink"), reason="no symbolic links")
def test_symbolic_links_are_resolved_both_ways(tmp_path, capsys, snapshot, no_work):
    bundle = write_logger(tmp_path / "log")
    link = tmp_path / "link"
    link.symlink_to(bundle, target_is_directory=True)
    before = snapshot(bundle)
    for args in (["reduce", link, "--out", bundle / "reduction"], ["reduce", bundle, "--out", link / "reduction"],
                 ["fit", link, "--out", link / "fit"]):
        code, _, err = run(capsys, *args)
        assert code == 2 and "--out lies inside the bundle folder" in err, (args, err)
    assert snapshot(bundle) == before


def test_an_out_beside_the_bundle_still_works(tmp_path, capsys, example_dir):
    """The rule refuses only what is inside an input bundle: a sibling folder is written as before."""
    from cpas_bayes.core.ownership import check_outside_inputs

    bundle = example_dir("drogue-clean")
    out = tmp_path / "drogue-clean-reduction"
    code, _, err = run(capsys, "reduce", bundle, "--out", out)
    assert code == 0, err
    assert (out / "reduction.json").is_file() and not (bundle / "reduction.json").exists()
    # a campaign's --out may sit in its folder beside the bundles, not in one of them
    assert check_outside_inputs(tmp_path / "out", [bundle]) == tmp_path / "out"
    shutil.rmtree(out)


# ---------------------------------------------------------------------------
# a clipped accelerometer


def test_a_flat_top_at_the_largest_reading_is_found_and_noise_or_rest_is_not():
    from cpas_bayes.data.bundle_notes import clipped_run

    t = np.arange(40) * 0.05
    rng = np.random.default_rng(0)
    g = 1.0 + 6.0 * np.exp(-0.5 * ((t - 1.0) / 0.2) ** 2) + 0.01 * rng.standard_normal(t.size)
    assert clipped_run(t, g) is None                                   # a peak with noise: no repeats
    clipped = np.minimum(g, 5.0)
    value, n, t0, t1 = clipped_run(t, clipped)
    flat = np.flatnonzero(clipped == 5.0)
    assert (value, n, t0, t1) == (5.0, flat.size, t[flat[0]], t[flat[-1]]) and n >= 3
    two = g.copy()
    two[[19, 20]] = g.max() + 1.0                                     # two equal readings: chance, not a clip
    assert clipped_run(t, two) is None
    rest = np.round(1.0 + 0.01 * rng.standard_normal(t.size), 1)        # a coarse sensor at rest repeats 1.0 g
    assert clipped_run(t, rest) is None
    holed = clipped.copy()
    holed[flat[1]] = np.nan                                            # a blank reading inside the top
    assert clipped_run(t, holed)[1] == flat.size - 1
    assert clipped_run(t, -clipped) == (-5.0, n, t0, t1)               # an axis clips at its negative end too


def test_a_body_axis_that_clipped_is_named():
    from cpas_bayes.data.bundle_notes import clipping_warnings
    from cpas_bayes.data.synth_logger import synthesize_logger

    test, _ = synthesize_logger("logger-attitude", 2)
    assert "G" not in test.data and clipping_warnings(test) == []
    axis = test.data["accel_x"].to_numpy()
    scale = np.nanquantile(np.abs(axis), 0.98)       # about 8 of its 400 readings at the full scale
    assert scale >= 2.0
    test.data["accel_x"] = np.clip(axis, -scale, scale)
    said = clipping_warnings(test)
    assert len(said) == 1 and said[0].startswith("data.csv accel_x holds its") and "rows of the three axes" in said[0]
    from cpas_bayes.inference.fit_health import reading_health_warnings

    assert [(w["code"], w["parameter"], w["message"]) for w in reading_health_warnings(test)] == [
        ("clipped_accelerometer", "accel_x", said[0])]          # the fit's warning names the axis, not G


def test_validate_reduce_and_the_fit_health_say_the_accelerometer_clipped(tmp_path, capsys):
    """The shipped logger example with its readings above 7 g set to 7 g (8 readings, as a ±7 g sensor reports):
    ``validate``, ``reduce`` and the fit's health warnings name the readings to blank; the example itself has no
    such warning."""
    from pathlib import Path

    from cpas_bayes.data.bundle_notes import clipping_warnings
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit_health import reading_health_warnings

    folder = tmp_path / "clipped"
    shutil.copytree(Path(__file__).parent.parent / "docs" / "examples" / "logger-drop", folder)
    lines = (folder / "data.csv").read_text().splitlines()
    column = lines[0].split(",").index("G")
    for i, line in enumerate(lines[1:], 1):
        cells = line.split(",")
        if cells[column] and float(cells[column]) > 7.0:
            cells[column] = "7.0"
        lines[i] = ",".join(cells)
    (folder / "data.csv").write_text("\n".join(lines) + "\n")
    assert main(["validate", str(folder)]) == 0
    said = capsys.readouterr().out
    assert "G holds its largest reading, 7 g, for 8 readings in a row" in said and "Blank those G cells" in said
    test = read_bundle(folder)
    assert reduce_test(test).warnings == clipping_warnings(test) and len(clipping_warnings(test)) == 1
    assert [(w["code"], w["parameter"]) for w in reading_health_warnings(test)] == [("clipped_accelerometer", "G")]
    assert clipping_warnings(read_bundle(Path(__file__).parent.parent / "docs" / "examples" / "logger-drop")) == []


# a dead load cell
def test_a_dead_load_cell_is_said_by_validate_reduce_and_the_fit_health(example_dir, capsys):
    """One Drogue's load cell zeroed (an unplugged channel), or reading its stated noise alone: ``validate``,
    ``reduce`` and the fit's health say so, naming the column and the fix; the example itself, whose cells
    span hundreds of sigma, has no such warning. Before, the zeroed cell fitted with error multipliers of 10
    and eight parameters at their priors' bounds, and nothing named the cell."""
    from cpas_bayes.data.bundle_notes import dead_load_cells
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit_health import reading_health_warnings

    folder = example_dir("drogue-clean", "dead-cell")
    assert dead_load_cells(read_bundle(folder)) == []
    lines = (folder / "data.csv").read_text().splitlines()
    column = lines[0].split(",").index("F_D3")
    for i, line in enumerate(lines[1:], 1):
        cells = line.split(",")
        cells[column] = "0"
        lines[i] = ",".join(cells)
    (folder / "data.csv").write_text("\n".join(lines) + "\n")
    assert main(["validate", str(folder)]) == 0
    said = capsys.readouterr().out
    assert "F_D3, the load cell of parachute 'D3', stays within its noise" in said
    assert "its readings span 0 lbf against a stated 1-sigma of 144.6 lbf" in said   # the sigma column's median
    assert "remove the load_cell of every parachute" in said
    test = read_bundle(folder)
    assert reduce_test(test).warnings == [text for _, text in dead_load_cells(test)]
    assert [(w["code"], w["parameter"]) for w in reading_health_warnings(test)] == [("dead_load_cell", "F_D3")]
    # noise alone (the stated 1-sigma, Gaussian) is as dead as zeros; a tenth of the load is not
    rng = np.random.default_rng(0)
    sigma = np.asarray(test.data["F_D3_sigma"], float)
    test.data["F_D3"] = rng.normal(0.0, sigma)
    assert [c for c, _ in dead_load_cells(test)] == ["F_D3"]
    test.data["F_D3"] = 0.1 * np.asarray(test.data["F_D6"], float)
    assert dead_load_cells(test) == []


# stage starts on another time base than the readings
def test_a_load_before_the_first_stage_start_is_said(example_dir, capsys):
    """The two-Drogue example's record shifted 5 s earlier (its stage starts left as they were), and the shipped
    logger example's stage stated at 19.9 s where its canopy opened at 1.8 s: ``validate``, ``reduce`` and the
    fit's health say that the load rises before any stage starts, and ask about the time base. The examples as
    shipped, and 168 synthetic tests of every scenario and hidden effect (checked when the rule was set), have
    no such warning. Before, the shifted Drogue ran to its 20,000-step cap (R-hat 1.7) with nothing naming it."""
    from pathlib import Path

    from cpas_bayes.data.bundle_notes import load_before_first_stage
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit_health import reading_health_warnings

    folder = example_dir("drogue-clean", "shifted")
    assert load_before_first_stage(read_bundle(folder)) is None
    lines = (folder / "data.csv").read_text().splitlines()
    for i, line in enumerate(lines[1:], 1):
        cells = line.split(",")
        cells[0] = repr(round(float(cells[0]) - 5.0, 6))
        lines[i] = ",".join(cells)
    (folder / "data.csv").write_text("\n".join(lines) + "\n")
    assert main(["validate", str(folder)]) == 0
    said = capsys.readouterr().out
    assert "the accelerometer's load rises before any stage starts: at -3.7" in said
    assert "before the first stated stage start ('reefed 1' at 1.038 s, 1-sigma 0.1 s)" in said
    assert "on the time base of data.csv's time column?" in said
    test = read_bundle(folder)
    assert load_before_first_stage(test) in reduce_test(test).warnings
    assert [w["code"] for w in reading_health_warnings(test)] == ["load_before_first_stage"]

    logger = Path(__file__).parent.parent / "docs" / "examples" / "logger-drop"
    assert load_before_first_stage(read_bundle(logger)) is None
    folder = Path(shutil.copytree(logger, folder.parent / "late-start"))
    toml = (folder / "test.toml").read_text()
    (folder / "test.toml").write_text(toml.replace("start = 1.818", "start = 19.9"))
    said = load_before_first_stage(read_bundle(folder))
    assert said is not None and "before the first stated stage start ('full open' at 19.900 s" in said


@pytest.mark.parametrize("scenario", ["drogue", "main"])
@pytest.mark.parametrize("effect", ["none", "friction_drift", "load_cell_tare_shift", "accelerometer_clipping"])
def test_synthetic_tests_get_no_reading_warnings(scenario, effect):
    """The reading warnings (a clipped accelerometer, a dead load cell, a load before the first stage) stay
    silent on synthetic tests whose readings are sound: clean, a drifting friction, a load cell's tare shift.
    An accelerometer clipped before its noise (a clip the diagnosis is to find, not a flat top) is said only as
    an accelerometer that the airspeed's rate contradicts (data.kinematics)."""
    from cpas_bayes.data.bundle_notes import reading_notes
    from cpas_bayes.data.synth import synthesize

    for seed in (0, 1):
        test, _ = synthesize(scenario, effect, seed)
        codes = [code for code, _, _ in reading_notes(test)]
        expected = ["accelerometer_kinematics"] if effect == "accelerometer_clipping" else []
        assert codes == expected, (scenario, effect, seed)


@pytest.mark.parametrize("column, factor, what", [("qbar", 0.04788, "a US qbar written in kPa"),
                                                  ("airspeed", 0.5925, "a US airspeed written in knots"),
                                                  ("airspeed", 0.84, "an equivalent airspeed at 11,700 ft")])
def test_air_data_in_another_unit_is_said(example_dir, capsys, column, factor, what):
    """The Main example with one air-data channel in another unit passes every range check; ``validate``, ``reduce``
    and the fit's health say that qbar is not ½·density·airspeed² and name the units to check. The examples
    (ratio 1.000) are silent, and so is a sensor error of 10 %."""
    from cpas_bayes.data.bundle_notes import air_data_mismatch
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit_health import reading_health_warnings

    test = read_bundle(example_dir("main-clean", "air"))
    assert air_data_mismatch(test) is None
    test.data["qbar"] = 1.1 * np.asarray(test.data["qbar"], float)
    assert air_data_mismatch(test) is None
    test.data["qbar"] = np.asarray(test.data["qbar"], float) / 1.1
    test.data[column] = factor * np.asarray(test.data[column], float)
    said = air_data_mismatch(test)
    ratio = 1 / factor if column == "qbar" else factor ** 2
    assert said is not None and said.startswith(f"data.csv qbar is {1 / ratio:.3g}× ½·density·airspeed²"), what
    assert "Check the units of qbar, density and airspeed against the bundle's units (US)" in said
    assert said in reduce_test(test).warnings
    codes = [w["code"] for w in reading_health_warnings(test)]   # a kPa q̄ also gives a drag coefficient of ~13
    assert codes == (["air_data_units", "drag_coefficient"] if column == "qbar" else ["air_data_units"])


def test_a_flyout_angle_from_the_horizontal_is_said(example_dir):
    """The Main example's fly-out angle of M1 written as its complement (from the horizontal): the reading
    warnings and the fit's health name the column and the angle to write; the example (8-15°) is silent."""
    from cpas_bayes.data.bundle_notes import reading_warnings, wide_flyout_angles
    from cpas_bayes.inference.fit_health import reading_health_warnings

    test = read_bundle(example_dir("main-clean", "angles"))
    assert wide_flyout_angles(test) == [] and reading_warnings(test) == []
    theta = np.asarray(test.data["theta_M1"], float)
    test.data["theta_M1"] = 90.0 - theta
    (column, said), = wide_flyout_angles(test)
    after = np.asarray(test.data["time"]) >= test.parachutes[0].stages[0].start
    median = float(np.median(90.0 - theta[after]))
    assert column == "theta_M1" and f"reads {median:.1f}°" in said
    assert f"write 90° minus it: {90 - median:.1f}°" in said
    assert said in reading_warnings(test)
    assert [(w["code"], w["parameter"]) for w in reading_health_warnings(test)] == [("flyout_angle", "theta_M1")]


def test_a_drag_coefficient_no_canopy_has_is_said(example_dir):
    """The two-Drogue example with G in m/s² (its cluster then reads a drag coefficient of ~6), or its diameters
    written 3.28× (feet where metres: ~0.06): the reading warnings and the fit's health say that a unit is off;
    the example itself (0.64) is silent."""
    from cpas_bayes.data.bundle_notes import implausible_drag_coefficient
    from cpas_bayes.inference.fit_health import reading_health_warnings

    folder = example_dir("drogue-clean", "units")
    test = read_bundle(folder)
    assert implausible_drag_coefficient(test) is None
    test.data["G"] = 9.80665 * np.asarray(test.data["G"], float)
    said = implausible_drag_coefficient(test)
    assert said is not None and re.search(r"give the cluster a drag coefficient of 6\.\d+ on the constructed", said)
    assert "G in m/s² or ft/s² rather than g" in said
    assert [w["code"] for w in reading_health_warnings(test)] == ["drag_coefficient"]
    toml = (folder / "test.toml").read_text()
    (folder / "test.toml").write_text(toml.replace("diameter = 23.00", "diameter = 75.46"))
    said = implausible_drag_coefficient(read_bundle(folder))
    assert said is not None and re.search(r"a drag coefficient of 0\.0\d+ ", said) and "a diameter in ft" in said
    # one parachute's diameter in metres in a US bundle: the cluster reads 1.2, that parachute's load cell 6.9
    (folder / "test.toml").write_text(toml.replace("diameter = 23.00", "diameter = 7.01", 1))
    said = implausible_drag_coefficient(read_bundle(folder))
    assert said is not None and re.search(r"give parachute 'D3' \(its load cell\) a drag coefficient of 6\.\d+ ", said)
    assert "give the cluster" not in said and "a diameter in m in a US bundle" in said


def test_fit_says_the_reading_warnings_before_it_samples(example_dir, tmp_path, capsys, monkeypatch):
    """``cpas-bayes fit`` prints what the readings show (here a load cell zeroed) before the sampling starts, not
    only in the health warnings at its end: the sampling is stopped at its start, and the warning was said."""
    import cpas_bayes.inference.fit as fit_module
    from cpas_bayes.core.errors import InputError

    folder = example_dir("drogue-clean", "dead-cell-fit")
    lines = (folder / "data.csv").read_text().splitlines()
    column = lines[0].split(",").index("F_D3")
    lines[1:] = [",".join(cells[:column] + ["0"] + cells[column + 1:])
                 for cells in (line.split(",") for line in lines[1:])]
    (folder / "data.csv").write_text("\n".join(lines) + "\n")

    def stop(*args, **kwargs):
        raise InputError(folder, "", "stopped where the sampling starts", "nothing")

    monkeypatch.setattr(fit_module, "fit_model", stop)
    assert main(["fit", str(folder), "--out", str(tmp_path / "fit"), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert err.index("warning: data.csv F_D3, the load cell of parachute 'D3', stays within its noise") \
        < err.index("stopped where the sampling starts")

"""Every command's options, campaign configs and damaged result folders are refused before any work.

A refusal is exit status 2, one message naming the option (or the file and
key), no traceback, and nothing written: the ``--out`` folder is absent, or
unchanged when it existed. Damaged fit folders and memos are refused by file
and key (or row) with what to re-run. The Monte Carlo refuses a run count
beyond its memory budget up front, in well under a second.
"""

from __future__ import annotations

import itertools
import json
import pickle
import re
import shutil
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cpas_bayes.app import campaign as cp
from cpas_bayes.app.campaign_steps import load_baseline_fit
from cpas_bayes.app import campaign_config as cfg
from cpas_bayes.app.cli import main
from cpas_bayes.core import resources
from cpas_bayes.core.errors import BundleError, InputError
from cpas_bayes.core.files import atomic_path, write_text
from cpas_bayes.core.executor import MAX_LOCAL_WORKERS
from cpas_bayes.core.scheduler_address import scheduler_problem
from cpas_bayes.data.bundle import EXAMPLES_DIR, read_bundle
from cpas_bayes.inference.fit_folder import load_fit
from cpas_bayes.loads.budget import MAX_RUNS, run_bytes, table_bytes
from cpas_bayes.loads.montecarlo import ClusterLayout
from cpas_bayes.population.memo import load_memo

from test_montecarlo import drogue_spec, hand_memo
from test_pool import write_fit_folder

DROGUE = EXAMPLES_DIR / "drogue-clean"
LOGGER_DROP = Path(__file__).parent.parent / "docs" / "examples" / "logger-drop"
SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def closed_port():
    """A local TCP port nobody listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def files(tmp_path_factory):
    """Inputs built once: a memo (drogue, with t_fp), a fit folder of the drogue example, a bad TOML."""
    root = tmp_path_factory.mktemp("inputs")
    t_fp = {"first": (0.3, 3.0), "full_open": (0.3, 3.0)}
    hand_memo(drogue_spec(t_fp=t_fp)).write(root / "memo")
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit import prepare_model

    test = read_bundle(DROGUE)
    write_fit_folder(root / "fit", prepare_model(test, reduce_test(test)), np.random.default_rng(3), test.name, seed=1,
                     n_draws=200)
    (root / "bad.toml").write_text("x = [\n")
    (root / "latin1.toml").write_bytes("name = 'Düse'\n".encode("latin-1"))
    (root / "a-file").write_text("not a folder\n")
    from cpas_bayes.core.files import atomic_path
    from cpas_bayes.core.ownership import claim_folder

    claim_folder(root / "fit_out")      # a fit command's output, as far as --out checks see it
    with atomic_path(root / "fit_out" / "posterior.nc") as tmp:
        tmp.write_bytes(b"")
    (root / "dangling").symlink_to(root / "nowhere")
    (root / "loop1").symlink_to(root / "loop2")
    (root / "loop2").symlink_to(root / "loop1")
    return root


@pytest.fixture(scope="session")
def fresh(tmp_path_factory):
    """``fresh()``: a new path that does not exist yet (for --out), also across hypothesis examples."""
    base = tmp_path_factory.mktemp("outs")
    counter = itertools.count()
    return lambda: base / f"out{next(counter)}"


def run(capsys, argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err and "internal error" not in out + err
    return code, out, err


def refused(capsys, argv, out, *needles):
    """Run ``argv``; assert exit 2, each needle in the message, and ``out`` never created."""
    code, stdout, err = run(capsys, argv)
    assert code == 2, (argv, stdout, err)
    for needle in needles:
        assert needle in err, (needle, err)
    assert not Path(out).exists(), f"{out} was written"
    return err


# ---------------------------------------------------------------------------
# every command's options, table-driven: (command line before --out, the option's name in the message)

def bad_options(f):
    """(id, argv with OUT for the output folder, what the message must name)."""
    port = closed_port()
    unreachable = f"tcp://127.0.0.1:{port}"
    mc = ["montecarlo", "--memo", f / "memo", "--like", DROGUE, "--out", "OUT"]
    cmp = ["compare", DROGUE, "--memo", f / "memo", "--out", "OUT"]
    fit = ["fit", DROGUE, "--out", "OUT"]
    diag = ["diagnose", DROGUE, "--out", "OUT"]
    camp = ["campaign", EXAMPLES_DIR, "--out", "OUT"]
    synth = ["synth", "--scenario", "drogue", "--seed", "1", "--out", "OUT"]
    return [
        ("reduce --scale", ["reduce", DROGUE, "--out", "OUT", "--scale", "quadratic"], "--scale"),
        ("reduce --window infinite", ["reduce", DROGUE, "--out", "OUT", "--window=-inf:5"], "must be finite"),
        ("reduce --window nan", ["reduce", DROGUE, "--out", "OUT", "--window", "nan:3"], "--window nan:3"),
        ("reduce --window reversed", ["reduce", DROGUE, "--out", "OUT", "--window", "5:1"], "--window 5:1"),
        ("reduce --out is a file", ["reduce", DROGUE, "--out", f / "a-file"], "--out"),
        ("reduce --out under a file", ["reduce", DROGUE, "--out", f / "a-file" / "x"], "--out"),
        ("reduce --out a broken link", ["reduce", DROGUE, "--out", f / "dangling"], "is a link to nothing"),
        ("reduce --out empty", ["reduce", DROGUE, "--out", ""], "an empty path"),
        ("fit --out blank", ["fit", DROGUE, "--out", "  "], "an empty path"),
        ("montecarlo --out a fit folder", mc[:-1] + [f / "fit_out"], "holds the output of 'cpas-bayes fit' (posterior.nc)"),
        ("pool --out a fit folder", ["pool", f / "fit", f / "fit", "--out", f / "fit_out"],
         "holds the output of 'cpas-bayes fit'"),
        ("fit --out a memo folder", fit[:-1] + [f / "memo"], "holds the output of 'cpas-bayes pool' (memo.toml)"),
        ("fit --out a loop of links", fit + ["--out", f / "loop1"], "a loop of links"),
        ("fit --priors a loop of links", fit + ["--priors", f / "loop1"], "a loop of links"),
        ("synth --magnitude nan", synth + ["--effect", "added_mass", "--magnitude", "nan"], "--magnitude"),
        ("synth --magnitude inf", synth + ["--effect", "sensor_lag", "--magnitude", "inf"], "--magnitude"),
        ("synth --magnitude -inf", synth + ["--effect", "friction_drift", "--magnitude", "-inf"], "--magnitude"),
        ("synth --magnitude too large", synth + ["--effect", "sensor_lag", "--magnitude", "100"], "--magnitude"),
        ("synth --magnitude negative", synth + ["--effect", "added_mass", "--magnitude", "-0.1"], "--magnitude"),
        ("synth --magnitude without effect", synth + ["--magnitude", "0.1"], "--magnitude"),
        ("synth --seed negative", ["synth", "--scenario", "drogue", "--seed", "-1", "--out", "OUT"], "--seed"),
        ("synth --seed beyond 64 bits", ["synth", "--scenario", "drogue", "--seed", str(2**63), "--out", "OUT"],
         "--seed"),
        ("fit --ensembles 0", fit + ["--ensembles", "0"], "--ensembles"),
        ("fit --ensembles 1000", fit + ["--ensembles", "1000"], "--ensembles"),
        ("fit --stop unknown", fit + ["--stop", "rhat"], "--stop"),
        ("fit --ess-target 0", fit + ["--stop", "ess", "--ess-target", "0"], "--ess-target"),
        ("fit --ess-target beyond", fit + ["--stop", "ess", "--ess-target", "1000000"], "--ess-target"),
        ("fit --ess-target with --stop tau", fit + ["--stop", "tau", "--ess-target", "1000"], "--ess-target"),
        ("fit --with unknown", fit + ["--with", "discrepency"], "did you mean 'discrepancy'"),
        ("fit --with twice", fit + ["--with", "discrepancy,discrepancy"], "discrepancy is given twice"),
        ("fit --with nothing", fit + ["--with", " , "], "--with"),
        ("fit --with a load-cell term where there are none",
         ["fit", LOGGER_DROP, "--out", "OUT", "--with", "discrepancy,friction_drift"],
         "friction_drift acts on load cells, and SYN-logger-drop-3 has none: leave it out"),
        ("fit --with a pasted list", fit + ["--with", ",".join(f"term{i}" for i in range(500))],
         "unknown extension(s) term0, term1, term2 and 497 more;"),
        ("fit --with two error models", fit + ["--with", "discrepancy,correlated_noise"],
         "discrepancy and correlated_noise each bring their own error model: give one of them"),
        ("fit --max-steps below one chunk", fit + ["--max-steps", "100"], "--max-steps"),
        ("fit --max-steps beyond", fit + ["--max-steps", "1000000"], "--max-steps"),
        ("fit with one ensemble (the ESS rule compares them)", fit + ["--ensembles", "1"], "--ensembles"),
        ("fit --stop ess with one ensemble", fit + ["--stop", "ess", "--ensembles", "1"], "--ensembles"),
        ("fit --workers 0", fit + ["--workers", "0"], "--workers"),
        ("fit --workers huge", fit + ["--workers", "100000"], "--workers"),
        ("fit --seed -1", fit + ["--seed", "-1"], "--seed"),
        ("fit --decay", fit + ["--decay", "cubic"], "--decay"),
        ("fit --priors missing", fit + ["--priors", f / "nowhere.toml"], "--priors"),
        ("fit --priors a folder", fit + ["--priors", f], "is a folder, not a file"),
        ("fit --priors not TOML", fit + ["--priors", f / "bad.toml"], "--priors"),
        ("fit --priors not UTF-8", fit + ["--priors", f / "latin1.toml"], "--priors"),
        ("fit --scheduler unreachable", fit + ["--scheduler", unreachable], "--scheduler"),
        ("fit --scheduler not an address", fit + ["--scheduler", "ftp://host:1"], "--scheduler"),
        ("fit --scheduler bad port", fit + ["--scheduler", "tcp://127.0.0.1:99999"], "--scheduler"),
        ("montecarlo --runs 0", mc + ["--runs", "0"], "--runs"),
        ("montecarlo --runs -5", mc + ["--runs", "-5"], "--runs"),
        ("montecarlo --runs 1e10", mc + ["--runs", "1e10"], "--runs"),
        ("montecarlo --runs 10^10", mc + ["--runs", "10000000000"], "--runs"),
        ("montecarlo --runs 10^8", mc + ["--runs", "100000000"], "--runs"),
        ("montecarlo --batch 0", mc + ["--batch", "0"], "--batch"),
        ("montecarlo --batch huge", mc + ["--batch", "10000000"], "--batch"),
        ("montecarlo --workers 0", mc + ["--workers", "0"], "--workers"),
        ("montecarlo --seed -1", mc + ["--seed", "-1"], "--seed"),
        ("montecarlo --mode", mc + ["--mode", "m"], "--mode"),
        ("montecarlo --scheduler", mc + ["--scheduler", unreachable], "--scheduler"),
        ("compare --runs 0", cmp + ["--runs", "0"], "--runs"),
        ("compare --runs huge", cmp + ["--runs", "99999999999"], "--runs"),
        ("compare --seed", cmp + ["--seed", "-3"], "--seed"),
        ("pool --seed", ["pool", f / "fit", "--out", "OUT", "--seed", "-1"], "--seed"),
        ("diagnose --candidates unknown", diag + ["--candidates", "sensor_lga"], "did you mean 'sensor_lag'"),
        ("diagnose --candidates twice", diag + ["--candidates", "sensor_lag,sensor_lag"], "--candidates"),
        ("diagnose --workers 0", diag + ["--workers", "0"], "--workers"),
        ("diagnose --priors", diag + ["--priors", f / "bad.toml"], "--priors"),
        ("diagnose --scheduler", diag + ["--scheduler", unreachable], "--scheduler"),
        ("campaign --workers 0", camp + ["--workers", "0"], "--workers"),
        ("campaign --diagnose", camp + ["--diagnose", "sometimes"], "--diagnose"),
        ("campaign --config missing", camp + ["--config", f / "nowhere.toml"], "--config"),
        ("campaign --scheduler", camp + ["--scheduler", unreachable], "--scheduler"),
        ("demo --out is a file", ["demo", "--out", f / "a-file"], "--out"),
    ]


CASES = [c[0] for c in bad_options(Path("/nonexistent"))]


@pytest.mark.parametrize("case", CASES)
def test_a_bad_option_is_refused_before_any_work(files, fresh, capsys, case):
    (_, argv, needle), = [c for c in bad_options(files) if c[0] == case]
    out = fresh()
    argv = [out if a == "OUT" else a for a in argv]
    started = time.perf_counter()
    err = refused(capsys, argv, out, needle)
    assert time.perf_counter() - started < 5.0    # refused up front (parse time), not after work
    assert "Error" in err or "error" in err


def test_an_existing_out_folder_is_left_unchanged(files, fresh, capsys, snapshot):
    out = fresh()
    write_text(out / "kept.txt", "from an earlier run\n")   # an earlier run's file: the folder is usable
    before = snapshot(out)
    code, _, err = run(capsys, ["montecarlo", "--memo", files / "memo", "--like", DROGUE, "--out", out,
                                "--runs", "0"])
    assert code == 2 and "--runs" in err
    code, _, err = run(capsys, ["fit", DROGUE, "--out", out, "--priors", files / "bad.toml"])
    assert code == 2 and "--priors" in err
    assert snapshot(out) == before


def test_unreachable_scheduler_is_refused_quickly():
    port = closed_port()
    started = time.perf_counter()
    problem = scheduler_problem(f"tcp://127.0.0.1:{port}")
    assert problem and f"127.0.0.1:{port}" in problem
    assert time.perf_counter() - started < 1.0
    assert scheduler_problem(None) is None and scheduler_problem("local") is None
    assert "protocol" in scheduler_problem("udp://x:1")
    assert "port" in scheduler_problem("tcp://host:notaport")


def test_a_refusal_raised_in_a_worker_travels_back_as_itself():
    for error in (InputError("memo.toml", "key 'x'", "bad", "re-run"), BundleError("b", "", "p", "f")):
        back = pickle.loads(pickle.dumps(error))
        assert type(back) is type(error) and str(back) == str(error) and back.fix == error.fix


# ---------------------------------------------------------------------------
# properties: any non-positive count or non-finite number is refused with exit 2, naming the option

COUNT_OPTIONS = [  # (argv before the option, option, the largest allowed value)
    (["montecarlo", "--memo", "MEMO", "--like", DROGUE], "--runs", MAX_RUNS),
    (["montecarlo", "--memo", "MEMO", "--like", DROGUE], "--batch", 100_000),
    (["montecarlo", "--memo", "MEMO", "--like", DROGUE], "--workers", MAX_LOCAL_WORKERS),
    (["compare", DROGUE, "--memo", "MEMO"], "--runs", MAX_RUNS),
    (["fit", DROGUE], "--ensembles", 16),
    (["fit", DROGUE], "--workers", MAX_LOCAL_WORKERS),
    (["diagnose", DROGUE], "--workers", MAX_LOCAL_WORKERS),
    (["campaign", EXAMPLES_DIR], "--workers", MAX_LOCAL_WORKERS),
]


@settings(max_examples=60, **SETTINGS)
@given(which=st.integers(0, len(COUNT_OPTIONS) - 1),
       value=st.one_of(st.integers(max_value=0), st.integers(min_value=MAX_RUNS + 1, max_value=2**70),
                       st.sampled_from(["nan", "inf", "-inf", "1e10", "2.5", "", "ten"])))
def test_any_non_positive_or_non_finite_count_is_refused(files, fresh, capsys, which, value):
    head, option, largest = COUNT_OPTIONS[which]
    if isinstance(value, int) and 1 <= value <= largest:
        return
    out = fresh()
    argv = [files / "memo" if a == "MEMO" else a for a in head] + ["--out", out, option, str(value)]
    refused(capsys, argv, out, option)


@settings(max_examples=40, **SETTINGS)
@given(effect=st.sampled_from(["added_mass", "friction_drift", "sensor_lag", "canopy_breathing"]),
       value=st.one_of(st.sampled_from(["nan", "NaN", "inf", "+inf", "-inf", "1e309"]),
                       st.floats(min_value=1e3, allow_infinity=False), st.floats(max_value=-1.0,
                                                                               allow_infinity=False)))
def test_any_non_finite_or_far_out_magnitude_is_refused(fresh, capsys, effect, value):
    out = fresh()
    refused(capsys, ["synth", "--scenario", "main", "--effect", effect, "--magnitude", str(value), "--seed", "1",
                     "--out", out], out, "--magnitude")


CONFIG_NUMBERS = {  # TOML key -> (table, key)
    "seed": ((), "seed"), "workers": ((), "workers"), "fit.ensembles": (("fit",), "ensembles"),
    "fit.max_steps": (("fit",), "max_steps"), "fit.check_every": (("fit",), "check_every"),
    "fit.tau_factor": (("fit",), "tau_factor"), "fit.ess_target": (("fit",), "ess_target"), "montecarlo.runs": (("montecarlo",), "runs"),
    "compare.runs": (("compare",), "runs"), "pool.draws": (("pool",), "draws"),
}


@settings(max_examples=80, **SETTINGS)
@given(key=st.sampled_from(sorted(CONFIG_NUMBERS)),
       value=st.one_of(st.integers(max_value=-1), st.sampled_from(["nan", "inf", "-inf", "0.5", "true", '"3"']),
                       st.integers(min_value=MAX_RUNS + 1, max_value=2**63 - 1)))
def test_any_bad_number_in_a_campaign_config_is_refused_naming_the_key(fresh, key, value):
    table, name = CONFIG_NUMBERS[key]
    if key == "fit.tau_factor" and (value == "0.5" or isinstance(value, int) and value > 0):
        return                                         # any positive finite number is a fine tau factor
    if key == "seed" and isinstance(value, int) and value >= 0:
        return
    text = (f"[{table[0]}]\n" if table else "") + f"{name} = {value}\n"
    path = fresh().with_suffix(".toml")
    path.write_text(text)
    with pytest.raises(InputError) as err:
        cfg.load_config(path)
    assert str(path) in str(err.value) and f"key '{key}'" in str(err.value)


# ---------------------------------------------------------------------------
# campaign configs: checked at load time, before the folder is even read

@pytest.mark.parametrize("text,needles", [
    ("workers = 0\n", ["key 'workers'", "outside 1"]),
    ("[fit]\ncheck_every = 0\n", ["key 'fit.check_every'"]),
    ("[fit]\nensembles = 0\n", ["key 'fit.ensembles'"]),
    ("[fit]\ntau_factor = nan\n", ["key 'fit.tau_factor'", "finite"]),
    ("[fit]\nstop = 'tua'\n", ["key 'fit.stop'", "did you mean 'tau'"]),
    ("[fit]\nensembles = 1\n", ["key 'fit.ensembles'", "2 or more ensembles", "fit.stop = \"tau\""]),
    ("[fit]\ntau_factor = 20\n", ["key 'fit.tau_factor'", "only with fit.stop = \"tau\""]),
    ("[fit]\nstop = 'tau'\ness_target = 500\n", ["key 'fit.ess_target'", "only with fit.stop = \"ess\""]),
    ("[fit]\nmax_steps = 200\ncheck_every = 500\n", ["check_every 500 is more than max_steps 200"]),
    ("[fit]\nensemble = 2\n", ["key 'fit.ensemble'", "did you mean 'fit.ensembles'"]),
    ("wokers = 2\n", ["key 'wokers'", "did you mean 'workers'"]),
    ("[montecarlo]\nrun = 10\n", ["did you mean 'montecarlo.runs'"]),
    ("fit = 3\n", ["key 'fit'", "must be a table"]),
    ("[montecarlo]\nruns = 0\n", ["key 'montecarlo.runs'"]),
    ("[montecarlo]\nruns = 100000000\n", ["key 'montecarlo.runs'"]),
    ("[compare]\nruns = -1\n", ["key 'compare.runs'"]),
    ("[pool]\ndraws = 1\n", ["key 'pool.draws'"]),
    ("seed = -1\n", ["key 'seed'"]),
    ("seed = 1.5\n", ["key 'seed'", "whole number"]),
    ("[diagnose]\ncandidates = []\n", ["key 'diagnose.candidates'"]),
    ("[diagnose]\ncandidates = ['sensor_lag', 'sensor_lag']\n", ["listed twice"]),
    ("[diagnose]\nmode = 'scren'\n", ["key 'diagnose.mode'", "did you mean 'screen'"]),
    ("priors = 'nowhere.toml'\n", ["key 'priors'", "nowhere.toml", "not found"]),
    ("priors = 'bad.toml'\n", ["key 'priors'", "bad.toml", "not valid TOML"]),
    ("decay = 3\n", ["key 'decay'"]),
    ("x = [\n", ["not valid TOML"]),
])
def test_a_bad_campaign_config_is_refused_before_any_work(files, fresh, capsys, text, needles):
    folder = fresh()
    folder.mkdir()
    config = folder / "campaign.toml"
    config.write_text(text)
    shutil.copy(files / "bad.toml", folder / "bad.toml")
    out = fresh()
    err = refused(capsys, ["campaign", EXAMPLES_DIR, "--out", out, "--config", config, "--workers", "1"], out,
                  str(config), *needles)
    assert len(err.strip().splitlines()) == 1


def test_the_documented_config_keeps_every_key_in_range(tmp_path):
    path = tmp_path / "campaign.toml"
    path.write_text(cfg.CONFIG_EXAMPLE)
    config = cfg.load_config(path)
    assert config.fit_check_every == 500 and config.workers == 2


# ---------------------------------------------------------------------------
# memory: a run count beyond the budget is refused before anything is drawn or written

def test_runs_beyond_the_memory_budget_are_refused_in_well_under_a_second(files, fresh, capsys, monkeypatch):
    monkeypatch.setattr(resources, "available_memory", lambda: 200_000_000)   # 200 MB: budget 100 MB
    out = fresh()
    import importlib

    for name in ("cpas_bayes.loads.fill_time", "cpas_bayes.outputs.montecarlo"):   # loaded before timing
        importlib.import_module(name)
    started = time.perf_counter()
    err = refused(capsys, ["montecarlo", "--memo", files / "memo", "--like", DROGUE, "--runs", "5000000",
                           "--out", out], out, "option --runs 5000000", "100.0 MB", "give at most")
    assert time.perf_counter() - started < 1.0
    allowed = int(re.search(r"give at most ([\d,]+) runs", err).group(1).replace(",", ""))
    layout = ClusterLayout.from_test(read_bundle(DROGUE))
    assert allowed * run_bytes(layout) + table_bytes(layout, allowed) <= 100_000_000
    assert 50_000 < allowed < 100_000           # ≈ 1.04 kB per Drogue run, and a 24 MB table slice
    # --compare-np keeps three results: fewer runs fit
    err = refused(capsys, ["montecarlo", "--memo", files / "memo", "--like", DROGUE, "--runs", "120000",
                           "--compare-np", "--out", out], out, "--runs")
    # and the comparison of memo and fit, two results
    refused(capsys, ["compare", DROGUE, "--memo", files / "memo", "--fit", files / "fit", "--runs", "90000",
                     "--out", out], out, "option --runs 90000")


def test_a_campaign_refuses_its_run_counts_before_any_step(files, fresh, capsys, monkeypatch):
    monkeypatch.setattr(resources, "available_memory", lambda: 200_000_000)
    config = fresh().with_suffix(".toml")
    config.write_text("[montecarlo]\nruns = 1000000\n")
    out = fresh()
    refused(capsys, ["campaign", EXAMPLES_DIR, "--out", out, "--config", config, "--workers", "1"], out,
            "key 'montecarlo.runs'", "give at most")


PEAK_GROWTH = """
import sys
from cpas_bayes.app.cli import main

def vm(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise SystemExit("no " + key)

def growth(argv):
    # the peak resident memory above the level before the run (VmHWM reset by clear_refs 5)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    base = vm("VmRSS")
    code = main(argv)
    return code, vm("VmHWM") - base

out, runs = sys.argv[1], sys.argv[2]
common = sys.argv[3:]
main([*common, "--runs", "1000", "--out", out + "-warm"])  # imports, compiled kernels, figure fonts: loaded once
codes, grown = zip(*(growth([*common, "--runs", n, "--out", out + "-" + n]) for n in ("1000", runs)))
print(max(codes), grown[1] - grown[0])
"""


@pytest.mark.slow
def test_the_memory_estimate_bounds_the_measured_peak(files, fresh):
    """Peak resident memory of a real Monte Carlo, above that of a 1,000-run one, is within the estimate.

    Both are measured in one process after a warm-up run, as the growth of the peak (VmHWM, reset
    before each run) above the resident memory before it: what imports, the compiled kernels'
    first load and the first figure cost is not the runs' memory (and differs between a fresh clone
    and a warm cache).
    """
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    runs = 100_000
    argv = ["montecarlo", "--memo", files / "memo", "--like", DROGUE]
    proc = subprocess.run([sys.executable, "-c", PEAK_GROWTH, str(fresh()), str(runs), *map(str, argv)],
                          capture_output=True, text=True, env=env, timeout=1800)
    code, grown = proc.stdout.split()[-2:]
    assert code == "0", proc.stderr
    layout = ClusterLayout.from_test(read_bundle(DROGUE))
    estimate = runs * run_bytes(layout) + table_bytes(layout, runs)
    assert 0 < int(grown) <= estimate
    assert int(grown) > 0.4 * estimate      # and not a wild over-estimate


def test_the_library_refuses_too_many_runs_too(files):
    from cpas_bayes.loads.montecarlo import run_monte_carlo

    memo = load_memo(files / "memo")
    with pytest.raises(InputError, match="1 to 10,000,000"):
        run_monte_carlo(memo, read_bundle(DROGUE), MAX_RUNS + 1, np.random.default_rng(0))
    with pytest.raises(InputError, match="argument runs"):
        run_monte_carlo(memo, read_bundle(DROGUE), 0, np.random.default_rng(0))


# ---------------------------------------------------------------------------
# damaged fit folders: refused by file and key, with what to re-run

def _edit_summary(change):
    def damage(folder):
        doc = json.loads((folder / "summary.json").read_text())
        change(doc)
        (folder / "summary.json").write_text(json.dumps(doc))
    return damage


def _truncate(name, keep=0.5):
    def damage(folder):
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[: int(len(data) * keep)])
    return damage


FIT_DAMAGE = {  # case: (damage, file, text in the message)
    "posterior truncated": (_truncate("posterior.nc"), "posterior.nc", "not a readable netCDF posterior"),
    "posterior empty": (_truncate("posterior.nc", 0), "posterior.nc", "empty"),
    "posterior garbage": (lambda d: (d / "posterior.nc").write_bytes(b"\x89HDF garbage" * 50), "posterior.nc",
                          "not a readable"),
    "summary garbage": (lambda d: (d / "summary.json").write_text("{'test': 1"), "summary.json", "not valid JSON"),
    "summary truncated": (_truncate("summary.json"), "summary.json", "not valid JSON"),
    "summary empty": (_truncate("summary.json", 0), "summary.json", "empty"),
    "summary not an object": (lambda d: (d / "summary.json").write_text("[1, 2]"), "summary.json", "not an object"),
    "summary binary": (lambda d: (d / "summary.json").write_bytes(b"\xff\xfe\x00\x01"), "summary.json", "UTF-8"),
    "summary without priors": (_edit_summary(lambda s: s.pop("priors")), "summary.json", "key 'priors'"),
    "summary without parachutes": (_edit_summary(lambda s: s.pop("parachutes")), "summary.json",
                                   "key 'parachutes'"),
    "summary stage without key": (_edit_summary(lambda s: s["parachutes"]["D3"]["stages"][0].pop("key")),
                                  "summary.json", "key 'parachutes.D3.stages[0].key'"),
    "summary diameter as text": (_edit_summary(lambda s: s["parachutes"]["D3"].update(diameter_m="big")),
                                 "summary.json", "key 'parachutes.D3.diameter_m'"),
    "summary test name a path": (_edit_summary(lambda s: s.update(test="../x")), "summary.json", "key 'test'"),
    "summary prior without family": (_edit_summary(lambda s: s["priors"]["D3.s1.n_p"].pop("family")),
                                     "summary.json", "key 'priors.D3.s1.n_p'"),
    "summary prior of a missing draw": (
        _edit_summary(lambda s: s["priors"].update({"D3.s9.n_p": s["priors"]["D3.s1.n_p"]})), "posterior.nc",
        "variable 'D3.s9.n_p'"),
}


@pytest.fixture
def damaged_fit(files, fresh):
    def make(case):
        folder = Path(shutil.copytree(files / "fit", fresh()))
        FIT_DAMAGE[case][0](folder)
        return folder
    return make


@pytest.mark.parametrize("case", FIT_DAMAGE)
def test_a_damaged_fit_folder_is_refused_by_name(damaged_fit, case):
    folder = damaged_fit(case)
    _, name, text = FIT_DAMAGE[case]
    with pytest.raises(InputError) as err:
        load_fit(folder)
    message = str(err.value)
    assert message.startswith(str(folder / name)) and text in message
    assert f"re-run 'cpas-bayes fit BUNDLE --out {folder}'" in message


@pytest.mark.parametrize("case", ["posterior truncated", "summary garbage", "summary without priors"])
def test_pool_and_compare_refuse_a_damaged_fit_folder(files, damaged_fit, fresh, capsys, case):
    folder = damaged_fit(case)
    out = fresh()
    refused(capsys, ["pool", files / "fit", folder, "--out", out], out, str(folder), "re-run 'cpas-bayes fit")
    refused(capsys, ["compare", DROGUE, "--fit", folder, "--out", out], out, str(folder))


# ---------------------------------------------------------------------------
# hand-edited memos: refused by file and key or row, with what to re-run

def _toml(old, new):
    def damage(folder):
        path = folder / "memo.toml"
        text = path.read_text()
        assert old in text
        path.write_text(text.replace(old, new, 1))
    return damage


def _draws(edit):
    def damage(folder):
        path = folder / "memo_draws.csv"
        path.write_text(edit(path.read_text()))
    return damage


def _cell(row, column, value):
    def edit(text):
        lines = text.splitlines()
        header = lines[0].split(",")
        cells = lines[row - 1].split(",")
        cells[header.index(column)] = value
        lines[row - 1] = ",".join(cells)
        return "\n".join(lines) + "\n"
    return edit


CK_PARAMS = "[drogue.first.ck.params]\nlow = 1.2\nhigh = 1.45\n"
CK_BOUNDS = "bounds = [\n    1.2,\n    1.45,\n]"
MEMO_DAMAGE = {  # case: (damage, file, where, text)
    "family without params": (_toml(CK_PARAMS, ""), "memo.toml", "key 'drogue.first.ck.params'", "missing"),
    "bounds as text": (_toml(CK_BOUNDS, 'bounds = "1.2 to 1.45"'), "memo.toml", "key 'drogue.first.ck.bounds'",
                       "[low, high]"),
    "bounds reversed": (_toml(CK_BOUNDS, "bounds = [1.45, 1.2]"), "memo.toml", "key 'drogue.first.ck.bounds'",
                        "not below"),
    "family that does not exist": (_toml('family = "uniform"', 'family = "gamma"'), "memo.toml",
                                   "key 'drogue.first.ck.family'", "unknown family 'gamma'"),
    "family misspelt": (_toml('family = "uniform"', 'family = "unifrom"'), "memo.toml",
                        "key 'drogue.first.ck.family'", "did you mean 'uniform'"),
    "param nan": (_toml(CK_PARAMS, CK_PARAMS.replace("1.2", "nan")), "memo.toml",
                  "key 'drogue.first.ck.params.low'", "finite"),
    "param inf": (_toml(CK_PARAMS, CK_PARAMS.replace("1.45", "inf")), "memo.toml",
                  "key 'drogue.first.ck.params.high'", "finite"),
    "param as text": (_toml(CK_PARAMS, CK_PARAMS.replace("1.2", "'low'")), "memo.toml",
                      "key 'drogue.first.ck.params.low'", "finite number"),
    "entry not a table": (_toml(CK_PARAMS, CK_PARAMS + "\n[drogue.reefed1]\nck = 3\n"), "memo.toml",
                          "key 'drogue.reefed1.ck'", "must be a table"),
    "unknown stage": (_toml(CK_PARAMS, CK_PARAMS + "\n[drogue.frist.ck]\nfamily = 'normal'\n"), "memo.toml",
                      "key 'drogue.frist'", "did you mean 'first'"),
    "memo not TOML": (lambda d: (d / "memo.toml").write_text("[drogue\n"), "memo.toml", "", "not valid TOML"),
    "memo binary": (lambda d: (d / "memo.toml").write_bytes(b"\xff\xfe\x00"), "memo.toml", "", "not UTF-8"),
    "draws wrong columns": (_draws(lambda t: "a,b\n1,2\n"), "memo_draws.csv", "column 'kind'", "missing"),
    "draws unknown column": (_draws(lambda t: t.replace("first.ck", "first.cx", 1)), "memo_draws.csv",
                             "column 'first.cx'", "<stage>.<parameter>"),
    "draws text in numbers": (_draws(_cell(4, "first.ck", "abc")), "memo_draws.csv",
                              "row 4, column 'first.ck'", "'abc' is not a finite number"),
    "draws infinity": (_draws(_cell(7, "first.n_p", "inf")), "memo_draws.csv", "row 7, column 'first.n_p'",
                       "not a finite number"),
    "draws hole": (_draws(_cell(9, "first.expopen", "")), "memo_draws.csv", "row 9, column 'first.expopen'",
                   "empty for kind 'drogue'"),
    "draws unknown kind": (_draws(_cell(3, "kind", "pilot")), "memo_draws.csv", "row 3, column 'kind'",
                           "no entries in memo.toml"),
    "draws empty": (_draws(lambda t: ""), "memo_draws.csv", "", "empty"),
    "draws header only": (_draws(lambda t: t.splitlines()[0] + "\n"), "memo_draws.csv", "", "no rows"),
    "draws missing": (lambda d: (d / "memo_draws.csv").unlink(), "memo_draws.csv", "", "missing"),
}


@pytest.fixture
def damaged_memo(files, fresh):
    def make(case):
        folder = Path(shutil.copytree(files / "memo", fresh()))
        MEMO_DAMAGE[case][0](folder)
        return folder
    return make


@pytest.mark.parametrize("case", MEMO_DAMAGE)
def test_a_hand_edited_memo_is_refused_by_name(damaged_memo, case):
    folder = damaged_memo(case)
    _, name, where, text = MEMO_DAMAGE[case]
    with pytest.raises(InputError) as err:
        load_memo(folder)
    message = str(err.value)
    assert message.startswith(str(folder / name) + (f", {where}" if where else "")), message
    assert text in message
    assert f"re-run 'cpas-bayes pool FITDIR... --out {folder}'" in message


@pytest.mark.parametrize("case", ["bounds reversed", "draws text in numbers", "draws empty"])
def test_montecarlo_and_compare_refuse_a_damaged_memo(damaged_memo, fresh, capsys, case):
    folder = damaged_memo(case)
    out = fresh()
    refused(capsys, ["montecarlo", "--memo", folder, "--like", DROGUE, "--runs", "10", "--out", out], out,
            str(folder), "re-run 'cpas-bayes pool")
    refused(capsys, ["compare", DROGUE, "--memo", folder / "memo.toml", "--out", out], out, str(folder))


def test_the_intact_inputs_still_load(files):
    memo = load_memo(files / "memo")
    assert ("drogue", "first", "ck") in memo.entries and len(memo.draws) == 4000
    fit = load_fit(files / "fit")
    assert fit.test == "EX-drogue" and fit.draws["D3.s1.n_p"].size == 200


def test_a_campaign_refuses_its_damaged_fit_and_diagnosis_files(files, fresh):
    from cpas_bayes.data.reduction import reduce_test

    out = fresh()
    fit = Path(shutil.copytree(files / "fit", out / "tests" / "EX-drogue" / "fit"))
    test = read_bundle(DROGUE)
    for text, where in (("{\"names\": [", "not valid JSON"), ("{\"names\": []}", "key 'names'")):
        (fit / "map.json").write_text(text)
        with pytest.raises(InputError) as err:
            load_baseline_fit(test, reduce_test(test), fit, cp.CampaignConfig())
        assert str(fit / "map.json") in str(err.value) and where in str(err.value)
        assert f"delete {fit}" in str(err.value)
    diagnosis = out / "tests" / "EX-drogue" / "diagnosis"
    diagnosis.mkdir()
    for text, where in (("\x00garbage", "not valid JSON"), ('{"cause": "gremlins"}', "key 'cause'")):
        (diagnosis / "diagnosis.json").write_text(text)
        with pytest.raises(InputError) as err:
            cp.pooled_fit_folder(out, "EX-drogue")
        assert str(diagnosis / "diagnosis.json") in str(err.value) and where in str(err.value)


def test_the_dask_client_gives_up_on_an_unreachable_scheduler_with_a_refusal():
    pytest.importorskip("distributed")
    from cpas_bayes.core.executor import DaskExecutor
    from cpas_bayes.core.scheduler_address import CONNECT_TIMEOUT

    started = time.perf_counter()
    with pytest.raises(InputError, match="no Dask scheduler answered"):
        DaskExecutor(f"tcp://127.0.0.1:{closed_port()}")
    assert time.perf_counter() - started < CONNECT_TIMEOUT + 10


@pytest.mark.parametrize("content", [b"", b"\x89HDF\r\n\x1a\n" + b"\x00" * 40, b"not hdf5 at all"])
def test_a_damaged_checkpoint_is_refused_with_what_to_delete(fresh, content):
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit import SamplerOptions, prepare_model, run_ensemble

    test = read_bundle(DROGUE)
    model = prepare_model(test, reduce_test(test))
    checkpoint = fresh() / "ensemble_0.h5"
    with atomic_path(checkpoint) as tmp:   # damaged, but the package's own file (listed in the folder's marker)
        tmp.write_bytes(content)
    init = np.random.default_rng(0).normal(size=(2 * model.ndim + 2, model.ndim))
    with pytest.raises(InputError) as err:
        run_ensemble(model, init, 1, SamplerOptions(max_steps=100, check_every=50), checkpoint=checkpoint)
    assert str(err.value).startswith(str(checkpoint)) and f"delete {checkpoint}" in str(err.value)


def test_fit_max_steps_caps_every_ensemble_and_the_fit_says_it_did_not_converge(tmp_path, capsys):
    out = tmp_path / "fit"
    assert main(["fit", str(DROGUE), "--out", str(out), "--max-steps", "500", "--ensembles", "2", "--workers", "1"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["diagnostics"]["steps"] == [500, 500]
    printed = capsys.readouterr().out
    assert "NOT converged" in printed and "500 steps per ensemble" in printed


def test_a_file_that_is_not_a_memo_gets_no_advice_to_pool_into_its_folder(files, fresh, capsys):
    """A fit's summary.json given as --memo: re-pooling into the fit's folder (or deleting it) would be harmful
    advice; the fix names what --memo takes."""
    out = fresh()
    err = refused(capsys, ["montecarlo", "--memo", files / "fit" / "summary.json", "--like", DROGUE, "--runs", "10",
                           "--out", out], out, "summary.json", "pass a memo.toml written by 'cpas-bayes pool'")
    assert "re-run 'cpas-bayes pool" not in err and "delete" not in err

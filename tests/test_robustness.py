"""Scale and robustness: every executor gives the same bytes; SIGKILL and Ctrl-C leave a resumable state.

Executors run seeded tasks, so "the same" here means equal arrays and equal
files, not statistically close ones. The kill tests start a real process,
kill it with SIGKILL (or interrupt it with SIGINT) once its first checkpoint
exists, check that the kill did land mid-run, and resume.
"""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from cpas_bayes.data.bundle import example_bundles, read_bundle
from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.app.cli import main
from cpas_bayes.core.executor import DaskExecutor, Executor, ProcessExecutor, in_worker, make_executor
from cpas_bayes.inference.fit import SamplerOptions, fit_model, prepare_model
from cpas_bayes.loads.montecarlo import run_monte_carlo
from cpas_bayes.data.synth import write_synthetic

from test_montecarlo import MAIN_SPEC, hand_memo


def _square_after(job, report=None):
    """A task whose finishing order is the reverse of its submission order."""
    value, delay = job
    time.sleep(delay)
    if report is not None:
        report("done", value)
    return value * value, in_worker()


def _fails(job):
    raise ValueError(f"task {job} failed")


def _nested(job):
    ex = make_executor(workers=4)
    return ex.kind


# ---------------------------------------------------------------------------
# the executors


def test_process_pool_keeps_submission_order_relays_reports_and_errors():
    jobs = [(v, 0.3 - 0.1 * v) for v in range(3)]
    seen = []
    with ProcessExecutor(2) as ex:
        out = ex.map(_square_after, jobs, on_report=lambda *m: seen.append(m))
        assert [o[0] for o in out] == [0, 1, 4]
        assert all(o[1] for o in out)                           # ran in a worker
        assert sorted(seen) == [("done", 0), ("done", 1), ("done", 2)]
        assert ex.map(_nested, [0, 1]) == ["serial", "serial"]  # pools do not nest
        with pytest.raises(ValueError, match="task 1 failed"):
            ex.map(_fails, [1, 2])
        assert ex.map(_square_after, [(5, 0)]) == [(25, True)]  # usable after a failure
    assert Executor().map(_square_after, jobs) == [(0, False), (1, False), (4, False)]
    assert make_executor(1).kind == "serial" and make_executor(3).kind == "processes"


def _numba_started(_):
    started = sys.modules.get("cpas_bayes.core.numba_start")
    return started is not None and bool(started._add_one.signatures)


def test_workers_are_forked_with_numba_already_started_by_their_server():
    """The fork server compiles (or loads) one kernel before it forks any worker, so a worker's first kernel
    does not pay numba's start (0.3-0.4 s a worker, measured on the two-Drogue fit's first chunk)."""
    with ProcessExecutor(2) as ex:
        assert ex.map(_numba_started, [0, 1]) == [True, True]


def _first(job, report=None):
    value, delay = job
    time.sleep(delay)
    if report is not None:
        report("first", value)
    return value * 10


def _then(job_and_first, report=None):
    (value, _), first = job_and_first
    if report is not None:
        report("then", value)
    if value < 0:
        raise ValueError(f"then {value} failed")
    return first + value, in_worker()


def test_chained_tasks_run_second_after_first_with_its_result_on_every_executor():
    jobs = [(v, 0.2 - 0.1 * v) for v in range(3)]
    expected = [(0, (0, True)), (10, (11, True)), (20, (22, True))]
    seen = []
    with ProcessExecutor(2) as ex:
        assert ex.map_chained(_first, _then, jobs, costs=[1, 3, 2], on_report=lambda *m: seen.append(m)) == expected
        assert sorted(seen) == sorted([("first", v) for v in range(3)] + [("then", v) for v in range(3)])
        with pytest.raises(ValueError, match="then -1 failed"):
            ex.map_chained(_first, _then, [(1, 0.0), (-1, 0.0)])
        assert ex.map_chained(_first, _then, [(5, 0.0)]) == [(50, (55, True))]   # usable after a failure
    with DaskExecutor(workers=2) as ex:
        assert ex.map_chained(_first, _then, jobs, on_report=lambda *m: None) == expected
    serial = [(a, (b, False)) for a, (b, _) in expected]
    assert Executor().map_chained(_first, _then, jobs) == serial


class _Done:
    """A task that has finished by the time the dispatcher looks."""

    def __init__(self, value):
        self.value = value

    def done(self):
        return True

    def result(self):
        return self.value


class _NoBar:
    def update(self, n):
        pass


def test_chained_tasks_hand_out_every_first_costliest_first_then_the_costliest_ready_second():
    launched = []

    def launch(fn, item, index):
        launched.append((fn.__name__, item if fn is _first else item[0]))
        return _Done(fn.__name__)

    ex = Executor()
    ex.workers = 2
    items = ["D1", "M1", "D2", "L1"]
    out = ex._chained_on_workers(launch, lambda: None, _first, _then, items, [1, 2, 1, 9], _NoBar())
    assert out == [("_first", "_then")] * 4
    assert launched == [("_first", "L1"), ("_first", "M1"), ("_first", "D1"), ("_first", "D2"),
                        ("_then", "L1"), ("_then", "M1"), ("_then", "D1"), ("_then", "D2")]


def _last(job_and_first, report=None):
    (value, _), first = job_and_first
    return -first


def test_chained_tasks_of_lower_priority_go_last_and_come_back_beside_the_others():
    launched = []

    def launch(fn, item, index):
        launched.append((fn.__name__, item if fn is _first else item[0], index))
        return _Done(fn.__name__)

    ex = Executor()
    ex.workers = 3
    out = ex._chained_on_workers(launch, lambda: None, _first, (_then, _last), ["A", "B"], [1, 2], _NoBar())
    assert out == [("_first", "_then", "_last")] * 2
    assert launched == [("_first", "B", 3), ("_first", "A", 0), ("_then", "B", 4), ("_then", "A", 1),
                        ("_last", "B", 5), ("_last", "A", 2)]
    jobs = [(1, 0.0), (2, 0.0)]
    expected = [(10, (11, False), -10), (20, (22, False), -20)]
    assert Executor().map_chained(_first, (_then, _last), jobs) == expected
    with ProcessExecutor(2) as pool:
        assert pool.map_chained(_first, (_then, _last), jobs, on_report=lambda *m: None) == [
            (a, (b, True), c) for a, (b, _), c in expected]


def test_monte_carlo_is_identical_on_every_executor():
    test = read_bundle(next(p for p in example_bundles() if p.name.startswith("main")))
    memo = hand_memo(MAIN_SPEC)

    def run(executor):
        result = run_monte_carlo(memo, test, 600, np.random.default_rng(4), batch=128, executor=executor,
                                 progress=False)
        return result.frame()

    reference = run(None)
    with ProcessExecutor(2) as ex:
        pooled = run(ex)
    with DaskExecutor(workers=2) as ex:
        assert ex.workers == 2
        dask = run(ex)
    assert reference.equals(pooled) and reference.equals(dask)


# ---------------------------------------------------------------------------
# a fit killed with SIGKILL, interrupted with Ctrl-C

FIT_OPTIONS = dict(seed=3, n_ensembles=2, workers=1, check_every=100, max_steps=800, stop="tau", tau_factor=1e9,
                   map_starts=1, progress=False)

FIT_SCRIPT = """
import sys
from cpas_bayes.data.bundle import read_bundle
from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.inference.fit import SamplerOptions, fit_model, prepare_model
test = read_bundle(sys.argv[1])
model = prepare_model(test, reduce_test(test))
fit_model(model, SamplerOptions(**{options}), checkpoint_dir=sys.argv[2])
"""


def _wait_for(path, process, timeout=300):
    started = time.time()
    while not path.exists():
        assert process.poll() is None, process.communicate()
        assert time.time() - started < timeout, f"{path} never appeared"
        time.sleep(0.05)


def _iterations(checkpoint):
    import h5py

    with h5py.File(checkpoint, "r") as f:
        return int(f["mcmc"].attrs["iteration"])


@pytest.mark.slow
def test_a_fit_killed_with_sigkill_resumes_to_the_same_posterior(tmp_path):
    bundle = next(p for p in example_bundles() if p.name.startswith("drogue"))
    checkpoints = tmp_path / "checkpoint"
    script = FIT_SCRIPT.format(options=FIT_OPTIONS)
    process = subprocess.Popen([sys.executable, "-c", script, str(bundle), str(checkpoints)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    first = checkpoints / "ensemble_0.h5"
    _wait_for(first, process)
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=30)
    assert process.returncode == -signal.SIGKILL
    stored_every = SamplerOptions().store_every
    done_at_kill = _iterations(first) * stored_every
    assert 0 < done_at_kill < FIT_OPTIONS["max_steps"], "the kill did not land mid-run"
    assert not (checkpoints / "ensemble_1.h5").exists()
    # the folder's marker and the ensemble's lock file are there by design; no temporary file is
    assert sorted(p.name for p in checkpoints.iterdir() if p.name.startswith(".")) == [".cpas-bayes",
                                                                                      ".ensemble_0.h5.lock"]

    test = read_bundle(bundle)
    model = prepare_model(test, reduce_test(test))
    options = SamplerOptions(**FIT_OPTIONS)
    resumed = fit_model(model, options, checkpoint_dir=checkpoints)
    uninterrupted = fit_model(model, options)
    for a, b in zip(resumed.sampling.runs, uninterrupted.sampling.runs):
        assert a.steps == b.steps == FIT_OPTIONS["max_steps"]
        np.testing.assert_array_equal(a.draws, b.draws)
        np.testing.assert_array_equal(a.log_prob, b.log_prob)


@pytest.mark.slow
def test_ctrl_c_stops_a_fit_with_a_resumable_checkpoint_and_says_how_to_resume(tmp_path):
    bundle = next(p for p in example_bundles() if p.name.startswith("drogue"))
    out = tmp_path / "fit"
    env = dict(os.environ, MPLBACKEND="Agg")
    # an ESS target the fit cannot reach within its steps keeps it running until the signal comes, however
    # fast or loaded the machine (the default target can be met a few chunks after the first checkpoint)
    process = subprocess.Popen([sys.executable, "-m", "cpas_bayes.app.cli", "fit", str(bundle), "--out", str(out),
                                "--workers", "2", "--ess-target", "100000"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=env,
                               # as a shell starts a foreground command: a suite run as a background job
                               # (nohup ... &) would pass SIGINT on ignored, and the fit keeps it so
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    _wait_for(out / "checkpoint" / "ensemble_0.h5", process)
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    assert "interrupted" in stderr and "rerun the same command to resume" in stderr
    assert "Traceback" not in stderr
    assert _iterations(out / "checkpoint" / "ensemble_0.h5") > 0
    assert not (out / "posterior.nc").exists() and not (out / "summary.json").exists()


# ---------------------------------------------------------------------------
# campaigns: process pool, Dask LocalCluster, killed and resumed

CAMPAIGN = """
name = "executor campaign"
[fit]
ensembles = 2
max_steps = 600
stop = "tau"
tau_factor = 10
check_every = 200
[diagnose]
mode = "off"
[montecarlo]
runs = 300
[compare]
runs = 100
[pool]
draws = 1000
"""

RESULT_FILES = ("memo/memo.toml", "memo/memo_draws.csv", "montecarlo/2xdrogue-2st/runs.csv")


def _campaign_inputs(tmp_path):
    folder = tmp_path / "bundles"
    write_synthetic("drogue", "none", 41, folder / "T1")
    write_synthetic("drogue", "none", 42, folder / "T2")
    config = tmp_path / "campaign.toml"
    config.write_text(CAMPAIGN)
    return folder, config


def _results(out):
    """The result files' bytes; the memo without its provenance table (output paths, times)."""
    import tomllib

    out_files = {f: (out / f).read_bytes() for f in RESULT_FILES}
    memo = tomllib.loads(out_files["memo/memo.toml"].decode())
    memo.pop("provenance")
    out_files["memo/memo.toml"] = json.dumps(memo, sort_keys=True)
    return out_files


@pytest.mark.slow
def test_campaign_memos_are_identical_under_the_process_pool_and_a_dask_local_cluster(tmp_path):
    folder, config = _campaign_inputs(tmp_path)
    args = ["campaign", str(folder), "--config", str(config), "--workers", "2"]
    assert main(args + ["--out", str(tmp_path / "pool")]) == 0
    assert main(args + ["--out", str(tmp_path / "dask"), "--scheduler", "local"]) == 0
    pool, dask = _results(tmp_path / "pool"), _results(tmp_path / "dask")
    for name in RESULT_FILES:
        assert pool[name] == dask[name], f"{name} differs between executors"
    manifest = json.loads((tmp_path / "dask" / "campaign.json").read_text())
    assert manifest["tests"] and all(s["status"] == "ran" for s in manifest["steps"])


@pytest.mark.slow
def test_a_campaign_killed_mid_fit_resumes_to_the_same_memo(tmp_path):
    folder, config = _campaign_inputs(tmp_path)
    killed = tmp_path / "killed"
    args = ["campaign", str(folder), "--config", str(config), "--workers", "1"]
    process = subprocess.Popen([sys.executable, "-m", "cpas_bayes.app.cli", *args, "--out", str(killed)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=dict(os.environ, MPLBACKEND="Agg"))
    second_ckpt = None
    started = time.time()
    # Kill once the second test's fit has written its first chunk: one fit done, one mid-way.
    while second_ckpt is None:
        assert process.poll() is None, process.communicate()
        assert time.time() - started < 600
        ckpts = sorted((killed / ".checkpoints").glob("*/ensemble_0.h5")) if (killed / ".checkpoints").exists() \
            else []
        if len(ckpts) == 2:
            second_ckpt = ckpts
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=30)
    finished_fits = [p for p in (killed / "tests").glob("*/fit/stamp.json")]
    assert len(finished_fits) == 1, "the kill should land while the second fit runs"
    assert not (killed / "memo").exists()

    assert main([*args, "--out", str(killed)]) == 0
    steps = {s["name"]: s["status"] for s in json.loads((killed / "campaign.json").read_text())["steps"]}
    assert sorted(steps[k] for k in steps if k.endswith(" fit")) == ["cached", "ran"]
    assert main([*args, "--out", str(tmp_path / "whole")]) == 0
    resumed, whole = _results(killed), _results(tmp_path / "whole")
    for name in RESULT_FILES:
        assert resumed[name] == whole[name], f"{name} differs after the resume"

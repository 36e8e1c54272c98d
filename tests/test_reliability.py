"""Never lose a user's file, never write outside --out, processes that die with their parent.

The output-folder rule (cpas_bayes.core.ownership): an --out is new, empty or
written by cpas-bayes; anything else is refused before any work with a message
naming the path and the fix, exit status 2, and nothing in it changed. Names
from the data never lead a path out of --out. Workers end with the process
that started them, however it ends; checkpoints have one writer at a time, and
a resumed fit equals an uninterrupted one. SIGTERM ends a command like Ctrl-C.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cpas_bayes.app import campaign as cp
from cpas_bayes.app.cli import main
from cpas_bayes.core.errors import InputError
from cpas_bayes.core.files import atomic_directory, exclusive_writer, write_text
from cpas_bayes.core.ownership import MARKER, OutputError, check_output, claim_folder, read_marker
from cpas_bayes.data.bundle import example_bundles, read_bundle
from cpas_bayes.data.synth import write_synthetic

DROGUE = next(p for p in example_bundles() if p.name.startswith("drogue"))
ENV = dict(os.environ, MPLBACKEND="Agg")


def tree_state(root):
    """Every path under ``root`` (itself included) with its mode and bytes: equal states mean nothing changed."""
    root = Path(root)
    state = {".": stat.S_IMODE(root.stat().st_mode)}
    for p in sorted(root.rglob("*")):
        st = p.lstat()
        state[p.relative_to(root).as_posix()] = (stat.S_IMODE(st.st_mode), p.read_bytes() if p.is_file() else None)
    return state


def run(capsys, *args):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err and "internal error" not in err
    return code, err


def user_folder(path):
    """A folder of the user's: a file, a private file in a sub-folder, unusual modes."""
    path.mkdir()
    (path / "notes.txt").write_text("my notes\n")
    os.chmod(path / "notes.txt", 0o640)
    (path / "keep").mkdir()
    (path / "keep" / "data.bin").write_bytes(os.urandom(256))
    os.chmod(path / "keep" / "data.bin", 0o600)
    os.chmod(path, 0o750)
    return path


def commands(out, tmp_path):
    """Every command that takes --out, with inputs (the --out check comes before they are read)."""
    fit, memo = tmp_path / "somefit", tmp_path / "memo.toml"
    return {
        "reduce": ["reduce", DROGUE, "--out", out],
        "synth": ["synth", "--scenario", "drogue", "--seed", "1", "--out", out],
        "fit": ["fit", DROGUE, "--out", out, "--workers", "1"],
        "pool": ["pool", fit, "--out", out],
        "montecarlo": ["montecarlo", "--memo", memo, "--like", DROGUE, "--runs", "10", "--out", out],
        "compare": ["compare", DROGUE, "--memo", memo, "--out", out],
        "diagnose": ["diagnose", DROGUE, "--out", out, "--workers", "1"],
        "campaign": ["campaign", DROGUE.parent, "--out", out, "--workers", "1"],
        "demo": ["demo", "--out", out],
    }


COMMANDS = ("reduce", "synth", "fit", "pool", "montecarlo", "compare", "diagnose", "campaign", "demo")


# ---------------------------------------------------------------------------
# --out: the user's files are never touched


@pytest.mark.parametrize("command", COMMANDS)
def test_an_out_folder_holding_user_files_is_refused_and_left_as_it_was(capsys, tmp_path, command):
    out = user_folder(tmp_path / "mine")
    before = tree_state(out)
    code, err = run(capsys, *commands(out, tmp_path)[command])
    assert code == 2
    assert "keep" in err and "not written by cpas-bayes" in err and "Fix:" in err
    assert tree_state(out) == before  # byte-identical, same modes, no marker added


@pytest.mark.parametrize("command", COMMANDS)
def test_an_out_that_is_an_existing_file_is_refused_and_left_as_it_was(capsys, tmp_path, command):
    out = tmp_path / "results.csv"
    out.write_text("a,b\n1,2\n")
    os.chmod(out, 0o604)
    before = tree_state(tmp_path)
    code, err = run(capsys, *commands(out, tmp_path)[command])
    assert code == 2 and "is a file, not a folder" in err and str(out) in err
    assert tree_state(tmp_path) == before


@pytest.mark.parametrize("command", ["reduce", "synth", "campaign"])
def test_an_out_through_a_file_or_with_a_300_character_name_is_refused_up_front(capsys, tmp_path, command):
    (tmp_path / "plain.txt").write_text("x")
    before = tree_state(tmp_path)
    code, err = run(capsys, *commands(tmp_path / "plain.txt" / "sub", tmp_path)[command])
    assert code == 2 and "plain.txt is a file, so no folder can be made under it" in err
    code, err = run(capsys, *commands(tmp_path / "new" / ("n" * 300), tmp_path)[command])
    assert code == 2 and "300 bytes" in err and "shorter names" in err
    assert tree_state(tmp_path) == before


@pytest.fixture
def read_only(tmp_path):
    """``read_only(folder)``: make a folder unwritable, also for root (immutable flag); undone afterwards."""
    made = []

    def freeze(folder):
        if os.geteuid() == 0:
            if subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode != 0:
                pytest.skip("running as root and cannot make a folder immutable (chattr)")
        else:
            os.chmod(folder, 0o555)
        made.append(folder)
        return folder

    yield freeze
    for folder in made:
        if os.geteuid() == 0:
            subprocess.run(["chattr", "-i", str(folder)], capture_output=True)
        os.chmod(folder, 0o755)


@pytest.mark.parametrize("command", ["reduce", "synth"])
def test_a_read_only_folder_ends_with_a_message_naming_it(capsys, tmp_path, read_only, command):
    locked = tmp_path / "locked"
    locked.mkdir()
    read_only(locked)
    for out in (locked, locked / "sub"):
        code, err = run(capsys, *commands(out, tmp_path)[command])
        assert code == 2, err
        assert str(locked) in err and "permission denied" in err and "Fix:" in err
    # past the up-front check (a folder that turns read-only mid-run): the same message, from the write itself
    with pytest.raises(OutputError, match="permission denied"):
        claim_folder(locked / "sub")
    with pytest.raises(OutputError, match="permission denied"):
        write_text(locked / "summary.json", "{}")
    assert list(locked.iterdir()) == []


def test_a_full_disk_ends_with_a_message_and_no_temporary_file(capsys, tmp_path, monkeypatch):
    import errno

    import pandas as pd

    def disk_full(self, path, *args, **kwargs):
        Path(path).write_bytes(b"x" * 1000)  # half-written, then the disk fills up
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pd.DataFrame, "to_csv", disk_full)
    out = tmp_path / "red"
    code, err = run(capsys, "reduce", DROGUE, "--out", out)
    assert code == 2 and "no space left" in err and str(out / "reduced.csv") in err
    assert sorted(p.name for p in out.iterdir()) == [MARKER]  # nothing half-written, no temporary file


def test_outputs_of_cpas_bayes_are_reused_and_created_folders_get_the_usual_mode(capsys, tmp_path):
    bundle = tmp_path / "bundle"
    assert run(capsys, "synth", "--scenario", "drogue", "--seed", "1", "--out", bundle)[0] == 0
    assert run(capsys, "synth", "--scenario", "drogue", "--seed", "2", "--out", bundle)[0] == 0  # its own: replaced
    assert read_bundle(bundle).name.endswith("-2")
    mask = os.umask(0o022)
    os.umask(mask)
    assert stat.S_IMODE(bundle.stat().st_mode) == 0o777 & ~mask  # not mkdtemp's 0700
    out = tmp_path / "a" / "b"
    for _ in range(2):
        assert run(capsys, "reduce", bundle, "--out", out)[0] == 0
    assert read_marker(out).entries == {"reduced.csv", "reduction.json", "reduction.png"}
    assert stat.S_IMODE((out / "reduced.csv").stat().st_mode) == 0o666 & ~mask
    # an empty folder of the user's is used as it is: same folder, same mode, never replaced
    given = tmp_path / "given"
    given.mkdir(mode=0o750)
    os.chmod(given, 0o750)
    inode = given.stat().st_ino
    for seed in ("3", "4"):
        assert run(capsys, "synth", "--scenario", "drogue", "--seed", seed, "--out", given)[0] == 0
    assert given.stat().st_ino == inode and stat.S_IMODE(given.stat().st_mode) == 0o750
    assert sorted(p.name for p in given.iterdir()) == [MARKER, "data.csv", "test.toml", "truth.json"]
    # a file the user adds to an output folder is never replaced, nor the folder holding it
    (out / "mine.txt").write_text("mine")
    with pytest.raises(OutputError, match="mine.txt"):
        check_output(out)
    with pytest.raises(OutputError, match="not written by cpas-bayes"):
        write_text(out / "mine.txt", "theirs")
    (bundle / "mine.txt").write_text("mine")
    with pytest.raises(OutputError, match="mine.txt"):
        with atomic_directory(bundle) as tmp:
            (tmp / "x").write_text("x")
    assert (out / "mine.txt").read_text() == (bundle / "mine.txt").read_text() == "mine"
    assert not [p for p in tmp_path.rglob("*.cpas-tmp")]


# ---------------------------------------------------------------------------
# names from the data never leave --out


def _hostile_campaign(tmp_path, monkeypatch, change):
    """A campaign whose one bundle, once read, carries ``change`` (the reader's checks bypassed)."""
    base = tmp_path / "a" / "b"
    bundles = base / "bundles"
    write_synthetic("drogue", "none", 5, bundles / "T1")
    victim = user_folder(base / "victim")
    real_read = cp.read_bundle
    monkeypatch.setattr(cp, "read_bundle", lambda path: change(real_read(path)))
    return bundles, base / "out", victim


@pytest.mark.parametrize("change", [
    lambda t: dataclasses.replace(t, name="../../victim"),
    lambda t: dataclasses.replace(t, name="../victim"),
    lambda t: dataclasses.replace(t, name=".."),
    lambda t: dataclasses.replace(t, name="/tmp/victim"),
    lambda t: dataclasses.replace(t, parachutes=tuple(dataclasses.replace(p, kind="../../../victim")
                                                      for p in t.parachutes)),
], ids=["up-two", "up-one", "dotdot", "absolute", "kind"])
def test_a_hostile_name_in_a_campaign_never_writes_outside_out(tmp_path, monkeypatch, change):
    bundles, out, victim = _hostile_campaign(tmp_path, monkeypatch, change)
    before = tree_state(tmp_path)
    with pytest.raises(InputError, match="outside|cannot be used"):
        cp.run_campaign(bundles, out, cp.CampaignConfig(workers=1, diagnose="off"), echo=lambda m: None)
    assert tree_state(tmp_path) == before  # nothing written anywhere, the victim untouched


def test_the_paths_of_a_campaign_are_checked_one_by_one(tmp_path):
    out = tmp_path / "out"
    assert cp.test_folder(out, "EDU-D3", "fit") == out / "tests" / "EDU-D3" / "fit"
    for name in ("../x", "..", "a/b", ".hidden", "", "x\ny"):
        with pytest.raises(InputError):
            cp.test_folder(out, name)
    (out / "tests").mkdir(parents=True)
    os.symlink(tmp_path, out / "tests" / "T9")  # a planted link out of the folder
    with pytest.raises(InputError, match="outside"):
        cp.test_folder(out, "T9")


def test_two_bundles_that_would_share_a_folder_are_refused(tmp_path, monkeypatch):
    folder = tmp_path / "bundles"
    write_synthetic("drogue", "none", 1, folder / "A")
    write_synthetic("drogue", "none", 1, folder / "B")  # same seed: same test name
    with pytest.raises(InputError, match="used by more than one bundle"):
        cp.validate_all(cp.find_bundles(folder))
    write_synthetic("drogue", "none", 2, folder / "B")
    real_read = cp.read_bundle
    monkeypatch.setattr(cp, "read_bundle", lambda p: dataclasses.replace(
        real_read(p), name="EDU-D1" if p.name == "A" else "edu-d1"))
    with pytest.raises(InputError, match="upper/lower case"):
        cp.validate_all(cp.find_bundles(folder))


# ---------------------------------------------------------------------------
# one writer per checkpoint; resumed = uninterrupted


LOCK_HOLDER = """
import sys, time
from cpas_bayes.core.files import exclusive_writer
with exclusive_writer(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(120)
"""


def test_a_checkpoint_has_one_writer_and_a_dead_writers_lock_is_taken_over(tmp_path):
    target = tmp_path / "checkpoint" / "ensemble_0.h5"
    holder = subprocess.Popen([sys.executable, "-c", LOCK_HOLDER, str(target)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(OutputError, match=f"another running process \\(pid {holder.pid}\\)"):
            with exclusive_writer(target, wait=0.5):
                pass
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    started = time.monotonic()
    with exclusive_writer(target, wait=0.5) as lock:  # the killed holder's lock is free at once
        assert lock.read_text().strip() == str(os.getpid())
    assert time.monotonic() - started < 0.5


@pytest.fixture(scope="module")
def drogue_start():
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit import prepare_model
    from cpas_bayes.inference.start import find_map, initial_walkers, laplace_covariance

    test = read_bundle(DROGUE)
    model = prepare_model(test, reduce_test(test))
    theta, _ = find_map(model, np.random.default_rng(0), starts=1)
    init = initial_walkers(model, theta, laplace_covariance(model, theta), 2 * model.ndim + 2,
                           np.random.default_rng(1))
    return model, init


def test_a_resumed_ensemble_keeps_the_convergence_history_and_a_finished_one_adds_no_chunk(drogue_start, tmp_path):
    from cpas_bayes.inference.fit import SamplerOptions, run_ensemble

    model, init = drogue_start
    # converges at the second check (τ settles at once): the first check's τ must survive a resume
    whole = SamplerOptions(max_steps=2000, check_every=250, stop="tau", tau_factor=0.01, tau_rtol=100.0)
    uninterrupted = run_ensemble(model, init, 5, whole)
    assert uninterrupted.converged and uninterrupted.steps == 500
    ckpt = tmp_path / "ckpt" / "ensemble_0.h5"
    run_ensemble(model, init, 5, dataclasses.replace(whole, max_steps=250), checkpoint=ckpt)  # killed here
    resumed = run_ensemble(model, init, 5, whole, checkpoint=ckpt)
    assert resumed.steps == 500
    np.testing.assert_array_equal(resumed.draws, uninterrupted.draws)
    again = run_ensemble(model, init, 5, whole, checkpoint=ckpt)  # a finished ensemble, rerun
    assert again.steps == 500 and again.acceptance == resumed.acceptance
    np.testing.assert_array_equal(again.draws, uninterrupted.draws)


# ---------------------------------------------------------------------------
# processes: nothing outlives the command


def descendants(pid):
    """Pids of every process below ``pid`` (psutil if installed, else /proc)."""
    try:
        import psutil

        return {p.pid for p in psutil.Process(pid).children(recursive=True)}
    except ImportError:
        children = {}
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                try:
                    ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                except (OSError, IndexError, ValueError):
                    continue
                children.setdefault(ppid, set()).add(int(entry.name))
        found, todo = set(), [pid]
        while todo:
            for child in children.get(todo.pop(), ()):
                found.add(child)
                todo.append(child)
        return found


def running(pid):
    """True while ``pid`` runs (a zombie waiting for its reaper has ended)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[0] not in ("Z", "X")


def processes_mentioning(text):
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            try:
                if text.encode() in (entry / "cmdline").read_bytes() and running(int(entry.name)):
                    found.append(int(entry.name))
            except OSError:
                continue
    return found


def assert_all_end(pids, timeout=15):
    started = time.monotonic()
    while [p for p in pids if running(p)]:
        assert time.monotonic() - started < timeout, f"orphans still running: {[p for p in pids if running(p)]}"
        time.sleep(0.1)


POOL_SCRIPT = """
import time
from cpas_bayes.core.executor import ProcessExecutor
if __name__ == "__main__":
    with ProcessExecutor(2) as ex:
        print("mapping", flush=True)
        ex.map(time.sleep, [120, 120])
"""


def test_workers_end_when_the_process_that_started_them_is_killed(tmp_path):
    process = subprocess.Popen([sys.executable, "-c", POOL_SCRIPT], stdout=subprocess.PIPE, text=True, env=ENV)
    assert process.stdout.readline().strip() == "mapping"
    started = time.monotonic()
    while len(descendants(process.pid)) < 4:  # fork server, resource tracker, two workers
        assert time.monotonic() - started < 60 and process.poll() is None
        time.sleep(0.1)
    family = descendants(process.pid)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert_all_end(family)


# A fit with short chains, through the CLI's own main(): `cpas-bayes fit BUNDLE --out OUT --workers 2`.
SHORT_FIT = dict(max_steps=1000, check_every=100, stop="tau", tau_factor=1e9, map_starts=1)
FIT_CLI = """
import dataclasses, sys
import cpas_bayes.inference.fit as fit
real = fit.fit_model
fit.fit_model = lambda model, options, **kw: real(model, dataclasses.replace(options, **{options}), **kw)
from cpas_bayes.app.cli import main
sys.exit(main(["fit", sys.argv[1], "--out", sys.argv[2], "--workers", "2", "--ensembles", "2", "--seed", "3"]))
"""


def start_fit(out):
    return subprocess.Popen([sys.executable, "-c", FIT_CLI.format(options=SHORT_FIT), str(DROGUE), str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)


def wait_for_checkpoint(out, process, timeout=300):
    first = out / "checkpoint" / "ensemble_0.h5"
    started = time.monotonic()
    while not first.exists():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() - started < timeout
        time.sleep(0.02)
    return first


def iterations(checkpoint):
    import h5py

    with h5py.File(checkpoint, "r") as f:
        return int(f["mcmc"].attrs["iteration"])


def chains(folder):
    import h5py

    result = []
    for e in range(2):
        with h5py.File(folder / f"ensemble_{e}.h5", "r") as f:
            result.append((f["mcmc"]["chain"][...], f["mcmc"]["log_prob"][...]))
    return result


@pytest.mark.slow
def test_a_fit_whose_main_process_is_killed_leaves_no_orphan_and_resumes_to_the_same_chains(tmp_path):
    out = tmp_path / "killed-fit-4f1c"
    process = start_fit(out)
    first = wait_for_checkpoint(out, process)
    family = descendants(process.pid)
    assert len(family) >= 3, "the workers should be running"
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert_all_end(family)
    assert not processes_mentioning(str(out))
    at_kill = iterations(first)
    time.sleep(1.0)
    assert iterations(first) == at_kill, "an orphan went on writing the checkpoint"
    assert 0 < at_kill * 5 < SHORT_FIT["max_steps"], "the kill did not land mid-run"
    assert not (out / "posterior.nc").exists()

    rerun = start_fit(out)
    _, err = rerun.communicate(timeout=600)
    assert rerun.returncode == 0, err
    assert not list(out.rglob("*.cpas-tmp"))
    # the same sampling uninterrupted, in this process (the fit command's model and options)
    from cpas_bayes.core.executor import Executor
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit import SamplerOptions, prepare_model, sample_posterior

    test = read_bundle(DROGUE)
    options = SamplerOptions(seed=3, workers=2, n_ensembles=2, **SHORT_FIT)
    sample_posterior(prepare_model(test, reduce_test(test)), options, checkpoint_dir=tmp_path / "whole",
                     executor=Executor())
    for (chain_a, lp_a), (chain_b, lp_b) in zip(chains(out / "checkpoint"), chains(tmp_path / "whole")):
        assert chain_a.shape[0] * 5 == SHORT_FIT["max_steps"]
        np.testing.assert_array_equal(chain_a, chain_b)
        np.testing.assert_array_equal(lp_a, lp_b)


@pytest.mark.slow
def test_sigterm_stops_a_fit_like_ctrl_c_with_no_orphan_and_no_temporary_file(tmp_path):
    out = tmp_path / "fit"
    process = start_fit(out)
    wait_for_checkpoint(out, process)
    family = descendants(process.pid)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    assert "interrupted" in err and "rerun the same command to resume" in err and "Traceback" not in err
    assert_all_end(family)
    assert not list(out.rglob("*.cpas-tmp"))
    assert check_output(out) == out  # still the package's folder: the rerun resumes


SLOW_REDUCE = """
import sys, time
from pathlib import Path
import pandas as pd
real = pd.DataFrame.to_csv
def slow(self, path, *args, **kwargs):
    real(self, path, *args, **kwargs)           # the temporary file is written...
    Path(sys.argv[3]).write_text("writing")
    time.sleep(120)                             # ...and the rename is far away
pd.DataFrame.to_csv = slow
from cpas_bayes.app.cli import main
sys.exit(main(["reduce", sys.argv[1], "--out", sys.argv[2]]))
"""


def test_sigterm_during_a_write_exits_130_and_leaves_no_temporary_file(tmp_path):
    out, ready = tmp_path / "red", tmp_path / "ready"
    process = subprocess.Popen([sys.executable, "-c", SLOW_REDUCE, str(DROGUE), str(out), str(ready)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    started = time.monotonic()
    while not ready.exists():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() - started < 120
        time.sleep(0.05)
    assert [p for p in out.iterdir() if p.name.endswith(".cpas-tmp")], "the temporary file should exist now"
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=30)
    assert process.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == [MARKER]

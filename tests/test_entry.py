"""The program's entry: which commands start the worker server early, and that doing so changes nothing
else a user sees (errors, exit status, outputs)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import pytest

from cpas_bayes.app import entry
from cpas_bayes.data.bundle import example_bundles


@pytest.mark.parametrize("args,expected", [
    (["fit", "b", "--out", "o"], "cpas_bayes.outputs.plots.fit"),
    (["diagnose", "b", "--out", "o", "--workers", "4"], "cpas_bayes.inference.diagnose"),
    (["campaign", "c.toml"], "cpas_bayes.app.campaign"),
    (["fit", "b", "--workers=1"], None),
    (["fit", "b", "--workers", "1"], None),
    (["fit", "b", "--scheduler", "local"], None),
    (["fit", "b", "--scheduler=tcp://h:8786"], None),
    (["fit", "--help"], None),
    (["validate", "b"], None),
    (["montecarlo", "--memo", "m"], None),
    ([], None),
])
def test_only_commands_that_start_local_workers_start_the_server(args, expected):
    modules = entry.worker_modules(args)
    if expected is None:
        assert modules is None
    else:
        assert expected in modules and "cpas_bayes.app.cli" in modules


def test_every_module_the_server_preloads_exists():
    # a renamed module would make the server fail at start, and every worker with it
    names = {m for mods in entry.WORKER_MODULES.values() for m in mods} | {"cpas_bayes.app.cli"}
    missing = [m for m in names if importlib.util.find_spec(m) is None]
    assert not missing


def _run(args, tmp_path):
    return subprocess.run([sys.executable, "-m", "cpas_bayes", *args], capture_output=True, text=True,
                          cwd=tmp_path, timeout=300)


def test_the_program_ends_without_teardown_but_with_its_whole_output_and_status(tmp_path):
    # the output goes to a pipe (block-buffered): ending the process with os._exit must flush it first
    bundle = next(p for p in example_bundles() if p.name.startswith("drogue"))
    proc = _run(["validate", str(bundle)], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.rstrip().endswith("F_D3, F_D6"), proc.stdout[-300:]
    bad = _run(["validate", str(tmp_path / "no-such-bundle")], tmp_path)
    assert bad.returncode == 2 and "no-such-bundle" in bad.stdout + bad.stderr


def test_the_program_runs_the_exit_handlers_then_ends_at_once_with_the_commands_status(monkeypatch):
    import threading

    calls = []
    # no thread of its own: a thread an earlier test left in this worker must not decide the exit taken
    monkeypatch.setattr(threading, "enumerate", lambda: [threading.main_thread()])
    monkeypatch.setattr(entry, "main", lambda: calls.append("command") or 2)
    monkeypatch.setattr("atexit._run_exitfuncs", lambda: calls.append("exit handlers"))
    monkeypatch.setattr("os._exit", lambda status: calls.append(status))
    entry.run_program()
    assert calls == ["command", "exit handlers", 2]


def test_the_program_takes_the_ordinary_exit_while_a_thread_it_must_wait_for_runs(monkeypatch):
    import threading

    release = threading.Event()
    worker = threading.Thread(target=release.wait, args=(60,))
    worker.start()                            # non-daemon and running: os._exit would cut it off
    exits = []
    monkeypatch.setattr(entry, "main", lambda: 3)
    monkeypatch.setattr("os._exit", exits.append)
    try:
        with pytest.raises(SystemExit) as stop:
            entry.run_program()
    finally:
        release.set()
        worker.join()
    assert stop.value.code == 3 and exits == []


def test_bad_input_after_the_server_started_is_still_one_clear_message(tmp_path):
    proc = _run(["fit", str(tmp_path / "no-such-bundle"), "--out", str(tmp_path / "fit")], tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert "no-such-bundle" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "fit").exists()


@pytest.mark.slow
def test_a_fit_through_the_program_uses_the_early_server_and_writes_its_outputs(tmp_path):
    bundle = next(p for p in example_bundles() if p.name.startswith("drogue"))
    out = tmp_path / "fit"
    proc = _run(["fit", str(bundle), "--out", str(out), "--ensembles", "2", "--ess-target", "400"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "running on 2 local processes" in proc.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["diagnostics"]["converged"]
    assert len(list(out.glob("*.png"))) >= 8


def test_the_fit_command_leaves_matplotlib_to_its_workers(tmp_path):
    """The fit command's own process plans the figures and computes the checks; the workers draw. Importing
    matplotlib there cost 0.45-0.6 s of CPU beside workers that fill the cores. Run up to the bundle's
    refusal (unreadable TOML), after every import of the command (matplotlib in it before: fails there)."""
    (tmp_path / "bundle").mkdir()
    (tmp_path / "bundle" / "test.toml").write_text("x = [\n")
    code = ("import os, sys; os.environ['MPLBACKEND'] = 'Agg'; from cpas_bayes.app.cli import main; "
            f"status = main(['fit', {str(tmp_path / 'bundle')!r}, '--out', {str(tmp_path / 'fit')!r}]); "
            "print(status, 'cpas_bayes.outputs.fit_figures' in sys.modules, 'matplotlib' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert proc.stdout.split()[-3:] == ["2", "True", "False"], (proc.stdout, proc.stderr)

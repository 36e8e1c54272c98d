"""Campaign: configuration, validation of a folder, and a small campaign run twice and grown by one test."""

from __future__ import annotations

import json
import time

import pytest

from cpas_bayes.app import campaign as cp
from cpas_bayes.app import campaign_config as cfg
from cpas_bayes.app.cli import main
from cpas_bayes.core.errors import InputError
from cpas_bayes.data.synth import write_synthetic


def test_the_documented_example_config_reads(tmp_path):
    path = tmp_path / "campaign.toml"
    path.write_text(cfg.CONFIG_EXAMPLE)
    config = cfg.load_config(path)
    assert config.name == "EDU Drogue and Main campaign"
    assert config.diagnose == "screen" and config.montecarlo_runs == 10000 and config.fit_ensembles == 4
    assert config.model_forms is True


@pytest.mark.parametrize("text,where", [
    ("[fit]\nensemble = 2\n", "fit.ensemble"),
    ("colour = 'red'\n", "colour"),
    ("[diagnose]\nmode = 'sometimes'\n", "diagnose.mode"),
    ("[diagnose]\ncandidates = ['wake']\n", "diagnose.candidates"),
    ("[diagnose]\nmodel_forms = 'yes'\n", "diagnose.model_forms"),
    ("[montecarlo]\nruns = 'many'\n", "montecarlo.runs"),
    ("[fit]\ncoordinates = 'drag_areas'\n", "fit.coordinates"),
])
def test_a_bad_config_is_refused_naming_the_key(tmp_path, text, where):
    path = tmp_path / "c.toml"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        cfg.load_config(path)
    assert str(path) in str(err.value) and where in str(err.value)


def test_every_bad_bundle_is_listed_and_nothing_is_written(tmp_path, capsys):
    folder = tmp_path / "tests"
    write_synthetic("drogue", "none", 1, folder / "good")
    for bad in ("bad1", "bad2"):
        b = write_synthetic("drogue", "none", 2, folder / bad)
        (b / "data.csv").write_text("time,G\n0,1\n")
    out = tmp_path / "out"
    assert main(["campaign", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "2 of 3 bundles" in err and "bad1" in err and "bad2" in err
    assert not out.exists()


def test_configurations_are_named_by_kind_count_and_stages():
    from cpas_bayes.data.synth import synthesize

    assert cp.configuration_of(synthesize("drogue", "none", 1)[0]) == "2xdrogue-2st"
    assert cp.configuration_of(synthesize("main", "none", 1)[0]) == "3xmain-3st"


def test_a_tests_cost_ranks_logger_drops_over_mains_over_drogues():
    from cpas_bayes.data.synth import synthesize
    from cpas_bayes.data.synth_logger import synthesize_logger

    drogue, main_ = synthesize("drogue", "none", 1)[0], synthesize("main", "none", 1)[0]
    logger = synthesize_logger("logger-drop", 1)[0]
    # measured on the benchmark run: logger drop 70 s > three-Main 37 s > two-Drogue 15 s
    assert cp.test_cost(logger) > cp.test_cost(main_) > cp.test_cost(drogue)


QUICK = """
name = "test campaign"
workers = 1
[fit]
ensembles = 1
max_steps = 1000
stop = "tau"
tau_factor = 10
[diagnose]
model_forms = false
candidates = ["sensor_lag"]     # the verdicts' flow through the campaign, not the catalogue (test_diagnose)
[montecarlo]
runs = 400
[compare]
runs = 200
[pool]
draws = 1000
"""


@pytest.mark.slow
def test_a_campaign_runs_reruns_in_seconds_and_grows_by_one_fit(tmp_path):
    folder = tmp_path / "bundles"
    write_synthetic("drogue", "none", 31, folder / "T1")
    write_synthetic("drogue", "sensor_lag", 33, folder / "T3", magnitude=0.05)
    config = tmp_path / "campaign.toml"
    config.write_text(QUICK)
    out = tmp_path / "out"
    assert main(["campaign", str(folder), "--out", str(out), "--config", str(config)]) == 0

    manifest = json.loads((out / "campaign.json").read_text())
    names = manifest["tests"]
    assert len(names) == 2
    causes = manifest["causes"]
    lag_test = next(n for n in names if "sensor_lag" in n)
    assert causes[lag_test] == ["sensor_lag"]
    assert all(c == [] for n, c in causes.items() if n != lag_test)
    assert manifest["verdicts"][lag_test] == "named" and manifest["flags"] == {n: [] for n in names}
    # the lag test enters the memo with its extended fit
    assert manifest["pooled_fits"][lag_test].endswith("diagnosis/extended")
    assert (out / "memo" / "memo.toml").is_file()
    # the pool's own tasks are timed where they ran (benchmarks' Amdahl law spreads them over workers)
    pool = next(s for s in manifest["steps"] if s["name"] == "pool")
    assert pool["tasks"] >= 2 + 4 and 0 < pool["longest_task_seconds"] <= pool["task_seconds"]
    mc = out / "montecarlo" / "2xdrogue-2st"
    for f in ("runs.csv", "summary.json", "peak_loads.png", "np_vs_n.json", "fill_time_np_vs_n.png"):
        assert (mc / f).stat().st_size > 0, f
    for n in names:
        for f in ("reduction/reduction.png", "fit/posterior.nc", "fit/bands.png", "fit/checks.json",
                  "diagnosis/diagnosis.json", "compare/compare.json", "compare/compare.png"):
            assert (out / "tests" / n / f).stat().st_size > 0, (n, f)
    md = (out / "report.md").read_text()
    html = (out / "index.html").read_text()
    for section in ("## Diagnoses", "## Model memo", "## Monte Carlo per configuration", "## Load comparisons",
                    "## Convergence and health of the fits"):
        assert section in md
    images = [line.split("](")[1].rstrip(")") for line in md.splitlines() if line.startswith("![")]
    assert len(images) >= 2 * 8
    for rel in images:
        assert (out / rel).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", rel
    assert html.count("<img") == len(images) and "http" not in html

    # nothing changed: every step kept, seconds
    started = time.perf_counter()
    assert main(["campaign", str(folder), "--out", str(out), "--config", str(config)]) == 0
    assert time.perf_counter() - started < 30
    steps = json.loads((out / "campaign.json").read_text())["steps"]
    assert all(s["status"] == "cached" for s in steps)

    # one test added, run on two workers (fits and diagnoses as chained tasks): its own steps and the pooled
    # ones run, the other tests' are kept (the number of workers is not part of a step's key)
    write_synthetic("drogue", "none", 34, folder / "T4")
    assert main(["campaign", str(folder), "--out", str(out), "--config", str(config), "--workers", "2"]) == 0
    steps = {s["name"]: s["status"] for s in json.loads((out / "campaign.json").read_text())["steps"]}
    new = next(n for n in json.loads((out / "campaign.json").read_text())["tests"] if n not in names)
    assert steps[f"{new} fit"] == "ran" and steps[f"{new} diagnosis"] == "ran" and steps["pool"] == "ran"
    assert all(steps[f"{n} fit"] == "cached" and steps[f"{n} diagnosis"] == "cached" for n in names)
    assert json.loads((out / "tests" / new / "diagnosis" / "diagnosis.json").read_text())["causes"] == []


def test_a_bundle_is_keyed_by_what_is_read_of_it(tmp_path):
    """The campaign's key of a bundle hashes test.toml, data.csv and the test's own prior files: a fit or a
    note written inside the bundle folder keeps the key (before, it changed it, and re-ran the test's steps),
    a changed byte of the data or of a prior file changes it."""
    from cpas_bayes.app.campaign import bundle_digest

    folder = tmp_path / "T1"
    write_synthetic("drogue", "none", 31, folder)
    prior = tmp_path / "mine.toml"
    prior.write_text("# a prior file\n")
    key = bundle_digest(folder, (prior,))
    (folder / "notes.txt").write_text("dropped on a windy day\n")
    (folder / "fit").mkdir()
    (folder / "fit" / "posterior.nc").write_bytes(b"\0" * 1000)
    assert bundle_digest(folder, (prior,)) == key
    prior.write_text("# a prior file, edited\n")
    assert bundle_digest(folder, (prior,)) != key
    prior.write_text("# a prior file\n")
    data = (folder / "data.csv").read_text()
    (folder / "data.csv").write_text(data.replace(",", ", ", 1))
    assert bundle_digest(folder, (prior,)) != key

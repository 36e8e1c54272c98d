"""The report's first screen, built from a fake campaign folder on disk (no fit, no sampling).

The folder holds what a campaign writes and the report reads: ``campaign.json``,
each test's ``fit/summary.json``, ``diagnosis/diagnosis.json`` in the old
schema (``cause``) and the new one (``causes``, ``verdict``, ``unexplained``),
a ``compare/compare.json`` and tiny PNG figures.
"""

from __future__ import annotations

import json
import re
import struct
import zlib
from html.parser import HTMLParser

import pytest

from cpas_bayes.app import campaign as cp
from cpas_bayes.core.errors import InputError
from cpas_bayes.core.ownership import claim_folder
from cpas_bayes.outputs.report import report_markdown, write_report

EVIL = "<script>alert('x')"
TESTS = ["T-none", "T-lag", "T-mass-unexplained", "T-unexplained", EVIL]


def _png(path):
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\x00\xff\x00\x00")) + chunk(b"IEND", b""))


def _write(path, doc):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc), encoding="utf-8")


def _compare(name):
    stage = {"stage": "disreef 1", "interval": [1.0, 9.0],
             "measured": {"accelerometer": {"load": 28160.0, "sigma": 380.0, "time": 1.5}, "load_cells": None},
             "predicted": {"population": {"peak_load": {"mean": 27800.0, "sd": 2300.0, "q01": 23000.0,
                                                        "q05": 24400.0, "q50": 27566.0, "q95": 31700.0,
                                                        "q99": 34000.0}}},
             "comparisons": {"population": {"accelerometer": {"percentile": 99.1}}}}
    return {"test": name, "units": {"force": "lbf", "time": "s"}, "stages": [stage]}


@pytest.fixture
def campaign_out(tmp_path):
    out = tmp_path / "out"
    claim_folder(out)  # as a campaign does: the report then replaces its own files
    diagnoses = {
        "T-none": {"test": "T-none", "cause": "none", "reasons": ["no physical term raised the MAP ..."],
                   "candidates": []},
        "T-lag": {"test": "T-lag", "cause": "sensor_lag", "reasons": ["sensor_lag gains ..."],
                  "candidates": [{"name": "sensor_lag", "elpd_diff": 403.2, "elpd_diff_se": 43.0}]},
        "T-mass-unexplained": {
            "test": "T-mass-unexplained", "cause": "added_mass", "causes": ["added_mass", "unexplained"],
            "verdict": "named", "reasons": ["added_mass gains ..."],
            "candidates": [{"name": "added_mass", "elpd_diff": 141.0, "elpd_diff_se": 30.0}],
            "unexplained": {"elpd_gain": 23.0, "elpd_gain_se": 8.0, "share_explained": 0.8,
                            "where": [{"channel": "F_D2", "phase": "disreef 1", "t_start": 12.31, "t_end": 13.08}]},
            "discrepancy": {"elpd_gain": 23.0, "elpd_gain_se": 8.0, "figure": "discrepancy.png"},
            "warnings": ["2 bins with Pareto k > 0.7"]},
        "T-unexplained": {
            "test": "T-unexplained", "cause": "unexplained", "causes": ["unexplained"], "verdict": "unexplained",
            "reasons": ["no term explains ..."],
            "unexplained": {"elpd_gain": 31.0, "elpd_gain_se": 9.5, "share_explained": 0.0,
                            "where": [{"channel": "acc", "phase": "reefed 1", "t_start": 1.4, "t_end": 2.2}]}},
        EVIL: {"test": EVIL, "causes": ["unexplained"], "verdict": "unexplained", "reasons": [EVIL],
               "unexplained": {"elpd_gain": 5.0, "elpd_gain_se": 1.0,
                               "where": [{"channel": "<img src=x onerror=alert(2)>", "phase": EVIL,
                                          "t_start": 0.0, "t_end": 1.0}]},
               "warnings": [EVIL]},
    }
    for name in TESTS:
        base = out / "tests" / name
        _write(base / "fit" / "summary.json", {
            "parachutes": {"D1": {"kind": "drogue"}, "D2": {"kind": "drogue"}},
            "diagnostics": {"converged": True, "rhat_max": 1.01, "ess_bulk_min": 400, "ess_tail_min": 380,
                            "tau_max": 40, "acceptance": 0.3}})
        _write(base / "diagnosis" / "diagnosis.json", diagnoses[name])
        _png(base / "diagnosis" / "residuals.png")
        _write(base / "compare" / "compare.json", _compare(name))
    _png(out / "tests" / "T-mass-unexplained" / "diagnosis" / "discrepancy.png")
    (out / "tests" / "T-lag" / "diagnosis" / "extended").mkdir()
    pooled = {n: f"tests/{n}/fit" for n in TESTS}
    pooled["T-lag"] = "tests/T-lag/diagnosis/extended"
    _write(out / "campaign.json", {
        "campaign": "fake", "folder": "/data/bundles", "version": "0", "config": {}, "tests": TESTS,
        "configurations": {},
        "causes": {"T-none": [], "T-lag": ["sensor_lag"], "T-mass-unexplained": ["added_mass", "unexplained"],
                   "T-unexplained": ["unexplained"], EVIL: ["unexplained"]},
        "flags": {"T-none": [], "T-lag": [], "T-mass-unexplained": ["unexplained"], "T-unexplained": ["unexplained"],
                  EVIL: ["unexplained"]},
        "pooled_fits": pooled, "steps": [], "seconds": 1.0})
    write_report(out)
    return out


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.ids, self.hrefs, self.srcs, self.tags = set(), [], [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append(tag)
        if "id" in a:
            self.ids.add(a["id"])
        if a.get("href"):
            self.hrefs.append(a["href"])
        if tag == "img":
            self.srcs.append(a["src"])


def _rows(page):
    """(row class, anchor, test name as written, badge class) of the at-a-glance table."""
    return re.findall(r"<tr class='(\w+)'><td class='test'><a href='#(test-\d+)'>(.*?)</a><br>"
                      r"<span class='badge (\w+)'>", page)


def test_the_first_screen_lists_every_test_with_its_verdict_badge(campaign_out):
    page = (campaign_out / "index.html").read_text(encoding="utf-8")
    rows = _rows(page)
    assert [r[2] for r in rows] == ["T-none", "T-lag", "T-mass-unexplained", "T-unexplained",
                                    "&lt;script&gt;alert(&#x27;x&#x27;)"]
    assert [r[3] for r in rows] == ["none", "named", "named", "unexplained", "unexplained"]
    assert [r[1] for r in rows] == [f"test-{i}" for i in range(1, 6)]
    # the first screen comes before the rest of the report, and the badges are coloured by the style sheet
    assert page.index("at-a-glance") < page.index("id='diagnoses'")
    for verdict in ("none", "named", "unexplained"):
        assert f".badge.{verdict}{{background:var(--{verdict})}}" in page
    assert "<script" not in page.lower() and "http" not in page


def test_the_sentences_say_what_is_missed_and_where(campaign_out):
    page = (campaign_out / "index.html").read_text(encoding="utf-8")
    md = report_markdown(campaign_out)
    assert "The simulation misses the canopy&#x27;s added mass (+141 ± 30 elpd) and something unexplained in load " \
           "cell F_D2 during disreef 1 (+23 ± 8 elpd)." in page
    assert "The simulation misses a lag of the load cells behind the accelerometer (+403 ± 43 elpd)." in page
    assert "The simulation matches the data" in page
    for where in ("load cell F_D2, disreef 1, 12.3–13.1 s", "accelerometer, reefed 1, 1.4–2.2 s"):
        assert f"<li>{where}</li>" in page and where in md
    # the thumbnail: discrepancy.png when written, residuals.png otherwise; none for a test without misfit
    parser = _Links()
    parser.feed(page)
    assert "tests/T-mass-unexplained/diagnosis/discrepancy.png" in parser.srcs
    assert "tests/T-unexplained/diagnosis/residuals.png" in parser.srcs
    assert not any(s.startswith("tests/T-none/diagnosis") for s in parser.srcs)


def test_tests_pooled_with_an_unexplained_misfit_are_flagged(campaign_out):
    page = (campaign_out / "index.html").read_text(encoding="utf-8")
    md = report_markdown(campaign_out)
    rows = re.findall(r"<tr class='\w+'>(.*?)</tr>", page.split("id='at-a-glance'")[1].split("</table>")[0])
    flagged = {re.search(r"href='#test-\d+'>(.*?)</a>", r).group(1): "⚑ flagged" in r for r in rows}
    assert flagged == {"T-none": False, "T-lag": False, "T-mass-unexplained": True, "T-unexplained": True,
                       "&lt;script&gt;alert(&#x27;x&#x27;)": True}
    assert "pooled with its extended fit (free of sensor lag)" in page
    md_rows = {line.split("|")[1].strip(): line for line in md.splitlines() if line.startswith("| [")}
    assert "**flagged**" in md_rows["[T-unexplained](#test-4)"] and "flagged" not in md_rows["[T-lag](#test-2)"]


def test_every_anchor_of_the_report_resolves_and_every_image_is_on_disk(campaign_out):
    page = (campaign_out / "index.html").read_text(encoding="utf-8")
    parser = _Links()
    parser.feed(page)
    internal = [h[1:] for h in parser.hrefs if h.startswith("#")]
    assert {f"test-{i}" for i in range(1, 6)} <= set(internal)
    assert {"diagnoses", "load-comparisons", "convergence-and-health-of-the-fits"} <= set(internal)
    assert set(internal) <= parser.ids
    # each test's anchor sits right before its own section
    for i, name in enumerate(["T-none", "T-lag"], start=1):
        assert re.search(rf"<a id='test-{i}'></a><h2 id='[a-z0-9-]+'>Test {name}</h2>", page)
    from urllib.parse import unquote

    for src in parser.srcs:
        assert (campaign_out / unquote(src)).is_file(), src


def test_names_from_the_data_are_escaped(campaign_out):
    page = (campaign_out / "index.html").read_text(encoding="utf-8")
    parser = _Links()
    parser.feed(page)
    assert "script" not in parser.tags and parser.tags.count("img") == len(parser.srcs)
    assert "onerror=alert(2)" not in page.replace("&lt;img src=x onerror=alert(2)&gt;", "")
    assert "load cell &lt;img src=x onerror=alert(2)&gt;" in page


def test_an_old_manifest_and_old_diagnoses_still_make_a_report(campaign_out):
    manifest = json.loads((campaign_out / "campaign.json").read_text())
    manifest["causes"] = {"T-none": "none", "T-lag": "sensor_lag", "T-mass-unexplained": "added_mass",
                          "T-unexplained": "none", EVIL: None}
    del manifest["flags"]
    (campaign_out / "campaign.json").write_text(json.dumps(manifest))
    write_report(campaign_out)
    rows = _rows((campaign_out / "index.html").read_text(encoding="utf-8"))
    # the diagnosis files decide; the flags follow from their causes
    assert [r[3] for r in rows] == ["none", "named", "named", "unexplained", "unexplained"]


def test_the_report_is_rebuilt_from_the_files_alone(campaign_out):
    first = (campaign_out / "index.html").read_bytes()
    (campaign_out / "index.html").unlink()
    write_report(campaign_out)
    assert (campaign_out / "index.html").read_bytes() == first


def test_the_campaign_reads_new_and_old_diagnoses(campaign_out):
    assert cp.diagnosed_causes(campaign_out, "T-none") == []
    assert cp.diagnosed_causes(campaign_out, "T-lag") == ["sensor_lag"]
    assert cp.diagnosed_causes(campaign_out, "T-mass-unexplained") == ["added_mass", "unexplained"]
    assert cp.diagnosed_cause(campaign_out, "T-unexplained") == "unexplained"
    assert [cp.verdict_of(cp.diagnosed_causes(campaign_out, n)) for n in TESTS] == [
        "none", "named", "named", "unexplained", "unexplained"]
    assert cp.pooled_fit_folder(campaign_out, "T-lag").parts[-2:] == ("diagnosis", "extended")
    assert cp.pooled_fit_folder(campaign_out, "T-unexplained").name == "fit"
    assert cp.pool_flags(campaign_out, "T-mass-unexplained") == ["unexplained"] and not cp.pool_flags(
        campaign_out, "T-lag")
    assert cp.diagnosed_causes(campaign_out, "T-missing") is None


@pytest.mark.parametrize("doc,key", [({"causes": ["added_mass", "gremlins"]}, "key 'causes'"),
                                     ({"cause": "gremlins"}, "key 'cause'"),
                                     ({"causes": "added_mass"}, "key 'causes'")])
def test_diagnosed_causes_refuses_an_unknown_cause_naming_the_file_and_key(campaign_out, doc, key):
    path = campaign_out / "tests" / "T-none" / "diagnosis" / "diagnosis.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        cp.diagnosed_causes(campaign_out, "T-none")
    assert str(path) in str(err.value) and key in str(err.value)
    assert "re-run the campaign" in str(err.value)


def test_a_reading_warning_said_by_the_fit_and_the_diagnosis_is_listed_once(tmp_path):
    """A test whose readings have a unit off: its fit's health and its diagnosis both say so (the diagnosis'
    warnings begin with the reduction's); the report's record lists it once, in the fit's order, beside what only the
    diagnosis said."""
    from cpas_bayes.outputs.report_html import test_overview

    said = "data.csv qbar is 0.0479× ½·density·airspeed² (...)"
    base = tmp_path / "tests" / "T1"
    _write(base / "fit" / "summary.json", {"warnings": [{"code": "air_data_units", "message": said},
                                                        {"code": "prior_bound", "message": "cd_o piled up"}]})
    _write(base / "diagnosis" / "diagnosis.json", {"test": "T1", "cause": "none", "causes": [], "reasons": [],
                                                    "warnings": [said, "not tried: sensor_lag (...)"]})
    (record,) = test_overview(tmp_path, {"tests": ["T1"]})
    assert record["warnings"] == [f"fit: {said}", "fit: cd_o piled up", "not tried: sensor_lag (...)"]

"""The campaign report: ``report.md`` and a self-contained ``index.html`` beside the figures.

It opens on a first screen (:mod:`cpas_bayes.outputs.report_html`): each test's
verdict, what the simulation gets wrong and where, what the memo pooled and
flagged, and its peak loads against the prediction; then the diagnoses, the
memo, the Monte Carlo, the load comparisons, convergence and each test's
section (anchored ``test-1``, ``test-2``, … in the manifest's order).

Built only from the files a campaign wrote (:mod:`cpas_bayes.app.campaign`), so it
can be rebuilt at any time (``write_report(OUT)``) and never recomputes
anything. Figures are referenced by relative path: the report folder can be
moved or zipped whole and opened without a network.
"""

from __future__ import annotations

import json
from pathlib import Path

from cpas_bayes.core.files import write_text
from cpas_bayes.core.inputs import inside
from cpas_bayes.outputs.report_html import (BADGE, first_screen_html, first_screen_markdown, fit_health_messages,
                                            html_page, markdown_body, test_overview)

FORCE = {"US": "lbf", "SI": "N"}


def _read(path):
    path = Path(path)
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None


def _img(out, path, alt):
    path = Path(path)
    return f"![{alt}]({path.relative_to(out).as_posix()})" if path.is_file() else f"*({alt}: not written)*"


def _fmt(v, digits=3):
    return "—" if v is None else f"{v:.{digits}g}"


def _summary_section(out, manifest, records):
    lines = ["Read it in this order: the **diagnoses** (does the simulation miss anything, test by test?), the "
             "**memo** (the pooled dispersions a Monte Carlo draws from), the **Monte Carlo** (n_p against n "
             "dispersion; predicted peak loads), the **load comparisons** (would the memo have predicted each "
             "test?), then each test's evidence.", "",
             "## Diagnoses", "",
             "| test | configuration | verdict | causes | pooled fit | the diagnosis's first reason |",
             "|---|---|---|---|---|---|"]
    for r in records:
        chutes = (_read(inside(out / "tests", r["name"]) / "fit" / "summary.json") or {}).get("parachutes", {})
        kinds = " + ".join(sorted({p["kind"] for p in chutes.values()}))
        d = _read(inside(out / "tests", r["name"]) / "diagnosis" / "diagnosis.json")
        words = "diagnosis off" if d is None else (d["reasons"][0] if d.get("reasons") else "")
        causes = "—" if r["causes"] is None else (" + ".join(r["causes"]) or "none")
        pooled = (r["pooled"] or "—") + (" (flagged)" if r["flags"] else "")
        lines.append(f"| {r['name']} | {len(chutes)} × {kinds} | **{BADGE[r['verdict']]}** | {causes} | {pooled} "
                     f"| {words} |")
    named = [r for r in records if r["verdict"] not in (None, "none")]
    lines += ["", (f"Causes in {len(named)} test(s): " + ", ".join(f"{r['name']} ({' + '.join(r['causes'])})"
                                                             for r in named)
                   + ". Tests with a measurement cause (friction drift, sensor lag) enter the memo with their "
                     "extended fit; tests with an unexplained misfit enter it as they are, flagged; see each "
                     "test's diagnosis below.") if named else
              "No test shows a cause the baseline simulation misses.", ""]
    return lines


def _convergence_section(out, manifest):
    lines = ["## Convergence and health of the fits", "",
             "| test | converged | R-hat max | bulk ESS min | tail ESS min | τ max [steps] | acceptance | "
             "health warnings |",
             "|---|---|---|---|---|---|---|---|"]
    listed = []
    for name in manifest["tests"]:
        s = _read(inside(out / "tests", name) / "fit" / "summary.json")
        d = s["diagnostics"]
        health = fit_health_messages(s)
        lines.append(f"| {name} | {'yes' if d['converged'] else 'NO'} | {d['rhat_max']:.4f} | "
                     f"{d['ess_bulk_min']:.0f} | {d['ess_tail_min']:.0f} | {d['tau_max']:.0f} | "
                     f"{d['acceptance']:.2f} | {len(health) or 'none'} |")
        listed += [f"* **{name}** — {m.removeprefix('fit: ')}" for m in health]
    if listed:
        lines += ["", "Fit health warnings (a fit can converge and still be bounded by its prior, noisier than "
                  "its stated sigmas, or unlike its data):", ""] + listed
    return lines + [""]


def _memo_section(out):
    memo_md = out / "memo" / "memo.md"
    lines = ["## Model memo", ""]
    if not memo_md.is_file():
        return lines + ["*(no memo written)*", ""]
    body = memo_md.read_text(encoding="utf-8").splitlines()
    # demote the memo's own headings under this section
    lines += [("##" + ln) if ln.startswith("#") else ln for ln in body]
    lines += ["", "How to read it: each row is one parameter of one parachute kind and stage; a Monte Carlo "
                  "run draws it from the named family with the given location and scale, truncated to the "
                  "bounds. The forest plots show each test's posterior against the population "
                  "distribution: the population should cover the tests, and the tests' spread is the "
                  "dispersion the memo carries.", ""]
    for fig in sorted((out / "memo").glob("*.png")):
        lines.append(_img(out, fig, fig.stem.replace("_", " ")))
    return lines + [""]


def _montecarlo_section(out, manifest):
    lines = ["## Monte Carlo per configuration", ""]
    for name, like in manifest.get("configurations", {}).items():
        folder = inside(out / "montecarlo", name)
        doc = _read(folder / "np_vs_n.json")
        lines += [f"### {name} (flown like {like})", ""]
        if doc:
            lines += ["Peak fill times outside the range seen in the tests (seed §V.D):", "",
                      "| kind | stage | tested t_fp range [s] | n_p dispersed | n dispersed |", "|---|---|---|---|---|"]
            for g in doc["groups"]:
                lo, hi = g["tested_t_fp_range_s"]
                lines.append(f"| {g['kind']} | {g['stage']} | {lo:.2f}–{hi:.2f} | "
                             f"{100 * g['n_p']['fraction_outside']:.1f} % | {100 * g['n']['fraction_outside']:.1f} % |")
            lines.append("")
        lines += [_img(out, folder / "fill_time_np_vs_n.png", "fill times, n_p against n"),
                  _img(out, folder / "peak_loads.png", "peak loads"),
                  _img(out, folder / "fill_times.png", "fill times"), ""]
    return lines


def _comparison_section(out, manifest):
    lines = ["## Load comparisons", "",
             "Percentile of each measured stage peak load within the predicted distribution (its measurement "
             "sigma included): population = Monte Carlo with the memo, posterior = the test's own fit. "
             "Near 50 is expected; below 2.5 or above 97.5 is a surprise.", "",
             "| test | stage | measured (accelerometer) | population percentile | posterior percentile |",
             "|---|---|---|---|---|"]
    for name in manifest["tests"]:
        doc = _read(inside(out / "tests", name) / "compare" / "compare.json")
        if not doc:
            continue
        units = doc.get("units", {})
        unit = units.get("force", "") if isinstance(units, dict) else str(units)
        for st in doc["stages"]:
            acc = st["measured"]["accelerometer"]
            pop = st["comparisons"].get("population", {}).get("accelerometer", {})
            post = st["comparisons"].get("posterior", {}).get("accelerometer", {})
            lines.append(f"| {name} | {st['stage']} | {acc['load']:,.0f} ± {acc['sigma']:,.0f} {unit} | "
                         f"{_fmt(pop.get('percentile'))} | {_fmt(post.get('percentile'))} |")
    lines.append("")
    for name in manifest["tests"]:
        lines.append(_img(out, inside(out / "tests", name) / "compare" / "compare.png", f"{name} load comparison"))
    return lines + [""]


def _test_section(out, name, anchor):
    base = inside(out / "tests", name)
    lines = [f'<a id="{anchor}"></a>', f"## Test {name}", "", "### Reduction (accelerometer against scaled load cells)", "",
             _img(out, base / "reduction" / "reduction.png", f"{name} reduction"), "",
             "### Posterior bands over the data", "", _img(out, base / "fit" / "bands.png", f"{name} bands"),
             _img(out, base / "fit" / "loads.png", f"{name} loads"), "", "### Corner plots", ""]
    lines += [_img(out, p, p.stem) for p in sorted((base / "fit").glob("corner_*.png"))]
    lines += ["", "### Checks: PPC, LOO-PIT, residuals", "",
              _img(out, base / "fit" / "ppc.png", f"{name} PPC"),
              _img(out, base / "fit" / "loo_pit.png", f"{name} LOO-PIT"),
              _img(out, base / "fit" / "residuals.png", f"{name} residuals"), ""]
    diag = base / "diagnosis" / "diagnosis.md"
    if diag.is_file():
        text = diag.read_text(encoding="utf-8").splitlines()
        lines += ["### Diagnosis", ""] + [("###" + ln) if ln.startswith("#") else ln for ln in text[1:]]
        for fig in ("screen.png", "elpd.png", "discrepancy.png", "residuals.png", "comparison.png"):
            if (base / "diagnosis" / fig).is_file():
                lines.append(_img(out, base / "diagnosis" / fig, f"{name} diagnosis {fig[:-4]}"))
        lines.append("")
    return lines


def _manifest(out):
    manifest = _read(out / "campaign.json")
    if manifest is None:
        raise FileNotFoundError(f"{out / 'campaign.json'}: not a campaign folder (run 'cpas-bayes campaign')")
    return manifest


def _rest_markdown(out, manifest, records):
    """Everything after the first screen, as Markdown lines."""
    lines = _summary_section(out, manifest, records)
    lines += _memo_section(out)
    lines += _montecarlo_section(out, manifest)
    lines += _comparison_section(out, manifest)
    lines += _convergence_section(out, manifest)
    for r in records:
        lines += _test_section(out, r["name"], r["anchor"])
    return lines


def report_markdown(out) -> str:
    """The report of the campaign in folder ``out`` as Markdown."""
    out = Path(out)
    manifest = _manifest(out)
    records = test_overview(out, manifest)
    lines = first_screen_markdown(out, manifest, records) + _rest_markdown(out, manifest, records)
    return "\n".join(lines) + "\n"


def report_html(out) -> str:
    """The report of the campaign in folder ``out`` as one self-contained HTML page (no script, no network)."""
    out = Path(out)
    manifest = _manifest(out)
    records = test_overview(out, manifest)
    body = first_screen_html(out, manifest, records) + markdown_body("\n".join(_rest_markdown(out, manifest, records)))
    return html_page(f"Campaign report: {manifest.get('campaign', out.name)}", body)


def write_report(out) -> Path:
    """Write ``report.md`` and ``index.html`` into the campaign folder ``out``; return the HTML path."""
    out = Path(out)
    write_text(out / "report.md", report_markdown(out))
    write_text(out / "index.html", report_html(out))
    return out / "index.html"


def markdown_to_html(md, title="cpas_bayes report"):
    """A Markdown document of the reports' subset as a self-contained HTML page."""
    return html_page(title, markdown_body(md))

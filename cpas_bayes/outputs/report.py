"""The campaign report: ``report.md`` and a self-contained ``index.html`` beside the figures.

Built only from the files a campaign wrote (:mod:`cpas_bayes.app.campaign`), so it
can be rebuilt at any time (``write_report(OUT)``) and never recomputes
anything. Figures are referenced by relative path: the report folder can be
moved or zipped whole and opened without a network.
"""

from __future__ import annotations

import html
import json
import re
from pathlib import Path

from cpas_bayes.core.files import write_text
from cpas_bayes.core.inputs import inside

FORCE = {"US": "lbf", "SI": "N"}


def _read(path):
    path = Path(path)
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None


def _img(out, path, alt):
    path = Path(path)
    return f"![{alt}]({path.relative_to(out).as_posix()})" if path.is_file() else f"*({alt}: not written)*"


def _fmt(v, digits=3):
    return "—" if v is None else f"{v:.{digits}g}"


def _summary_section(out, manifest):
    causes = manifest.get("causes", {})
    lines = [f"# Campaign report: {manifest['campaign']}", "",
             f"{len(manifest['tests'])} flight tests from `{manifest['folder']}`, cpas_bayes {manifest['version']}; "
             f"this run took {manifest['seconds']:.0f} s "
             f"({sum(s['status'] == 'cached' for s in manifest['steps'])} of {len(manifest['steps'])} steps "
             "unchanged since the last run and kept).", "",
             "Read it in this order: the **diagnoses** (does the simulation miss anything, test by test?), the "
             "**memo** (the pooled dispersions a Monte Carlo draws from), the **Monte Carlo** (n_p against n "
             "dispersion; predicted peak loads), the **load comparisons** (would the memo have predicted each "
             "test?), then each test's evidence.", "",
             "## Diagnoses", "",
             "| test | configuration | cause | in words |", "|---|---|---|---|"]
    for name in manifest["tests"]:
        chutes = (_read(inside(out / "tests", name) / "fit" / "summary.json") or {}).get("parachutes", {})
        kinds = " + ".join(sorted({p["kind"] for p in chutes.values()}))
        d = _read(inside(out / "tests", name) / "diagnosis" / "diagnosis.json")
        cause = causes.get(name)
        words = "diagnosis off" if d is None else (d["reasons"][0] if d.get("reasons") else "")
        lines.append(f"| {name} | {len(chutes)} × {kinds} | **{cause or '—'}** | {words} |")
    named = [n for n, c in causes.items() if c and c != "none"]
    lines += ["", (f"Named causes in {len(named)} test(s): " + ", ".join(f"{n} ({causes[n]})" for n in named)
                   + ". Tests with a measurement cause (friction drift, sensor lag) enter the memo with their "
                     "extended fit; see each test's diagnosis below.") if named else
              "No test shows a physical cause the baseline simulation misses.", ""]
    return lines


def _convergence_section(out, manifest):
    lines = ["## Convergence of the fits", "",
             "| test | converged | R-hat max | bulk ESS min | tail ESS min | τ max [steps] | acceptance |",
             "|---|---|---|---|---|---|---|"]
    for name in manifest["tests"]:
        s = _read(inside(out / "tests", name) / "fit" / "summary.json")
        d = s["diagnostics"]
        lines.append(f"| {name} | {'yes' if d['converged'] else 'NO'} | {d['rhat_max']:.4f} | "
                     f"{d['ess_bulk_min']:.0f} | {d['ess_tail_min']:.0f} | {d['tau_max']:.0f} | "
                     f"{d['acceptance']:.2f} |")
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


def _test_section(out, name):
    base = inside(out / "tests", name)
    lines = [f"## Test {name}", "", "### Reduction (accelerometer against scaled load cells)", "",
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
        for fig in ("screen.png", "elpd.png", "residuals.png", "comparison.png"):
            if (base / "diagnosis" / fig).is_file():
                lines.append(_img(out, base / "diagnosis" / fig, f"{name} diagnosis {fig[:-4]}"))
        lines.append("")
    return lines


def report_markdown(out) -> str:
    """The report of the campaign in folder ``out`` as Markdown."""
    out = Path(out)
    manifest = _read(out / "campaign.json")
    if manifest is None:
        raise FileNotFoundError(f"{out / 'campaign.json'}: not a campaign folder (run 'cpas-bayes campaign')")
    lines = _summary_section(out, manifest)
    lines += _memo_section(out)
    lines += _montecarlo_section(out, manifest)
    lines += _comparison_section(out, manifest)
    lines += _convergence_section(out, manifest)
    for name in manifest["tests"]:
        lines += _test_section(out, name)
    return "\n".join(lines) + "\n"


def write_report(out) -> Path:
    """Write ``report.md`` and ``index.html`` into the campaign folder ``out``; return the HTML path."""
    out = Path(out)
    md = report_markdown(out)
    write_text(out / "report.md", md)
    title = md.splitlines()[0].lstrip("# ").strip()
    write_text(out / "index.html", markdown_to_html(md, title))
    return out / "index.html"


# ---------------------------------------------------------------------------
# a small Markdown subset → HTML


def _inline(text):
    text = html.escape(text)
    text = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", text)
    text = re.sub(r"`(.+?)`", r"<code>\1</code>", text)
    text = re.sub(r"(?<![\w*])\*(?!\s)(.+?)(?<!\s)\*(?![\w*])", r"<em>\1</em>", text)
    return text


def markdown_to_html(md, title="cpas_bayes report"):
    """Headings, tables, images, bullet lists, bold/italic/code and paragraphs: enough for the reports."""
    body, table, items = [], [], []

    def flush():
        if table:
            rows = [r for r in table if not set(r.replace("|", "").strip()) <= {"-", " ", ":"}]
            cells = [[_inline(c.strip()) for c in r.strip().strip("|").split("|")] for r in rows]
            head = "".join(f"<th>{c}</th>" for c in cells[0])
            rest = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in cells[1:])
            body.append(f"<table><tr>{head}</tr>{rest}</table>")
            table.clear()
        if items:
            body.append("<ul>" + "".join(f"<li>{_inline(i)}</li>" for i in items) + "</ul>")
            items.clear()

    for line in md.splitlines():
        if line.startswith("|"):
            table.append(line)
            continue
        if line.startswith("- "):
            items.append(line[2:])
            continue
        flush()
        if line.startswith("#"):
            level = min(6, len(line) - len(line.lstrip("#")))
            text = line.lstrip("#").strip()
            anchor = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
            body.append(f"<h{level} id='{anchor}'>{_inline(text)}</h{level}>")
        elif line.startswith("!["):
            alt, src = line[2:].split("](", 1)
            body.append(f"<figure><img src='{html.escape(src.rstrip(')'))}' alt='{html.escape(alt)}' "
                        f"loading='lazy'><figcaption>{html.escape(alt)}</figcaption></figure>")
        elif line.strip():
            body.append(f"<p>{_inline(line)}</p>")
    flush()
    style = ("body{font-family:sans-serif;max-width:1200px;margin:auto;padding:1em;line-height:1.4}"
             "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #bbb;padding:2px 6px;"
             "font-size:90%}img{max-width:100%}figure{margin:0.5em 0}figcaption{font-size:80%;color:#555}"
             "code{background:#f3f3f3;padding:0 3px}")
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{style}</style></head><body>{''.join(body)}</body></html>\n")

"""The campaign report's first screen: which tests the simulation gets wrong, how, where, and what it changes.

:func:`test_overview` reads, for every test of a campaign folder, the files the
campaign wrote (``campaign.json``, each ``diagnosis/diagnosis.json`` in its old
or new schema, ``compare/compare.json``) into one plain record;
:func:`first_screen_markdown` and :func:`first_screen_html` render those
records (the HTML with a small inline style sheet: no script, no external
asset). :func:`markdown_body` and :func:`html_page` turn the rest of the
report, written as a small Markdown subset, into HTML.

Every string taken from the data (test names, channels, phases, warnings) is
HTML-escaped where it is written; anchors are ``test-1``, ``test-2``, … in the
manifest's order of tests, never built from a name.
"""

from __future__ import annotations

import html
import json
import re
from pathlib import Path
from urllib.parse import quote

from cpas_bayes.core.inputs import inside

UNEXPLAINED = "unexplained"
VERDICTS = ("none", "named", UNEXPLAINED)
BADGE = {"none": "no misfit", "named": "named cause", UNEXPLAINED: "unexplained", None: "not diagnosed"}
CAUSE_WORDS = {
    "added_mass": "the canopy's added mass",
    "friction_drift": "a drift of the load cells' friction factor",
    "sensor_lag": "a lag of the load cells behind the accelerometer",
    "canopy_breathing": "the canopies' breathing after each peak",
    "correlated_noise": "time-correlated noise",
}
FLAG_WORDS = {
    UNEXPLAINED: "the unexplained misfit stays in its pooled fit",
    "no_extended_fit": "a measurement cause was named but no extended fit was written: the baseline was pooled",
}
SECTIONS = (("diagnoses", "Diagnoses"), ("model-memo", "Memo"), ("monte-carlo-per-configuration", "Monte Carlo"),
            ("load-comparisons", "Load comparisons"), ("convergence-and-health-of-the-fits", "Fit health"))


def read_doc(path):
    """A JSON file's content, or None when it is missing or not JSON (the report shows what is there)."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None
    except (ValueError, OSError):
        return None


def test_anchor(index):
    """The anchor of the ``index``-th test's section (0-based, manifest order)."""
    return f"test-{index + 1}"


def causes_of(diag, listed):
    """The causes, as a list, from a diagnosis document (new ``causes`` or old ``cause``) or the manifest's entry."""
    if isinstance(diag, dict) and isinstance(diag.get("causes"), list):
        return [str(c) for c in diag["causes"]]
    if isinstance(listed, list):
        return [str(c) for c in listed]
    cause = diag.get("cause") if isinstance(diag, dict) else listed
    if cause is None:
        return None
    return [] if cause == "none" else [str(cause)]


def verdict_of(causes, diag=None):
    if isinstance(diag, dict) and diag.get("verdict") in VERDICTS:
        return diag["verdict"]
    if causes is None:
        return None
    if any(c != UNEXPLAINED for c in causes):
        return "named"
    return UNEXPLAINED if causes else "none"


def _num(v, digits=3):
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return "—"
    return f"{v:,.0f}" if abs(v) >= 10 ** (digits - 1) else f"{v:.{digits}g}"


def _short(v):
    """A load for a glance: ``28.2k``, ``940``."""
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return "—"
    return f"{v / 1e3:.1f}k" if abs(v) >= 1e4 else f"{v:.3g}"


def _gain(g, se):
    if not isinstance(g, (int, float)):
        return ""
    return f"{g:+.0f} ± {se:.0f} elpd" if isinstance(se, (int, float)) else f"{g:+.0f} elpd"


def _channel(ch, article=False):
    if ch in ("acc", "accelerometer"):
        return "the accelerometer" if article else "accelerometer"
    return f"load cell {ch}"


def where_words(w):
    """One place of an unexplained misfit: ``load cell F_M1, disreef 1, 12.3–13.1 s``."""
    parts = [_channel(str(w.get("channel", "?")))]
    if w.get("phase"):
        parts.append(str(w["phase"]))
    t0, t1 = w.get("t_start"), w.get("t_end")
    if isinstance(t0, (int, float)) and isinstance(t1, (int, float)):
        parts.append(f"{t0:.1f}–{t1:.1f} s")
    return ", ".join(parts)


def _and(parts):
    return parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]


def sentence(verdict, causes, diag):
    """One plain sentence on what the simulation gets wrong in a test."""
    if verdict is None:
        return "Not diagnosed (diagnosis off, or not finished)."
    if verdict == "none":
        return "The simulation matches the data: no candidate term improves the fit."
    gains = {r.get("name"): r for r in (diag or {}).get("candidates") or [] if isinstance(r, dict)}
    parts = []
    for c in causes:
        if c == UNEXPLAINED:
            continue
        g = _gain(gains.get(c, {}).get("elpd_diff"), gains.get(c, {}).get("elpd_diff_se"))
        parts.append(CAUSE_WORDS.get(c, c.replace("_", " ")) + (f" ({g})" if g else ""))
    unexp = (diag or {}).get("unexplained") or {}
    if UNEXPLAINED in causes:
        where = [w for w in unexp.get("where") or [] if isinstance(w, dict)]
        text = "something no catalogued term explains" if not parts else "something unexplained"
        if where:
            w = where[0]
            text += f" in {_channel(str(w.get('channel', '?')), article=True)}"
            text += f" during {w['phase']}" if w.get("phase") else ""
            text += f" and {len(where) - 1} other place{'s' * (len(where) > 2)}" if len(where) > 1 else ""
        g = _gain(unexp.get("elpd_gain"), unexp.get("elpd_gain_se"))
        parts.append(text + (f" ({g})" if g else ""))
    out = "The simulation misses " + _and(parts) + "."
    share = unexp.get("share_explained")
    if UNEXPLAINED in causes and len(parts) > 1 and isinstance(share, (int, float)):
        out += f" The named terms explain {100 * share:.0f} % of the misfit."
    return out


def _peaks(doc):
    """Measured accelerometer stage peaks against the memo's Monte Carlo (population) prediction."""
    rows = []
    units = (doc or {}).get("units", {})
    unit = units.get("force", "") if isinstance(units, dict) else str(units or "")
    for st in (doc or {}).get("stages") or []:
        acc = (st.get("measured") or {}).get("accelerometer") or {}
        pred = ((st.get("predicted") or {}).get("population") or {}).get("peak_load") or {}
        comp = ((st.get("comparisons") or {}).get("population") or {}).get("accelerometer") or {}
        rows.append({"stage": str(st.get("stage", "")), "measured": acc.get("load"), "sigma": acc.get("sigma"),
                     "q05": pred.get("q05"), "q50": pred.get("q50"), "q95": pred.get("q95"),
                     "percentile": comp.get("percentile"), "unit": unit})
    return rows


def fit_health_messages(summary):
    """The health warnings of a fit's ``summary.json`` (:mod:`cpas_bayes.inference.fit_health`) as text."""
    out = []
    for w in (summary or {}).get("warnings") or []:
        if isinstance(w, dict) and "message" in w:
            out.append(f"fit: {w['message']}")
    return out


def _warnings(summary, diag):
    """A test's fit health messages, then its diagnosis' warnings that the fit did not already say (the readings'
    own problems are in both)."""
    fit = fit_health_messages(summary)
    said = {m.removeprefix("fit: ") for m in fit}
    return fit + [str(w) for w in (diag or {}).get("warnings") or [] if str(w) not in said]


def test_overview(out, manifest):
    """One record per test of the campaign in ``out`` (manifest order), from the files on disk only."""
    out = Path(out)
    records = []
    for i, name in enumerate(manifest.get("tests", [])):
        base = inside(out / "tests", name)
        diag = read_doc(base / "diagnosis" / "diagnosis.json")
        causes = causes_of(diag, manifest.get("causes", {}).get(name))
        verdict = verdict_of(causes, diag)
        pooled = str(manifest.get("pooled_fits", {}).get(name, ""))
        flags = manifest.get("flags", {}).get(name)
        if not isinstance(flags, list):
            flags = [UNEXPLAINED] if causes and UNEXPLAINED in causes else []
        figure = None
        if verdict not in (None, "none"):
            figure = next((p for p in (base / "diagnosis" / "discrepancy.png", base / "diagnosis" / "residuals.png",
                                       base / "fit" / "residuals.png") if p.is_file()), None)
        unexp = (diag or {}).get("unexplained") or {}
        records.append({
            "name": name, "anchor": test_anchor(i), "verdict": verdict, "causes": causes,
            "sentence": sentence(verdict, causes or [], diag),
            "where": [where_words(w) for w in unexp.get("where") or [] if isinstance(w, dict)],
            "warnings": _warnings(read_doc(base / "fit" / "summary.json"), diag),
            "pooled": "extended" if pooled.rstrip("/").endswith("extended") else ("baseline" if pooled else None),
            "flags": [str(f) for f in flags],
            "figure": figure.relative_to(out).as_posix() if figure else None,
            "peaks": _peaks(read_doc(base / "compare" / "compare.json"))})
    return records


# ---------------------------------------------------------------------------
# Markdown


def _cell(text):
    return str(text).replace("|", "\\|")


def _pooled_words(r):
    if r["pooled"] is None:
        return "not pooled"
    words = f"{r['pooled']} fit"
    if r["pooled"] == "extended":
        words += " (free of " + ", ".join(c.replace("_", " ") for c in r["causes"] or [] if c != UNEXPLAINED) + ")"
    return words


def first_screen_markdown(out, manifest, records):
    steps = manifest.get("steps", [])
    lines = [f"# Campaign report: {manifest.get('campaign', Path(out).name)}", "",
             f"{len(records)} flight tests from `{manifest.get('folder', '?')}`, cpas_bayes "
             f"{manifest.get('version', '?')}; this run took {manifest.get('seconds', 0):.0f} s "
             f"({sum(s.get('status') == 'cached' for s in steps)} of {len(steps)} steps unchanged since the "
             "last run and kept).", "", "## At a glance", "",
             "| test | verdict | what the simulation gets wrong, and where | memo |", "|---|---|---|---|"]
    for r in records:
        where = ("<br>Where: " + "; ".join(r["where"])) if r["where"] else ""
        flag = "; **flagged**: " + "; ".join(FLAG_WORDS.get(f, f) for f in r["flags"]) if r["flags"] else ""
        lines.append(f"| [{_cell(r['name'])}](#{r['anchor']}) | **{BADGE[r['verdict']]}** | "
                     f"{_cell(r['sentence'])}{_cell(where)} | pooled with its {_cell(_pooled_words(r))}{_cell(flag)} |")
    lines += ["", "Peak loads, test against prediction (measured accelerometer peak ± sigma; the memo's Monte Carlo "
                  "median and 5–95 % range; percentile of the test in the prediction, surprising below 2.5 or "
                  "above 97.5):", "", "| test | stage | measured | predicted | percentile |", "|---|---|---|---|---|"]
    for r in records:
        for p in r["peaks"]:
            lines.append(f"| {_cell(r['name'])} | {_cell(p['stage'])} | {_num(p['measured'])} ± {_num(p['sigma'])} "
                         f"{p['unit']} | {_num(p['q50'])} ({_num(p['q05'])}–{_num(p['q95'])}) | "
                         f"{_num(p['percentile'], 2)} |")
    lines.append("")
    lines += [f"![{r['name']} misfit]({r['figure']})" for r in records if r["figure"]]
    return lines + [""]


# ---------------------------------------------------------------------------
# HTML


STYLE = """
:root{--none:#1a7f37;--named:#b35900;--unexplained:#c62828;--off:#8c959f;--line:#d8dee4;--muted:#57606a}
body{font-family:system-ui,"Segoe UI",Roboto,"DejaVu Sans",sans-serif;max-width:1240px;margin:0 auto;
 padding:0 16px 32px;line-height:1.4;color:#1f2328;font-size:15px}
h1{font-size:1.45em;margin:.5em 0 .1em}h2{border-bottom:1px solid var(--line);padding-bottom:.15em;margin-top:1.6em}
.meta{color:var(--muted);margin:.1em 0 .4em;font-size:.9em}
nav{font-size:.88em;padding:.35em 0;border-bottom:1px solid var(--line);margin-bottom:.6em}
nav a{margin-right:.9em;text-decoration:none;color:#0969da;white-space:nowrap}nav b{margin-right:.5em;color:var(--muted)}
.tally{margin:.5em 0;font-size:.95em}.tally .badge{margin-left:.6em}
.badge{display:inline-block;padding:1px 9px;border-radius:10px;font-size:.8em;font-weight:600;color:#fff;
 white-space:nowrap}
.badge.none{background:var(--none)}.badge.named{background:var(--named)}
.badge.unexplained{background:var(--unexplained)}.badge.off{background:var(--off)}
table.glance{width:100%;border-collapse:collapse;margin:.4em 0}
.glance th{border:none;text-align:left;font-size:.8em;color:var(--muted);font-weight:600;border-bottom:2px solid var(--line);
 padding:4px 8px}
.glance td{border:none;border-bottom:1px solid var(--line);padding:8px;vertical-align:top}
.glance td.test{width:11em;overflow-wrap:anywhere}.glance td.memo{width:12em;font-size:.92em}
.glance td.peaks{width:280px}.glance td.fig{width:190px}
.test .badge{margin-top:.35em}
.glance tr.none td:first-child{border-left:5px solid var(--none)}
.glance tr.named td:first-child{border-left:5px solid var(--named)}
.glance tr.unexplained td:first-child{border-left:5px solid var(--unexplained)}
.glance tr.off td:first-child{border-left:5px solid var(--off)}
.test a{font-weight:700;text-decoration:none;color:#0969da}.sub{color:var(--muted);font-size:.82em}
ul.where{margin:.25em 0 0;padding-left:1.1em;font-size:.88em;color:#3d444d}
.warn{font-size:.82em;color:#7d4e00;margin-top:.2em}
.flag{display:inline-block;margin-top:.2em;color:var(--unexplained);font-weight:600;font-size:.88em}
.pk{display:grid;grid-template-columns:4.6em 100px auto;gap:0 8px;align-items:center;font-size:.82em;
 white-space:nowrap;line-height:1.9}
.pk .st{color:var(--muted);overflow:hidden;text-overflow:ellipsis;white-space:nowrap}
.bar{position:relative;height:10px;background:#eef1f4;border-radius:5px}
.band{position:absolute;top:0;bottom:0;background:#a9bdd3;border-radius:5px}
.med{position:absolute;top:-2px;bottom:-2px;width:2px;background:#2c3e50}
.mark{position:absolute;top:-2px;width:10px;height:10px;margin-left:-6px;border-radius:50%;background:var(--none);
 border:2px solid #fff}
.mark.surprise{background:var(--unexplained)}
.pct.surprise{color:var(--unexplained);font-weight:700}
img.thumb{max-width:190px;max-height:120px;border:1px solid var(--line);border-radius:4px;display:block}
.legend{font-size:.8em;color:var(--muted)}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #c8ced4;padding:2px 6px;font-size:.9em}
img{max-width:100%}figure{margin:.5em 0}figcaption{font-size:.8em;color:#555}code{background:#f3f3f3;padding:0 3px}
"""


def _e(text):
    return html.escape(str(text), quote=True)


def _src(rel):
    return _e(quote(rel, safe="/"))


def _peak_html(p):
    vals = [v for v in (p["measured"], p["q05"], p["q95"]) if isinstance(v, (int, float))]
    pct = p["percentile"]
    surprise = " surprise" if isinstance(pct, (int, float)) and not 2.5 <= pct <= 97.5 else ""
    title = (f"measured {_num(p['measured'])} ± {_num(p['sigma'])} {p['unit']}; predicted median {_num(p['q50'])}, "
             f"5–95 % {_num(p['q05'])}–{_num(p['q95'])} {p['unit']}")
    bar = ""
    if len(vals) == 3:
        lo, hi = min(vals), max(vals)
        pad = 0.08 * (hi - lo) or 1.0
        lo, hi = lo - pad, hi + pad

        def x(v):
            return f"{100 * (v - lo) / (hi - lo):.1f}%"
        bar = (f"<span class='band' style='left:{x(p['q05'])};width:{100 * (p['q95'] - p['q05']) / (hi - lo):.1f}%'>"
               "</span>" + (f"<span class='med' style='left:{x(p['q50'])}'></span>"
                            if isinstance(p["q50"], (int, float)) else "")
               + f"<span class='mark{surprise}' style='left:{x(p['measured'])}'></span>")
    pct_text = f"p{pct:.0f}" if isinstance(pct, (int, float)) else "—"
    return (f"<div class='pk' title='{_e(title)}'><span class='st'>{_e(p['stage'])}</span>"
            f"<span class='bar'>{bar}</span><span><span class='pct{surprise}'>{pct_text}</span> · "
            f"{_e(_short(p['measured']))} vs {_e(_short(p['q50']))} {_e(p['unit'])}</span></div>")


def _row_html(r):
    v = r["verdict"] or "off"
    where = ("<ul class='where'>" + "".join(f"<li>{_e(w)}</li>" for w in r["where"]) + "</ul>") if r["where"] else ""
    warn = "".join(f"<div class='warn'>⚠ {_e(w)}</div>" for w in r["warnings"][:2])
    memo = _e("pooled with its " + _pooled_words(r))
    if r["flags"]:
        memo += "<br><span class='flag'>⚑ flagged</span> <span class='sub'>" + _e(
            "; ".join(FLAG_WORDS.get(f, f) for f in r["flags"])) + "</span>"
    peaks = "".join(_peak_html(p) for p in r["peaks"]) or "<span class='sub'>no load comparison</span>"
    thumb = (f"<a href='{_src(r['figure'])}'><img class='thumb' src='{_src(r['figure'])}' "
             f"alt='{_e(r['name'])} misfit'></a>") if r["figure"] else ""
    return (f"<tr class='{v}'><td class='test'><a href='#{r['anchor']}'>{_e(r['name'])}</a><br>"
            f"<span class='badge {v}'>{_e(BADGE[r['verdict']])}</span></td>"
            f"<td>{_e(r['sentence'])}{where}{warn}</td><td class='memo'>{memo}</td><td class='peaks'>{peaks}</td>"
            f"<td class='fig'>{thumb}</td></tr>")


def first_screen_html(out, manifest, records):
    """The header, navigation and the at-a-glance table of the report, as HTML."""
    steps = manifest.get("steps", [])
    count = {v: sum(r["verdict"] == v for r in records) for v in (*VERDICTS, None)}
    tally = "".join(f"<span class='badge {v or 'off'}'>{count[v]} {_e(BADGE[v])}</span>"
                    for v in (*VERDICTS, None) if count[v])
    extended = [r for r in records if r["pooled"] == "extended"]
    flagged = [r for r in records if r["flags"]]

    def links(rs):
        return ", ".join(f"<a href='#{r['anchor']}'>{_e(r['name'])}</a>" for r in rs)
    memo = (f"The memo pools {sum(r['pooled'] is not None for r in records)} tests: "
            + (f"the extended fit (measurement cause removed) of {links(extended)}, the baseline fit of the "
               "others; " if extended else "every test with its baseline fit; ")
            + (f"<span class='flag'>⚑ flagged</span> {links(flagged)} (pooled with an unexplained misfit)."
               if flagged else "nothing flagged."))
    nav = ("<nav><b>Sections</b>" + "".join(f"<a href='#{a}'>{t}</a>" for a, t in SECTIONS)
           + "<br><b>Tests</b>" + "".join(f"<a href='#{r['anchor']}'>{_e(r['name'])}</a>" for r in records) + "</nav>")
    return (f"<header><h1>Campaign report: {_e(manifest.get('campaign', Path(out).name))}</h1>"
            f"<p class='meta'>{len(records)} flight tests from <code>{_e(manifest.get('folder', '?'))}</code> · "
            f"cpas_bayes {_e(manifest.get('version', '?'))} · this run {manifest.get('seconds', 0):.0f} s, "
            f"{sum(s.get('status') == 'cached' for s in steps)} of {len(steps)} steps kept</p>{nav}</header>"
            f"<section id='at-a-glance'><p class='tally'><b>Verdicts</b>{tally}</p><p class='tally'>{memo}</p>"
            "<table class='glance'><tr><th>test, verdict</th><th>what the simulation gets wrong, and where</th>"
            "<th>memo</th><th>stage peak load: test vs prediction<br><span class='legend'>band 5–95 %, line median,"
            " dot the test; p = its percentile</span></th><th>misfit</th></tr>"
            + "".join(_row_html(r) for r in records) + "</table></section>")


# ---------------------------------------------------------------------------
# a small Markdown subset → HTML


ANCHOR_LINE = re.compile(r'^<a id="(test-[0-9]+)"></a>$')


def _inline(text):
    text = html.escape(text)
    text = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", text)
    text = re.sub(r"`(.+?)`", r"<code>\1</code>", text)
    text = re.sub(r"(?<![\w*])\*(?!\s)(.+?)(?<!\s)\*(?![\w*])", r"<em>\1</em>", text)
    return text


def markdown_body(md):
    """Headings, tables, images, bullet lists, bold/italic/code, paragraphs and ``<a id="test-N"></a>`` anchors."""
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
        anchor = ANCHOR_LINE.match(line)
        if anchor:
            body.append(f"<a id='{anchor.group(1)}'></a>")
        elif line.startswith("#"):
            level = min(6, len(line) - len(line.lstrip("#")))
            text = line.lstrip("#").strip()
            slug = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
            body.append(f"<h{level} id='{slug}'>{_inline(text)}</h{level}>")
        elif line.startswith("!["):
            alt, src = line[2:].split("](", 1)
            body.append(f"<figure><img src='{html.escape(src.rstrip(')'))}' alt='{html.escape(alt)}' "
                        f"loading='lazy'><figcaption>{html.escape(alt)}</figcaption></figure>")
        elif line.strip():
            body.append(f"<p>{_inline(line)}</p>")
    flush()
    return "".join(body)


def html_page(title, body):
    """A self-contained HTML document: the body with the report's inline style sheet."""
    return (f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width,initial-scale=1'><title>{html.escape(title)}</title>"
            f"<style>{' '.join(STYLE.split())}</style></head><body>{body}</body></html>\n")

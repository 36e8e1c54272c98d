"""``make demo``: the main job on the data shipped with the package.

It grows with each capability. Now: validate and reduce the two bundled
example tests (from an independent simulator), show the four hidden effects of
the synthetic-test library against the same seed without them, and fit the
two-Drogue example's posterior with its figures. The report is
``<out>/index.html`` with ``report.md`` beside it.
"""

from __future__ import annotations

import html
import time
from pathlib import Path

from .bundle import example_bundles, read_bundle, summary
from .fileio import save_figure, write_text


def _reduce_section(path, out, echo):
    from .reduction import reduce_test, write_reduction

    test = read_bundle(path)
    s = summary(test)
    reduction = reduce_test(test)
    folder = out / "reduction" / path.name
    write_reduction(reduction, folder)
    scale = reduction.scale
    applied = scale.at(test.time[[0, -1]])
    factor = (f"{applied[0]:.4f}" if scale.mode == "constant"
              else f"{applied[0]:.4f} → {applied[1]:.4f}")
    echo(f"reduced {path.name}: load-cell friction factor {factor} ({scale.mode})")
    rows = "\n".join(
        f"| {p['id']} | {p['kind']} | {p['inflation']} | {p['diameter']:g} | "
        f"{', '.join(st['label'] for st in p['stages'])} |" for p in s["parachutes"])
    return (f"### {s['name']} ({s['phase']})\n\n"
            f"{s['samples']} samples, {s['duration_s']:.2f} s at {s['sample_rate_hz']:.0f} Hz, {s['units']} units.\n\n"
            "| parachute | kind | inflation | D_o | stages |\n|---|---|---|---|---|\n" + rows + "\n\n"
            f"Load-cell friction factor ({scale.mode}): {factor}; steady-window ratios "
            f"{', '.join(f'{v:.4f}' for v in scale.values)}.\n\n"
            f"![reduction]({folder.relative_to(out) / 'reduction.png'})\n")


def _effects_section(out, echo):
    from .plots.simulation import plot_effect_comparison

    fig = plot_effect_comparison("drogue", seed=3)
    target = out / "effects_drogue.png"
    save_figure(fig, target, dpi=110)
    echo("drew the four hidden effects against the same seed without them")
    return ("## Hidden effects of the synthetic-test library\n\n"
            "Each effect (added mass, friction drift, sensor lag, canopy breathing) against the same "
            "seed without it, in both reduction channels.\n\n"
            f"![effects]({target.name})\n")


def _fit_section(path, out, echo):
    from .fit import SamplerOptions, fit_test
    from .plots.fit import write_fit_figures

    test = read_bundle(path)
    folder = out / "fit" / path.name
    t0 = time.perf_counter()
    fit = fit_test(test, SamplerOptions(seed=0), out=folder)
    wall = time.perf_counter() - t0
    figures = write_fit_figures(fit, folder)
    d = fit.summary["diagnostics"]
    echo(f"fitted {path.name} in {wall:.0f} s: R-hat max {d['rhat_max']:.4f}, ESS bulk min {d['ess_bulk_min']:.0f}")
    rows = []
    for pid, chute in fit.summary["parachutes"].items():
        for st in chute["stages"]:
            def cell(name, st=st):
                v = st.get(name)
                return f"{v['q50']:.3f} [{v['q05']:.3f}, {v['q95']:.3f}]" if v else "—"
            rows.append(f"| {pid} | {st['label']} | {cell('start')} | {cell('n_p')} | {cell('expopen')} | "
                        f"{cell('ck')} | {cell('tk')} | {cell('eps')} |")
    images = "\n".join(f"![{p.stem}]({p.relative_to(out)})" for p in figures if p.suffix == ".png")
    return (f"## Posterior of {test.name}\n\n"
            f"{wall:.0f} s on this machine; R-hat max {d['rhat_max']:.4f}, bulk ESS min {d['ess_bulk_min']:.0f}, "
            f"τ max {d['tau_max']:.0f} steps, acceptance {d['acceptance']:.2f}.\n\n"
            "Median [5 %, 95 %] per parachute and stage:\n\n"
            "| parachute | stage | start [s] | n_p | expopen | C_k | t_k [s] | eps |\n|---|---|---|---|---|---|---|---|\n"
            + "\n".join(rows) + "\n\n" + images + "\n")


def run_demo(out, echo=print):
    """Run the demo into folder ``out``; return the path of its index.html."""
    out = Path(out)
    examples = example_bundles()
    sections = ["## Reduction of the bundled example tests\n"]
    sections += [_reduce_section(p, out, echo) for p in examples]
    sections.append(_effects_section(out, echo))
    drogue = next(p for p in examples if p.name.startswith("drogue"))
    sections.append(_fit_section(drogue, out, echo))
    md = "# cpas_bayes demo report\n\n" + "\n".join(sections)
    write_text(out / "report.md", md)
    index = out / "index.html"
    write_text(index, _markdown_to_html(md))
    return index


def _markdown_to_html(md):
    """Just enough Markdown (headings, tables, images, paragraphs) for a self-contained page."""
    body, table = [], []

    def flush_table():
        if table:
            rows = [r for r in table if not set(r.replace("|", "").strip()) <= {"-", " "}]
            cells = [[html.escape(c.strip()) for c in r.strip().strip("|").split("|")] for r in rows]
            head = "".join(f"<th>{c}</th>" for c in cells[0])
            rest = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in cells[1:])
            body.append(f"<table><tr>{head}</tr>{rest}</table>")
            table.clear()

    for line in md.splitlines():
        if line.startswith("|"):
            table.append(line)
            continue
        flush_table()
        if line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            body.append(f"<h{level}>{html.escape(line[level:].strip())}</h{level}>")
        elif line.startswith("!["):
            alt, src = line[2:].split("](", 1)
            body.append(f"<p><img src='{html.escape(src.rstrip(')'))}' alt='{html.escape(alt)}' "
                        "style='max-width:100%'></p>")
        elif line.strip():
            body.append(f"<p>{html.escape(line)}</p>")
    flush_table()
    style = ("body{font-family:sans-serif;max-width:1100px;margin:auto;padding:1em}"
             "table{border-collapse:collapse}td,th{border:1px solid #bbb;padding:2px 6px;font-size:90%}")
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>cpas_bayes demo</title>"
            f"<style>{style}</style></head><body>{''.join(body)}</body></html>\n")

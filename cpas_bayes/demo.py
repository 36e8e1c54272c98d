"""``make demo``: the main job on the data shipped with the package.

It grows with each capability; it now validates and summarises the bundled
example tests and writes a report.
"""

from __future__ import annotations

import html
from pathlib import Path

from .bundle import example_bundles, read_bundle, summary
from .fileio import write_text


def run_demo(out, echo=print):
    """Run the demo into folder ``out``; return the path of its index.html."""
    out = Path(out)
    sections = []
    for path in example_bundles():
        s = summary(read_bundle(path))
        echo(f"validated {path.name}: {len(s['parachutes'])} parachutes, {s['duration_s']:.1f} s")
        rows = "\n".join(
            f"| {p['id']} | {p['kind']} | {p['inflation']} | {p['diameter']:g} | "
            f"{', '.join(st['label'] for st in p['stages'])} |" for p in s["parachutes"])
        sections.append(
            f"## {s['name']} ({s['phase']})\n\n"
            f"{s['samples']} samples, {s['duration_s']:.2f} s at {s['sample_rate_hz']:.0f} Hz, "
            f"{s['units']} units; channels: {', '.join(s['channels'])}.\n\n"
            "| parachute | kind | inflation | D_o | stages |\n|---|---|---|---|---|\n" + rows + "\n")
    md = "# cpas_bayes demo report\n\nBundled example flight tests, validated.\n\n" + "\n".join(sections)
    write_text(out / "report.md", md)
    index = out / "index.html"
    write_text(index, "<!doctype html><meta charset='utf-8'><title>cpas_bayes demo</title>"
               f"<pre>{html.escape(md)}</pre>\n")
    return index

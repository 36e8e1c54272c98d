"""``make demo``'s job: the bundled data through every capability, to a report."""

import pytest

from cpas_bayes.cli import main


@pytest.mark.slow
def test_demo_writes_a_report_with_its_figures(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"report: {out / 'index.html'}" in printed
    md = (out / "report.md").read_text()
    html = (out / "index.html").read_text()
    for section in ("Reduction of the bundled example tests", "Hidden effects", "Posterior of EX-drogue"):
        assert section in md and section in html
    images = [line.split("](")[1].rstrip(")") for line in md.splitlines() if line.startswith("![")]
    assert len(images) >= 8
    for rel in images:
        path = out / rel
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", rel
    assert "<img src=" in html and "http" not in html

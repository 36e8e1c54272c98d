"""The memo folder of ``cpas-bayes pool``: memo.toml, memo_draws.csv, memo.md and the pooling figures.

:func:`write_pool` writes, for a :class:`cpas_bayes.population.pool.PoolResult`:
``memo.toml`` and ``memo_draws.csv`` (the memo's own format,
:meth:`cpas_bayes.population.memo.Memo.write`), ``memo.md`` (:func:`memo_markdown`:
the entries as a table, the hyper-posterior of each population's mean and sd,
the family criterion, the (n_p, expopen) correlations, peak fill times,
warnings and provenance) and the forest and pair figures
(:mod:`cpas_bayes.outputs.plots.pool`). Every file is written atomically.
"""

from __future__ import annotations

import numpy as np

from cpas_bayes.core.files import write_text
from cpas_bayes.core.ownership import claim_folder
from cpas_bayes.outputs.plots.pool import write_pool_figures
from cpas_bayes.population.families import FAMILY_NAMES
from cpas_bayes.population.pool import PoolResult


def memo_markdown(result: PoolResult, provenance=None) -> str:
    """memo.md: one table row per entry, then criteria, correlations, ESS warnings and provenance."""

    def fmt(v):
        return f"{v:.4g}" if isinstance(v, (int, float, np.floating)) else str(v)

    lines = ["# Model memo: population dispersions", "",
             f"Pooled {len(result.tests)} tests: {', '.join(result.tests)}.", "",
             "Population-predictive quantiles (hyper-parameter uncertainty included). "
             "Parameters are the family fitted to the predictive draws.", "",
             "| kind | stage | parameter | family | parameters | 5 % | 50 % | 95 % | n_tests |",
             "|---|---|---|---|---|---|---|---|---|"]
    table = result.summary_table()
    for _, row in table.iterrows():
        params = ", ".join(f"{k} = {fmt(v)}" for k, v in row["params"].items())
        lines.append(f"| {row['kind']} | {row['stage']} | {row['parameter']} | {row['family']} | {params} | "
                     f"{fmt(row['q05'])} | {fmt(row['q50'])} | {fmt(row['q95'])} | {row['n_tests']} |")
    lines += ["", "## Hyper-posterior of the population mean and sd (5 / 50 / 95 %)", "",
              "| kind | stage | parameter | mean | sd | min ESS |", "|---|---|---|---|---|---|"]
    for (kind, stage, param), e in sorted(result.entries.items()):
        pop = e.population()
        lines.append(f"| {kind} | {stage} | {param} | " + " / ".join(fmt(v) for v in pop["mean"]) + " | "
                     + " / ".join(fmt(v) for v in pop["sd"]) + f" | {np.min(e.pool.ess):.0f} |")
    lines += ["", "## Family choice: leave-one-test-out elpd (larger is better)", "",
              "| kind | stage | parameter | " + " | ".join(FAMILY_NAMES) + " | chosen |",
              "|---|---|---|" + "---|" * len(FAMILY_NAMES) + "---|"]
    for (kind, stage, param), e in sorted(result.entries.items()):
        vals = " | ".join(fmt(e.criterion[f]) if f in e.criterion else "–" for f in FAMILY_NAMES)
        lines.append(f"| {kind} | {stage} | {param} | {vals} | {e.family} |")
    if result.pairs:
        lines += ["", "## Correlation of n_p and expopen (Gaussian copula)", "",
                  "| kind | stage | rho median | rho 90 % | elpd correlated | elpd rho = 0 | difference ± se | kept |",
                  "|---|---|---|---|---|---|---|---|"]
        for (kind, stage), p in sorted(result.pairs.items()):
            lines.append(f"| {kind} | {stage} | {p.rho_median:.3f} | [{p.rho_interval[0]:.3f}, "
                         f"{p.rho_interval[1]:.3f}] | {p.elpd_correlated:.2f} | {p.elpd_independent:.2f} | "
                         f"{p.elpd_diff:.2f} ± {p.elpd_diff_se:.2f} | {'yes' if p.keep else 'no'} |")
    if result.peak_fill:
        lines += ["", "## Peak fill time t_fp seen in the tests (posterior medians, s)", ""]
        for (kind, stage), p in sorted(result.peak_fill.items()):
            meds = ", ".join(f"{r.test}/{r.canopy} {r.median:.3f}" for r in p.per_canopy.itertuples())
            lines.append(f"- {kind} {stage}: range {p.range[0]:.3f}–{p.range[1]:.3f} s ({meds})")
    if result.warnings or result.skipped:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in result.warnings] + \
                 [f"- skipped {s}" for s in result.skipped]
    prov = provenance or {}
    lines += ["", "## Provenance", "",
              f"- tests: {', '.join(result.tests)}",
              f"- fit seeds: {', '.join(str(s) for s in result.seeds)}",
              f"- method: {result.method}"]
    lines += [f"- {k}: {v}" for k, v in prov.items() if k not in ("tests", "seeds", "method")]
    return "\n".join(lines) + "\n"


def write_pool(result: PoolResult, out, provenance=None, executor=None):
    """Write memo.toml, memo_draws.csv, memo.md and the forest plots into ``out``; return the paths.
    ``executor`` draws the figures as tasks (:func:`~cpas_bayes.outputs.plots.pool.write_pool_figures`)."""
    out = claim_folder(out)
    memo = result.to_memo(provenance)
    memo_path = memo.write(out)
    md = out / "memo.md"
    write_text(md, memo_markdown(result, memo.provenance))
    figures = write_pool_figures(result, out, executor=executor)
    return {"memo": memo_path, "draws": out / "memo_draws.csv", "markdown": md, "figures": figures}

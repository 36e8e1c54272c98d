"""Files of a Monte Carlo (``cpas-bayes montecarlo``) and of the n_p-vs-n fill-time study.

:func:`write_monte_carlo` writes, for a :class:`cpas_bayes.loads.montecarlo.MonteCarloResult`:
``runs.csv`` (``result.frame()``: one row per run in the like-test's units,
columns as :mod:`cpas_bayes.loads.montecarlo` lists them), ``summary.json``
(``result.summary()``: per stage peak-load, peak-time, t_fp and load-share
quantiles 1/5/50/95/99 %, mean and sd; configuration, mode, runtime, runs/s;
plus the caller's extra entries), ``peak_loads.png`` and ``fill_times.png``
(:mod:`cpas_bayes.outputs.plots.montecarlo`).

:func:`write_fill_time_comparison` writes a
:class:`cpas_bayes.loads.fill_time.FillTimeComparison`: ``np_vs_n.json`` and
``fill_time_np_vs_n.png``.

Every file is written atomically; non-finite numbers become JSON null.
"""

from __future__ import annotations

import matplotlib.pyplot as plt

from cpas_bayes.core.files import atomic_path, jsonable, write_json
from cpas_bayes.core.ownership import claim_folder
from cpas_bayes.loads.budget import TABLE_CHUNK
from cpas_bayes.loads.fill_time import FillTimeComparison
from cpas_bayes.loads.montecarlo import MonteCarloResult
from cpas_bayes.outputs.figures import save_figure, write_document
from cpas_bayes.outputs.plots.montecarlo import plot_fill_time_np_vs_n, plot_fill_times, plot_peak_loads
from cpas_bayes.population.memo import Memo


def write_monte_carlo(result: MonteCarloResult, out, memo: Memo | None = None, extra=None):
    """Write runs.csv, summary.json, peak_loads.png and fill_times.png into ``out`` (each atomically).

    ``memo`` adds the pooled tests' t_fp ranges to the fill-time figure;
    ``extra`` entries are added to summary.json (seed, command line).
    The summary and figures are built before anything is written; runs.csv
    (written first) is built and written ``TABLE_CHUNK`` runs at a time.
    """
    out = claim_folder(out)
    summary = result.summary()
    summary.update(extra or {})
    figures = {"peak_loads.png": plot_peak_loads(result), "fill_times.png": plot_fill_times(result, memo)}
    paths = {"csv": out / "runs.csv", "json": out / "summary.json"}
    try:
        with atomic_path(paths["csv"]) as tmp:   # TABLE_CHUNK runs at a time: the table never holds them all
            for first in range(0, max(result.runs, 1), TABLE_CHUNK):
                result.frame(slice(first, first + TABLE_CHUNK)).to_csv(
                    tmp, mode="a" if first else "w", header=not first, index=False, float_format="%.8g")
        write_json(paths["json"], jsonable(summary))
        for name, fig in figures.items():
            paths[name] = out / name
            save_figure(fig, paths[name], dpi=110)
    finally:
        for fig in figures.values():
            plt.close(fig)
    return paths


def write_fill_time_comparison(comparison: FillTimeComparison, out, extra=None):
    """Write np_vs_n.json and fill_time_np_vs_n.png into ``out`` (atomically); return their paths."""
    return write_document(out, comparison.to_json(), extra, "np_vs_n.json", "fill_time_np_vs_n.png",
                          plot_fill_time_np_vs_n(comparison))

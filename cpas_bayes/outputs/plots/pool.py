"""Figures of pooling (cpas_bayes.population.pool): per-test posteriors beside the pooled population.

``plot_forest``: one panel per parameter of a parachute kind and stage. Each
row is one canopy of one test — its posterior median (dot) and 90 % interval
(line). Below a separator, the population: the hyper-posterior 90 % interval
of the population mean, and the population-predictive 90 % band with its
median and 1–99 % whiskers (what a Monte Carlo will draw).
``plot_pair``: per-canopy medians of n_p against expopen over the population-
predictive cloud of the correlated pair, with ρ in the title.
``write_pool_figures`` writes them all as PNG files (atomically).
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from cpas_bayes.core.inputs import inside
from cpas_bayes.outputs.figures import save_figure

_TEST = "#3b6ea5"        # per-test posteriors
_POPULATION = "#c0392b"  # population predictive
_MEAN = "#7f4f24"        # hyper-posterior of the population mean
_UNITS = {"tk": "s", "t_fp": "s"}
_ORDER = ("n_p", "n", "expopen", "ck", "tk", "eps", "cd_o")
_SHORT = {"truncnormal": "trunc", "lognormal": "logn"}


def _forest_panel(ax, entry):
    table = entry.per_canopy
    n = len(table)
    y = np.arange(n)[::-1] + 3.0
    ax.hlines(y, table["q05"], table["q95"], color=_TEST, lw=1.6)
    ax.plot(table["median"], y, "o", color=_TEST, ms=4, label="test posterior: median, 90 %")
    labels = [f"{t} {c}" for t, c in zip(table["test"], table["canopy"])]
    pred = entry.predictive
    q01, q05, q50, q95, q99 = np.quantile(pred, [0.01, 0.05, 0.5, 0.95, 0.99])
    ax.axvspan(q05, q95, color=_POPULATION, alpha=0.10, lw=0)
    ax.hlines(1.0, q01, q99, color=_POPULATION, lw=0.8)
    ax.hlines(1.0, q05, q95, color=_POPULATION, lw=4.0, alpha=0.8, label="population predictive: 5–95 %, 1–99 %")
    ax.plot([q50], [1.0], "|", color="white", ms=8, mew=2)
    lo, med, hi = entry.pool.interval("mean")
    ax.hlines(2.0, lo, hi, color=_MEAN, lw=2.0)
    ax.plot([med], [2.0], "D", color=_MEAN, ms=4, label="population mean: 90 % (hyper-posterior)")
    ax.axhline(2.5, color="0.6", lw=0.6)
    ax.set_yticks(list(y) + [2.0, 1.0])
    ax.set_yticklabels(labels + ["population mean", f"predictive ({entry.family})"], fontsize=7)
    ax.set_ylim(0.3, n + 2.7)
    unit = _UNITS.get(entry.parameter)
    ax.set_xlabel(entry.parameter + (f" [{unit}]" if unit else ""))
    crit = entry.criterion
    best = max(crit.values())
    others = ", ".join(f"{_SHORT.get(k, k)} {v - best:+.1f}" for k, v in sorted(crit.items(), key=lambda kv: -kv[1])
                       if k != entry.family)
    ax.set_title(f"{entry.parameter}: {entry.family}, {entry.n_tests} tests"
                 + (f"\nLOO elpd vs chosen: {others}" if others else ""), fontsize=8)
    ax.grid(axis="x", alpha=0.3)


def plot_forest(result, kind, stage):
    """Forest plot of every pooled parameter of ``kind`` at ``stage`` (None if there is none)."""
    entries = [result.entries[(kind, stage, p)] for p in _ORDER if (kind, stage, p) in result.entries]
    if not entries:
        return None
    cols = min(3, len(entries))
    rows = int(np.ceil(len(entries) / cols))
    n_rows = max(len(e.per_canopy) for e in entries)
    fig, axes = plt.subplots(rows, cols, figsize=(max(4.6 * cols, 8.0), (1.2 + 0.22 * (n_rows + 3)) * rows + 0.6),
                             constrained_layout=True, squeeze=False)
    for ax, entry in zip(axes.flat, entries):
        _forest_panel(ax, entry)
    for ax in list(axes.flat)[len(entries):]:
        ax.set_visible(False)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=3, fontsize=7, frameon=False)
    fig.suptitle(f"{kind}, {stage}: per-test posteriors and the pooled population")
    return fig


def plot_pair(result, kind, stage):
    """n_p against expopen: canopy medians with 90 % intervals over the predictive cloud."""
    pair = result.pairs.get((kind, stage))
    if pair is None:
        return None
    e1, e2 = (result.entries[(kind, stage, p)] for p in pair.names)
    fig, ax = plt.subplots(figsize=(5.5, 4.8), constrained_layout=True)
    cloud = pair.predictive[:: max(1, pair.predictive.shape[0] // 3000)]
    ax.scatter(cloud[:, 0], cloud[:, 1], s=3, color=_POPULATION, alpha=0.15, lw=0,
               label="population predictive (correlated model)")
    t1, t2 = e1.per_canopy, e2.per_canopy
    ax.errorbar(t1["median"], t2["median"],
                xerr=[t1["median"] - t1["q05"], t1["q95"] - t1["median"]],
                yerr=[t2["median"] - t2["q05"], t2["q95"] - t2["median"]],
                fmt="o", color=_TEST, ms=4, lw=1, label="tests: median, 90 %")
    ax.set_xlabel(pair.names[0])
    ax.set_ylabel(pair.names[1])
    ax.set_title(f"{kind}, {stage}: ρ = {pair.rho_median:.2f} [{pair.rho_interval[0]:.2f}, "
                 f"{pair.rho_interval[1]:.2f}]; Δelpd {pair.elpd_diff:+.2f} ± {pair.elpd_diff_se:.2f} → "
                 f"{'kept' if pair.keep else 'not kept'}", fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return fig


class _Part:
    """The entries and pair of one kind and stage: what its two figures read of a pool's result, shipped
    to a worker without the rest (the draws, the other stages)."""

    def __init__(self, result, kind, stage):
        self.entries = {k: e for k, e in result.entries.items() if k[:2] == (kind, stage)}
        self.pairs = {k: p for k, p in result.pairs.items() if k == (kind, stage)}


def _draw_pool_figure(job):
    """Task: draw one figure (``"pool"`` forest or ``"pair"``) into ``path``; the path, or None if it has nothing to show."""
    name, kind, stage, part, path = job
    fig = (plot_forest if name == "pool" else plot_pair)(part, kind, stage)
    if fig is None:
        return None
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def write_pool_figures(result, out, executor=None):
    """Forest plots per kind and stage (``pool_<kind>_<stage>.png``) and pair plots; returns the paths.

    ``executor`` (:mod:`cpas_bayes.core.executor`) draws them as tasks: with fifty tests a forest plot
    takes a second or more, and drawn one after another they were the pool step's largest serial part."""
    from cpas_bayes.core.executor import Executor

    jobs = []
    for kind, stage in sorted({(k, s) for k, s, _ in result.entries}):
        part = _Part(result, kind, stage)
        jobs += [(name, kind, stage, part, inside(out, f"{name}_{kind}_{stage}.png")) for name in ("pool", "pair")]
    drawn = (executor or Executor()).map(_draw_pool_figure, jobs, desc="figures", progress=False)
    return [path for path in drawn if path is not None]

"""Figures of Monte Carlo loads (cpas_bayes.loads.montecarlo), the n_p-vs-n fill-time study
(cpas_bayes.loads.fill_time) and load comparisons (cpas_bayes.loads.compare).

``plot_peak_loads``: histograms of the peak loads per cluster stage, total
and per parachute. ``plot_fill_times``: peak fill times per parachute and
stage, with the range the pooled tests showed. ``plot_fill_time_np_vs_n``: the
seed's §V.D claim — t_fp with n_p dispersed against n dispersed.
``plot_load_comparison``: measured total load against the predicted load
bands and peak distributions (after the seed's Fig. 17, 26 and 31). All
values in the test bundle's units.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import MaxNLocator

_ACC = "#1f9bd1"      # accelerometer (as the reduction figures)
_CELLS = "#7b3294"    # load-cell sum
_TOTAL = "0.15"
_SOURCE_COLOURS = {"population": "#e6550d", "posterior": "#31a354"}
_SOURCE_NAMES = {"population": "population predictive (memo Monte Carlo)",
                 "posterior": "posterior predictive (this test's fit)"}
_MODE_COLOURS = {"n_p": "#1f9bd1", "n": "#d95f02"}
_MODE_NAMES = {"n_p": "n_p dispersed, n by Eq. 18", "n": "n dispersed (old way)"}
_TESTED = "#bdbdbd"


def _finite(x):
    x = np.asarray(x, float)
    return x[np.isfinite(x)]


def _mark_quantiles(ax, values, colour):
    q01, q50, q99 = np.quantile(values, [0.01, 0.5, 0.99])
    ax.axvline(q50, color=colour, lw=1.4, label=f"median {q50:,.0f}")
    ax.axvline(q01, color=colour, lw=0.9, ls="--", label=f"1 % / 99 %: {q01:,.0f} / {q99:,.0f}")
    ax.axvline(q99, color=colour, lw=0.9, ls="--")


def plot_peak_loads(result):
    """Histograms of each cluster stage's peak total load and each parachute's own-stage peak load."""
    lay, u = result.layout, result.layout.units
    force = u.label("force")
    out = result.outputs
    K, P = lay.n_stages, lay.n_chutes
    fig, axes = plt.subplots(K, P + 1, figsize=(3.6 * (P + 1), 2.8 * K), constrained_layout=True, squeeze=False)
    for k in range(K):
        columns = [("total Σ F_i", out.stage_peak_load[:, k], _TOTAL)]
        columns += [(pid, out.chute_peak_load[:, i, k] if k < lay.stages_per_chute[i] else np.array([]), f"C{i}")
                    for i, pid in enumerate(lay.ids)]
        for j, (name, values, colour) in enumerate(columns):
            ax = axes[k, j]
            x = u.from_si(_finite(values), "force")
            if x.size == 0:
                ax.set_axis_off()
                continue
            ax.hist(x, bins=60, color=colour, alpha=0.55)
            _mark_quantiles(ax, x, colour)
            ax.xaxis.set_major_locator(MaxNLocator(5))
            ax.set_title(f"{lay.cluster_stage_labels[k]}: {name}", fontsize=9)
            ax.set_xlabel(f"peak load [{force}]")
            ax.set_ylabel("runs")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{lay.test_name}: Monte Carlo peak loads, {result.runs:,} runs ({result.mode} dispersed, "
                 f"{'joint population draws' if result.joint else 'independent parameters'})\nleft column: the "
                 "cluster total per stage; then each parachute in its own stage", fontsize=10)
    return fig


def plot_fill_times(result, memo=None):
    """Histograms of each parachute's peak fill time t_fp per stage; the pooled tests' range shaded."""
    lay = result.layout
    out = result.outputs
    K, P = lay.n_stages, lay.n_chutes
    fig, axes = plt.subplots(K, P, figsize=(3.8 * P, 2.8 * K), constrained_layout=True, squeeze=False)
    for k in range(K):
        for i, pid in enumerate(lay.ids):
            ax = axes[k, i]
            if k >= lay.stages_per_chute[i]:
                ax.set_axis_off()
                continue
            x = _finite(out.t_fp[:, i, k])
            key = lay.stage_key(i, k)
            entry = memo.entries.get((lay.kinds[i], key, "t_fp")) if memo is not None else None
            title = f"{pid} {lay.stage_labels[i][k]} ({key})"
            if entry is not None and np.all(np.isfinite(entry.bounds)):
                lo, hi = entry.bounds
                ax.axvspan(lo, hi, color=_TESTED, alpha=0.5, label="range seen in the pooled tests")
                if x.size:
                    title += f"\n{100 * np.mean((x < lo) | (x > hi)):.1f} % of runs outside the tested range"
            if x.size:
                ax.hist(x, bins=60, color=f"C{i}", alpha=0.6, label=f"t_fp, median {np.median(x):.2f} s")
            ax.set_title(title, fontsize=9)
            ax.set_xlabel("peak fill time t_fp [s]")
            ax.set_ylabel("runs")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{lay.test_name}: peak fill times t_fp (Eq. 15) of the Monte Carlo runs ({result.mode} dispersed)",
                 fontsize=10)
    return fig


def plot_fill_time_np_vs_n(comparison):
    """Per kind and stage: t_fp histograms with n_p dispersed and with n dispersed over the tested range."""
    groups = comparison.groups
    n = len(groups)
    cols = min(n, 3)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.4 * rows), constrained_layout=True, squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_axis_off()
    for ax, g in zip(axes.flat, groups):
        lo, hi = g.bounds
        width = hi - lo
        both = np.concatenate([_finite(g.t_fp[m]) for m in ("n_p", "n")])
        left = max(0.0, min(lo - 0.5 * width, np.quantile(both, 0.005) if both.size else lo))
        right = max(hi + 0.5 * width, np.quantile(both, 0.995) if both.size else hi)
        bins = np.linspace(left, right, 70)
        ax.axvspan(lo, hi, color=_TESTED, alpha=0.5, label="t_fp range seen in the pooled tests")
        for mode in ("n_p", "n"):
            x = _finite(g.t_fp[mode])
            beyond = np.mean((x < left) | (x > right)) if x.size else 0.0
            label = f"{_MODE_NAMES[mode]}: {100 * g.fraction_outside(mode):.1f} % outside"
            if beyond > 0:
                label += f"\n({100 * beyond:.1f} % beyond the axis, piled in the end bins)"
            ax.hist(np.clip(x, left, right), bins=bins, histtype="stepfilled" if mode == "n_p" else "step",
                    alpha=0.45 if mode == "n_p" else 1.0, lw=1.6, color=_MODE_COLOURS[mode], label=label)
        ax.set_title(f"{g.kind} {g.stage} ({', '.join(g.stage_labels)})", fontsize=9)
        ax.set_xlabel("peak fill time t_fp [s]")
        ax.set_ylabel("runs × canopies")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2))
    fig.suptitle(f"{comparison.layout.test_name}: peak fill times with n_p dispersed (n by Eq. 18) and with n "
                 "dispersed\nthe seed (§V.D) expects fewer runs outside the tested range with n_p;\n"
                 f"{comparison.runs:,} runs per mode, every parameter drawn independently, same draws except the "
                 "fill constant", fontsize=10)
    return fig


def plot_load_comparison(comparison):
    """Measured total load vs time with the predicted 50/90 % load bands; side panels of the peak distributions.

    After the seed's Fig. 17/26/31: the measured accelerometer load (Eq. 6)
    and load-cell sum, each stage's measured peak with its 1-sigma bar, and
    for each prediction source the 25–75 % and 5–95 % bands of the simulated
    total load Σ F_i over time with its median.
    """
    test = comparison.test
    u = test.units
    force = u.label("force")
    stages = comparison.stage_labels
    K = len(stages)
    fig = plt.figure(figsize=(15, max(6.0, 2.3 * K)), constrained_layout=True)
    grid = fig.add_gridspec(K, 2, width_ratios=[2.6, 1.0])
    ax = fig.add_subplot(grid[:, 0])
    frame = comparison.reduction.frame
    time = frame["time"].to_numpy()
    ax.plot(time, u.from_si(frame["load_total"].to_numpy(), "force"), color=_ACC, lw=0.5, alpha=0.6,
            label="measured: accelerometer total load (Eq. 6)")
    if "load_cells" in frame:
        ax.plot(time, u.from_si(frame["load_cells"].to_numpy(), "force"), color=_CELLS, lw=0.7, alpha=0.8,
                label="measured: scaled load-cell sum")
    for source, result in comparison.predictions.items():
        colour = _SOURCE_COLOURS[source]
        hist = result.outputs.history
        if hist.shape[0] == 0:
            continue
        q = u.from_si(np.quantile(hist, [0.05, 0.25, 0.5, 0.75, 0.95], axis=0), "force")
        t = result.outputs.history_time
        ax.fill_between(t, q[0], q[4], color=colour, alpha=0.15, lw=0,
                        label=f"{_SOURCE_NAMES[source]}: 90 % band")
        ax.fill_between(t, q[1], q[3], color=colour, alpha=0.35, lw=0, label="… 50 % band")
        ax.plot(t, q[2], color=colour, lw=1.0, label="… median")
    for k, pk in enumerate(comparison.reduction.peaks):
        acc = pk.accelerometer
        ax.errorbar([acc.time], [u.from_si(acc.load, "force")], yerr=[u.from_si(acc.sigma, "force")], fmt="o",
                    color="k", ms=4, capsize=3, label="measured peak ±1σ (accelerometer, Eq. 7)" if k == 0 else None)
        if pk.load_cells is not None:
            lc = pk.load_cells
            ax.errorbar([lc.time], [u.from_si(lc.load, "force")], yerr=[u.from_si(lc.sigma, "force")], fmt="s",
                        color=_CELLS, ms=4, capsize=3, label="measured peak ±1σ (load-cell sum)" if k == 0 else None)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"total parachute load [{force}]")
    ax.set_title("Total load: measurement against the predicted load histories")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")

    for k in range(K):
        side = fig.add_subplot(grid[k, 1])
        pk = comparison.reduction.peaks[k]
        lines = []
        for source, result in comparison.predictions.items():
            x = u.from_si(_finite(result.outputs.stage_peak_load[:, k]), "force")
            if x.size:
                side.hist(x, bins=50, density=True, alpha=0.45, color=_SOURCE_COLOURS[source], label=source)
            c = comparison.find(source, "accelerometer", k)
            if c is not None:
                lines.append(f"{source}: percentile {c.percentile:.0f}, P(pred > meas) {c.p_exceed:.2f}")
        m, s = u.from_si(pk.accelerometer.load, "force"), u.from_si(pk.accelerometer.sigma, "force")
        side.axvspan(m - s, m + s, color="k", alpha=0.12, lw=0)
        side.axvline(m, color="k", lw=1.4, label="measured ±1σ (accelerometer)")
        if pk.load_cells is not None:
            side.axvline(u.from_si(pk.load_cells.load, "force"), color=_CELLS, lw=1.2, ls="--",
                         label="measured (load-cell sum)")
        side.set_title(f"{stages[k]} peak\n" + "\n".join(lines), fontsize=8)
        side.set_xlabel(f"peak load [{force}]")
        side.xaxis.set_major_locator(MaxNLocator(5))
        side.set_yticks([])
        side.grid(alpha=0.3)
        side.legend(fontsize=6, loc="upper right")
    fig.suptitle(f"{test.name}: measured loads against predictions; percentile of each measured peak in the "
                 "predicted peaks convolved with the measurement's N(0, σ²)", fontsize=10)
    return fig

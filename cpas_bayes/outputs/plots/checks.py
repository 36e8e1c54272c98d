"""Figures of a fit's checks: the posterior predictive check, LOO-PIT and the standardised residuals.

``ppc.png``, ``loo_pit.png`` and ``residuals.png`` of :func:`cpas_bayes.outputs.fit_figures.write_fit_figures`,
and of a diagnosis' baseline, drawn from :mod:`cpas_bayes.inference.predictive_checks` and
:mod:`cpas_bayes.inference.residuals`; the phase shading and the residual figure's legend are shared with
the diagnosis' residual figures.
"""

from __future__ import annotations

import textwrap

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Patch

from cpas_bayes.inference.predictive_checks import STATISTICS
from cpas_bayes.inference.residuals import PARETO_K_LIMIT
from cpas_bayes.outputs.figures import DATA_COLOR as _DATA
from cpas_bayes.outputs.figures import MODEL_COLOR as _MODEL
from cpas_bayes.outputs.figures import fixed_grid

_PHASE_COLORS = {"pre_deploy": "0.88", "fill": "#fdd0a2", "overinflation": "#fcbba1",
                 "steady": "#c6dbef", "full_open": "#c7e9c0"}


def plot_ppc(result):
    """Observed statistic against its replicated distribution, standardised, p-values annotated."""
    table = result.table
    stats = list(STATISTICS)
    rows = table[["parachute", "stage", "stage_label"]].drop_duplicates().reset_index(drop=True)
    fig = plt.figure(figsize=(3.3 * len(stats) + 1.0, 0.42 * len(rows) + 2.2))
    # fixed margins in inches: room for the stage labels on the left and each panel's p-values on its right
    axes = fixed_grid(fig, 1, len(stats), left=1.75, right=0.6, top=0.75, bottom=0.9, wspace=0.75,
                      hspace=0.0).subplots(sharey=True, squeeze=False)
    y = np.arange(len(rows))[::-1]
    for c, name in enumerate(stats):
        ax = axes[0, c]
        for r, row in rows.iterrows():
            sel = np.flatnonzero(((table["parachute"] == row["parachute"]) & (table["stage"] == row["stage"])
                                  & (table["statistic"] == name)).to_numpy())
            if not sel.size:
                continue
            i = int(sel[0])
            rep = result.replicated[i]
            rep = rep[np.isfinite(rep)]
            obs = table["observed"].iloc[i]
            p = table["p_value"].iloc[i]
            if rep.size < 2 or not np.isfinite(obs):
                ax.text(0, y[r], "n/a", ha="center", va="center", fontsize=7)
                continue
            mu, sd = rep.mean(), rep.std(ddof=1)
            sd = sd if sd > 0 else 1.0
            z = (rep - mu) / sd
            q05, q25, q75, q95 = np.quantile(z, (0.05, 0.25, 0.75, 0.95))
            ax.plot([q05, q95], [y[r], y[r]], color=_MODEL, lw=1.2)
            ax.plot([q25, q75], [y[r], y[r]], color=_MODEL, lw=4.5, solid_capstyle="butt")
            extreme = p < 0.01 or p > 0.99
            ax.plot((obs - mu) / sd, y[r], "o", ms=5, color="crimson" if extreme else "k", zorder=3)
            ax.text(1.02, y[r], f"p={p:.3f}", transform=ax.get_yaxis_transform(), fontsize=7, va="center",
                    color="crimson" if extreme else "k")
        ax.axvline(0, color="0.6", lw=0.8)
        ax.set_title(name.replace("_", " "), fontsize=9)
        ax.set_xlabel("(T − mean T_rep) / sd T_rep [-]", fontsize=8)
        ax.grid(alpha=0.3, axis="x")
    axes[0, 0].set_yticks(y)
    axes[0, 0].set_yticklabels([f"{r.parachute} s{r.stage} ({r.stage_label})" for r in rows.itertuples()],
                               fontsize=8)
    handles = [plt.Line2D([], [], color=_MODEL, lw=4.5, label="replicated 50 %"),
               plt.Line2D([], [], color=_MODEL, lw=1.2, label="replicated 90 %"),
               plt.Line2D([], [], marker="o", ls="", color="k", label="observed"),
               plt.Line2D([], [], marker="o", ls="", color="crimson", label="observed, p < 0.01 or > 0.99")]
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8, bbox_to_anchor=(0.5, 0.0))
    fig.suptitle("Posterior predictive check: each observed statistic (dot) should sit inside the replicated "
                 "range (bars); p = P(T_rep ≥ T_obs)", fontsize=10)
    return fig


def plot_loo_pit(result):
    """LOO-PIT ECDF difference per channel with the DKW 95 % band, and the PIT histograms."""
    fig = plt.figure(figsize=(12, 4.6))
    if not result.values:
        fig.text(0.5, 0.5, textwrap.fill("LOO-PIT " + result.not_computed, 90), ha="center", va="center")
        return fig
    ax_e, ax_h = fixed_grid(fig, 1, 2, left=0.85, right=0.2, top=0.7, bottom=0.55, wspace=0.85,
                            hspace=0.0).subplots(squeeze=False)[0]
    grid = np.linspace(0, 1, 201)
    band = result.table["dkw_band"].max()
    ax_e.fill_between(grid, -band, band, color="0.85", label="95 % simultaneous band (DKW)")
    for channel, u in result.values.items():
        ecdf = np.searchsorted(np.sort(u), grid, side="right") / u.size
        row = result.table[result.table["channel"] == channel].iloc[0]
        line, = ax_e.plot(grid, ecdf - grid, lw=1.3, label=f"{channel}: KS D = {row.ks_distance:.3f}")
        ax_h.hist(u, bins=20, range=(0, 1), density=True, histtype="step", lw=1.3, color=line.get_color(),
                  label=f"{channel}: sd = {row.pit_sd:.3f}")
    ax_h.axhline(1.0, color="k", ls="--", lw=0.8, label="uniform (sd 0.289)")
    ax_e.axhline(0.0, color="k", lw=0.6)
    ax_e.set_xlabel("LOO-PIT value u [-]")
    ax_e.set_ylabel("ECDF(u) − u [-]")
    ax_e.set_title("ECDF difference: should stay inside the grey band", fontsize=10)
    ax_h.set_xlabel("LOO-PIT value u [-]")
    ax_h.set_ylabel("density [-]")
    ax_h.set_title("histogram: ∪-shape = predictive too narrow, ∩-shape = too wide", fontsize=10)
    for ax in (ax_e, ax_h):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("LOO-PIT calibration per channel (neighbouring bins are correlated: the band is a guide)",
                 fontsize=10)
    return fig


def _phase_segments(time, labels):
    """(t_start, t_end, label) runs of equal phase, edges half-way between bins."""
    edges = np.concatenate([[time[0]], 0.5 * (time[1:] + time[:-1]), [time[-1]]])
    change = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    bounds = np.concatenate([[0], change, [labels.size]])
    return [(edges[a], edges[b], labels[a]) for a, b in zip(bounds[:-1], bounds[1:])]


def shade_phases(ax, time, labels):
    """Shade each flight phase's run of bins behind a residual panel."""
    for t0, t1, label in _phase_segments(time, labels):
        ax.axvspan(t0, t1, color=_PHASE_COLORS[label], lw=0, zorder=0)


def finish_residual_figure(fig, axes, handles, bottom, title):
    """Common legend (series + phases) under the panels, time axis label and title."""
    phase_handles = [Patch(color=c, label=f"phase: {name.replace('_', ' ')}") for name, c in _PHASE_COLORS.items()]
    fig.legend(handles=handles + phase_handles, loc="lower center", ncol=4, fontsize=8)
    if fig.get_layout_engine() is not None:   # a fixed grid (fit's residuals) left the legend its room already
        fig.get_layout_engine().set(rect=(0, bottom, 1, 1 - bottom))
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(title, fontsize=10)


def plot_residuals(report):
    """Standardised residuals against time per channel, phases shaded, high Pareto-k bins marked."""
    channels = list(report.residuals)
    fig = plt.figure(figsize=(12, 2.6 * len(channels) + 1.4))
    axes = fixed_grid(fig, len(channels), 1, left=0.85, right=0.2, top=0.7, bottom=1.15, wspace=0.0,
                      hspace=0.45).subplots(sharex=True, squeeze=False)
    t = report.time
    for r, channel in enumerate(channels):
        ax = axes[r, 0]
        res = report.residuals[channel]
        shade_phases(ax, t, report.phases[channel])
        ax.plot(t, res, ".", ms=2.5, color=_DATA, zorder=2, label="standardised residual")
        for level in (-2, 2):
            ax.axhline(level, color="k", ls="--", lw=0.7, label="±2" if level == 2 else None)
        if r == 0 and report.high_pareto_k.shape[0]:
            hk = report.high_pareto_k
            top = np.nanmax(np.abs(res)) if res.size else 1.0
            ax.plot(hk["time"], np.full(hk.shape[0], top), "v", color="crimson", ms=6, zorder=3,
                    label=f"Pareto k > {PARETO_K_LIMIT} (all channels of the bin)")
        row = report.overall(channel)
        ax.set_title(f"{channel}: mean {row['mean']:+.2f}, sd {row['sd']:.2f}, lag-1 ACF {row.acf1:+.2f}, "
                     f"Ljung–Box p = {row.ljung_box_p:.2g}", fontsize=9)
        ax.set_ylabel("(y − E[ŷ]) / (λ̄σ) [-]", fontsize=8)
        ax.grid(alpha=0.3)
        if r == 0:
            handles, _ = ax.get_legend_handles_labels()
    finish_residual_figure(fig, axes, handles, 0.06,
                           "Standardised residuals: should look like white noise of sd 1 in every phase — runs, "
                           "waves or offsets in a phase point at what the model misses")
    return fig

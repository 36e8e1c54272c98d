"""Figures of a diagnosis (:mod:`cpas_bayes.inference.diagnose`).

* ``screen.png`` — (mode screen) each physical term's MAP gain over the baseline.
* ``elpd.png`` — every fitted model's elpd gain over the baseline with its
  ±2 se bar (the discrepancy alone, each term with it, the named terms).
* ``discrepancy.png`` — the generic discrepancy's fitted shape per channel
  (posterior mean ± 2 sd, in drag area, against the stated 1-sigma): where in
  time and in which channel the simulation is wrong.
* ``residuals.png`` — standardised residuals against time per channel,
  flight phases shaded, baseline (grey) and with the named (or best) term
  (colour): what the term removes.
* ``comparison.png`` — each channel's data with the posterior-mean
  prediction of the baseline and of the extended model, whole test and a zoom
  on the window where the term changes the fit most.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from cpas_bayes.outputs.plots.checks import finish_residual_figure, shade_phases

_BASE = "0.45"
_EXT = "#d95f02"
_AR = "#7570b3"


def plot_elpd(table, causes, min_gain, min_gain_se, test_name):
    """Horizontal bars: elpd gain over the baseline ± min_gain_se·se per fitted model."""
    causes = [causes] if isinstance(causes, str) else list(causes)
    named = "+".join(c for c in causes if c != "unexplained")
    table = table.sort_values("elpd_diff")
    fig, ax = plt.subplots(figsize=(8.5, 0.6 * len(table) + 1.8), constrained_layout=True)
    y = np.arange(len(table))
    colours = [(_EXT if named and n == named else (_AR if "discrepancy" in n else "0.35")) for n in table["name"]]
    ax.barh(y, table["elpd_diff"], color=colours, alpha=0.85)
    ax.errorbar(table["elpd_diff"], y, xerr=min_gain_se * table["elpd_diff_se"], fmt="none", ecolor="k",
                capsize=3, lw=1, label=f"± {min_gain_se:g} se")
    ax.axvline(0, color="k", lw=0.8)
    ax.axvline(min_gain, color="crimson", ls="--", lw=0.8, label=f"rule: gain > {min_gain:g}")
    ax.set_yticks(y, [n.replace("_", " ").replace("+", " + ") for n in table["name"]])
    ax.set_xscale("symlog", linthresh=10)
    ax.set_xlabel("elpd gain over the baseline (PSIS-LOO, log units; symmetric-log axis)")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3, axis="x")
    verdict = ("causes: " + ", ".join(c.replace("_", " ") for c in causes)) if causes else "nothing to explain"
    ax.set_title(f"{test_name}: how much each model explains ({verdict})\n"
                 "purple: with the generic discrepancy; orange: the named terms alone", fontsize=9)
    return fig


def plot_screen(screen, threshold, test_name):
    """MAP log-posterior gain of each physical term over the baseline, with the screen threshold."""
    names = list(screen)
    gains = [screen[n].map_gain for n in names]
    fig, ax = plt.subplots(figsize=(8.5, 0.6 * len(names) + 1.8), constrained_layout=True)
    y = np.arange(len(names))
    ax.barh(y, gains, color=[_EXT if screen[n].passed else "0.6" for n in names])
    ax.axvline(threshold, color="crimson", ls="--", lw=0.8, label=f"screen: gain > {threshold:g}")
    ax.axvline(0, color="k", lw=0.8)
    labels = [n.replace("_", " ") + ("" if screen[n].size is None else f"  (size {screen[n].size:.3g})")
              for n in names]
    ax.set_yticks(y, labels)
    ax.set_xscale("symlog", linthresh=10)
    ax.set_xlabel("log posterior at the extended MAP − at the baseline MAP (symmetric-log axis)")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3, axis="x")
    ax.set_title(f"{test_name}: MAP screen — orange terms (gain above the line, size beyond its floor) "
                 "go on to sampling and PSIS-LOO", fontsize=9)
    return fig


def plot_residual_comparison(baseline_report, extended_report, name, test_name):
    """Standardised residuals of the baseline and of the extended model, per channel, phases shaded."""
    channels = list(baseline_report.residuals)
    fig, axes = plt.subplots(len(channels), 1, figsize=(12, 2.5 * len(channels) + 1.2), constrained_layout=True,
                             sharex=True, squeeze=False)
    t = baseline_report.time
    for r, channel in enumerate(channels):
        ax = axes[r, 0]
        shade_phases(ax, t, baseline_report.phases[channel])
        rb = baseline_report.residuals[channel]
        re = extended_report.residuals[channel]
        ax.plot(t, rb, ".", ms=2.5, color=_BASE, zorder=2, label="baseline")
        ax.plot(t, re, ".", ms=2.5, color=_EXT, zorder=3, label=f"with {name.replace('_', ' ')}")
        for level in (-2, 2):
            ax.axhline(level, color="k", ls="--", lw=0.7)
        acf_b = float(baseline_report.overall(channel)["acf1"])
        acf_e = float(extended_report.overall(channel)["acf1"])
        ax.set_title(f"{channel}: sd {np.std(rb):.2f} → {np.std(re):.2f}, lag-1 ACF {acf_b:+.2f} → {acf_e:+.2f}",
                     fontsize=9)
        ax.set_ylabel("standardised\nresidual [-]", fontsize=8)
        ax.grid(alpha=0.3)
        if r == 0:
            handles, _ = ax.get_legend_handles_labels()
    finish_residual_figure(fig, axes, handles, 0.07,
                           f"{test_name}: residuals before (grey) and after adding {name.replace('_', ' ')} "
                           "(orange) — a real cause turns waves and runs into white noise")
    return fig


def plot_fit_comparison(time, channels, units, name, test_name, window):
    """Data and the two posterior-mean predictions per channel; right column zooms on ``window``.

    ``channels``: list of (label, data, baseline mean, extended mean), SI drag areas.
    """
    area = units.label("area")
    fig, axes = plt.subplots(len(channels), 2, figsize=(13, 2.8 * len(channels) + 1), constrained_layout=True,
                             squeeze=False, gridspec_kw={"width_ratios": [1.4, 1]})
    zoom = (time >= window[0]) & (time <= window[1])
    for r, (label, data, base, ext) in enumerate(channels):
        for c, mask in enumerate((np.ones_like(zoom), zoom)):
            ax = axes[r, c]
            ax.plot(time[mask], units.from_si(data[mask], "area"), ".", ms=2.5, color="0.2", label="data")
            ax.plot(time[mask], units.from_si(base[mask], "area"), "-", color=_BASE, lw=1.3, label="baseline")
            ax.plot(time[mask], units.from_si(ext[mask], "area"), "-", color=_EXT, lw=1.3,
                    label=f"with {name.replace('_', ' ')}")
            ax.grid(alpha=0.3)
            ax.set_ylabel(f"drag area [{area}]", fontsize=8)
            if c == 0:
                ax.axvspan(*window, color="gold", alpha=0.2, lw=0)
                ax.set_title(label, fontsize=9)
            else:
                ax.set_title(f"{label}: zoom where the term changes the fit most", fontsize=9)
            if r == 0 and c == 0:
                ax.legend(fontsize=8, loc="upper right")
    for c in range(2):
        axes[-1, c].set_xlabel("time [s]")
    fig.suptitle(f"{test_name}: posterior-mean predictions of the baseline and of the model with "
                 f"{name.replace('_', ' ')} against the data (load cells: raw Eq. 11 drag areas)", fontsize=10)
    return fig


def plot_discrepancy(shape, where, units, test_name):
    """One panel per channel: the discrepancy's posterior mean ± 2 sd (drag area) against ±1 stated sigma,
    the regions the diagnosis reports shaded."""
    time, names = shape["time"], shape["channels"]
    area = units.label("area")
    fig, axes = plt.subplots(len(names), 1, figsize=(9, 2.1 * len(names) + 0.8), sharex=True, squeeze=False,
                             constrained_layout=True)
    for c, (ax, name) in enumerate(zip(axes[:, 0], names)):
        mean, sd, sigma = (units.from_si(shape[k][c], "area") for k in ("mean", "sd", "sigma"))
        ax.fill_between(time, -sigma, sigma, color="0.85", lw=0, label="± stated 1-sigma")
        ax.fill_between(time, mean - 2 * sd, mean + 2 * sd, color=_AR, alpha=0.3, lw=0, label="± 2 sd")
        ax.plot(time, mean, color=_AR, lw=1.2, label="discrepancy (posterior mean)")
        for w in where:
            if w["channel"] == name:
                ax.axvspan(w["t_start"], w["t_end"], color=_EXT, alpha=0.15)
                ax.annotate(w["phase"], (w["t_start"], 0.92), xycoords=("data", "axes fraction"), fontsize=7,
                            color=_EXT)
        ax.axhline(0, color="k", lw=0.6)
        ax.set_ylabel(f"{name}\n({area})", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="upper right", ncol=3)
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle(f"{test_name}: what the simulation misses (generic discrepancy, orange: reported regions)",
                 fontsize=10)
    return fig

"""Figure of the friction-loss calibration (the seed's Fig. 5–6).

Left: accelerometer drag area against the raw load-cell sum, steady windows
shaded. Middle: the same after scaling. Right: the scale factor against time,
with each window's ratio. All in the bundle's units.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from cpas_bayes.data.friction import running_mean

_ACC = "#1f9bd1"     # accelerometer (cyan-ish, as in the seed's figures)
_CELLS = "#7b3294"   # load-cell sum (purple)


def _shade_windows(ax, scale):
    for j, (t0, t1) in enumerate(scale.windows):
        ax.axvspan(t0, t1, color="0.85", zorder=0, label="steady window" if j == 0 else None)


def _drag_panel(ax, time, acc, cells, chutes, smooth, area, title):
    ax.plot(time, acc, color=_ACC, lw=0.4, alpha=0.35, label="accelerometer (Eq. 8), samples")
    for pid, values in chutes.items():
        ax.plot(time, values, lw=0.7, alpha=0.8, label=f"load cell {pid} (Eq. 11)")
    if cells is not None:
        ax.plot(time, cells, color=_CELLS, lw=1.0, label="load-cell sum")
    # Drawn last so the (noisier) accelerometer trend stays visible over the sum.
    ax.plot(time, running_mean(acc, smooth), color="#08519c", lw=1.2, ls="--",
            label="accelerometer, 0.25 s running mean")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"drag area PRF·(C_D S) [{area}]")
    ax.set_title(title)
    ax.grid(alpha=0.3)


def plot_reduction(reduction):
    """Return the calibration figure of a :class:`~cpas_bayes.data.reduction.Reduction`."""
    test = reduction.test
    u = test.units
    area = u.label("area")
    df = reduction.to_bundle_units()
    time = df["time"].to_numpy()
    smooth = max(1, int(round(0.25 * test.sample_rate)))
    scale = reduction.scale
    if scale is None:
        fig, ax = plt.subplots(figsize=(7, 4.5), constrained_layout=True)
        _drag_panel(ax, time, df["cds_total"].to_numpy(), None, {}, smooth, area,
                    "accelerometer drag area")
        ax.legend(fontsize=7, loc="upper left")
        fig.suptitle(f"{test.name}: no load cells — total parachute drag area from the accelerometer only")
        return fig

    ids = [p.id for p in test.parachutes]
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.2), constrained_layout=True,
                             gridspec_kw={"width_ratios": [1.2, 1.2, 1.0]})
    _drag_panel(axes[0], time, df["cds_total"].to_numpy(), df["cds_cells_raw"].to_numpy(),
                {pid: df[f"cds_{pid}_raw"].to_numpy() for pid in ids}, smooth, area,
                "before scaling: load cells read low (friction)")
    _drag_panel(axes[1], time, df["cds_total"].to_numpy(), df["cds_cells"].to_numpy(),
                {pid: df[f"cds_{pid}"].to_numpy() for pid in ids}, smooth, area,
                f"after scaling ({scale.mode} factor)")
    for ax in axes[:2]:
        _shade_windows(ax, scale)
        # Drag areas grow to the right: the upper left stays clear (and "best" is slow on long series).
        ax.legend(fontsize=7, loc="upper left")

    ax = axes[2]
    s, s_sigma = df["scale"].to_numpy(), df["scale_sigma"].to_numpy()
    ax.fill_between(time, s - s_sigma, s + s_sigma, color=_CELLS, alpha=0.2, label="applied factor ±1σ")
    ax.plot(time, s, color=_CELLS, lw=1.5, label="applied factor")
    half = np.array([0.5 * (b - a) for a, b in scale.windows])
    ax.errorbar(scale.midpoints, scale.values, xerr=half, yerr=scale.sigma, fmt="none", ecolor="0.4",
                lw=0.8, capsize=3, label="window ratio ±1σ total (bar: window)")
    ax.errorbar(scale.midpoints, scale.values, yerr=scale.sigma_random, fmt="o", color="k", ms=4, lw=2.5,
                label="window ratio ±1σ random (scatter only)")
    _shade_windows(ax, scale)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("scale factor: accelerometer / load-cell drag area [-]")
    ax.set_title("friction-loss scale factor")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    fig.suptitle(f"{test.name}: load-cell calibration against the accelerometer — after scaling the "
                 "load-cell sum (purple) should lie on the accelerometer drag area (dashed blue) in the shaded "
                 "steady windows", fontsize=10)
    return fig

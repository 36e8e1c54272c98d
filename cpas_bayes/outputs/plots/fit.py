"""Figures of a fitted test: posterior bands over the data, loads, corners, traces and checks.

The figures :func:`cpas_bayes.outputs.fit_figures.write_fit_figures` writes, in the bundle's units:

* ``bands.png`` — each parachute's load-cell drag area (points; raw Eq. 11
  values scaled by the posterior-median friction factor s̄:
  CDS = s̄·(lc − W_p·G/q̄) + W_p·G/q̄) with the posterior 50 % / 90 % bands
  and median of the model drag area; last column the accelerometer drag area
  (Eq. 8) with the bands of the predicted cluster channel. Row 1 the whole
  test, the rows below zoom on each stage's fill (the seed's Fig. 12/15/25).
* ``loads.png`` — total load from the accelerometer (Eq. 6,
  F = q̄·CDS_acc − ΣW_p·G) with the predicted-load bands (model and
  model + noise), and the scaled load-cell sum (the seed's Fig. 17/26/31).
* ``corner_<chute>_s<k>.png`` — joint posterior of one stage's parameters.
* ``trace.png`` — traces and rank histograms per ensemble of the parameters
  with the worst R-hat.
* ``ppc.png``, ``loo_pit.png``, ``residuals.png`` — the checks of
  :mod:`cpas_bayes.inference.predictive_checks` and
  :mod:`cpas_bayes.inference.residuals`.
"""

from __future__ import annotations

import textwrap

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import MaxNLocator

from cpas_bayes.inference.check_draws import channel_sigma, posterior_median
from cpas_bayes.inference.residuals import stage_timing_medians
from cpas_bayes.outputs.figures import DATA_COLOR as _DATA
from cpas_bayes.outputs.figures import MODEL_COLOR as _MODEL
from cpas_bayes.outputs.figures import fixed_grid, save_figure
from cpas_bayes.outputs.plots.checks import plot_loo_pit, plot_ppc, plot_residuals

_ACC = "#1f9bd1"
ZOOM = {"infinite": (0.5, 3.0), "finite": (1.0, 10.0)}   # s before / after a stage start
CORNER_TICKS = 3   # MaxNLocator's bins: 3-4 ticks on a 2-inch panel
_SI_QUANTITY = {"m²": "area", "N": "force"}   # parameter unit -> quantity converted to the bundle's units
DPI = 110


# ---------------------------------------------------------------------------
# helpers


def _quantile_bands(x):
    """5, 25, 50, 75, 95 % quantiles over the first axis."""
    return np.quantile(x, (0.05, 0.25, 0.5, 0.75, 0.95), axis=0)


def _data_and_bands(ax, t, data, color, data_label, bands, band_label, starts, ylabel):
    """One drag-area panel: measured points (if any), posterior bands, stage starts, labels."""
    if data is not None:
        ax.plot(t, data, ".", ms=2.5, color=color, label=data_label)
    _draw_bands(ax, t, bands, _MODEL, band_label)
    _mark_starts(ax, starts)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)


def _draw_bands(ax, time, bands, color, label):
    q05, q25, q50, q75, q95 = bands
    ax.fill_between(time, q05, q95, color=color, alpha=0.2, lw=0, label=f"{label} 90 % band")
    ax.fill_between(time, q25, q75, color=color, alpha=0.45, lw=0, label=f"{label} 50 % band")
    ax.plot(time, q50, color=color, lw=1.2, zorder=4, label=f"{label} median")


def _zoom(ax, time, t0, t1, *series, pad=0.05):
    """Set x to [t0, t1] and y to the range of ``series`` (arrays over ``time``) in that window."""
    ax.set_xlim(t0, t1)
    m = (time >= t0) & (time <= t1)
    if not m.any():
        return
    lo = min(float(np.nanmin(s[..., m])) for s in series)
    hi = max(float(np.nanmax(s[..., m])) for s in series)
    span = hi - lo if hi > lo else 1.0
    ax.set_ylim(lo - pad * span, hi + pad * span)


def _mark_starts(ax, starts, label=True):
    for j, s in enumerate(starts):
        ax.axvline(s, color="k", ls=":", lw=0.9, label="stage start (posterior median)" if label and j == 0 else None)


def _save(fig, path):
    save_figure(fig, path, dpi=DPI)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------
# bands.png


def _cluster_stage_window(model, timing, k):
    """Parachutes having stage k, and the zoom window around their stage-k starts (ZOOM by inflation)."""
    having = [p for p in model.parachutes if len(p.stages) > k]
    first = min(timing[p.id][0][k] for p in having)
    last = max(timing[p.id][0][k] for p in having)
    before, after = ZOOM["finite" if any(p.inflation == "finite" for p in having) else "infinite"]
    return having, first - before, last + after


def plot_bands(fit, pred):
    """Drag-area data with posterior bands, one column per parachute plus the accelerometer."""
    model, obs, tree = fit.model, fit.model.obs, fit.tree
    u = model.test.units
    area = u.label("area")
    t = obs.time
    timing = stage_timing_medians(fit)
    s_bar = posterior_median(tree, "load_scale", 1.0)
    lc_row = {int(c): r for r, c in enumerate(obs.lc_index)}
    n_cols = model.n_chutes + 1
    n_rows = 1 + model.n_stages
    footer = _health_lines(fit.summary.get("warnings") or [], 4.6 * n_cols)
    footer_height = 0.15 * len(footer) + (0.1 if footer else 0.0)
    fig = plt.figure(figsize=(4.6 * n_cols, 3.3 * n_rows + footer_height))
    axes = fixed_grid(fig, n_rows, n_cols, left=0.75, right=0.15, top=0.8, bottom=0.5 + footer_height,
                      wspace=0.75, hspace=0.75).subplots(squeeze=False)
    for i, p in enumerate(model.parachutes):
        bands = u.from_si(_quantile_bands(pred["cds"][:, i, :]), "area")
        data = None
        if i in lc_row:
            w = obs.lc_weight_term[lc_row[i]]
            data = u.from_si(s_bar * (obs.lc[lc_row[i]] - w) + w, "area")
        starts = timing[p.id][0]
        for row in range(n_rows):
            ax = axes[row, i]
            if row > len(p.stages):
                ax.set_axis_off()
                continue
            _data_and_bands(ax, t, data, _DATA, f"load cell {p.id} (Eq. 11, × s̄ = {s_bar:.3f})", bands, "model",
                            starts, f"drag area C_D S [{area}]")
            if row == 0:
                against = "load cell against the model" if data is not None else "the model (no load cell)"
                ax.set_title(f"{p.id} ({p.kind}, {p.inflation} mass): {against}", fontsize=10)
                ax.legend(fontsize=7, loc="upper left")
            else:
                before, after = ZOOM[p.inflation]
                s0 = starts[row - 1]
                end = starts[row] if row < len(starts) else t[-1]
                t1 = min(s0 + after, max(end, s0 + 0.5))
                _zoom(ax, t, s0 - before, t1, bands, *(() if data is None else (data,)))
                ax.set_title(f"{p.id} stage {row} ({p.stages[row - 1].label}): fill, peak and decay", fontsize=9)
    ax_col = n_cols - 1
    acc_bands = u.from_si(_quantile_bands(pred["acc"]), "area")
    acc_data = u.from_si(obs.acc, "area")
    all_starts = np.concatenate([timing[p.id][0] for p in model.parachutes])
    for row in range(n_rows):
        ax = axes[row, ax_col]
        _data_and_bands(ax, t, acc_data, _ACC, "accelerometer drag area (Eq. 8)", acc_bands, "Σ canopies (model)",
                        all_starts, f"total drag area [{area}]")
        if row == 0:
            ax.set_title("cluster: accelerometer against the summed model", fontsize=10)
            ax.legend(fontsize=7, loc="upper left")
        else:
            _, t0, t1 = _cluster_stage_window(model, timing, row - 1)
            _zoom(ax, t, t0, t1, acc_bands, acc_data)
            ax.set_title(f"cluster stage {row}: the sum of the individual fills", fontsize=9)
    fig.suptitle(f"{model.test.name}: reconstructed drag areas — the posterior bands of the model (its "
                 "uncertainty, not the noise)\nshould run through the middle of the points, fill, peak and decay "
                 "included; lower rows zoom on each fill", fontsize=10)
    if footer:
        fig.text(0.5, 0.08 / fig.get_figheight(), "\n".join(footer), color="firebrick", fontsize=8, ha="center",
                 va="bottom")
    return fig


def _health_lines(warnings, fig_width, shown=4):
    """Lines of the fit's health warnings (summary.json ``warnings``) for under the figure; none when clean."""
    if not warnings:
        return []
    width = max(60, int(fig_width * 15))   # characters of 8-pt text across the figure
    lines = [line for w in warnings[:shown] for line in textwrap.wrap(f"[{w['code']}] {w['message']}", width)]
    if len(warnings) > shown:
        lines.append(f"... and {len(warnings) - shown} more in summary.json")
    return ["FIT HEALTH WARNINGS"] + lines


# ---------------------------------------------------------------------------
# loads.png


def plot_loads(fit, pred, rng):
    """Total load (Eq. 6) data with predicted-load bands; zooms on each stage."""
    model, obs, tree = fit.model, fit.model.obs, fit.tree
    u = model.test.units
    force = u.label("force")
    t = obs.time
    qbar, g = obs.qbar_at(t), obs.g_at(t)
    w_chutes = model.chute_weight.sum()

    def to_load(cds_acc):
        """Eq. 6 in drag-area form: F = q̄·CDS_acc − ΣW_p·G (= W_V·G − q̄·CDS_V), bundle units."""
        return u.from_si(qbar * cds_acc - w_chutes * g, "force")

    data = to_load(obs.acc)
    model_bands = _quantile_bands(to_load(pred["acc"]))
    sigma_acc, _ = channel_sigma(obs)   # marginal 1-sigma of the channel (independent + q̄ parts)
    noisy = pred["acc"] + pred["noise_acc"][:, None] * sigma_acc * rng.standard_normal(pred["acc"].shape)
    predictive = np.quantile(to_load(noisy), (0.05, 0.95), axis=0)
    s_bar = posterior_median(tree, "load_scale", 1.0)
    cells = None
    if obs.lc_index.size:
        weights = model.chute_weight[obs.lc_index][:, None]
        cells = u.from_si((s_bar * (qbar * obs.lc - weights * g)).sum(axis=0), "force")
    timing = stage_timing_medians(fit)
    K = model.n_stages
    fig = plt.figure(figsize=(max(10, 4.2 * K), 8))
    grid = fixed_grid(fig, 2, K, left=0.85, right=0.2, top=0.75, bottom=0.55, wspace=0.9, hspace=0.85)
    top = fig.add_subplot(grid[0, :])
    zooms = [fig.add_subplot(grid[1, k]) for k in range(K)]
    for j, ax in enumerate([top] + zooms):
        ax.fill_between(t, predictive[0], predictive[1], color="0.7", alpha=0.35, lw=0,
                        label="predicted load + noise, 90 %")
        _draw_bands(ax, t, model_bands, _MODEL, "predicted load")
        ax.plot(t, data, ".", ms=2.5, color=_ACC, label="accelerometer load (Eq. 6)")
        if cells is not None:
            ax.plot(t, cells, lw=0.7, ls="--", color="#7b3294", alpha=0.7, zorder=1,
                    label=f"load-cell sum × s̄ = {s_bar:.3f}")
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"total parachute load [{force}]")
        ax.grid(alpha=0.3)
        if j == 0:
            ax.legend(fontsize=7, loc="upper right")
            ax.set_title("whole test")
            continue
        k = j - 1
        having, t0, t1 = _cluster_stage_window(model, timing, k)
        _zoom(ax, t, t0, t1, model_bands, data, predictive)
        _mark_starts(ax, [timing[p.id][0][k] for p in having], label=False)
        ax.set_title(f"stage {k + 1} ({having[0].stages[k].label}): peak load", fontsize=9)
    fig.suptitle(f"{model.test.name}: total inflation load — the peak of the data should fall inside the "
                 "predicted band, at the predicted time", fontsize=10)
    return fig


# ---------------------------------------------------------------------------
# corner plots


def _density_levels(h, fractions=(0.5, 0.9)):
    """Histogram heights enclosing the given probability fractions (highest first)."""
    flat = np.sort(h.ravel())[::-1]
    cum = np.cumsum(flat) / flat.sum()
    return sorted({float(flat[min(np.searchsorted(cum, f), flat.size - 1)]) for f in fractions})


def plot_corner(values, names, labels, title, max_points=2500, rng=None):
    """Corner plot: histograms on the diagonal, scatter with 50 %/90 % contours below.

    ``values`` (S, D) draws, ``names`` short names, ``labels`` axis labels with units.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    d = len(names)
    fig = plt.figure(figsize=(2.2 * d + 1, 2.2 * d + 1))
    # Fixed spacing: a constrained layout of d² axes costs seconds per figure. Only the lower triangle's
    # axes are made (~9 ms each) and each histogram is one patch, not 40 bars.
    grid = fig.add_gridspec(d, d, left=0.09, right=0.98, bottom=0.08, top=0.95, wspace=0.08, hspace=0.25)
    pick = rng.choice(values.shape[0], size=min(max_points, values.shape[0]), replace=False)
    for r in range(d):
        for c in range(r + 1):
            ax = fig.add_subplot(grid[r, c])
            # at most four ticks an axis: a tick and its label are a third of a corner's drawing time
            ax.xaxis.set_major_locator(MaxNLocator(CORNER_TICKS))
            ax.yaxis.set_major_locator(MaxNLocator(CORNER_TICKS))
            x = values[:, c]
            if r == c:
                q05, q50, q95 = np.quantile(x, (0.05, 0.5, 0.95))
                ax.hist(x, bins=40, color=_MODEL, alpha=0.7, density=True, histtype="stepfilled")
                for q in (q05, q50, q95):
                    ax.axvline(q, color="k", lw=0.8, ls="--" if q != q50 else "-")
                ax.set_title(f"{names[c]} = {q50:.4g} [{q05:.4g}, {q95:.4g}]", fontsize=8)
                ax.set_yticks([])
            else:
                y = values[:, r]
                ax.plot(x[pick], y[pick], ".", ms=1.2, color="0.5", alpha=0.4)
                h, xe, ye = np.histogram2d(x, y, bins=30)
                if h.sum() > 0 and np.ptp(x) > 0 and np.ptp(y) > 0:
                    xc, yc = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1])
                    levels = [lv for lv in _density_levels(h) if 0 < lv < h.max()]
                    if levels:
                        ax.contour(xc, yc, h.T, levels=levels, colors=[_MODEL], linewidths=0.9)
            if r == d - 1:
                ax.set_xlabel(labels[c], fontsize=8)
            else:
                ax.set_xticklabels([])
            if c == 0 and r != 0:
                ax.set_ylabel(labels[r], fontsize=8)
            elif c != r:
                ax.set_yticklabels([])
            ax.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=10)
    return fig


# ---------------------------------------------------------------------------
# trace.png


def plot_trace(fit, names):
    """Per parameter: trace of each ensemble (walker median and a few walkers) and rank histograms."""
    post = fit.tree["posterior"]
    ensemble = np.asarray(post["ensemble"].values) if "ensemble" in post.coords else np.zeros(post.sizes["chain"])
    ids = np.unique(ensemble)
    per = fit.summary.get("diagnostics_per_parameter", {}) or {}
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig = plt.figure(figsize=(12, 2.1 * len(names) + 1))
    axes = fixed_grid(fig, len(names), 2, left=0.9, right=0.2, top=0.7, bottom=0.55, wspace=0.75, hspace=0.5,
                      width_ratios=[1.6, 1.0]).subplots(squeeze=False)
    units = fit.model.test.units
    for r, name in enumerate(names):
        unit = next((prm.unit for prm in fit.model.parameters if prm.name == name), "")
        quantity = _SI_QUANTITY.get(unit)
        x = np.asarray(post[name].values, float)          # (chain, draw)
        if quantity:
            x, unit = units.from_si(x, quantity), units.label(quantity)
        ranks = np.argsort(np.argsort(x.ravel())).reshape(x.shape)
        n_bins = 20
        ax_t, ax_r = axes[r]
        for j, e in enumerate(ids):
            rows = x[ensemble == e]
            color = colors[j % len(colors)]
            for walker in rows[:3]:
                ax_t.plot(walker, color=color, lw=0.4, alpha=0.35)
            ax_t.plot(np.median(rows, axis=0), color=color, lw=1.4, label=f"ensemble {int(e) + 1} (walker median)")
            counts, edges = np.histogram(ranks[ensemble == e], bins=n_bins, range=(0, x.size))
            ax_r.stairs(counts / counts.sum() * n_bins, edges / x.size, color=color, lw=1.3, baseline=None,
                        label=f"ensemble {int(e) + 1}")
        ax_r.axhline(1.0, color="k", ls="--", lw=0.8, label="uniform (well mixed)")
        ax_r.set_ylim(0.0, max(1.6, ax_r.get_ylim()[1]))   # from zero, so sampling wiggles look their size
        rhat = per.get(name, {}).get("rhat")
        ax_t.set_ylabel(f"{name} [{unit or '-'}]", fontsize=8)
        ax_t.set_title(f"{name}: R-hat = {rhat:.4f}" if rhat is not None else name, fontsize=9)
        ax_r.set_ylabel("rank density [-]", fontsize=8)
        ax_t.grid(alpha=0.3)
        if r == len(names) - 1:
            ax_t.set_xlabel("stored draw after burn-in and thinning [-]")
            ax_r.set_xlabel("normalised rank of the draw among all ensembles [-]")
        if r == 0:
            ax_t.legend(fontsize=7, loc="upper right")
            ax_r.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"{fit.model.test.name}: parameters with the worst R-hat — ensembles should overlap in the "
                 "traces and their rank histograms stay flat", fontsize=10)
    return fig


# ---------------------------------------------------------------------------
# all figures


_DRAWERS = {"bands": plot_bands, "loads": plot_loads, "corner": plot_corner, "trace": plot_trace,
            "ppc": plot_ppc, "loo_pit": plot_loo_pit, "residuals": plot_residuals}


def draw_figure(job):
    """Draw one figure of :mod:`cpas_bayes.outputs.fit_figures`' plan and save it (``job`` = (drawer, path,
    args, kwargs)); its path."""
    drawer, path, args, kwargs = job
    return _save(_DRAWERS[drawer](*args, **kwargs), path)

"""Figures of simulated flight tests (cpas_bayes.physics.trajectory, cpas_bayes.data.synth).

``plot_simulated_test``: per-parachute drag areas and riser loads of one
simulated test, with the measured channels of its bundle behind them.
``plot_effect_comparison``: each hidden effect against the same seed without
it, as the change it makes in the accelerometer and load-cell drag areas.
All values in the bundle's (or the given) units.
"""

from __future__ import annotations

import matplotlib.pyplot as plt

from cpas_bayes.core.units import unit_system

_ACC = "#1f9bd1"    # accelerometer channel
_CELLS = "#7b3294"  # load-cell channel
_TOTAL = "0.15"


def plot_simulated_test(result, ids, units="US", test=None, title=None, run=0):
    """Drag areas, riser loads and load factor of run ``run`` of a :class:`TrajectoryResult`.

    ``ids`` names the parachutes in order. With ``test`` (the bundle made
    from this result) the measured channels are drawn behind: the
    accelerometer drag area (Eq. 8, stated weights) and each raw load-cell
    reading.
    """
    u = unit_system(units) if isinstance(units, str) else units
    area, force = u.label("area"), u.label("force")
    time = result.time
    cds = u.from_si(result.cds[run], "area")
    tension = u.from_si(result.tension[run], "force")

    fig, (ax_cds, ax_load, ax_g) = plt.subplots(3, 1, figsize=(9, 10), sharex=True, constrained_layout=True)
    if test is not None:
        d = test.data
        acc = (test.total_weight * d["G"].to_numpy() / d["qbar"].to_numpy() - test.vehicle.cds)
        ax_cds.plot(d["time"], u.from_si(acc, "area"), color=_ACC, lw=0.4, alpha=0.4,
                    label="measured: accelerometer drag area (Eq. 8)")
    for j, pid in enumerate(ids):
        line, = ax_cds.plot(time, cds[j], lw=1.3, label=f"{pid} simulated C_D S")
        ax_load.plot(time, tension[j], lw=1.3, color=line.get_color(), label=f"{pid} riser tension F (Eq. 10)")
        if test is not None and test.parachutes[j].load_column:
            col = test.parachutes[j].load_column
            ax_load.plot(test.data["time"], u.from_si(test.data[col].to_numpy(), "force"), lw=0.4, alpha=0.35,
                         color=line.get_color(), label=f"{pid} load-cell reading (friction, fly-out, noise)")
    ax_cds.plot(time, cds.sum(axis=0), color=_TOTAL, lw=1.0, ls="--", label="sum of canopies")
    ax_load.plot(time, tension.sum(axis=0), color=_TOTAL, lw=1.0, ls="--", label="total riser load")
    ax_cds.set_ylabel(f"drag area C_D S [{area}]")
    ax_cds.set_title("Drag area of each canopy: stage growth, over-inflation peak, decay")
    ax_load.set_ylabel(f"load [{force}]")
    ax_load.set_title("Riser loads: peaks at each inflation; load cells read low by the friction factor")
    ax_g.plot(time, result.load_factor[run], color=_ACC, lw=1.2, label="simulated G (Eq. 5)")
    if test is not None:
        ax_g.plot(test.data["time"], test.data["G"], color=_ACC, lw=0.4, alpha=0.35, label="measured G")
    ax_g.set_ylabel("load factor G [g]")
    ax_g.set_xlabel("time [s]")
    ax_g.set_title("Sensed load factor along the flight path")
    # the drag areas grow to the right: their legend goes top left, out of the way
    for ax, corner in ((ax_cds, "upper left"), (ax_load, "upper right"), (ax_g, "upper right")):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc=corner)
    fig.suptitle(title or "Simulated test: per-parachute drag areas and loads")
    return fig


_EFFECT_TITLES = {
    "added_mass": "added mass k_a = {magnitude:.2f}: both channels, + while filling, − while the air decelerates",
    "friction_drift": "friction drift {magnitude:.3f}: load cells only, a slow trend; accelerometer unchanged",
    "sensor_lag": "sensor lag {lag_ms:.0f} ms: load cells only, spikes at every fast change",
    "canopy_breathing": "breathing A = {magnitude:.2f}, {frequency_hz:.2f} Hz: both channels ring after each peak",
}


def plot_effect_comparison(scenario="drogue", seed=0, magnitudes=None, units="US"):
    """Four panels, one per hidden effect: change in each channel's drag area vs the same seed without it.

    Noise-free channels (:func:`cpas_bayes.data.synth.noise_free_drag_areas`): the
    accelerometer drag area (Eq. 8) and the sum of the load-cell drag areas
    (Eq. 11, unscaled with the constant friction factor). ``magnitudes`` maps
    an effect to its size; missing ones are drawn from the seed as ``synth``
    would.
    """
    from cpas_bayes.data.synth import (EFFECTS, draw_effect_params, draw_truth, noise_free_drag_areas, random_streams,
                         simulate_truth)

    u = unit_system(units) if isinstance(units, str) else units
    area = u.label("area")
    magnitudes = dict(magnitudes or {})
    truth_rng = random_streams(seed)[0]
    truth = draw_truth(scenario, truth_rng)
    baseline_result = simulate_truth(truth)
    baseline = noise_free_drag_areas(truth, "none", {}, result=baseline_result)

    effects = [e for e in EFFECTS if e != "none"]
    fig, axes = plt.subplots(2, 2, figsize=(12, 8), sharex=True, constrained_layout=True)
    for ax, effect in zip(axes.flat, effects):
        # A fresh effect stream per effect: the size `cpas-bayes synth --effect <e> --seed <seed>` draws.
        params = draw_effect_params(effect, scenario, random_streams(seed)[1], magnitudes.get(effect))
        # Load-cell-only effects leave the dynamics alone: reuse the baseline trajectory.
        reuse = baseline_result if effect in ("friction_drift", "sensor_lag") else None
        shown = noise_free_drag_areas(truth, effect, params, result=reuse)
        time = shown.time
        ax.plot(time, u.from_si(shown.accelerometer - baseline.accelerometer, "area"), color=_ACC, lw=1.2,
                label="accelerometer drag area (Eq. 8)")
        ax.plot(time, u.from_si(shown.load_cells.sum(axis=0) - baseline.load_cells.sum(axis=0), "area"),
                color=_CELLS, lw=1.0, ls="--", label="load-cell drag area, sum (Eq. 11)")
        ax.axhline(0.0, color="0.5", lw=0.6)
        ax.set_title(_EFFECT_TITLES[effect].format(lag_ms=1000 * params.get("lag", 0.0), **params), fontsize=9)
        ax.set_ylabel(f"Δ drag area, with − without [{area}]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle(f"Hidden effects, {scenario} scenario, seed {seed}: what each adds to the noise-free channels "
                 "(zero line = channel untouched)")
    return fig

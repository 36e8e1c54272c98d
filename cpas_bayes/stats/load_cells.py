"""What the load cells read: the drag area a riser's force shows through a friction factor and a lag.

Step 3 of :class:`~cpas_bayes.stats.model.TestModel`'s pipeline for the load
cells (Eq. 11 before friction scaling)::

    lc_i(t) = [q̄(t−δ)·CDS_i(t−δ) − W_p,i·G(t−δ)] / (s·q̄(t)) + W_p,i·G(t)/q̄(t)

with s the friction factor (constant, or a term's function of time) and δ a
load-cell lag, a weighted sum over a few delays for a first-order cell
(``Extension.load_cell_lag``); δ = 0 gives lc_i = CDS_i/s + (1 − 1/s)·W_p,i·G/q̄.

At each lagged time base the stage law runs once, with its rate when a term
reads it (an added mass, whose apparent drag area is recomputed there through
:class:`~cpas_bayes.stats.model_parts.Context`), and the smoothed q̄ and G and
any term's air data are read in one walk for all series
(:meth:`~cpas_bayes.stats.observations.Observations.native_series_at`). Before,
the law ran twice per delay and each of seven series searched the native times
on its own: with an added mass beside the lag a Drogue's batch now takes
0.64–0.70× the time, a Main's 0.79–0.85×, for the same values to the bit
(README, Measured figures).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from cpas_bayes.stats.observations import AIR_DATA

_SMOOTH_FLIGHT = ("native_qbar_smooth", "native_g_smooth")


def load_cell_drag_areas(model, ctx, seen, t):
    """Raw load-cell drag areas (B, L, N) at the bin times ``t`` from ``seen`` (B, P, N), the drag areas the
    channels see there (the stage law's, reshaped by the extensions, plus any apparent drag area)."""
    obs = model.obs
    values = ctx.values
    factor = None
    for ext in model.extensions:
        f = ext.friction_factor(ctx, t)
        if f is not None:
            factor = f
    s = values["load_scale"][:, None] if factor is None else factor          # (B, 1) or (B, N)
    lag = next((d for d in (ext.load_cell_lag(ctx) for ext in model.extensions) if d is not None), None)
    idx = obs.lc_index
    weights = model.chute_weight[idx][None, :, None]
    baseline = seen[:, idx, :] / s[:, None, :] + obs.lc_weight_term[None] * (1.0 - 1.0 / s[:, None, :])
    if lag is None:
        return baseline
    # Added to the baseline as the change of the riser force over the lag (δ = 0: the baseline exactly), with
    # q̄ and G smoothed in it: the difference of two noisy samples is noise (±5 m² on a Main's 500 m²).
    delays, node_weights = lag
    force_lag = 0.0
    for k, node_weight in enumerate(node_weights):
        force_lag = force_lag + node_weight * riser_force_at(model, ctx, t[None, :] - delays[:, k, None])
    force_now = obs.smooth_qbar_at(t)[None, None, :] * seen[:, idx, :] - weights * obs.smooth_g_at(t)[None, None, :]
    return baseline + (force_lag - force_now) / (s[:, None, :] * obs.qbar_at(t)[None, None, :])


def riser_force_at(model, ctx, times):
    """The load cells' riser forces q̄·CDS_seen − W_p·G (N), (B, L, M), at a time base ``times`` (B, M) per
    walker: the stage law run there (with its rate when a term reads it), the extensions' reshaping and any
    apparent drag area recomputed there, with q̄ and G smoothed."""
    obs = model.obs
    idx = obs.lc_index
    needs_rate = any(ext.needs_drag_area_rate for ext in model.extensions)
    reads_air = any(ext.reads_air_data for ext in model.extensions)
    names = _SMOOTH_FLIGHT + (AIR_DATA if reads_air else ())
    tt = times[:, None, :]
    if needs_rate:
        cds, rate, _ = model.drag_areas(ctx.stage, tt, with_rate=True)
    else:
        (cds, _), rate = model.drag_areas(ctx.stage, tt), None
    flight = obs.native_series_at(times, names)[:, :, None, :]    # q̄ and G smoothed, then any air data
    there = replace(ctx, time=tt, law=None if rate is None else (cds, rate),
                    air=tuple(flight[2:]) if reads_air else None)
    for ext in model.extensions:
        cds = ext.reshape_drag_area(there, cds, tt)
    extra = model.apparent_drag_area(there, tt)
    cds = cds if extra is None else cds + extra
    return flight[0] * cds[:, idx, :] - model.chute_weight[idx][None, :, None] * flight[1]

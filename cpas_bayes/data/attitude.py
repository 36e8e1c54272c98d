"""Attitude quaternions of a logger bundle: G as the body axes' specific force along the drag direction.

Convention (docs/test-bundle.md, "Logger bundles"): ``q = (w, x, y, z)``, scalar
first, Hamilton product (i² = j² = k² = ijk = −1), a unit quaternion that
rotates body-frame vectors into the local north-east-down (NED) frame::

    v_NED = q ⊗ v_body ⊗ q* = R(q)·v_body,   f = R(q)·a   the specific force (g, NED)

The point-mass model predicts the sensed specific force as drag alone; a
swinging vehicle adds a lateral force L that |a| = √(G² + L²) counts as drag
(≈ L²/(2G) high). G is therefore the component of f along the drag direction,
and this module has two estimates of that direction:

:func:`swing_load_factor` (used: :func:`cpas_bayes.data.bundle_air.attitude_load_factor`)
    The swing's lateral force oscillates about the drag direction, so the drag
    direction is the time-averaged direction of f itself: d̂(t) the normalised
    centred moving average of the unit vectors f/|f| over one swing period
    (:func:`swing_period`, estimated from the record), G = f·d̂. Neither the
    wind nor the receiver enters.
The wind projection (benchmarks/attitude_methods.py, for comparison)
    G = −f·v̂_air with v_air the receiver's velocity less the stated wind. A
    wind error δw turns v̂_air by ~|δw|/|v_air| and biases G low by G·δθ²/2,
    which at descent speeds is larger than the swing bias it removes.

Measured on the ``logger-attitude`` scenario, seeds 1–30, against the noise-free
drag reading (benchmarks/attitude_methods.md), mean error over the readings /
worst seed's mean / RMS z / RMS over seeds of the error at the peak reading: the
moving average +0.0009 g / +0.0073 g / 1.03 / 0.068 g; the wind projection
−0.031 g / −0.189 g / 0.95 / 0.077 g; the magnitude +0.014 g / +0.024 g / 1.40 /
0.117 g. What the moving average leaves is at the fill, where the flight path
turns faster than one swing period resolves (its direction up to ~9° off there;
worst peak reading −0.25 g of 11.7 g). Pure functions, SI (m, m/s, s) and g.
"""

from __future__ import annotations

import math

import numpy as np


NORM_TOLERANCE = 0.01   # |q| may be off 1 by this much (rounding of written cells); beyond, a wrong column
# s: the swing periods looked for, those of pendulums 0.25–16 m long; beyond 8 s the window would also smear the
# flight path's own turns, below 1 s it is of the order of the fill.
PERIOD_BOUNDS = (1.0, 8.0)
# A reading whose |f| is below this many times its axes' combined 1-sigma (free fall right after release) has no
# direction of its own: it is left out of the averages and takes the direction of the readings about it.
DEFINED_NOISE = 3.0
PERIODOGRAM_BIN = 0.1   # s: readings are averaged in bins this long before the periodogram (Nyquist 5 × 1 Hz)


def quaternion_product(p, q):
    """Hamilton product p ⊗ q of (..., 4) arrays, scalar first: R(p ⊗ q) = R(p)·R(q)."""
    p, q = np.asarray(p, float), np.asarray(q, float)
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack([pw * qw - px * qx - py * qy - pz * qz,
                     pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx,
                     pw * qz + px * qy - py * qx + pz * qw], axis=-1)


def rotation_matrix(q):
    """R(q) (..., 3, 3) of unit quaternions q (..., 4), scalar first: body-frame vectors into NED."""
    w, x, y, z = np.moveaxis(np.asarray(q, float), -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1)],
                    axis=-2)


def specific_force(q, accel):
    """f = R(q)·a (N, 3), g, NED, of body axes ``accel`` (N, 3) at attitudes ``q`` (N, 4)."""
    return np.einsum("nij,nj->ni", rotation_matrix(q), accel)


# ---------------------------------------------------------------------------
# the drag direction from the specific force itself (no wind, no receiver)


def moving_direction(times, unit, defined, window):
    """(d̂ (N, 3), spread (N,), count (N,)) at each reading of increasing ``times`` (N,), s.

    d̂ is the normalised mean of the unit vectors ``unit`` (N, 3) whose ``defined`` (N,) is set over the centred
    ``window`` (s) about the reading; near the record's ends the window shrinks to the reading's distance from
    the end, so that it stays centred (a one-sided window would lag the flight path's turn right after
    release). ``spread`` = √(1 − |ū|²)/|ū| (rad) is the unit vectors' scatter about their mean ū, ``count``
    how many were averaged. A reading whose window holds no defined vector takes the nearest reading's answer.
    """
    times = np.asarray(times, float)
    half = np.minimum(0.5 * window, np.minimum(times - times[0], times[-1] - times))
    lo = np.searchsorted(times, times - half - 1e-9, side="left")
    hi = np.searchsorted(times, times + half + 1e-9, side="right")
    weight = np.asarray(defined, float)
    sums = np.concatenate([np.zeros((1, 4)), np.cumsum(np.column_stack([unit * weight[:, None], weight]), axis=0)])
    total = sums[hi] - sums[lo]
    count = total[:, 3]
    mean = total[:, :3] / np.maximum(count, 1.0)[:, None]
    length = np.linalg.norm(mean, axis=1)
    have = np.flatnonzero((count > 0) & (length > 1e-9))
    if have.size < len(times):   # hold the nearest reading's answer (defined readings have themselves)
        after = np.clip(np.searchsorted(have, np.arange(len(times))), 0, have.size - 1)
        before = np.clip(after - 1, 0, have.size - 1)
        nearest = np.where(np.abs(times[have[before]] - times) < np.abs(times[have[after]] - times),
                           have[before], have[after])
        mean, length, count = mean[nearest], length[nearest], count[nearest]
    return mean / length[:, None], np.sqrt(np.maximum(1.0 - length**2, 0.0)) / length, count


def swing_period(times, unit, defined, bounds=PERIOD_BOUNDS):
    """The dominant period (s) within ``bounds`` of the unit vectors' part across a first direction averaged
    over the longest period: the peak of the periodogram of that part (its three NED components, averaged
    in PERIODOGRAM_BIN bins), frequencies spaced a quarter of 1/record."""
    times = np.asarray(times, float)
    first, _, _ = moving_direction(times, unit, defined, bounds[1])
    across = (unit - np.sum(unit * first, axis=1, keepdims=True) * first)[defined]
    t = times[defined]
    bins = np.floor((t - t[0]) / PERIODOGRAM_BIN).astype(int)
    count = np.bincount(bins)
    kept = count > 0
    x = np.column_stack([np.bincount(bins, across[:, k])[kept] / count[kept] for k in range(3)])
    x -= x.mean(axis=0)
    t_bin = t[0] + (np.flatnonzero(kept) + 0.5) * PERIODOGRAM_BIN
    span = max(t[-1] - t[0], bounds[1])
    frequency = np.arange(1.0 / bounds[1], 1.0 / bounds[0] + 1e-12, 0.25 / span)
    power = [np.sum(np.abs(np.exp(-2j * np.pi * nu * t_bin) @ x) ** 2) for nu in frequency]
    return 1.0 / frequency[int(np.argmax(power))]


def swing_load_factor(times, q, accel, accel_sigma, periods=1.0):
    """(G (N,), σ_G (N,), window s): the specific force along its own time-averaged direction.

    ``times`` (N,) increasing, s; ``q`` (N, 4) unit quaternions; ``accel``, ``accel_sigma`` (N, 3), g. The
    window is ``periods`` swing periods (:func:`swing_period`): a centred box-car of one period cancels a
    sinusoidal swing exactly, and a longer one smears the flight path's turn at the fill more (two periods:
    RMS error at the peak reading 0.090 g against one period's 0.068 g, benchmarks/attitude_methods.md).
    σ_G² is the axes' noise through d̂ in body axes, Σ(σ_i·u_i)² with u = R(q)ᵀ·d̂, plus the direction's,
    |f_⊥|²·spread²/count with f_⊥ = f − G·d̂ (:func:`moving_direction`).
    If no reading's |f| reaches DEFINED_NOISE times its noise, each nonzero one is used; if all are zero, G is
    0 with the axes' mean sigma.
    """
    times, accel, accel_sigma = np.asarray(times, float), np.asarray(accel, float), np.asarray(accel_sigma, float)
    force = specific_force(q, accel)
    size = np.linalg.norm(force, axis=1)
    defined = size > DEFINED_NOISE * np.sqrt(np.sum(accel_sigma**2, axis=1))
    if not defined.any():
        defined = size > 0.0
    if not defined.any():
        return np.zeros(len(times)), np.sqrt(np.mean(accel_sigma**2, axis=1)), math.nan
    unit = force / np.maximum(size, 1e-300)[:, None]
    window = periods * swing_period(times, unit, defined)
    direction, spread, count = moving_direction(times, unit, defined, window)
    g = np.sum(force * direction, axis=1)
    across = np.linalg.norm(force - g[:, None] * direction, axis=1)
    body = np.einsum("nji,nj->ni", rotation_matrix(q), direction)   # u = Rᵀ·d̂
    sigma = np.sqrt(np.sum((accel_sigma * body) ** 2, axis=1) + (across * spread) ** 2 / np.maximum(count, 1.0))
    return g, sigma, window


# ---------------------------------------------------------------------------
# the drag direction from the air-relative velocity (for comparison: benchmarks/attitude_methods.py)
#
#     G = −f·v̂_air = −a·u,   u = R(q)ᵀ·v̂_air   (v̂_air in body axes)
#
# v_air at a reading is the receiver's velocity interpolated to the reading's time plus the latency prior's mean,
# less the stated wind there (reading_air_velocity). Its 1-sigma (projection_sigma):
#
#     σ_G² = Σ_i (σ_i·u_i)² + Σ_k (f_⊥,k·σ_v,k)² / max(|v_air|, SPEED_FLOOR)²
#
# the axes' noise, then the direction's: an error δv in v_air turns v̂ by (I − v̂v̂ᵀ)·δv/|v_air| and so moves G
# by −f_⊥·δv/|v_air|, f_⊥ = f − (f·v̂)v̂.

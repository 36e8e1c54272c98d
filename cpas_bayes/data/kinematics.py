"""Does the accelerometer agree with the airspeed's rate? A check of the readings that no fitted term can pass.

Along the flight path the accelerometer senses every force but gravity, so its load factor G (in g) and the
airspeed V obey

    dV/dt = −g₀·(G + sin γ)          (γ the flight-path angle, up positive)

whatever the canopies do: an added mass, a breathing canopy, a friction factor or a lagging load cell change
the drag and the load cells, not this balance. Over a window [a, b] the balance reads

    m = mean over [a, b] of (G + sin γ) + (V(b) − V(a)) / (g₀·(b − a))

the mean load factor the accelerometer reads beyond what the airspeed's change allows (positive: it reads
high); 0 within noise when the two agree. V(a) and V(b) are means of the readings within 0.05 s of the
window's ends, so the check needs no derivative of a noisy channel, and the window's mismatch is exact for
any shape of the deceleration in between. Its 1-sigma follows from the stated ones: the airspeed's from
q̄'s at the two ends (σ_V = V·σ_q̄/(2·q̄), as V ∝ √q̄), and G's summed over the window.

What it catches: an accelerometer whose zero drifts (+0.05 g over a Main's 40 s: m = +0.042 g in the
last full window, χ² p below 1e-200), one that saturates, a pitot line that lags. A friction drift of the
load cells calibrated against such an accelerometer fits the drifting ratio between the two as well as a real
friction drift does (on the independent simulator's Main with a 0.05 g zero drift, ``diagnose`` named
``friction_drift`` and ``sensor_lag``); this balance, which involves no load cell, tells them apart.

Thresholds, on 4-s windows (short enough to say where, long enough that a fill's transient at a window's end
moves its mean by little): the check fails when the windows' χ² (stated sigmas) has p < :data:`ALPHA` *and*
some window's |m| exceeds what it may have: :data:`FLOOR_G` plus a wind's share (below). Tests whose accelerometer and air data are sound read |m| ≤ 0.006 g
in every window: the independent simulator's two example bundles; 64 synthetic Drogues and Mains (seeds
10000-10003), clean or with an added mass (of either form), a breathing canopy, a friction drift, a load-cell
lag, riser ringing or a tare shift; and 32 more (seeds 30000-30001) with two catalogued effects at once or the
other forms of a friction drift and a lag. The floor, 0.015 g, is 1.5 % of a canopy's steady load and 2.5× that.

A wind that changes with altitude breaks the balance in the air's frame: the airspeed then changes by the
wind's rate along the path, shear × descent rate × cos γ, as well. The bundles hold no wind, so a shear of
5 m/s per km (:data:`WIND_SHEAR`, a strong one for the lower atmosphere) is allowed on top of the floor in each
window: next to nothing on a Main's slow descent (its limit 0.015-0.026 g on the example, the most where it
still descends fast), where a Drogue's ~90 m/s gives 0.036-0.048 g. So the check speaks mainly of Mains: the synthetic
pitot lags fail it 4 of 4 on Mains (|m| 0.057-0.14 g), 1 of 4 on Drogues; the synthetic clippings 4 of 4 and 2
of 4; the Main's 0.05 g zero drift reads 0.042 g, the Drogue's 0.031 g, which is not said.

Logger bundles are not checked: their airspeed is reconstructed from the same accelerometer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from cpas_bayes.core.units import STANDARD_GRAVITY

WINDOW_S = 4.0
END_S = 0.05          # readings within this of a window's end give its airspeed
ALPHA = 1e-4
FLOOR_G = 0.015
# a wind that changes with altitude breaks the balance in the air's frame by its rate along the path,
# shear × (descent rate) × cos γ: this much shear is allowed on top of the floor (5 m/s per km of altitude)
WIND_SHEAR = 0.005    # 1/s
COLUMNS = ("G", "airspeed", "gamma")


@dataclass(frozen=True)
class KinematicCheck:
    """The balance over each window: ``windows`` rows (t_start, t_end, mismatch in g, its 1-sigma in g, the
    mismatch a window may have in g: :data:`FLOOR_G` plus what :data:`WIND_SHEAR` would give)."""

    windows: np.ndarray
    chi2: float
    p_value: float

    @property
    def worst(self):
        """The row whose |mismatch| is furthest beyond (or least within) what the window may have."""
        return self.windows[np.argmax(np.abs(self.windows[:, 2]) - self.windows[:, 4])]

    @property
    def p_text(self):
        """The χ² p-value as said: below double precision's smallest, a bound."""
        return f"p = {self.p_value:.1e}" if self.p_value > 0 else "p < 1e-300"

    @property
    def fails(self):
        return bool(self.p_value < ALPHA and abs(self.worst[2]) > self.worst[4])

    def failing_windows(self):
        """[(t_start, t_end, mismatch)] of the windows beyond what they may have and 3 of their sigmas."""
        w = self.windows
        bad = (np.abs(w[:, 2]) > w[:, 4]) & (np.abs(w[:, 2]) > 3.0 * w[:, 3])
        return [(float(a), float(b), float(m)) for a, b, m, _, _ in w[bad]]


def _end_speed(time, speed, sigma, at):
    near = np.abs(time - at) <= END_S + 1e-9
    if not near.any():
        near = np.abs(time - at) == np.abs(time - at).min()
    return time[near].mean(), speed[near].mean(), float(np.sqrt(np.mean(sigma[near] ** 2) / near.sum()))


def accelerometer_kinematics(test, window=WINDOW_S):
    """:class:`KinematicCheck` of ``test`` (SI readings, as :func:`cpas_bayes.data.bundle.read_bundle` gives
    them), or None: a logger bundle, a bundle without G, airspeed and gamma, or a record shorter than two
    windows."""
    data = test.data
    if test.air_data is not None or not all(c in data for c in COLUMNS):
        return None
    time = np.asarray(data["time"], float)
    g = np.asarray(data["G"], float)
    speed = np.asarray(data["airspeed"], float)
    gamma = np.radians(np.asarray(data["gamma"], float))
    sin_gamma = np.sin(gamma)
    shear = WIND_SHEAR * speed * np.abs(sin_gamma * np.cos(gamma)) / STANDARD_GRAVITY   # g: descent rate × cos γ
    g_sigma = np.asarray(data["G_sigma"], float) if "G_sigma" in data else np.zeros_like(time)
    if "qbar_sigma" in data and "qbar" in data:
        speed_sigma = 0.5 * speed * np.asarray(data["qbar_sigma"], float) / np.asarray(data["qbar"], float)
    else:
        speed_sigma = np.zeros_like(time)
    keep = np.isfinite(time) & np.isfinite(g) & np.isfinite(speed) & np.isfinite(sin_gamma)
    keep &= np.isfinite(g_sigma) & np.isfinite(speed_sigma)
    time, g, speed, sin_gamma, g_sigma, speed_sigma, shear = (x[keep] for x in (time, g, speed, sin_gamma, g_sigma,
                                                                              speed_sigma, shear))
    if time.size < 20 or time[-1] - time[0] < 2 * window + 2 * END_S:
        return None
    rows = []
    for a in np.arange(time[0] + END_S, time[-1] - END_S - window + 1e-9, window):
        ta, va, sa = _end_speed(time, speed, speed_sigma, a)
        tb, vb, sb = _end_speed(time, speed, speed_sigma, a + window)
        inside = (time >= ta) & (time <= tb)
        span = tb - ta
        load = np.trapezoid(g[inside] + sin_gamma[inside], time[inside]) / span
        mismatch = load + (vb - va) / (STANDARD_GRAVITY * span)
        step = np.diff(time[inside]).mean() if inside.sum() > 1 else span
        sigma = np.hypot(np.hypot(sa, sb) / (STANDARD_GRAVITY * span),
                         np.sqrt(np.sum(g_sigma[inside] ** 2)) * step / span)
        rows.append((a, a + window, mismatch, max(sigma, 1e-12), FLOOR_G + float(shear[inside].max())))
    windows = np.array(rows)
    chi2 = float(np.sum((windows[:, 2] / windows[:, 3]) ** 2))
    return KinematicCheck(windows=windows, chi2=chi2, p_value=float(stats.chi2.sf(chi2, len(windows))))


def kinematic_warning(test, check=None):
    """The warning a failing :func:`accelerometer_kinematics` gives (naming the columns and the fix), else None."""
    check = check if check is not None else accelerometer_kinematics(test)
    if check is None or not check.fails:
        return None
    a, b, m, s, _ = check.worst
    return (f"data.csv G disagrees with the airspeed's rate: over {a:.1f}-{b:.1f} s the accelerometer reads "
            f"{m:+.3f} g beyond what the airspeed's change and gamma allow (dV/dt = −g₀·(G + sin γ); 1-sigma "
            f"{s:.3f} g from the stated sigmas, χ² {check.p_text} over {len(check.windows)} windows of "
            f"{b - a:g} s). No fitted term changes this balance: check the accelerometer (a drifting zero, a scale "
            "error, saturation), the pitot-static line (a lag), the airspeed (an equivalent airspeed, or one from a "
            "density off, scales its every change), and that gamma is the flight-path angle in degrees, up positive")

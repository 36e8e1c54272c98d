"""Flight-test load reduction: loads and drag areas with 1-sigma (seed §II–III).

Pure numpy functions implement the seed's equations; :func:`reduce_test`
applies them to a :class:`~cpas_bayes.data.bundle.FlightTest` and returns a
:class:`Reduction`; :func:`write_reduction` writes ``reduced.csv``,
``reduction.json`` and ``reduction.png`` in the bundle's units. Everything
inside is SI (N, m², Pa, s); angles are degrees in tables, radians in formulas.

Equations (seed numbering; W_V vehicle weight, W_p,i parachute i's dry weight,
W_T = W_V + Σ W_p,i, G sensed load factor in g, q̄ dynamic pressure)
------------------------------------------------------------------------------
Eq. 6, total parachute load from the accelerometer::

    F = W_V·G − q̄·(CDS)_V

Eq. 7, its 1-sigma (RSS of partial derivatives, inputs uncorrelated)::

    |ΔF| = [(|ΔW_V|·G)² + (|ΔG|·W_V)² + (|Δq̄|·(CDS)_V)² + (|Δ(CDS)_V|·q̄)²]^½

Eq. 8, total parachute drag area from the accelerometer::

    PRF·(CDS)_p = W_T·G/q̄ − (CDS)_V

Eq. 9, its 1-sigma (|ΔW_T|² = |ΔW_V|² + Σ|ΔW_p,i|²)::

    [(|ΔW_T|·G/q̄)² + (|ΔG|·W_T/q̄)² + (|Δq̄|·W_T·G/q̄²)² + |Δ(CDS)_V|²]^½

Eq. 11, drag area of parachute i from its riser load F_i::

    PRF·(CDS)_p,i = (F_i + W_p,i·G)/q̄

Eq. 12 as corrected here. The printed Eq. 12 has a third term
``(|ΔG|·|ΔG|·W_p,i/q̄)²``: it carries |ΔG| twice, which is no partial-
derivative term (it is second order in ΔG and would all but drop the G noise,
by a factor ΔG ≈ 0.03). The RSS of the partial derivatives of Eq. 11 — ∂/∂F_i = 1/q̄,
∂/∂W_p,i = G/q̄, ∂/∂G = W_p,i/q̄, ∂/∂q̄ = −(F_i + W_p,i·G)/q̄² — gives::

    [(|ΔF_i|/q̄)² + (|ΔW_p,i|·G/q̄)² + (|ΔG|·W_p,i/q̄)² + (|Δq̄|·(F_i + W_p,i·G)/q̄²)²]^½

Eq. 13, fly-out correction: the axial (along the flight path) part of a riser
tension read at fly-out angle θ_i is ``F_i·cos θ_i``; with ∂/∂θ = −F_i·sin θ_i
and θ's sigma converted from degrees to radians::

    |Δ(F_i cos θ_i)| = [(|ΔF_i|·cos θ_i)² + (F_i·sin θ_i·|Δθ_i|·π/180)²]^½

Friction-loss scale factor (seed §III.A–C)
------------------------------------------
Load cells in the vehicle read less than the riser tension (friction over the
fairlead). In each steady-state window the ratio::

    R_j = mean(accelerometer drag area, Eq. 8) / mean(Σ_i load-cell drag area, Eq. 11)

is computed, and the axial load of every cell is multiplied by the factor
s(t): ``load_i = s(t)·F_i·cos θ_i``; the drag area is recomputed by Eq. 11.

* Window rule (automatic). For stage k: it may begin once the last parachute
  has started the stage, ``a = max_i(start_i,k + 3·start_sigma_i,k)``, and
  must end before the first one starts the next stage,
  ``b = min_i(start_i,k+1 − 3·start_sigma_i,k+1)`` (or the end of the data).
  The inflation transient is then found in the data: the raw load-cell drag
  area sum, smoothed over 0.25 s, is compared with its level (median of the
  last quarter of [a, b]); the window begins half a smoothing width after the
  last sample outside a band of ±max(1 % of the level, 4 smoothed noise sd),
  looking only in the first half of [a, b] (later excursions are taken as
  oscillation of a steady canopy, not transient), and runs to b. Stages whose
  [a, b] is shorter than 0.5 s or 20 samples are not used. Explicit windows
  (``windows=[(t0, t1), ...]``, CLI ``--window T0:T1``) replace the rule.
* Window ratio uncertainty. Random: the standard error of R_j by the delta
  method, sd of e = A − R_j·L over the window / (√n·mean L), inflated by the
  AR(1) factor √((1+ρ₁)/(1−ρ₁)) of e so serially correlated samples are not
  counted as independent. Systematic: the stated W_V, W_p,i and (CDS)_V
  uncertainties through ∂R/∂W_V = mean(G/q̄)/mean L,
  ∂R/∂W_p,i = mean(G/q̄)·(1 − R)/mean L, ∂R/∂(CDS)_V = −1/mean L. These are
  common to all windows, so they are carried as vectors and combined
  linearly, never RSS'd across windows.
* ``mode="constant"`` (default; the seed's Main practice, and the simpler
  model unless the windows disagree beyond their scatter — the Birge ratio
  in reduction.json tells): one factor, the weighted mean of R_j with
  weights 1/σ_random,j²; its random sigma is the weighted-mean standard error
  times the Birge ratio √(χ²/(n−1)) when that exceeds 1 (windows disagreeing
  more than their scatter allows, as friction changing with stability does).
* ``mode="linear"`` (the seed's Drogue practice): piecewise-linear through
  the points (window midpoint, R_j) — a straight line for two windows as in
  the seed's Fig. 5 — held constant before the first and after the last
  midpoint (extrapolating a friction trend over a transient is not trusted).
  A single window gives a flat factor.

The scale factor's sigma (random and systematic parts as above) enters every
scaled quantity as a systematic term, ``∂load_i/∂s = F_i·cos θ_i``.

Peaks and load share (seed §III.B)
----------------------------------
Stage k's interval for totals runs from the earliest start of stage k among
the parachutes to the earliest start of stage k+1 (or the end of the data).
Peaks are maxima of the series after a quadratic Savitzky–Golay filter over
``peak_smoothing`` seconds (default 0.1 s, an odd number of samples): a raw
maximum of noisy samples is biased high by about one to two noise sd (the
accelerometer's 0.03 g is ~600 lbf on a 20,000 lbf vehicle), while a running
mean of the same width cuts a sharp Drogue over-inflation peak by ~2 %; the
quadratic filter keeps such a peak within ~0.5 % and cuts the noise ~2.2×.
The reported sigma is that of the filtered value (random part √Σc_j²σ_j²).
A parachute's own peak is searched in its own stage interval. Load share
(fractions of the scaled load-cell sum, per stage): at the time of the peak
of the sum; at the time of each parachute's own peak; time-independent,
∫load_i dt / ∫Σ load dt over the stage interval; and the mean of these
(N + 2 methods for N parachutes; four for the seed's pair of Drogues).

Frame columns (SI; ``reduced.csv`` holds the first group only)
--------------------------------------------------------------
``time``; ``load_total``, ``cds_total`` (accelerometer, Eq. 6 and 8) with
``_sigma``; per parachute id: ``load_<id>`` (scaled axial riser load),
``load_<id>_sigma``, ``cds_<id>_raw`` (Eq. 11 with the fly-out-corrected but
unscaled load), ``cds_<id>`` (scaled), ``cds_<id>_sigma``.

Extra columns, for likelihoods that need the error structure:
``<q>_sigma_random`` (per-sample noise of G, q̄, F, θ) and
``<q>_sigma_systematic`` (W_V, W_p, (CDS)_V and scale factor: common to all
samples) for q in ``load_total, cds_total, load_<id>, cds_<id>``;
``load_<id>_raw`` (F_i·cos θ_i) with ``load_<id>_raw_sigma_random``;
``cds_<id>_raw_sigma``, ``cds_<id>_raw_sigma_random``,
``cds_<id>_raw_sigma_systematic`` (W_p,i only); sums over the parachutes
``load_cells``, ``cds_cells`` (scaled) with the same three sigma columns, and
``load_cells_raw``, ``cds_cells_raw`` with ``cds_cells_raw_sigma_random``;
``scale`` and ``scale_sigma`` (the factor applied at each sample). Every
``*_sigma`` is the RSS of its random and systematic parts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
from scipy.signal import savgol_coeffs, savgol_filter

from cpas_bayes.data.bundle import FlightTest
from cpas_bayes.core.errors import InputError
from cpas_bayes.core.files import write_csv, write_json
from cpas_bayes.outputs.figures import save_figure

SCALE_MODES = ("constant", "linear")
DEFAULT_PEAK_SMOOTHING = 0.1   # s, quadratic-filter width before taking a maximum
SETTLE_SMOOTHING = 0.25        # s, running mean used to detect the end of a transient
SETTLE_REL_TOL = 0.01          # band around the steady level, fraction of the level
SETTLE_NOISE_TOL = 4.0         # band in smoothed-noise sd, whichever is wider
MIN_AUTO_SECONDS = 0.5         # shortest stage interval used for calibration
MIN_AUTO_SAMPLES = 20
MIN_WINDOW_SAMPLES = 3         # a user window needs scatter to give an uncertainty


# ---------------------------------------------------------------------------
# equations: pure, vectorised


class SigmaParts(NamedTuple):
    """A 1-sigma split into per-sample random and common systematic parts."""

    random: np.ndarray
    systematic: np.ndarray

    @property
    def total(self):
        return np.hypot(self.random, self.systematic)


def _rss(*terms):
    return np.sqrt(sum(np.square(t) for t in terms))


def accelerometer_load(G, qbar, vehicle_weight, vehicle_cds):
    """Eq. 6: total parachute load F = W_V·G − q̄·(CDS)_V."""
    return vehicle_weight * np.asarray(G, float) - np.asarray(qbar, float) * vehicle_cds


def accelerometer_load_sigma(G, qbar, vehicle_weight, vehicle_cds, G_sigma, qbar_sigma,
                             vehicle_weight_sigma, vehicle_cds_sigma):
    """Eq. 7: 1-sigma of :func:`accelerometer_load`."""
    G, qbar = np.asarray(G, float), np.asarray(qbar, float)
    random = _rss(G_sigma * vehicle_weight, qbar_sigma * vehicle_cds)
    systematic = _rss(vehicle_weight_sigma * G, vehicle_cds_sigma * qbar)
    return SigmaParts(*np.broadcast_arrays(random, systematic))


def accelerometer_drag_area(G, qbar, total_weight, vehicle_cds):
    """Eq. 8: total parachute drag area PRF·(CDS)_p = W_T·G/q̄ − (CDS)_V."""
    return total_weight * np.asarray(G, float) / np.asarray(qbar, float) - vehicle_cds


def accelerometer_drag_area_sigma(G, qbar, total_weight, G_sigma, qbar_sigma,
                                  total_weight_sigma, vehicle_cds_sigma):
    """Eq. 9: 1-sigma of :func:`accelerometer_drag_area`."""
    G, qbar = np.asarray(G, float), np.asarray(qbar, float)
    random = _rss(G_sigma * total_weight / qbar, qbar_sigma * total_weight * G / qbar**2)
    systematic = _rss(total_weight_sigma * G / qbar, vehicle_cds_sigma * np.ones_like(qbar))
    return SigmaParts(*np.broadcast_arrays(random, systematic))


def axial_load(F, theta_deg):
    """Eq. 13 (one term): axial part F·cos θ of a riser tension at fly-out angle θ (deg)."""
    return np.asarray(F, float) * np.cos(np.deg2rad(theta_deg))


def axial_load_sigma(F, theta_deg, F_sigma, theta_sigma_deg):
    """1-sigma of :func:`axial_load`; every input is per-sample noise, so it is all random."""
    theta = np.deg2rad(theta_deg)
    # ∂/∂θ = −F·sin θ per radian; the angle's sigma is given in degrees.
    return _rss(F_sigma * np.cos(theta), np.asarray(F, float) * np.sin(theta) * np.deg2rad(theta_sigma_deg))


def load_cell_drag_area(F, G, qbar, parachute_weight):
    """Eq. 11: PRF·(CDS)_p,i = (F_i + W_p,i·G)/q̄, F_i the axial riser load."""
    return (np.asarray(F, float) + parachute_weight * np.asarray(G, float)) / np.asarray(qbar, float)


def load_cell_drag_area_sigma(F, G, qbar, parachute_weight, F_sigma, G_sigma, qbar_sigma,
                              parachute_weight_sigma, F_sigma_systematic=0.0):
    """Eq. 12 as corrected in the module docstring: 1-sigma of :func:`load_cell_drag_area`.

    ``F_sigma`` is the per-sample noise of the load; ``F_sigma_systematic`` a
    part common to all samples (the friction scale factor's).
    """
    F, G, qbar = (np.asarray(a, float) for a in (F, G, qbar))
    cds = (F + parachute_weight * G) / qbar
    random = _rss(F_sigma / qbar, G_sigma * parachute_weight / qbar, qbar_sigma * cds / qbar)
    systematic = _rss(parachute_weight_sigma * G / qbar, F_sigma_systematic / qbar)
    return SigmaParts(*np.broadcast_arrays(random, systematic))


def running_mean(values, width):
    """Centred running mean over ``width`` samples; fewer samples at the ends."""
    values = np.asarray(values, float)
    width = max(int(width), 1)
    if width == 1 or values.size == 0:
        return values.copy()
    csum = np.concatenate(([0.0], np.cumsum(values)))
    idx = np.arange(values.size)
    lo = np.clip(idx - width // 2, 0, values.size)
    hi = np.clip(lo + width, 0, values.size)
    return (csum[hi] - csum[lo]) / (hi - lo)


def _ar1_inflation(e):
    """Variance inflation (1+ρ₁)/(1−ρ₁) of a mean for serially correlated samples (ρ₁ ≥ 0)."""
    e = e - e.mean()
    denom = float(np.dot(e, e))
    if e.size < 3 or denom <= 0:
        return 1.0
    rho = float(np.dot(e[:-1], e[1:]) / denom)
    rho = min(max(rho, 0.0), 0.99)
    return (1.0 + rho) / (1.0 - rho)


def window_ratio(accelerometer_cds, cells_cds):
    """Friction scale factor of one window and its random standard error.

    R = mean(accelerometer drag area)/mean(load-cell drag area sum); the error
    by the delta method, sd(A − R·L)/(√n·mean L), with the AR(1) inflation.
    """
    A = np.asarray(accelerometer_cds, float)
    L = np.asarray(cells_cds, float)
    mean_L = float(L.mean())
    ratio = float(A.mean()) / mean_L
    e = A - ratio * L
    var_mean = float(np.var(e, ddof=1)) / e.size * _ar1_inflation(e)
    return ratio, math.sqrt(var_mean) / abs(mean_L)


# ---------------------------------------------------------------------------
# the scale factor


@dataclass(frozen=True)
class ScaleFactor:
    """Friction-loss scale factor of the load cells, from steady-state windows.

    ``values``/``sigma_random``/``sigma_systematic`` are per window;
    ``systematic_terms`` (n_windows, n_params) holds each window's derivative
    times the parameter sigma for the parameters ``systematic_names``, so any
    linear combination of windows gets its systematic sigma right.
    """

    mode: str
    windows: tuple
    values: np.ndarray
    sigma_random: np.ndarray
    systematic_terms: np.ndarray
    systematic_names: tuple
    source: str               # "automatic" or "user"
    stages: tuple = ()        # stage label of each automatic window ("" for user windows)

    @property
    def midpoints(self):
        return np.array([0.5 * (a + b) for a, b in self.windows])

    @property
    def sigma_systematic(self):
        return np.sqrt((self.systematic_terms**2).sum(axis=1))

    @property
    def sigma(self):
        """Per-window total 1-sigma."""
        return np.hypot(self.sigma_random, self.sigma_systematic)

    @property
    def _constant_weights(self):
        w = 1.0 / np.maximum(self.sigma_random, 1e-12) ** 2
        return w / w.sum()

    @property
    def birge_ratio(self):
        """√(χ²/(n−1)) of the windows about the constant factor; 1 for one window."""
        n = len(self.values)
        if n < 2:
            return 1.0
        w = self._constant_weights
        mean = float(w @ self.values)
        chi2 = float((((self.values - mean) / np.maximum(self.sigma_random, 1e-12)) ** 2).sum())
        return math.sqrt(chi2 / (n - 1))

    def weights(self, t):
        """(len(t), n_windows) weights: factor(t) = weights(t) @ values."""
        t = np.atleast_1d(np.asarray(t, float))
        n = len(self.values)
        if self.mode == "constant":
            return np.tile(self._constant_weights, (t.size, 1))
        m = self.midpoints
        # np.interp holds the end values outside the midpoints: constant extrapolation.
        return np.stack([np.interp(t, m, np.eye(n)[j]) for j in range(n)], axis=1)

    def at(self, t):
        """The factor at times ``t`` (s)."""
        return self.weights(t) @ self.values

    def sigma_parts(self, t):
        """(random, systematic) 1-sigma of the factor at times ``t``."""
        w = self.weights(t)
        random = np.sqrt((w**2) @ self.sigma_random**2)
        if self.mode == "constant":
            random = random * max(1.0, self.birge_ratio)
        systematic = np.sqrt(((w @ self.systematic_terms) ** 2).sum(axis=1))
        return random, systematic

    def sigma_at(self, t):
        """Total 1-sigma of the factor at times ``t``."""
        return np.hypot(*self.sigma_parts(t))

    @property
    def factor(self):
        """The constant factor (constant mode), else None."""
        return float(self.at([0.0])[0]) if self.mode == "constant" else None

    @property
    def factor_sigma(self):
        return float(self.sigma_at([0.0])[0]) if self.mode == "constant" else None

    def to_json(self):
        out = {"mode": self.mode, "source": self.source,
               "windows": [[float(a), float(b)] for a, b in self.windows],
               "stages": list(self.stages),
               "midpoints": self.midpoints.tolist(),
               "values": self.values.tolist(), "sigma": self.sigma.tolist(),
               "sigma_random": self.sigma_random.tolist(),
               "sigma_systematic": self.sigma_systematic.tolist(),
               "birge_ratio": self.birge_ratio}
        if self.mode == "constant":
            random, systematic = self.sigma_parts([0.0])
            out.update(factor=self.factor, factor_sigma=self.factor_sigma,
                       factor_sigma_random=float(random[0]), factor_sigma_systematic=float(systematic[0]))
        else:
            out.update(factor=None, factor_sigma=None,
                       note="piecewise linear through (midpoint, value), constant outside the midpoints")
        return out


# ---------------------------------------------------------------------------
# stages and windows


@dataclass(frozen=True)
class StageInterval:
    index: int
    label: str
    start: float   # earliest start of this stage among the parachutes
    end: float     # earliest start of the next stage, or the end of the data


def stage_intervals(test: FlightTest):
    """Intervals of the stages for totals: earliest start of stage k to earliest start of k+1."""
    t_end = float(test.time[-1])
    n_stages = max(len(p.stages) for p in test.parachutes)
    out = []
    for k in range(n_stages):
        having = [p for p in test.parachutes if len(p.stages) > k]
        start = min(p.stages[k].start for p in having)
        nxt = [p.stages[k + 1].start for p in test.parachutes if len(p.stages) > k + 1]
        out.append(StageInterval(k, having[0].stages[k].label, start, min(nxt) if nxt else t_end))
    return tuple(out)


def settling_time(time, values, start, end, smoothing=SETTLE_SMOOTHING):
    """Time after which ``values`` has settled within [start, end] (rule in the module docstring)."""
    m = (time >= start) & (time <= end)
    tt, yy = time[m], values[m]
    dt = float(np.median(np.diff(tt)))
    k = max(3, int(round(smoothing / dt)))
    smooth = running_mean(yy, k)
    level = float(np.median(yy[int(0.75 * yy.size):]))
    diffs = np.diff(yy)
    noise = 1.4826 * float(np.median(np.abs(diffs - np.median(diffs)))) / math.sqrt(2.0)
    tol = max(SETTLE_REL_TOL * abs(level), SETTLE_NOISE_TOL * noise / math.sqrt(k))
    half = start + 0.5 * (end - start)
    outside = np.flatnonzero((np.abs(smooth - level) > tol) & (tt <= half))
    settled = float(tt[outside[-1]]) + 0.5 * k * dt if outside.size else float(tt[0])
    return min(settled, half)


def automatic_windows(test: FlightTest, cells_cds):
    """Steady-state windows, one per usable stage: list of (t0, t1, stage label)."""
    time = test.time
    dt = float(np.median(np.diff(time)))
    windows = []
    n_stages = max(len(p.stages) for p in test.parachutes)
    for k in range(n_stages):
        having = [p for p in test.parachutes if len(p.stages) > k]
        # Begin once every canopy has surely started this stage (3 sigma of its stated start) ...
        a = max(p.stages[k].start + 3 * p.stages[k].start_sigma for p in having)
        nxt = [p.stages[k + 1] for p in test.parachutes if len(p.stages) > k + 1]
        # ... and end before any canopy can have started the next one.
        b = min((s.start - 3 * s.start_sigma for s in nxt), default=float(time[-1]))
        a, b = max(a, float(time[0])), min(b, float(time[-1]))
        if b - a < MIN_AUTO_SECONDS or (b - a) / dt < MIN_AUTO_SAMPLES:
            continue
        m = (time >= a) & (time <= b)
        if np.median(cells_cds[m]) <= 0:
            continue
        t0 = settling_time(time, cells_cds, a, b)
        windows.append((t0, b, having[0].stages[k].label))
    return windows


def _check_windows(test: FlightTest, windows):
    """Validate user windows; return them sorted as float pairs."""
    time = test.time
    t_lo, t_hi = float(time[0]), float(time[-1])
    checked = []
    for w in windows:
        try:
            t0, t1 = (float(x) for x in w)
        except (TypeError, ValueError):
            raise InputError(test.label, "option --window", f"a window must be two times, got {w!r}",
                             "write each window as T0:T1 in seconds, e.g. --window 3.0:9.0") from None
        text = f"{t0:g}:{t1:g}"
        if not (math.isfinite(t0) and math.isfinite(t1)) or t1 <= t0:
            raise InputError(test.label, f"option --window {text}", "the end is not after the start",
                             "write T0:T1 with T0 < T1, in seconds")
        if t0 < t_lo or t1 > t_hi:
            raise InputError(test.label, f"option --window {text}",
                             f"the window extends beyond the data ({t_lo:g} to {t_hi:g} s)",
                             f"choose T0 and T1 within {t_lo:g}:{t_hi:g}")
        n = int(((time >= t0) & (time <= t1)).sum())
        if n < MIN_WINDOW_SAMPLES:
            raise InputError(test.label, f"option --window {text}",
                             f"the window holds {n} sample{'s' if n != 1 else ''}; "
                             f"at least {MIN_WINDOW_SAMPLES} are needed for a ratio and its scatter",
                             "widen the window to span several samples of a steady stage")
        checked.append((t0, t1))
    checked.sort()
    for (a0, a1), (b0, b1) in zip(checked, checked[1:]):
        if b0 < a1:
            raise InputError(test.label, f"option --window {b0:g}:{b1:g}",
                             f"overlaps the window {a0:g}:{a1:g}", "give windows that do not overlap")
    return checked


def fit_scale_factor(test: FlightTest, mode, windows, accelerometer_cds, cells_cds,
                     source="user", stages=None):
    """Scale factor from windows [(t0, t1), ...] (validated), see the module docstring."""
    time = test.time
    data = test.data
    g_over_q = data["G"].to_numpy() / data["qbar"].to_numpy()
    names = ("vehicle.weight",) + tuple(f"{p.id}.weight" for p in test.parachutes) + ("vehicle.cds",)
    param_sigma = np.array([test.vehicle.weight_sigma] + [p.weight_sigma for p in test.parachutes]
                           + [test.vehicle.cds_sigma])
    values, sig_r, terms = [], [], []
    for t0, t1 in windows:
        m = (time >= t0) & (time <= t1)
        mean_L = float(cells_cds[m].mean())
        if mean_L <= 0:
            raise InputError(test.label, f"option --window {t0:g}:{t1:g}",
                             "the load cells carry no load there (mean load-cell drag area ≤ 0)",
                             "place windows where the canopies are inflated and steady")
        ratio, s_r = window_ratio(accelerometer_cds[m], cells_cds[m])
        gq = float(g_over_q[m].mean())
        grad = np.array([gq / mean_L] + [gq * (1.0 - ratio) / mean_L] * len(test.parachutes)
                        + [-1.0 / mean_L])
        values.append(ratio)
        sig_r.append(s_r)
        terms.append(grad * param_sigma)
    return ScaleFactor(mode=mode, windows=tuple((float(a), float(b)) for a, b in windows),
                       values=np.array(values), sigma_random=np.array(sig_r),
                       systematic_terms=np.array(terms), systematic_names=names, source=source,
                       stages=tuple(stages) if stages else tuple("" for _ in windows))


# ---------------------------------------------------------------------------
# peaks and load share


@dataclass(frozen=True)
class Peak:
    """A peak load (N) with its 1-sigma at time ``time`` (s)."""

    load: float
    sigma: float
    time: float

    def to_json(self, units):
        return {"load": units.from_si(self.load, "force"), "sigma": units.from_si(self.sigma, "force"),
                "time": self.time}


@dataclass(frozen=True)
class StagePeaks:
    stage: StageInterval
    accelerometer: Peak
    load_cells: Peak | None
    parachutes: dict

    @property
    def agreement(self):
        """(accelerometer − load-cell sum)/combined sigma, or None without load cells."""
        combined = math.hypot(self.accelerometer.sigma, self.load_cells.sigma) if self.load_cells else 0.0
        if combined == 0.0:
            return None
        return (self.accelerometer.load - self.load_cells.load) / combined

    def to_json(self, units):
        return {"stage": self.stage.label, "interval": [self.stage.start, self.stage.end],
                "accelerometer": self.accelerometer.to_json(units),
                "load_cells": self.load_cells.to_json(units) if self.load_cells else None,
                "difference_in_sigma": self.agreement,
                "parachutes": {pid: pk.to_json(units) for pid, pk in self.parachutes.items()}}


@dataclass(frozen=True)
class LoadShare:
    """Fractions of the summed load-cell load per parachute in one stage, four ways."""

    stage: StageInterval
    at_global_peak: dict
    at_parachute_peak: dict      # id of the parachute whose peak -> {id: fraction}
    time_independent: dict
    mean: dict

    def to_json(self):
        return {"stage": self.stage.label, "interval": [self.stage.start, self.stage.end],
                "at_global_peak": self.at_global_peak, "at_parachute_peak": self.at_parachute_peak,
                "time_independent": self.time_independent, "mean": self.mean}


def peak_filter_width(width_s, sample_rate):
    """Odd number of samples (≥ 3) spanning about ``width_s`` seconds; 1 (no filter) for width 0."""
    if width_s <= 0:
        return 1
    return max(3, 2 * int(round(0.5 * width_s * sample_rate)) + 1)


def peak_filter(values, sigma_random, width):
    """Savitzky–Golay (quadratic) smoothing for peak finding, and the random sigma after it.

    A quadratic filter keeps the height of a sharp peak far better than a
    running mean of the same width while cutting the noise by √Σc².
    """
    values = np.asarray(values, float)
    sigma_random = np.asarray(sigma_random, float)
    if width <= 1 or values.size < width:
        return values.copy(), sigma_random.copy()
    coeffs = savgol_coeffs(width, 2)
    smooth = savgol_filter(values, width, 2, mode="interp")
    # Independent samples: var = Σ c_j²·σ²(t − j); the same weights are used at the ends.
    var = np.convolve(sigma_random**2, coeffs[::-1] ** 2, mode="same")
    return smooth, np.sqrt(var)


def _interval_mask(time, t0, t1):
    """Samples in [t0, t1); an interval reaching the end of the data keeps its last sample."""
    return (time >= t0) & ((time < t1) | (t1 >= time[-1]))


def _peak(time, smooth, random, systematic, t0, t1):
    """Largest filtered value in [t0, t1) with its 1-sigma; (None, None) if no sample."""
    m = np.flatnonzero(_interval_mask(time, t0, t1))
    if m.size == 0:
        return None, None
    i = int(m[np.argmax(smooth[m])])
    return Peak(float(smooth[i]), float(math.hypot(random[i], systematic[i])), float(time[i])), i


def _shares(loads, index):
    total = sum(v[index] for v in loads.values())
    return {pid: float(v[index] / total) for pid, v in loads.items()}


# ---------------------------------------------------------------------------
# the reduction


@dataclass(frozen=True)
class Reduction:
    """Result of :func:`reduce_test`; ``frame`` is SI with the columns of the module docstring."""

    test: FlightTest = field(repr=False)
    frame: pd.DataFrame = field(repr=False)
    scale: ScaleFactor | None
    peaks: tuple
    load_share: tuple
    peak_smoothing: float = DEFAULT_PEAK_SMOOTHING

    @property
    def csv_columns(self):
        """The columns of ``reduced.csv``, in order."""
        cols = ["time", "load_total", "load_total_sigma", "cds_total", "cds_total_sigma"]
        for p in self.test.parachutes:
            if p.load_column:
                cols += [f"load_{p.id}", f"load_{p.id}_sigma", f"cds_{p.id}_raw", f"cds_{p.id}",
                         f"cds_{p.id}_sigma"]
        return cols

    def to_bundle_units(self, columns=None):
        """The frame (or ``columns`` of it) in the bundle's units."""
        u = self.test.units
        out = self.frame[list(columns) if columns is not None else list(self.frame.columns)].copy()
        for col in out.columns:
            if col.startswith("load_"):
                out[col] = u.from_si(out[col].to_numpy(), "force")
            elif col.startswith("cds_"):
                out[col] = u.from_si(out[col].to_numpy(), "area")
            elif col == "time":
                out[col] = u.from_si(out[col].to_numpy(), "time")
        return out

    def to_json(self):
        u = self.test.units
        return {"test": self.test.name, "bundle": str(self.test.source) if self.test.source else None,
                "units": {"force": u.label("force"), "area": u.label("area"), "time": u.label("time"),
                          "angle": "deg"},
                "scale_factor": self.scale.to_json() if self.scale else None,
                "peak_smoothing_s": self.peak_smoothing,
                "peaks": [p.to_json(u) for p in self.peaks],
                "load_share": [s.to_json() for s in self.load_share]}


def _check_mode(test, scale):
    if scale not in SCALE_MODES:
        raise InputError(test.label, "option --scale", f"unknown scale-factor mode {scale!r}",
                         "use --scale constant (one factor) or --scale linear (trend through the windows)")
    return scale


def reduce_test(test: FlightTest, scale="constant", windows=None,
                peak_smoothing=DEFAULT_PEAK_SMOOTHING) -> Reduction:
    """Reduce a flight test: loads, drag areas, friction scale factor, peaks and load share.

    ``scale`` is ``"constant"`` or ``"linear"``; ``windows`` a list of
    (t0, t1) in seconds replacing the automatic steady-state windows;
    ``peak_smoothing`` the peak filter's width (s), 0 for raw maxima.
    """
    mode = _check_mode(test, scale)
    d = test.data
    time = d["time"].to_numpy()
    G, dG = d["G"].to_numpy(), d["G_sigma"].to_numpy()
    q, dq = d["qbar"].to_numpy(), d["qbar_sigma"].to_numpy()
    veh = test.vehicle
    W_T = test.total_weight
    dW_T = math.sqrt(veh.weight_sigma**2 + sum(p.weight_sigma**2 for p in test.parachutes))

    cols = {"time": time}
    load_total = accelerometer_load(G, q, veh.weight, veh.cds)
    load_total_s = accelerometer_load_sigma(G, q, veh.weight, veh.cds, dG, dq, veh.weight_sigma, veh.cds_sigma)
    cds_total = accelerometer_drag_area(G, q, W_T, veh.cds)
    cds_total_s = accelerometer_drag_area_sigma(G, q, W_T, dG, dq, dW_T, veh.cds_sigma)
    for name, value, s in (("load_total", load_total, load_total_s), ("cds_total", cds_total, cds_total_s)):
        cols[name], cols[f"{name}_sigma"] = value, s.total
        cols[f"{name}_sigma_random"], cols[f"{name}_sigma_systematic"] = s.random, s.systematic

    with_cells = [p for p in test.parachutes if p.load_column]
    if with_cells and len(with_cells) != len(test.parachutes):
        missing = ", ".join(p.id for p in test.parachutes if not p.load_column)
        raise InputError(test.label, "test.toml, load_cell",
                         f"parachute(s) {missing} have no load cell, so the load cells cannot be calibrated "
                         "against the accelerometer total",
                         "give every parachute a load_cell column, or none to reduce the accelerometer alone")
    intervals = stage_intervals(test)
    width = peak_filter_width(peak_smoothing, test.sample_rate)

    if not with_cells:
        if windows:
            raise InputError(test.label, "option --window", "the test has no load cells to calibrate",
                             "drop --window, or add load_cell columns to the bundle")
        frame = pd.DataFrame(cols)
        acc_f, acc_r = peak_filter(load_total, load_total_s.random, width)
        peaks = tuple(StagePeaks(st, _peak(time, acc_f, acc_r, load_total_s.systematic, st.start, st.end)[0],
                                 None, {}) for st in intervals)
        return Reduction(test, frame, None, peaks, (), peak_smoothing)

    # Fly-out-corrected (Eq. 13) but unscaled loads and drag areas (Eq. 11, 12).
    axial, axial_s = {}, {}
    cells_raw = np.zeros_like(time)
    for p in with_cells:
        F, dF = d[p.load_column].to_numpy(), d[f"{p.load_column}_sigma"].to_numpy()
        if p.angle_column:
            theta, dtheta = d[p.angle_column].to_numpy(), d[f"{p.angle_column}_sigma"].to_numpy()
        else:
            theta, dtheta = np.zeros_like(F), np.zeros_like(F)
        axial[p.id] = axial_load(F, theta)
        axial_s[p.id] = axial_load_sigma(F, theta, dF, dtheta)
        raw = load_cell_drag_area(axial[p.id], G, q, p.weight)
        raw_s = load_cell_drag_area_sigma(axial[p.id], G, q, p.weight, axial_s[p.id], dG, dq, p.weight_sigma)
        cols[f"load_{p.id}_raw"], cols[f"load_{p.id}_raw_sigma_random"] = axial[p.id], axial_s[p.id]
        cols[f"cds_{p.id}_raw"], cols[f"cds_{p.id}_raw_sigma"] = raw, raw_s.total
        cols[f"cds_{p.id}_raw_sigma_random"] = raw_s.random
        cols[f"cds_{p.id}_raw_sigma_systematic"] = raw_s.systematic
        cells_raw = cells_raw + raw

    # Friction-loss scale factor from the steady windows.
    if windows:
        chosen = _check_windows(test, windows)
        scale_factor = fit_scale_factor(test, mode, chosen, cds_total, cells_raw, source="user")
    else:
        auto = automatic_windows(test, cells_raw)
        if not auto:
            raise InputError(test.label, "stages",
                             f"no stage has a steady interval of at least {MIN_AUTO_SECONDS} s between stage "
                             "starts for the friction calibration",
                             "give steady-state windows explicitly with --window T0:T1")
        scale_factor = fit_scale_factor(test, mode, [(a, b) for a, b, _ in auto], cds_total, cells_raw,
                                        source="automatic", stages=[lab for _, _, lab in auto])
    s = scale_factor.at(time)
    s_random, s_systematic = scale_factor.sigma_parts(time)
    s_sigma = np.hypot(s_random, s_systematic)
    cols["scale"], cols["scale_sigma"] = s, s_sigma

    # Scaled loads and drag areas; the factor's sigma is common to all samples: systematic.
    W_p = sum(p.weight for p in with_cells)
    dW_p = math.sqrt(sum(p.weight_sigma**2 for p in with_cells))
    sum_axial = sum(axial.values())
    loads = {}
    sum_rand2 = np.zeros_like(time)
    for p in with_cells:
        load = s * axial[p.id]
        rand = s * axial_s[p.id]
        syst = np.abs(axial[p.id]) * s_sigma
        cds_s = load_cell_drag_area_sigma(load, G, q, p.weight, rand, dG, dq, p.weight_sigma, syst)
        loads[p.id] = load
        sum_rand2 = sum_rand2 + rand**2
        cols[f"load_{p.id}"], cols[f"load_{p.id}_sigma"] = load, np.hypot(rand, syst)
        cols[f"load_{p.id}_sigma_random"], cols[f"load_{p.id}_sigma_systematic"] = rand, syst
        cols[f"cds_{p.id}"] = load_cell_drag_area(load, G, q, p.weight)
        cols[f"cds_{p.id}_sigma"] = cds_s.total
        cols[f"cds_{p.id}_sigma_random"], cols[f"cds_{p.id}_sigma_systematic"] = cds_s.random, cds_s.systematic

    # Sums over the parachutes: F noise independent between cells, the scale factor common.
    load_cells = s * sum_axial
    lc_rand, lc_syst = np.sqrt(sum_rand2), np.abs(sum_axial) * s_sigma
    cols["load_cells"], cols["load_cells_sigma"] = load_cells, np.hypot(lc_rand, lc_syst)
    cols["load_cells_sigma_random"], cols["load_cells_sigma_systematic"] = lc_rand, lc_syst
    cols["load_cells_raw"] = sum_axial
    cc = load_cell_drag_area_sigma(load_cells, G, q, W_p, lc_rand, dG, dq, dW_p, lc_syst)
    cols["cds_cells"], cols["cds_cells_sigma"] = load_cell_drag_area(load_cells, G, q, W_p), cc.total
    cols["cds_cells_sigma_random"], cols["cds_cells_sigma_systematic"] = cc.random, cc.systematic
    cols["cds_cells_raw"] = cells_raw
    raw_sum_s = load_cell_drag_area_sigma(sum_axial, G, q, W_p,
                                          np.sqrt(sum(v**2 for v in axial_s.values())), dG, dq, dW_p)
    cols["cds_cells_raw_sigma_random"] = raw_sum_s.random
    frame = pd.DataFrame(cols)

    # Peaks and load share per stage.
    peaks, shares = [], []
    acc_f, acc_r = peak_filter(load_total, load_total_s.random, width)
    cells_f, cells_r = peak_filter(load_cells, lc_rand, width)
    filtered = {pid: peak_filter(v, cols[f"load_{pid}_sigma_random"], width) for pid, v in loads.items()}
    smooth_loads = {pid: v[0] for pid, v in filtered.items()}
    for st in intervals:
        acc, _ = _peak(time, acc_f, acc_r, load_total_s.systematic, st.start, st.end)
        cells, i_glob = _peak(time, cells_f, cells_r, lc_syst, st.start, st.end)
        own, own_index = {}, {}
        for p in with_cells:
            if len(p.stages) <= st.index:
                continue
            # A parachute's own peak is looked for in its own stage interval.
            t0 = p.stages[st.index].start
            t1 = p.stages[st.index + 1].start if len(p.stages) > st.index + 1 else math.inf
            pk, idx = _peak(time, *filtered[p.id], cols[f"load_{p.id}_sigma_systematic"], t0, t1)
            if pk is not None:
                own[p.id], own_index[p.id] = pk, idx
        peaks.append(StagePeaks(st, acc, cells, own))

        m = _interval_mask(time, st.start, st.end)
        if i_glob is None or m.sum() < 2:
            continue
        integrals = {pid: float(np.trapezoid(v[m], time[m])) for pid, v in loads.items()}
        total_int = sum(integrals.values())
        indices = [i_glob, *own_index.values()]
        if total_int <= 0 or min(sum(v[i] for v in smooth_loads.values()) for i in indices) <= 0:
            continue   # no load in this stage: a share is undefined
        at_global = _shares(smooth_loads, i_glob)
        at_own = {pid: _shares(smooth_loads, idx) for pid, idx in own_index.items()}
        independent = {pid: v / total_int for pid, v in integrals.items()}
        methods = [at_global, *at_own.values(), independent]
        mean = {pid: float(np.mean([mth[pid] for mth in methods])) for pid in loads}
        shares.append(LoadShare(st, at_global, at_own, independent, mean))

    return Reduction(test, frame, scale_factor, tuple(peaks), tuple(shares), peak_smoothing)


# ---------------------------------------------------------------------------
# command-line helpers and output


def parse_window(text, source=""):
    """Parse ``"T0:T1"`` (seconds) into a pair; InputError naming --window otherwise."""
    parts = str(text).split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise InputError(source or "command line", f"option --window {text}",
                         "not a window of the form T0:T1", "write --window 3.0:9.0 (seconds)") from None


def write_reduction(reduction: Reduction, out):
    """Write reduced.csv, reduction.json and reduction.png into folder ``out``; return their paths."""
    from cpas_bayes.outputs.plots.reduction import plot_reduction

    out = Path(out)
    # Build everything before writing anything, so a failure leaves no partial output.
    table = reduction.to_bundle_units(reduction.csv_columns)
    summary = reduction.to_json()
    fig = plot_reduction(reduction)
    paths = {"csv": out / "reduced.csv", "json": out / "reduction.json", "png": out / "reduction.png"}
    try:
        write_csv(paths["csv"], table, float_format="%.9g")
        write_json(paths["json"], summary)
        save_figure(fig, paths["png"], dpi=110)
    finally:
        import matplotlib.pyplot as plt
        plt.close(fig)
    return paths

"""Load-cell friction calibration: the friction-loss scale factor s(t) and its 1-sigma.

:func:`calibrate_scale_factor` compares the accelerometer drag area (Eq. 8)
with the load cells' (Eq. 11) in steady-state windows and returns a
:class:`ScaleFactor`; :func:`cpas_bayes.data.reduction.reduce_test` applies
it to the load cells. The equations are those of
:mod:`cpas_bayes.data.reduction`. Everything inside is SI.

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cpas_bayes.core.errors import InputError
from cpas_bayes.data.bundle import FlightTest

SCALE_MODES = ("constant", "linear")
SETTLE_SMOOTHING = 0.25        # s, running mean used to detect the end of a transient
SETTLE_REL_TOL = 0.01          # band around the steady level, fraction of the level
SETTLE_NOISE_TOL = 4.0         # band in smoothed-noise sd, whichever is wider
MIN_AUTO_SECONDS = 0.5         # shortest stage interval used for calibration
MIN_AUTO_SAMPLES = 20
MIN_WINDOW_SAMPLES = 3         # a user window needs scatter to give an uncertainty
MAX_SCALE_FACTOR = 3.0         # friction factors outside [1/3, 3] are errors of units or channels


# ---------------------------------------------------------------------------
# the ratio of one window


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
# steady-state windows


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


def _check_ratio(test, ratio, window, source):
    """Refuse a window's accelerometer/load-cell ratio that friction cannot explain: riser friction costs
    the load cells some per cent of the load, so a ratio outside [1/MAX_SCALE_FACTOR, MAX_SCALE_FACTOR]
    (or not positive) is a units, channel or data error, and scaling the cells by it would hide it."""
    where = f"option --window {window}" if source == "user" else f"steady window {window} s (automatic)"
    if not np.isfinite(ratio) or ratio <= 0:
        raise InputError(test.label, where, f"the accelerometer's drag area (W_T·G/q̄ − CDS_V) there is "
                         f"not positive (load-cell friction factor {ratio:.3g})",
                         "check data.csv's G and qbar columns in that stretch, and the vehicle's weight and cds")
    if not 1.0 / MAX_SCALE_FACTOR <= ratio <= MAX_SCALE_FACTOR:
        raise InputError(test.label, where, f"the load cells read {1.0 / ratio:.3g}× the load the accelerometer "
                         f"gives (friction factor {ratio:.3g}): too far from 1 to be riser friction",
                         "check the load-cell columns' units (test.toml [units]; lbf read as N is a factor of "
                         "4.45), which column each parachute's load_cell names, and the weights")


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
        _check_ratio(test, ratio, f"{t0:g}:{t1:g}", source)
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


def calibrate_scale_factor(test: FlightTest, mode, accelerometer_cds, cells_cds, windows=None):
    """The scale factor from the user's ``windows`` [(t0, t1), ...] (validated here) or, without
    them, from the automatic steady-state windows (rules in the module docstring)."""
    if windows:
        chosen = _check_windows(test, windows)
        return fit_scale_factor(test, mode, chosen, accelerometer_cds, cells_cds, source="user")
    auto = automatic_windows(test, cells_cds)
    if not auto:
        raise InputError(test.label, "stages",
                         f"no stage has a steady interval of at least {MIN_AUTO_SECONDS} s between stage "
                         "starts for the friction calibration",
                         "give steady-state windows explicitly with --window T0:T1")
    return fit_scale_factor(test, mode, [(a, b) for a, b, _ in auto], accelerometer_cds, cells_cds,
                            source="automatic", stages=[lab for _, _, lab in auto])

"""Events and clocks in raw drop-test logger records: release, line stretch, and clock offsets.

Pure functions of sampled series (time in seconds, increasing); no files.
:mod:`cpas_bayes.data.importer` uses them to turn logger CSV files into a
bundle (docs/import.md).

Sensed acceleration
-------------------
``g`` below is the sensed load factor in g: the accelerometer's specific
force f = a − g⃗ divided by g0 = 9.80665 m/s² (its magnitude, or one axis with
its sign). Hanging from a carrier (or carried in level flight) it reads ~1;
in free fall it reads the drag deceleration only (~0 at release); a parachute
pulling makes it rise sharply.

Events
------
An event is a change from level A to level B. Its time is the **half-level
crossing** t50: the instant the signal crosses (A + B)/2, linearly
interpolated between the two samples that bracket the crossing (for a ramp,
its midpoint). Its 1-sigma combines three terms in quadrature:

* sampling, Δt/√12: a transition faster than a sample lies anywhere between
  the two samples that bracket it (uniform over one interval Δt);
* noise, σ_n/|slope|: the noise of the samples (σ_n, from the median absolute
  first difference, /√2) moves the crossing by σ_n over the local slope;
* threshold ambiguity, (t75 − t25)/2: how much the time depends on which
  level one calls "the event", from the crossings at 25 % and 75 % of the way
  from A to B (zero for a step, half the rise for a slow one).

**Release** (onset of free fall): A = the hanging level (median of the second
before), B = the free-fall level (median of the 0.05–0.3 s after). Found as the
first time the median-filtered signal stays below 0.5 g for 0.2 s after having
been above 0.75 g for 0.5 s.

**Line stretch / first load**: A = the free-fall level (median of the 0.5 s
before, after release), B = the first peak (largest 3-sample mean in the
0.25 s after the rise is seen). Found as the first time, 0.1 s to 600 s after
release, that the median-filtered signal exceeds the median of its previous
0.5 s by ``threshold`` (default 0.5 g). Its t50 is half-way up the first rise,
a few hundredths of a second after the first pull for a typical snatch.

Clock offsets
-------------
Two loggers with their own clocks see the same motion. With t_ref = t_other
+ τ, :func:`align_clocks` finds τ from a shared signal (sensed acceleration,
or the specific force derived from GNSS velocity or vertical speed):

1. coarse: both signals are block-averaged onto grids of one step h (the
   coarser sample interval, ≥ 0.02 s) and the Pearson correlation r(τ) is
   computed at every grid lag (FFT) within the search range, with at least
   ``min_overlap`` seconds in common; the best lag is kept;
2. fine: around it, τ minimises the residual sum of squares of
   y_j = a·x̃(t_j ± τ) + b, where y are the samples of the signal with the wider
   smoothing and x̃ the other signal box-car smoothed to the same width
   (a, b by linear least squares at each τ; bounded Brent search);
3. sigma: the Gauss–Newton variance κ·s² / Σ J_j², with s² the residual
   variance, J_j = a·dx̃/dt at each sample (a difference over the data's sample
   interval, its noise share subtracted) and κ = (1 + ρ1)/(1 − ρ1) ≥ 1 for the
   lag-one autocorrelation ρ1 of the residuals (correlated residuals carry
   fewer independent samples); plus, in quadrature, the sampling of the
   smoothed signal, (Δt_m/√12)·min(1, Δt_m/w): each of its sharp features lies
   anywhere within one of its sample intervals Δt_m, an error the box-car of
   width w dilutes by Δt_m/w (measured on simulated drops: z-scores of the
   offset with a standard deviation of 0.8–0.95 for 20–200 Hz accelerometers
   against 10 Hz GNSS velocity).

σ_τ is statistical: a systematic lag between the two signals (a GNSS receiver's
velocity filter, a logger that stamps samples late) is not in it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import median_filter
from scipy.optimize import minimize_scalar
from scipy.signal import correlate, correlation_lags

from cpas_bayes.core.units import STANDARD_GRAVITY

RELEASE_LEVEL = 0.5       # g: half-way between hanging (1 g) and free fall (~0 g)
HANG_LEVEL = 0.75         # g: "still hanging" before a release
HANG_TIME = 0.5           # s above HANG_LEVEL before a release (the vehicle hung or was carried)
FREE_FALL_HOLD = 0.2      # s below RELEASE_LEVEL: free fall, not a dip of vibration
LINE_STRETCH_THRESHOLD = 0.5  # g above the free-fall level that marks the first load
LINE_STRETCH_DELAY = 0.1  # s after release before a first load is looked for (the release transition)
LINE_STRETCH_SEARCH = 600.0  # s after release within which the first load is looked for
BASELINE_TIME = 0.5       # s of free fall whose median is the level before the first load
PEAK_WINDOW = 0.25        # s after the rise is seen in which its first peak is taken
MEDIAN_TIME = 0.03        # s: width of the median filter that rejects single-sample spikes
MIN_CORRELATION = 0.5     # below: the two loggers' signals do not match at any lag
MIN_GRID_STEP = 0.02      # s: finest coarse-correlation grid
MAX_GRID_POINTS = 1_000_000   # coarse grid: beyond, the step grows (memory of the FFTs)


class EventNotFound(ValueError):
    """The record does not show the event (the message says what was looked for)."""


@dataclass(frozen=True)
class Event:
    """One detected event: half-level crossing time and its 1-sigma (module notes)."""

    name: str
    time: float            # s, on the clock of the series it was found in
    sigma: float           # 1-sigma, s
    level_before: float    # g
    level_after: float     # g
    rise: float            # t75 − t25, s
    terms: dict = field(default_factory=dict)  # the sigma's terms: sampling, noise, ambiguity (s)


@dataclass(frozen=True)
class SharedSignal:
    """A signal two loggers can both show, in g, with the width (s) of the box-car smoothing it already has."""

    time: np.ndarray
    value: np.ndarray
    width: float
    source: str            # what it was derived from, for messages


@dataclass(frozen=True)
class Alignment:
    """t_ref = t_other + offset, with its 1-sigma and how well the signals matched."""

    offset: float          # s
    sigma: float           # s
    correlation: float     # Pearson r at the best coarse lag
    runner_up: float       # best r more than 2 s of lag away from it (how distinct the match is)
    search: tuple          # (lowest, highest) offset searched, s
    samples: int           # samples in the fine fit


def sample_interval(t):
    """Median sample interval, s."""
    return float(np.median(np.diff(t)))


def noise_sigma(x):
    """Robust 1-sigma of white noise on ``x``: 1.4826·MAD of the first differences, /√2."""
    d = np.diff(np.asarray(x, float))
    if d.size < 2:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def _median_smooth(x, dt):
    width = max(3, int(round(MEDIAN_TIME / dt)) | 1)
    return median_filter(np.asarray(x, float), size=width, mode="nearest")


def _samples(seconds, dt):
    return max(1, int(round(seconds / dt)))


def _window(t, x, t0, t1):
    inside = (t >= t0) & (t <= t1)
    return x[inside]


def _last_crossing(t, x, level, stop, rising):
    """(time, k) of the last crossing of ``level`` before index ``stop``: x[k-1] before it, x[k..stop] past it."""
    before = x <= level if rising else x >= level
    idx = np.flatnonzero(before[:stop + 1])
    if not idx.size or idx[-1] == stop:
        return None, None
    k = int(idx[-1]) + 1
    frac = (x[k - 1] - level) / (x[k - 1] - x[k])
    return float(t[k - 1] + frac * (t[k] - t[k - 1])), k


def _event(name, t, x, a, b, stop, noise):
    """The half-level crossing of a change from ``a`` to ``b`` seen before index ``stop``, with its sigma."""
    rising = b > a
    crossings = {}
    for fraction in (0.25, 0.5, 0.75):
        crossings[fraction] = _last_crossing(t, x, a + fraction * (b - a), stop, rising)
    t50, k = crossings[0.5]
    if t50 is None or crossings[0.25][0] is None or crossings[0.75][0] is None:
        raise EventNotFound(f"{name}: the signal does not cross from {a:.2f} g to {b:.2f} g")
    dt = float(t[k] - t[k - 1])
    slope = abs(x[k] - x[k - 1]) / dt
    rise = abs(crossings[0.75][0] - crossings[0.25][0])
    terms = {"sampling": dt / math.sqrt(12.0), "noise": float(noise / slope) if slope > 0 else dt,
             "ambiguity": float(rise / 2)}
    sigma = math.sqrt(sum(v * v for v in terms.values()))
    return Event(name, t50, sigma, float(a), float(b), rise, terms)


def detect_release(t, g):
    """The release: onset of free fall, where the sensed load factor ``g`` falls from ~1 g to ~0 g."""
    t, g = np.asarray(t, float), np.asarray(g, float)
    dt = sample_interval(t)
    smooth = _median_smooth(g, dt)
    below = smooth < RELEASE_LEVEL
    hold, hang = _samples(FREE_FALL_HOLD, dt), _samples(HANG_TIME, dt)
    starts = np.flatnonzero(below & ~np.concatenate([[True], below[:-1]]))
    for s in starts:
        run = below[s:s + hold]
        if s < hang or run.size < hold or not run.all():
            continue
        if np.mean(smooth[s - hang:s] > HANG_LEVEL) < 0.9:
            continue
        t_s = t[s]
        a = float(np.median(_window(t, g, t_s - 1.0, t_s - 0.1)))
        b = float(np.median(_window(t, g, t_s + 0.05, t_s + 0.3)))
        noise = noise_sigma(_window(t, g, t_s - 1.0, t_s - 0.1))
        return _event("release", t, g, a, b, s + hold // 2, noise)
    raise EventNotFound(f"no release: the sensed acceleration never falls below {RELEASE_LEVEL} g for "
                        f"{FREE_FALL_HOLD} s after {HANG_TIME} s above {HANG_LEVEL} g (hanging or carried)")


def detect_line_stretch(t, g, release, threshold=LINE_STRETCH_THRESHOLD):
    """Line stretch / first load: the first sharp rise of ``g`` by more than ``threshold`` g after ``release`` (s).

    Looked for from ``LINE_STRETCH_DELAY`` to ``LINE_STRETCH_SEARCH`` seconds
    after release; the hanging level before the release does not enter the
    free-fall baseline (it is replaced by the level just after release).
    """
    t, g = np.asarray(t, float), np.asarray(g, float)
    dt = sample_interval(t)
    lo = int(np.searchsorted(t, release - BASELINE_TIME - 0.1))
    hi = int(np.searchsorted(t, release + LINE_STRETCH_SEARCH, side="right"))
    t, g = t[lo:hi], g[lo:hi]
    fell = t >= release + 0.05
    early = fell & (t <= release + LINE_STRETCH_DELAY)
    if not fell.any():
        raise EventNotFound(f"no line stretch: the record ends at the release ({release:.3f} s)")
    free_fall = float(np.median(g[early])) if early.any() else float(g[fell][0])
    smooth = _median_smooth(g, dt)
    smooth[~fell] = free_fall  # the hanging level is not a baseline for the first load
    n_base, gap = _samples(BASELINE_TIME, dt), _samples(0.05, dt)
    # the median of the previous BASELINE_TIME seconds (up to `gap` before), at every sample
    centred = median_filter(smooth, size=n_base | 1, mode="nearest")
    shift = gap + n_base // 2
    baseline = np.full_like(smooth, np.inf)
    baseline[shift:] = centred[:-shift]
    first = max(int(np.searchsorted(t, release + LINE_STRETCH_DELAY)), shift + 1)
    rising = np.flatnonzero(smooth[first:] - baseline[first:] > threshold)
    if not rising.size or first + int(rising[0]) >= len(g) - 2:
        raise EventNotFound(f"no line stretch: the sensed acceleration never rises more than {threshold:g} g above "
                            f"its free-fall level in the {LINE_STRETCH_SEARCH:g} s after the release at "
                            f"{release:.3f} s")
    d = first + int(rising[0])
    before = _window(t, g, max(t[d] - BASELINE_TIME, release + 0.05), t[d] - 2 * dt)
    if before.size < 2:
        before = g[fell][:max(2, d - int(np.argmax(fell)))]
    a = float(np.median(before))
    noise = noise_sigma(before)
    mean3 = np.convolve(g, np.ones(3) / 3, mode="same")
    end = min(len(g) - 2, d + _samples(PEAK_WINDOW, dt))
    peak = d + int(np.argmax(mean3[d:end + 1]))
    return _event("line stretch", t, g, a, float(mean3[peak]), peak, noise)


# ---------------------------------------------------------------------------
# shared signals for clock alignment (all in g)


def from_acceleration(t, g):
    """The sensed load factor itself (magnitude or signed axis, g); smoothed over one sample."""
    t = np.asarray(t, float)
    return SharedSignal(t, np.asarray(g, float), sample_interval(t), "sensed acceleration")


def from_velocity(t, north, east, down):
    """|dv/dt − g⃗|/g0 from north-east-down velocity (m/s): what an accelerometer would sense.

    Central differences average the acceleration over two sample intervals (the width).
    """
    t = np.asarray(t, float)
    a = np.stack([np.gradient(np.asarray(c, float), t) for c in (north, east, down)])
    a[2] -= STANDARD_GRAVITY  # gravity is +g0 along "down": f = a − g⃗
    return SharedSignal(t, np.sqrt((a ** 2).sum(axis=0)) / STANDARD_GRAVITY, 2 * sample_interval(t),
                        "GNSS velocity")


def from_vertical_speed(t, up):
    """|dv_up/dt + g0|/g0 from vertical speed (m/s, positive up); horizontal acceleration neglected."""
    t = np.asarray(t, float)
    return SharedSignal(t, np.abs(np.gradient(np.asarray(up, float), t) + STANDARD_GRAVITY) / STANDARD_GRAVITY,
                        2 * sample_interval(t), "vertical speed")


# ---------------------------------------------------------------------------
# alignment


def _cumulative(t, x):
    """Running integral of x over t (trapezoids), for box-car averages."""
    return np.concatenate([[0.0], np.cumsum(0.5 * (x[1:] + x[:-1]) * np.diff(t))])


def _boxcar(t, x, at, width):
    """Mean of x over [at − width/2, at + width/2] (linear between samples, clipped to the record)."""
    if width <= 0:
        return np.interp(at, t, x)
    c = _cumulative(t, x)
    lo = np.clip(at - width / 2, t[0], t[-1])
    hi = np.clip(at + width / 2, t[0], t[-1])
    span = hi - lo
    mean = np.interp(hi, t, c) - np.interp(lo, t, c)
    return np.where(span > 0, mean / np.where(span > 0, span, 1.0), np.interp(at, t, x))


def _grid(signal, h):
    n = int((signal.time[-1] - signal.time[0]) / h) + 1
    at = signal.time[0] + h * np.arange(n)
    return at, _boxcar(signal.time, signal.value, at, h)


def _pearson_by_lag(a, b):
    """Pearson r of a[j + k] with b[j] over their overlap, for every lag k; and the overlap counts."""
    a, b = a - a.mean(), b - b.mean()
    ones_a, ones_b = np.ones_like(a), np.ones_like(b)
    n = np.rint(correlate(ones_a, ones_b, method="fft"))
    sa, sb = correlate(a, ones_b, method="fft"), correlate(ones_a, b, method="fft")
    saa, sbb = correlate(a * a, ones_b, method="fft"), correlate(ones_a, b * b, method="fft")
    sab = correlate(a, b, method="fft")
    with np.errstate(invalid="ignore", divide="ignore"):
        m = np.maximum(n, 1)
        cov = sab - sa * sb / m
        var = (saa - sa * sa / m) * (sbb - sb * sb / m)
        r = np.where(var > 1e-12 * m * m, cov / np.sqrt(np.abs(var)), 0.0)
    return correlation_lags(len(a), len(b)), r, n


def _coarse(ref, other, lo, hi, min_overlap):
    span = max(ref.time[-1] - ref.time[0], other.time[-1] - other.time[0])
    h = max(sample_interval(ref.time), sample_interval(other.time), MIN_GRID_STEP, span / MAX_GRID_POINTS)
    ta, a = _grid(ref, h)
    tb, b = _grid(other, h)
    lags, r, n = _pearson_by_lag(a, b)
    offsets = ta[0] - tb[0] + lags * h
    usable = (n * h >= min_overlap) & (offsets >= lo - h) & (offsets <= hi + h)
    if not usable.any():
        raise EventNotFound(f"no offset in {lo:g} … {hi:g} s gives the two records {min_overlap:.1f} s in common")
    r = np.where(usable, r, -np.inf)
    best = int(np.argmax(r))
    far = usable & (np.abs(offsets - offsets[best]) > 2.0)
    runner_up = float(r[far].max()) if far.any() else float("nan")
    return float(offsets[best]), float(r[best]), runner_up, h


def _fit_at(offset, data, model, sign, width, idx):
    """Residuals and slope of data ≈ p·model(t ∓ offset) + q at ``offset``; (rss, p, q, x, residuals)."""
    at = data.time[idx] + sign * offset
    x = _boxcar(model.time, model.value, at, width)
    y = data.value[idx]
    design = np.stack([x, np.ones_like(x)], axis=1)
    (p, q), *_ = np.linalg.lstsq(design, y, rcond=None)
    res = y - p * x - q
    return float(res @ res), float(p), float(q), at, res


def align_clocks(ref, other, hint=None, search=None, min_overlap=None):
    """The offset τ with t_ref = t_other + τ between two :class:`SharedSignal` records (module notes).

    ``hint`` centres the search (default: none, every lag with enough overlap),
    ``search`` is its half-width, s (default 60 s with a hint, else unbounded);
    ``min_overlap`` the seconds the records must share (default a quarter of
    the shorter record, at least 5 s). Raises :class:`EventNotFound` when the
    best correlation is below ``MIN_CORRELATION``.
    """
    shorter = min(ref.time[-1] - ref.time[0], other.time[-1] - other.time[0])
    min_overlap = max(5.0, 0.25 * shorter) if min_overlap is None else min_overlap
    if hint is None:
        lo, hi = -math.inf, math.inf
    else:
        half = 60.0 if search is None else search
        lo, hi = hint - half, hint + half
    coarse, r, runner_up, h = _coarse(ref, other, lo, hi, min(min_overlap, shorter))
    if not r >= MIN_CORRELATION:
        raise EventNotFound(f"the two records' {ref.source} and {other.source} do not match at any offset in the "
                            f"search (best correlation {r:.2f} < {MIN_CORRELATION})")
    # data: the signal with the wider smoothing; model: the other, smoothed to that width
    if other.width >= ref.width:
        data, model, sign = other, ref, 1.0     # other(t) ~ ref(t + τ)
    else:
        data, model, sign = ref, other, -1.0    # ref(t) ~ other(t − τ)
    width = math.sqrt(max(data.width ** 2 - model.width ** 2, 0.0))
    margin = 2 * h + width
    at0 = data.time + sign * coarse
    idx = np.flatnonzero((at0 >= model.time[0] + margin) & (at0 <= model.time[-1] - margin))
    if idx.size < 10:
        raise EventNotFound("the records share fewer than 10 samples at the best offset")
    found = minimize_scalar(lambda tau: _fit_at(tau, data, model, sign, width, idx)[0],
                            bounds=(coarse - 2 * h, coarse + 2 * h), method="bounded",
                            options={"xatol": 1e-6 * h})
    offset = float(found.x)
    rss, p, _, at, res = _fit_at(offset, data, model, sign, width, idx)
    step = sample_interval(data.time)
    slope = p * (_boxcar(model.time, model.value, at + step / 2, width)
                 - _boxcar(model.time, model.value, at - step / 2, width)) / step
    noise_share = (1.4826 * np.median(np.abs(slope - np.median(slope)))) ** 2 * slope.size
    information = max(float(slope @ slope) - noise_share, 0.5 * float(slope @ slope))
    s2 = rss / max(idx.size - 3, 1)
    rho = float(np.corrcoef(res[1:], res[:-1])[0, 1]) if res.size > 3 and res.std() > 0 else 0.0
    rho = min(max(rho, 0.0), 0.95)
    statistical = (1 + rho) / (1 - rho) * s2 / information if information > 0 else math.inf
    # the model's own sampling places each sharp feature within ±Δt_m/2; a box-car of width w dilutes that by Δt_m/w
    dt_model = sample_interval(model.time)
    sampling = dt_model / math.sqrt(12.0) * min(1.0, dt_model / max(width, dt_model))
    sigma = math.sqrt(statistical + sampling ** 2)
    return Alignment(offset, sigma, r, runner_up, (lo, hi), int(idx.size))

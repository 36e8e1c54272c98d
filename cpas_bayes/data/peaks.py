"""Peak loads and load share per stage, with their 1-sigma.

:func:`peaks_and_load_share` finds, in each stage interval
(:func:`stage_intervals`), the peak of the accelerometer load, of the
load-cell sum and of each parachute, and the parachutes' shares of the
load-cell sum, from the load columns of a reduction
(:mod:`cpas_bayes.data.reduction`). Everything inside is SI.

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_coeffs, savgol_filter

from cpas_bayes.data.bundle import FlightTest

DEFAULT_PEAK_SMOOTHING = 0.1   # s, quadratic-filter width before taking a maximum


# ---------------------------------------------------------------------------
# stage intervals


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


def peaks_and_load_share(columns, intervals, parachutes, width):
    """Peaks of each stage (:class:`StagePeaks`) and, where defined, its load share (:class:`LoadShare`).

    ``columns`` maps names of the reduction's frame columns to arrays (SI):
    ``time``, ``load_total`` and, with load cells, ``load_cells`` and
    ``load_<id>``, each with its ``_sigma_random`` and ``_sigma_systematic``.
    ``parachutes`` are those with a load cell (none: accelerometer peaks
    only); ``width`` is the peak filter's width in samples
    (:func:`peak_filter_width`). Returns (peaks, shares) as tuples.
    """
    def column(name):
        return np.asarray(columns[name], float)

    time = column("time")
    acc_f, acc_r = peak_filter(column("load_total"), column("load_total_sigma_random"), width)
    acc_syst = column("load_total_sigma_systematic")
    if not parachutes:
        return tuple(StagePeaks(st, _peak(time, acc_f, acc_r, acc_syst, st.start, st.end)[0], None, {})
                     for st in intervals), ()

    loads = {p.id: column(f"load_{p.id}") for p in parachutes}
    lc_syst = column("load_cells_sigma_systematic")
    peaks, shares = [], []
    cells_f, cells_r = peak_filter(column("load_cells"), column("load_cells_sigma_random"), width)
    filtered = {pid: peak_filter(v, column(f"load_{pid}_sigma_random"), width) for pid, v in loads.items()}
    smooth_loads = {pid: v[0] for pid, v in filtered.items()}
    for st in intervals:
        acc, _ = _peak(time, acc_f, acc_r, acc_syst, st.start, st.end)
        cells, i_glob = _peak(time, cells_f, cells_r, lc_syst, st.start, st.end)
        own, own_index = {}, {}
        for p in parachutes:
            if len(p.stages) <= st.index:
                continue
            # A parachute's own peak is looked for in its own stage interval.
            t0 = p.stages[st.index].start
            t1 = p.stages[st.index + 1].start if len(p.stages) > st.index + 1 else math.inf
            pk, idx = _peak(time, *filtered[p.id], column(f"load_{p.id}_sigma_systematic"), t0, t1)
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
    return tuple(peaks), tuple(shares)

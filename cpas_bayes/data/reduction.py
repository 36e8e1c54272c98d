"""Flight-test load reduction: loads and drag areas with 1-sigma (seed §II–III).

Pure numpy functions implement the seed's equations; :func:`reduce_test`
applies them to a :class:`~cpas_bayes.data.bundle.FlightTest` and returns a
:class:`Reduction` (data only; :func:`cpas_bayes.outputs.reduction.write_reduction`
writes ``reduced.csv``, ``reduction.json`` and ``reduction.png`` in the bundle's
units). Everything inside is SI (N, m², Pa, s); angles are degrees in tables,
radians in formulas.

The load cells' friction-loss scale factor is calibrated in
:mod:`cpas_bayes.data.friction`; peaks and load share are found in
:mod:`cpas_bayes.data.peaks` (each module's docstring states its rules).

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
from typing import NamedTuple

import numpy as np
import pandas as pd

from cpas_bayes.core.errors import InputError
from cpas_bayes.data.bundle import TOML_NAME, FlightTest
from cpas_bayes.data.friction import SCALE_MODES, ScaleFactor, calibrate_scale_factor
from cpas_bayes.data.peaks import (DEFAULT_PEAK_SMOOTHING, peak_filter_width, peaks_and_load_share,
                                   stage_intervals)


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
    air_estimate: object = None   # a logger bundle's best-estimate trajectory (data.air_reconstruction)

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

    @property
    def warnings(self):
        """What to know before trusting the numbers: a logger bundle's trajectory that misses the receiver, and
        what the readings themselves show (:func:`cpas_bayes.data.bundle_notes.reading_warnings`)."""
        from cpas_bayes.data.bundle_notes import reading_warnings

        said = self.air_estimate.misfit_warning() if self.air_estimate is not None else None
        return ([said] if said else []) + reading_warnings(self.test)

    def to_json(self):
        u = self.test.units
        return {"test": self.test.name, "bundle": str(self.test.source) if self.test.source else None,
                "units": {"force": u.label("force"), "area": u.label("area"), "time": u.label("time"),
                          "angle": "deg"},
                "scale_factor": self.scale.to_json() if self.scale else None,
                "peak_smoothing_s": self.peak_smoothing,
                "peaks": [p.to_json(u) for p in self.peaks],
                "load_share": [s.to_json() for s in self.load_share], "warnings": self.warnings}


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
    air_estimate = None
    if not test.measured_qbar:
        # A logger bundle: q̄ from the best-estimate trajectory, at the accelerometer's readings.
        from cpas_bayes.data.air_reconstruction import best_estimate_trajectory, with_best_estimate
        air_estimate = best_estimate_trajectory(test)
        test = with_best_estimate(test, air_estimate)
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
    if air_estimate is not None:
        # The reconstructed q̄'s error is one set of air parameters for the whole record: systematic.
        no_q = np.zeros_like(dq)
        r_load = accelerometer_load_sigma(G, q, veh.weight, veh.cds, dG, no_q, 0.0, 0.0).random
        r_cds = accelerometer_drag_area_sigma(G, q, W_T, dG, no_q, 0.0, 0.0).random
        load_total_s = SigmaParts(r_load, np.sqrt(np.maximum(load_total_s.total**2 - r_load**2, 0.0)))
        cds_total_s = SigmaParts(r_cds, np.sqrt(np.maximum(cds_total_s.total**2 - r_cds**2, 0.0)))
    for name, value, s in (("load_total", load_total, load_total_s), ("cds_total", cds_total, cds_total_s)):
        cols[name], cols[f"{name}_sigma"] = value, s.total
        cols[f"{name}_sigma_random"], cols[f"{name}_sigma_systematic"] = s.random, s.systematic

    check_load_cells(test)
    with_cells = [p for p in test.parachutes if p.load_column]
    intervals = stage_intervals(test)
    width = peak_filter_width(peak_smoothing, test.sample_rate)

    if not with_cells:
        if windows:
            raise InputError(test.label, "option --window", "the test has no load cells to calibrate",
                             "drop --window, or add load_cell columns to the bundle")
        frame = pd.DataFrame(cols)
        peaks, _ = peaks_and_load_share(cols, intervals, (), width)
        return Reduction(test, frame, None, peaks, (), peak_smoothing, air_estimate)

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
    scale_factor = calibrate_scale_factor(test, mode, cds_total, cells_raw, windows)
    s = scale_factor.at(time)
    s_random, s_systematic = scale_factor.sigma_parts(time)
    s_sigma = np.hypot(s_random, s_systematic)
    cols["scale"], cols["scale_sigma"] = s, s_sigma

    # Scaled loads and drag areas; the factor's sigma is common to all samples: systematic.
    W_p = sum(p.weight for p in with_cells)
    dW_p = math.sqrt(sum(p.weight_sigma**2 for p in with_cells))
    sum_axial = sum(axial.values())
    sum_rand2 = np.zeros_like(time)
    for p in with_cells:
        load = s * axial[p.id]
        rand = s * axial_s[p.id]
        syst = np.abs(axial[p.id]) * s_sigma
        cds_s = load_cell_drag_area_sigma(load, G, q, p.weight, rand, dG, dq, p.weight_sigma, syst)
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
    peaks, shares = peaks_and_load_share(cols, intervals, with_cells, width)
    return Reduction(test, frame, scale_factor, peaks, shares, peak_smoothing, air_estimate)


# ---------------------------------------------------------------------------
# command-line helper


def check_load_cells(test):
    """Every parachute has a load cell, or none has: the friction calibration compares the cells' sum with
    the accelerometer's total, so a cluster measured in part cannot be reduced (refused naming the key)."""
    missing = [p for p in test.parachutes if not p.load_column]
    if missing and len(missing) != len(test.parachutes):
        file = test.source / TOML_NAME if test.source else test.label
        raise InputError(file, f"key 'parachute '{missing[0].id}'.load_cell'",
                         f"parachute(s) {', '.join(p.id for p in missing)} have no load cell, so the load cells "
                         "cannot be calibrated against the accelerometer total",
                         "give every parachute a load_cell column, or none to reduce the accelerometer alone")


def check_reducible(test):
    """What ``reduce`` refuses before any work, for ``validate`` to refuse too: a cluster's load cells in part
    (:func:`check_load_cells`), and a logger bundle whose record cannot be reconstructed (its release at the
    record's end, too few receiver samples inside it, a density in the wrong unit: the checks of
    :func:`~cpas_bayes.data.air_reconstruction.logger_channels`, which reads the channels and fits nothing)."""
    check_load_cells(test)
    if not test.measured_qbar:
        from cpas_bayes.data.air_reconstruction import logger_channels
        logger_channels(test)


def parse_window(text, source=""):
    """Parse ``"T0:T1"`` (seconds) into a pair; InputError naming --window otherwise."""
    parts = str(text).split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        window = float(parts[0]), float(parts[1])
    except ValueError:
        raise InputError(source or "command line", f"option --window {text}",
                         "not a window of the form T0:T1", "write --window 3.0:9.0 (seconds)") from None
    if not all(math.isfinite(t) for t in window):
        raise InputError(source or "command line", f"option --window {text}", "T0 and T1 must be finite numbers",
                         "write --window 3.0:9.0 (seconds)")
    return window

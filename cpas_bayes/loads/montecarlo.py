"""Monte Carlo loads of a parachute cluster from the model memo (seed §V.D; Fig. 17, 26, 31).

Each run draws one inflation parameter set per canopy of a test's cluster
from the memo's population distributions, disperses the cutter times, flies
the cluster from the test's first data sample and reports the peak loads,
the peak fill times and the load share. Runs are simulated in batches, all
runs of a batch at once.

What a run is made of
---------------------
The test given as ``like`` fixes the configuration: its parachutes (kind,
inflation, nominal diameter D_o, weight W_p,i, number of stages), the vehicle
(W_V, CDS_V), the initial state (airspeed, flight-path angle and altitude of
the first data sample), the start time and the duration. Per run and canopy:

* every parameter from the memo of the canopy's kind: ``Memo.sample`` either
  resamples rows of the population-predictive draws (``joint=True``, keeps
  correlations) or draws each ``<stage>.<parameter>`` independently from its
  family (``joint=False``, the classic per-parameter dispersion);
* full-open drag area from the drag coefficient on the constructed area::

      CDS_o = C_D,o · π·D_o²/4

* stage drag areas CDS_i = ε_i·CDS_o, with ε = 1 for the full-open stage;
* C_k = 1 and t_k = 0 for finite-mass canopies (seed §VI), memo values for
  infinite-mass ones;
* stage starts t_i = t_i,nominal + N(0, σ_t,i²) from the bundle's ``start`` and
  ``start_sigma`` (cutter-time dispersion). Stage order is kept: a draw that
  would not follow the previous stage is moved to 1 ms after it (with the
  usual 0.05–0.1 s sigmas and seconds between cutters this does not occur).

Fill constant, the seed's re-parameterisation (Eq. 14–18)
---------------------------------------------------------
Fill time and peak fill time of a stage that starts from the drag area
CDS_start held at its start (0 at bag strip)::

    t_f  = n · D_o · sqrt((CDS_i − CDS_start)/CDS_o) / V_i                (Eq. 14)
    S    = (C_k·CDS_i − CDS_start) / (CDS_i − CDS_start)
    t_fp = t_f · S^(1/expopen)                                            (Eq. 15, 16)
    n_p  = n · S^(1/expopen)                                              (Eq. 17)
    n    = n_p · S^(−1/expopen)                                           (Eq. 18)

``mode="n_p"`` disperses n_p and derives n per run by Eq. 18 (the seed's
recommendation): the peak fill time is then fixed by n_p alone,
t_fp = n_p·D_o·sqrt((CDS_i − CDS_start)/CDS_o)/V_i, whatever C_k and expopen
were drawn. ``mode="n"`` disperses n itself ("the old way"), drawn from the
memo's ``<stage>.n`` entry independently of the other parameters; t_fp then
picks up the factor S^(1/expopen) of C_k and expopen drawn apart from n,
which is how Monte Carlo runs produced peak fill times no test showed (seed
Fig. 21–22). V_i is the simulated airspeed at the run's own stage start.

Dynamics and loads (as :mod:`cpas_bayes.physics.trajectory`)
----------------------------------------------------
Planar point mass, no wind (seed Eq. 1–3)::

    (W_T/g)·dV/dt = −q̄·(PRF·Σ CDS_i + CDS_V) − W_T·sin γ,   dγ/dt = −g·cos γ/V,   dh/dt = V·sin γ
    G   = −(dV/dt + g·sin γ)/g                                            (Eq. 5)
    F_i = PRF·q̄·CDS_i − W_p,i·G                                           (Eq. 10)

and Σ F_i = W_V·G − q̄·CDS_V, the accelerometer total load of Eq. 6, so the
simulated total is directly comparable with a reduced test.

What is reported per run
------------------------
Cluster stage k runs from the earliest start of stage k among the canopies to
the earliest start of stage k+1 (the rule of :func:`cpas_bayes.data.reduction.stage_intervals`,
applied to the run's own dispersed starts). Per cluster stage: the peak of
Σ F_i, its time and the load share F_i/Σ F_i at that instant. Per canopy and
own stage (from its start to its next start): the peak of F_i and its time,
and the stage timing t_f, t_fp, n, n_p, V_i. A stage that never started
within the simulated duration reports NaN.

Engines
-------
``"trajectory"`` runs :func:`cpas_bayes.physics.trajectory.simulate` on each batch
and takes the peaks from its samples. ``"compiled"`` integrates the same
equations with the same fixed-step RK4 scheme and the same rules (V_i
extrapolated inside the step along dV/dt, drag areas at the step midpoint
and end, γ clipped to ±90°) in one compiled loop per run, evaluating the
drag areas with :mod:`cpas_bayes.physics.inflation`'s compiled stage law and the
density from a 1 m table of ``options.density`` (linear interpolation,
relative error ~1e-9). It keeps no full histories, so a batch costs memory
for its outputs only. It also takes each canopy's drag-area peak instant
t_i + t_fp as an extra evaluation point (a partial RK4 step from the last
step), so the sharp corner of an infinite-mass peak is not missed between
samples. ``"auto"`` (default) uses the compiled engine unless added mass or
breathing is switched on in ``options``. Tests hold the two engines equal.

Outputs (:func:`write_monte_carlo`, ``cpas-bayes montecarlo``)
---------------------------------------------------------------
``runs.csv``, one row per run in the like-test's units (loads in its force
unit, speeds, areas likewise; times in s), stage tags ``s1``, ``s2``…:
``s<k>.peak_load``, ``s<k>.peak_time``, ``s<k>.share.<id>`` (cluster stage
k); ``<id>.cds_o`` and per canopy stage ``<id>.s<k>.{peak_load, peak_time,
t_fp, t_f, v_i, n_p, n, start, expopen, ck, tk, eps}``; ``vehicle_weight``,
``vehicle_cds``. ``summary.json``: per cluster stage the peak load and its
time (quantiles 1/5/50/95/99 %, mean, sd) and per parachute its own-stage
peak load, peak time, t_fp and load share at the stage peak; the
configuration, mode, runtime and runs/s. ``peak_loads.png`` and
``fill_times.png`` (:mod:`cpas_bayes.outputs.plots.montecarlo`).
"""

from __future__ import annotations

import math
import sys
import time as _time
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np
import pandas as pd
from tqdm import tqdm

from cpas_bayes.data.bundle import FlightTest
from cpas_bayes.core.errors import InputError
from cpas_bayes.core.files import write_csv, write_json
from cpas_bayes.outputs.figures import save_figure, write_json_and_figure
from cpas_bayes.physics.inflation import _stage_value
from cpas_bayes.population.memo import DRAWS_NAME, MEMO_NAME, Memo
from cpas_bayes.physics.inflation import stage_key, stage_tag
from cpas_bayes.physics.trajectory import ClusterParameters, SimulationOptions, VehicleProperties, VehicleState0, simulate
from cpas_bayes.core.units import UnitSystem

MODES = ("n_p", "n")
ENGINES = ("auto", "compiled", "trajectory")
DEFAULT_BATCH = 1000          # runs per batch, compiled engine
TRAJECTORY_BATCH = 200        # runs per batch, trajectory engine (it stores full histories)
STAGE_ORDER_GAP = 1e-3        # s, a dispersed start is kept at least this far after the previous one
PADDED_START_DELAY = 1e3      # s after the data end: start of a padding stage slot (never active)
DENSITY_TABLE_STEP = 1.0      # m
QUANTILE_LEVELS = (0.01, 0.05, 0.5, 0.95, 0.99)
SHARE_QUANTILES = (0.05, 0.5, 0.95)


# ---------------------------------------------------------------------------
# the configuration of a test


@dataclass(frozen=True)
class ClusterLayout:
    """What a Monte Carlo takes from the ``like`` test: the cluster, the vehicle, the initial state (SI)."""

    test_name: str
    source: Path | None
    units: UnitSystem
    ids: tuple
    kinds: tuple
    inflations: tuple
    diameter: np.ndarray           # (P,) D_o, m
    weight: np.ndarray             # (P,) W_p,i, N
    stages_per_chute: np.ndarray   # (P,) int
    stage_labels: tuple            # per canopy, its stage labels
    nominal_start: np.ndarray      # (P, K) s, NaN in padding slots
    start_sigma: np.ndarray        # (P, K) s, 0 in padding slots
    cluster_stage_labels: tuple    # (K,) label of cluster stage k (first canopy having it)
    t0: float                      # s, first data sample
    duration: float                # s
    airspeed0: float               # m/s
    gamma0: float                  # rad
    altitude0: float               # m
    vehicle_weight: float          # N
    vehicle_cds: float             # m²

    @classmethod
    def from_test(cls, test: FlightTest) -> "ClusterLayout":
        """The configuration of ``test``; InputError if the first sample lacks what a run starts from."""
        data = test.data
        where = test.source / "data.csv" if test.source else test.label
        if "altitude" not in data.columns:
            raise InputError(where, "column 'altitude'", "missing; a Monte Carlo run starts from the first "
                             "sample's altitude (it sets the air density)",
                             "add an altitude column to data.csv, or use another test as --like")
        first = data.iloc[0]
        if not float(first["airspeed"]) > 0:
            raise InputError(where, "row 2, column 'airspeed'", f"initial airspeed {first['airspeed']} is not "
                             "positive", "trim the rows before the vehicle has airspeed")
        P = len(test.parachutes)
        K = max(len(p.stages) for p in test.parachutes)
        start = np.full((P, K), np.nan)
        sigma = np.zeros((P, K))
        for i, p in enumerate(test.parachutes):
            for k, st in enumerate(p.stages):
                start[i, k], sigma[i, k] = st.start, st.start_sigma
        labels = []
        for k in range(K):
            having = [p for p in test.parachutes if len(p.stages) > k]
            labels.append(having[0].stages[k].label)
        return cls(
            test_name=test.name, source=test.source, units=test.units,
            ids=tuple(p.id for p in test.parachutes), kinds=tuple(p.kind for p in test.parachutes),
            inflations=tuple(p.inflation for p in test.parachutes),
            diameter=np.array([p.diameter for p in test.parachutes]),
            weight=np.array([p.weight for p in test.parachutes]),
            stages_per_chute=np.array([len(p.stages) for p in test.parachutes], dtype=np.int64),
            stage_labels=tuple(tuple(s.label for s in p.stages) for p in test.parachutes),
            nominal_start=start, start_sigma=sigma, cluster_stage_labels=tuple(labels),
            t0=float(data["time"].iloc[0]), duration=test.duration,
            airspeed0=float(first["airspeed"]), gamma0=math.radians(float(first["gamma"])),
            altitude0=float(first["altitude"]), vehicle_weight=test.vehicle.weight,
            vehicle_cds=test.vehicle.cds)

    @property
    def n_chutes(self):
        return len(self.ids)

    @property
    def n_stages(self):
        """K: the most stages any canopy has (= the number of cluster stages)."""
        return int(self.stages_per_chute.max())

    @property
    def t_end(self):
        return self.t0 + self.duration

    @property
    def padding_start(self):
        """Start time given to padding stage slots: far after the data end, so never active."""
        return self.t_end + PADDED_START_DELAY

    def stage_key(self, chute, k):
        """Memo stage key (``first``, ``reefed1``…, ``full_open``) of canopy ``chute``'s stage ``k``."""
        return stage_key(k, int(self.stages_per_chute[chute]))

    def has_stage(self):
        """(P, K) mask of real stage slots."""
        return np.arange(self.n_stages)[None, :] < self.stages_per_chute[:, None]

    def stage_tag(self, k):
        """Short column tag of (cluster or canopy) stage k: ``s1``, ``s2``…"""
        return stage_tag(k)


# ---------------------------------------------------------------------------
# run inputs


@dataclass(frozen=True)
class RunInputs:
    """Parameter sets of B runs, SI. Stage arrays (B, P, K) in time order; padding slots are inert."""

    start: np.ndarray
    cds_stage: np.ndarray
    n_fill: np.ndarray         # n_p or n, see fill_constant
    expopen: np.ndarray
    ck: np.ndarray
    tk: np.ndarray
    eps: np.ndarray
    cds_o: np.ndarray          # (B, P)
    vehicle_weight: np.ndarray  # (B,)
    vehicle_cds: np.ndarray     # (B,)
    fill_constant: str = "n_p"

    def __len__(self):
        return self.start.shape[0]

    def take(self, index) -> "RunInputs":
        """The runs at ``index`` (a slice or integer array)."""
        names = ("start", "cds_stage", "n_fill", "expopen", "ck", "tk", "eps", "cds_o", "vehicle_weight",
                 "vehicle_cds")
        return RunInputs(**{n: getattr(self, n)[index] for n in names}, fill_constant=self.fill_constant)

    def cluster(self, layout: ClusterLayout) -> ClusterParameters:
        """The runs as :class:`~cpas_bayes.physics.trajectory.ClusterParameters` (batch axis first)."""
        return ClusterParameters(
            start=self.start, cds_stage=self.cds_stage, n_fill=self.n_fill, expopen=self.expopen, ck=self.ck,
            tk=self.tk, cds_o=self.cds_o, diameter=layout.diameter, weight=layout.weight,
            fill_constant=self.fill_constant, ids=layout.ids)


def assemble_inputs(layout: ClusterLayout, values: dict, fill_constant: str, runs: int,
                    vehicle_weight=None, vehicle_cds=None) -> RunInputs:
    """RunInputs from per-canopy arrays ``values[(chute, k, name)]`` (B,) and ``values[(chute, 'cds_o')]``.

    ``name`` in start, fill, expopen, ck, tk, eps. Missing C_k / t_k / ε mean
    1 / 0 / 1 (finite mass, full open). Padding slots get a start after the
    data end and copies of the canopy's last stage.
    """
    P, K = layout.n_chutes, layout.n_stages
    shape = (runs, P, K)
    arrays = {name: np.empty(shape) for name in ("start", "n_fill", "expopen", "ck", "tk", "eps")}
    cds_o = np.empty((runs, P))
    defaults = {"ck": 1.0, "tk": 0.0, "eps": 1.0}
    for i in range(P):
        n = int(layout.stages_per_chute[i])
        cds_o[:, i] = values[(i, "cds_o")]
        for k in range(K):
            kk = min(k, n - 1)
            for name, target in (("start", "start"), ("fill", "n_fill"), ("expopen", "expopen"), ("ck", "ck"),
                                 ("tk", "tk"), ("eps", "eps")):
                key = (i, kk, name)
                arrays[target][:, i, k] = values[key] if key in values else defaults[name]
            if k >= n:
                arrays["start"][:, i, k] = layout.padding_start + k
    weight = np.full(runs, layout.vehicle_weight) if vehicle_weight is None else np.asarray(vehicle_weight, float)
    cds_v = np.full(runs, layout.vehicle_cds) if vehicle_cds is None else np.asarray(vehicle_cds, float)
    return RunInputs(start=arrays["start"], cds_stage=arrays["eps"] * cds_o[:, :, None], n_fill=arrays["n_fill"],
                     expopen=arrays["expopen"], ck=arrays["ck"], tk=arrays["tk"], eps=arrays["eps"], cds_o=cds_o,
                     vehicle_weight=weight, vehicle_cds=cds_v, fill_constant=fill_constant)


def _memo_where(memo: Memo, joint):
    name = DRAWS_NAME if joint else MEMO_NAME
    return memo.folder / name if memo.folder else name


def _needed_columns(layout: ClusterLayout, chute: int, mode: str):
    """(column, role, stage index) the memo must supply for canopy ``chute``."""
    n = int(layout.stages_per_chute[chute])
    need = [("parachute.cd_o", "cds_o", None)]
    for k in range(n):
        key = layout.stage_key(chute, k)
        need.append((f"{key}.{mode}", "fill", k))
        need.append((f"{key}.expopen", "expopen", k))
        if layout.inflations[chute] == "infinite":
            need.append((f"{key}.ck", "ck", k))
            need.append((f"{key}.tk", "tk", k))
        if k < n - 1:
            need.append((f"{key}.eps", "eps", k))
    return need


# Physical domain of each drawn role: (bound, strict) — a draw must exceed the bound (strict) or reach it.
_DOMAIN = {"cds_o": (0.0, True), "fill": (0.0, True), "expopen": (0.0, True), "ck": (1.0, False),
           "tk": (0.0, False), "eps": (0.0, True)}


def draw_run_inputs(memo: Memo, layout: ClusterLayout, runs: int, rng: np.random.Generator, mode="n_p",
                    joint=True) -> RunInputs:
    """Draw ``runs`` parameter sets for every canopy of ``layout`` from ``memo``.

    One ``Memo.sample`` call per parachute kind draws the sets of all its
    canopies in all runs; then the stage starts are dispersed, N(0, σ_t²)
    about the nominal starts, in one draw (B, P, K). The draws depend on the
    seed and on ``runs`` only, never on how the runs are later batched.
    In mode "n" the fill constant n is always drawn from its own memo entry,
    independently of the rest (the old way; the population draws carry n_p,
    not n), while the other parameters follow ``joint``.
    Refuses (InputError naming the memo file and key) a memo lacking a kind,
    stage or parameter the configuration needs, or giving values outside
    their physical domain.
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if runs < 1:
        raise ValueError("runs must be at least 1")
    P, K = layout.n_chutes, layout.n_stages
    values = {}
    for kind in sorted(set(layout.kinds)):
        chutes = [i for i, k in enumerate(layout.kinds) if k == kind]
        frame = memo.sample(kind, runs * len(chutes), rng, joint=joint)
        if mode == "n" and joint:
            # The old way: n independent of everything else, from its own memo entry.
            keys = sorted({layout.stage_key(i, k) for i in chutes for k in range(int(layout.stages_per_chute[i]))})
            for key in keys:
                frame[f"{key}.n"] = memo.entry(kind, key, "n").sample(rng, len(frame))
        for j, i in enumerate(chutes):
            rows = slice(j * runs, (j + 1) * runs)
            for column, role, k in _needed_columns(layout, i, mode):
                where = f"key '{kind}.{column}'" if not joint else f"column '{column}' of kind '{kind}'"
                if column not in frame.columns:
                    stage = f", stage '{layout.stage_labels[i][k]}'" if k is not None else ""
                    raise InputError(_memo_where(memo, joint), where,
                                     f"the memo has no {column.split('.')[-1]} for {kind} stage "
                                     f"'{column.split('.')[0]}', which parachute {layout.ids[i]}{stage} of "
                                     f"{layout.test_name} needs",
                                     "pool tests of this kind with this stage layout into the memo, or use a "
                                     "--like test whose parachutes the memo covers")
                x = frame[column].to_numpy(dtype=float)[rows]
                low, strict = _DOMAIN[role]
                bad = ~np.isfinite(x) | ((x <= low) if strict else (x < low))
                if bad.any():
                    raise InputError(_memo_where(memo, joint), where,
                                     f"drew {x[bad][0]!r}, outside the physical domain "
                                     f"({'>' if strict else '≥'} {low:g})",
                                     "give the entry bounds (or draws) within the domain")
                if role == "cds_o":
                    x = x * math.pi / 4.0 * layout.diameter[i] ** 2
                values[(i, role) if k is None else (i, k, role)] = x
    noise = rng.standard_normal((runs, P, K))
    start = np.where(layout.has_stage(), layout.nominal_start, 0.0)[None] + layout.start_sigma[None] * noise
    for k in range(1, K):
        start[:, :, k] = np.maximum(start[:, :, k], start[:, :, k - 1] + STAGE_ORDER_GAP)
    for i in range(P):
        for k in range(int(layout.stages_per_chute[i])):
            values[(i, k, "start")] = start[:, i, k]
    return assemble_inputs(layout, values, mode, runs)


# ---------------------------------------------------------------------------
# run outputs


@dataclass(frozen=True)
class RunOutputs:
    """Per-run results, SI. S = K cluster stages; NaN where a stage did not happen."""

    stage_peak_load: np.ndarray      # (B, S) peak of Σ F_i in cluster stage k, N
    stage_peak_time: np.ndarray      # (B, S) s
    stage_peak_tension: np.ndarray   # (B, S, P) each F_i at that instant, N
    chute_peak_load: np.ndarray      # (B, P, K) peak of F_i in its own stage k, N
    chute_peak_time: np.ndarray      # (B, P, K) s
    t_f: np.ndarray                  # (B, P, K) fill time (Eq. 14), s
    t_fp: np.ndarray                 # (B, P, K) peak fill time (Eq. 15), s
    n: np.ndarray                    # (B, P, K) fill constant (Eq. 18)
    n_p: np.ndarray                  # (B, P, K) fill distance to peak (Eq. 17)
    v_i: np.ndarray                  # (B, P, K) airspeed at the stage start, m/s
    history_time: np.ndarray         # (T,) s
    history: np.ndarray              # (H, T) Σ F_i of the first H runs, N

    @property
    def stage_share(self):
        """(B, S, P) load share F_i/Σ F_i at each cluster stage's peak (NaN where that peak is not positive)."""
        total = self.stage_peak_load[..., None]
        positive = total > 0
        return np.divide(self.stage_peak_tension, np.where(positive, total, 1.0),
                         out=np.full(self.stage_peak_tension.shape, np.nan), where=positive)

    @staticmethod
    def concatenate(parts):
        first = parts[0]
        fields = {}
        for name in first.__dataclass_fields__:
            if name == "history_time":
                fields[name] = first.history_time
            else:
                fields[name] = np.concatenate([getattr(p, name) for p in parts], axis=0)
        return RunOutputs(**fields)


def _cluster_stage_starts(layout: ClusterLayout, start):
    """(B, K) earliest start of each cluster stage among the canopies having it."""
    masked = np.where(layout.has_stage()[None], start, np.inf)
    return masked.min(axis=1)


# ---------------------------------------------------------------------------
# compiled engine
#
# Per-run inputs are packed into a few arrays so that the compiled helpers
# take few arguments (a numba array argument is passed as a dozen words, and
# calls with many arrays cost more than the arithmetic they wrap).

# fields of the stage-parameter array (B, P, K, 7)
_START, _CDS, _FILL, _EXPOPEN, _CK, _TK, _CDS_O = range(7)
# fields of the stage-timing array (B, P, K, 6)
_HELD, _T_F, _T_FP, _N, _N_P, _V_I = range(6)
# fields of the run array (B, 5)
_V0, _GAMMA0, _ALT0, _W_V, _CDS_V = range(5)


@numba.njit(cache=True, inline="always")
def _density(alt, base, step, table):
    """Linear interpolation in the density table (clamped at its ends)."""
    x = (alt - base) / step
    last = table.shape[0] - 1
    if x < 0.0:
        x = 0.0
    elif x > last:
        x = float(last)
    i = min(int(x), last - 1)
    f = x - i
    return table[i] + f * (table[i + 1] - table[i])


@numba.njit(cache=True, inline="always")
def _derivatives(v, gamma, alt, cds_sum, total_weight, vehicle_cds, prf, gravity, base, step, table):
    """dV/dt (Eq. 3), dγ/dt, dh/dt, q̄ and sin γ: the trajectory module's equations without added mass."""
    rho = _density(alt, base, step, table)
    qbar = 0.5 * rho * v**2
    drag = qbar * (prf * cds_sum + vehicle_cds)
    sin_gamma = math.sin(gamma)
    accel = (-drag - total_weight * sin_gamma) / (total_weight / gravity)
    gamma_rate = -gravity * max(math.cos(gamma), 0.0) / v
    return accel, gamma_rate, v * sin_gamma, qbar, sin_gamma


@numba.njit(cache=True)
def _cluster_cds(t, b, par, timing, n_stages, linear, out):
    """Each canopy's drag area at time t into ``out`` (the active stage's law, 0 before the first start); Σ."""
    total = 0.0
    for p in range(out.shape[0]):
        m = n_stages[p]
        k = m - 1
        while k >= 0 and t < par[b, p, k, _START]:
            k -= 1
        value = 0.0
        if k >= 0:
            value = _stage_value(t - par[b, p, k, _START], timing[b, p, k, _HELD], par[b, p, k, _CDS],
                                 timing[b, p, k, _T_F], timing[b, p, k, _T_FP], par[b, p, k, _EXPOPEN],
                                 par[b, p, k, _CK], par[b, p, k, _TK], linear)
        out[p] = value
        total += value
    return total


@numba.njit(cache=True)
def _begin_stage(b, p, k, v_stage, par, timing, diameter, fill_is_np, linear):
    """Stage k of canopy p starts at airspeed V_i: held drag area, S, n ↔ n_p (Eq. 17/18), t_f (Eq. 14), t_fp (Eq. 15).

    The same arithmetic as :func:`cpas_bayes.physics.inflation.parachute_drag_area`.
    """
    if k == 0:
        held = 0.0
    else:
        held = _stage_value(par[b, p, k, _START] - par[b, p, k - 1, _START], timing[b, p, k - 1, _HELD],
                            par[b, p, k - 1, _CDS], timing[b, p, k - 1, _T_F], timing[b, p, k - 1, _T_FP],
                            par[b, p, k - 1, _EXPOPEN], par[b, p, k - 1, _CK], par[b, p, k - 1, _TK], linear)
    cds_i = par[b, p, k, _CDS]
    growth = cds_i - held
    ratio = (par[b, p, k, _CK] * cds_i - held) / growth if growth > 0.0 else 1.0
    e = par[b, p, k, _EXPOPEN]
    if fill_is_np:
        n_p = par[b, p, k, _FILL]
        n = n_p * ratio ** (-1.0 / e)
    else:
        n = par[b, p, k, _FILL]
        n_p = n * ratio ** (1.0 / e)
    t_f = n * diameter[p] * math.sqrt(max(growth, 0.0) / par[b, p, k, _CDS_O]) / v_stage
    timing[b, p, k, _HELD] = held
    timing[b, p, k, _T_F] = t_f
    timing[b, p, k, _T_FP] = t_f * ratio ** (1.0 / e) if t_f > 0.0 else 0.0
    timing[b, p, k, _N] = n
    timing[b, p, k, _N_P] = n_p
    timing[b, p, k, _V_I] = v_stage


@numba.njit(cache=True)
def _update_peaks(b, t, tension, total, par, n_stages, cluster_start, stage_peaks, chute_peaks):
    """Raise the running peaks of cluster stage and canopy stage holding time t (B, S, 2 + P) / (B, P, K, 2)."""
    s = cluster_start.shape[1] - 1
    while s >= 0 and t < cluster_start[b, s]:
        s -= 1
    if s >= 0 and total > stage_peaks[b, s, 0]:
        stage_peaks[b, s, 0] = total
        stage_peaks[b, s, 1] = t
        for p in range(tension.shape[0]):
            stage_peaks[b, s, 2 + p] = tension[p]
    for p in range(tension.shape[0]):
        k = n_stages[p] - 1
        while k >= 0 and t < par[b, p, k, _START]:
            k -= 1
        if k >= 0 and tension[p] > chute_peaks[b, p, k, 0]:
            chute_peaks[b, p, k, 0] = tension[p]
            chute_peaks[b, p, k, 1] = t


@numba.njit(cache=True)
def _simulate_run(b, t0, h, n_steps, record_every, runs, chute_weight, diameter, par, n_stages, fill_is_np, linear,
                  prf, gravity, base, step, table, cluster_start, timing, stage_peaks, chute_peaks, history, status):
    """Integrate run b (RK4, the trajectory module's step rules) and record its peaks, timing and history."""
    P = par.shape[1]
    K = par.shape[2]
    alt_low = base
    alt_high = base + step * (table.shape[0] - 1)
    chutes_weight = 0.0
    for p in range(P):
        chutes_weight += chute_weight[p]
    total_weight = runs[b, _W_V] + chutes_weight
    cds_v = runs[b, _CDS_V]
    v, gam, alt = runs[b, _V0], runs[b, _GAMMA0], runs[b, _ALT0]
    cds = np.zeros(P)
    cds_mid = np.zeros(P)
    cds_end = np.zeros(P)
    cds_a = np.zeros(P)
    tension = np.zeros(P)
    record_step = np.full((P, K), -2, dtype=np.int64)
    corner = np.full((P, K), np.inf)
    for p in range(P):
        for k in range(n_stages[p]):
            start = par[b, p, k, _START]
            if start > t0:
                record_step[p, k] = int(math.ceil((start - t0) / h)) - 1
            else:
                # Started at or before t0: V_i = V0, as in the trajectory module.
                _begin_stage(b, p, k, v, par, timing, diameter, fill_is_np, linear)
                if timing[b, p, k, _T_FP] > 0.0:
                    corner[p, k] = start + timing[b, p, k, _T_FP]
    next_record = n_steps + 1
    for p in range(P):
        for k in range(n_stages[p]):
            if record_step[p, k] >= 0 and record_step[p, k] < next_record:
                next_record = record_step[p, k]
    next_corner = np.inf
    for p in range(P):
        for k in range(n_stages[p]):
            next_corner = min(next_corner, corner[p, k])
    cds_sum = _cluster_cds(t0, b, par, timing, n_stages, linear, cds)
    H = history.shape[0]
    for n in range(n_steps + 1):
        t_n = t0 + n * h
        a1, g1, c1, qbar, sin_gamma = _derivatives(v, gam, alt, cds_sum, total_weight, cds_v, prf, gravity, base,
                                                   step, table)
        # Channels at t_n: G (Eq. 5) and F_i (Eq. 10).
        load_factor = -(a1 + gravity * sin_gamma) / gravity
        total = 0.0
        for p in range(P):
            tension[p] = prf * qbar * cds[p] - chute_weight[p] * load_factor
            total += tension[p]
        if b < H and n % record_every == 0:
            history[b, n // record_every] = total
        _update_peaks(b, t_n, tension, total, par, n_stages, cluster_start, stage_peaks, chute_peaks)
        if n == n_steps:
            break
        if n == next_record:
            # Stages starting in (t_n, t_n + h]: V_i extrapolated from t_n along dV/dt.
            next_record = n_steps + 1
            for p in range(P):
                for k in range(n_stages[p]):
                    if record_step[p, k] == n:
                        start = par[b, p, k, _START]
                        _begin_stage(b, p, k, v + (start - t_n) * a1, par, timing, diameter, fill_is_np, linear)
                        if timing[b, p, k, _T_FP] > 0.0:
                            corner[p, k] = start + timing[b, p, k, _T_FP]
                            next_corner = min(next_corner, corner[p, k])
                    elif record_step[p, k] > n and record_step[p, k] < next_record:
                        next_record = record_step[p, k]
        t_end = t0 + h * (n + 1.0)
        sum_mid = _cluster_cds(t0 + h * (n + 0.5), b, par, timing, n_stages, linear, cds_mid)
        sum_end = _cluster_cds(t_end, b, par, timing, n_stages, linear, cds_end)
        if next_corner < t_end:
            # Drag-area peaks inside this step: a partial RK4 step to each exact instant.
            next_corner = np.inf
            for p in range(P):
                for k in range(n_stages[p]):
                    tc = corner[p, k]
                    if tc >= t_end:
                        next_corner = min(next_corner, tc)
                        continue
                    if not tc > t_n or (k + 1 < n_stages[p] and tc >= par[b, p, k + 1, _START]):
                        continue
                    d = tc - t_n
                    s_a = _cluster_cds(t_n + 0.5 * d, b, par, timing, n_stages, linear, cds_a)
                    a2, g2, c2, _, _ = _derivatives(v + d / 2 * a1, gam + d / 2 * g1, alt + d / 2 * c1, s_a,
                                                    total_weight, cds_v, prf, gravity, base, step, table)
                    a3, g3, c3, _, _ = _derivatives(v + d / 2 * a2, gam + d / 2 * g2, alt + d / 2 * c2, s_a,
                                                    total_weight, cds_v, prf, gravity, base, step, table)
                    s_b = _cluster_cds(tc, b, par, timing, n_stages, linear, cds_a)
                    a4, g4, c4, _, _ = _derivatives(v + d * a3, gam + d * g3, alt + d * c3, s_b, total_weight,
                                                    cds_v, prf, gravity, base, step, table)
                    vc = v + d / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
                    gc = min(max(gam + d / 6 * (g1 + 2 * g2 + 2 * g3 + g4), -math.pi / 2), math.pi / 2)
                    hc = alt + d / 6 * (c1 + 2 * c2 + 2 * c3 + c4)
                    ac, _, _, qc, sc = _derivatives(vc, gc, hc, s_b, total_weight, cds_v, prf, gravity, base, step,
                                                    table)
                    gc_load = -(ac + gravity * sc) / gravity
                    total_c = 0.0
                    for j in range(P):
                        cds_a[j] = prf * qc * cds_a[j] - chute_weight[j] * gc_load
                        total_c += cds_a[j]
                    _update_peaks(b, tc, cds_a, total_c, par, n_stages, cluster_start, stage_peaks, chute_peaks)
        a2, g2, c2, _, _ = _derivatives(v + h / 2 * a1, gam + h / 2 * g1, alt + h / 2 * c1, sum_mid, total_weight,
                                        cds_v, prf, gravity, base, step, table)
        a3, g3, c3, _, _ = _derivatives(v + h / 2 * a2, gam + h / 2 * g2, alt + h / 2 * c2, sum_mid, total_weight,
                                        cds_v, prf, gravity, base, step, table)
        a4, g4, c4, _, _ = _derivatives(v + h * a3, gam + h * g3, alt + h * c3, sum_end, total_weight, cds_v, prf,
                                        gravity, base, step, table)
        v = v + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
        gam = min(max(gam + h / 6 * (g1 + 2 * g2 + 2 * g3 + g4), -math.pi / 2), math.pi / 2)
        alt = alt + h / 6 * (c1 + 2 * c2 + 2 * c3 + c4)
        if not (alt >= alt_low and alt <= alt_high and v > 0.0):
            status[b] = 1
            return
        for p in range(P):
            cds[p] = cds_end[p]
        cds_sum = sum_end


@numba.njit(cache=True, parallel=True)
def _simulate_batch(t0, h, n_steps, record_every, runs, chute_weight, diameter, par, n_stages, fill_is_np, linear,
                    prf, gravity, base, step, table, cluster_start, timing, stage_peaks, chute_peaks, history, status):
    for b in numba.prange(par.shape[0]):
        _simulate_run(b, t0, h, n_steps, record_every, runs, chute_weight, diameter, par, n_stages, fill_is_np,
                      linear, prf, gravity, base, step, table, cluster_start, timing, stage_peaks, chute_peaks,
                      history, status)


_ENGINE_READY = False  # per process: the compiled engine has been loaded


def ensure_compiled():
    """Compile (or load from numba's cache) the compiled engine with a one-run, one-step call.

    Called before a Monte Carlo starts its clock, so runtimes measure runs, not compilation,
    and by each batch task (a worker's first batch loads it); once per process.
    """
    global _ENGINE_READY
    if _ENGINE_READY:
        return
    par = np.zeros((1, 1, 1, 7))
    par[..., _CDS] = par[..., _CDS_O] = par[..., _FILL] = par[..., _EXPOPEN] = par[..., _CK] = 1.0
    runs = np.array([[1.0, 0.0, 0.0, 1.0, 0.0]])
    _simulate_batch(0.0, 0.01, 1, 1, runs, np.zeros(1), np.ones(1), par, np.ones(1, dtype=np.int64), True, True,
                    1.0, 9.80665, -10.0, 1.0, np.ones(21), np.zeros((1, 1)), np.full((1, 1, 1, 6), np.nan),
                    np.zeros((1, 1, 3)), np.zeros((1, 1, 1, 2)), np.zeros((0, 2)), np.zeros(1, dtype=np.int64))
    _ENGINE_READY = True


def _density_table(layout: ClusterLayout, options: SimulationOptions):
    """Density of ``options.density`` every DENSITY_TABLE_STEP m over every altitude a run can reach.

    Down: the initial altitude minus the larger of twice the initial speed
    and the initial speed plus free-fall gain, times the duration; up: the
    climb V0²/(2g) of an ascending start; 500 m margins.
    """
    v0, h0, T = layout.airspeed0, layout.altitude0, layout.duration
    speed = max(2.0 * v0, v0 + options.gravity * T)
    low = max(h0 - speed * T - 500.0, -4900.0)
    high = h0 + v0**2 / (2.0 * options.gravity) + 500.0
    altitudes = low + DENSITY_TABLE_STEP * np.arange(int(math.ceil((high - low) / DENSITY_TABLE_STEP)) + 1)
    return low, DENSITY_TABLE_STEP, np.ascontiguousarray(options.density(altitudes), dtype=float)


def _time_grid(layout: ClusterLayout, options: SimulationOptions):
    n_samples = int(round(layout.duration / options.dt)) + 1
    return layout.t0 + options.dt * np.arange(n_samples)


def _run_compiled(layout: ClusterLayout, inputs: RunInputs, options: SimulationOptions, n_history: int):
    B, P, K = inputs.start.shape
    time = _time_grid(layout, options)
    h = options.dt / options.substeps
    n_steps = (time.size - 1) * options.substeps
    base, step, table = _density_table(layout, options)
    par = np.empty((B, P, K, 7))
    for index, values in ((_START, inputs.start), (_CDS, inputs.cds_stage), (_FILL, inputs.n_fill),
                          (_EXPOPEN, inputs.expopen), (_CK, inputs.ck), (_TK, inputs.tk),
                          (_CDS_O, inputs.cds_o[:, :, None])):
        par[..., index] = values
    runs = np.empty((B, 5))
    runs[:, _V0], runs[:, _GAMMA0], runs[:, _ALT0] = layout.airspeed0, layout.gamma0, layout.altitude0
    runs[:, _W_V], runs[:, _CDS_V] = inputs.vehicle_weight, inputs.vehicle_cds
    timing = np.full((B, P, K, 6), np.nan)
    stage_peaks = np.full((B, K, 2 + P), np.nan)
    stage_peaks[:, :, 0] = -np.inf
    chute_peaks = np.full((B, P, K, 2), np.nan)
    chute_peaks[..., 0] = -np.inf
    history = np.zeros((n_history, time.size))
    status = np.zeros(B, dtype=np.int64)
    _simulate_batch(float(layout.t0), float(h), int(n_steps), int(options.substeps), runs,
                    np.ascontiguousarray(layout.weight, dtype=float),
                    np.ascontiguousarray(layout.diameter, dtype=float),
                    par, layout.stages_per_chute.astype(np.int64), inputs.fill_constant == "n_p",
                    options.decay == "linear", float(options.prf), float(options.gravity), float(base), float(step),
                    table, np.ascontiguousarray(_cluster_stage_starts(layout, inputs.start)), timing, stage_peaks,
                    chute_peaks, history, status)
    if status.any():
        raise ValueError(f"{int(status.sum())} run(s) left the density table or stopped (airspeed ≤ 0); "
                         "check the initial state and the memo's drag areas")
    stage_peaks[:, :, 0][~np.isfinite(stage_peaks[:, :, 0])] = np.nan
    chute_peaks[..., 0][~np.isfinite(chute_peaks[..., 0])] = np.nan
    return RunOutputs(stage_peak_load=stage_peaks[:, :, 0], stage_peak_time=stage_peaks[:, :, 1],
                      stage_peak_tension=stage_peaks[:, :, 2:], chute_peak_load=chute_peaks[..., 0],
                      chute_peak_time=chute_peaks[..., 1], t_f=timing[..., _T_F], t_fp=timing[..., _T_FP],
                      n=timing[..., _N], n_p=timing[..., _N_P], v_i=timing[..., _V_I], history_time=time,
                      history=history)


# ---------------------------------------------------------------------------
# trajectory engine


def _masked_peak(values, mask, time):
    """Max over the last axis where ``mask``; its time; NaN where the mask is empty. Also the argmax."""
    masked = np.where(mask, values, -np.inf)
    index = masked.argmax(axis=-1)
    peak = np.take_along_axis(masked, index[..., None], axis=-1)[..., 0]
    empty = ~mask.any(axis=-1)
    return np.where(empty, np.nan, peak), np.where(empty, np.nan, time[index]), index, empty


def _run_trajectory(layout: ClusterLayout, inputs: RunInputs, options: SimulationOptions, n_history: int):
    B, P, K = inputs.start.shape
    state0 = VehicleState0(np.full(B, layout.airspeed0), np.full(B, layout.gamma0), np.full(B, layout.altitude0))
    vehicle = VehicleProperties(inputs.vehicle_weight, inputs.vehicle_cds)
    result = simulate(state0, vehicle, inputs.cluster(layout), layout.duration, options, t0=layout.t0,
                      refine_peaks=0)
    time = result.time
    tension, total = result.tension, result.tension.sum(axis=1)
    cluster_start = _cluster_stage_starts(layout, inputs.start)
    bounds = np.concatenate([cluster_start, np.full((B, 1), np.inf)], axis=1)
    stage_peak = np.full((B, K), np.nan)
    stage_time = np.full((B, K), np.nan)
    stage_tension = np.full((B, K, P), np.nan)
    rows = np.arange(B)
    for s in range(K):
        mask = (time[None] >= bounds[:, s, None]) & (time[None] < bounds[:, s + 1, None])
        peak, when, index, empty = _masked_peak(total, mask, time)
        stage_peak[:, s], stage_time[:, s] = peak, when
        stage_tension[:, s] = np.where(empty[:, None], np.nan, tension[rows, :, index])
    has = layout.has_stage()
    ends = np.concatenate([inputs.start[:, :, 1:], np.full((B, P, 1), np.inf)], axis=2)
    ends = np.where(np.concatenate([has[:, 1:], np.zeros((P, 1), bool)], axis=1)[None], ends, np.inf)
    chute_peak = np.full((B, P, K), np.nan)
    chute_time = np.full((B, P, K), np.nan)
    for k in range(K):
        mask = (time >= inputs.start[:, :, k, None]) & (time < ends[:, :, k, None]) & has[None, :, k, None]
        chute_peak[:, :, k], chute_time[:, :, k], _, _ = _masked_peak(tension, mask, time)
    started = has[None] & (inputs.start <= time[-1])
    timing = result.timing

    def keep(a):
        return np.where(started, a, np.nan)

    return RunOutputs(stage_peak_load=stage_peak, stage_peak_time=stage_time, stage_peak_tension=stage_tension,
                      chute_peak_load=chute_peak, chute_peak_time=chute_time, t_f=keep(timing.t_f),
                      t_fp=keep(timing.t_fp), n=keep(timing.n), n_p=keep(timing.n_p),
                      v_i=keep(result.stage_airspeed), history_time=time, history=total[:n_history].copy())


# ---------------------------------------------------------------------------
# batches


def choose_engine(engine, options: SimulationOptions):
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if engine == "auto":
        return "trajectory" if (options.added_mass_k is not None or options.breathing is not None) else "compiled"
    if engine == "compiled" and (options.added_mass_k is not None or options.breathing is not None):
        raise ValueError("the compiled engine has no added mass or breathing; use engine='trajectory'")
    return engine


def _show_progress(progress):
    return sys.stderr.isatty() if progress is None else bool(progress)


def _batch_task(job):
    engine, layout, chunk, options, n_history = job
    if engine == "compiled":
        ensure_compiled()
        return _run_compiled(layout, chunk, options, n_history)
    return _run_trajectory(layout, chunk, options, n_history)


def simulate_runs(layout: ClusterLayout, inputs: RunInputs, options: SimulationOptions = SimulationOptions(),
                  engine="auto", batch=None, history_runs=0, progress=None, desc="runs", executor=None) -> RunOutputs:
    """Fly every run of ``inputs`` in batches of ``batch`` runs; per-run peaks, timing and H load histories.

    ``history_runs`` H keeps Σ F_i(t) of the first H runs at the sample times
    (for load bands). A tqdm bar counts batches when ``progress`` is true
    (default: when stderr is a terminal). ``executor``
    (:mod:`cpas_bayes.core.executor`) flies the batches side by side. Neither the
    batch size nor the executor changes the results: every run's inputs are
    drawn beforehand and each run is flown on its own.
    """
    from cpas_bayes.core.executor import Executor

    engine = choose_engine(engine, options)
    runs = len(inputs)
    batch = int(batch or (DEFAULT_BATCH if engine == "compiled" else TRAJECTORY_BATCH))
    if batch < 1:
        raise ValueError("batch must be at least 1")
    jobs = [(engine, layout, inputs.take(slice(first, min(first + batch, runs))), options,
             max(0, min(history_runs - first, min(batch, runs - first)))) for first in range(0, runs, batch)]
    executor = executor if executor is not None else Executor()
    return RunOutputs.concatenate(executor.map(_batch_task, jobs, desc=desc, progress=_show_progress(progress)))


# ---------------------------------------------------------------------------
# the Monte Carlo


def describe(values, levels=QUANTILE_LEVELS):
    """Quantiles q01… (names from ``levels``), mean and sd of finite values; None if there are none."""
    x = np.asarray(values, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return None
    out = {f"q{round(100 * q):02d}": float(v) for q, v in zip(levels, np.quantile(x, levels))}
    out["mean"] = float(x.mean())
    out["sd"] = float(x.std(ddof=1)) if x.size > 1 else 0.0
    return out


@dataclass(frozen=True)
class MonteCarloResult:
    """Inputs and outputs of a Monte Carlo of one configuration."""

    layout: ClusterLayout
    inputs: RunInputs
    outputs: RunOutputs
    mode: str
    joint: bool
    runtime_s: float
    engine: str
    options: SimulationOptions
    source: dict = field(default_factory=dict)   # where the parameter sets came from
    cpu_time_s: float = math.nan                 # processor time of all threads (runtime_s is wall-clock)

    @property
    def runs(self):
        return len(self.inputs)

    @property
    def runs_per_second(self):
        return self.runs / self.runtime_s if self.runtime_s > 0 else math.inf

    def single_run_cluster(self, index) -> ClusterParameters:
        """Run ``index``'s parameters as a batch-of-one ClusterParameters (to re-fly it with simulate)."""
        return self.inputs.take(slice(index, index + 1)).cluster(self.layout)

    def frame(self) -> pd.DataFrame:
        """One row per run in the like-test's units (columns: module notes, "Outputs")."""
        lay, u, o, x = self.layout, self.layout.units, self.outputs, self.inputs
        cols = {"run": np.arange(self.runs)}
        share = o.stage_share
        for k in range(lay.n_stages):
            tag = lay.stage_tag(k)
            cols[f"{tag}.peak_load"] = u.from_si(o.stage_peak_load[:, k], "force")
            cols[f"{tag}.peak_time"] = o.stage_peak_time[:, k]
            for i, pid in enumerate(lay.ids):
                cols[f"{tag}.share.{pid}"] = share[:, k, i]
        for i, pid in enumerate(lay.ids):
            cols[f"{pid}.cds_o"] = u.from_si(x.cds_o[:, i], "area")
            for k in range(int(lay.stages_per_chute[i])):
                pre = f"{pid}.{lay.stage_tag(k)}"
                cols[f"{pre}.peak_load"] = u.from_si(o.chute_peak_load[:, i, k], "force")
                cols[f"{pre}.peak_time"] = o.chute_peak_time[:, i, k]
                cols[f"{pre}.t_fp"] = o.t_fp[:, i, k]
                cols[f"{pre}.t_f"] = o.t_f[:, i, k]
                cols[f"{pre}.v_i"] = u.from_si(o.v_i[:, i, k], "speed")
                cols[f"{pre}.n_p"] = o.n_p[:, i, k]
                cols[f"{pre}.n"] = o.n[:, i, k]
                cols[f"{pre}.start"] = x.start[:, i, k]
                cols[f"{pre}.expopen"] = x.expopen[:, i, k]
                cols[f"{pre}.ck"] = x.ck[:, i, k]
                cols[f"{pre}.tk"] = x.tk[:, i, k]
                cols[f"{pre}.eps"] = x.eps[:, i, k]
        cols["vehicle_weight"] = u.from_si(x.vehicle_weight, "force")
        cols["vehicle_cds"] = u.from_si(x.vehicle_cds, "area")
        return pd.DataFrame(cols)

    def summary(self) -> dict:
        """summary.json content: per stage peak-load, fill-time and load-share statistics, in the like-test's units."""
        lay, u, o = self.layout, self.layout.units, self.outputs
        share = o.stage_share
        stages = []
        for k in range(lay.n_stages):
            chutes = {}
            for i, pid in enumerate(lay.ids):
                if k >= lay.stages_per_chute[i]:
                    continue
                chutes[pid] = {
                    "stage_label": lay.stage_labels[i][k],
                    "memo_stage": lay.stage_key(i, k),
                    "peak_load": describe(u.from_si(o.chute_peak_load[:, i, k], "force")),
                    "peak_time": describe(o.chute_peak_time[:, i, k]),
                    "t_fp": describe(o.t_fp[:, i, k]),
                    "share_at_stage_peak": describe(share[:, k, i], SHARE_QUANTILES),
                }
            stages.append({"stage": lay.cluster_stage_labels[k], "tag": lay.stage_tag(k),
                           "peak_load": describe(u.from_si(o.stage_peak_load[:, k], "force")),
                           "peak_time": describe(o.stage_peak_time[:, k]),
                           "parachutes": chutes})
        return {
            "like": {"test": lay.test_name, "bundle": str(lay.source) if lay.source else None,
                     "parachutes": [{"id": pid, "kind": kind, "inflation": infl,
                                     "diameter": u.from_si(float(d), "length"), "stages": list(labels)}
                                    for pid, kind, infl, d, labels in zip(lay.ids, lay.kinds, lay.inflations,
                                                                          lay.diameter, lay.stage_labels)],
                     "initial_state": {"time": lay.t0, "airspeed": u.from_si(lay.airspeed0, "speed"),
                                       "gamma_deg": math.degrees(lay.gamma0),
                                       "altitude": u.from_si(lay.altitude0, "length")},
                     "duration_s": lay.duration},
            "units": {"force": u.label("force"), "time": "s", "speed": u.label("speed"), "area": u.label("area")},
            "source": dict(self.source),
            "runs": self.runs,
            "mode": self.mode,
            "joint": self.joint,
            "engine": self.engine,
            "dt_s": self.options.dt,
            "decay": self.options.decay,
            "runtime_s": self.runtime_s,
            "runs_per_s": self.runs_per_second,
            "cpu_time_s": self.cpu_time_s,
            "stages": stages,
        }


def run_monte_carlo(memo: Memo, like: FlightTest, runs: int, rng: np.random.Generator, mode="n_p", joint=True,
                    batch=None, progress=None, options: SimulationOptions = SimulationOptions(), engine="auto",
                    history_runs=0, executor=None) -> MonteCarloResult:
    """Monte Carlo of ``like``'s cluster with parameter sets drawn from ``memo``.

    ``mode`` "n_p": disperse n_p, derive n per run (Eq. 18); "n": disperse n
    (Eq. 14) independently. ``joint``: resample the memo's population draws
    (True) or draw each parameter from its own distribution (False). Runs are
    simulated ``batch`` at a time, on ``executor`` if given (see
    :func:`simulate_runs`). The runtime covers drawing and simulating.
    """
    layout = ClusterLayout.from_test(like)
    engine_used = choose_engine(engine, options)
    if engine_used == "compiled":
        ensure_compiled()
    clock, cpu = _time.perf_counter(), _time.process_time()
    inputs = draw_run_inputs(memo, layout, runs, rng, mode=mode, joint=joint)
    outputs = simulate_runs(layout, inputs, options, engine_used, batch, history_runs, progress,
                            desc=f"Monte Carlo ({mode})", executor=executor)
    runtime, cpu = _time.perf_counter() - clock, _time.process_time() - cpu
    source = {"memo": str(memo.folder / MEMO_NAME) if memo.folder else None,
              "memo_provenance": dict(memo.provenance)}
    return MonteCarloResult(layout, inputs, outputs, mode, bool(joint), runtime, engine_used, options, source, cpu)


def write_monte_carlo(result: MonteCarloResult, out, memo: Memo | None = None, extra=None):
    """Write runs.csv, summary.json, peak_loads.png and fill_times.png into ``out`` (each atomically).

    ``memo`` adds the pooled tests' t_fp ranges to the fill-time figure;
    ``extra`` entries are added to summary.json (seed, command line).
    Everything is built before anything is written.
    """
    import matplotlib.pyplot as plt

    from cpas_bayes.outputs.plots.montecarlo import plot_fill_times, plot_peak_loads

    out = Path(out)
    table = result.frame()
    summary = result.summary()
    summary.update(extra or {})
    figures = {"peak_loads.png": plot_peak_loads(result), "fill_times.png": plot_fill_times(result, memo)}
    paths = {"csv": out / "runs.csv", "json": out / "summary.json"}
    try:
        write_csv(paths["csv"], table, float_format="%.8g")
        write_json(paths["json"], json_safe(summary))
        for name, fig in figures.items():
            paths[name] = out / name
            save_figure(fig, paths[name], dpi=110)
    finally:
        for fig in figures.values():
            plt.close(fig)
    return paths


def json_safe(obj):
    """JSON-safe copy: non-finite floats become None."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


# ---------------------------------------------------------------------------
# the seed's n_p claim, measured


@dataclass(frozen=True)
class FillTimeGroup:
    """Peak fill times of one parachute kind and memo stage in both dispersion modes."""

    kind: str
    stage: str                 # memo stage key
    stage_labels: tuple        # the like-test's labels of the canopies' stages pooled here
    bounds: tuple              # (low, high) t_fp range seen in the pooled tests, s
    t_fp: dict                 # mode -> (runs × canopies,) peak fill times, s

    def _finite_values(self, mode):
        x = np.asarray(self.t_fp[mode], float)
        return x[np.isfinite(x)]

    def fraction_below(self, mode):
        x = self._finite_values(mode)
        return float(np.mean(x < self.bounds[0])) if x.size else math.nan

    def fraction_above(self, mode):
        x = self._finite_values(mode)
        return float(np.mean(x > self.bounds[1])) if x.size else math.nan

    def fraction_outside(self, mode):
        """Share of (run, canopy) peak fill times outside the tested range."""
        return self.fraction_below(mode) + self.fraction_above(mode)


@dataclass(frozen=True)
class FillTimeComparison:
    """Monte Carlo of the same configuration with n_p (Eq. 17/18) and with n dispersed, parameters independent."""

    layout: ClusterLayout
    runs: int
    groups: tuple
    results: dict              # mode -> MonteCarloResult
    runtime_s: float

    def to_json(self):
        groups = []
        for g in self.groups:
            entry = {"kind": g.kind, "stage": g.stage, "stage_labels": list(g.stage_labels),
                     "tested_t_fp_range_s": list(g.bounds), "samples": int(len(g.t_fp["n_p"]))}
            for mode in MODES:
                entry[mode] = {"fraction_outside": g.fraction_outside(mode), "fraction_below": g.fraction_below(mode),
                               "fraction_above": g.fraction_above(mode), "t_fp_s": describe(g.t_fp[mode])}
            groups.append(entry)
        return {
            "claim": ("seed §V.D: dispersing n, C_k and expopen independently yields peak fill times no test showed; "
                      "dispersing n_p (Eq. 17) and deriving n per run (Eq. 18) keeps them within the tested range"),
            "like": {"test": self.layout.test_name,
                     "bundle": str(self.layout.source) if self.layout.source else None},
            "runs": self.runs,
            "dispersion": "independent per parameter (joint=False) in both modes; identical draws of every "
                          "other parameter and of the stage starts",
            "fraction_definition": "share of (run, canopy) peak fill times t_fp outside the memo's t_fp bounds "
                                   "(the range of peak fill times seen in the pooled tests)",
            "groups": groups,
            "runtime_s": self.runtime_s,
        }


def compare_fill_time_dispersion(memo: Memo, like: FlightTest, runs: int, rng: np.random.Generator, batch=None,
                                 progress=None, options: SimulationOptions = SimulationOptions(),
                                 engine="auto", executor=None) -> FillTimeComparison:
    """Run the same Monte Carlo with n_p and with n dispersed; t_fp outside the tested range per kind and stage.

    Both modes draw every parameter independently from its memo family
    (``joint=False``, the classic dispersion, in which C_k and expopen are
    free of n) from one seed, so every drawn value except the fill constant
    and every stage start are the same in both; the only difference is
    whether the fill constant drawn is n_p (n then derived by Eq. 18) or n.
    The tested range of each kind and stage is the memo's ``t_fp`` bounds.
    """
    layout = ClusterLayout.from_test(like)
    groups_needed = {}
    for i, kind in enumerate(layout.kinds):
        for k in range(int(layout.stages_per_chute[i])):
            groups_needed.setdefault((kind, layout.stage_key(i, k)), []).append((i, k))
    bounds = {}
    for kind, key in groups_needed:
        lo, hi = memo.entry(kind, key, "t_fp").bounds
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise InputError(memo.folder / MEMO_NAME if memo.folder else MEMO_NAME, f"key '{kind}.{key}.t_fp'",
                             f"bounds {[lo, hi]} are not a finite range of peak fill times",
                             "give t_fp bounds = [shortest, longest] peak fill time seen in the pooled tests")
        bounds[(kind, key)] = (float(lo), float(hi))
    seed = int(rng.integers(2**63))
    clock = _time.perf_counter()
    results = {mode: run_monte_carlo(memo, like, runs, np.random.default_rng(seed), mode=mode, joint=False,
                                     batch=batch, progress=progress, options=options, engine=engine,
                                     executor=executor)
               for mode in MODES}
    runtime = _time.perf_counter() - clock
    groups = []
    for (kind, key), members in groups_needed.items():
        t_fp = {mode: np.concatenate([res.outputs.t_fp[:, i, k] for i, k in members]) for mode, res in results.items()}
        labels = tuple(dict.fromkeys(layout.stage_labels[i][k] for i, k in members))
        groups.append(FillTimeGroup(kind, key, labels, bounds[(kind, key)], t_fp))
    return FillTimeComparison(layout, runs, tuple(groups), results, runtime)


def write_fill_time_comparison(comparison: FillTimeComparison, out, extra=None):
    """Write np_vs_n.json and fill_time_np_vs_n.png into ``out`` (atomically); return their paths."""
    from cpas_bayes.outputs.plots.montecarlo import plot_fill_time_np_vs_n

    out = Path(out)
    doc = comparison.to_json()
    doc.update(extra or {})
    paths = {"json": out / "np_vs_n.json", "png": out / "fill_time_np_vs_n.png"}
    write_json_and_figure(paths["json"], json_safe(doc), paths["png"], plot_fill_time_np_vs_n(comparison))
    return paths

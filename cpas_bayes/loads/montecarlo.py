"""Monte Carlo loads of a parachute cluster from the model memo (seed §V.D; Fig. 17, 26, 31).

Each run draws one inflation parameter set per canopy of a test's cluster
from the memo's population distributions, disperses the cutter times, flies
the cluster from the test's first data sample and reports the peak loads,
the peak fill times and the load share. Runs are simulated in batches, all
runs of a batch at once, by :func:`cpas_bayes.physics.engine.simulate_peaks`
(the dynamics, what is reported per run and the two engines are described
there).

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
  infinite-mass ones (and for finite-mass ones whose kind's memo holds them);
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
Fig. 21–22; measured by :mod:`cpas_bayes.loads.fill_time`). V_i is the
simulated airspeed at the run's own stage start. Under NASA CML's linear mode
(``SimulationOptions(decay="cml_linear")``) the peak is at t_f: the exponent
1/expopen above is 0, so t_fp = t_f and n = n_p, and the two modes differ only
by the memo entries they draw from.

Results (:class:`MonteCarloResult`)
-----------------------------------
``frame()``, one row per run in the like-test's units (loads in its force
unit, speeds, areas likewise; times in s), stage tags ``s1``, ``s2``…:
``s<k>.peak_load``, ``s<k>.peak_time``, ``s<k>.share.<id>`` (cluster stage
k); ``<id>.cds_o`` and per canopy stage ``<id>.s<k>.{peak_load, peak_time,
t_fp, t_f, v_i, n_p, n, start, expopen, ck, tk, eps}``; ``vehicle_weight``,
``vehicle_cds``. ``summary()``: per cluster stage the peak load and its
time (quantiles 1/5/50/95/99 %, mean, sd) and per parachute its own-stage
peak load, peak time, t_fp and load share at the stage peak; the
configuration, mode, runtime and runs/s. :mod:`cpas_bayes.outputs.montecarlo`
writes them (``cpas-bayes montecarlo``).

Memory: every run's inputs and outputs are kept (the quantiles, the figures
and ``runs.csv`` need them all); :func:`run_monte_carlo` refuses, before
drawing anything, a run count beyond :mod:`cpas_bayes.loads.budget`'s limits.
"""

from __future__ import annotations

import math
import sys
import time as _time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.summaries import quantile_summary
from cpas_bayes.core.units import UnitSystem
from cpas_bayes.data.bundle import FlightTest
from cpas_bayes.loads.budget import check_runs
from cpas_bayes.physics.engine import RunOutputs, choose_engine, ensure_compiled, real_stages, simulate_peaks
from cpas_bayes.physics.inflation import stage_key, stage_tag
from cpas_bayes.physics.trajectory import ClusterParameters, SimulationOptions, VehicleProperties, VehicleState0
from cpas_bayes.population.memo import DRAWS_NAME, MEMO_NAME, Memo

MODES = ("n_p", "n")
DEFAULT_BATCH = 1000          # runs per batch, compiled engine
TRAJECTORY_BATCH = 200        # runs per batch, trajectory engine (it stores full histories)
STAGE_ORDER_GAP = 1e-3        # s, a dispersed start is kept at least this far after the previous one
PADDED_START_DELAY = 1e3      # s after the data end: start of a padding stage slot (never active)
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
        if not test.measured_qbar:   # a logger bundle: the receiver's state carried back to the first reading
            from cpas_bayes.data.air_reconstruction import air_priors, logger_channels

            channels = logger_channels(test)
            state = {k: v.mu for k, v in air_priors(channels).items()}
            t0 = float(channels.accel_time[0])
            first = {"airspeed": state["airspeed_0"], "gamma": state["flight_path_angle_0"],
                     "altitude": state["altitude_0"]}
        else:
            first, t0 = data.iloc[0], float(data["time"].iloc[0])
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
            t0=t0, duration=test.duration,
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
        return real_stages(self.stages_per_chute, self.n_stages)

    def initial_state(self, runs):
        """The first data sample's state, for each of ``runs`` runs."""
        return VehicleState0(np.full(runs, self.airspeed0), np.full(runs, self.gamma0), np.full(runs, self.altitude0))

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


def _needed_columns(layout: ClusterLayout, chute: int, mode: str, available=()):
    """(column, role, stage index) the memo must supply for canopy ``chute``; a finite-mass stage takes
    C_k and t_k when the memo has them (a kind whose priors let it over-inflate), else C_k = 1."""
    n = int(layout.stages_per_chute[chute])
    need = [("parachute.cd_o", "cds_o", None)]
    for k in range(n):
        key = layout.stage_key(chute, k)
        need.append((f"{key}.{mode}", "fill", k))
        need.append((f"{key}.expopen", "expopen", k))
        if layout.inflations[chute] == "infinite" or {f"{key}.ck", f"{key}.tk"} <= set(available):
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
            for column, role, k in _needed_columns(layout, i, mode, frame.columns):
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
                                     f"drew {float(x[bad][0]):.6g}, outside the physical domain "
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
# batches


def _show_progress(progress):
    return sys.stderr.isatty() if progress is None else bool(progress)


def _batch_task(job):
    engine, layout, chunk, options, n_history = job
    return simulate_peaks(layout.initial_state(len(chunk)), VehicleProperties(chunk.vehicle_weight, chunk.vehicle_cds),
                          chunk.cluster(layout), layout.stages_per_chute, layout.duration, options, t0=layout.t0,
                          engine=engine, history_runs=n_history)


def simulate_runs(layout: ClusterLayout, inputs: RunInputs, options: SimulationOptions = SimulationOptions(),
                  engine="auto", batch=None, history_runs=0, progress=None, desc="runs", executor=None) -> RunOutputs:
    """Fly every run of ``inputs`` in batches of ``batch`` runs; per-run peaks, timing and H load histories.

    Each batch goes to :func:`cpas_bayes.physics.engine.simulate_peaks`.

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

    def frame(self, rows=None) -> pd.DataFrame:
        """One row per run in the like-test's units (columns: module notes, "Outputs"); only the runs of
        slice ``rows`` if given (runs.csv is written a slice at a time, so the table never holds every run)."""
        lay, u = self.layout, self.layout.units
        rows = slice(None) if rows is None else rows
        per_run = {n: getattr(self.outputs, n)[rows] for n in self.outputs.__dataclass_fields__
                   if n not in ("history_time", "history")}
        o, x = replace(self.outputs, **per_run), self.inputs.take(rows)
        cols = {"run": np.arange(self.runs)[rows]}
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

        def stats(values, levels=QUANTILE_LEVELS):
            # A run that never reached a stage has NaN there: summarise the runs that did.
            return quantile_summary(values, levels, finite_only=True)

        stages = []
        for k in range(lay.n_stages):
            chutes = {}
            for i, pid in enumerate(lay.ids):
                if k >= lay.stages_per_chute[i]:
                    continue
                chutes[pid] = {
                    "stage_label": lay.stage_labels[i][k],
                    "memo_stage": lay.stage_key(i, k),
                    "peak_load": stats(u.from_si(o.chute_peak_load[:, i, k], "force")),
                    "peak_time": stats(o.chute_peak_time[:, i, k]),
                    "t_fp": stats(o.t_fp[:, i, k]),
                    "share_at_stage_peak": stats(share[:, k, i], SHARE_QUANTILES),
                }
            stages.append({"stage": lay.cluster_stage_labels[k], "tag": lay.stage_tag(k),
                           "peak_load": stats(u.from_si(o.stage_peak_load[:, k], "force")),
                           "peak_time": stats(o.stage_peak_time[:, k]),
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
            "below_previous": self.options.below_previous,
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
    check_runs(layout, runs)
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

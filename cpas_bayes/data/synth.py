"""Synthetic flight tests with known truth, optionally with one hidden effect.

A synthetic test is a bundle (docs/test-bundle.md, US units) made by
:mod:`cpas_bayes.physics.trajectory` from parameters drawn around realistic CPAS
values, with the measurement model of the example bundles, plus a
``truth.json`` that says what was simulated. Package code never reads a
truth.json; tests and recovery studies do.

Scenario library
----------------
``drogue``: two 23 ft Drogues (infinite mass), a reefed stage (eps ≈ 0.44)
then full open, 16 s at 100 Hz, vehicle ≈ 20,000 lbf descending at ≈ 410 ft/s.
``main``: three 116 ft Mains (finite mass, C_k = 1, t_k = 0), two reefed
stages (eps ≈ 0.06, 0.19) then full open, 40 s at 100 Hz, vehicle ≈ 17,500 lbf
at ≈ 200 ft/s. The ranges (see ``_SCENARIOS``) bracket the example bundles'
truth.

Measurement model (that of the example bundles)
-----------------------------------------------
* ``G`` = true G + N(0, 0.03); ``G_sigma`` = 0.03.
* ``qbar`` = true q̄·(1 + N(0, 0.01)); ``qbar_sigma`` = 1 % of the reported value.
* ``airspeed`` = true V + N(0, 0.5 ft/s); ``gamma``, ``altitude``, ``density`` noise-free.
* load cell ``F_<id>`` = F_i / (s(t)·cos θ_i) + N(0, σ), σ = a + b·|reading|,
  a = 40 lbf (Drogue) / 60 lbf (Main), b = 0.01, given per sample in
  ``F_<id>_sigma``; s(t) the friction factor (a constant ``load_scale`` ≈
  1.03–1.10 unless the ``friction_drift`` effect is on).
* fly-out angle ``theta_<id>`` (Mains): 0 until the riser first pulls (F_i > 0),
  then a per-canopy mean (8–15°) plus an Ornstein–Uhlenbeck wander (sd 2°,
  correlation time 2 s), reported with N(0, 0.5°) noise (``theta_<id>_sigma``).
* stated vehicle weight and CDS_V are the truth plus N(0, 100 lbf), N(0, 2 ft²)
  (their stated sigmas); stated stage starts are the true starts plus
  N(0, 0.10 s) (first stage) or N(0, 0.05 s) (later stages).

Hidden effects of the catalogue (the diagnosis' causes), each with a magnitude
-----------------------------------------------------------------------------
:mod:`cpas_bayes.data.synth_effects` (``ALL_EFFECTS``) adds effects outside it, a
form variant of added mass and pairs ``"a+b"``; every function here takes them.

============== ===================================== ==================== =================
effect         what                                  magnitude            drawn range
============== ===================================== ==================== =================
none           —                                     —                    —
added_mass     m_a = k_a·ρ·CDS^(3/2) in the dynamics k_a                  0.2 – 1.0
               (both G and load cells see it)
friction_drift friction factor falls linearly from   s_start − s_end      0.03 – 0.08
               the first stage's middle to the last  (seed: 1.159→1.107)
               stage's middle (load cells only)
sensor_lag     load cells delayed vs the IMU time    lag, s               0.020 – 0.080
               base (load cells only)
canopy_        each canopy's drag area rings after   amplitude A          0.03 – 0.10
breathing      each stage's peak, damped (both       (f: 0.8–2 Hz Drogue,
               channels)                             0.2–0.6 Hz Main; ζ: 0.05–0.3)
============== ===================================== ==================== =================

A magnitude given (``--magnitude``) must be finite and within
``EFFECT_MAGNITUDE_LIMITS``: k_a 0–5, friction fall within ±0.5, lag 0–1 s,
amplitude 0 ≤ A < 1.

Random streams: ``draw_truth`` and ``draw_effect_params`` take their own
generators and ``simulate_test`` draws all measurement noise from its
generator in a fixed order that does not depend on the effect, so the same
seed with and without an effect differs only through the effect.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from cpas_bayes.data.bundle import FlightTest, Parachute, Stage, Vehicle
from cpas_bayes.data.bundle_write import write_bundle
from cpas_bayes.data import synth_effects as fx
from cpas_bayes.physics.effects import first_order_lag, friction_scale, friction_settle, lagged
from cpas_bayes.physics.inflation import n_from_n_p, overinflation_ratio
from cpas_bayes.physics.trajectory import (BreathingParameters, ClusterParameters, SimulationOptions, TrajectoryResult,
                         VehicleProperties, VehicleState0, simulate)
from cpas_bayes.core.units import unit_system

SCENARIOS = ("drogue", "main")
EFFECTS = ("none", "added_mass", "friction_drift", "sensor_lag", "canopy_breathing")  # the catalogue
SAMPLE_INTERVAL = 0.01  # s, 100 Hz as in the example bundles
US = unit_system("US")

# Magnitude ranges of the hidden effects (uniform draws); see the module table.
EFFECT_MAGNITUDE_RANGE = {
    "added_mass": (0.2, 1.0),          # k_a
    "friction_drift": (0.03, 0.08),    # s_start − s_end
    "sensor_lag": (0.020, 0.080),      # s
    "canopy_breathing": (0.03, 0.10),  # amplitude A
}
# What a given magnitude may be: (low, high, low included, high included, what it is). A few times the
# drawn range at most: beyond it the "test" is no parachute test (a lag longer than a stage, an added
# mass many times the canopy's), and a non-finite one would write a bundle no command reads.
EFFECT_MAGNITUDE_LIMITS = {
    "added_mass": (0.0, 5.0, True, True, "k_a"),
    "friction_drift": (-0.5, 0.5, False, False, "the fall of the friction factor"),
    "sensor_lag": (0.0, 1.0, True, True, "the load cells' delay in s"),
    "canopy_breathing": (0.0, 1.0, True, False, "the relative amplitude A"),
}
BREATHING_FREQUENCY_HZ = {"drogue": (0.8, 2.0), "main": (0.2, 0.6)}
BREATHING_DAMPING_RATIO = (0.05, 0.3)

# Measurement model, US units (the bundles' units).
G_SIGMA = 0.03                      # g
QBAR_RELATIVE_SIGMA = 0.01
AIRSPEED_SIGMA_FPS = 0.5
LOAD_CELL_FLOOR_LBF = {"drogue": 40.0, "main": 60.0, "pilot": 40.0, "fbcp": 40.0}  # a of σ = a + b·|F|, by kind
LOAD_CELL_RELATIVE = 0.01                              # b
THETA_SIGMA_DEG = 0.5
THETA_MEAN_DEG = (8.0, 15.0)
THETA_WANDER_SD_DEG = 2.0
THETA_CORRELATION_TIME = 2.0  # s
VEHICLE_WEIGHT_SIGMA_LBF = 100.0
VEHICLE_CDS_SIGMA_FT2 = 2.0
PARACHUTE_WEIGHT_SIGMA_LBF = 2.0
FIRST_START_SIGMA = 0.10  # s
LATER_START_SIGMA = 0.05  # s


@dataclass(frozen=True)
class StageTruth:
    """One stage's true parameters (times in s, dimensionless otherwise)."""

    label: str
    eps: float      # CDS_i / CDS_o
    start: float    # true start time t_i, s
    n_p: float      # fill distance to the peak (Eq. 17); = n when C_k = 1
    expopen: float
    ck: float
    tk: float       # s


@dataclass(frozen=True)
class ChuteTruth:
    """One canopy's truth, SI (m, N, m²)."""

    id: str
    kind: str
    inflation: str
    diameter: float
    weight: float
    cds_o: float
    stages: tuple[StageTruth, ...]


@dataclass(frozen=True)
class SyntheticTruth:
    """Everything a synthetic test is simulated from, SI (m, m/s, rad, N, m²)."""

    scenario: str
    duration: float
    airspeed0: float
    flight_path_angle0: float
    altitude0: float
    vehicle_weight: float
    vehicle_cds: float
    load_scale: float
    chutes: tuple[ChuteTruth, ...]

    def initial_state(self) -> VehicleState0:
        return VehicleState0(self.airspeed0, self.flight_path_angle0, self.altitude0)

    def vehicle(self) -> VehicleProperties:
        return VehicleProperties(self.vehicle_weight, self.vehicle_cds)

    def cluster(self) -> ClusterParameters:
        """The cluster as simulation input, a batch of one."""
        def per_stage(name):
            return np.array([[[getattr(s, name) for s in c.stages] for c in self.chutes]])

        cds_o = np.array([[c.cds_o for c in self.chutes]])
        return ClusterParameters(
            start=per_stage("start"), cds_stage=per_stage("eps") * cds_o[..., None], n_fill=per_stage("n_p"),
            expopen=per_stage("expopen"), ck=per_stage("ck"), tk=per_stage("tk"), cds_o=cds_o,
            diameter=np.array([[c.diameter for c in self.chutes]]), weight=np.array([[c.weight for c in self.chutes]]),
            fill_constant="n_p", ids=tuple(c.id for c in self.chutes))


# ---------------------------------------------------------------------------
# scenario library (US units: ft, ft/s, deg, lbf, ft²; drawn uniformly unless noted)

_SCENARIOS = {
    "drogue": dict(
        duration=16.0, kind="drogue", inflation="infinite", diameter_ft=23.0, ids=("D1", "D2"),
        airspeed0=(380.0, 440.0), gamma0_deg=(-55.0, -40.0), altitude0=(21_000.0, 25_000.0),
        vehicle_weight=(19_000.0, 21_500.0), vehicle_cds=(14.0, 22.0), parachute_weight=(75.0, 90.0),
        cds_o=(240.0, 265.0), load_scale=(1.03, 1.10),
        labels=("reefed 1", "full open"),
        eps=((0.42, 0.46), None),                       # None: full open, eps = 1
        start=((0.9, 1.2), (9.2, 10.2)),                # per canopy
        n_p=((9.0, 13.5), (8.5, 12.0)),
        expopen=((2.0, 2.5), (1.9, 2.5)),
        ck=((1.15, 1.45), (1.10, 1.30)),
        tk=((0.35, 0.70), (0.40, 0.70)),
    ),
    "main": dict(
        duration=40.0, kind="main", inflation="finite", diameter_ft=116.0, ids=("M1", "M2", "M3"),
        airspeed0=(185.0, 215.0), gamma0_deg=(-72.0, -62.0), altitude0=(11_000.0, 12_500.0),
        vehicle_weight=(16_500.0, 18_500.0), vehicle_cds=(34.0, 42.0), parachute_weight=(290.0, 330.0),
        cds_o=(5_350.0, 5_850.0), load_scale=(1.03, 1.10),
        labels=("reefed 1", "reefed 2", "full open"),
        eps=((0.05, 0.07), (0.18, 0.20), None),
        start=((1.1, 1.3), (10.5, 11.3), (20.4, 21.5)),
        n_p=((14.0, 21.0), (8.0, 13.0), (6.0, 7.5)),
        expopen=((1.6, 2.9), (1.6, 2.9), (1.4, 1.8)),
        ck=(None, None, None),                          # finite mass: C_k = 1, t_k = 0
        tk=(None, None, None),
    ),
}


def _scenario(name):
    if name not in _SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; use one of {', '.join(SCENARIOS)}")
    return _SCENARIOS[name]


def draw_truth(scenario: str, rng: np.random.Generator) -> SyntheticTruth:
    """Draw a test's true parameters for ``scenario`` ("drogue" or "main")."""
    spec = _scenario(scenario)

    def uniform(bounds):
        return float(rng.uniform(*bounds))

    airspeed0 = US.si(uniform(spec["airspeed0"]), "speed")
    gamma0 = np.radians(uniform(spec["gamma0_deg"]))
    altitude0 = US.si(uniform(spec["altitude0"]), "length")
    vehicle_weight = US.si(uniform(spec["vehicle_weight"]), "force")
    vehicle_cds = US.si(uniform(spec["vehicle_cds"]), "area")
    load_scale = uniform(spec["load_scale"])
    chutes = []
    for pid in spec["ids"]:
        weight = US.si(uniform(spec["parachute_weight"]), "force")
        cds_o = US.si(uniform(spec["cds_o"]), "area")
        stages = []
        for k, label in enumerate(spec["labels"]):
            finite = spec["ck"][k] is None
            stages.append(StageTruth(
                label=label,
                eps=1.0 if spec["eps"][k] is None else uniform(spec["eps"][k]),
                start=uniform(spec["start"][k]),
                n_p=uniform(spec["n_p"][k]),
                expopen=uniform(spec["expopen"][k]),
                ck=1.0 if finite else uniform(spec["ck"][k]),
                tk=0.0 if finite else uniform(spec["tk"][k])))
        chutes.append(ChuteTruth(id=pid, kind=spec["kind"], inflation=spec["inflation"],
                                 diameter=US.si(spec["diameter_ft"], "length"), weight=weight, cds_o=cds_o,
                                 stages=tuple(stages)))
    return SyntheticTruth(scenario=scenario, duration=spec["duration"], airspeed0=airspeed0, flight_path_angle0=gamma0,
                     altitude0=altitude0, vehicle_weight=vehicle_weight, vehicle_cds=vehicle_cds,
                     load_scale=load_scale, chutes=tuple(chutes))


def draw_effect_params(effect: str, scenario: str, rng: np.random.Generator, magnitude=None) -> dict:
    """Parameters of a hidden effect; ``magnitude`` None draws it from its range.

    Returned dicts hold ``magnitude`` and the effect's own parameters, in
    seconds or dimensionless (the same in every unit system). The friction
    ramp's times are filled in by :func:`simulate_test` from the stage starts.
    A pair ``"a+b"`` takes None or two magnitudes (each None or a number) and
    returns ``{a: params, b: params}``, drawn in that order.
    """
    names = fx.effect_components(effect)
    spec = _scenario(scenario)
    if len(names) == 2:
        sizes = (None, None) if magnitude is None else tuple(magnitude)
        if len(sizes) != 2:
            raise ValueError(f"a pair's magnitude is two values (each may be None), got {magnitude!r}")
        return {n: draw_effect_params(n, scenario, rng, m) for n, m in zip(names, sizes)}
    if effect == "none":
        return {}
    low, high = (EFFECT_MAGNITUDE_RANGE if effect in EFFECT_MAGNITUDE_RANGE else fx.HIDDEN_MAGNITUDE_RANGE)[effect]
    value = float(rng.uniform(low, high)) if magnitude is None else float(magnitude)
    problem = magnitude_problem(effect, value)
    if problem:
        raise ValueError(problem)
    if effect in fx.HIDDEN_EFFECTS:
        return fx.draw_hidden_params(effect, rng, value, len(spec["ids"]), len(spec["labels"]))
    if effect == "added_mass":
        return {"magnitude": value, "k_a": value}
    if effect == "friction_drift":
        return {"magnitude": value}
    if effect == "sensor_lag":
        return {"magnitude": value, "lag": value}
    # canopy_breathing
    return {"magnitude": value, "amplitude": value,
            "frequency_hz": float(rng.uniform(*BREATHING_FREQUENCY_HZ[scenario])),
            "damping_ratio": float(rng.uniform(*BREATHING_DAMPING_RATIO))}


def magnitude_problem(effect: str, value) -> str | None:
    """Why ``value`` cannot be the magnitude of ``effect`` (a sentence), or None."""
    if effect == "none":
        return "a magnitude needs an effect other than 'none'"
    if fx.PAIR_SEPARATOR in effect:
        return fx.pair_magnitude_problem(effect, value, magnitude_problem)
    if effect in fx.HIDDEN_EFFECTS:
        return fx.hidden_magnitude_problem(effect, value)
    return fx.limits_problem(effect, value, EFFECT_MAGNITUDE_LIMITS[effect])


def simulation_options(effect: str, effect_params: dict) -> SimulationOptions:
    """Integration options that put the dynamic effects (added mass in either form, breathing) in the dynamics."""
    parts = fx.effect_parts(effect, effect_params)
    fields = {}
    if "added_mass" in parts:
        fields["added_mass_k"] = parts["added_mass"]["k_a"]
    if "added_mass_form" in parts:
        fields.update(fx.added_mass_form_options(parts["added_mass_form"]))
    if "canopy_breathing" in parts:
        b = parts["canopy_breathing"]
        fields["breathing"] = BreathingParameters(b["amplitude"], b["frequency_hz"], b["damping_ratio"])
    return SimulationOptions(**fields)


def _complete_params(truth: SyntheticTruth, result: TrajectoryResult, parts: dict) -> None:
    """Fill in, in place, what effects take from the truth and the simulation (friction ramp, ceiling, tare)."""
    if "friction_drift" in parts and "scale_start" not in parts["friction_drift"]:
        parts["friction_drift"].update(_friction_ramp(truth, parts["friction_drift"]["magnitude"]))
    settle = parts.get("friction_drift_form")
    if settle is not None and "scale_start" not in settle:
        t_start = float(np.mean([c.stages[0].start for c in truth.chutes]))
        settle.update(scale_start=truth.load_scale + settle["magnitude"], scale_end=truth.load_scale,
                      t_start=t_start, tau=settle["time_constant_fraction"] * (truth.duration - t_start))
    fx.complete_hidden_params(parts, result.load_factor[0].max(), result.peak_tension[0], _stage_starts(truth),
                           [c.id for c in truth.chutes], truth.load_scale, US.si(1.0, "force"))


def _stage_starts(truth):  # (P, K) s
    return np.array([[s.start for s in c.stages] for c in truth.chutes])


def simulate_truth(truth: SyntheticTruth, effect: str = "none", effect_params=None) -> TrajectoryResult:
    """The noise-free trajectory of ``truth`` (with a dynamic effect if any), batch of one."""
    options = replace(simulation_options(effect, effect_params or {}), dt=SAMPLE_INTERVAL)
    return simulate(truth.initial_state(), truth.vehicle(), truth.cluster(), truth.duration, options)


def _friction_ramp(truth: SyntheticTruth, drop: float):
    """Friction factor ramp of ``friction_drift``: from the first stage's middle to the last stage's middle."""
    first_starts = [c.stages[0].start for c in truth.chutes]
    last_starts = [c.stages[-1].start for c in truth.chutes]
    second_starts = [c.stages[1].start for c in truth.chutes] if len(truth.chutes[0].stages) > 1 else [truth.duration]
    t_start = 0.5 * (np.mean(first_starts) + np.mean(second_starts))
    t_end = 0.5 * (np.mean(last_starts) + truth.duration)
    return {"scale_start": truth.load_scale + drop, "scale_end": truth.load_scale,
            "t_start": float(t_start), "t_end": float(t_end)}


def _flyout_angles(tension, time, rng, n_chutes):
    """True fly-out angles (P, T) in deg: 0 until the riser first pulls, then mean + OU wander."""
    dt = time[1] - time[0]
    mean = rng.uniform(*THETA_MEAN_DEG, size=n_chutes)
    decay = np.exp(-dt / THETA_CORRELATION_TIME)
    innovations = rng.normal(0.0, THETA_WANDER_SD_DEG * np.sqrt(1 - decay**2), size=(n_chutes, len(time)))
    wander = np.empty_like(innovations)
    wander[:, 0] = rng.normal(0.0, THETA_WANDER_SD_DEG, size=n_chutes)
    for i in range(1, len(time)):
        wander[:, i] = decay * wander[:, i - 1] + innovations[:, i]
    pulling = np.maximum.accumulate(tension > 0, axis=-1)
    return np.where(pulling, np.clip(mean[:, None] + wander, 1.0, 30.0), 0.0)


def _stated_stages(chute: ChuteTruth, rng):
    stages = []
    for k, s in enumerate(chute.stages):
        sigma = FIRST_START_SIGMA if k == 0 else LATER_START_SIGMA
        stages.append(Stage(label=s.label, start=round(float(s.start + rng.normal(0.0, sigma)), 3),
                            start_sigma=sigma))
    # Noise must not reorder the stated stages (a reader refuses that).
    for k in range(1, len(stages)):
        if stages[k].start <= stages[k - 1].start:
            stages[k] = replace(stages[k], start=stages[k - 1].start + 0.01)
    return tuple(stages)


def load_cell_readings(truth: SyntheticTruth, result: TrajectoryResult, effect: str, effect_params: dict,
                       theta_deg) -> np.ndarray:
    """Noise-free load-cell readings (P, T), N: F_i / (s(t)·cos θ_i), delayed under ``sensor_lag`` (a first-order
    response under ``sensor_lag_form``).

    ``effect_params`` of ``friction_drift`` must hold the ramp, those of ``friction_drift_form`` its settle (see
    :func:`simulate_test`), those of a tare shift its ``shift_lbf``;
    ``theta_deg`` (P, T) or 0. Ringing and a tare shift come before the delay.
    """
    parts = fx.effect_parts(effect, effect_params)
    time = result.time
    if "friction_drift" in parts:
        f = parts["friction_drift"]
        scale = friction_scale(time, f["scale_start"], f["scale_end"], f["t_start"], f["t_end"])
    elif "friction_drift_form" in parts:
        f = parts["friction_drift_form"]
        scale = friction_settle(time, f["scale_start"], f["scale_end"], f["t_start"], f["tau"])
    else:
        scale = np.full(len(time), truth.load_scale)
    reading = result.tension[0] / (scale * np.cos(np.radians(theta_deg)))
    reading = fx.hidden_load_cell_readings(time, reading, _stage_starts(truth), parts, US.si(1.0, "force"))
    if "sensor_lag" in parts:
        reading = lagged(time, reading, parts["sensor_lag"]["lag"])
    elif "sensor_lag_form" in parts:
        reading = first_order_lag(time, reading, parts["sensor_lag_form"]["tau"])
    return reading


@dataclass(frozen=True)
class ChannelDragAreas:
    """What the two reduction channels show without noise, SI (m²)."""

    time: np.ndarray           # (T,) s
    accelerometer: np.ndarray  # (T,) W_T·G/q̄ − CDS_V (Eq. 8), true weights
    load_cells: np.ndarray     # (P, T) (s·F_reading + W_p,i·G)/q̄ (Eq. 11), constant load_scale
    true_cds: np.ndarray       # (P, T) the simulated canopies' drag areas


def noise_free_drag_areas(truth: SyntheticTruth, effect: str, effect_params: dict,
                          result: TrajectoryResult | None = None) -> ChannelDragAreas:
    """Both channels' drag areas as a reducer would compute them, without noise or fly-out angles.

    The load-cell channel is unscaled with the constant ``load_scale`` (what
    a reduction assuming a constant friction factor would do), so a friction
    drift or a lag shows up there and nowhere else. ``result`` may pass a
    trajectory already simulated for this truth and effect.
    """
    parts = fx.effect_parts(effect, effect_params)
    if result is None:
        result = simulate_truth(truth, effect, effect_params)
    _complete_params(truth, result, parts)
    reading = load_cell_readings(truth, result, effect, fx.document_params(effect, parts), 0.0)
    qbar = fx.recorded_air_data(result.time, result.qbar[0], result.airspeed[0], result.density[0], parts)[0]
    load_factor = fx.recorded_load_factor(result.load_factor[0], parts)
    accelerometer = result.total_weight[0] * load_factor / qbar - result.vehicle_cds[0]
    load_cells = (truth.load_scale * reading + result.parachute_weight[0][:, None] * load_factor) / qbar
    return ChannelDragAreas(result.time, accelerometer, load_cells, result.cds[0])


def truth_document(truth: SyntheticTruth, result: TrajectoryResult, effect: str, effect_params: dict,
                   load_scale: float) -> dict:
    """truth.json in the examples' layout, US units."""
    chutes = []
    for j, c in enumerate(truth.chutes):
        stages = []
        for k, s in enumerate(c.stages):
            stages.append({"eps": s.eps, "start": s.start, "n": float(result.timing.n[0, j, k]), "n_p": s.n_p,
                           "expopen": s.expopen, "ck": s.ck, "tk": s.tk,
                           "cds_end": US.from_si(s.eps * c.cds_o, "area")})
        chutes.append({"id": c.id, "cds_o": US.from_si(c.cds_o, "area"), "stages": stages,
                       "peak_load": US.from_si(float(result.peak_tension[0, j]), "force")})
    causes, parts = fx.causes_of(effect), fx.effect_parts(effect, effect_params)
    return {"effect": effect, "effect_params": dict(effect_params), "effects": parts,
            "cause": fx.PAIR_SEPARATOR.join(causes) or "none", "causes": causes, "load_scale": load_scale,
            "vehicle_weight": US.from_si(truth.vehicle_weight, "force"),
            "vehicle_cds": US.from_si(truth.vehicle_cds, "area"),
            "chutes": chutes, "peak_total_load": US.from_si(float(result.peak_total_tension[0]), "force")}


def simulate_test(truth: SyntheticTruth, effect: str, effect_params: dict, rng: np.random.Generator,
                  name: str | None = None) -> tuple[FlightTest, dict]:
    """Simulate ``truth`` with ``effect`` and the measurement model; return the test and truth.json's dict.

    ``rng`` supplies every measurement-noise draw, in an order that does not
    depend on ``effect``.
    """
    parts = fx.effect_parts(effect, effect_params)
    result = simulate_truth(truth, effect, effect_params)
    _complete_params(truth, result, parts)
    effect_params = fx.document_params(effect, parts)
    time = result.time
    n = len(time)
    # Fly-out angles are measured on the Mains (photogrammetry of the big canopies).
    has_angles = np.array([c.kind == "main" for c in truth.chutes])

    # Noise draws, fixed order: stated metadata, fly-out angles, IMU/air data, load cells.
    stated_weight = truth.vehicle_weight + US.si(rng.normal(0.0, VEHICLE_WEIGHT_SIGMA_LBF), "force")
    stated_cds = max(truth.vehicle_cds + US.si(rng.normal(0.0, VEHICLE_CDS_SIGMA_FT2), "area"), 0.0)
    stated_stages = [_stated_stages(c, rng) for c in truth.chutes]
    theta_true = (_flyout_angles(result.tension[0], time, rng, len(truth.chutes)) * has_angles[:, None]
                  if has_angles.any() else np.zeros((len(truth.chutes), n)))
    theta_noise = rng.normal(0.0, THETA_SIGMA_DEG, size=theta_true.shape)
    g_noise = rng.normal(0.0, G_SIGMA, size=n)
    qbar_noise = rng.normal(0.0, QBAR_RELATIVE_SIGMA, size=n)
    airspeed_noise = US.si(rng.normal(0.0, AIRSPEED_SIGMA_FPS, size=n), "speed")
    load_noise = rng.normal(0.0, 1.0, size=(len(truth.chutes), n))

    air_qbar, air_speed = fx.recorded_air_data(time, result.qbar[0], result.airspeed[0], result.density[0], parts)
    qbar = air_qbar * (1.0 + qbar_noise)
    data = {"time": time, "G": fx.recorded_load_factor(result.load_factor[0] + g_noise, parts),
            "G_sigma": np.full(n, G_SIGMA), "qbar": qbar, "qbar_sigma": QBAR_RELATIVE_SIGMA * np.abs(qbar),
            "airspeed": air_speed + airspeed_noise,
            "gamma": np.degrees(result.flight_path_angle[0]),
            "density": result.density[0], "altitude": result.altitude[0]}

    reading = load_cell_readings(truth, result, effect, effect_params, theta_true)
    floor = US.si(np.array([LOAD_CELL_FLOOR_LBF[c.kind] for c in truth.chutes]), "force")
    load_sigma = floor[:, None] + LOAD_CELL_RELATIVE * np.abs(reading)
    measured = reading + load_sigma * load_noise

    parachutes = []
    for j, c in enumerate(truth.chutes):
        data[f"F_{c.id}"] = measured[j]
        data[f"F_{c.id}_sigma"] = load_sigma[j]
        if has_angles[j]:
            pulling = theta_true[j] > 0
            data[f"theta_{c.id}"] = np.where(pulling, theta_true[j] + theta_noise[j], 0.0)
            data[f"theta_{c.id}_sigma"] = np.where(pulling, THETA_SIGMA_DEG, 0.0)
        parachutes.append(Parachute(
            id=c.id, kind=c.kind, inflation=c.inflation, diameter=c.diameter, weight=c.weight,
            weight_sigma=US.si(PARACHUTE_WEIGHT_SIGMA_LBF, "force"), stages=stated_stages[j],
            load_cell=f"F_{c.id}", flyout_angle=f"theta_{c.id}" if has_angles[j] else None))

    vehicle = Vehicle(weight=stated_weight, weight_sigma=US.si(VEHICLE_WEIGHT_SIGMA_LBF, "force"),
                      cds=stated_cds, cds_sigma=US.si(VEHICLE_CDS_SIGMA_FT2, "area"))
    test = FlightTest(name=name or f"SYN-{truth.scenario}-{effect}", phase=truth.scenario, units=US, vehicle=vehicle,
                      parachutes=tuple(parachutes), data=pd.DataFrame(data))
    load_scale = parts["friction_drift"]["scale_end"] if "friction_drift" in parts else truth.load_scale
    return test, truth_document(truth, result, effect, effect_params, load_scale)


def random_streams(seed: int):
    """Independent generators for the truth, the effect's magnitude and the noise of one seed."""
    truth_seq, effect_seq, noise_seq = np.random.SeedSequence(seed).spawn(3)
    return (np.random.default_rng(truth_seq), np.random.default_rng(effect_seq),
            np.random.default_rng(noise_seq))


def synthesize(scenario: str, effect: str, seed: int, magnitude=None, name: str | None = None):
    """Draw and simulate one synthetic test from a seed: (FlightTest, truth dict)."""
    truth_rng, effect_rng, noise_rng = random_streams(seed)
    truth = draw_truth(scenario, truth_rng)
    params = draw_effect_params(effect, scenario, effect_rng, magnitude)
    return simulate_test(truth, effect, params, noise_rng, name=name or f"SYN-{scenario}-{effect}-{seed}")


def write_synthetic(scenario: str, effect: str, seed: int, out, magnitude=None) -> Path:
    """``cpas-bayes synth``: simulate and write the bundle with its truth.json; returns the folder."""
    test, truth = synthesize(scenario, effect, seed, magnitude)
    return write_bundle(test, Path(out), extra_files={"truth.json": json.dumps(truth, indent=1) + "\n"})


def truth_from_bundle(test: FlightTest, truth_doc: dict) -> SyntheticTruth:
    """A :class:`SyntheticTruth` from a bundle and its truth.json (for tests and recovery studies).

    The initial state is the first data row (airspeed, gamma, altitude); the
    canopies' diameters and weights come from test.toml; everything else from
    truth.json (in the bundle's units).
    """
    u = test.units
    first = test.data.iloc[0]
    chutes = []
    for c in truth_doc["chutes"]:
        p = test.parachute(c["id"])
        stages = tuple(StageTruth(label=stage.label, eps=s["eps"], start=s["start"], n_p=s["n_p"],
                                  expopen=s["expopen"], ck=s["ck"], tk=s["tk"])
                       for stage, s in zip(p.stages, c["stages"]))
        chutes.append(ChuteTruth(id=p.id, kind=p.kind, inflation=p.inflation, diameter=p.diameter,
                                 weight=p.weight, cds_o=u.si(c["cds_o"], "area"), stages=stages))
    return SyntheticTruth(scenario=test.phase, duration=test.duration, airspeed0=float(first["airspeed"]),
                     flight_path_angle0=float(np.radians(first["gamma"])), altitude0=float(first["altitude"]),
                     vehicle_weight=u.si(truth_doc["vehicle_weight"], "force"),
                     vehicle_cds=u.si(truth_doc["vehicle_cds"], "area"),
                     load_scale=float(truth_doc["load_scale"]), chutes=tuple(chutes))


def n_p_consistency(truth_doc: dict) -> float:
    """Largest relative mismatch of n = n_p·S^(−1/expopen) (Eq. 18) over truth.json's stages.

    S uses the drag area held at the stage start; for a stage that starts
    after the previous one has settled that is the previous stage's cds_end.
    """
    worst = 0.0
    for c in truth_doc["chutes"]:
        held = 0.0
        for s in c["stages"]:
            ratio = overinflation_ratio(s["ck"], s["cds_end"], held)
            n = float(n_from_n_p(s["n_p"], ratio, s["expopen"]))
            worst = max(worst, abs(n - s["n"]) / s["n"])
            held = s["cds_end"]
    return worst


def truth_parameter_values(test: FlightTest, truth_doc: dict) -> dict:
    """The true value of every baseline model parameter, by model parameter name, in SI.

    Maps truth.json (bundle units) onto :class:`cpas_bayes.stats.model.TestModel`'s
    names: ``<id>.cds_o``, ``<id>.s<k>.{start,n_p,n,expopen,ck,tk,eps}``,
    ``vehicle_weight``, ``vehicle_cds``, ``load_scale``. Used to check recovery.
    """
    u = test.units
    out = {"vehicle_weight": u.si(truth_doc["vehicle_weight"], "force"),
           "vehicle_cds": u.si(truth_doc["vehicle_cds"], "area"),
           "load_scale": float(truth_doc["load_scale"])}
    for c in truth_doc["chutes"]:
        out[f"{c['id']}.cds_o"] = u.si(c["cds_o"], "area")
        for k, s in enumerate(c["stages"]):
            for name in ("start", "n_p", "n", "expopen", "ck", "tk", "eps"):
                out[f"{c['id']}.s{k + 1}.{name}"] = float(s[name])
    return out

"""Hidden effects outside the diagnosis' catalogue, form variants, and pairs, for synthetic tests.

:mod:`cpas_bayes.data.synth` simulates a test with at most one hidden effect
from its catalogue (``EFFECTS``: none, added_mass, friction_drift,
sensor_lag, canopy_breathing), the causes the diagnosis has candidate terms
for. This module adds what tests that diagnosis: effects it has no term for
(the right answer is "unexplained"), a catalogued cause in a form its term
was not written for, and two effects at once (``"a+b"``). ``synthesize``,
``write_synthetic`` and ``cpas-bayes synth --effect`` accept every name in
``ALL_EFFECTS`` and pairs of them.

Out-of-catalogue effects (cause "unexplained"); instrument effects, applied to
what the sensors record from the noise-free simulation, the dynamics untouched
---------------------------------------------------------------------------------
====================== ====================================== =================== ============ ==========
effect                 what (equations)                       channels changed    magnitude    drawn
====================== ====================================== =================== ============ ==========
pitot_lag              pneumatic lag of the pitot-static      qbar, qbar_sigma,   τ, s         0.15 – 0.45
                       line: τ·dq̄_m/dt = q̄ − q̄_m (effects    airspeed            (limits
                       Eq. I1), V_m = sqrt(2·q̄_m/ρ); then                         (0, 2])
                       the usual noise
accelerometer_         the accelerometer saturates:           G                   clipped      0.15 – 0.30
clipping               G_m = min(G + noise, G_c),                                 fraction c   (limits
                       G_c = (1 − c)·max G (noise-free peak)                      of the peak  (0, 0.75])
riser_ringing          elastic load path rings after each     load cells F_i,     amplitude A  0.15 – 0.30
                       of its canopy's stage starts t_k:      F_i_sigma                        (limits
                       F_m = F·[1 + A·Σ_k e^(−ζωτ_k)·                                          (0, 0.5])
                       sin(ω·sqrt(1−ζ²)·τ_k)] (Eq. I2),
                       f = 3–8 Hz, ζ = 0.03–0.10 (drawn)
load_cell_tare_shift   one cell's zero steps by ±c·(its peak  one load cell and   c, fraction  0.05 – 0.10
                       reading) at the true start of one of   its sigma           of the peak  (limits
                       its canopy's later stages (cell, stage,                                 (0, 0.5])
                       sign drawn)
====================== ====================================== =================== ============ ==========

Why realistic: pitot-static tubing on a drop-test vehicle gives lags of a
tenth to a few tenths of a second (longer at altitude, where the air is
thin); an accelerometer ranged for the expected load saturates when a
canopy overshoots it; risers, links and the load cell's own structure are
springs that ring at a few Hz after a snatch (line stretch, disreef); a
load cell's zero can jump under a shock load (a slipped mount, a connector).
Distinct from the catalogue: pitot_lag shows in both reduction channels
(both divide by q̄) and its error grows with dq̄/dt, whereas sensor_lag
shifts the load cells alone by a pure delay; clipping is flat tops in G
alone; ringing is load cells alone, fast (3–8 Hz) and starts at the stage
start, whereas breathing changes the drag area (both channels, 0.2–2 Hz,
after the peak); a tare shift is an additive step in one cell, friction
drift a slow multiplicative ramp in all.

Strength at the low end of each range (noise-free change / the channel's
σ, seeds 1–3): pitot_lag 0.15 s, airspeed ≈ 10–15σ and q̄ ≈ 3–7σ over
hundreds of samples of the deceleration; clipping 15 %, G ≈ 11–14σ on
30–90 samples; ringing 15 %, ≈ 6–10σ peaks at each disreef; tare shift 5 %,
≈ 6–10σ on every sample after it (≥ 500 lbf against σ ≈ 60–150 lbf).

Form variants (causes "added_mass", "friction_drift", "sensor_lag")
-------------------------------------------------------------------
=================== ============================================== ========== ============ ==============
effect              what                                           magnitude  drawn        form, drawn
=================== ============================================== ========== ============ ==============
added_mass_form     m_a = k_a·ρ·CDS_o^(3/2)·(CDS/CDS_o)^p (effects k_a        0.2 – 1.0    p 1.25 – 1.75,
                    Eq. A1') reached through a first-order lag τ_m            (limits      τ_m 0.05 –
                    (``SimulationOptions.added_mass_exponent`` and            [0, 5])      0.20 s
                    ``added_mass_lag``), in the dynamics
friction_drift_form friction factor settling exponentially from    s_start −  0.03 – 0.08  τ 0.10 – 0.35
                    s_start to s_end after the first stage start   s_end      (limits      of the record
                    (``effects.friction_settle``), not a ramp                 ±0.5)        after t_start
sensor_lag_form     load cells seen through a first-order response τ, s       0.02 – 0.08  —
                    (``effects.first_order_lag``), not a pure                 (limits
                    delay                                                     (0, 1])
=================== ============================================== ========== ============ ==============

With p = 1.5 and τ_m = 0 the first is ``added_mass`` exactly; the
diagnosis fits p and τ_m. The second is no ramp at all, and the
diagnosis' ``friction_drift`` is a ramp over the whole record. The third is
no delay: the diagnosis' ``sensor_lag`` fits a delay and a first-order
response together. The causes are catalogued, these forms are not.

Pairs
-----
``"a+b"`` simulates two different effects at once, each with its own
magnitude (``magnitude`` None, or a pair of values each None or a number).
"none" does not pair, nor do two forms of one cause (added mass, friction
drift, sensor lag). Dynamic effects (added mass in either form, breathing)
enter the dynamics together; on a load cell the reading is F/(s·cos θ), then
ringing, then a tare shift, then the sensor_lag delay (or the
sensor_lag_form response).

Truth document keys (truth.json, besides the examples' layout)
--------------------------------------------------------------
``effect`` the name as given ("a+b" for a pair); ``effect_params`` the
effect's parameters (for a pair: by component name); ``effects`` always by
component name ({} for none); ``causes`` each component's catalogued cause
("unexplained" for out-of-catalogue effects; [] for none); ``cause`` the
single cause ("none" for none; a pair's causes joined by "+").
"""

from __future__ import annotations

import math

import numpy as np

from cpas_bayes.physics.effects import first_order_lag, load_path_ringing

CATALOGUED_EFFECTS = ("added_mass", "friction_drift", "sensor_lag", "canopy_breathing")
OUT_OF_CATALOGUE = ("pitot_lag", "accelerometer_clipping", "riser_ringing", "load_cell_tare_shift")
FORM_VARIANTS = {"added_mass_form": "added_mass", "friction_drift_form": "friction_drift",
                 "sensor_lag_form": "sensor_lag"}   # effect → its catalogued cause
HIDDEN_EFFECTS = OUT_OF_CATALOGUE + tuple(FORM_VARIANTS)
ALL_EFFECTS = ("none",) + CATALOGUED_EFFECTS + HIDDEN_EFFECTS
DYNAMIC_EFFECTS = ("added_mass", "canopy_breathing", "added_mass_form")
PAIR_SEPARATOR = "+"
UNEXPLAINED = "unexplained"

HIDDEN_MAGNITUDE_RANGE = {
    "pitot_lag": (0.15, 0.45),               # τ, s
    "accelerometer_clipping": (0.15, 0.30),  # clipped fraction c of the peak G
    "riser_ringing": (0.15, 0.30),           # relative amplitude A
    "load_cell_tare_shift": (0.05, 0.10),    # shift / the cell's peak reading
    "added_mass_form": (0.2, 1.0),           # k_a
    "friction_drift_form": (0.03, 0.08),     # s_start − s_end
    "sensor_lag_form": (0.02, 0.08),         # τ, s
}
# (low, high, low included, high included, what it is), as synth.EFFECT_MAGNITUDE_LIMITS.
HIDDEN_MAGNITUDE_LIMITS = {
    "pitot_lag": (0.0, 2.0, False, True, "the air data's lag time constant in s"),
    "accelerometer_clipping": (0.0, 0.75, False, True, "the fraction of the peak G clipped off"),
    "riser_ringing": (0.0, 0.5, False, True, "the ringing's relative amplitude A"),
    "load_cell_tare_shift": (0.0, 0.5, False, True, "the zero shift as a fraction of the cell's peak"),
    "added_mass_form": (0.0, 5.0, True, True, "k_a"),
    "friction_drift_form": (-0.5, 0.5, False, False, "the fall of the friction factor"),
    "sensor_lag_form": (0.0, 1.0, False, True, "the load cells' response time constant in s"),
}
RINGING_FREQUENCY_HZ = (3.0, 8.0)
RINGING_DAMPING_RATIO = (0.03, 0.10)  # lightly damped: webbing, links, the cell's own structure
ADDED_MASS_FORM_EXPONENT = (1.25, 1.75)
ADDED_MASS_FORM_LAG = (0.05, 0.20)  # s
FRICTION_FORM_TIME_CONSTANT = (0.10, 0.35)  # of the record after the first stage start


def effect_components(effect: str) -> tuple[str, ...]:
    """The effects named by ``effect`` ("a" or "a+b"), checked; ("none",) for none."""
    if not isinstance(effect, str):
        raise ValueError(f"an effect is a name, got {effect!r}")
    names = tuple(effect.split(PAIR_SEPARATOR))
    unknown = [n for n in names if n not in ALL_EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect {unknown[0]!r}; use one of {', '.join(ALL_EFFECTS)}, "
                         f"or two joined by '{PAIR_SEPARATOR}'")
    if len(names) > 2:
        raise ValueError(f"at most two effects at once, got {effect!r}")
    if len(names) == 2:
        if "none" in names:
            raise ValueError(f"'none' does not pair with an effect: {effect!r}")
        if names[0] == names[1]:
            raise ValueError(f"a pair needs two different effects: {effect!r}")
        causes = [cause_of(n) for n in names]
        if causes[0] == causes[1] != UNEXPLAINED:
            raise ValueError(f"two forms of {causes[0].replace('_', ' ')} do not pair: {effect!r}")
    return names


def is_pair(effect: str) -> bool:
    return len(effect_components(effect)) == 2


def effect_parts(effect: str, effect_params) -> dict:
    """``{component name: its params (a copy)}`` of an effect or a pair; {} for none.

    ``effect_params`` is one effect's params, or a pair's by component name.
    """
    names = effect_components(effect)
    if names == ("none",):
        return {}
    params = effect_params or {}
    return {n: dict(params.get(n, {}) if len(names) == 2 else params) for n in names}


def document_params(effect: str, parts: dict) -> dict:
    """``effect_params`` of the truth document from the parts: a pair's by component, one effect's own."""
    return parts if is_pair(effect) else parts.get(effect, {})


def pair_magnitude_problem(effect: str, value, problem_of) -> str | None:
    """Why ``value`` cannot be a pair's magnitudes (two, each None or checked by ``problem_of(name, v)``)."""
    values = value if isinstance(value, (list, tuple)) else ()
    if len(values) != 2:
        return f"a pair's magnitude is two values (each may be None), got {value!r}"
    problems = [problem_of(n, v) for n, v in zip(effect_components(effect), values) if v is not None]
    return next((p for p in problems if p), None)


def cause_of(name: str) -> str:
    """The catalogued cause of one effect: itself, added_mass for its form variant, or "unexplained"."""
    if name in FORM_VARIANTS:
        return FORM_VARIANTS[name]
    if name in OUT_OF_CATALOGUE:
        return UNEXPLAINED
    if name == "none" or name in CATALOGUED_EFFECTS:
        return name
    raise ValueError(f"unknown effect {name!r}")


def causes_of(effect: str) -> list[str]:
    """Each component's catalogued cause, in order; [] for none."""
    return [cause_of(n) for n in effect_components(effect) if n != "none"]


def hidden_magnitude_problem(effect: str, value) -> str | None:
    """Why ``value`` cannot be the magnitude of the hidden ``effect`` (a sentence), or None."""
    return limits_problem(effect, value, HIDDEN_MAGNITUDE_LIMITS[effect])


def limits_problem(effect: str, value, limits) -> str | None:
    """Why ``value`` is outside ``limits`` = (low, high, low included, high included, what it is), or None."""
    low, high, low_in, high_in, what = limits
    try:
        value = float(value)
    except (TypeError, ValueError):
        return f"{effect} magnitude ({what}) must be a number, got {value!r}"
    inside = (value >= low if low_in else value > low) and (value <= high if high_in else value < high)
    if not math.isfinite(value) or not inside:
        return (f"{effect} magnitude ({what}) must be in {'[' if low_in else '('}{low:g}, {high:g}"
                f"{']' if high_in else ')'}, got {value:g}")
    return None


def draw_hidden_params(effect: str, rng: np.random.Generator, value: float, n_chutes: int, n_stages: int) -> dict:
    """Parameters of a hidden effect of magnitude ``value`` (already checked); the rest drawn from ``rng``.

    Quantities that need the simulation (the clipping ceiling, the tare
    shift in lbf and its time) are filled in by :func:`complete_hidden_params`.
    """
    if effect == "pitot_lag":
        return {"magnitude": value, "tau": value}
    if effect == "accelerometer_clipping":
        return {"magnitude": value, "ceiling_fraction": 1.0 - value}
    if effect == "riser_ringing":
        return {"magnitude": value, "amplitude": value,
                "frequency_hz": float(rng.uniform(*RINGING_FREQUENCY_HZ)),
                "damping_ratio": float(rng.uniform(*RINGING_DAMPING_RATIO))}
    if effect == "load_cell_tare_shift":
        return {"magnitude": value, "cell_index": int(rng.integers(n_chutes)),
                "stage_index": int(rng.integers(1, n_stages)) if n_stages > 1 else 0,
                "sign": float(rng.choice([-1.0, 1.0]))}
    if effect == "added_mass_form":
        return {"magnitude": value, "k_a": value, "exponent": float(rng.uniform(*ADDED_MASS_FORM_EXPONENT)),
                "mass_lag": float(rng.uniform(*ADDED_MASS_FORM_LAG))}
    if effect == "friction_drift_form":
        return {"magnitude": value, "time_constant_fraction": float(rng.uniform(*FRICTION_FORM_TIME_CONSTANT))}
    if effect == "sensor_lag_form":
        return {"magnitude": value, "tau": value}
    raise ValueError(f"{effect!r} is not a hidden effect; use one of {', '.join(HIDDEN_EFFECTS)}")


def complete_hidden_params(components: dict, peak_load_factor: float, peak_tension, stage_starts, ids,
                           load_scale: float, lbf: float) -> None:
    """Fill in, in place, what the hidden effects take from the noise-free simulation.

    ``peak_tension`` (P,) N and ``stage_starts`` (P, K) s of the truth; ``lbf``
    the newton value of one lbf (the shift is recorded in lbf, the bundles' unit).
    """
    clipping = components.get("accelerometer_clipping")
    if clipping is not None and "ceiling_g" not in clipping:
        clipping["ceiling_g"] = clipping["ceiling_fraction"] * float(peak_load_factor)
    tare = components.get("load_cell_tare_shift")
    if tare is not None and "shift_lbf" not in tare:
        j, k = tare["cell_index"], tare["stage_index"]
        tare.update(cell=ids[j], time=float(stage_starts[j][k]),
                    shift_lbf=tare["sign"] * tare["magnitude"] * float(peak_tension[j]) / load_scale / lbf)


def added_mass_form_options(params: dict) -> dict:
    """``SimulationOptions`` fields of added_mass_form."""
    return {"added_mass_k": params["k_a"], "added_mass_exponent": params["exponent"],
            "added_mass_lag": params["mass_lag"]}


def recorded_air_data(time, qbar, airspeed, density, components: dict):
    """Noise-free q̄ and V as the air-data system records them (lagged under pitot_lag), SI."""
    lag = components.get("pitot_lag")
    if lag is None:
        return qbar, airspeed
    lagged_qbar = first_order_lag(time, qbar, lag["tau"])
    return lagged_qbar, np.sqrt(2.0 * np.clip(lagged_qbar, 0.0, None) / density)


def recorded_load_factor(load_factor, components: dict):
    """G as the accelerometer records it (noisy or not): flat tops at the ceiling under clipping."""
    clipping = components.get("accelerometer_clipping")
    return load_factor if clipping is None else np.minimum(load_factor, clipping["ceiling_g"])


def hidden_load_cell_readings(time, reading, stage_starts, components: dict, lbf: float):
    """Load-cell readings (P, T), N, with riser ringing then a tare shift applied."""
    ringing = components.get("riser_ringing")
    if ringing is not None:
        reading = reading * load_path_ringing(time, np.asarray(stage_starts, float), ringing["amplitude"],
                                               ringing["frequency_hz"], ringing["damping_ratio"])
    tare = components.get("load_cell_tare_shift")
    if tare is not None:
        reading = np.array(reading, float)
        j = tare["cell_index"]
        reading[j] = reading[j] + np.where(np.asarray(time) >= tare["time"], tare["shift_lbf"] * lbf, 0.0)
    return reading

"""Hidden effects of the synthetic logger tests (:mod:`cpas_bayes.data.synth_logger`).

``canopy_breathing``: every canopy's drag area is multiplied after its current
stage's peak by :func:`cpas_bayes.physics.effects.breathing_factor` (amplitude A,
frequency f, damping ratio ζ; one set for the test), inside the integration, so
the trajectory, the accelerometer and the receiver all see it. That is the form
of the diagnosis's ``canopy_breathing`` term, and of the breathing in
:mod:`cpas_bayes.data.synth`.

``added_mass``: each canopy carries the air mass m_a = k_a·ρ·CDS^(3/2) (the
seed's Eq. A1, no lag), and the flight's momentum balance along the air
velocity is Eq. A3, (M + m_a)·dV/dt = −D − M·g·sin γ − V·dm_a/dt, integrated in
3-D (the part across the air velocity is as without it); the accelerometer
senses (D + V·dm_a/dt + m_a·dV/dt)/M. dCDS/dt is the stage law's central
difference over ±0.1 ms. k_a ~ U(0.2, 1.0) or the magnitude given.

Draws: A ~ U(0.03, 0.10) (or the magnitude given), ζ ~ U(0.05, 0.3), f ~ U over
the kind's range: Drogues 0.8–2 Hz, Mains of the Main scenario 0.2–0.6 Hz, and
for the single canopy of ``logger-drop`` f·D_o in 8–12 m/s (breathing scales
roughly as 1/D_o). They come from their own random stream, so a test with an
effect has the same truth and noise draws as the same seed without one.
"""

from __future__ import annotations

import numpy as np

LOGGER_EFFECTS = ("none", "canopy_breathing", "added_mass")
ADDED_MASS_K = (0.2, 1.0)
ADDED_MASS_LIMITS = (0.0, 5.0)     # k_a a magnitude may give, as synth's
BREATHING_AMPLITUDE = (0.03, 0.10)
BREATHING_DAMPING = (0.05, 0.3)
BREATHING_HZ = {"logger-drogue": (0.8, 2.0), "logger-main": (0.2, 0.6)}
BREATHING_HZ_TIMES_DIAMETER = (8.0, 12.0)     # m/s, where the scenario has no range of its own
NO_BREATHING = (0.0, 1.0, 0.0)


def effect_stream(seed: int) -> np.random.Generator:
    """The effect's generator of ``seed``: the third child of its SeedSequence (the truth and noise
    streams are the first two)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2,)))


def draw_breathing(effect: str, scenario: str, diameter: float, rng: np.random.Generator, magnitude=None):
    """(amplitude, frequency Hz, damping ratio) of ``effect`` (:data:`NO_BREATHING` for "none")."""
    if effect not in LOGGER_EFFECTS:
        raise ValueError(f"unknown logger effect {effect!r}; use one of {', '.join(LOGGER_EFFECTS)}")
    if effect == "none":
        if magnitude is not None:
            raise ValueError("a magnitude needs an effect other than 'none'")
        return NO_BREATHING
    if effect != "canopy_breathing":
        return NO_BREATHING
    amplitude = float(rng.uniform(*BREATHING_AMPLITUDE)) if magnitude is None else float(magnitude)
    if not 0.0 < amplitude < 1.0:
        raise ValueError(f"the breathing amplitude must lie in (0, 1), got {amplitude}")
    low, high = BREATHING_HZ.get(scenario, tuple(v / diameter for v in BREATHING_HZ_TIMES_DIAMETER))
    frequency = float(rng.uniform(low, high))
    return amplitude, frequency, float(rng.uniform(*BREATHING_DAMPING))


def draw_added_mass(effect: str, rng: np.random.Generator, magnitude=None) -> float:
    """k_a of ``effect`` (0 unless it is ``added_mass``)."""
    if effect != "added_mass":
        return 0.0
    k_a = float(rng.uniform(*ADDED_MASS_K)) if magnitude is None else float(magnitude)
    low, high = ADDED_MASS_LIMITS
    if not low < k_a <= high:
        raise ValueError(f"the added-mass k_a must lie in ({low:g}, {high:g}], got {k_a}")
    return k_a


def effect_fields(breathing, added_mass=0.0) -> dict:
    """truth.json's effect keys (the layout of :mod:`cpas_bayes.data.synth`'s truth)."""
    if added_mass > 0.0:
        params = {"magnitude": added_mass, "k_a": added_mass}
        return {"effect": "added_mass", "effect_params": params, "effects": {"added_mass": params},
                "cause": "added_mass", "causes": ["added_mass"]}
    amplitude, frequency, damping = breathing
    if amplitude == 0.0:
        return {"effect": "none", "effect_params": {}, "effects": {}, "cause": "none", "causes": []}
    params = {"magnitude": amplitude, "amplitude": amplitude, "frequency_hz": frequency, "damping_ratio": damping}
    return {"effect": "canopy_breathing", "effect_params": params, "effects": {"canopy_breathing": params},
            "cause": "canopy_breathing", "causes": ["canopy_breathing"]}

"""Hidden effects of the synthetic logger tests (:mod:`cpas_bayes.data.synth_logger`).

One effect so far, ``canopy_breathing``: every canopy's drag area is multiplied
after its current stage's peak by :func:`cpas_bayes.physics.effects.breathing_factor`
(amplitude A, frequency f, damping ratio ζ; one set for the test), inside the
integration, so the trajectory, the accelerometer and the receiver all see it.
That is the form of the diagnosis's ``canopy_breathing`` term, and of the
breathing in :mod:`cpas_bayes.data.synth`.

Draws: A ~ U(0.03, 0.10) (or the magnitude given), ζ ~ U(0.05, 0.3), f ~ U over
the kind's range: Drogues 0.8–2 Hz, Mains of the Main scenario 0.2–0.6 Hz, and
for the single canopy of ``logger-drop`` f·D_o in 8–12 m/s (breathing scales
roughly as 1/D_o). They come from their own random stream, so a test with an
effect has the same truth and noise draws as the same seed without one.
"""

from __future__ import annotations

import numpy as np

LOGGER_EFFECTS = ("none", "canopy_breathing")
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
    amplitude = float(rng.uniform(*BREATHING_AMPLITUDE)) if magnitude is None else float(magnitude)
    if not 0.0 < amplitude < 1.0:
        raise ValueError(f"the breathing amplitude must lie in (0, 1), got {amplitude}")
    low, high = BREATHING_HZ.get(scenario, tuple(v / diameter for v in BREATHING_HZ_TIMES_DIAMETER))
    frequency = float(rng.uniform(low, high))
    return amplitude, frequency, float(rng.uniform(*BREATHING_DAMPING))


def effect_fields(breathing) -> dict:
    """truth.json's effect keys (the layout of :mod:`cpas_bayes.data.synth`'s truth)."""
    amplitude, frequency, damping = breathing
    if amplitude == 0.0:
        return {"effect": "none", "effect_params": {}, "effects": {}, "cause": "none", "causes": []}
    params = {"magnitude": amplitude, "amplitude": amplitude, "frequency_hz": frequency, "damping_ratio": damping}
    return {"effect": "canopy_breathing", "effect_params": params, "effects": {"canopy_breathing": params},
            "cause": "canopy_breathing", "causes": ["canopy_breathing"]}

"""Terms added to the baseline model to explain what it gets wrong.

Each extension is a :class:`cpas_bayes.stats.model.Extension`: it declares its
parameters with priors and plugs into one hook of the model's pipeline, so the
baseline is never copied. The physics is the same as the simulator's
(:mod:`cpas_bayes.physics.effects`), so a fitted term means what a simulated one did.

``added_mass`` — enclosed + apparent air mass (both channels)
    m_a,i = k_a·ρ·CDS_o,i^(3/2)·(CDS_i/CDS_o,i)^p reached through a
    first-order lag τ_m (effects Eq. A1', A5); both reduction channels then
    show CDS_i + d(m_a,i·V)/dt / q̄ with d(m_a·V)/dt = ṁ_a·V + m_a·dV/dt
    (Eq. A1–A4). p = 3/2 and τ_m = 0 is Eq. A1. The form parameters are fitted
    because the cause is physical but its form is not known: a filling
    canopy is not geometrically similar to the open one (p), and the flow
    that carries the air takes a moment to establish (τ_m); a term of one
    fixed form lost to the generic discrepancy on an added mass with a lag
    of 0.1 s. V is the measured (smoothed) airspeed; dV/dt comes from the
    momentum balance Eq. A3 with the model's drag areas and added mass;
    dCDS_i/dt is differenced from the stage law. Priors: k_a lognormal,
    median 0.3, factor-e spread, 0.005–5; p ~ N(1.5, 0.25) on [1, 2.25];
    τ_m ~ half-normal, scale 0.25 s, below 1 s (τ_m = 0 is a physical
    limit, not an edge of the prior).

``friction_drift`` — load-cell friction factor changing in time (load cells only)
    s(t) = s + Δs·(clip((t − t_a)/(t_b − t_a), 0, 1) − ½), t_a the first
    nominal stage start, t_b the end of the record; ``load_scale`` stays the
    mean factor. Prior: Δs ~ N(0, 0.08) (the seed's Drogues moved by 0.05).

``sensor_lag`` — load cells behind the IMU time base (load cells only)
    The load cell at t shows the riser force delayed by L − r and seen through
    a first-order response of time constant r: ∫₀^∞ F(t − (L − r) − r·s)·e^(−s) ds
    (four Gauss–Laguerre nodes), whose mean delay is L; r = 0 is a pure delay.
    A real cell and its conditioning filter respond in the first-order way;
    a pure delay is a clock offset. Priors: L ~ N(0, 0.1 s) truncated to
    [−0.2, 0.3] s; r ~ half-normal, scale 0.05 s, below 0.3 s (r = 0 is a
    physical limit, not an edge of the prior).

``canopy_breathing`` — oscillation of each canopy after its peak (both)
    CDS_i(t)·[1 + A_k·exp(−ζωτ)·(cos φ_i·sin(ω_d·τ) + sin φ_i·(cos(ω_d·τ) − 1))],
    τ the time since the current stage's peak drag area, ω = 2πf,
    ω_d = ω·sqrt(1−ζ²); φ_i canopy i's phase at its peak; A_k = A in the last
    (full-open) stage and s·A in the reefed ones
    (:func:`~cpas_bayes.physics.effects.breathing_drag_area`). Priors: A ~ U(0, 0.25);
    f lognormal around 1.2 Hz (Drogue) or 0.35 Hz (Main), spread factor 1.8;
    ζ ~ U(0, 0.4) (ζ = 0, a breathing that goes on, is a physical limit);
    s ~ U(0, 2) (s = 0, an open canopy breathing alone, is a physical limit);
    φ_i ~ U(−π, π), an angle, which has no edge. At φ = 0 and s = 1 it is the
    damped ring from every peak that ``synth`` simulates; the phases and the
    share let a breathing that the peak does not set going, or that goes on
    undamped in the open canopy alone, be read as breathing: an independent
    bundle with such a breathing laid on was `unexplained` without them
    (``benchmarks/independent_effects.md``, ``canopy_pulse``).

``correlated_noise`` — AR(1) errors, the generic alternative
    The baseline's errors whitened per bin, z_t = Σ_t^(−½)·e_t (channels and the
    shared q̄ error included, :meth:`TestModel.whitened_residuals`), follow
    z_t = φ_t·z_{t−1} + √(1−φ_t²)·ξ_t with φ_t = exp(−Δt_t/τ_c) between
    consecutive bins (an Ornstein–Uhlenbeck process, so bins of different
    widths are handled). The pointwise log-likelihood is the conditional
    log p(y_t | y_{t−1}) — the AR-conditional form that PSIS-LOO can use on
    correlated samples; its sum is the joint likelihood and at τ_c → 0 it is
    the baseline's, bin by bin. Reported beside a diagnosis on request; the
    generic term its rule uses is ``discrepancy`` (:mod:`cpas_bayes.stats.discrepancy`).
    Prior: τ_c lognormal, median 0.05 s, spread factor e^1.5, 0.001–5 s.
"""

from __future__ import annotations

import math

import numpy as np

from cpas_bayes.physics.effects import (added_mass_acceleration, added_mass_momentum_rate, breathing_drag_area,
                                        lagged_added_mass)
from cpas_bayes.stats.discrepancy import Discrepancy
from cpas_bayes.stats.model_parts import Extension, Parameter
from cpas_bayes.stats.distributions import LogNormal, Normal, TruncNormal, Uniform
from cpas_bayes.stats.observations import AIR_DATA
from cpas_bayes.core.units import STANDARD_GRAVITY

_LOG_2PI = math.log(2.0 * math.pi)


class AddedMass(Extension):
    name = "added_mass"
    practical_floor = ("k_a", 0.05)   # below: < 1/4 of the smallest added mass the Drogue tests suggest
    physical_lower_limits = ("mass_lag",)
    # Reads the air data at the bins: measured (obs.*_at), or on a logger bundle each walker's reconstruction.
    reads_air_data = True
    needs_drag_area_rate = True

    def parameters(self, model):
        return [Parameter("k_a", LogNormal(0.3, 1.0, 0.005, 5.0), "", self.name),
                Parameter("mass_exponent", TruncNormal(1.5, 0.25, 1.0, 2.25), "", self.name),
                Parameter("mass_lag", TruncNormal(0.0, 0.25, 0.0, 1.0), "s", self.name)]

    def start_points(self, model):
        # nearly absent; a typical Drogue value at once; the same value behind a lag
        return [{"k_a": 0.02, "mass_exponent": 1.5, "mass_lag": 0.02},
                {"k_a": 0.5, "mass_exponent": 1.5, "mass_lag": 0.02},
                {"k_a": 0.5, "mass_exponent": 1.5, "mass_lag": 0.12}]

    def apparent_drag_area(self, ctx, t):
        model, obs = ctx.model, ctx.model.obs
        v = ctx.values
        tt = t if np.ndim(t) == 3 else np.asarray(t)[None, None, :]      # (1 or B, 1, N)
        if ctx.law is not None and t is ctx.time:   # the model's pass, at the bins or a load cell's lagged times
            cds, cds_rate = ctx.law
        else:
            cds, cds_rate, _ = model.drag_areas(ctx.stage, tt, with_rate=True)
        if ctx.air is not None and t is ctx.time:   # a logger's reconstruction, or read with a lagged load cell's
            rho, speed, qbar, gamma, rho_rate = ctx.air
        else:
            rho, speed, qbar, gamma, rho_rate = obs.native_series_at(tt[:, 0, :], AIR_DATA)[:, :, None, :]
        mass, rate = lagged_added_mass(cds, cds_rate, rho, rho_rate, v["k_a"], v["mass_exponent"],
                                       ctx.stage["cds_o"], tt, v["mass_lag"])
        # dV/dt from the system's momentum balance (effects Eq. A3) with the model's own
        # drag areas: differencing the measured airspeed would turn its noise into
        # m_a·dV/dt errors far larger than the effect on a Main.
        total_weight = (v["vehicle_weight"] + model.chute_weight.sum())[:, None]
        accel = added_mass_acceleration(qbar[:, 0], cds.sum(axis=1), v["vehicle_cds"][:, None],
                                        total_weight, gamma[:, 0], speed[:, 0], mass.sum(axis=1),
                                        rate.sum(axis=1), STANDARD_GRAVITY)
        return added_mass_momentum_rate(mass, rate, speed, accel[:, None, :]) / qbar


class FrictionDrift(Extension):
    name = "friction_drift"
    needs_load_cells = True
    practical_floor = ("load_scale_change", 0.015)   # 1.5 % of the load; clean Mains fit up to 0.6 %

    def parameters(self, model):
        starts = [s.start for p in model.parachutes for s in p.stages]
        self._t_a = min(starts)
        self._t_b = float(model.obs.native_time[-1])
        return [Parameter("load_scale_change", Normal(0.0, 0.08), "", self.name)]

    def start_points(self, model):
        return [{"load_scale_change": 0.0}]      # the likelihood is nearly quadratic in it

    def friction_factor(self, ctx, t):
        frac = np.clip((np.asarray(t) - self._t_a) / (self._t_b - self._t_a), 0.0, 1.0)
        change = ctx.values["load_scale_change"][:, None]
        return ctx.values["load_scale"][:, None] + change * (frac[None, :] - 0.5)


# Gauss–Laguerre nodes and weights of ∫₀^∞ f(s)·e^(−s) ds: a first-order sensor's response as a few delays
RESPONSE_NODES, RESPONSE_WEIGHTS = np.polynomial.laguerre.laggauss(4)


class SensorLag(Extension):
    name = "sensor_lag"
    needs_load_cells = True
    practical_floor = ("lag", 0.010)   # one 100 Hz sample: clean bundles of two simulators fit 2–4 ms
    physical_lower_limits = ("lag_response",)   # a pure delay, not an edge

    def parameters(self, model):
        return [Parameter("lag", TruncNormal(0.0, 0.1, -0.2, 0.3), "s", self.name),
                Parameter("lag_response", TruncNormal(0.0, 0.05, 0.0, 0.3), "s", self.name)]

    def start_points(self, model):
        return [{"lag": 0.0, "lag_response": 0.002}, {"lag": 0.05, "lag_response": 0.01}]

    def load_cell_lag(self, ctx):
        """The delays (B, K) and weights (K,) of a pure delay δ = L − r followed by a first-order response of
        time constant r: y(t) = ∫₀^∞ x(t − δ − r·s)·e^(−s) ds, whose mean delay is the lag L (so at r = 0 it
        is the delay L)."""
        lag, response = ctx.values["lag"][:, None], ctx.values["lag_response"][:, None]
        return lag - response + response * RESPONSE_NODES[None, :], RESPONSE_WEIGHTS


BREATHING_FREQUENCY = {"drogue": 1.2, "pilot": 1.5, "fbcp": 1.5, "main": 0.35}  # Hz, prior medians
# Kinds of the user's own: breathing scales roughly as 1/D_o (f·D_o ≈ 8–12 m/s for the Drogue's 7 m and the
# Main's 35 m); clipped to the prior's usable range.
BREATHING_FREQUENCY_TIMES_DIAMETER = 10.0   # m/s


def breathing_frequency_median(parachute):
    """Prior median of a canopy's breathing frequency, Hz: its kind's, else from its diameter."""
    if parachute.kind in BREATHING_FREQUENCY:
        return BREATHING_FREQUENCY[parachute.kind]
    return float(np.clip(BREATHING_FREQUENCY_TIMES_DIAMETER / parachute.diameter, 0.1, 3.0))


# The breathing's damping ratio at most: a ring, whose successive peaks fall by exp(−2πζ/√(1−ζ²)), 6 % at 0.4.
# A more damped "breathing" is one bump: a stand-in for an added mass beside a drift was fitted at ζ 0.55.
BREATHING_DAMPING_MAX = 0.4
# The reefed stages' ring as a share of the open canopy's, at most: a reefed canopy may breathe harder.
BREATHING_REEFED_SHARE_MAX = 2.0
BREATHING_PHASE = "breathing_phase_"    # + a canopy's prefix: its phase at its peak, rad


def breathing_phase_names(model):
    """The breathing's phase parameter of each canopy of ``model``, in its order (like canopies of a
    composite cluster share one)."""
    return [BREATHING_PHASE + prefix for prefix in model.chute_prefix]


class CanopyBreathing(Extension):
    name = "canopy_breathing"
    # A ring of 1.5 % of the drag area, the friction drift's 1.5 % of the load: a 1.0 % ring stood in beside an
    # added mass (power seed 40003, Drogue k_a 0.4: amplitude 0.004–0.019, frequency 1.0–2.5 Hz, +11.1 ± 5.1).
    practical_floor = ("breathing_amplitude", 0.015)
    physical_lower_limits = ("breathing_damping", "breathing_reefed_share")
    periodic = (BREATHING_PHASE,)

    def __init__(self, frequency_guess=None):
        self.frequency_guess = frequency_guess

    def parameters(self, model):
        kinds = {p.kind: breathing_frequency_median(p) for p in model.parachutes}
        median = float(np.exp(np.mean([math.log(f) for f in kinds.values()])))
        return ([Parameter("breathing_amplitude", Uniform(0.0, 0.25), "", self.name),
                 Parameter("breathing_frequency", LogNormal(median, 0.6, 0.05, 5.0), "Hz", self.name),
                 Parameter("breathing_damping", Uniform(0.0, BREATHING_DAMPING_MAX), "", self.name),
                 Parameter("breathing_reefed_share", Uniform(0.0, BREATHING_REEFED_SHARE_MAX), "", self.name)]
                + [Parameter(name, Uniform(-math.pi, math.pi), "rad", self.name)
                   for name in dict.fromkeys(breathing_phase_names(model))])

    def initial_values(self, model):
        return {"breathing_frequency": self.frequency_guess} if self.frequency_guess else {}

    def start_points(self, model):
        # A small ring at the guessed frequency (the residuals' periodogram peak), and one
        # at the prior median frequency in case the guess picked noise.
        # Each canopy in phase with its peak (the simulated form), and at the guessed frequency also a
        # quarter period either way, from where the search moves each canopy's phase on its own.
        median = model.parameters[model.index["breathing_frequency"]].prior.ppf(0.5)
        frequencies = [self.frequency_guess, median] if self.frequency_guess else [median]
        phases = dict.fromkeys(breathing_phase_names(model))
        starts = [(f, phase) for f in frequencies for phase in ((0.0, math.pi / 2, -math.pi / 2)
                                                                  if f == frequencies[0] else (0.0,))]
        return [{"breathing_amplitude": 0.05, "breathing_frequency": f, "breathing_damping": 0.15,
                 "breathing_reefed_share": 1.0, **{name: phase for name in phases}} for f, phase in starts]

    def reshape_drag_area(self, ctx, cds, t):
        stage, v = ctx.stage, ctx.values
        phase = np.stack([v[name] for name in breathing_phase_names(ctx.model)], axis=1)      # (B, P)
        return breathing_drag_area(cds, t, stage["start"], stage["start"] + stage["timing"].t_fp,
                                   v["breathing_amplitude"], v["breathing_frequency"], v["breathing_damping"],
                                   phase, v["breathing_reefed_share"])


class CorrelatedNoise(Extension):
    name = "correlated_noise"

    def parameters(self, model):
        self._gap = np.diff(model.obs.time, prepend=model.obs.time[0] - np.median(np.diff(model.obs.time)))
        return [Parameter("ar_time", LogNormal(0.05, 1.5, 0.001, 5.0), "s", self.name)]

    def start_points(self, model):
        return [{"ar_time": 0.05}, {"ar_time": 0.5}]

    def log_likelihood(self, ctx, pred, obs):
        phi = np.exp(-self._gap[None, :] / ctx.values["ar_time"][:, None])          # (B, N)
        phi[:, 0] = 0.0                                                              # first bin: unconditional
        innovation_var = 1.0 - phi**2
        z, log_det = ctx.model.whitened_residuals(ctx.theta, pred)                  # (B, C, N), (B, N)
        return (_ar1_conditional(z, phi[:, None, :], innovation_var[:, None, :]).sum(axis=1)
                - 0.5 * log_det)


def _ar1_conditional(e, phi, innovation_var):
    """log N(e_t | φ_t·e_{t−1}, 1 − φ_t²) in standardised units, per bin."""
    previous = np.concatenate([np.zeros_like(e[..., :1]), e[..., :-1]], axis=-1)
    resid = e - phi * previous
    return -0.5 * (resid**2 / innovation_var + np.log(innovation_var) + _LOG_2PI)


EXTENSIONS = {cls.name: cls for cls in (AddedMass, FrictionDrift, SensorLag, CanopyBreathing, CorrelatedNoise,
                                        Discrepancy)}
PHYSICAL = ("added_mass", "friction_drift", "sensor_lag", "canopy_breathing")


def applies(name, test):
    """Whether term ``name`` can act on the channels ``test`` has (load-cell terms need load cells)."""
    term = EXTENSIONS[name]
    return not term.needs_load_cells or any(p.load_cell for p in test.parachutes)


def make_extension(name, **options):
    """An extension by name (``added_mass``, ``friction_drift``, ``sensor_lag``, ``canopy_breathing``,
    ``correlated_noise``, ``discrepancy``)."""
    try:
        return EXTENSIONS[name](**options)
    except KeyError:
        raise ValueError(f"unknown extension {name!r}; use one of {', '.join(EXTENSIONS)}") from None

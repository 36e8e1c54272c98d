"""Physical and sensor effects beyond the seed's reduction equations.

Pure functions (numpy, and numba loops for a lag, the lagged added mass and a breathing drag area), each
broadcasting over leading batch axes (runs, walkers, parachutes) with time last where there is a time axis. The simulator
(:mod:`cpas_bayes.physics.trajectory`), the synthetic-test generator
(:mod:`cpas_bayes.data.synth`) and the model extensions that fit these effects all
call these same functions, so a fitted effect means what the simulated one did.

Sign conventions follow the seed (Eq. 1–11): forces along the flight path,
drag and the riser tension F_i positive, the sensed load factor G positive
under drag, γ negative below the horizon.

Added mass (seed §II: "enclosed and apparent mass ... accounted for later in
the simulation codes")
-----------------------------------------------------------------------------
A canopy drags along the air it encloses plus an apparent mass of the air
around it. Its volume scales with (drag area)^(3/2), so::

    m_a = k_a · ρ · CDS^(3/2)                                     (A1)

with k_a dimensionless (about 0.2–1.0). A hemisphere over a projected disk
of area CDS/C_D,p encloses (2/3)·π^(−1/2)·(CDS/C_D,p)^(3/2) of air, i.e.
k_a ≈ 0.376·C_D,p^(−3/2) ≈ 0.25 for C_D,p ≈ 1.3; apparent mass raises it.

That air is captured from rest, so its momentum m_a·V has to be supplied by
the riser. In the free body of parachute i (seed Eq. 10 with the air added;
the air's weight is carried by buoyancy, so it adds no W·sin γ term)::

    d/dt[(m_p,i + m_a,i)·V] = F_i − PRF·q̄·CDS_i − W_p,i·sin γ
    ⇒  F_i = PRF·q̄·CDS_i − W_p,i·G + d(m_a,i·V)/dt               (A2)

where G = −(dV/dt + g·sin γ)/g is the sensed load factor (Eq. 5) and
d(m_a·V)/dt = ṁ_a·V + m_a·dV/dt: capturing air (ṁ_a > 0) pulls harder on the
riser; decelerating the air already carried (dV/dt < 0) relieves it. The
whole system (seed Eq. 1 with the air added)::

    (m_T + Σ m_a,i)·dV/dt = −q̄·(PRF·Σ CDS_i + CDS_V) − W_T·sin γ − V·Σ ṁ_a,i   (A3)

and the vehicle alone (Eq. 2) still gives G = (Σ F_i + q̄·CDS_V)/W_V (Eq. 6).
Eliminating dV/dt::

    W_T·G = q̄·(PRF·Σ CDS_i + CDS_V) + Σ d(m_a,i·V)/dt            (A4)

So both reduction channels see the same apparent drag area:

    accelerometer (Eq. 8):  W_T·G/q̄ − CDS_V   = Σ [PRF·CDS_i + d(m_a,i·V)/dt / q̄]
    load cell    (Eq. 11):  (F_i + W_p,i·G)/q̄ = PRF·CDS_i + d(m_a,i·V)/dt / q̄

The momentum term raises the apparent drag area while the canopy fills fast
and lowers it afterwards while the carried air decelerates with the vehicle.

Form variants of added mass (for robustness studies; the simulator's
``added_mass_exponent`` and ``added_mass_lag``): the volume of a filling
canopy is not geometrically similar to the open one, so the exponent p of
the drag area may differ from 3/2; normalised at the full-open drag area
CDS_o so that k_a keeps its meaning at full open::

    m_a = k_a · ρ · CDS_o^(3/2) · (CDS/CDS_o)^p                  (A1')

and the flow that carries the air may take a moment to establish, so the
carried mass follows (A1') through a first-order lag, dm_a/dt = (m_a,A1' −
m_a)/τ_m, and that dm_a/dt enters the momentum term of (A2–A4).

Instrument effects (applied to what a sensor records, not to the dynamics)
---------------------------------------------------------------------------
First-order lag of a channel (pneumatic lag of a pitot-static line)::

    τ·dy/dt = x − y,   y(t_0) = x(t_0)                           (I1)

Damped ringing of an elastic load path after an excitation at t_k::

    r(t) = 1 + A·Σ_k exp(−ζ·ω·τ_k)·sin(ω·sqrt(1 − ζ²)·τ_k),  τ_k = t − t_k ≥ 0   (I2)

multiplying the load-cell reading (ω = 2π·f).
"""

from __future__ import annotations

import numba
import numpy as np

ADDED_MASS_EXPONENT = 1.5  # volume ∝ (area)^(3/2)


def added_mass(cds, density, k_a, exponent=ADDED_MASS_EXPONENT, reference_cds=None):
    """Eq. A1: enclosed plus apparent air mass m_a = k_a·ρ·CDS^(3/2).

    ``cds`` (m²), ``density`` (kg/m³) and ``k_a`` (dimensionless) broadcast
    together; the result is in kg. Negative drag areas count as zero. An
    ``exponent`` other than 3/2 is the form variant A1', normalised at
    ``reference_cds`` (CDS_o, m², required then).
    """
    cds = np.clip(np.asarray(cds, float), 0.0, None)
    if np.ndim(exponent) == 0 and exponent == ADDED_MASS_EXPONENT:
        return np.asarray(k_a, float) * np.asarray(density, float) * cds**ADDED_MASS_EXPONENT
    reference = _reference_area(reference_cds)
    return (np.asarray(k_a, float) * np.asarray(density, float) * reference**ADDED_MASS_EXPONENT
            * (cds / reference)**exponent)


def added_mass_rate(cds, cds_rate, density, density_rate, k_a, exponent=ADDED_MASS_EXPONENT, reference_cds=None):
    """dm_a/dt of Eq. A1: k_a·(ρ̇·CDS^(3/2) + (3/2)·ρ·CDS^(1/2)·dCDS/dt), kg/s (A1' for another exponent)."""
    cds = np.clip(np.asarray(cds, float), 0.0, None)
    k_a = np.asarray(k_a, float)
    if np.ndim(exponent) == 0 and exponent == ADDED_MASS_EXPONENT:
        return k_a * (np.asarray(density_rate, float) * cds**ADDED_MASS_EXPONENT
                      + ADDED_MASS_EXPONENT * np.asarray(density, float) * np.sqrt(cds)
                      * np.asarray(cds_rate, float))
    reference = _reference_area(reference_cds)
    ratio = cds / reference
    return k_a * reference**ADDED_MASS_EXPONENT * (
        np.asarray(density_rate, float) * ratio**exponent
        + exponent * np.asarray(density, float) * ratio**(exponent - 1.0) * np.asarray(cds_rate, float) / reference)


def added_mass_and_rate(cds, cds_rate, density, density_rate, k_a, exponent, reference_cds):
    """(m_a, dm_a/dt) of Eq. A1' together, as :func:`added_mass` and :func:`added_mass_rate` give them,
    with one power of the area ratio for both ((CDS/CDS_o)^p = (CDS/CDS_o)^(p−1)·CDS/CDS_o); with
    :func:`lagged_mass_rate`, the numpy reference of the likelihood's compiled :func:`lagged_added_mass`."""
    cds = np.clip(np.asarray(cds, float), 0.0, None)
    reference = _reference_area(reference_cds)
    ratio = cds / reference
    scale = np.asarray(k_a, float) * reference**ADDED_MASS_EXPONENT
    exponent = np.asarray(exponent, float)
    with np.errstate(divide="ignore"):
        lower = ratio**(exponent - 1.0)           # as added_mass_rate's, inf at a zero area if p < 1
    powered = np.where(ratio > 0, lower * ratio, 0.0)   # (CDS/CDS_o)^p, 0 at a zero area (p > 0)
    density = np.asarray(density, float)
    mass = scale * density * powered
    rate = scale * (np.asarray(density_rate, float) * powered
                    + exponent * density * lower * np.asarray(cds_rate, float) / reference)
    return mass, rate


def _reference_area(reference_cds):
    if reference_cds is None:
        raise ValueError("an added-mass exponent other than 3/2 needs reference_cds (CDS_o)")
    reference = np.asarray(reference_cds, float)
    if np.any(reference <= 0):
        raise ValueError("reference_cds must be positive")
    return reference


def lagged_mass_rate(target_rate, t, lag):
    """Eq. A5: the lag error over τ_m, g (kg/s), of a mass following its target through a first-order lag.

    ``target_rate`` ṁ_a,A1' (B, P, N) on the increasing times ``t`` (N,) or
    (B or 1, 1, N); ``lag`` τ_m ≥ 0 (B,) in s. Returns g (B, P, N): the
    lagged mass is target + τ_m·g and its rate −g. The record starts in
    steady state (g = −ṁ at the first time).
    """
    rate = np.ascontiguousarray(target_rate, float)
    times = np.asarray(t, float)
    times = np.ascontiguousarray(times.reshape(-1, times.shape[-1]))
    lag = np.ascontiguousarray(np.broadcast_to(np.asarray(lag, float), rate.shape[:1]))
    if np.any(lag < 0):
        raise ValueError("the added-mass lag must be ≥ 0")
    return _lag_error(rate, times, lag)


@numba.njit(cache=True)
def _lag_step(g, previous_rate, rate, one_minus_a, c):
    """Eq. A5's lag error g one step on, the target's rate going from ``previous_rate`` to ``rate`` over a step
    Δt with 1 − a = 1 − e^(−Δt/τ_m) and c = τ_m/Δt·(1 − a): the one recursion of :func:`lagged_mass_rate`
    and :func:`lagged_added_mass`."""
    return (1.0 - one_minus_a) * g - previous_rate * one_minus_a - (rate - previous_rate) * (1.0 - c)


@numba.njit(cache=True)
def _lag_error(rate, times, lag):
    n_rows, n_chutes, n_times = rate.shape
    out = np.empty_like(rate)
    for b in range(n_rows):
        t = times[b if times.shape[0] > 1 else 0]
        tau = lag[b]
        for i in range(n_chutes):
            g = -rate[b, i, 0]
            out[b, i, 0] = g
            for n in range(1, n_times):
                if tau <= 0.0:
                    g = -rate[b, i, n]
                else:
                    step = t[n] - t[n - 1]
                    one_minus_a = -np.expm1(-step / tau)
                    c = tau / step * one_minus_a
                    g = _lag_step(g, rate[b, i, n - 1], rate[b, i, n], one_minus_a, c)
                out[b, i, n] = g
    return out


def lagged_added_mass(cds, cds_rate, density, density_rate, k_a, exponent, reference_cds, t, lag):
    """(m_a, dm_a/dt) of a mass that follows Eq. A1' through the first-order lag of Eq. A5, in one compiled
    pass: what :func:`added_mass_and_rate` then :func:`lagged_mass_rate` give (mass = target + τ_m·g,
    rate = −g), for the likelihood's walker batches.

    ``cds``, ``cds_rate`` (B, P, N); ``density``, ``density_rate`` (B or 1, N); ``k_a``, ``exponent``,
    ``lag`` (B,); ``reference_cds`` CDS_o (B, P); ``t`` (N,) or (B or 1, N) increasing. The area ratio's
    power is computed once per run of equal drag areas (a settled stage), not per bin.
    """
    cds = np.ascontiguousarray(cds, float)
    B = cds.shape[0]
    rows = lambda a: np.ascontiguousarray(np.asarray(a, float).reshape(-1, cds.shape[-1]))  # noqa: E731
    per_row = lambda a: np.ascontiguousarray(np.broadcast_to(np.asarray(a, float).reshape(-1), (B,)))  # noqa: E731
    reference = np.ascontiguousarray(np.broadcast_to(_reference_area(reference_cds), cds.shape[:2]))
    lag = per_row(lag)
    if np.any(lag < 0):
        raise ValueError("the added-mass lag must be ≥ 0")
    return _lagged_added_mass(cds, np.ascontiguousarray(cds_rate, float), rows(density), rows(density_rate),
                              per_row(k_a), per_row(exponent), reference, rows(t), lag, ADDED_MASS_EXPONENT)


@numba.njit(cache=True)
def _lagged_added_mass(cds, cds_rate, density, density_rate, k_a, exponent, reference, times, lag, volume_power):
    n_rows, n_chutes, n_times = cds.shape
    mass = np.empty_like(cds)
    rate = np.empty_like(cds)
    for b in range(n_rows):
        t = times[b if times.shape[0] > 1 else 0]
        rho = density[b if density.shape[0] > 1 else 0]
        rho_rate = density_rate[b if density_rate.shape[0] > 1 else 0]
        p, tau = exponent[b], lag[b]
        # the lag's step factors depend on the row's τ_m and the times only: once per row, not per parachute
        one_minus_a = np.zeros(n_times)
        c = np.zeros(n_times)
        if tau > 0.0:
            for n in range(1, n_times):
                step = t[n] - t[n - 1]
                one_minus_a[n] = -np.expm1(-step / tau)
                c[n] = tau / step * one_minus_a[n]
        for i in range(n_chutes):
            ref = reference[b, i]
            scale = k_a[b] * ref ** volume_power
            previous_area, lower, powered = -1.0, 0.0, 0.0
            g, previous_target_rate = 0.0, 0.0
            for n in range(n_times):
                area = max(cds[b, i, n], 0.0)
                if area != previous_area:     # (CDS/CDS_o)^(p−1) and ^p; p ≥ 1 in the prior, so finite at 0
                    ratio = area / ref
                    if ratio > 0.0:
                        lower = ratio ** (p - 1.0)
                        powered = lower * ratio
                    else:
                        lower = 1.0 if p == 1.0 else (0.0 if p > 1.0 else np.inf)
                        powered = 0.0
                    previous_area = area
                target = scale * rho[n] * powered
                target_rate = scale * (rho_rate[n] * powered + p * rho[n] * lower * cds_rate[b, i, n] / ref)
                if n == 0 or tau <= 0.0:
                    g = -target_rate
                else:
                    g = _lag_step(g, previous_target_rate, target_rate, one_minus_a[n], c[n])
                previous_target_rate = target_rate
                mass[b, i, n] = target + tau * g
                rate[b, i, n] = -g
    return mass, rate


def added_mass_momentum_rate(mass, mass_rate, airspeed, acceleration):
    """d(m_a·V)/dt = ṁ_a·V + m_a·dV/dt (N): the momentum term of Eq. A2–A4."""
    return np.asarray(mass_rate, float) * airspeed + np.asarray(mass, float) * acceleration


def added_mass_acceleration(qbar, drag_area_total, vehicle_cds, total_weight, flight_path_angle,
                            airspeed, added_mass_total, added_mass_rate_total, gravity):
    """Eq. A3 solved for dV/dt (m/s²).

    ``drag_area_total`` is PRF·Σ CDS_i (m²), ``vehicle_cds`` CDS_V, the total
    weight W_T in N, ``added_mass_total`` Σ m_a,i (kg) and its rate (kg/s).
    With zero added mass this is the seed's Eq. 3:
    dV/dt = −q̄·(PRF·Σ CDS_i + CDS_V)·g/W_T − g·sin γ.
    """
    total_mass = np.asarray(total_weight, float) / gravity
    drag = np.asarray(qbar, float) * (np.asarray(drag_area_total, float) + vehicle_cds)
    return ((-drag - np.asarray(total_weight, float) * np.sin(flight_path_angle)
             - np.asarray(airspeed, float) * added_mass_rate_total)
            / (total_mass + np.asarray(added_mass_total, float)))


def riser_tension(qbar, cds, parachute_weight, load_factor, prf=1.0, momentum_rate=0.0):
    """Eq. 10 / A2: F_i = PRF·q̄·CDS_i − W_p,i·G + d(m_a,i·V)/dt (N).

    ``load_factor`` is G in g (dimensionless); ``momentum_rate`` is the added
    mass term (0 when added mass is off).
    """
    return prf * np.asarray(qbar, float) * cds - np.asarray(parachute_weight, float) * load_factor + momentum_rate


def sensed_load_factor(acceleration, flight_path_angle, gravity):
    """Eq. 5 along the flight path: G = −(dV/dt + g·sin γ)/g, positive under drag."""
    return -(np.asarray(acceleration, float) + gravity * np.sin(flight_path_angle)) / gravity


def breathing_factor(tau, amplitude, frequency_hz, damping_ratio):
    """Canopy breathing after a peak: multiplier of the drag area.

    ::

        b(τ) = 1 + A·exp(−ζ·ω·τ)·sin(ω·sqrt(1 − ζ²)·τ),  ω = 2π·f,   τ ≥ 0
        b(τ) = 1                                                  τ < 0

    ``tau`` is the time since the stage's peak drag area (t_i + t_fp). A
    damped oscillation that starts at zero, so a drag area multiplied by it
    stays continuous. Realistic values: A 0.03–0.10; f 0.8–2 Hz for Drogues,
    0.2–0.6 Hz for Mains; ζ 0.05–0.3 (ζ < 1 required).
    """
    tau = np.asarray(tau, float)
    damping_ratio = np.asarray(damping_ratio, float)
    if np.any((damping_ratio < 0) | (damping_ratio >= 1)):
        raise ValueError("damping_ratio must be in [0, 1)")
    omega = 2.0 * np.pi * np.asarray(frequency_hz, float)
    after = np.clip(tau, 0.0, None)
    ringing = np.exp(-damping_ratio * omega * after) * np.sin(omega * np.sqrt(1.0 - damping_ratio**2) * after)
    return np.where(tau >= 0, 1.0 + np.asarray(amplitude, float) * ringing, 1.0)


def breathing_drag_area(cds, t, start, peak, amplitude, frequency_hz, damping_ratio, phase=0.0, reefed_share=1.0):
    """``cds`` (B, P, N) times the breathing factor of the stage active at each time, τ from its peak::

        b = 1 + A_k·exp(−ζωτ)·[cos φ_p·sin(ω_d·τ) + sin φ_p·(cos(ω_d·τ) − 1)],   ω_d = ω·sqrt(1 − ζ²)

    i.e. A_k·e^(−ζωτ)·[sin(ω_d·τ + φ_p) − sin φ_p]: a ring of phase φ_p at the canopy's peak that starts
    from zero, so the drag area stays continuous. A_k is A in the canopy's
    last stage (full open) and ``reefed_share``·A in the stages before it. With φ = 0 and the share 1 it is
    :func:`breathing_factor` at every stage (the synthetic tests' form); a phase per canopy and a share let
    a breathing that the peak does not set going in phase, or one that only the open canopy shows, be read
    as breathing too.

    The active stage at t is the last whose start has passed (the count of starts ≤ t, less one; none
    before the first: factor 1); a canopy's last stage is its last with a finite start. ``t`` is (N,) or
    (B, 1, N) (a lagged time base per walker); ``start`` and ``peak`` (t_i + t_fp) are (B, P, K); the
    breathing's parameters (B,), ``phase`` (B, P) or broadcastable, rad.

    One compiled pass: the same as finding the active stage with numpy and calling
    :func:`breathing_factor`, which built four (B, P, K, N) and (B, P, N) temporaries per call and took
    more than half of a Main's lag + breathing batch (README, Measured figures)."""
    damping_ratio = np.asarray(damping_ratio, float)
    if np.any((damping_ratio < 0) | (damping_ratio >= 1)):
        raise ValueError("damping_ratio must be in [0, 1)")
    cds = np.ascontiguousarray(cds, dtype=float)
    times = np.asarray(t, float)
    times = np.ascontiguousarray(times.reshape(-1, times.shape[-1]))          # (1, N) or (B, N)
    batch = cds.shape[0]
    start, peak = (np.ascontiguousarray(np.broadcast_to(a, (batch,) + np.shape(a)[1:]), dtype=float)
                   for a in (start, peak))
    amplitude, frequency_hz, damping_ratio, reefed_share = (
        np.ascontiguousarray(np.broadcast_to(a, (batch,)), dtype=float)
        for a in (amplitude, frequency_hz, damping_ratio, reefed_share))
    phase = np.asarray(phase, float)
    phase = np.broadcast_to(phase.reshape(phase.shape + (1,) * (2 - phase.ndim)) if phase.ndim < 2 else phase,
                            cds.shape[:2])
    cos_phase, sin_phase = np.ascontiguousarray(np.cos(phase)), np.ascontiguousarray(np.sin(phase))
    out = np.empty_like(cds)
    _breathing_drag_area_kernel(cds, times, start, peak, amplitude, frequency_hz, damping_ratio, cos_phase,
                                sin_phase, reefed_share, out)
    return out


@numba.njit(cache=True)
def _breathing_drag_area_kernel(cds, times, start, peak, amplitude, frequency_hz, damping_ratio, cos_phase,
                                sin_phase, reefed_share, out):
    n_batch, n_chutes, n_times = cds.shape
    n_stages = start.shape[2]
    per_walker = times.shape[0] > 1
    for b in range(n_batch):
        omega = 2.0 * np.pi * frequency_hz[b]
        decay = -damping_ratio[b] * omega
        omega_d = omega * np.sqrt(1.0 - damping_ratio[b] ** 2)
        row = b if per_walker else 0
        for p in range(n_chutes):
            last = 0
            for k in range(n_stages):
                if np.isfinite(start[b, p, k]):
                    last += 1
            c, s = cos_phase[b, p], sin_phase[b, p]
            for n in range(n_times):
                tn = times[row, n]
                started = 0
                for k in range(n_stages):
                    if start[b, p, k] <= tn:
                        started += 1
                factor = 1.0
                if started > 0:
                    tau = tn - peak[b, p, started - 1]
                    if tau >= 0.0:      # NaN (a walker's undefined stage) is not: factor 1, as in numpy
                        a = amplitude[b] if started == last else amplitude[b] * reefed_share[b]
                        x = omega_d * tau
                        factor = 1.0 + a * np.exp(decay * tau) * (c * np.sin(x) + s * (np.cos(x) - 1.0))
                out[b, p, n] = cds[b, p, n] * factor


def friction_scale(t, s_start, s_end, t_start, t_end):
    """Load-cell friction factor, a linear ramp in time (seed §III.B).

    The load cell reads the riser tension divided by this factor (friction
    over the fairlead loses tension before the cell). The seed's CDT-3-2
    Drogues went from 1.159 to 1.107 between the midpoints of the two stages::

        s(t) = s_start                                          t ≤ t_start
        s(t) = s_start + (s_end − s_start)·(t − t_start)/(t_end − t_start)
        s(t) = s_end                                            t ≥ t_end

    ``t`` has time last (..., T); the other arguments broadcast over the
    leading axes (shape (...,)). ``t_end`` must be after ``t_start``.
    """
    t = np.asarray(t, float)
    s_start, s_end, t_start, t_end = (np.asarray(a, float)[..., None] for a in (s_start, s_end, t_start, t_end))
    if np.any(t_end <= t_start):
        raise ValueError("friction_scale needs t_end > t_start")
    frac = np.clip((t - t_start) / (t_end - t_start), 0.0, 1.0)
    return s_start + (s_end - s_start) * frac


def friction_settle(t, s_start, s_end, t_start, tau):
    """Load-cell friction factor settling exponentially from ``s_start`` toward ``s_end`` after ``t_start``
    (a fairlead or swivel wearing in: fast at first, then ever slower)::

        s(t) = s_start                                               t ≤ t_start
        s(t) = s_end + (s_start − s_end)·exp(−(t − t_start)/τ)       t > t_start

    Not a ramp: the form the diagnosis' ``friction_drift`` term was not written for. Shapes as
    :func:`friction_scale`; ``tau`` > 0.
    """
    t = np.asarray(t, float)
    s_start, s_end, t_start, tau = (np.asarray(a, float)[..., None] for a in (s_start, s_end, t_start, tau))
    if np.any(tau <= 0):
        raise ValueError("friction_settle needs tau > 0")
    return s_end + (s_start - s_end) * np.exp(-np.clip(t - t_start, 0.0, None) / tau)


def lagged(t, values, lag):
    """A channel delayed by ``lag`` seconds: values(t − lag), linear interpolation.

    ``t`` (T,) strictly increasing sample times; ``values`` (..., T); ``lag``
    scalar or (...,) broadcasting with the leading axes of ``values``, ≥ 0.
    Before the first sample the first value is held (the sensor read its
    initial value before the record began).
    """
    t = np.asarray(t, float)
    values = np.asarray(values, float)
    lag = np.asarray(lag, float)
    if np.any(lag < 0):
        raise ValueError("lag must be ≥ 0 (a delay)")
    batch = np.broadcast_shapes(values.shape[:-1], lag.shape)
    values = np.broadcast_to(values, batch + t.shape)
    query = t - lag[..., None]                      # (..., T)
    query = np.broadcast_to(query, batch + t.shape)
    right = np.clip(np.searchsorted(t, query, side="right"), 1, len(t) - 1)
    left = right - 1
    t_left, t_right = t[left], t[right]
    weight = np.clip((query - t_left) / (t_right - t_left), 0.0, 1.0)
    v_left = np.take_along_axis(values, left, axis=-1)
    v_right = np.take_along_axis(values, right, axis=-1)
    return v_left + weight * (v_right - v_left)


def first_order_lag(t, values, tau):
    """Eq. I1: ``values`` (..., T) seen through a first-order lag of time constant ``tau`` (s, > 0).

    Exact for a channel that is linear between the samples ``t`` (T,):
    y_{n+1} = x_{n+1} − τ·s_n + (y_n − x_n + τ·s_n)·exp(−Δt/τ), s_n the
    slope over the step; y starts at the first value (settled before the record).
    ``tau`` is a scalar or broadcasts with the leading axes of ``values``.
    """
    t = np.asarray(t, float)
    values = np.asarray(values, float)
    tau = np.asarray(tau, float)
    if np.any(tau <= 0) or not np.all(np.isfinite(tau)):
        raise ValueError("tau must be positive and finite")
    tau = tau[..., None]                                   # (..., 1)
    dt = np.diff(t)
    lag_term = tau * np.diff(values, axis=-1) / dt         # τ·s_n, (..., T − 1)
    decay = np.broadcast_to(np.exp(-dt / tau), lag_term.shape)
    values = np.broadcast_to(values, lag_term.shape[:-1] + t.shape)
    out = np.empty(values.shape)
    out[..., 0] = values[..., 0]
    for n in range(len(t) - 1):
        out[..., n + 1] = (values[..., n + 1] - lag_term[..., n]
                           + (out[..., n] - values[..., n] + lag_term[..., n]) * decay[..., n])
    return out


def load_path_ringing(t, starts, amplitude, frequency_hz, damping_ratio):
    """Eq. I2: multiplier (..., T) of a load-cell reading ringing after each excitation time.

    ``t`` (T,) s; ``starts`` (..., K) the excitation times (a canopy's stage
    starts); ``amplitude`` A, ``frequency_hz`` f and ``damping_ratio`` ζ
    (0 ≤ ζ < 1) scalars or (...,). The same damped sine as
    :func:`breathing_factor`, started at each excitation and superposed.
    """
    starts = np.asarray(starts, float)
    tau = np.asarray(t, float) - starts[..., None]                        # (..., K, T)
    params = [np.asarray(v, float)[..., None, None] for v in (amplitude, frequency_hz, damping_ratio)]
    return 1.0 + (breathing_factor(tau, *params) - 1.0).sum(axis=-2)

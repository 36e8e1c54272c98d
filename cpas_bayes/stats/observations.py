"""What the likelihood compares against: reduced drag areas with their random 1-sigma.

The reduction (Eq. 8, Eq. 11–13) gives, per sample, the accelerometer drag area
of the cluster and each load cell's raw drag area (before friction scaling),
with 1-sigma split into a random part (G, q̄, F, θ noise: independent sample to
sample) and a systematic part (W_V, W_p, CDS_V, scale factor: one value for
the whole test). The likelihood uses the random part only; the systematic
quantities are parameters of the model (vehicle weight, vehicle drag area,
load-cell friction factor), so their uncertainty is not counted once per
sample, which would let a constant offset pose as thousands of independent
errors.

Shared q̄ error: Eq. 8 and Eq. 11 both divide by the same measured q̄, so its
error moves every channel of a sample together (by −y·Δq̄/q̄). The random
1-sigma is therefore split into an independent part per channel (``*_sigma``)
and the q̄ part (``*_qbar``), a vector common to the channels of a bin; the
likelihood uses the covariance diag(σ²) + u·uᵀ per bin. Counting the q̄ error
once per channel, as independent errors would, overstates what two load cells
and an accelerometer seeing the same q̄ know about a shared feature such as
simultaneous disreefs.

Binning: samples are averaged in bins where nothing changes fast (steady
stages), and kept at full rate around every stage start, where fill times of a
few tenths of a second live. A bin's value is the mean of its samples, its
sigma sqrt(Σσ²)/m, its time the mean time; the model is evaluated at that
time, which is exact for a drag area that is steady or linear in the bin.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from cpas_bayes.data.bundle import FlightTest

# Bin widths, s. Infinite-mass fills last 0.2-0.6 s: 0.02 s bins keep 10-30 points
# per fill, and the model's curvature over a bin changes its mean by < 0.1 % of
# the noise; finite-mass fills last seconds: 0.05 s bins lose nothing.
TRANSIENT_WINDOW = {"infinite": (0.4, 2.5), "finite": (0.4, 12.0)}  # s before / after a stage start
TRANSIENT_BIN = {"infinite": 0.02, "finite": 0.05}
STEADY_BIN = 0.1


# The native series of a term's air data, in the order of ``Context.air`` (ρ, V, q̄, γ, dρ/dt)
AIR_DATA = ("native_density", "native_airspeed", "native_qbar", "native_gamma", "native_density_rate")


@dataclass(frozen=True)
class Observations:
    """Binned observations of one test, SI.

    ``acc`` (N,) is the accelerometer drag area of the cluster computed with
    the stated W_T and CDS_V (Eq. 8); ``lc`` (L, N) each load cell's raw drag
    area (F_i·cos θ_i + W_p,i·G)/q̄ without friction scaling (Eq. 11, 13);
    ``lc_weight_term`` (L, N) = W_p,i·G/q̄, which the friction factor does not
    scale. ``lc_index`` maps each load cell row to its parachute's position.
    ``acc_sigma``/``lc_sigma`` are the independent random parts, ``acc_qbar``/
    ``lc_qbar`` the shared q̄ part (see the module docstring).
    """

    time: np.ndarray
    acc: np.ndarray
    acc_sigma: np.ndarray
    acc_qbar: np.ndarray
    lc: np.ndarray
    lc_sigma: np.ndarray
    lc_qbar: np.ndarray
    lc_weight_term: np.ndarray
    lc_index: np.ndarray
    samples_per_bin: np.ndarray
    # Native-rate flight condition, for interpolation by the model.
    native_time: np.ndarray
    native_airspeed: np.ndarray   # smoothed, m/s
    native_qbar: np.ndarray       # Pa
    native_g: np.ndarray          # load factor, smoothed
    native_density: np.ndarray    # kg/m³
    native_gamma: np.ndarray      # flight-path angle, rad
    stated_vehicle_weight: float
    stated_vehicle_cds: float
    # q̄ and G smoothed over FLIGHT_SMOOTHING s: their change over a load cell's lag
    native_qbar_smooth: np.ndarray
    native_g_smooth: np.ndarray

    @property
    def n_bins(self):
        return self.time.size

    def airspeed_at(self, t):
        return np.interp(t, self.native_time, self.native_airspeed)

    def qbar_at(self, t):
        return np.interp(t, self.native_time, self.native_qbar)

    def g_at(self, t):
        return np.interp(t, self.native_time, self.native_g)

    def smooth_qbar_at(self, t):
        """q̄ at ``t`` with its sample noise smoothed out: the change of q̄ over a short interval is physics,
        the difference of two noisy samples is mostly noise (see :data:`FLIGHT_SMOOTHING`)."""
        return np.interp(t, self.native_time, self.native_qbar_smooth)

    def smooth_g_at(self, t):
        """G at ``t`` smoothed alike."""
        return np.interp(t, self.native_time, self.native_g_smooth)

    def density_at(self, t):
        return np.interp(t, self.native_time, self.native_density)

    @cached_property
    def native_density_rate(self):
        """dρ/dt at the native times, kg/m³/s."""
        return np.gradient(self.native_density, self.native_time)

    def native_series_at(self, t, names):
        """The native series ``names`` (attributes, e.g. ``"native_qbar"``) at times ``t`` (R, N), each row
        increasing: (S, R, N), what np.interp gives each, in one walk along the native times."""
        from cpas_bayes.stats.likelihood_kernel import interp_rows

        t = np.ascontiguousarray(t, float)
        series = np.ascontiguousarray(np.stack([getattr(self, name) for name in names]), float)
        return interp_rows(t, np.ascontiguousarray(self.native_time, float), series,
                           np.empty((len(names),) + t.shape))

    def gamma_at(self, t):
        return np.interp(t, self.native_time, self.native_gamma)


# Window of the local quadratic (Savitzky–Golay) that smooths q̄ and G for differences over a few hundredths
# of a second (a load cell's lag). q̄ and G follow the vehicle's speed and deceleration, smooth over a second;
# a quadratic keeps their slope and curvature. Measured on synthetic tests simulated twice with the same noise,
# without and with a 0.04 s load-cell lag, as the least-squares ratio of the model's predicted lag effect to the
# data's: with the 5-sample means (q̄ 1 % per 100 Hz sample) a Main's was 0.05–0.12 (the q̄ noise of two
# samples, ±5 m² on 500 m², swamped a true ±2 m²; the fitted lag read 15–20 % short and the generic
# discrepancy fitted better without it), 0.66–0.82 at 0.5 s, 0.89–0.96 at 1 s, 0.92–0.99 at 2 s; a Drogue's
# (higher q̄) 0.99–1.01 at every window, its residual least at 1 s.
FLIGHT_SMOOTHING = 1.0   # s


def smooth_flight_condition(time, x, window=FLIGHT_SMOOTHING):
    """``x`` sampled at ``time`` smoothed by a local quadratic over ``window`` seconds (as is when the record
    is too short or too coarse for one)."""
    from scipy.signal import savgol_filter

    x = np.asarray(x, float)
    if x.size < 5:
        return x
    width = int(round(window / float(np.median(np.diff(time)))))
    width = min(width + 1 - width % 2, x.size - 1 + x.size % 2)   # odd, within the record
    if width < 5:
        return x
    return savgol_filter(x, width, 2, mode="interp")


def _moving_average(x, width):
    if width <= 1:
        return x
    kernel = np.ones(width) / width
    padded = np.pad(x, (width // 2, width - 1 - width // 2), mode="edge")
    return np.convolve(padded, kernel, mode="valid")


def bin_edges(test: FlightTest, native_rate=False):
    """Index edges of the bins: native rate near stage starts, coarser elsewhere."""
    t = test.time
    dt = float(np.median(np.diff(t)))
    if native_rate:
        return np.arange(t.size + 1)
    width = np.full(t.size, STEADY_BIN)
    for p in test.parachutes:
        before, after = TRANSIENT_WINDOW[p.inflation]
        for s in p.stages:
            lo, hi = s.start - before - 4 * s.start_sigma, s.start + after + 4 * s.start_sigma
            inside = (t >= lo) & (t <= hi)
            width[inside] = np.minimum(width[inside], TRANSIENT_BIN[p.inflation])
    edges = [0]
    i = 0
    while i < t.size:
        # A bin never straddles a change of width, so transients stay resolved.
        m = max(1, int(round(width[i] / dt)))
        j = i + 1
        while j < t.size and j - i < m and width[j] == width[i]:
            j += 1
        edges.append(j)
        i = j
    return np.asarray(edges)


def _bin_mean(x, edges):
    sums = np.add.reduceat(x, edges[:-1], axis=-1)
    return sums / np.diff(edges)


def _bin_sigma(sigma, edges):
    return np.sqrt(np.add.reduceat(sigma**2, edges[:-1], axis=-1)) / np.diff(edges)


def _independent_part(total, shared):
    """sqrt(σ² − u²): what is left of a random 1-sigma once the shared q̄ part is taken out."""
    # A floor of 1 % of the total keeps a channel whose error is all q̄ from a zero sigma.
    return np.sqrt(np.maximum(total**2 - shared**2, (0.01 * total) ** 2))


def build_observations(test: FlightTest, reduced, native_rate=False) -> Observations:
    """Observations from a test and its reduction frame (SI, see :mod:`cpas_bayes.data.reduction`)."""
    edges = bin_edges(test, native_rate)
    lc_chutes = [i for i, p in enumerate(test.parachutes) if p.load_cell]
    d = test.data
    g = d["G"].to_numpy()
    q = d["qbar"].to_numpy()
    q_rel = d["qbar_sigma"].to_numpy() / q
    n = len(d)
    acc = reduced["cds_total"].to_numpy()
    acc_rand = reduced["cds_total_sigma_random"].to_numpy()
    acc_q = q_rel * (acc + test.vehicle.cds)              # ∂(Eq. 8)/∂q̄ · Δq̄
    lc = np.array([reduced[f"cds_{test.parachutes[i].id}_raw"].to_numpy() for i in lc_chutes]).reshape(-1, n)
    lc_rand = np.array([reduced[f"cds_{test.parachutes[i].id}_raw_sigma_random"].to_numpy()
                        for i in lc_chutes]).reshape(-1, n)
    lc_q = q_rel * lc                                      # ∂(Eq. 11)/∂q̄ · Δq̄
    weight_term = np.array([test.parachutes[i].weight * g / q for i in lc_chutes]).reshape(-1, n)
    if "density" in d:
        density = d["density"].to_numpy()
    else:
        from cpas_bayes.physics.atmosphere import standard_atmosphere
        density = standard_atmosphere(d["altitude"].to_numpy())[0] if "altitude" in d else 2 * q / d["airspeed"].to_numpy() ** 2
    return Observations(
        time=_bin_mean(test.time, edges),
        acc=_bin_mean(acc, edges),
        acc_sigma=_bin_sigma(_independent_part(acc_rand, acc_q), edges),
        acc_qbar=_bin_sigma(np.abs(acc_q), edges),
        lc=_bin_mean(lc, edges),
        lc_sigma=_bin_sigma(_independent_part(lc_rand, lc_q), edges),
        lc_qbar=_bin_sigma(np.abs(lc_q), edges),
        lc_weight_term=_bin_mean(weight_term, edges),
        lc_index=np.asarray(lc_chutes, dtype=int),
        samples_per_bin=np.diff(edges),
        native_time=test.time,
        native_airspeed=_moving_average(d["airspeed"].to_numpy(), 11),
        native_qbar=_moving_average(q, 5),
        native_g=_moving_average(g, 5),
        native_qbar_smooth=smooth_flight_condition(test.time, q),
        native_g_smooth=smooth_flight_condition(test.time, g),
        native_density=density,
        native_gamma=np.radians(d["gamma"].to_numpy()),
        stated_vehicle_weight=test.vehicle.weight,
        stated_vehicle_cds=test.vehicle.cds,
    )

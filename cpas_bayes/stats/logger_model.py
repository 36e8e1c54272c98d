"""The model of a logger bundle: inflation and air data fitted together to the raw accelerometer and GNSS samples.

A logger bundle (no measured q̄; docs/test-bundle.md) is fitted with the same
inflation parameters as :class:`~cpas_bayes.stats.model.TestModel` plus the nine
systematic air-data parameters of :mod:`cpas_bayes.data.air_reconstruction`
(initial airspeed, flight-path angle, heading and altitude, the wind profile's
error, accelerometer scale and bias, receiver latency).

For each parameter set θ:

1. the flight path is reconstructed with the accelerometer as input
   (:mod:`cpas_bayes.physics.flight_path`): airspeed V(t), altitude h(t),
   q̄(t) = ½ρ(h)V²; each stage's V_i is V at its start;
2. the receiver's velocity and altitude samples are compared with the
   reconstruction at their time stamps less the latency;
3. the accelerometer's readings, averaged in bins (one reading per bin near
   each stage start, up to 0.1 s elsewhere), are compared with the drag model
   (Eq. 3, 5)::

       G_model(t) = q̄(t)·(Σ CDS_i(t) + CDS_V)/W_T
       bin mean   = s·mean(G_model over the span the bin's readings average) + b

   The mean over the span (Gauss–Legendre, one node per 10 ms) is what an
   averaging logger records, so a slow logger's attenuated peak is modelled
   rather than read as a slow inflation.

The readings are both the input of step 1 and the data of step 3. Their
errors e_j therefore reach every residual: a bin's own, and through the
reconstruction's airspeed (a random walk) every later receiver sample and
every later bin (q̄ ∝ V²). Steps 2 and 3 are one Gaussian with Σ holding
all of it (:func:`joint_errors`), factored as L = [[L_rr, 0], [L_gr, L_gg]]:
receiver residuals r = λ_R·L_rr·u_r, bins λ_R·L_gr·u_r + λ_A·L_gg·u_g
(u ~ N(0, I)). Each sensor has its own error multiplier: λ_R = ``noise_gnss``
scales the receiver's residuals (its noise and the walk it sees), λ_A =
``noise_acc`` the bins' innovations given the receiver. With one shared λ a
misfit of the bins (an inflation the law cannot make) inflated the receiver's
sigmas too and let the bins pull the accelerometer's scale and the latency:
on six drops of an independent simulator with an over-inflation bump the
scale went to 0.986 and the latency 5 ms early (MAP of two), against
0.994–0.997 and 1–2 ms with λ_R apart (``benchmarks/independent_drops.md``). The inflation model
never enters step 1, so the airspeed does not bend to fit it.

Step 3 is shown in drag-area units so that every figure and check of the
q̄ path reads it unchanged: with the best-estimate q̄_ref (the air parameters'
maximum, fixed before sampling) each bin becomes the observation
acc = W_T,stated·mean reading/q̄_ref − CDS_V,stated, its 1-sigma the marginal
one, and the prediction is mapped by the same fixed affine transform; q̄_ref
sets the units of that view, not the fit.

Extensions. A term that reshapes the drag area (canopy breathing) acts on the
averaging nodes of step 3, and so does the added mass: its apparent drag area
d(m_a·V)/dt/q̄ reads each walker's reconstructed ρ, V, q̄ and γ at the nodes
(``Context.air``) where a bundle with a q̄ channel gives the measured ones. A
term with its own error model (the generic discrepancy, AR(1) errors) acts on
the bins given the receiver: their residuals are whitened with the Cholesky
factor of that conditional covariance, z = L_gg⁻¹·(reading residual)/λ, so
z_i is the innovation of bin i given the receiver and the bins before it and
Σ z_i² is the bins' part of the joint. The pointwise log-likelihood (PSIS-LOO, model comparison) is these
sequential conditionals, in reading units; the receiver's part is common to
every bin and left out of it. Terms on the load cells do not apply.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import solve_triangular

from cpas_bayes.data import air_reconstruction as air
from cpas_bayes.data.bundle import FlightTest
from cpas_bayes.physics import flight_path as fp
from cpas_bayes.stats.distributions import TruncNormal
from cpas_bayes.stats.model import TestModel
from cpas_bayes.stats.model_parts import Context, Parameter, Prediction
from cpas_bayes.stats.observations import STEADY_BIN, TRANSIENT_BIN, TRANSIENT_WINDOW, Observations

AVERAGING_STEP = 0.01   # s between the points that average the model over a reading's interval
# Where the canopies decelerate the system (a bin's reading above FINE_SHARE of the way from the record's
# median to its peak, and the bins either side) the points are FINE_STEP apart: the fills end there, where
# the added mass' dm_a/dt steps, and a step inside one 50 ms reading averaged at 10 ms missed 3 % of the
# peak (at 2 ms: 0.5 %). About a quarter more points on the drops simulated.
FINE_STEP, FINE_SHARE = 0.002, 0.05
_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class ReadingBins:
    """How the model averages over each bin of readings: Gauss–Legendre nodes over the span the bin averages.

    A bin of m consecutive readings (interval Δ each) is their mean, which equals the mean of the
    sensed load factor over their joint span (t_first − Δ, t_last]; M = ⌈span/10 ms⌉ nodes cover it,
    ⌈span/2 ms⌉ where the load is high (:data:`FINE_STEP`).
    """

    node_time: np.ndarray     # (K,) s, increasing
    node_weight: np.ndarray   # (K,) each bin's weights sum to 1
    first_node: np.ndarray    # (N,) index of each bin's first node
    q_ref: np.ndarray         # (N,) the best-estimate q̄ that maps a bin's mean reading to drag-area units
    first_reading: np.ndarray  # (N,) index of each bin's first reading
    readings: np.ndarray      # (N,) readings per bin


def reading_edges(test: FlightTest, time, interval):
    """Edges of the reading bins: one reading per bin near each stage start, up to 0.1 s elsewhere."""
    width = np.full(time.size, STEADY_BIN)
    for p in test.parachutes:
        before, after = TRANSIENT_WINDOW[p.inflation]
        for st in p.stages:
            near = (time >= st.start - before - 4 * st.start_sigma) & (time <= st.start + after + 4 * st.start_sigma)
            width[near] = np.minimum(width[near], TRANSIENT_BIN[p.inflation])
    per_bin = np.maximum(1, np.floor(width / max(interval, 1e-9) + 1e-9).astype(int))
    edges, i = [0], 0
    while i < time.size:
        j = i + 1
        while j < time.size and j - i < per_bin[i] and per_bin[j] == per_bin[i]:
            j += 1
        edges.append(j)
        i = j
    return np.asarray(edges)


def logger_observations(test: FlightTest, estimate: air.AirDataEstimate, channels: air.LoggerChannels):
    """The reading bins as drag areas with the best-estimate q̄ (module docstring), and their :class:`ReadingBins`."""
    f = estimate.frame
    t, g = channels.accel_time, channels.accel
    interval = max(channels.accel_interval, 1e-6)
    edges = reading_edges(test, t, interval)
    lo, hi = edges[:-1], edges[1:]
    count = hi - lo
    g_bin = np.add.reduceat(g, lo) / count
    span_start, span_end = t[lo] - interval, t[hi - 1]
    centre = 0.5 * (span_start + span_end)
    q_ref = np.interp(centre, t, f["qbar"].to_numpy())
    excess = g_bin - np.median(g_bin)
    high = excess >= FINE_SHARE * max(excess.max(), 1e-12)
    high = high | np.roll(high, 1) | np.roll(high, -1)
    times, weights, first = [], [], []
    for a, b, fine in zip(span_start, span_end, high):
        m = max(1, int(math.ceil((b - a) / (FINE_STEP if fine else AVERAGING_STEP) - 1e-9)))
        nodes, w = np.polynomial.legendre.leggauss(m)
        first.append(sum(len(x) for x in times))
        times.append(a + (b - a) * (nodes + 1.0) / 2.0)
        weights.append(w / 2.0)
    bins = ReadingBins(np.concatenate(times), np.concatenate(weights), np.asarray(first), q_ref, lo, count)
    n = lo.size
    empty = np.empty((0, n))
    w_stated = test.total_weight
    obs = Observations(
        time=centre, acc=w_stated * g_bin / q_ref - test.vehicle.cds,
        acc_sigma=np.full(n, np.nan), acc_qbar=np.zeros(n),   # LoggerModel sets it from joint_errors
        lc=empty, lc_sigma=empty, lc_qbar=empty, lc_weight_term=empty, lc_index=np.zeros(0, dtype=int),
        samples_per_bin=count, native_time=t,
        native_airspeed=f["airspeed"].to_numpy(), native_qbar=f["qbar"].to_numpy(), native_g=g,
        native_density=f["density"].to_numpy(), native_gamma=np.radians(f["gamma"].to_numpy()),
        stated_vehicle_weight=test.vehicle.weight, stated_vehicle_cds=test.vehicle.cds,
        # the reconstructed q̄ is smooth already, and no load cell of a logger bundle reads these
        native_qbar_smooth=f["qbar"].to_numpy(), native_g_smooth=g)
    return obs, bins


def speed_bend(ch: air.LoggerChannels, times, right):
    """(T,) what the airspeed inside a reading's interval adds to the chord between the readings' speeds.

    The reconstruction holds each reading's deceleration over its interval, so its speed is linear there.
    The true deceleration changes inside the interval (fast during a fill); with the rate k of the readings'
    deceleration (centred difference), a deceleration ā + k·(t − t_mid) keeps the interval's mean and bends
    the speed above the chord by (k/2)·((Δ/2)² − (t − t_mid)²): at 20 Hz, ~0.1 m/s at a fill's middle,
    a 0.3 % error in q̄ otherwise.
    """
    t = ch.accel_time
    decel = air.STANDARD_GRAVITY * ch.accel
    rate = np.gradient(decel, t) if t.size > 2 else np.zeros(t.size)
    j = np.asarray(right)
    width = t[j] - t[j - 1]
    middle = t[j] - 0.5 * width
    inside = (np.asarray(times) > t[j - 1]) & (np.asarray(times) <= t[j])
    return np.where(inside, 0.5 * rate[j] * ((0.5 * width) ** 2 - (np.asarray(times) - middle) ** 2), 0.0)


def joint_errors(ch: air.LoggerChannels, estimate: air.AirDataEstimate, bins: ReadingBins):
    """Cholesky factor and log det of the joint covariance Σ of [receiver samples; reading bins] (g for bins).

    Every term is linear in the readings' errors e_j (variance σ_j²) or is the receiver's own noise:

    * a bin's mean reading holds its own readings' errors (1/m each);
    * the reconstruction integrates every earlier error into its airspeed (:func:`~cpas_bayes.data.
      air_reconstruction.walk_design`), which moves the receiver's residuals and, through q̄ ∝ V², a later
      bin's predicted reading by (2·G/V)·(v̂_bin·δv).

    So the receiver's residuals and the bins' are correlated, a random walk shared by all of them; Σ holds it
    whole. The flight direction, G/V and the sample times come from the best estimate, fixed before sampling.
    """
    reference = air.track(ch, estimate.phi[None])
    latency, scale = float(estimate.phi[8]), float(estimate.phi[6])
    design_r = air.walk_design(ch, reference, latency, scale)
    t = ch.accel_time
    n_read, n_bin = t.size, bins.first_reading.size
    own = np.zeros((n_bin, n_read))
    rows = np.repeat(np.arange(n_bin), bins.readings)
    own[rows, np.arange(n_read)] = 1.0 / bins.readings[rows]
    last = bins.first_reading + bins.readings - 1
    centre = 0.5 * (t[bins.first_reading] - ch.accel_interval + t[last])
    speed = np.interp(centre, t, reference.airspeed[0])
    u_bin = np.column_stack([np.interp(centre, t, reference.air_velocity[0, :, c]) for c in range(3)])
    u_bin /= np.maximum(np.linalg.norm(u_bin, axis=1), 1e-9)[:, None]
    g_bin = np.add.reduceat(ch.accel, bins.first_reading) / bins.readings
    # The airspeed error at the bin's centre, from readings before its span (its own are in ``own``).
    sens, _ = air.error_sensitivity(ch, reference, scale, t[bins.first_reading] - ch.accel_interval, np.zeros(0))
    walk = (2.0 * np.abs(g_bin) / np.maximum(speed, 1.0))[:, None] * np.einsum("bc,bcn->bn", u_bin, sens)
    design = np.vstack([design_r, own + walk])
    cov = (design * ch.accel_sigma**2) @ design.T
    cov[np.diag_indices_from(cov)] += np.concatenate([air.receiver_variance(ch), np.zeros(n_bin)])
    chol = np.linalg.cholesky(cov)
    return chol, float(2.0 * np.log(np.diag(chol)).sum())


class LoggerModel(TestModel):
    """:class:`TestModel` of a logger bundle: the air-data parameters join the inflation parameters."""

    averages_readings = True   # the prediction is each reading's interval mean (fit health words its rate warning so)

    def __init__(self, test: FlightTest, kind_priors: dict, nuisance, decay="linear", extensions=(),
                 cluster="individual", below_previous="drop", estimate=None):
        for ext in extensions:
            if ext.needs_load_cells:
                raise ValueError(f"the {ext.name} term needs the load cells, which a logger bundle does not have; "
                                 "leave it out (added_mass, canopy_breathing, discrepancy and correlated_noise "
                                 "apply)")
        self.channels = air.logger_channels(test)
        self.air_estimate = estimate if estimate is not None else air.best_estimate_trajectory(test)
        self._air_priors = self.air_estimate.priors
        obs, self.bins = logger_observations(test, self.air_estimate, self.channels)
        chol, self._errors_log_det = joint_errors(self.channels, self.air_estimate, self.bins)
        # Receiver first, bins second: L = [[L_rr, 0], [L_gr, L_gg]]. Given the receiver's residuals r, the
        # bins' errors have mean L_gr·L_rr⁻¹·r (the walk the receiver saw) and covariance L_gg·L_ggᵀ.
        k = chol.shape[0] - self.bins.q_ref.size
        self._chol_rr, self._chol_gr, self._chol_gg = chol[:k, :k], chol[k:, :k], chol[k:, k:]
        self._log_det_rr = float(np.log(np.diag(self._chol_rr)).sum())   # ½·log det of each block
        self._log_diag_gg = np.log(np.diag(self._chol_gg))
        # Set before the base class: an extension may whiten while declaring its parameters.
        self._to_reading = self.bins.q_ref / test.total_weight   # drag-area residual -> reading residual, g
        # Per-bin diagnostics (pointwise log-likelihood, residual checks) read the conditional marginal sigmas;
        # set before the base class derives its per-bin constants from them.
        conditional = np.sqrt((self._chol_gg**2).sum(axis=1))
        obs = replace(obs, acc_sigma=test.total_weight * conditional / self.bins.q_ref)
        super().__init__(test, obs, kind_priors, nuisance, decay=decay, extensions=extensions, cluster=cluster,
                         below_previous=below_previous)
        self._air_index = np.array([self.index[n] for n in air.AIR_PARAMETERS])
        self._noise_gnss = self.index["noise_gnss"]
        # the law is evaluated at the averaging nodes, which do the averaging: dCDS/dt there is a point rate
        self.rate_half_width = None
        # The averaging nodes are the same for every row: their interpolation weights on the reconstruction's
        # time base (the readings), once.
        t = self.channels.accel_time
        q = np.clip(self.bins.node_time, t[0], t[-1])
        self._node_right = np.clip(np.searchsorted(t, q, side="left"), 1, t.size - 1)
        self._node_frac = (q - t[self._node_right - 1]) / (t[self._node_right] - t[self._node_right - 1])
        self._node_speed_bend = speed_bend(self.channels, self.bins.node_time, self._node_right)

    # -- parameters -------------------------------------------------------

    def _build_parameters(self):
        params = super()._build_parameters()
        units = dict(zip(air.AIR_PARAMETERS, air.AIR_UNITS))
        for name in air.AIR_PARAMETERS:
            p = self._air_priors[name]
            params.append(Parameter(name, TruncNormal(p.mu, p.sigma, p.low, p.high), units[name], "air data"))
        params.append(Parameter("noise_gnss", self.nuisance_priors["noise_gnss"], "", "nuisance"))
        return params

    def initial_values(self):
        """The best-estimate trajectory's air parameters: the MAP search starts there."""
        return dict(zip(air.AIR_PARAMETERS, self.air_estimate.phi))

    # -- forward model ------------------------------------------------------

    def air_track(self, theta) -> air.AirTrack:
        """The reconstructed flight of each row of θ."""
        return air.track(self.channels, np.atleast_2d(theta)[:, self._air_index])

    def gather_stages(self, theta):
        """As :meth:`TestModel.gather_stages`, plus the reconstruction and each stage's airspeed V_i."""
        theta = np.atleast_2d(theta)
        stage = super().gather_stages(theta)
        tr = self.air_track(theta)
        start = stage["start"]
        B = theta.shape[0]
        stage["track"] = tr
        stage["v_start"] = fp.interpolate_rows(tr.time, tr.airspeed, start.reshape(B, -1)).reshape(start.shape)
        return stage

    def stage_start_airspeed(self, stage):
        return stage["v_start"]     # the fitted track's, not a measured airspeed

    def _predict(self, theta):
        theta = np.atleast_2d(theta)
        values = self.values(theta)
        stage = self.gather_stages(theta)
        tr = stage["track"]
        B, N = theta.shape[0], self.obs.n_bins
        # Speed is linear in time within a reading's interval up to gravity's share (the sensed drag is held
        # there), so speed and density are interpolated and then squared, not q̄ itself.
        right, w = self._node_right, self._node_frac
        speed, rho = tr.airspeed, self.channels.density(tr.altitude)
        v_node = speed[:, right - 1] + w * (speed[:, right] - speed[:, right - 1]) + self._node_speed_bend
        rho_node = rho[:, right - 1] + w * (rho[:, right] - rho[:, right - 1])
        q_node = 0.5 * rho_node * v_node**2
        ctx = Context(self, theta, values, self.bins.node_time, stage)
        if any(ext.reads_air_data for ext in self.extensions):
            ctx.air = self._node_air(tr, right, w, rho_node, v_node, q_node)
        cds, seen, timing = self._extended_drag_areas(ctx)   # seen: with the added mass' d(m_a·V)/dt/q̄
        total_weight = values["vehicle_weight"] + self.chute_weight.sum()
        g_node = q_node * (seen.sum(axis=1) + values["vehicle_cds"][:, None]) / total_weight[:, None]
        weight, first = self.bins.node_weight, self.bins.first_node
        g_mean = np.add.reduceat(g_node * weight, first, axis=1)
        reading = values["accel_scale"][:, None] * g_mean + values["accel_bias"][:, None]
        # What the receiver's residuals say about the walk in these readings (the conditional mean).
        dv, dh = air.gnss_misfit(self.channels, tr)
        z_r = solve_triangular(self._chol_rr, np.concatenate([dv.reshape(B, -1), dh], axis=1).T, lower=True,
                               check_finite=False)
        reading = reading + (self._chol_gr @ z_r).T
        acc = self.stated_total_weight * reading / self.bins.q_ref[None] - self.obs.stated_vehicle_cds
        cds_mean = np.add.reduceat(cds * weight, first, axis=2)
        pred = Prediction(acc=acc, lc=np.empty((B, 0, N)), cds=cds_mean,
                          timing=timing, noise_acc=values["noise_acc"], noise_lc=np.ones(B))
        return pred, z_r.T

    def _node_air(self, tr, right, w, rho, v_node, q_node):
        """(ρ, V, q̄, γ, dρ/dt) at the averaging nodes, (B, 1, N) each, from each walker's reconstruction:
        what a term reading the air data (the added mass) sees in place of measured channels.
        dρ/dt = dρ/dh·dh/dt, the climb rate being the air velocity's up part (the wind is horizontal)."""
        def at_nodes(x):
            return x[:, right - 1] + w * (x[:, right] - x[:, right - 1])

        climb = at_nodes(tr.air_velocity[..., 2])
        h = at_nodes(tr.altitude)
        step = 1.0   # m: the density table is piecewise linear in altitude, far coarser than this
        rho_rate = (self.channels.density(h + step) - self.channels.density(h - step)) / (2 * step) * climb
        gamma = np.arcsin(np.clip(climb / np.maximum(v_node, 1e-9), -1.0, 1.0))
        return tuple(x[:, None, :] for x in (rho, v_node, q_node, gamma, rho_rate))

    def predict(self, theta):
        return self._predict(theta)[0]

    def replicated_noise(self, rng, n):
        """n draws of the bins' errors in drag-area units given the receiver's samples, correlated as the
        likelihood says (no load cells)."""
        z = rng.standard_normal((n, self.obs.n_bins)) @ self._chol_gg.T
        return z * self.stated_total_weight / self.bins.q_ref, np.zeros((n, 0, self.obs.n_bins))

    # -- likelihood -----------------------------------------------------------

    def whiten(self, y):
        """Whiten drag-area residuals y (..., 1, N) of the bins given the receiver: L_gg⁻¹ of the reading
        residuals, along the bins (multiplier excluded)."""
        y = np.asarray(y, float)
        flat = (y * self._to_reading).reshape(-1, y.shape[-1])
        return solve_triangular(self._chol_gg, flat.T, lower=True, check_finite=False).T.reshape(y.shape)

    def whitened_residuals(self, theta, pred):
        """The bins' innovations z (B, 1, N), z ~ N(0, I) under the model, and log det per bin (B, N) of
        their sequential conditional variances λ²·L_ii² (reading units; the sum is log det λ²·Σ_gg)."""
        r = (self.obs.acc[None] - pred.acc) / pred.noise_acc[:, None]
        log_det = 2.0 * (self._log_diag_gg[None] + np.log(pred.noise_acc)[:, None])
        return self.whiten(r[:, None, :]), log_det

    def pointwise_log_likelihood(self, theta, pred=None, by_channel=False):
        """Per bin (B, N): log p(bin i | receiver, bins before i), which sums to the bins' part of the joint;
        an extension's own error model when it has one. ``by_channel``: the base class's per-bin marginals."""
        if by_channel:
            return super().pointwise_log_likelihood(theta, pred, by_channel=True)
        theta = np.atleast_2d(theta)
        pred = self.predict(theta) if pred is None else pred
        if self.replaces_error_model:   # not on the baseline's hot path
            _, ll = self._error_model_pointwise(theta, pred)
            if ll is not None:
                return ll
        z, log_det = self.whitened_residuals(theta, pred)
        return -0.5 * (z[:, 0] ** 2 + log_det + _LOG_2PI)

    def log_likelihood(self, theta):
        """Receiver samples and reading bins jointly normal (:func:`joint_errors`; module docstring), (B,):
        log p(receiver | noise_gnss) + log p(bins | receiver, noise_acc), which is the joint exactly. An
        extension with its own error model replaces the second part."""
        theta = np.atleast_2d(theta)
        pred, z_r = self._predict(theta)
        noise = theta[:, self._noise_gnss]
        k_r = z_r.shape[1]
        receiver = (-0.5 * (z_r**2).sum(axis=1) / noise**2 - k_r * np.log(noise) - self._log_det_rr
                    - 0.5 * k_r * _LOG_2PI)
        if self.replaces_error_model:
            return receiver + self._error_model_total(theta, pred)
        return receiver + self.pointwise_log_likelihood(theta, pred).sum(axis=1)

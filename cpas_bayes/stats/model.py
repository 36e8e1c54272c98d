"""The forward model and likelihood of one flight test, batched over parameter sets.

A :class:`TestModel` is a set of named parameters with priors and a pipeline
that turns a batch of parameter vectors θ (B, D) into predicted observations:

1. inflation: each parachute's drag area CDS_i(t) by the stage law
   (:func:`cpas_bayes.physics.inflation.parachute_drag_area`, with the model's
   ``decay`` and ``below_previous``), V_i = measured airspeed at each sampled
   stage start;
2. extensions may reshape CDS_i (e.g. canopy breathing), add an apparent
   drag area seen by both channels (added mass), change the load-cell
   friction factor in time, or shift the load-cell time base;
3. channels: accelerometer drag area, computed by the reduction with the
   *stated* W_T and CDS_V (Eq. 8)::

       acc = (W_T,stated / W_T) · (Σ CDS_i + CDS_V) − CDS_V,stated

   and each load cell's raw drag area (Eq. 11, before friction scaling)::

       lc_i(t) = [q̄(t−δ)·CDS_i(t−δ) − W_p,i·G(t−δ)] / (s·q̄(t)) + W_p,i·G(t)/q̄(t)

   with s the friction factor (true load / reading) and δ a load-cell lag (a first-order cell's response:
   a weighted sum over a few δ; 0 in the baseline, where lc_i = CDS_i/s + (1 − 1/s)·W_p,i·G/q̄);
4. noise: Gaussian errors, independent from one time bin to the next; within a
   bin the channels share the measured q̄'s error (both Eq. 8 and Eq. 11 divide
   by it), so their covariance is Λ·(D + u·uᵀ)·Λ with D the independent
   variances, u the q̄ part of each channel's 1-sigma and Λ the error
   multipliers per channel group (``noise_acc``, ``noise_lc``). With
   r̃ = r/λ, Sherman–Morrison gives per bin::

       r̃ᵀ(D + uuᵀ)⁻¹r̃ = Σ r̃_c²/d_c² − (Σ r̃_c·u_c/d_c²)² / (1 + Σ u_c²/d_c²)
       log det = Σ log d_c² + log(1 + Σ u_c²/d_c²) + 2·Σ log λ_c

   An extension may replace this (AR(1) errors).

The baseline is the seed's simulation: individual parachutes, the stage law,
no added mass, ideal sensors up to the load-cell scale, independent errors.
Extensions (:mod:`cpas_bayes.stats.model_terms`) plug into the hooks of step 2 and 4
without copying the model.

For the sampler, the baseline's total log-likelihood runs steps 1, 3 and 4 in
one compiled loop per walker
(:func:`cpas_bayes.stats.likelihood_kernel.baseline_quadratic_form`); the numpy
pipeline above stays the reference (``predict``, pointwise values, extensions).

Parameter names: ``<chute>.cds_o``, ``<chute>.s<k>.<name>`` for stage k (1-based)
and name in start, n_p, expopen, ck, tk, eps (ck, tk on infinite-mass stages, and on
finite-mass ones when the kind's priors say ``finite_mass_ck = true``); ``<chute>.d_o``
when the bundle states a ``diameter_sigma`` (D_o enters the stage law only as
n_p·D_o, Eq. 14, so the kernels see n_p·D_o/D_nominal at the nominal D_o); ``vehicle_weight``,
``vehicle_cds``, ``load_scale``, ``noise_acc``, ``noise_lc``; extensions add
their own.

Cluster form (:mod:`cpas_bayes.stats.cluster_form`): ``cluster="individual"``
as above, or ``"composite"``, where the parachutes of one kind inflate in
lockstep on one set of parameters ``cluster.<kind>.*``, tied by the gather
arrays. :meth:`TestModel.parameter_name` maps a parachute's field to its
parameter; :meth:`TestModel.derived` gives every parachute's ``<chute>.cds_o``
and ``<chute>.s<k>.<name>`` in either form.
"""

from __future__ import annotations

import math

import numpy as np

from cpas_bayes.data.bundle import FlightTest
from cpas_bayes.physics.inflation import (below_previous_code, cluster_drag_area, decay_code, stage_fill_map,
                                          stage_role, stage_tag)
from cpas_bayes.stats.cluster_form import chute_prefixes, stage_exchanges, start_prior
from cpas_bayes.stats.likelihood_kernel import baseline_quadratic_form
from cpas_bayes.stats.likelihood_kernel import whitened_residuals as fused_whitened_residuals
from cpas_bayes.stats.load_cells import load_cell_drag_areas
from cpas_bayes.stats.observations import Observations
from cpas_bayes.stats.distributions import TruncNormal
from cpas_bayes.stats.model_parts import Context, Parameter, Prediction, one_error_model
from cpas_bayes.stats.priors import KindPriors, NuisancePriors, PriorSet

_LOG_2PI = math.log(2.0 * math.pi)
_STAGE_FIELDS = ("start", "n_p", "expopen", "ck", "tk", "eps")


def _rows(values, noise):
    """A prediction's channel (B, ...) and its multiplier per row (B,), contiguous, for a compiled kernel."""
    values = np.ascontiguousarray(values, float)
    return values, np.ascontiguousarray(np.broadcast_to(np.asarray(noise, float), values.shape[:1]))


def diameter_prior(nominal, sigma):
    """Prior of a fitted nominal diameter: normal about the stated value, cut at ±4 sigma (and above 0)."""
    return TruncNormal(nominal, sigma, max(nominal - 4 * sigma, 0.05 * nominal), nominal + 4 * sigma)


class TestModel:
    """Parameters, priors and batched likelihood of one flight test.

    ``model(theta)`` returns the log posterior for θ (B, D) as emcee's
    ``vectorize=True`` expects (−inf outside the prior, never NaN).
    """

    __test__ = False  # a flight *test* model, not a pytest class

    def __init__(self, test: FlightTest, obs: Observations, kind_priors: dict, nuisance: NuisancePriors,
                 decay="linear", extensions=(), cluster="individual", below_previous="drop"):
        # The stage law's options, and their codes for the fused kernel (refuses unknown ones).
        self._law_codes = decay_code(decay), below_previous_code(below_previous)
        self.chute_prefix = chute_prefixes(test.parachutes, cluster)   # refuses an unknown form
        self.cluster = cluster
        self.test = test
        self.obs = obs
        self.decay = decay
        self.below_previous = below_previous
        self.extensions = one_error_model(extensions)
        self.kind_priors = kind_priors
        self.nuisance_priors = nuisance
        self.parachutes = test.parachutes
        self.n_chutes = len(test.parachutes)
        self.n_stages = max(len(p.stages) for p in test.parachutes)
        self.stages_per_chute = np.array([len(p.stages) for p in test.parachutes])
        # The error model first: extensions may whiten with it while declaring their parameters.
        self._w_acc = 1.0 / obs.acc_sigma**2
        self._w_lc = 1.0 / obs.lc_sigma**2
        self._a_acc = obs.acc_qbar * self._w_acc
        self._a_lc = obs.lc_qbar * self._w_lc
        self._denom = 1.0 + obs.acc_qbar * self._a_acc + (obs.lc_qbar * self._a_lc).sum(axis=0)
        self._inv_denom = 1.0 / self._denom
        # the per-bin whitening (I − c·vvᵀ)·D^(−½) of :meth:`whiten`, once
        self._white_scale = np.concatenate([np.sqrt(self._w_acc)[None], np.sqrt(self._w_lc)])
        self._white_v = np.concatenate([(obs.acc_qbar * np.sqrt(self._w_acc))[None],
                                        obs.lc_qbar * np.sqrt(self._w_lc)])
        v2 = self._denom - 1.0
        self._white_c = np.where(v2 > 1e-12, (1.0 - 1.0 / np.sqrt(self._denom)) / np.where(v2 > 1e-12, v2, 1.0),
                                 0.5)
        n_channels = 1 + obs.lc.shape[0]
        # Parameter-free part of log N per bin: −½·log det(D + uuᵀ) − ½·C·log 2π.
        self._ll_const = -0.5 * (np.log(obs.acc_sigma**2) + np.log(obs.lc_sigma**2).sum(axis=0)
                                 + np.log(self._denom) + n_channels * _LOG_2PI)
        self.parameters = self._build_parameters()
        self.names = [p.name for p in self.parameters]
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"parameter names are not unique: {self.names}")
        self.prior_set = PriorSet(p.prior for p in self.parameters)
        self.index = {n: i for i, n in enumerate(self.names)}
        self._build_gather()
        self.diameter = np.array([p.diameter for p in test.parachutes])
        self.area_o = math.pi / 4 * self.diameter**2
        self.chute_weight = np.array([p.weight for p in test.parachutes])
        self.stated_total_weight = obs.stated_vehicle_weight + self.chute_weight.sum()
        # The added mass' dCDS/dt at a bin: the difference across the bin's span, the mean rate over the bin
        # that a channel of bin means sees, smooth as the law's kinks cross bins (±1 ms stalled MAP searches).
        step = float(np.median(np.diff(obs.native_time))) if obs.native_time.size > 1 else 0.0
        self.rate_half_width = 0.5 * obs.samples_per_bin * step if step > 0 else None

    # -- parameters -------------------------------------------------------

    @property
    def ndim(self):
        return len(self.parameters)

    @property
    def log_scale(self):
        """Per parameter: True where its prior is lognormal (the sampler's proposal then works in log θ)."""
        return np.array([p.prior.log_scale for p in self.parameters], bool)

    @property
    def name(self):
        return "baseline" if not self.extensions else "+".join(e.name for e in self.extensions)

    def parameter_name(self, chute, field):
        """The parameter holding parachute ``chute``'s (index) ``field`` (``cds_o``, ``s<k>.<name>``), or None."""
        name = f"{self.chute_prefix[chute]}.{field}"
        return name if name in self.index else None

    def exchanges(self):
        """Label exchanges of like parachutes that no channel tells apart (the sampler's
        :class:`~cpas_bayes.inference.moves.ExchangeMove`); none in the composite form."""
        if self.cluster != "individual":
            return []
        return stage_exchanges(self.parachutes, lambda i, field: self.index.get(self.parameter_name(i, field)))

    def _build_parameters(self):
        params = []
        test = self.test
        members = {}
        for p, prefix in zip(test.parachutes, self.chute_prefix):
            members.setdefault(prefix, []).append(p)
        for prefix, group in members.items():
            p = group[0]
            kp: KindPriors = self.kind_priors[p.kind]
            s_o = math.pi / 4 * p.diameter**2
            cd = kp.parachute["cd_o"]
            params.append(Parameter(f"{prefix}.cds_o", cd.scaled(s_o), "m²"))
            if p.diameter_sigma > 0:   # a guessed diameter: D_o fitted within its stated 1-sigma
                params.append(Parameter(f"{prefix}.d_o", diameter_prior(p.diameter, p.diameter_sigma), "m"))
            n = len(p.stages)
            for k in range(n):
                role = stage_role(k, n)
                pre = f"{prefix}.{stage_tag(k)}"
                params.append(Parameter(f"{pre}.start", start_prior([q.stages[k] for q in group]), "s"))
                params.append(Parameter(f"{pre}.n_p", kp.for_stage(role, "n_p")))
                params.append(Parameter(f"{pre}.expopen", kp.for_stage(role, "expopen")))
                if p.inflation == "infinite" or kp.finite_mass_ck:   # finite mass: only where the prior allows
                    params.append(Parameter(f"{pre}.ck", kp.for_stage(role, "ck")))
                    params.append(Parameter(f"{pre}.tk", kp.for_stage(role, "tk"), "s"))
                if k < n - 1:
                    params.append(Parameter(f"{pre}.eps", kp.for_stage(role, "eps")))
        v = test.vehicle
        params.append(Parameter("vehicle_weight",
                                TruncNormal(v.weight, max(v.weight_sigma, 1e-6 * v.weight), 0.5 * v.weight,
                                            1.5 * v.weight), "N", "nuisance"))
        params.append(Parameter("vehicle_cds",
                                TruncNormal(v.cds, max(v.cds_sigma, 1e-3), 0.0, v.cds + 10 * max(v.cds_sigma, 1e-3)),
                                "m²", "nuisance"))
        has_lc = any(p.load_cell for p in test.parachutes)
        params.append(Parameter("noise_acc", self.nuisance_priors["noise_acc"], "", "nuisance"))
        if has_lc:
            params.append(Parameter("load_scale", self.nuisance_priors["load_scale"], "", "nuisance"))
            params.append(Parameter("noise_lc", self.nuisance_priors["noise_lc"], "", "nuisance"))
        for ext in self.extensions:
            for prm in ext.parameters(self):
                params.append(prm)
        return params

    def _build_gather(self):
        """Index arrays that gather (B, D) θ into (B, P, K) stage arrays; constants sit past D."""
        P, K, D = self.n_chutes, self.n_stages, self.ndim
        constants = {"one": D, "zero": D + 1}
        self._constants = np.array([1.0, 0.0])
        gather = {name: np.full((P, K), -1, dtype=int) for name in _STAGE_FIELDS}
        self.stage_mask = np.zeros((P, K), dtype=bool)
        for i, p in enumerate(self.parachutes):
            n = len(p.stages)
            for k in range(K):
                kk = min(k, n - 1)  # pad short parachutes by repeating their last stage
                pre = f"{self.chute_prefix[i]}.{stage_tag(kk)}"
                self.stage_mask[i, k] = k < n
                for name in gather:
                    key = f"{pre}.{name}"
                    if key in self.index:
                        gather[name][i, k] = self.index[key]
                    elif name == "ck" or name == "eps":
                        gather[name][i, k] = constants["one"]
                    elif name == "tk":
                        gather[name][i, k] = constants["zero"]
                if k >= n:  # padded stage: starts after the data end, never active
                    gather["start"][i, k] = -2
        self._gather = gather
        self._cds_o_index = np.array([self.index[f"{prefix}.cds_o"] for prefix in self.chute_prefix])
        # The same gather for the fused kernel, which never reads padded stages.
        stacked = np.stack(list(gather.values()))
        self._gather_array = np.where(stacked < 0, constants["zero"], stacked).astype(np.int64)
        # Without load cells there is no load_scale or noise_lc; the kernel then reads neither.
        self._scalar_index = np.array([self.index.get(n, 0) for n in
                                       ("vehicle_weight", "vehicle_cds", "noise_acc", "load_scale", "noise_lc")],
                                      dtype=np.int64)
        # Columns of each parachute's consecutive stage starts, for the prior's ordering check.
        # (A composite group's parachutes share their columns: each pair once.)
        pairs = list(dict.fromkeys((int(gather["start"][i, k]), int(gather["start"][i, k + 1]))
                                   for i, n in enumerate(self.stages_per_chute) for k in range(n - 1)))
        self._start_order = tuple(np.ascontiguousarray(a) for a in np.array(pairs, dtype=np.int64).reshape(-1, 2).T)
        # A fitted diameter enters the stage law only through n_p·D_o (Eq. 14), so the kernels keep the
        # nominal D_o and see n_p scaled by D_o/D_nominal: per n_p column, its d_o column and D_nominal.
        scaled = []
        for prefix, p in dict(zip(self.chute_prefix, self.parachutes)).items():
            if f"{prefix}.d_o" in self.index:
                scaled += [(self.index[f"{prefix}.{stage_tag(k)}.n_p"], self.index[f"{prefix}.d_o"], p.diameter)
                           for k in range(len(p.stages))]
        self._np_scaling = tuple(np.array(c) for c in zip(*scaled)) if scaled else None

    def effective_theta(self, theta):
        """θ as the stage law reads it: with a fitted diameter, n_p columns times D_o/D_nominal (the law
        holds the nominal D_o); θ itself otherwise."""
        if self._np_scaling is None:
            return theta
        cols, d_cols, nominal = self._np_scaling
        theta = np.array(theta, dtype=float, copy=True)
        theta[:, cols] *= theta[:, d_cols] / nominal
        return theta

    def diameter_ratio(self, theta):
        """D_o/D_nominal per row and parachute (B, P): 1 where the diameter is not fitted."""
        ratio = np.ones((theta.shape[0], self.n_chutes))
        for i, prefix in enumerate(self.chute_prefix):
            j = self.index.get(f"{prefix}.d_o")
            if j is not None:
                ratio[:, i] = theta[:, j] / self.diameter[i]
        return ratio

    def gather_stages(self, theta):
        """Stage arrays (B, P, K) from θ (B, D): start, n_p, expopen, ck, tk, eps, cds_stage."""
        B = theta.shape[0]
        theta = self.effective_theta(theta)
        ext = np.concatenate([theta, np.broadcast_to(self._constants, (B, 2))], axis=1)
        out = {}
        for name, idx in self._gather.items():
            if name == "start":
                safe = np.where(idx == -2, 0, idx)
                vals = ext[:, safe]
                out[name] = np.where(idx == -2, self.obs.native_time[-1] + 1e3, vals)
            else:
                out[name] = ext[:, idx]
        out["cds_o"] = theta[:, self._cds_o_index]
        out["cds_stage"] = out["eps"] * out["cds_o"][:, :, None]
        return out

    def replicated_noise(self, rng, n):
        """n draws of the observations' errors before the multipliers: accelerometer (n, N) and load cells
        (n, L, N), independent parts plus one shared q̄ draw per bin (the likelihood's error structure)."""
        obs = self.obs
        shared = rng.standard_normal((n, obs.n_bins))
        acc = obs.acc_sigma * rng.standard_normal((n, obs.n_bins)) + obs.acc_qbar * shared
        lc = obs.lc_sigma * rng.standard_normal((n,) + obs.lc.shape) + obs.lc_qbar * shared[:, None, :]
        return acc, lc

    def initial_values(self):
        """{parameter: value} the data fix before any fit (the MAP search's first guess uses them); none here."""
        return {}

    def values(self, theta):
        """Named view of θ: {name: (B,)}."""
        return {n: theta[:, i] for i, n in enumerate(self.names)}

    # -- prior ----------------------------------------------------------------

    def log_prior(self, theta):
        """Log prior (B,): :attr:`prior_set` with −inf where a parachute's stages are out of order."""
        theta = np.atleast_2d(theta)
        lp = self.prior_set.logpdf(theta)
        earlier, later = self._start_order
        ordered = np.all(theta[:, later] > theta[:, earlier], axis=1)
        return np.where(ordered & np.isfinite(lp), lp, -np.inf)

    def sample_prior(self, rng, size):
        """Draws from the prior (B, D), each column by inverse transform."""
        return np.column_stack([p.prior.sample(rng, size) for p in self.parameters])

    # -- forward model ------------------------------------------------------

    def stage_start_airspeed(self, stage):
        """V_i of every stage (B, P, K): the measured airspeed at its start."""
        return self.obs.airspeed_at(stage["start"])

    def drag_areas(self, stage, t, with_rate=False):
        """Per-parachute drag areas (B, P, N) at times ``t`` (N,) or (B, 1, N) and the stage timing;
        ``with_rate``: (drag areas, their time derivative, timing)."""
        if np.ndim(t) == 3:  # (B, 1, N): one time base per row
            t = t[:, 0, :]
        half = self.rate_half_width
        half = half if with_rate and half is not None and np.shape(t)[-1] == half.size else None
        return cluster_drag_area(
            t, stage["start"], stage["cds_stage"], stage["cds_o"], self.diameter,
            stage["n_p"], stage["expopen"], stage["ck"], stage["tk"], self.stage_start_airspeed(stage),
            n_stages=self.stages_per_chute, decay=self.decay, fill_constant="n_p",
            below_previous=self.below_previous, with_rate=with_rate, rate_half_width=half)

    def fill_map(self, theta, kind=0, ref_time=1.0):
        """:class:`FillMap` of every stage (B, P, K) at θ (B, D) whose n_p columns hold what ``kind`` (P, K)
        says: n_p, the seconds to peak t_fp = n_p·s, or the drag area grown by ``ref_time`` (:func:`stage_fill_map`)."""
        stage = self.gather_stages(np.atleast_2d(theta))
        return stage_fill_map(stage["start"], stage["cds_stage"], stage["cds_o"], self.diameter, stage["n_p"],
                              stage["expopen"], stage["ck"], stage["tk"], self.stage_start_airspeed(stage),
                              self.stages_per_chute, self.decay, self.below_previous, kind, ref_time)

    def predict(self, theta):
        theta = np.atleast_2d(theta)
        obs = self.obs
        values = self.values(theta)
        stage = self.gather_stages(theta)
        ctx = Context(self, theta, values, obs.time, stage)
        t = obs.time
        cds, seen, timing = self._extended_drag_areas(ctx)

        weight_ratio = self.stated_total_weight / (values["vehicle_weight"] + self.chute_weight.sum())
        cds_v = values["vehicle_cds"]
        acc = weight_ratio[:, None] * (seen.sum(axis=1) + cds_v[:, None]) - obs.stated_vehicle_cds

        lc = np.empty((theta.shape[0], obs.lc_index.size, t.size))
        if obs.lc_index.size:
            lc = load_cell_drag_areas(self, ctx, seen, t)
        noise_lc = values.get("noise_lc", np.ones(theta.shape[0]))
        return Prediction(acc=acc, lc=lc, cds=cds, timing=timing,
                          noise_acc=values["noise_acc"], noise_lc=noise_lc)

    def _extended_drag_areas(self, ctx):
        """(cds, seen, timing) at ``ctx.time``: the stage law's drag areas reshaped by the extensions, and
        ``seen``, those plus the momentum terms' apparent drag area (what the channels see)."""
        t = ctx.time
        if any(ext.needs_drag_area_rate for ext in self.extensions):   # one pass of the law for both
            cds, rate, timing = self.drag_areas(ctx.stage, t, with_rate=True)
            ctx.law = (cds, rate)
        else:
            cds, timing = self.drag_areas(ctx.stage, t)
        ctx.stage["timing"] = timing
        for ext in self.extensions:
            cds = ext.reshape_drag_area(ctx, cds, t)
        apparent = self.apparent_drag_area(ctx, t)
        return cds, (cds if apparent is None else cds + apparent), timing

    def apparent_drag_area(self, ctx, t):
        """The momentum terms' apparent drag area (B, P, N) at ``t``, summed; None without one."""
        total = None
        for ext in self.extensions:
            extra = ext.apparent_drag_area(ctx, t)
            if extra is not None:
                total = extra if total is None else total + extra
        return total

    # -- likelihood -----------------------------------------------------------

    def _quadratic_form(self, theta, pred):
        """Per-bin r̃ᵀ(D + uuᵀ)⁻¹r̃ (B, N) and the per-channel parts of its diagonal."""
        obs = self.obs
        r_acc = (obs.acc[None, :] - pred.acc) / pred.noise_acc[:, None]
        r_lc = (obs.lc[None] - pred.lc) / pred.noise_lc[:, None, None]
        shared = r_acc * self._a_acc + (r_lc * self._a_lc).sum(axis=1)
        diag_acc = r_acc**2 * self._w_acc
        diag_lc = r_lc**2 * self._w_lc
        return diag_acc + diag_lc.sum(axis=1) - shared**2 / self._denom, r_acc, r_lc

    def whiten(self, y):
        """Apply the per-bin whitening Σ_b^(−½) (multipliers excluded) to drag-area residuals y (..., C, N).

        Channels are ordered accelerometer, then the load cells. With v = D^(−½)u,
        (I + vvᵀ)^(−½) = I − c·vvᵀ, c = (1 − 1/√(1 + |v|²))/|v|², so
        z = (I − c·vvᵀ)·D^(−½)·y and zᵀz is the quadratic form of the likelihood.
        """
        y = np.asarray(y, float) * self._white_scale
        v, c = self._white_v, self._white_c
        return y - c * v * (v * y).sum(axis=-2, keepdims=True)

    def whitened_residuals(self, theta, pred):
        """Residuals whitened with the per-bin covariance: z (B, C, N) with z ~ N(0, I) under the model.

        :meth:`whiten` of the residuals divided by their channel's error
        multiplier. Also returns log det Σ per bin (B, N) (with the multipliers).
        """
        obs = self.obs
        z = fused_whitened_residuals(obs.acc, *_rows(pred.acc, pred.noise_acc), obs.lc,
                                     *_rows(pred.lc, pred.noise_lc), self._white_scale, self._white_v,
                                     self._white_c)
        log_det = -2.0 * (self._ll_const + 0.5 * (1 + obs.lc.shape[0]) * _LOG_2PI) \
            + 2.0 * self._log_multipliers(pred)[:, None]
        return z, log_det

    def _log_multipliers(self, pred):
        """Σ_c log λ_c per bin (B,): one accelerometer channel and L load cells."""
        return np.log(pred.noise_acc) + self.obs.lc.shape[0] * np.log(pred.noise_lc)

    def pointwise_log_likelihood(self, theta, pred=None, by_channel=False):
        """Log-likelihood per time bin (B, N), all channels jointly.

        With ``by_channel`` returns ``(acc (B, N), lc (B, L, N))``: each channel's
        *marginal* log density (variance λ²·(d² + u²)), for per-channel diagnostics;
        their sum is not the joint value because of the shared q̄ error.
        """
        theta = np.atleast_2d(theta)
        pred = self.predict(theta) if pred is None else pred
        ext, ll = self._error_model_pointwise(theta, pred)
        if ll is not None:
            if by_channel:
                raise ValueError(f"the {ext.name} error model has no per-channel log-likelihood; "
                                 "ask for the joint one (by_channel=False)")
            return ll
        obs = self.obs
        if by_channel:
            var_acc = pred.noise_acc[:, None] ** 2 * (obs.acc_sigma**2 + obs.acc_qbar**2)
            var_lc = pred.noise_lc[:, None, None] ** 2 * (obs.lc_sigma**2 + obs.lc_qbar**2)
            ll_acc = -0.5 * ((obs.acc - pred.acc) ** 2 / var_acc + np.log(var_acc) + _LOG_2PI)
            ll_lc = -0.5 * ((obs.lc - pred.lc) ** 2 / var_lc + np.log(var_lc) + _LOG_2PI)
            return ll_acc, ll_lc
        quad, _, _ = self._quadratic_form(theta, pred)
        return -0.5 * quad - self._log_multipliers(pred)[:, None] + self._ll_const

    def _error_model_pointwise(self, theta, pred):
        """(term, pointwise values (B, N)) of the first extension with an error model of its own, else (None, None)."""
        ctx = Context(self, theta, self.values(theta), self.obs.time)
        for ext in self.extensions:
            ll = ext.log_likelihood(ctx, pred, self.obs)
            if ll is not None:
                return ext, ll
        return None, None

    def _error_model_total(self, theta, pred):
        """The joint log-likelihood (B,) under an extension's own error model: its total where it has one
        (a marginalised discrepancy), else the sum of the pointwise values."""
        ctx = Context(self, theta, self.values(theta), self.obs.time)
        for ext in self.extensions:
            total = ext.total_log_likelihood(ctx, pred, self.obs)
            if total is not None:
                return total
        return self.pointwise_log_likelihood(theta, pred).sum(axis=1)

    @property
    def replaces_error_model(self):
        """True when an extension brings its own error model (no per-channel log-likelihood then)."""
        return any(ext.brings_error_model() for ext in self.extensions)

    def log_likelihood(self, theta):
        """Total log-likelihood (B,), the sum of :meth:`pointwise_log_likelihood` over bins."""
        theta = np.atleast_2d(theta)
        if not self.extensions:
            return self._baseline_log_likelihood(theta)
        pred = self.predict(theta)
        if self.replaces_error_model:
            return self._error_model_total(theta, pred)
        quad, _, _ = self._quadratic_form(theta, pred)
        return (-0.5 * quad.sum(axis=1) - self.obs.n_bins * self._log_multipliers(pred)
                + self._ll_const.sum())

    def _baseline_log_likelihood(self, theta):
        """log_likelihood without extensions by the fused kernel (the sampler's hot path)."""
        theta = np.ascontiguousarray(theta, dtype=float)
        obs = self.obs          # read per call: checks and tests swap in edited observations
        quad = np.empty(theta.shape[0])
        baseline_quadratic_form(
            np.ascontiguousarray(self.effective_theta(theta)), self._constants, self._gather_array, self._cds_o_index, self.diameter,
            self.stages_per_chute, *self._law_codes, obs.native_time, obs.native_airspeed,
            obs.time, obs.acc, obs.lc, obs.lc_weight_term, obs.lc_index, self._scalar_index,
            float(obs.stated_vehicle_cds), float(self.stated_total_weight), float(self.chute_weight.sum()),
            self._w_acc, self._a_acc, self._w_lc, self._a_lc, self._inv_denom, quad)
        idx = self._scalar_index
        log_multipliers = np.log(theta[:, idx[2]])
        if obs.lc_index.size:
            log_multipliers = log_multipliers + obs.lc.shape[0] * np.log(theta[:, idx[4]])
        return -0.5 * quad - obs.n_bins * log_multipliers + self._ll_const.sum()

    def log_posterior(self, theta):
        theta = np.atleast_2d(theta)
        lp = self.log_prior(theta)
        out = np.full(theta.shape[0], -np.inf)
        ok = np.isfinite(lp)
        if ok.any():
            ll = self.log_likelihood(theta[ok])
            out[ok] = np.where(np.isfinite(ll), lp[ok] + ll, -np.inf)
        return out

    __call__ = log_posterior

    # -- derived quantities ------------------------------------------------------

    def derived(self, theta):
        """Per-stage derived quantities {name: (B,)}: n (Eq. 18), eps, cds, t_f, t_fp.

        In the composite form also each parachute's view of its group's parameters
        (``<chute>.cds_o``, ``<chute>.s<k>.start``, ...), under the individual form's names.
        """
        theta = np.atleast_2d(theta)
        stage = self.gather_stages(theta)
        _, timing = self.drag_areas(stage, self.obs.time[:1])
        ratio = self.diameter_ratio(theta)
        out = {}
        for i, p in enumerate(self.parachutes):
            if p.id != self.chute_prefix[i]:
                out[f"{p.id}.cds_o"] = stage["cds_o"][:, i]
            for k in range(len(p.stages)):
                pre = f"{p.id}.{stage_tag(k)}"
                for name in _STAGE_FIELDS[:5]:
                    tied = self.parameter_name(i, f"{stage_tag(k)}.{name}")
                    if tied is not None and tied != f"{pre}.{name}":
                        out[f"{pre}.{name}"] = theta[:, self.index[tied]]
                out[f"{pre}.n"] = timing.n[:, i, k] / ratio[:, i]   # the law saw n_p·D_o/D_nominal
                out[f"{pre}.eps"] = stage["eps"][:, i, k]
                out[f"{pre}.cds"] = stage["cds_stage"][:, i, k]
                out[f"{pre}.t_f"] = timing.t_f[:, i, k]
                out[f"{pre}.t_fp"] = timing.t_fp[:, i, k]
        return out

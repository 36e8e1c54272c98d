"""A generic model discrepancy: what the simulation misses, whatever it is.

Kennedy–O'Hagan style, each channel's drag area gets a smooth additive term
δ_c(t) on top of the simulation (the physics of every named term included)::

    y_c(t_i) = prediction_c(t_i; θ) + δ_c(t_i) + ε_c,i,
    δ_c(t) = λ_c · s_c · Σ_m e_c,m · b_c,m · φ_m(t),      b ~ N(0, σ_δ² I)

φ_m are cubic B-splines uniform in *bin index*: the bins are 0.02 s wide
around stage starts and 0.1 s in steady flight, so knots every ``knot_bins``
bins resolve a fill (0.1 s apart there) while staying coarse where nothing
happens. s_c is the channel's median 1-sigma, so σ_δ is the discrepancy's size
in units of the stated noise; λ_c is the channel's error multiplier (so the
term is independent of it after whitening); e_c,m is the baseline's local
residual excess at the basis function's centre (:func:`residual_envelope`),
which gives the term room where the baseline misses and almost none where it
fits. One hyperparameter σ_δ with a
lognormal prior of median 0.05 (sampled as log σ_δ) keeps the term off unless the data need it:
at σ_δ → 0 the model is the baseline exactly, bin by bin.

The coefficients are integrated out. With z = Σ^(−½)·r the whitened residuals
(:meth:`TestModel.whiten`, channels and the shared q̄ error), Φ̃ the whitened
basis (C·N × M), G = Φ̃ᵀΦ̃ = U·diag(g)·Uᵀ (once), p = Uᵀ·Φ̃ᵀ·z and
w_j = σ_δ²/(1 + σ_δ²·g_j)::

    log p(y | θ, σ_δ) = baseline(θ) + ½·Σ_j w_j·p_j² − ½·Σ_j log(1 + σ_δ²·g_j)

Pointwise values for PSIS-LOO are the exact leave-one-bin-out conditionals
log p(y_i | y_−i, θ, σ_δ) of this Gaussian (Bürkner, Gabry & Vehtari 2021,
non-factorised normal models): with Q = (I + σ_δ²·Φ̃Φ̃ᵀ)⁻¹ = I − Ψ·diag(w)·Ψᵀ,
Ψ = Φ̃·U, and g = Q·z::

    z_i | z_−i ~ N(z_i − Q_ii⁻¹·g_i, Q_ii⁻¹)
    ⇒ log p = −½·(g_iᵀ·Q_ii⁻¹·g_i − log det Q_ii + C·log 2π + log det Σ_i)

The fitted shape — the conditional posterior mean of δ_c(t) with its
spread — is :func:`discrepancy_shape`: where in time and in which channel the
simulation is wrong.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse
from scipy.interpolate import BSpline

from cpas_bayes.stats.distributions import TruncNormal
from cpas_bayes.stats.model_parts import Extension, Parameter

_LOG_2PI = math.log(2.0 * math.pi)
KNOT_BINS = 6            # bins between knots: 0.12 s in a transient, 0.6 s in steady flight
# log σ_δ (σ_δ in units of each channel's noise): lognormal σ_δ, median 0.05, spread factor e²; sampled as
# its log because the posterior spans decades when nothing is missing
DISCREPANCY_PRIOR = TruncNormal(math.log(0.05), 2.0, math.log(1e-4), math.log(1e3))
ENVELOPE_FLOOR = 0.1     # the envelope's floor: where the baseline fits, a tenth of the noise
LOO_BATCH = 64           # draws per chunk of the pointwise values (memory: batch·N·C² doubles)


def channel_sigma(obs):
    """Each channel's total random 1-sigma per bin (C, N): accelerometer, then the load cells."""
    return np.concatenate([np.hypot(obs.acc_sigma, obs.acc_qbar)[None], np.hypot(obs.lc_sigma, obs.lc_qbar)])


def spline_basis(n_bins, knot_bins=KNOT_BINS):
    """Cubic B-spline design matrix (n_bins × M), uniform knots every ``knot_bins`` bin indices."""
    intervals = max(1, int(round((n_bins - 1) / knot_bins)))
    inner = np.linspace(0.0, n_bins - 1.0, intervals + 1)
    knots = np.concatenate([[inner[0]] * 3, inner, [inner[-1]] * 3])
    return BSpline.design_matrix(np.arange(n_bins, dtype=float), knots, 3).toarray()


def drag_area_basis(obs, envelope=None, knot_bins=KNOT_BINS):
    """The discrepancy's basis in drag-area units, (C·K, C, N): channel c's K splines, each scaled by the
    channel's median 1-sigma s_c and the envelope at its centre (``None``: 1); and s_c (C,), m²."""
    n, channels = obs.n_bins, 1 + obs.lc.shape[0]
    phi = spline_basis(n, knot_bins)                                        # (N, K)
    k = phi.shape[1]
    channel_scale = np.median(channel_sigma(obs), axis=1)
    local = np.ones((channels, n)) if envelope is None else envelope
    centre = np.clip(np.argmax(phi, axis=0), 0, n - 1)
    raw = np.zeros((channels * k, channels, n))
    for c in range(channels):
        # each basis function's prior scale: the channel's noise times the envelope at its centre
        raw[c * k:(c + 1) * k, c, :] = (channel_scale[c] * local[c, centre])[:, None] * phi.T
    return raw, channel_scale


class Discrepancy(Extension):
    """The generic discrepancy term (see the module docstring); ``name = "discrepancy"``."""

    name = "discrepancy"

    def __init__(self, knot_bins=KNOT_BINS, envelope=None):
        self.knot_bins = knot_bins
        self.envelope = envelope      # (C, N) prior scale per channel and bin, in noise units (≥ 1), or None

    def parameters(self, model):
        self._prepare(model)
        return [Parameter("discrepancy_log_scale", DISCREPANCY_PRIOR, "", self.name)]

    def start_points(self, model):
        return [{"discrepancy_log_scale": math.log(v)} for v in (0.05, 0.5, 3.0)]

    # -- the whitened basis, once per model ---------------------------------------

    def _prepare(self, model):
        obs = model.obs
        n, channels = obs.n_bins, 1 + obs.lc.shape[0]
        raw, self.channel_scale = drag_area_basis(obs, self.envelope, self.knot_bins)   # s_c (C,), m²
        white = model.whiten(raw).reshape(raw.shape[0], channels * n)      # Φ̃ᵀ (M, C·N)
        gram = white @ white.T
        g, u = np.linalg.eigh(gram)
        self.eigenvalues = np.clip(g, 0.0, None)                            # (M,)
        self._rotation = u                                                  # U (M, M)
        self._white_t = sparse.csr_matrix(np.where(np.abs(white) > 1e-14 * np.abs(white).max(), white, 0.0))
        self._psi = (u.T @ white).reshape(-1, channels, n)                  # Ψᵀ (M, C, N)
        # ψ_ij ψ_ijᵀ per basis direction j and bin i, flattened (M, C·C·N): the Q_ii blocks are
        # then one matrix product per chunk of draws
        self._psi_outer = np.einsum("mcn,mdn->mcdn", self._psi, self._psi).reshape(self._psi.shape[0], -1)
        self._raw_rotated = (u.T @ raw.reshape(raw.shape[0], channels * n)).reshape(-1, channels, n)  # (Φ·U)ᵀ
        self.n_channels, self.n_bins = channels, n

    def _projections(self, z):
        """p = Uᵀ·Φ̃ᵀ·z for z (B, C, N): (B, M)."""
        flat = z.reshape(z.shape[0], -1)
        return (self._rotation.T @ (self._white_t @ flat.T)).T

    def _weights(self, scale):
        s2 = scale[:, None] ** 2
        return s2 / (1.0 + s2 * self.eigenvalues[None, :])                # (B, M)

    # -- likelihood hooks -------------------------------------------------------

    def total_log_likelihood(self, ctx, pred, obs):
        z, log_det = ctx.model.whitened_residuals(ctx.theta, pred)
        scale = np.exp(ctx.values["discrepancy_log_scale"])
        p = self._projections(z)
        w = self._weights(scale)
        quad = (z**2).sum(axis=(1, 2)) - (w * p**2).sum(axis=1)
        occam = np.log1p(scale[:, None] ** 2 * self.eigenvalues[None, :]).sum(axis=1)
        return -0.5 * (quad + occam + log_det.sum(axis=1) + self.n_channels * self.n_bins * _LOG_2PI)

    def log_likelihood(self, ctx, pred, obs):
        """Leave-one-bin-out conditionals log p(y_i | y_−i, θ) (B, N), in chunks of draws."""
        z, log_det = ctx.model.whitened_residuals(ctx.theta, pred)
        scale = np.exp(ctx.values["discrepancy_log_scale"])
        out = np.empty((z.shape[0], z.shape[2]))
        eye = np.eye(self.n_channels)
        for lo in range(0, z.shape[0], LOO_BATCH):
            sl = slice(lo, lo + LOO_BATCH)
            w = self._weights(scale[sl])                                    # (b, M)
            p = self._projections(z[sl])
            g = z[sl] - np.einsum("bm,mcn->bcn", w * p, self._psi)          # Q·z
            # Q_ii = I − Σ_j w_j ψ_ij ψ_ijᵀ per bin: (b, N, C, C)
            c, n = self.n_channels, self.n_bins
            q = eye - np.moveaxis((w @ self._psi_outer).reshape(-1, c, c, n), 3, 1)
            sign, logdet_q = np.linalg.slogdet(q)
            gi = np.moveaxis(g, 1, 2)[..., None]                            # (b, N, C, 1)
            solved = np.linalg.solve(q, gi)[..., 0]
            quad = (gi[..., 0] * solved).sum(axis=-1)
            out[sl] = -0.5 * (quad - logdet_q + self.n_channels * _LOG_2PI + log_det[sl])
        return out

    # -- the fitted shape ---------------------------------------------------------

    def shape(self, model, theta, pred):
        """Conditional posterior mean and variance of δ (B, C, N) in drag-area units at θ (B, D)."""
        ctx_values = model.values(theta)
        z, _ = model.whitened_residuals(theta, pred)
        scale = np.exp(ctx_values["discrepancy_log_scale"])
        w = self._weights(scale)
        p = self._projections(z)
        multipliers = np.concatenate([pred.noise_acc[:, None], np.repeat(pred.noise_lc[:, None],
                                                                          self.n_channels - 1, axis=1)], axis=1)
        mean = np.einsum("bm,mcn->bcn", w * p, self._raw_rotated) * multipliers[:, :, None]
        var = np.einsum("bm,mcn->bcn", w, self._raw_rotated**2) * multipliers[:, :, None] ** 2
        return mean, var


def residual_envelope(model, theta, half_width=KNOT_BINS):
    """The local excess of the standardised residuals at θ over their stated noise (C, N):
    sqrt(max(RMS² − 1, 0.1²)), the RMS over ±``half_width`` bins.

    The discrepancy's prior scale follows it. A global scale alone would have
    to grow everywhere to fit a misfit that sits in one transient, paying the
    Occam factor of every basis direction the data pin at zero (a few hundred
    directions of ½·log(1 + σ²·g) each); with the envelope the discrepancy has
    room where the baseline misses and almost none where it fits. The
    envelope is read off the baseline's MAP, the same for every model with the
    discrepancy in one diagnosis; on a test the baseline fits it is ~0.1–0.6
    and the term stays off.
    """
    pred = model.predict(np.atleast_2d(theta))
    obs = model.obs
    r = np.concatenate([(obs.acc - pred.acc[0])[None], obs.lc - pred.lc[0]]) / channel_sigma(obs)
    kernel = np.ones(2 * half_width + 1) / (2 * half_width + 1)
    mean_square = np.array([np.convolve(np.pad(x**2, half_width, mode="edge"), kernel, mode="valid") for x in r])
    return np.sqrt(np.maximum(mean_square - 1.0, ENVELOPE_FLOOR**2))


def discrepancy_shape(model, theta, predict=None):
    """Posterior mean and sd (C, N) of the discrepancy over draws θ (S, D) of a model holding a
    :class:`Discrepancy`: the mean over draws of the conditional means, and the total spread
    (mean conditional variance plus the variance of the conditional means)."""
    term = next(e for e in model.extensions if isinstance(e, Discrepancy))
    theta = np.atleast_2d(theta)
    pred = (predict or model.predict)(theta)
    mean, var = term.shape(model, theta, pred)
    m = mean.mean(axis=0)
    sd = np.sqrt(var.mean(axis=0) + mean.var(axis=0))
    return m, sd

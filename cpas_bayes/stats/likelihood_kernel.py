"""The compiled likelihood of the baseline model: predict and quadratic form fused per walker.

:class:`cpas_bayes.stats.model.TestModel` without extensions hands its
log-likelihood to :func:`baseline_quadratic_form`: for each row of θ it
gathers the stage parameters (through the model's gather arrays, so tied
parameters of a composite cluster need nothing here), runs the stage law of
each parachute, forms the accelerometer (Eq. 8) and load-cell (Eq. 11)
predictions and sums the per-bin quadratic form r̃ᵀ(D + uuᵀ)⁻¹r̃ (the
Sherman–Morrison form of :mod:`cpas_bayes.stats.model`). The numpy pipeline of
the model (``predict``, ``pointwise_log_likelihood``) stays the reference the
tests hold this kernel to.
"""

from __future__ import annotations

import numba
import numpy as np

from cpas_bayes.physics.inflation import parachute_stage_law


@numba.njit(cache=True)
def interp(x, xp, fp):
    """np.interp at one point (same formula and end clamping), without numba's per-call array."""
    n = xp.shape[0]
    if np.isnan(x):
        return x
    if x < xp[0]:
        return fp[0]
    j = np.searchsorted(xp, x, side="right") - 1
    if j >= n - 1 or xp[j] == x:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    return slope * (x - xp[j]) + fp[j]


@numba.njit(cache=True)
def baseline_quadratic_form(theta, consts, gather, cds_o_index, diameter, n_stages, decay, below_previous,
                            native_time, native_airspeed, t, acc_obs, lc_obs, lc_weight_term, lc_index, scalars,
                            stated_vehicle_cds, stated_total_weight, chute_weight_sum,
                            w_acc, a_acc, w_lc, a_lc, inv_denom, out):
    """Σ over bins of r̃ᵀ(D + uuᵀ)⁻¹r̃ per walker (B,) into ``out``: TestModel.predict and _quadratic_form fused.

    ``gather`` (6, P, K) indexes θ for start, n_p, expopen, ck, tk, eps (≥ D: ``consts``);
    ``scalars`` the columns of vehicle_weight, vehicle_cds, noise_acc, load_scale, noise_lc;
    ``decay`` and ``below_previous`` the stage law's codes (inflation.DECAY_CODES, BELOW_PREVIOUS_CODES).
    Scratch is one walker's (P, N) drag areas and (N,) sums, so memory stays small for any batch.
    """
    B, D = theta.shape
    P, K = gather.shape[1], gather.shape[2]
    N = t.shape[0]
    L = lc_index.shape[0]
    cds = np.empty((P, N))
    stage = np.empty((7, K))      # start, n_p, expopen, ck, tk, cds_stage, v_start
    timing = np.empty((4, K))     # unused outputs of the stage law
    shared = np.empty(N)          # Σ_c r̃_c·u_c/d_c² per bin
    diag = np.empty(N)            # Σ_c r̃_c²/d_c² per bin
    for b in range(B):
        for p in range(P):
            cds_o = theta[b, cds_o_index[p]]
            for k in range(n_stages[p]):
                for j in range(6):
                    g = gather[j, p, k]
                    stage[j, k] = theta[b, g] if g < D else consts[g - D]
                stage[5, k] *= cds_o
                stage[6, k] = interp(stage[0, k], native_time, native_airspeed)
            cds[p, :] = 0.0
            parachute_stage_law(t, stage[0], stage[5], cds_o, diameter[p], stage[1], stage[2], stage[3],
                                stage[4], stage[6], n_stages[p], decay, below_previous, True, True, cds[p],
                                timing[0], timing[1], timing[2], timing[3])
        weight_ratio = stated_total_weight / (theta[b, scalars[0]] + chute_weight_sum)
        cds_v = theta[b, scalars[1]]
        # Reciprocals: divisions in the bin loop would bound its speed.
        inv_noise_acc = 1.0 / theta[b, scalars[2]]
        inv_scale = 1.0 / theta[b, scalars[3]] if L > 0 else 1.0
        inv_noise_lc = 1.0 / theta[b, scalars[4]] if L > 0 else 1.0
        keep = 1.0 - inv_scale
        # Channel by channel over the bins (contiguous loops the compiler vectorises).
        for i in range(N):
            total = cds[0, i]
            for p in range(1, P):
                total += cds[p, i]
            r = (acc_obs[i] - (weight_ratio * (total + cds_v) - stated_vehicle_cds)) * inv_noise_acc
            shared[i] = r * a_acc[i]
            diag[i] = r * r * w_acc[i]
        for l in range(L):
            c = lc_index[l]
            for i in range(N):
                r = (lc_obs[l, i] - (cds[c, i] * inv_scale + lc_weight_term[l, i] * keep)) * inv_noise_lc
                shared[i] += r * a_lc[l, i]
                diag[i] += r * r * w_lc[l, i]
        quad = 0.0
        for i in range(N):
            quad += diag[i] - shared[i] * shared[i] * inv_denom[i]
        out[b] = quad


@numba.njit(cache=True)
def whitened_residuals(acc_obs, acc_pred, noise_acc, lc_obs, lc_pred, noise_lc, scale, v, c):
    """z (B, C, N): each bin's residuals over their channel's multiplier, whitened with
    (I − c·vvᵀ)·D^(−½) (:meth:`cpas_bayes.stats.model.TestModel.whiten`, which this fuses with the
    residuals: one pass instead of a numpy temporary per step, for the discrepancy's every call).

    ``acc_obs`` (N,), ``acc_pred`` (B, N), ``noise_acc`` (B,); ``lc_obs`` (L, N), ``lc_pred`` (B, L, N),
    ``noise_lc`` (B,); ``scale`` = D^(−½) and ``v`` (C, N), ``c`` (N,), C = 1 + L.
    """
    B, N = acc_pred.shape
    L = lc_obs.shape[0]
    z = np.empty((B, L + 1, N))
    dot = np.empty(N)
    for b in range(B):     # channel by channel along the bins: contiguous, so the loops vectorise
        inv_acc, inv_lc = 1.0 / noise_acc[b], 1.0 / noise_lc[b]
        for n in range(N):
            y = (acc_obs[n] - acc_pred[b, n]) * inv_acc * scale[0, n]
            z[b, 0, n] = y
            dot[n] = v[0, n] * y
        for k in range(L):
            for n in range(N):
                y = (lc_obs[k, n] - lc_pred[b, k, n]) * inv_lc * scale[k + 1, n]
                z[b, k + 1, n] = y
                dot[n] += v[k + 1, n] * y
        for k in range(L + 1):
            for n in range(N):
                z[b, k, n] -= c[n] * dot[n] * v[k, n]
    return z


@numba.njit(cache=True)
def interp_rows(x, xp, fps, out):
    """np.interp of every row of ``fps`` (S, M), sampled at ``xp`` (M,), at the points ``x`` (R, N) into ``out``
    (S, R, N): one walk along ``xp`` per row of ``x`` for all S series (each row of ``x`` increasing, as a
    shifted time base is), where S calls of np.interp would each search ``xp`` for every point."""
    R, N = x.shape
    M = xp.shape[0]
    S = fps.shape[0]
    for r in range(R):
        j = 0
        for n in range(N):
            v = x[r, n]
            if v <= xp[0]:
                for s in range(S):
                    out[s, r, n] = fps[s, 0]
                continue
            if v >= xp[M - 1]:
                for s in range(S):
                    out[s, r, n] = fps[s, M - 1]
                continue
            if xp[j] > v:            # not increasing after all: search afresh
                j = 0
            while xp[j + 1] <= v:
                j += 1
            if xp[j] == v:
                for s in range(S):
                    out[s, r, n] = fps[s, j]
                continue
            for s in range(S):
                # np.interp's formula, so that the values are the same
                slope = (fps[s, j + 1] - fps[s, j]) / (xp[j + 1] - xp[j])
                out[s, r, n] = slope * (v - xp[j]) + fps[s, j]
    return out

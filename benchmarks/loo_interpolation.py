"""Why a named term with the discrepancy can score below the discrepancy alone: leave-one-bin-out rewards interpolation.

The diagnosis compares term + discrepancy with the discrepancy alone by PSIS-LOO over leave-one-bin-out
conditionals (``stats/discrepancy.py``). On the Main pair of the detection study that stays `unexplained`
(friction drift + breathing, seed 30002) the breathing + discrepancy model scored 38 ± 15 below the
discrepancy alone, though its breathing sat at the truth. This script computes, at each model's MAP:

* the log posterior and the marginal log-likelihood (the discrepancy's coefficients integrated out);
* the sum of the leave-one-bin-out conditionals log p(y_i | y_-i, θ), what PSIS-LOO estimates;
* the sum of leave-one-block-out conditionals log p(y_B | y_-B, θ) over consecutive blocks of ``--block``
  bins (all channels), from the same Gaussian (dense, C·N square: a MAP-only experiment).

    python benchmarks/loo_interpolation.py [--scenario main] [--effect friction_drift+canopy_breathing]
                                           [--seed 30002] [--term canopy_breathing]

Every model with the discrepancy gets the baseline's envelope, as in ``diagnose``. A third row fits the term +
discrepancy with σ_δ pinned at the discrepancy-alone MAP's (a prior 0.001 wide in log σ_δ): does the term still
lose once the discrepancy keeps the flexibility it had alone?
"""

import argparse
import time

import numpy as np


def starts(model, reference_model, reference_theta):
    """The reference's MAP by parameter name, every other parameter at its prior median."""
    base = dict(zip(reference_model.names, reference_theta))
    theta = np.array([base.get(p.name, p.prior.ppf(0.5)) for p in model.parameters], dtype=float)
    return [theta]


def block_log_likelihood(model, theta, envelope, block):
    """Σ over consecutive blocks B of ``block`` bins of log p(z_B | z_−B, θ) for a model holding the
    discrepancy, plus the whitening's log-determinants: Q = (I + σ_δ²·Φ̃Φ̃ᵀ)⁻¹, g = Q·z,
    log p = −½·(g_Bᵀ·Q_BB⁻¹·g_B − log det Q_BB + |B|·log 2π + log det Σ_B)."""
    from cpas_bayes.stats.discrepancy import drag_area_basis

    raw, _ = drag_area_basis(model.obs, envelope)                          # as the model's own discrepancy
    channels, n = raw.shape[1], raw.shape[2]
    white = model.whiten(raw).reshape(raw.shape[0], channels * n)          # Φ̃ᵀ (M, C·N)
    theta = np.atleast_2d(theta)
    z, log_det = model.whitened_residuals(theta, model.predict(theta))     # (1, C, N), (1, N)
    sigma2 = np.exp(2.0 * theta[0, model.index["discrepancy_log_scale"]])
    q = np.linalg.inv(np.eye(channels * n) + sigma2 * white.T @ white)
    g = q @ z[0].reshape(-1)
    total = 0.0
    for lo in range(0, n, block):
        bins = np.arange(lo, min(lo + block, n))
        idx = (np.arange(channels)[:, None] * n + bins[None, :]).ravel()
        q_bb = q[np.ix_(idx, idx)]
        g_b = g[idx]
        _, logdet_q = np.linalg.slogdet(q_bb)
        total += -0.5 * (g_b @ np.linalg.solve(q_bb, g_b) - logdet_q + idx.size * np.log(2 * np.pi)
                         + log_det[0, bins].sum())
    return float(total)


def pinned_discrepancy(envelope, log_scale):
    """The discrepancy with log σ_δ held at ``log_scale`` (a truncated normal 0.001 wide)."""
    from cpas_bayes.stats.discrepancy import Discrepancy
    from cpas_bayes.stats.distributions import TruncNormal
    from cpas_bayes.stats.model_parts import Parameter

    class Pinned(Discrepancy):
        def parameters(self, model):
            self._prepare(model)
            return [Parameter("discrepancy_log_scale",
                              TruncNormal(log_scale, 1e-3, log_scale - 0.01, log_scale + 0.01), "", self.name)]

        def start_points(self, model):
            return [{"discrepancy_log_scale": log_scale}]

    return Pinned(envelope=envelope)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="main")
    parser.add_argument("--effect", default="friction_drift+canopy_breathing")
    parser.add_argument("--seed", type=int, default=30002)
    parser.add_argument("--term", default="canopy_breathing")
    parser.add_argument("--block", type=int, default=24, help="bins per block (24: a cubic basis function's support)")
    args = parser.parse_args()

    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.data.synth import synthesize
    from cpas_bayes.inference.candidate_fits import breathing_frequency_guess
    from cpas_bayes.inference.fit import prepare_model
    from cpas_bayes.inference.start import find_map
    from cpas_bayes.stats.discrepancy import Discrepancy, residual_envelope
    from cpas_bayes.stats.model_terms import make_extension

    rng = np.random.default_rng(0)
    test, _ = synthesize(args.scenario, args.effect, args.seed)
    reduction = reduce_test(test)
    started = time.perf_counter()
    baseline = prepare_model(test, reduction)
    theta_b, _ = find_map(baseline, rng)
    options = {}
    if args.term == "canopy_breathing":
        options["frequency_guess"] = breathing_frequency_guess(baseline, theta_b)

    def term():
        return make_extension(args.term, **options)

    alone = prepare_model(test, reduction, extensions=(term(),))
    theta_t, _ = find_map(alone, rng, guesses=starts(alone, baseline, theta_b))
    envelope = residual_envelope(baseline, theta_b)
    rows = []
    fits = (("discrepancy", lambda: (Discrepancy(envelope=envelope),), (baseline, theta_b)),
            (f"{args.term}+discrepancy", lambda: (term(), Discrepancy(envelope=envelope)), (alone, theta_t)),
            ("... σ_δ pinned as alone", lambda: (term(), pinned_discrepancy(envelope, rows[0][5])), (alone, theta_t)))
    for label, extensions, (ref_model, ref_theta) in fits:
        model = prepare_model(test, reduction, extensions=extensions())
        theta, log_post = find_map(model, rng, guesses=starts(model, ref_model, ref_theta))
        marginal = float(model.log_likelihood(theta[None])[0])
        loo_sum = float(model.pointwise_log_likelihood(theta[None])[0].sum())
        log_scale = float(theta[model.index["discrepancy_log_scale"]])
        block_sum = block_log_likelihood(model, theta, envelope, args.block)
        rows.append((label, log_post, marginal, loo_sum, block_sum, log_scale))
    print(f"{args.scenario} {args.effect} seed {args.seed} ({time.perf_counter() - started:.0f} s)")
    print(f"{'model':<34} {'log posterior':>14} {'marginal loglik':>16} {'sum LOO-bin cond.':>18} "
          f"{f'sum LO-{args.block}-bins-O':>18} {'log σ_δ':>8}")
    for label, lp, ml, lo, bl, ls in rows:
        print(f"{label:<34} {lp:14.1f} {ml:16.1f} {lo:18.1f} {bl:18.1f} {ls:8.2f}")
    (_, lp0, ml0, lo0, bl0, _) = rows[0]
    for label, (_, lp1, ml1, lo1, bl1, _) in zip(("term + discrepancy − discrepancy", "pinned − discrepancy"), rows[1:]):
        print(f"{label:<34} {lp1 - lp0:+14.1f} {ml1 - ml0:+16.1f} {lo1 - lo0:+18.1f} {bl1 - bl0:+18.1f}")


if __name__ == "__main__":
    main()

"""How far the sensor-lag term's four Gauss–Laguerre delays are from the first-order response they stand for.

``sensor_lag`` (``stats/model_terms.py``) models a load cell as the riser force delayed by L − r and seen through
a first-order response of time constant r, y(t) = ∫₀^∞ F(t − (L − r) − r·s)·e^(−s) ds, evaluated with four
Gauss–Laguerre nodes (the law run at four delayed time bases). F has kinks (a stage's start, the end of its
growth), where a few-node quadrature errs. This script measures that error at the bins, in units of each
load-cell bin's stated 1-sigma, against a reference: F on a 0.5 ms grid, delayed by L − r, through the exact
first-order recursion for a signal linear between samples (``physics.effects.first_order_lag``), read at the
bins. Beside it, two cheaper alternatives: Gauss–Laguerre with K nodes (``--nodes``) and the recursion run on
the bins themselves (one delayed time base, the filter exact only if F is linear between bins).

    python benchmarks/lag_quadrature.py [--scenario drogue] [--effect sensor_lag] [--seed 30003] [--nodes 2,8]

The model is ``sensor_lag`` + discrepancy at the baseline's MAP (an added mass is left out: its lagged mass is
a recursion over the time base, so it would differ between grids for a reason of its own).
"""

import argparse

import numpy as np

CASES = ((0.04, 0.0), (0.04, 0.01), (0.04, 0.03), (0.08, 0.05), (0.2, 0.1), (0.3, 0.3), (-0.1, 0.02))
FINE_STEP = 0.0005   # s


def response(times, force, r):
    """``force`` (B, L, M) at ``times`` (M,) through a first-order response of time constant r (B,); r = 0 as is."""
    from cpas_bayes.physics.effects import first_order_lag

    return np.stack([first_order_lag(times, force[b], r[b]) if r[b] > 0 else force[b] for b in range(r.size)])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="drogue")
    parser.add_argument("--effect", default="sensor_lag")
    parser.add_argument("--seed", type=int, default=30003)
    parser.add_argument("--nodes", default="2,8", help="Gauss–Laguerre node counts to compare with the four")
    args = parser.parse_args()

    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.data.synth import synthesize
    from cpas_bayes.inference.candidate_fits import _model_for, DiagnoseOptions, fit_candidate, start_guesses
    from cpas_bayes.stats.load_cells import riser_force_at
    from cpas_bayes.stats.model_parts import Context
    from cpas_bayes.stats.model_terms import RESPONSE_NODES, RESPONSE_WEIGHTS

    test, _ = synthesize(args.scenario, args.effect, args.seed)
    reduction = reduce_test(test)
    options = DiagnoseOptions(seed=args.seed)
    baseline = fit_candidate("baseline", test, reduction, options)
    model = _model_for("sensor_lag+discrepancy", test, reduction, options, baseline)
    start = np.atleast_2d(np.array(start_guesses(model, baseline), float))[0]
    theta = np.repeat(start[None], len(CASES), axis=0)
    theta[:, model.index["lag"]] = [c[0] for c in CASES]
    theta[:, model.index["lag_response"]] = [c[1] for c in CASES]
    t = model.obs.time
    values = model.values(theta)
    ctx = Context(model, theta, values, t, model.gather_stages(theta))
    delay, r = values["lag"] - values["lag_response"], values["lag_response"]

    fine = np.union1d(np.arange(t[0] - 2.0, t[-1], FINE_STEP), t)
    at_bins = np.searchsorted(fine, t)
    reference = response(fine, riser_force_at(model, ctx, fine[None, :] - delay[:, None]), r)[:, :, at_bins]

    def gauss_laguerre(k):
        nodes, weights = np.polynomial.laguerre.laggauss(k) if k != 4 else (RESPONSE_NODES, RESPONSE_WEIGHTS)
        return sum(w * riser_force_at(model, ctx, t[None, :] - (delay[:, None] + r[:, None] * x))
                   for x, w in zip(nodes, weights))

    schemes = {"Gauss–Laguerre 4 (the term)": gauss_laguerre(4)}
    for k in (int(x) for x in args.nodes.split(",") if x):
        schemes[f"Gauss–Laguerre {k}"] = gauss_laguerre(k)
    schemes["recursion on the bins"] = response(t, riser_force_at(model, ctx, t[None, :] - delay[:, None]), r)
    # what the force error does to a load cell's drag area: divided by s·q̄ as the term's reading is
    scale = values["load_scale"][:, None, None] * model.obs.qbar_at(t)[None, None, :] * model.obs.lc_sigma[None]
    print(f"{args.scenario} {args.effect} seed {args.seed}: error at the bins against the 0.5 ms reference, "
          "max |error|/σ and Σ (error/σ)²")
    print(f"{'lag L, s':>9} {'r, s':>6} " + " ".join(f"{name:>30}" for name in schemes))
    for j, (lag, tau) in enumerate(CASES):
        cells = []
        for estimate in schemes.values():
            e = (estimate[j] - reference[j]) / scale[j]
            cells.append(f"{np.abs(e).max():13.3f} {np.sum(e ** 2):16.2f}")
        print(f"{lag:9.3f} {tau:6.3f} " + " ".join(f"{c:>30}" for c in cells))


if __name__ == "__main__":
    main()

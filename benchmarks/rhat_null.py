"""How often the ESS rule's R-hat test fails chains that have converged: its null distribution.

    python benchmarks/rhat_null.py [--out benchmarks/rhat_null.md] [--replicas 200]

The ESS rule (:mod:`cpas_bayes.inference.stopping`) asks every parameter's
nested R-hat (the larger of its bulk and folded values, the ensembles as
super-chains) to be at most 1.01. Here every walker of every ensemble is a
stationary AR(1) chain of the target itself (a normal, or its exponential for
a skewed one, half the replicas each), so a failure is the statistic's own
noise, not a chain that has not mixed. Each setting is a fit's kept draws:
K ensembles of W walkers, S kept draws per walker with lag-one correlation ρ,
D parameters; the table gives the ESS those draws hold, K·W·S·(1 − ρ)/(1 + ρ)
(an AR(1) chain's), the smallest bulk/tail ESS the rule estimates over the
parameters (median over replicas), the median and 90 % quantile of the largest R-hat over
the parameters, and the share of replicas in which that largest R-hat exceeds
1.01, i.e. the rule would go on sampling chains that are already stationary.

With two ensembles (the diagnosis' fits) the between-ensemble variance has one
degree of freedom, so R-hat − 1 ≈ χ²₁/ESS for each of 2·D statistics; with
four (the memo fits) three.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cpas_bayes.inference.stopping import RHAT_TARGET, chain_statistics

# (label, ensembles K, walkers W, kept draws S, lag-one correlation ρ, parameters D)
SETTINGS = [
    ("diagnosis fit, Main lag (47 parameters)", 2, 96, 13, 0.85, 47),
    ("diagnosis fit, Main lag, less correlated draws", 2, 96, 13, 0.5, 47),
    ("diagnosis fit, twice as long", 2, 96, 26, 0.85, 47),
    ("diagnosis fit, Drogue (29 parameters)", 2, 60, 13, 0.85, 29),
    ("memo fit, Main (4 ensembles)", 4, 84, 20, 0.7, 41),
]


def stationary_chains(rng, k, w, s, rho, d, skewed):
    """(K·W chains, S draws, D) of a stationary AR(1) chain of N(0, 1) (exp of it when ``skewed``)."""
    x = np.empty((k * w, s, d))
    x[:, 0] = rng.standard_normal((k * w, d))
    for i in range(1, s):
        x[:, i] = rho * x[:, i - 1] + np.sqrt(1.0 - rho ** 2) * rng.standard_normal((k * w, d))
    return np.exp(x) if skewed else x


def null_row(rng, k, w, s, rho, d, replicas):
    """(median min ESS, median max R-hat, 90 % quantile of max R-hat, share of max R-hat > target)."""
    largest, ess = [], []
    for r in range(replicas):
        chains = stationary_chains(rng, k, w, s, rho, d, skewed=bool(r % 2))
        stats = chain_statistics(chains, np.repeat(np.arange(k), w))
        largest.append(float(np.max(stats.rhat)))
        ess.append(float(min(np.min(stats.ess_bulk), np.min(stats.ess_tail))))
    largest = np.array(largest)
    return float(np.median(ess)), float(np.median(largest)), float(np.quantile(largest, 0.9)), \
        float(np.mean(largest > RHAT_TARGET))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("rhat_null.md"))
    parser.add_argument("--replicas", type=int, default=200)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    if args.replicas < 10:
        parser.error("--replicas must be at least 10")
    rng = np.random.default_rng(args.seed)
    lines = [f"Stationary chains, {args.replicas} replicas per row (seed {args.seed}); target R-hat {RHAT_TARGET}.",
             "", "| setting | K | W | S | ρ | D | ESS held | min ESS estimated (median) | max R-hat median | 90 % | "
             "P(max > target) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, k, w, s, rho, d in SETTINGS:
        ess, median, q90, share = null_row(rng, k, w, s, rho, d, args.replicas)
        held = k * w * s * (1.0 - rho) / (1.0 + rho)
        lines.append(f"| {label} | {k} | {w} | {s} | {rho} | {d} | {held:.0f} | {ess:.0f} | {median:.4f} | {q90:.4f} | "
                     f"**{100 * share:.0f} %** |")
        print(lines[-1], flush=True)
    args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()

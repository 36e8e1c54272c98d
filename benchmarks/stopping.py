"""The two stopping rules on the bundled example bundles: cost, diagnostics and the answer.

    PYTHONPATH=. python benchmarks/stopping.py [--workers 2] [--ess-target 1000] [--out benchmarks/stopping.md]

For each example bundle and each rule (``SamplerOptions.stop`` "tau" and "ess",
same seed, so the same MAP and the same chains, only stopped elsewhere) it
reports the wall time of sampling (the MAP search, common to both, timed
apart), the steps per ensemble, max τ, the pooled diagnostics of the kept
draws (min bulk ESS, min tail ESS, max nested R-hat: the summary's numbers)
and the 90 % interval widths of a few key parameters, which should agree
between the rules within Monte-Carlo error (≈ 3 % of a width at tail ESS 1000).

``ESS check`` tests the walker-as-chain ESS against the ensembles: for each
parameter var(ensemble means)·ESS_bulk / (E·var(draws)), averaged over the
parameters; about 1 if the ESS is honest, above 1 if it is optimistic (each
term has E − 1 degrees of freedom, so the average over D parameters scatters
by roughly √(2/((E − 1)·D))).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cpas_bayes.data.bundle import example_bundles, read_bundle
from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.inference.fit import SamplerOptions, prepare_model, sample_posterior
from cpas_bayes.inference.stopping import ESS_TARGET, chain_statistics

KEY_FIELDS = ("cds_o", "s1.n_p", "s2.n_p", "s1.ck", "s2.expopen")


def key_parameters(names, first_chute):
    return [f"{first_chute}.{f}" for f in KEY_FIELDS if f"{first_chute}.{f}" in names][:4]


def measure(model, options):
    sampling = sample_posterior(model, options)
    wall = sampling.extras["sampling_seconds"]      # the ensembles only, not the MAP search
    chains, _, ensemble = sampling.stacked()
    stats = chain_statistics(chains, ensemble)
    means = np.stack([chains[ensemble == e].mean(axis=(0, 1)) for e in np.unique(ensemble)])
    n_ens = means.shape[0]
    check = np.mean(means.var(axis=0, ddof=1) * stats.ess_bulk / (n_ens * chains.reshape(-1, chains.shape[-1]).var(axis=0)))
    flat = chains.reshape(-1, chains.shape[-1])
    lo, hi = np.quantile(flat, [0.05, 0.95], axis=0)
    return {"wall": wall, "steps": max(r.steps for r in sampling.runs),
            "tau": max(float(np.max(r.tau)) for r in sampling.runs), "bulk": float(np.min(stats.ess_bulk)),
            "tail": float(np.min(stats.ess_tail)), "rhat": float(np.max(stats.rhat)), "check": float(check),
            "widths": dict(zip(model.names, hi - lo)), "draws": flat.shape[0]}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--ess-target", type=int, default=ESS_TARGET)
    parser.add_argument("--rules", nargs="+", default=["tau", "ess"], choices=["tau", "ess"])
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("stopping.md"))
    args = parser.parse_args()
    rows, widths = [], []
    for path in example_bundles():
        test = read_bundle(path)
        model = prepare_model(test, reduce_test(test))
        keys = key_parameters(model.names, model.parachutes[0].id)
        results = {}
        for stop in args.rules:
            options = SamplerOptions(seed=0, workers=args.workers, progress=False, stop=stop,
                                     ess_target=args.ess_target)
            r = results[stop] = measure(model, options)
            rows.append(f"| {path.name} ({model.ndim} par.) | {stop} | {r['wall']:.0f} | {r['steps']:,} | "
                        f"{r['tau']:.0f} | {r['bulk']:,.0f} | {r['tail']:,.0f} | {r['rhat']:.4f} | {r['check']:.2f} | "
                        f"{r['draws']:,} |")
            print(rows[-1], flush=True)
        for k in keys if len(results) == 2 else ():
            a, b = results["tau"]["widths"][k], results["ess"]["widths"][k]
            widths.append(f"| {path.name} | {k} | {a:.4g} | {b:.4g} | {100 * (b / a - 1):+.1f} % |")
    text = "\n".join([
        f"Stopping rules on the example bundles (seed 0, 4 ensembles, {args.workers} workers, ESS target "
        f"{args.ess_target}; sampling s: the ensembles, not the MAP search common to both rules).",
        "",
        "| bundle | rule | sampling s | steps per ensemble | max τ | min bulk ESS | min tail ESS | max R-hat "
        "| ESS check | kept draws |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        *rows,
        "",
        "90 % interval widths (SI units):",
        "",
        "| bundle | parameter | τ rule | ESS rule | difference |",
        "|---|---|---:|---:|---:|",
        *widths,
        "",
    ])
    args.out.write_text(text, encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()

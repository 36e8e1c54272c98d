"""Simulation-based calibration (Talts et al. 2018) of the package's posterior fits.

    PYTHONPATH=. python benchmarks/sbc.py --scenario drogue --replicas 100 --workers 2
    PYTHONPATH=. python benchmarks/sbc.py --scenario main --replicas 30 --workers 2
    PYTHONPATH=. python benchmarks/sbc.py --report          # tables and figures from the CSVs only

Replica i of a scenario: the template is the synthetic test
``synthesize(scenario, "none", seed)`` with seed = SEED_BASE[scenario] + i
(its flight condition, time base, stage nominal starts and stated sigmas are
what the calibration is conditional on), reduced and modelled as a fit would;
θ̃ is drawn from the model's prior, observations are simulated from the
model's likelihood at θ̃, and the package's default sampler refits them
(``fit_model``, ESS rule, 4 ensembles, one process per fit);
:func:`cpas_bayes.inference.calibration.run_replica` does all this.

Recorded per parameter: θ̃, its rank among 99 posterior draws picked at
random, and whether the central 50 % and 90 % intervals cover it; per
replica: the fit's convergence verdict, max R-hat, min bulk ESS, steps per
ensemble and seconds. Rows go to ``sbc_<scenario>.csv`` after every replica,
so a rerun resumes (done replicas are skipped). The report (``sbc.md``, one
section per scenario with a CSV) tests each parameter group's ranks for
uniformity (chi-square, 10 bins) and compares the coverage with its binomial
95 % band; ``docs/sbc_<scenario>.png`` shows the rank histograms with the 99 %
band of uniform ranks shaded (Talts et al. Fig. 1).
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

SCENARIOS = ("drogue", "main")
SEED_BASE = {"drogue": 70_000, "main": 80_000}
N_RANKS = 99
BINS = 10
ROLES = ("first", "reefed", "full_open")
FIELDS = ("start", "n_p", "expopen", "ck", "tk", "eps")
COLUMNS = ["scenario", "replica", "seed", "parameter", "group", "truth", "rank", "in50", "in90", "rhat", "ess_bulk",
           "ess_tail", "converged", "rhat_max", "ess_bulk_min", "steps", "seconds", "n_parameters"]
HERE = Path(__file__).resolve().parent


def parameter_groups(model):
    """Report group of each parameter: ``cds_o``, ``<stage role> <field>`` or a nuisance parameter's name."""
    from cpas_bayes.physics.inflation import stage_role, stage_tag

    groups = {}
    for i, p in enumerate(model.parachutes):    # the model's own names (model.parameter_name), None if absent
        groups[model.parameter_name(i, "cds_o")] = "cds_o"
        groups[model.parameter_name(i, "d_o")] = "d_o"
        n = len(p.stages)
        for k in range(n):
            for field in FIELDS:
                groups[model.parameter_name(i, f"{stage_tag(k)}.{field}")] = f"{stage_role(k, n)} {field}"
    return {name: groups.get(name, name) for name in model.names}


def group_order(groups):
    """Groups in reading order: cds_o, stage groups by role then field, then the rest as found."""
    def key(g):
        if g == "cds_o":
            return (0, 0, 0)
        role, _, field = g.partition(" ")
        if role in ROLES and field in FIELDS:
            return (1, ROLES.index(role), FIELDS.index(field))
        return (2, 0, 0)
    return sorted(dict.fromkeys(groups), key=key)


def replica_task(item, report=None):
    """One replica in a worker: its CSV rows, also sent through ``report`` as soon as they exist."""
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.data.synth import synthesize
    from cpas_bayes.inference.calibration import run_replica
    from cpas_bayes.inference.fit import SamplerOptions, prepare_model

    scenario, replica, seed = item
    try:
        test, _ = synthesize(scenario, "none", seed)
        template = prepare_model(test, reduce_test(test))
        # the replica's own streams: the template's seed would spawn the ones its truth and noise used
        r = run_replica(template, [seed, 1], SamplerOptions(seed=seed, workers=1, progress=False), N_RANKS)
    except Exception:   # one broken replica is reported, not the end of the others; a rerun retries it
        if report is not None:
            report("failed", scenario, replica, traceback.format_exc())
        return None
    groups = parameter_groups(template)
    rows = [{"scenario": scenario, "replica": replica, "seed": seed, "parameter": name, "group": groups[name],
             "truth": f"{r.truth[j]:.10g}", "rank": int(r.ranks[j]), "in50": int(r.covered[0, j]),
             "in90": int(r.covered[1, j]), "rhat": f"{r.rhat[j]:.5f}", "ess_bulk": f"{r.ess_bulk[j]:.0f}",
             "ess_tail": f"{r.ess_tail[j]:.0f}", "converged": int(r.converged), "rhat_max": f"{r.rhat_max:.5f}",
             "ess_bulk_min": f"{r.ess_bulk_min:.0f}", "steps": r.steps, "seconds": f"{r.seconds:.1f}",
             "n_parameters": len(r.names)} for j, name in enumerate(r.names)]
    if report is not None:
        report("done", scenario, replica, rows)
    return rows


def done_replicas(path):
    """Replicas with all their rows in the CSV (a row cut short by a kill does not count)."""
    if not path.is_file():
        return {}, []
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    by_replica = {}
    for row in rows:
        by_replica.setdefault(int(row["replica"]), []).append(row)
    complete = {i: g for i, g in by_replica.items()
                if all(r["n_parameters"] for r in g) and len(g) == int(g[0]["n_parameters"])}
    return complete, [r for i in sorted(complete) for r in complete[i]]


def run(args):
    from cpas_bayes.core.executor import limit_blas_threads, make_executor

    path = args.out / f"sbc_{args.scenario}.csv"
    complete, kept = done_replicas(path)
    # rewrite the file with complete replicas only: a replica cut short by a kill is redone
    args.out.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")   # then renamed: a kill now leaves the old file whole
    with tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, COLUMNS)
        writer.writeheader()
        writer.writerows(kept)
    os.replace(tmp, path)
    todo = [(args.scenario, i, SEED_BASE[args.scenario] + i) for i in range(args.replicas) if i not in complete]
    print(f"{args.scenario}: {len(todo)} replicas to run, {len(complete)} already in {path}; "
          f"{args.workers} worker(s), one process per fit", flush=True)
    covered = {"in50": [int(r["in50"]) for r in kept], "in90": [int(r["in90"]) for r in kept]}
    state = {"finished": 0, "failed": [], "started": time.perf_counter()}

    def on_report(kind, scenario, replica, payload):
        if kind == "failed":
            state["failed"].append(replica)
            print(f"replica {replica} FAILED (rerun to retry):\n{payload}", file=sys.stderr, flush=True)
            return
        with path.open("a", newline="") as f:   # all rows of a replica in one write
            csv.DictWriter(f, COLUMNS).writerows(payload)
        for key in covered:
            covered[key] += [r[key] for r in payload]
        state["finished"] += 1
        first = payload[0]
        elapsed = time.perf_counter() - state["started"]
        print(f"[{state['finished']}/{len(todo)}] {scenario} replica {replica}: {float(first['seconds']):.0f} s, "
              f"{first['steps']} steps, R-hat {float(first['rhat_max']):.4f}, "
              f"{'converged' if first['converged'] else 'NOT converged'}; running coverage 50 % "
              f"{np.mean(covered['in50']):.3f}, 90 % {np.mean(covered['in90']):.3f} "
              f"({len(covered['in90'])} parameters); {elapsed / 60:.1f} min elapsed", flush=True)

    if todo:
        if args.workers == 1:
            limit_blas_threads()   # the replica runs here: one BLAS thread, as in a pool worker
        with make_executor(args.workers) as executor:
            executor.map(replica_task, todo, desc="replicas", progress=False, on_report=on_report)
    if state["failed"]:
        print(f"failed replicas (rerun to retry): {sorted(state['failed'])}", file=sys.stderr)


# ---------------------------------------------------------------------------
# report


def load_rows(path):
    import pandas as pd

    complete, _ = done_replicas(path)
    d = pd.read_csv(path)
    d = d[d["replica"].isin(list(complete))]   # a row cut short by a kill made some columns float
    return d.astype({k: int for k in ("rank", "in50", "in90", "converged", "steps", "n_parameters")})


def group_table(d):
    """One row per parameter group (and one for all): ranks, uniformity p, coverage with 95 % bands."""
    from cpas_bayes.inference.calibration import binomial_band, rank_uniformity

    lines = ["| group | ranks | χ² p (10 bins) | 50 % coverage | 95 % band | 90 % coverage | 95 % band |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    parts = [(g, d[d["group"] == g]) for g in group_order(d["group"])] + [("**all parameters**", d)]
    for group, g in parts:
        n = len(g)
        p = rank_uniformity(g["rank"].to_numpy(), N_RANKS, BINS)[1]
        cells = []
        for key, prob in (("in50", 0.5), ("in90", 0.9)):
            low, high = binomial_band(n, prob)
            share = g[key].mean()
            flag = "" if low <= share <= high else " ⚠"
            cells.append(f"{share:.3f}{flag} | {low:.3f}–{high:.3f}")
        flag = " ⚠" if p < 0.01 else ""
        lines.append(f"| {group} | {n} | {p:.3g}{flag} | {' | '.join(cells)} |")
    return lines


def not_converged_lines(d, not_converged):
    """What held the non-converged replicas back (their worst parameter) and the coverage without them."""
    if not len(not_converged):
        return []
    bad = d[d["replica"].isin(not_converged["replica"])].copy()
    bad["ess"] = bad[["ess_bulk", "ess_tail"]].min(axis=1)
    worst = bad.loc[bad.groupby("replica")["ess"].idxmin()]
    counts = worst["group"].value_counts()
    good = d[~d["replica"].isin(not_converged["replica"])]
    lines = ["Their lowest-ESS parameter group (min of bulk and tail ESS, one per replica): "
             + ", ".join(f"{g} {n}" for g, n in counts.items()) + "; that ESS: median "
             f"{worst['ess'].median():.0f}, min {worst['ess'].min():.0f}; max R-hat {bad['rhat'].max():.4f}."]
    if len(good):
        lines.append(f"Coverage over the converged replicas only: 50 % {good['in50'].mean():.3f}, "
                     f"90 % {good['in90'].mean():.3f} ({len(good)} parameters).")
    return lines


def scenario_section(scenario, d, figure):
    from cpas_bayes.inference.calibration import rank_uniformity

    reps = d.drop_duplicates("replica")
    not_converged = reps[reps["converged"] == 0]
    per_parameter = sorted((rank_uniformity(g["rank"].to_numpy(), N_RANKS, BINS)[1], name)
                           for name, g in d.groupby("parameter"))
    lines = [
        f"## {scenario.capitalize()} ({len(reps)} replicas, {reps['n_parameters'].iloc[0]} parameters)",
        "",
        f"Replicas not converged (the fit's own verdict): **{len(not_converged)}**"
        + (f" (replica{'s' * (len(not_converged) > 1)} {', '.join(map(str, not_converged['replica']))})"
           if len(not_converged) else "") + ".",
        f"Seconds per replica (one process each, MAP search included): median {reps['seconds'].median():.0f}, "
        f"mean {reps['seconds'].mean():.0f}, max {reps['seconds'].max():.0f}; steps per ensemble: median "
        f"{reps['steps'].median():.0f}, max {reps['steps'].max():.0f}; max R-hat over replicas "
        f"{reps['rhat_max'].max():.4f}, min bulk ESS {reps['ess_bulk_min'].min():.0f}.",
        *not_converged_lines(d, not_converged),
        "",
        *group_table(d),
        "",
        "Lowest per-parameter rank-uniformity p-values ("
        + f"{len(reps)} ranks each, {len(per_parameter)} parameters, so the smallest of "
        + f"{len(per_parameter)} uniform p-values is expected near {1 / (len(per_parameter) + 1):.3f}): "
        + ", ".join(f"{name} {p:.2g}" for p, name in per_parameter[:4]) + ".",
        "",
        f"![rank histograms]({figure})",
        "",
    ]
    return lines


def rank_figure(scenario, d, target):
    """One panel per parameter group: rank histogram (10 bins), 99 % band of uniform ranks shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cpas_bayes.inference.calibration import rank_histogram, rank_uniformity, uniform_histogram_band

    groups = group_order(d["group"])
    cols = 5
    rows = -(-len(groups) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.3 * cols, 1.9 * rows), squeeze=False)
    edges = np.arange(BINS + 1) * (N_RANKS + 1) / BINS
    for ax, group in zip(axes.flat, groups):
        ranks = d.loc[d["group"] == group, "rank"].to_numpy()
        counts, prob = rank_histogram(ranks, N_RANKS, BINS)
        low, high = uniform_histogram_band(ranks.size, N_RANKS, BINS, level=0.99)
        ax.bar(edges[:-1], counts, width=np.diff(edges), align="edge", color="C0", alpha=0.75, edgecolor="white")
        # the band over the bars (translucent), so that a bin outside it shows on either side
        ax.fill_between(edges, np.r_[low, low[-1]], np.r_[high, high[-1]], step="post", color="0.4", alpha=0.3,
                        lw=0, zorder=3)
        ax.axhline(ranks.size * prob.mean(), color="0.3", lw=0.8, zorder=4)
        p = rank_uniformity(ranks, N_RANKS, BINS)[1]
        ax.set_title(f"{group}\nn={ranks.size}, p={p:.2g}", fontsize=8)
        ax.set_xlim(0, N_RANKS + 1)
        ax.set_ylim(0, 1.08 * max(high.max(), counts.max()))
        ax.set_yticks([])
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(groups):]:
        ax.axis("off")
    fig.suptitle(f"SBC rank histograms, {scenario} (rank of θ̃ among {N_RANKS} posterior draws; grey: 99 % band "
                 "of uniform ranks)", fontsize=9)
    fig.tight_layout()
    target.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(target, dpi=110)
    plt.close(fig)


def report(out, figures):
    sections = []
    for scenario in SCENARIOS:
        path = out / f"sbc_{scenario}.csv"
        if not path.is_file():
            continue
        d = load_rows(path)
        if d.empty:
            continue
        target = figures / f"sbc_{scenario}.png"
        rank_figure(scenario, d, target)
        sections += scenario_section(scenario, d, Path(os.path.relpath(target, out)).as_posix())
    if not sections:
        print(f"no SBC results in {out}", file=sys.stderr)
        return
    text = "\n".join([
        "# Simulation-based calibration of the posterior fits",
        "",
        "Talts et al. (2018): θ̃ from the prior, data from the model's likelihood at θ̃, a refit with the",
        "package's default sampler (ESS rule: bulk and tail ESS ≥ 1000, nested R-hat ≤ 1.01 over 4 ensembles),",
        f"and the rank of θ̃ among {N_RANKS} posterior draws picked at random: uniform on 0..{N_RANKS} for a",
        "calibrated posterior. Conditioning: the flight condition, time base, stage nominal starts and stated",
        "sigmas of a synthetic template test per replica (`synthesize(scenario, \"none\", seed)`).",
        "Written by `benchmarks/sbc.py` (see its docstring).",
        "",
        "Columns: ranks in the group (replicas × parameters of the group); χ² p: Pearson's test of the ranks'",
        "10-bin histogram against uniform (⚠ below 0.01; ranks of one replica's parameters are correlated, so",
        "the test is liberal); coverage: share of θ̃ inside the central 50 % / 90 % posterior interval, with the",
        "binomial 95 % band of that share for a calibrated posterior (⚠ outside it).",
        "",
        *sections,
    ])
    (out / "sbc.md").write_text(text, encoding="utf-8")
    print(text)


def main(argv=None):
    from cpas_bayes.core.executor import MAX_LOCAL_WORKERS

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", choices=SCENARIOS, help="synthetic scenario of the templates")
    parser.add_argument("--replicas", type=int, default=100, help="replicas 0..N−1 (done ones are skipped)")
    parser.add_argument("--workers", type=int, default=2, help="replicas run at once, one process each")
    parser.add_argument("--report", action="store_true", help="only write sbc.md and the figures from the CSVs")
    parser.add_argument("--out", type=Path, default=HERE, help="folder of the CSVs and sbc.md")
    parser.add_argument("--figures", type=Path, default=HERE.parent / "docs", help="folder of the figures")
    args = parser.parse_args(argv)
    if not args.report:
        if args.scenario is None:
            parser.error("--scenario is required (drogue or main), unless --report")
        if args.replicas < 1:
            parser.error(f"--replicas must be at least 1, not {args.replicas}")
        if not 1 <= args.workers <= MAX_LOCAL_WORKERS:
            parser.error(f"--workers must be between 1 and {MAX_LOCAL_WORKERS} (twice the cores), not {args.workers}")
        run(args)
    report(args.out, args.figures)


if __name__ == "__main__":
    sys.exit(main())

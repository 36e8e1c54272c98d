"""Benchmarks of cpas_bayes on this machine: prints a table and writes JSON.

    python benchmarks/run.py [--out benchmarks/results.json] [--only fit_drogue,fit_main]

Measured (not timed tests):
* fit_drogue / fit_main: wall time of a full posterior (MAP, 4 ensembles to 50 τ,
  DataTree) on the bundled two-Drogue and three-Main examples, ESS per second
  (minimum bulk ESS over parameters / wall time), and in the same run the wall
  time of a Nelder–Mead point fit of the same model (scipy, from the same
  first guess, to its default tolerance), with the ratio of the two.
* diagnose_drogue / diagnose_main: wall time of ``cpas-bayes diagnose`` (mode
  full: baseline + five candidates sampled, PSIS-LOO, gain, no figures) on the
  same examples; and in mode screen.

Results are merged into the JSON file, so ``--only`` refreshes some entries.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy import optimize

from cpas_bayes import __version__
from cpas_bayes.bundle import example_bundles, read_bundle
from cpas_bayes.fit import SamplerOptions, first_guess, fit_model, prepare_model


def nelder_mead_point_fit(model):
    """The in-house practice: fminsearch-style Nelder–Mead on −log posterior, one start."""
    x0 = first_guess(model)
    t0 = time.perf_counter()
    res = optimize.minimize(lambda x: -model(x[None])[0], x0, method="Nelder-Mead",
                            options={"maxiter": 200 * model.ndim, "maxfev": 200 * model.ndim, "adaptive": True})
    return time.perf_counter() - t0, -res.fun, int(res.nfev)


def bench_fit(path):
    test = read_bundle(path)
    model = prepare_model(test)
    point_s, point_lp, nfev = nelder_mead_point_fit(model)
    t0 = time.perf_counter()
    fit = fit_model(model, SamplerOptions(seed=0, progress=False))
    wall = time.perf_counter() - t0
    d = fit.summary["diagnostics"]
    return {"test": test.name, "parameters": model.ndim, "bins": int(model.obs.n_bins),
            "posterior_wall_s": wall, "ess_bulk_min": d["ess_bulk_min"], "ess_per_s": d["ess_bulk_min"] / wall,
            "rhat_max": d["rhat_max"], "tau_max_steps": d["tau_max"], "steps_per_ensemble": d["steps"],
            "converged": d["converged"], "nelder_mead_wall_s": point_s, "nelder_mead_evaluations": nfev,
            "nelder_mead_log_post": point_lp, "map_log_post": fit.sampling.log_post_map,
            "posterior_over_point_fit": wall / point_s}


def bench_diagnose(path, mode):
    from dataclasses import replace

    from cpas_bayes.diagnose import DIAGNOSIS_SAMPLER, DiagnoseOptions, diagnose_test

    test = read_bundle(path)
    t0 = time.perf_counter()
    d = diagnose_test(test, DiagnoseOptions(mode=mode, sampler=replace(DIAGNOSIS_SAMPLER, progress=False)))
    wall = time.perf_counter() - t0
    return {"test": test.name, "mode": mode, "wall_s": wall, "cause": d.cause,
            "candidates_sampled": sorted(d.candidates),
            "elpd_diff": {r["name"]: r["elpd_diff"] for r in d.versus_baseline.to_dict("records")},
            "summary": f"cause {d.cause}, {len(d.candidates)} candidates sampled"}


BENCHES = {
    "fit_drogue": lambda: bench_fit(next(p for p in example_bundles() if p.name.startswith("drogue"))),
    "fit_main": lambda: bench_fit(next(p for p in example_bundles() if p.name.startswith("main"))),
    "diagnose_drogue": lambda: bench_diagnose(next(p for p in example_bundles() if p.name.startswith("drogue")),
                                              "full"),
    "diagnose_main": lambda: bench_diagnose(next(p for p in example_bundles() if p.name.startswith("main")), "full"),
    "diagnose_screen_main": lambda: bench_diagnose(next(p for p in example_bundles() if p.name.startswith("main")),
                                                   "screen"),
}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results.json"))
    parser.add_argument("--only", default=",".join(BENCHES), help="comma-separated subset of " + ", ".join(BENCHES))
    args = parser.parse_args(argv)
    results = json.loads(args.out.read_text()) if args.out.is_file() else {}
    results["machine"] = {"cpus": os.cpu_count(), "platform": platform.platform(), "python": sys.version.split()[0],
                          "cpas_bayes": __version__}
    for name in args.only.split(","):
        print(f"running {name} ...", flush=True)
        results[name] = BENCHES[name]()
    print(f"\n{'benchmark':<22} {'wall [s]':>9}  notes")
    for name, r in results.items():
        if name == "machine":
            continue
        if "posterior_wall_s" in r:
            print(f"{name:<22} {r['posterior_wall_s']:9.1f}  ESS/s {r['ess_per_s']:.0f}, R-hat {r['rhat_max']:.4f}, "
                  f"Nelder-Mead {r['nelder_mead_wall_s']:.1f} s (ratio {r['posterior_over_point_fit']:.1f})")
        else:
            print(f"{name:<22} {r['wall_s']:9.1f}  {r['summary']}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2, default=float) + "\n")
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())

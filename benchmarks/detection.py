"""Detection study of ``diagnose``: false alarms, power, out-of-catalogue effects and pairs.

    python benchmarks/detection.py [--out benchmarks/detection.csv] [--study clean,ooc,pairs,power]
                                   [--seeds 20] [--mode full|screen] [--scenarios drogue,main]
                                   [--effects a,b] [--sizes 0.4,0.06]

Each case is a synthetic test (:mod:`cpas_bayes.data.synth`) with a known
hidden effect, diagnosed with the default rule; one row per case goes into
the CSV as soon as it is done (and the case's diagnosis, without its
residual tables, into a ``.jsonl`` beside it), so an interrupted study resumes where it
stopped (cases already in the CSV are skipped). The summary table printed at
the end (and written next to the CSV as ``.md``) is the README's:

* clean — no effect; a false alarm is any verdict other than ``none``;
* ooc — each out-of-catalogue effect (``synth_effects.OUT_OF_CATALOGUE``) at
  a size drawn from its realistic range; right = ``unexplained`` and no
  catalogued name;
* pairs — two catalogued effects at once; right = both named;
* power — each catalogued effect at fixed sizes; right = named (an
  ``unexplained`` beside it is allowed);
* form — a catalogued cause simulated with a form its term was not
  written for (``synth_effects.FORM_VARIANTS``: added mass of another
  exponent of drag area and lagged, ``added_mass_form``; a friction factor
  settling exponentially, not a ramp, ``friction_drift_form``; load cells
  through a first-order response, not a delay, ``sensor_lag_form``); right =
  the cause named.

Seeds: case k of a study uses seed 10_000·(study index) + k, so every study
draws its own truths and noise.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

STUDIES = ("clean", "ooc", "pairs", "power", "form")
PAIRS = ("sensor_lag+canopy_breathing", "added_mass+friction_drift", "friction_drift+canopy_breathing",
         "sensor_lag+added_mass")
POWER_SIZES = {"added_mass": (0.2, 0.4, 0.6), "friction_drift": (0.03, 0.05), "sensor_lag": (0.02, 0.04, 0.08),
               "canopy_breathing": (0.03, 0.06)}
FIELDS = ["study", "scenario", "effect", "magnitude", "seed", "mode", "expected", "causes", "verdict", "right",
          "discrepancy_gain", "seconds"]


def cases(studies, seeds, scenarios):
    from cpas_bayes.data.synth_effects import FORM_VARIANTS, OUT_OF_CATALOGUE

    for s_index, study in enumerate(STUDIES):
        if study not in studies:
            continue
        base = 10_000 * (s_index + 1)
        if study == "clean":
            for k in range(seeds):
                yield study, scenarios[k % len(scenarios)], "none", None, base + k
        elif study == "ooc":
            for effect in OUT_OF_CATALOGUE:
                for k in range(seeds):
                    yield study, scenarios[k % len(scenarios)], effect, None, base + k
        elif study == "pairs":
            for k in range(seeds):
                yield study, scenarios[k % len(scenarios)], PAIRS[k % len(PAIRS)], None, base + k
        elif study == "form":
            for effect in FORM_VARIANTS:
                for k in range(seeds):
                    yield study, scenarios[k % len(scenarios)], effect, None, base + k
        else:
            for effect, sizes in POWER_SIZES.items():
                for size in sizes:
                    for k in range(seeds):
                        yield study, scenarios[k % len(scenarios)], effect, size, base + k


def expected(study, effect):
    from cpas_bayes.data.synth_effects import FORM_VARIANTS

    if study == "clean":
        return "none"
    if study == "ooc":
        return "unexplained"
    if study == "form":
        return FORM_VARIANTS[effect]
    return effect


def is_right(study, effect, causes):
    named = [c for c in causes if c != "unexplained"]
    if study == "clean":
        return not causes
    if study == "ooc":
        return causes == ["unexplained"]
    if study == "pairs":
        return sorted(named) == sorted(effect.split("+"))
    return named == [expected(study, effect)]


def run(args):
    from cpas_bayes.core.executor import make_executor
    from cpas_bayes.data.synth import synthesize
    from cpas_bayes.inference.candidate_fits import DIAGNOSIS_SAMPLER, DiagnoseOptions
    from cpas_bayes.inference.diagnose import diagnose_test
    from cpas_bayes.outputs.diagnosis import diagnosis_document

    out = Path(args.out)
    done = set()
    if out.is_file():
        with out.open(newline="") as f:
            done = {(r["study"], r["scenario"], r["effect"], r["magnitude"], r["seed"], r["mode"])
                    for r in csv.DictReader(f)}
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        with out.open("w", newline="") as f:
            csv.DictWriter(f, FIELDS).writeheader()
    effects = set(args.effects.split(",")) if args.effects else None
    sizes = {float(x) for x in filter(None, args.sizes.split(","))} or None
    todo = [c for c in cases(args.study.split(","), args.seeds, args.scenarios.split(","))
            if (effects is None or c[2] in effects) and (sizes is None or c[3] is None or c[3] in sizes)]
    todo = [c for c in todo
            if (c[0], c[1], c[2], "" if c[3] is None else str(c[3]), str(c[4]), args.mode) not in done]
    print(f"{len(todo)} cases to run ({len(done)} already in {out})", flush=True)
    executor = make_executor(args.workers)
    try:
        for i, (study, scenario, effect, magnitude, seed) in enumerate(todo):
            test, _ = synthesize(scenario, effect, seed, magnitude=magnitude)
            options = DiagnoseOptions(seed=seed, mode=args.mode, model_forms=False,
                                      sampler=replace(DIAGNOSIS_SAMPLER, workers=args.workers, progress=False))
            t0 = time.perf_counter()
            d = diagnose_test(test, options, executor=executor)
            row = {"study": study, "scenario": scenario, "effect": effect,
                   "magnitude": "" if magnitude is None else magnitude, "seed": seed, "mode": args.mode,
                   "expected": expected(study, effect), "causes": "+".join(d.causes) or "none",
                   "verdict": d.verdict, "right": is_right(study, effect, d.causes),
                   "discrepancy_gain": round(d.discrepancy["elpd_gain"], 1),
                   "seconds": round(time.perf_counter() - t0, 1)}
            doc = {k: v for k, v in diagnosis_document(d).items() if k not in ("gain", "evidence", "comparison")}
            with out.with_suffix(".jsonl").open("a") as f:   # the why of each verdict, for reading failures
                f.write(json.dumps({**row, "diagnosis": doc}) + "\n")
            with out.open("a", newline="") as f:
                csv.DictWriter(f, FIELDS).writerow(row)
            print(f"[{i + 1}/{len(todo)}] {study} {scenario} {effect} {magnitude or ''} seed {seed}: "
                  f"{row['causes']} ({'right' if row['right'] else 'WRONG'}, {row['seconds']} s)", flush=True)
    finally:
        executor.close()
    table = summary(out)
    out.with_suffix(".md").write_text(table + "\n")
    print(table)


def summary(path):
    import pandas as pd

    d = pd.read_csv(path, dtype=str, keep_default_na=False)
    d["right"] = d["right"] == "True"
    lines = ["| study | scenario | effect | size | mode | cases | right | rate | verdicts |",
             "|---|---|---|---|---|---|---|---|---|"]
    for (study, scenario, effect, size, mode), g in d.groupby(
            ["study", "scenario", "effect", "magnitude", "mode"], sort=False):
        verdicts = ", ".join(f"{k} {v}" for k, v in g["causes"].value_counts().items())
        lines.append(f"| {study} | {scenario} | {effect} | {size} | {mode} | {len(g)} | {int(g['right'].sum())} | "
                     f"{g['right'].mean():.0%} | {verdicts} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="benchmarks/detection.csv")
    parser.add_argument("--study", default=",".join(STUDIES))
    parser.add_argument("--seeds", type=int, default=20, help="cases per study cell")
    parser.add_argument("--scenarios", default="drogue,main")
    parser.add_argument("--effects", default="", help="only these hidden effects (comma-separated; default all)")
    parser.add_argument("--sizes", default="",
                        help="power study: only these sizes (comma-separated; default every size of POWER_SIZES)")
    parser.add_argument("--mode", default="full", choices=("screen", "full"),
                        help="full is what `cpas-bayes diagnose` runs; screen is the campaign's default")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    unknown = set(args.study.split(",")) - set(STUDIES)
    if unknown:
        parser.error(f"unknown study {sorted(unknown)[0]!r}; use any of {', '.join(STUDIES)}")
    known = sorted({c[2] for c in cases(STUDIES, len(PAIRS), ["drogue"])})
    unknown = set(filter(None, args.effects.split(","))) - set(known)
    if unknown:
        parser.error(f"unknown effect {sorted(unknown)[0]!r}; use any of {', '.join(known)}")
    try:
        {float(x) for x in filter(None, args.sizes.split(","))}
    except ValueError:
        parser.error(f"--sizes {args.sizes!r}: give numbers separated by commas, as 0.4,0.06")
    run(args)


if __name__ == "__main__":
    sys.exit(main())

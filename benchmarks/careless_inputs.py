"""Careless and hostile inputs: mutate the shipped bundles and a prior file, and say what the package does.

    python benchmarks/careless_inputs.py [--out benchmarks/careless_inputs.md] [NAME ...]

Each case copies an example (the two-Drogue and three-Main bundles, the logger drop, the Drogue prior file),
changes one thing a user could get wrong (a unit, a time base, a dead channel, a number at a domain's edge, a
malformed file), and runs what ``validate``, ``reduce`` and ``fit`` run before sampling: read, check, reduce,
build the model, search the MAP (one start). The outcome is one of

* ``refused`` — an input error naming the file, the place and the fix (the first words are in the table);
* ``warned`` — accepted, with the reading warnings of ``validate``/``reduce`` (their codes are in the table);
* ``accepted`` — nothing said (the MAP's log posterior beside it: far below the example's means the fit will
  be poor without a word why);
* ``CRASH`` — any other exception: a defect. The script exits with status 1 if any case crashes.

A script, not a test: the tests hold one case per rule (``tests/test_logger_input_hygiene.py``,
``tests/test_bundle.py``, ``tests/test_priors.py``); this pass is how those rules were found.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
DROGUE = ROOT / "cpas_bayes" / "data" / "examples" / "drogue-clean"
MAIN = ROOT / "cpas_bayes" / "data" / "examples" / "main-clean"
LOGGER = ROOT / "docs" / "examples" / "logger-drop"
DROGUE_PRIORS = ROOT / "cpas_bayes" / "data" / "priors" / "drogue.toml"


# ---------------------------------------------------------------------------
# mutations: functions of a bundle folder copy


def toml_sub(pattern, repl):
    def mutate(folder):
        path = folder / "test.toml"
        text = path.read_text()
        changed = re.sub(pattern, repl, text, count=1, flags=re.S)
        if changed == text:
            raise ValueError(f"pattern {pattern!r} not in {path}")
        path.write_text(changed)
    return mutate


def csv_frame(fn):
    def mutate(folder):
        path = folder / "data.csv"
        fn(pd.read_csv(path)).to_csv(path, index=False, na_rep="")
    return mutate


def column(name, fn):
    return csv_frame(lambda df: df.assign(**{name: fn(df[name].to_numpy(), df)}))


def rows(selection, name, value):
    def fn(df):
        df = df.copy()
        df.loc[selection, name] = value
        return df
    return csv_frame(fn)


def csv_bytes(fn):
    def mutate(folder):
        path = folder / "data.csv"
        path.write_bytes(fn(path.read_bytes()))
    return mutate


def both(*mutations):
    def mutate(folder):
        for m in mutations:
            m(folder)
    return mutate


def _gnss(fn):
    def frame(df):
        df = df.copy()
        fn(df, df["v_north"].notna().to_numpy())
        return df
    return csv_frame(frame)


CASES = {   # name: (example, mutation, what a user did)
    "qbar zero mid-record": (DROGUE, rows(slice(300, 310), "qbar", 0.0), "a dropout written as 0"),
    "qbar a millionth": (DROGUE, column("qbar", lambda v, df: v * 1e-6), "a unit off by 1e6"),
    "qbar in kPa (US bundle)": (MAIN, column("qbar", lambda v, df: v * 0.04788), "the wrong pressure unit"),
    "airspeed zero": (DROGUE, column("airspeed", lambda v, df: v * 0), "an empty channel written as 0"),
    "airspeed in knots": (MAIN, column("airspeed", lambda v, df: v * 0.5925), "the wrong speed unit"),
    "G all zero": (DROGUE, column("G", lambda v, df: v * 0), "a dead accelerometer"),
    "G in m/s²": (MAIN, column("G", lambda v, df: v * 9.80665), "acceleration, not load factor"),
    "G in m/s², no load cells": (DROGUE, both(column("G", lambda v, df: v * 9.80665),
                                                toml_sub(r'load_cell = "F_D3"\n', ""),
                                                toml_sub(r'load_cell = "F_D6"\n', "")),
                                 "acceleration, not load factor"),
    "G sigma negative": (DROGUE, column("G_sigma", lambda v, df: -v), "a sign slip"),
    "load cell zeroed": (DROGUE, column("F_D3", lambda v, df: v * 0), "an unplugged load cell"),
    "load cells swapped": (MAIN, csv_frame(lambda df: df.rename(columns={"F_M1": "F_M2", "F_M2": "F_M1"})),
                           "two columns mislabelled (alike canopies: no reading tells them apart)"),
    "fly-out angle from the horizontal": (MAIN, column("theta_M1", lambda v, df: 90.0 - v), "the complement"),
    "time duplicated rows": (DROGUE, csv_frame(lambda df: pd.concat([df.iloc[:100], df.iloc[99:]])),
                             "a repeated sample"),
    "time shifted 5 s": (DROGUE, column("time", lambda v, df: v - 5.0), "stage starts on another clock"),
    "time in ms": (DROGUE, column("time", lambda v, df: v * 1000), "the wrong time unit"),
    "record ends before full open": (DROGUE, csv_frame(lambda df: df[df.time < 9.0]), "a short record"),
    "diameter zero": (DROGUE, toml_sub(r"diameter = 23.00", "diameter = 0.0"), "a missing number"),
    "diameter in m (US bundle)": (DROGUE, toml_sub(r"diameter = 23.00", "diameter = 7.01"), "the wrong unit"),
    "vehicle weight zero": (DROGUE, toml_sub(r"weight = 20263.7", "weight = 0.0"), "a missing number"),
    "stages out of order": (DROGUE, toml_sub(r"start = 9.481", "start = 0.5"), "a typo"),
    "stage after the record": (DROGUE, toml_sub(r"start = 9.481", "start = 99.0"), "a typo"),
    "parachute id with a path": (DROGUE, toml_sub(r'id = "D6"', 'id = "../x"'), "a hostile name"),
    "two parachutes share a load cell": (DROGUE, toml_sub(r'load_cell = "F_D6"', 'load_cell = "F_D3"'),
                                         "a copy-paste slip"),
    "200 parachutes": (DROGUE, None, "a hostile file"),
    "unknown kind": (DROGUE, toml_sub(r'kind = "drogue"', 'kind = "dragon"'), "a kind without priors"),
    "CSV with semicolons": (DROGUE, csv_bytes(lambda b: b.replace(b",", b";")), "a European export"),
    "CSV not UTF-8": (DROGUE, csv_bytes(lambda b: b.replace(b"gamma", b"gamm\xe9", 1)), "a Latin-1 export"),
    "CSV with a NUL byte": (DROGUE, csv_bytes(lambda b: b[:5000] + b"\x00" + b[5000:]), "a damaged file"),
    "CSV ragged row": (DROGUE, csv_bytes(lambda b: b.replace(b"\n0.5,", b"\n0.5,1,2,", 1)), "a damaged file"),
    "logger: GNSS stuck": (LOGGER, _gnss(lambda df, m: [df.__setitem__(c, np.where(m, df.loc[m, c].iloc[0], np.nan))
                                                       for c in ("v_north", "v_east", "v_up", "altitude")]),
                           "a receiver that lost its fix"),
    "logger: altitude in ft": (LOGGER, _gnss(lambda df, m: df.__setitem__("altitude", df.altitude * 3.28084)),
                               "the wrong length unit"),
    "logger: time from the epoch": (LOGGER, both(column("time", lambda v, df: v + 1.7e9),
                                                 toml_sub(r"start = 1.818", "start = 1700000001.818")),
                                    "wall-clock time (accepted: it is a time base)"),
    "logger: stage at the record's end": (LOGGER, toml_sub(r"start = 1.818", "start = 19.9"),
                                          "stage start on another clock"),
    "logger: rows shuffled": (LOGGER, csv_frame(lambda df: df.sample(frac=1.0, random_state=0)), "a bad sort"),
}


def _many_parachutes(folder):
    path = folder / "test.toml"
    text = path.read_text().replace('load_cell = "F_D3"\n', "").replace('load_cell = "F_D6"\n', "")
    block = text[text.index('[[parachute]]\nid = "D6"'):]
    path.write_text(text + "".join("\n" + block.replace('id = "D6"', f'id = "X{k}"') for k in range(200)))


CASES["200 parachutes"] = (DROGUE, _many_parachutes, CASES["200 parachutes"][2])

FIRST_NP = 'n_p = { family = "lognormal", median = 10.0, sigma_log = 0.5, low = 2.0, high = 50.0 }'
PRIOR_CASES = {   # name: (text, replacement)
    "prior: expopen uniform from 0": ('expopen = { family = "lognormal", median = 2.0, sigma_log = 0.5, low = 0.3, '
                                      'high = 8.0 }', 'expopen = { family = "uniform", low = 0.0, high = 8.0 }'),
    "prior: n_p bounds reversed": (FIRST_NP, FIRST_NP.replace("low = 2.0", "low = 60.0")),
    "prior: n_p sigma 0": (FIRST_NP, FIRST_NP.replace("sigma_log = 0.5", "sigma_log = 0.0")),
    "prior: n_p a string": (FIRST_NP, 'n_p = "ten"'),
    "prior: unknown family": (FIRST_NP, 'n_p = { family = "gamma", a = 2.0 }'),
    "prior: reefing ratio above 1": ('eps = { family = "uniform", low = 0.10, high = 0.90 }',
                                     'eps = { family = "uniform", low = 0.10, high = 1.50 }'),
}


# ---------------------------------------------------------------------------
# running a case


def _first_words(text, n=14):
    words = str(text).split(": ", 1)[-1].split()
    return " ".join(words[:n]) + (" …" if len(words) > n else "")


def run_bundle(folder, priors=None):
    """(outcome, detail) of reading, checking, reducing, modelling and one MAP search of ``folder``."""
    from cpas_bayes.core.errors import InputError
    from cpas_bayes.data.bundle import read_bundle
    from cpas_bayes.data.reduction import check_reducible, reduce_test
    from cpas_bayes.inference.fit import prepare_model
    from cpas_bayes.inference.fit_health import reading_health_warnings
    from cpas_bayes.inference.start import find_map
    from cpas_bayes.stats.priors import check_override_applies, priors_of_test

    try:
        test = read_bundle(folder)
        if priors is not None:
            priors_of_test(test, priors)
            check_override_applies(priors, [p.kind for p in test.parachutes])
        check_reducible(test)
        reduction = reduce_test(test)
        model = prepare_model(test, reduction, priors=priors)
        _, log_post = find_map(model, np.random.default_rng(0), 1)
    except InputError as exc:
        return "refused", _first_words(exc)
    except Exception as exc:   # noqa: BLE001 - what this pass looks for
        return "CRASH", f"{type(exc).__name__}: {str(exc)[:120]}"
    codes = [w["code"] for w in reading_health_warnings(test)]
    others = [w for w in reduction.warnings if "trajectory" in w]   # a logger bundle's misfit to its receiver
    if codes or others:
        return "warned", ", ".join(codes + (["trajectory_misfit"] if others else [])) + f"; MAP log p {log_post:.0f}"
    return "accepted", f"MAP log p {log_post:.0f}"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "careless_inputs.md"))
    parser.add_argument("names", nargs="*", help="cases to run (default all)")
    args = parser.parse_args(argv)
    names = args.names or ["examples as shipped"] + list(CASES) + list(PRIOR_CASES)
    lines = ["| case | what a user did | outcome | detail |", "|---|---|---|---|"]
    crashed = 0
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            if name == "examples as shipped":
                results = [run_bundle(example) for example in (DROGUE, MAIN, LOGGER)]
                outcome = "accepted" if all(r[0] == "accepted" for r in results) else "/".join(r[0] for r in results)
                detail, what = "; ".join(r[1] for r in results), "(the Drogue, Main and logger examples)"
            elif name in CASES:
                example, mutate, what = CASES[name]
                folder = Path(shutil.copytree(example, Path(tmp) / re.sub(r"\W+", "_", name)))
                mutate(folder)
                outcome, detail = run_bundle(folder)
            else:
                old, new = PRIOR_CASES[name]
                text = DROGUE_PRIORS.read_text()
                if old not in text:
                    raise ValueError(f"{name}: {old!r} not in {DROGUE_PRIORS}")
                path = Path(tmp) / (re.sub(r"\W+", "_", name) + ".toml")
                path.write_text(text.replace(old, new, 1))
                outcome, detail, what = *run_bundle(DROGUE, priors=path), "a prior file (--priors)"
            crashed += outcome == "CRASH"
            lines.append(f"| {name} | {what} | {outcome} | {detail.replace('|', '/')} |")
            print(lines[-1], flush=True)
    Path(args.out).write_text("# Careless and hostile inputs\n\nWritten by `benchmarks/careless_inputs.py` (see its "
                              "docstring).\n\n" + "\n".join(lines) + "\n")
    return 1 if crashed else 0


if __name__ == "__main__":
    sys.exit(main())

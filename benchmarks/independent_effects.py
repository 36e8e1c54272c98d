"""Does `cpas-bayes diagnose` name instrument effects on data its own simulator did not write?

The two bundles in ``cpas_bayes/data/examples/`` come from an independent simulator (its truth beside them). This
script writes copies of them with an instrument effect laid onto the recorded columns, in forms written here
from scratch (nothing is imported from ``cpas_bayes``; the effects are not those of
``cpas_bayes/data/synth_effects.py``), runs ``cpas-bayes diagnose`` on each as a user would, and tabulates the
verdicts against what a right answer is:

==================  ==============================================================  ==================
effect              what is done to the recorded columns                            right verdict
==================  ==============================================================  ==================
none                nothing                                                         ``none``
cell_filter         every load cell through a critically damped two-pole low-pass   ``sensor_lag``
                    (mean delay 0.03 s); fresh noise restores the stated sigma
friction_sag        every load cell × (1 − 0.05·logistic((t − t_m)/w)): the riser   ``friction_drift``
                    friction settles in mid-record (t_m halfway from the first
                    stage to the end, w a tenth of the record), not a ramp
cell_filter+        both at once                                                    both named
friction_sag
pitot_filter        q̄ through the two-pole low-pass (mean delay 0.3 s), airspeed      ``unexplained``
                    from it at the recorded density; fresh noise as above
accel_saturation    G held at 82 % of its peak (a 5-sample running median's)         ``unexplained``
cell_zero_step      the first cell's zero steps by +6 % of its peak reading 1 s       ``unexplained``
                    after its last stage starts
riser_ring          each cell + its reading 0.3 s after each of its stage starts     ``unexplained``
                    × 0.15·e^(−τ/0.4 s)·sin(2π·6 Hz·τ): additive, not a factor
accel_zero_drift    G + 0.05·(t − t_1)/(t_end − t_1) after the first stage start      ``unexplained``
                    t_1: the accelerometer's zero drifts (load cells unchanged)
accel_warm_drift    G + 0.05·((t − t_0)/(t_end − t_0))²: the zero drifts from the      ``unexplained``
                    record's start as the sensor warms, faster later
canopy_pulse        each canopy's drag force × (1 + b_i(t)) from its full-open peak ``canopy_breathing``
                    on: b_i = A·(1 − e^(−τ·f₀))·sin(φ_i + 2π·f₀·(τ + 0.05·τ²/T)),
                    sustained (no damping), building up over a period, a random
                    phase per canopy, the frequency drifting 10 % over the rest of
                    the record (A 0.06; f₀ 1.0 Hz Drogue, 0.3 Hz Main); the
                    vehicle slows under the extra drag (first order: ΔV̇ =
                    −ΣΔD_i/m, Δq̄ = ρ·V·ΔV, every force and G re-formed)
cell_filter+        both at once                                                    both named
canopy_pulse
==================  ==============================================================  ==================

``canopy_pulse`` is a catalogued cause in a form its term was not written for: the term
(``canopy_breathing``) rings from each stage's peak with one damping ratio, phase zero at the peak.

    python benchmarks/independent_effects.py --out /tmp/independent_effects [--parallel 2] [--effects a,b]

Each diagnosis runs ``cpas-bayes diagnose BUNDLE --out DIR --workers 1`` (``--parallel`` of them at once). Rows go
to ``OUT/results.csv`` as each finishes, so a second run resumes; ``--report`` writes the Markdown table
(``OUT/independent_effects.md``) from the CSV alone.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
import time
import tomllib
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

HERE = Path(__file__).resolve().parent
EXAMPLES = HERE.parent / "cpas_bayes" / "data" / "examples"
SCENARIOS = {"drogue": "drogue-clean", "main": "main-clean"}
RIGHT = {"none": [], "cell_filter": ["sensor_lag"], "friction_sag": ["friction_drift"],
         "cell_filter+friction_sag": ["sensor_lag", "friction_drift"], "pitot_filter": ["unexplained"],
         "accel_saturation": ["unexplained"], "cell_zero_step": ["unexplained"], "riser_ring": ["unexplained"],
         "accel_zero_drift": ["unexplained"], "accel_warm_drift": ["unexplained"],
         "canopy_pulse": ["canopy_breathing"], "cell_filter+canopy_pulse": ["sensor_lag", "canopy_breathing"]}
COLUMNS = ["scenario", "effect", "right", "causes", "verdict_right", "unexplained_gain", "unexplained_se",
           "warnings", "seconds"]

CELL_DELAY = 0.03      # s, mean delay of the load cells' two-pole filter
PITOT_DELAY = 0.3      # s, mean delay of the pitot line's
SAG = 0.05             # the friction factor's fall
SATURATION = 0.82      # G ceiling / peak G
ZERO_STEP = 0.06       # the cell's zero step / its peak reading
RING = (0.15, 0.4, 6.0)   # amplitude (of the reading 0.3 s after the start), decay time constant s, Hz
G_DRIFT = 0.05         # g at the record's end
PULSE = 0.06           # the sustained breathing's relative amplitude of the drag force
PULSE_HZ = {"drogue": 1.0, "main": 0.3}
PULSE_ONSET = {"drogue": 2.0, "main": 5.0}   # s after full open within which a canopy's peak is sought
G0 = 32.174            # ft/s², the bundles' US units


def _one_pole(x, a, settled):
    """y[i] = a·y[i−1] + (1 − a)·x[i]: settled at x[0] before the record, or at rest (0)."""
    return lfilter([1.0 - a], [1.0, -a], x, zi=[a * x[0] if settled else 0.0])[0]


def two_pole(time, x, mean_delay):
    """x through two equal first-order stages (time constant mean_delay/2 each, one recursion per sample on the
    record's median step), settled at x[0]. Returns (y, Σh²): Σh² the white-noise variance ratio, from the
    two stages' impulse response."""
    a = np.exp(-float(np.median(np.diff(time))) / (0.5 * mean_delay))
    y = _one_pole(_one_pole(np.asarray(x, float), a, True), a, True)
    impulse = np.zeros(2000)
    impulse[0] = 1.0
    h = _one_pole(_one_pole(impulse, a, False), a, False)
    return y, float(np.sum(h ** 2))


def filtered_with_noise(time, x, sigma, mean_delay, rng):
    """The filtered column plus fresh white noise so that its noise again has the stated sigma (the digitiser's
    noise comes after the filter)."""
    y, share = two_pole(time, x, mean_delay)
    return y + rng.normal(0.0, 1.0, y.size) * np.asarray(sigma, float) * np.sqrt(max(1.0 - share, 0.0))


def stage_starts(test):
    return {p["id"]: [s["start"] for s in p["stage"]] for p in test["parachute"]}


def cells(test):
    return [(p["id"], p["load_cell"]) for p in test["parachute"] if "load_cell" in p]


def scenario_of(test):
    return "main" if test.get("phase") == "main" else "drogue"


def sustained_breathing(test, data, rng):
    """``canopy_pulse``: each canopy's drag D_i = F_i + W_p,i·G (lbf) grows by b_i(t)·D_i, and the vehicle
    responds to first order: ΔV(t) = −∫ΣΔD_i·cos θ_i/m dt, Δq̄ = ρ·V·ΔV; each drag is re-formed at the new q̄,
    the cells read D_i' − W_p,i·G', and G' = G + (ΣΔF_i·cos θ_i + Δq̄·CDS_V)/W_V."""
    t = data["time"]
    scenario = scenario_of(test)
    f0, span = PULSE_HZ[scenario], t[-1] - t[0]
    chutes = [p for p in test["parachute"] if "load_cell" in p]
    drag, factor, cosines = {}, {}, {}
    for p in chutes:
        col = p["load_cell"]
        full = max(s["start"] for s in p["stage"])
        window = (t >= full) & (t <= full + PULSE_ONSET[scenario])
        onset = t[window][np.argmax(data[col][window])]
        tau = np.clip(t - onset, 0.0, None)
        phase = rng.uniform(0.0, 2 * np.pi)
        b = PULSE * (1.0 - np.exp(-tau * f0)) * np.sin(phase + 2 * np.pi * f0 * (tau + 0.05 * tau ** 2 / span))
        drag[col] = data[col] + p["weight"] * data["G"]
        factor[col] = np.where(t >= onset, b, 0.0)
        angle = p.get("flyout_angle")
        cosines[col] = np.cos(np.radians(data[angle])) if angle in data else 1.0
    mass = (test["vehicle"]["weight"] + sum(p["weight"] for p in chutes)) / G0
    extra = sum(factor[c] * drag[c] * cosines[c] for c in drag)
    dv = -np.concatenate([[0.0], np.cumsum(0.5 * (extra[1:] + extra[:-1]) * np.diff(t))]) / mass   # ft/s
    dq = data["density"] * data["airspeed"] * dv
    ratio = 1.0 + dq / data["qbar"]
    force_change = {c: drag[c] * ((1.0 + factor[c]) * ratio - 1.0) for c in drag}
    dg = (sum(force_change[c] * cosines[c] for c in drag) + dq * test["vehicle"]["cds"]) / test["vehicle"]["weight"]
    for p in chutes:
        col = p["load_cell"]
        data[col] = data[col] + force_change[col] - p["weight"] * dg
    data["G"] = data["G"] + dg
    data["qbar"] = data["qbar"] + dq
    data["airspeed"] = data["airspeed"] + dv
    return data


def apply_effect(effect, test, data, rng):
    """The recorded columns (dict of arrays) with ``effect`` laid on (a '+'-joined pair: both)."""
    t = data["time"]
    starts = stage_starts(test)
    first = min(min(s) for s in starts.values())
    for part in effect.split("+"):
        if part == "none":
            continue
        if part == "cell_filter":
            for _, col in cells(test):
                data[col] = filtered_with_noise(t, data[col], data[f"{col}_sigma"], CELL_DELAY, rng)
        elif part == "friction_sag":
            mid, width = 0.5 * (first + t[-1]), 0.1 * (t[-1] - t[0])
            factor = 1.0 - SAG / (1.0 + np.exp(-(t - mid) / width))
            for _, col in cells(test):
                data[col] = data[col] * factor
        elif part == "pitot_filter":
            lagged = filtered_with_noise(t, data["qbar"], data["qbar_sigma"], PITOT_DELAY, rng)
            data["airspeed"] = data["airspeed"] * np.sqrt(np.clip(lagged, 1e-9, None) / data["qbar"])
            data["qbar"] = lagged
        elif part == "accel_saturation":
            g = data["G"]
            smooth = np.array([np.median(g[max(0, i - 2):i + 3]) for i in range(g.size)])
            data["G"] = np.minimum(g, SATURATION * smooth.max())
        elif part == "cell_zero_step":
            chute, col = cells(test)[0]
            when = max(starts[chute]) + 1.0
            data[col] = data[col] + np.where(t >= when, ZERO_STEP * np.max(data[col]), 0.0)
        elif part == "riser_ring":
            amplitude, decay, hz = RING
            for chute, col in cells(test):
                ring = np.zeros_like(t)
                for start in starts[chute]:
                    tau = t - start
                    after = tau >= 0
                    level = np.interp(start + 0.3, t, data[col])
                    ring[after] += amplitude * level * np.exp(-tau[after] / decay) * np.sin(2 * np.pi * hz * tau[after])
                data[col] = data[col] + ring
        elif part == "accel_zero_drift":
            data["G"] = data["G"] + np.where(t > first, G_DRIFT * (t - first) / (t[-1] - first), 0.0)
        elif part == "accel_warm_drift":
            data["G"] = data["G"] + G_DRIFT * ((t - t[0]) / (t[-1] - t[0])) ** 2
        elif part == "canopy_pulse":
            data = sustained_breathing(test, data, rng)
        else:
            raise SystemExit(f"unknown effect {part!r}; use some of {', '.join(RIGHT)}")
    return data


def read_columns(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    values = np.array(rows[1:], float)
    return header, {name: values[:, j] for j, name in enumerate(header)}


def write_bundle(scenario, effect, out, seed):
    source = EXAMPLES / SCENARIOS[scenario]
    target = out / "bundles" / f"{scenario}-{effect.replace('+', '-and-')}"
    if (target / "data.csv").exists():
        return target
    test = tomllib.loads((source / "test.toml").read_text())
    header, data = read_columns(source / "data.csv")
    data = apply_effect(effect, test, data, np.random.default_rng(seed))
    tmp = target.with_name(target.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    shutil.copy(source / "test.toml", tmp / "test.toml")
    with open(tmp / "data.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for i in range(data["time"].size):
            w.writerow([f"{data[name][i]:.9g}" for name in header])
    tmp.rename(target)
    return target


def diagnose(bundle, out):
    folder = out / "diagnose" / bundle.name
    t0 = time.perf_counter()
    if not (folder / "diagnosis.json").exists():
        subprocess.run([sys.executable, "-m", "cpas_bayes", "diagnose", str(bundle), "--out", str(folder),
                        "--workers", "1"], check=True, capture_output=True)
    seconds = time.perf_counter() - t0
    return json.loads((folder / "diagnosis.json").read_text()), seconds


def run_case(scenario, effect, out, seed):
    bundle = write_bundle(scenario, effect, out, seed)
    doc, seconds = diagnose(bundle, out)
    causes = list(doc.get("causes", []))
    right = RIGHT[effect]
    unexplained = doc.get("unexplained") or {}
    return {"scenario": scenario, "effect": effect, "right": ",".join(right) or "none",
            "causes": ",".join(causes) or "none", "verdict_right": sorted(causes) == sorted(right),
            "unexplained_gain": unexplained.get("elpd_gain", ""), "unexplained_se": unexplained.get("elpd_gain_se", ""),
            "warnings": len(doc.get("warnings", [])), "seconds": round(seconds, 1)}


def done_cases(path):
    if not path.exists():
        return set(), []
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {(r["scenario"], r["effect"]) for r in rows}, rows


def report(out):
    _, rows = done_cases(out / "results.csv")
    lines = ["| scenario | effect | right | verdict | right? | unexplained gain | s |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        gain = f"{float(r['unexplained_gain']):.1f} ± {float(r['unexplained_se']):.1f}" if r["unexplained_gain"] else ""
        lines.append(f"| {r['scenario']} | {r['effect']} | {r['right']} | {r['causes']} | "
                     f"{'yes' if r['verdict_right'] == 'True' else '**no**'} | {gain} | {r['seconds']} |")
    right = sum(r["verdict_right"] == "True" for r in rows)
    lines.append(f"\n{right} of {len(rows)} verdicts right.")
    (out / "independent_effects.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--effects", default=",".join(RIGHT))
    parser.add_argument("--scenarios", default="drogue,main")
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--report", action="store_true")
    args = parser.parse_args(argv)
    effects = args.effects.split(",")
    unknown = [e for e in effects if e not in RIGHT] + [s for s in args.scenarios.split(",") if s not in SCENARIOS]
    if unknown:
        parser.error(f"unknown {unknown}; effects: {', '.join(RIGHT)}; scenarios: {', '.join(SCENARIOS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    if args.report:
        return report(args.out)
    results = args.out / "results.csv"
    done, _ = done_cases(results)
    cases = [(s, e) for s in args.scenarios.split(",") for e in effects if (s, e) not in done]
    # the Mains first: they take longest
    cases.sort(key=lambda c: c[0] != "main")
    new_file = not results.exists()
    with open(results, "a", newline="") as fh, ThreadPoolExecutor(args.parallel) as pool:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        if new_file:
            w.writeheader()
        for task in as_completed([pool.submit(run_case, *c, args.out, args.seed) for c in cases]):
            row = task.result()
            w.writerow(row)
            fh.flush()
            print(row, flush=True)
    report(args.out)


if __name__ == "__main__":
    main()

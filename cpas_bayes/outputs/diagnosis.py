"""Output of a diagnosis (:mod:`cpas_bayes.inference.diagnose`), written into one folder.

* ``diagnosis.json`` — the verdict and causes, what is unexplained and where,
  the reasons, the rule, every fitted model's elpd gain and parameters, the
  forward-selection rounds, the model-form comparisons, the gain table and
  the baseline's evidence (SI); written last, so its presence marks a
  complete diagnosis.
* ``diagnosis.md`` — a short report for a flight-test engineer.
* ``candidates.csv`` — the candidates against the baseline, one row each;
  ``baseline/residual_table.csv`` and ``baseline/ppc.csv`` — the baseline's checks.
* Figures (:mod:`cpas_bayes.outputs.plots.diagnose`, :mod:`cpas_bayes.outputs.plots.fit`):
  ``elpd.png``, ``discrepancy.png``, ``screen.png`` (mode screen), ``residuals.png`` and
  ``comparison.png`` (with a term to show), ``baseline/residuals.png``,
  ``baseline/ppc.png``, ``baseline/loo_pit.png``.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from cpas_bayes.core.files import jsonable, write_csv, write_json, write_text
from cpas_bayes.core.ownership import claim_folder
from cpas_bayes.inference.candidate_fits import extension_parameters
from cpas_bayes.inference.diagnose import Diagnosis
from cpas_bayes.outputs.figures import save_figure
from cpas_bayes.outputs.plots import diagnose as figs
from cpas_bayes.outputs.plots.checks import plot_loo_pit, plot_ppc, plot_residuals
from cpas_bayes.stats.model_terms import EXTENSIONS

DIAGNOSIS_NAME = "diagnosis.json"

_WHAT = {
    "added_mass": "the air mass carried along with each canopy (enclosed and apparent) adds a momentum term "
                  "d(m_a·V)/dt to the load while the canopy grows and the system decelerates; without it the "
                  "model reaches the peak load too early and too sharp (its fitted exponent of drag area and "
                  "lag say how the carried air builds up)",
    "friction_drift": "the load-cell friction factor changes during the test, so one constant scale factor "
                      "cannot match the load cells to the accelerometer in every stage",
    "sensor_lag": "the load cells run behind the accelerometer's time base: every load-cell feature arrives "
                  "late by the same delay",
    "canopy_breathing": "the canopies' drag area rings (breathes) after each peak, a damped oscillation the "
                        "stage law does not have",
    "correlated_noise": "the errors are correlated in time (a generic AR(1) process)",
    "unexplained": "the simulation misses something no catalogued term describes; the generic discrepancy "
                   "shows where",
}


def _rounds(d: Diagnosis):
    return [{"named_before": r["named"], "reference": r["reference"], "chosen": r["chosen"], "reasons": r["reasons"],
             "terms": [c.as_dict() for c in r["checks"]], "waiting": list(r.get("waiting", [])),
             "screen": {n: {"map_gain": x.map_gain, "size": x.size, "passed": x.passed} for n, x in r["screen"].items()}}
            for r in d.rounds]


def _rule_text(o):
    return (f"a catalogued term T is judged with the generic discrepancy present: elpd(named + T + discrepancy) - "
            f"elpd(named + discrepancy) must exceed {o.min_gain:g} and {o.min_gain_se:g} se; its fit must converge, "
            "its size pass its practical floor, no parameter sit at the edge of its prior, its size posterior not "
            f"repeat its prior, and it must lead any other passing term by > {o.min_margin_se:g} se (or > "
            f"{o.min_gain:g} with {o.min_margin_ratio:g}x its gain); named terms join the reference and the others "
            "are tried again. 'unexplained' is added when the discrepancy's gain over the named terms passes the "
            f"same thresholds and they explain less than {100 * o.min_share:.0f} % of its gain over the baseline, or "
            "when nothing is named and the baseline fails its adequacy checks; 'none' needs nothing named and an "
            "adequate baseline")


def diagnosis_document(d: Diagnosis):
    """The ``diagnosis.json`` content (SI)."""
    rows = []
    for r in d.versus_baseline.to_dict("records"):
        c = d.candidates[r["name"]]
        rows.append({"name": r["name"], "elpd_diff": r["elpd_diff"], "elpd_diff_se": r["elpd_diff_se"],
                     "params": extension_parameters(c), "physical": r["physical"], "p_loo": r["p_loo"],
                     "n_high_pareto_k": r["n_high_pareto_k"], "converged": r["converged"],
                     "rhat_max": r["rhat_max"], "seconds": r["seconds"], "moved": d.moved[r["name"]]})
    for name, r in d.screen.items():
        if any(row["name"].split("+")[0] == name for row in rows):
            continue
        size = {} if r.size is None else {EXTENSIONS[name].practical_floor[0]: {"map": r.size}}
        rows.append({"name": name, "elpd_diff": None, "elpd_diff_se": None, "params": size, "physical": True,
                     "screened_out": True, "map_gain": r.map_gain, "seconds": r.seconds})
    gain = {k: v for k, v in d.gain.items() if k not in ("residuals", "means")}
    o = d.options
    disc = d.discrepancy
    return jsonable({
        "test": d.test,
        "cause": d.cause,
        "causes": d.causes,
        "verdict": d.verdict,
        "unexplained": d.unexplained,
        "reasons": d.reasons,
        "warnings": d.warnings,
        "discrepancy": {"elpd_gain": disc.get("elpd_gain"), "elpd_gain_se": disc.get("elpd_gain_se"),
                        "shape_from": disc.get("model"), "figure": "discrepancy.png",
                        "where": disc.get("where", [])},
        "adequacy": d.adequacy,
        "model_forms": d.model_forms,
        "rule": {"min_gain": o.min_gain, "min_gain_se": o.min_gain_se, "min_margin_se": o.min_margin_se,
                 "min_share": o.min_share, "text": _rule_text(o),
                 "loo": "PSIS-LOO per time bin on the joint log-likelihood of all channels of the bin; models with "
                        "the discrepancy use the exact leave-one-bin-out conditional log p(y_i | y_-i, theta)"},
        "mode": o.mode,
        "rounds": _rounds(d),
        "screen": {n: {"map_gain": r.map_gain, "size": r.size, "passed": r.passed} for n, r in d.screen.items()},
        "candidates": rows,
        "baseline": {"elpd_loo": float(d.baseline.loo.elpd), "se": float(d.baseline.loo.se),
                     "p_loo": float(d.baseline.loo.p), "seconds": d.baseline.seconds,
                     "converged": bool(d.baseline.fit.summary["diagnostics"]["converged"])},
        "comparison": d.comparison.reset_index().rename(columns={"index": "model"}),
        "gain": gain,
        "evidence": d.evidence,
        "units": "SI",
    })


def _fmt_gain_rows(gain):
    lines = ["| channel | RMSE baseline → extended | 90 % band coverage | lag-1 ACF |", "|---|---|---|---|"]
    for ch, m in gain["channels"].items():
        lines.append(f"| {ch} | {m['rmse_m2']['baseline']:.3g} → {m['rmse_m2']['extended']:.3g} m² | "
                     f"{m['coverage_90']['baseline']:.2f} → {m['coverage_90']['extended']:.2f} | "
                     f"{m['acf1']['baseline']:+.2f} → {m['acf1']['extended']:+.2f} |")
    return lines


def _headline(d: Diagnosis):
    named = [c for c in d.causes if c != "unexplained"]
    lines = []
    if named:
        lines += [f"**Cause{'s' if len(named) > 1 else ''} named: {', '.join(f'`{c}`' for c in named)}.**", ""]
        lines += [f"- `{c}`: {_WHAT[c]}." for c in named] + [""]
    if d.unexplained:
        u = d.unexplained
        places = "; ".join(f"{w['channel']}, {w['phase']}, {w['t_start']:.2f}–{w['t_end']:.2f} s" for w in u["where"])
        lines += [f"**{'Also u' if named else 'U'}nexplained**: the generic discrepancy gains "
                  f"{u['elpd_gain']:.1f} ± {u['elpd_gain_se']:.1f} in elpd beyond "
                  f"{'the named terms' if named else 'the baseline'}"
                  + (f", which explain {100 * u['share_explained']:.0f} % of it" if named else "")
                  + f". Where: {places or 'spread over the record (no region stands out)'}. "
                  "See `discrepancy.png` for its shape.", ""]
    if d.causes:
        terms = ",".join(named + (["discrepancy"] if d.unexplained else []))
        lines += [f"To fit the test with {'them' if len(named) > 1 or (named and d.unexplained) else 'it'}: "
                  f"`cpas-bayes fit BUNDLE --out FOLDER --with {terms}`"
                  + (" (the discrepancy carries what no term explains, so that it does not pull the weights, drag "
                     "areas and air-data terms)" if d.unexplained else "") + ".", ""]
    if not d.causes:
        lines += ["**No cause** (`none`): nothing to explain. The generic discrepancy gains "
                  f"{d.discrepancy['elpd_gain']:.1f} ± {d.discrepancy['elpd_gain_se']:.1f} and the baseline passes its "
                  "own checks (error multipliers, residual structure, PPC, LOO-PIT).", ""]
    return lines


def diagnosis_markdown(d: Diagnosis, units):
    """A short ``diagnosis.md`` for a flight-test engineer."""
    force = units.label("force")
    lines = [f"# Diagnosis of {d.test}", "", f"Verdict: **{d.verdict}**.", ""] + _headline(d)
    lines += ["Why:", ""] + [f"- {r}" for r in d.reasons] + [""]
    if d.warnings:
        lines += ["Warnings:", ""] + [f"- {w}" for w in d.warnings] + [""]
    if not d.adequacy.get("adequate", True):
        lines += ["The baseline fails its own checks:", ""] + [f"- {f}" for f in d.adequacy["failures"]] + [""]
    disc = d.discrepancy
    lines += ["## What the simulation gets wrong (generic discrepancy)", "",
              f"The discrepancy gains {disc['elpd_gain']:.1f} ± {disc['elpd_gain_se']:.1f} in elpd over the baseline. "
              f"Regions where its fitted shape (model `{disc['model']}`) is beyond 2 sd and beyond the stated 1-sigma:",
              "", "| channel | phase | from (s) | to (s) | largest (m²) |", "|---|---|---|---|---|"]
    for w in disc["where"]:
        lines.append(f"| {w['channel']} | {w['phase']} | {w['t_start']:.2f} | {w['t_end']:.2f} | {w['peak_m2']:+.3g} |")
    if not disc["where"]:
        lines.append("| — | — | — | — | — |")
    lines += ["", "Its shape, channel by channel: `discrepancy.png` (and `discrepancy.csv`).", ""]
    lines += ["## Forward selection (each term judged with the discrepancy present)", "",
              "| round | term | elpd gain ± se over | converged | size | stand-in / prior only | passed |",
              "|---|---|---|---|---|---|---|"]
    for i, r in enumerate(d.rounds):
        for c in r["checks"]:
            flags = "; ".join(c.at_edge + ([f"prior only: {', '.join(c.repeats_prior)}"] if c.repeats_prior else []))
            size = "—" if c.size is None else f"{c.size:.3g}"
            lines.append(f"| {i + 1} | {c.term} | {c.elpd_diff:.1f} ± {c.elpd_diff_se:.1f} over `{c.reference}` | "
                         f"{'yes' if c.converged else '**failed**'} | {size} | {flags or '—'} | "
                         f"{'yes' if c.gains and c.eligible else 'no'} |")
        for name, x in r["screen"].items():
            if name in r.get("waiting", []):
                lines.append(f"| {i + 1} | {name} | not sampled: MAP gain {x.map_gain:+.1f} could not rival "
                             f"{r['chosen']} (tried again next round) | — | "
                             f"{'—' if x.size is None else f'{x.size:.3g}'} | — | no |")
            elif name not in {c.term for c in r["checks"]}:
                lines.append(f"| {i + 1} | {name} | not sampled: MAP gain {x.map_gain:+.1f} (screen) | — | "
                             f"{'—' if x.size is None else f'{x.size:.3g}'} | — | no |")
    lines += ["", "## Every model fitted (elpd gain over the baseline, PSIS-LOO)", "",
              "| model | elpd gain ± se | its terms' parameters (posterior mean ± sd) | parameters that moved > 1 sd |",
              "|---|---|---|---|"]
    for r in d.versus_baseline.sort_values("elpd_diff", ascending=False).to_dict("records"):
        params = extension_parameters(d.candidates[r["name"]])
        ptxt = ", ".join(f"{k} = {v['mean']:.3g} ± {v['sd']:.2g}{(' ' + v['unit']) if v['unit'] else ''}"
                         for k, v in params.items())
        moved = d.moved[r["name"]]
        mtxt = ", ".join(f"{k} ({v['shift_in_baseline_sd']:+.1f} sd)" for k, v in list(moved.items())[:4]) or "—"
        lines.append(f"| {r['name']} | {r['elpd_diff']:.1f} ± {r['elpd_diff_se']:.1f} | {ptxt} | {mtxt} |")
    if d.model_forms:
        lines += ["", "## Model form (the seed's by-eye arguments, by ΔELPD)", ""]
        lines += [f"- {f['comparison']}: {f['in_words']}" for f in d.model_forms]
    lines.append("")
    if d.gain:
        g = d.gain
        title = f"Gain of the named terms ({g['extension']}) over the baseline"
        lines += [f"## {title}", "", f"elpd gain {g['elpd_gain']:.1f} ± {g['elpd_gain_se']:.1f}.", ""]
        lines += _fmt_gain_rows(g) + [""]
        em = ", ".join(f"{k} {v['baseline']:.2f} → {v['extended']:.2f}" for k, v in g["error_multipliers"].items())
        lines += [f"Error multipliers (1 = the stated sigmas suffice): {em}.", ""]
        lines += ["| series | measured peak | baseline: peak error, time error | extended: peak error, time error |",
                  "|---|---|---|---|"]
        for s, p in g["peaks"].items():
            lines.append(f"| {s} | {units.from_si(p['measured_peak_n'], 'force'):,.0f} {force} at "
                         f"{p['measured_time_s']:.2f} s | {p['peak_error_pct']['baseline']:+.1f} %, "
                         f"{p['time_error_s']['baseline']:+.3f} s | {p['peak_error_pct']['extended']:+.1f} %, "
                         f"{p['time_error_s']['extended']:+.3f} s |")
        lines.append("")
    ev = d.evidence
    lines += ["## What the baseline's checks showed", "",
              "| channel | residual sd | lag-1 ACF | Ljung–Box p |", "|---|---|---|---|"]
    for ch, r in ev["residuals"].items():
        lines.append(f"| {ch} | {r['sd']:.2f} | {r['acf1']:+.2f} | {r['ljung_box_p']:.2g} |")
    lines += ["", f"PPC statistics outside 1–99 %: {len(ev['ppc_flags'])}; bins with Pareto k > 0.7: "
                  f"{ev['pareto_k']['n_high_pareto_k']}.", "",
              "Figures: `elpd.png` (the comparison), `discrepancy.png` (what is missing, where), `screen.png` (MAP screen, mode screen), `residuals.png` "
              "(before/after), `comparison.png` (predictions against the data), `baseline/residuals.png`, "
              "`baseline/ppc.png`, `baseline/loo_pit.png`.", ""]
    return "\n".join(lines)


def _change_window(time, base_mean, ext_mean, data, half_width):
    """Centre of the window where the extended prediction improves the squared error most."""
    gain = (data - base_mean) ** 2 - (data - ext_mean) ** 2
    kernel = np.ones(max(3, int(np.sum(np.abs(time - time[0]) < 2 * half_width))))
    smooth = np.convolve(gain, kernel / kernel.size, mode="same")
    centre = time[int(np.argmax(smooth))]
    return centre - half_width, centre + half_width


def write_diagnosis(d: Diagnosis, out):
    """Write ``diagnosis.json``, ``diagnosis.md``, the tables and the figures into ``out``."""
    out = claim_folder(out)
    units = d.baseline.fit.model.test.units

    def save(fig, name):
        save_figure(fig, out / name, dpi=110)
        plt.close(fig)

    if len(d.versus_baseline):
        save(figs.plot_elpd(d.versus_baseline, d.causes, d.options.min_gain, d.options.min_gain_se, d.test),
             "elpd.png")
    if d.discrepancy.get("shape") is not None:
        save(figs.plot_discrepancy(d.discrepancy["shape"], d.discrepancy["where"], units, d.test), "discrepancy.png")
        shape = d.discrepancy["shape"]
        table = {"time_s": shape["time"]}
        for c, name in enumerate(shape["channels"]):
            table[f"{name} mean_m2"] = shape["mean"][c]
            table[f"{name} sd_m2"] = shape["sd"][c]
        write_csv(out / "discrepancy.csv", pd.DataFrame(table))
    if d.screen:
        save(figs.plot_screen(d.screen, d.options.screen_gain, d.test), "screen.png")
    save(plot_residuals(d.checks.residuals), "baseline/residuals.png")
    save(plot_ppc(d.checks.ppc), "baseline/ppc.png")
    save(plot_loo_pit(d.checks.loo_pit), "baseline/loo_pit.png")
    write_csv(out / "baseline" / "residual_table.csv", d.checks.residuals.table)
    write_csv(out / "baseline" / "ppc.csv", d.checks.ppc.table)
    write_csv(out / "candidates.csv", d.versus_baseline)
    if d.gain:
        name = d.gain["extension"]
        reports = d.gain["residuals"]
        save(figs.plot_residual_comparison(reports["baseline"], reports["extended"], name, d.test), "residuals.png")
        model = d.baseline.fit.model
        obs = model.obs
        (base_acc, base_lc), (ext_acc, ext_lc) = d.gain["means"]["baseline"], d.gain["means"]["extended"]
        channels = [("accelerometer drag area (Eq. 8)", obs.acc, base_acc, ext_acc)]
        for row, chute in enumerate(obs.lc_index):
            pid = model.parachutes[int(chute)].id
            channels.append((f"load cell {pid}", obs.lc[row], base_lc[row], ext_lc[row]))
        infinite = all(p.inflation == "infinite" for p in model.parachutes)
        # zoom on the channel the term improves most (load cells carry lag and friction effects)
        best = max(channels, key=lambda c: np.sum((c[1] - c[2]) ** 2 - (c[1] - c[3]) ** 2))
        window = _change_window(obs.time, best[2], best[3], best[1], 1.0 if infinite else 4.0)
        save(figs.plot_fit_comparison(obs.time, channels, units, name, d.test, window), "comparison.png")
    write_text(out / "diagnosis.md", diagnosis_markdown(d, units))
    write_json(out / DIAGNOSIS_NAME, diagnosis_document(d))   # last: its presence marks a complete diagnosis
    return out / DIAGNOSIS_NAME

"""Output of a diagnosis (:mod:`cpas_bayes.inference.diagnose`), written into one folder.

* ``diagnosis.json`` — the cause, the reasons, the rule, every candidate's
  elpd gain and parameters, the gain table and the baseline's evidence (SI);
  written last, so its presence marks a complete diagnosis.
* ``diagnosis.md`` — a short report for a flight-test engineer.
* ``candidates.csv`` — the candidates against the baseline, one row each;
  ``baseline/residual_table.csv`` and ``baseline/ppc.csv`` — the baseline's checks.
* Figures (:mod:`cpas_bayes.outputs.plots.diagnose`, :mod:`cpas_bayes.outputs.plots.fit`):
  ``elpd.png``, ``screen.png`` (mode screen), ``residuals.png`` and
  ``comparison.png`` (with a term to show), ``baseline/residuals.png``,
  ``baseline/ppc.png``, ``baseline/loo_pit.png``.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from cpas_bayes.core.files import jsonable, write_csv, write_json, write_text
from cpas_bayes.core.ownership import claim_folder
from cpas_bayes.inference.candidate_fits import extension_parameters
from cpas_bayes.inference.diagnose import Diagnosis
from cpas_bayes.outputs.figures import save_figure
from cpas_bayes.outputs.plots import diagnose as figs
from cpas_bayes.outputs.plots.fit import plot_loo_pit, plot_ppc, plot_residuals
from cpas_bayes.stats.model_terms import EXTENSIONS

DIAGNOSIS_NAME = "diagnosis.json"

_WHAT = {
    "added_mass": "the air mass carried along with each canopy (enclosed and apparent) adds a momentum term "
                  "d(m_a·V)/dt to the load while the canopy grows and the system decelerates; without it the "
                  "model reaches the peak load too early and too sharp",
    "friction_drift": "the load-cell friction factor changes during the test, so one constant scale factor "
                      "cannot match the load cells to the accelerometer in every stage",
    "sensor_lag": "the load cells run behind the accelerometer's time base: every load-cell feature arrives "
                  "late by the same delay",
    "canopy_breathing": "the canopies' drag area rings (breathes) after each peak, a damped oscillation the "
                        "stage law does not have",
    "correlated_noise": "the errors are correlated in time (a generic AR(1) process), which no physical term "
                        "explains better",
}


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
        if name in d.candidates:
            continue
        size = {} if r.size is None else {EXTENSIONS[name].practical_floor[0]: {"map": r.size}}
        rows.append({"name": name, "elpd_diff": None, "elpd_diff_se": None, "params": size, "physical": True,
                     "screened_out": True, "map_gain": r.map_gain, "seconds": r.seconds})
    gain = {k: v for k, v in d.gain.items() if k not in ("residuals", "means")}
    o = d.options
    return jsonable({
        "test": d.test,
        "cause": d.cause,
        "reasons": d.reasons,
        "rule": {"min_gain": o.min_gain, "min_gain_se": o.min_gain_se, "min_margin_se": o.min_margin_se,
                 "text": f"the physical term with the largest elpd gain is named when the gain is > "
                         f"{o.min_gain:g} and > {o.min_gain_se:g} se, it beats correlated_noise, and, when the next "
                         f"physical term also gains > {o.min_gain:g}, it leads that term by > {o.min_margin_se:g} "
                         f"se of their paired difference or by > {o.min_gain:g} with {o.min_margin_ratio:g}x its "
                         "gain; the named term's size must pass its practical floor; otherwise none",
                 "loo": "PSIS-LOO per time bin on the joint log-likelihood of all channels of the bin; "
                        "correlated_noise uses the AR-conditional log p(y_t | y_t-1)"},
        "mode": o.mode,
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


def diagnosis_markdown(d: Diagnosis, units):
    """A short ``diagnosis.md`` for a flight-test engineer."""
    force = units.label("force")
    lines = [f"# Diagnosis of {d.test}", ""]
    if d.cause != "none":
        lines += [f"**Cause named: `{d.cause}`.** In words: {_WHAT[d.cause]}.", ""]
    else:
        lines += ["**No physical cause named** (`none`): the baseline simulation explains the data as well as "
                  "any of the candidate terms, within the rule below.", ""]
    lines += ["Why:", ""] + [f"- {r}" for r in d.reasons] + [""]
    lines += ["## Candidates (elpd gain over the baseline, PSIS-LOO)", "",
              "| term | elpd gain ± se | its parameters (posterior mean ± sd) | parameters that moved > 1 sd |",
              "|---|---|---|---|"]
    for r in d.versus_baseline.sort_values("elpd_diff", ascending=False).to_dict("records"):
        params = extension_parameters(d.candidates[r["name"]])
        ptxt = ", ".join(f"{k} = {v['mean']:.3g} ± {v['sd']:.2g}{(' ' + v['unit']) if v['unit'] else ''}"
                         for k, v in params.items())
        moved = d.moved[r["name"]]
        mtxt = ", ".join(f"{k} ({v['shift_in_baseline_sd']:+.1f} sd)" for k, v in list(moved.items())[:4]) or "—"
        lines.append(f"| {r['name']} | {r['elpd_diff']:.1f} ± {r['elpd_diff_se']:.1f} | {ptxt} | {mtxt} |")
    for name, r in d.screen.items():
        if name not in d.candidates:
            size = f"size {r.size:.3g} at the MAP" if r.size is not None else ""
            lines.append(f"| {name} | not sampled: MAP gain {r.map_gain:+.1f} (screen) | {size} | — |")
    lines.append("")
    if d.gain:
        g = d.gain
        title = "Gain of the named term" if g.get("named") else f"What the best physical term ({g['extension']}) would change"
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
              "Figures: `elpd.png` (the comparison), `screen.png` (MAP screen, mode screen), `residuals.png` "
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
        save(figs.plot_elpd(d.versus_baseline, d.cause, d.options.min_gain, d.options.min_gain_se, d.test),
             "elpd.png")
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

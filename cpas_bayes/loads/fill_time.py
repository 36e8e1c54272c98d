"""The seed's claim about n_p, measured: peak fill times with n_p dispersed against n dispersed (§V.D).

Dispersing the fill constant n (Eq. 14) independently of C_k and expopen
gives peak fill times t_fp = t_f·S^(1/expopen) (Eq. 15) that no test showed,
since S^(1/expopen) comes from parameters drawn apart from n; dispersing
n_p (Eq. 17) and deriving n per run (Eq. 18) fixes t_fp by n_p alone (seed
Fig. 21–22). :func:`compare_fill_time_dispersion` runs the same Monte Carlo
(:mod:`cpas_bayes.loads.montecarlo`) both ways and counts, per parachute kind
and memo stage, the peak fill times outside the range seen in the pooled
tests (the memo's ``t_fp`` bounds). :mod:`cpas_bayes.outputs.montecarlo`
writes the result (``np_vs_n.json``, ``fill_time_np_vs_n.png``).

Under NASA CML's linear mode (``decay="cml_linear"``) the growth ends at the
peak: t_fp = t_f and n = n_p (:func:`cpas_bayes.physics.inflation.peak_exponent`),
so the factor S^(1/expopen) that the claim is about is not there.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass

import numpy as np

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.summaries import quantile_summary
from cpas_bayes.data.bundle import FlightTest
from cpas_bayes.loads.montecarlo import MODES, QUANTILE_LEVELS, ClusterLayout, run_monte_carlo
from cpas_bayes.physics.trajectory import SimulationOptions
from cpas_bayes.population.memo import MEMO_NAME, Memo


@dataclass(frozen=True)
class FillTimeGroup:
    """Peak fill times of one parachute kind and memo stage in both dispersion modes."""

    kind: str
    stage: str                 # memo stage key
    stage_labels: tuple        # the like-test's labels of the canopies' stages pooled here
    bounds: tuple              # (low, high) t_fp range seen in the pooled tests, s
    t_fp: dict                 # mode -> (runs × canopies,) peak fill times, s

    def _finite_values(self, mode):
        x = np.asarray(self.t_fp[mode], float)
        return x[np.isfinite(x)]

    def fraction_below(self, mode):
        x = self._finite_values(mode)
        return float(np.mean(x < self.bounds[0])) if x.size else math.nan

    def fraction_above(self, mode):
        x = self._finite_values(mode)
        return float(np.mean(x > self.bounds[1])) if x.size else math.nan

    def fraction_outside(self, mode):
        """Share of (run, canopy) peak fill times outside the tested range."""
        return self.fraction_below(mode) + self.fraction_above(mode)


@dataclass(frozen=True)
class FillTimeComparison:
    """Monte Carlo of the same configuration with n_p (Eq. 17/18) and with n dispersed, parameters independent."""

    layout: ClusterLayout
    runs: int
    groups: tuple
    results: dict              # mode -> MonteCarloResult
    runtime_s: float

    def to_json(self):
        groups = []
        for g in self.groups:
            entry = {"kind": g.kind, "stage": g.stage, "stage_labels": list(g.stage_labels),
                     "tested_t_fp_range_s": list(g.bounds), "samples": int(len(g.t_fp["n_p"]))}
            for mode in MODES:
                entry[mode] = {"fraction_outside": g.fraction_outside(mode), "fraction_below": g.fraction_below(mode),
                               "fraction_above": g.fraction_above(mode),
                               "t_fp_s": quantile_summary(g.t_fp[mode], QUANTILE_LEVELS, finite_only=True)}
            groups.append(entry)
        return {
            "claim": ("seed §V.D: dispersing n, C_k and expopen independently yields peak fill times no test showed; "
                      "dispersing n_p (Eq. 17) and deriving n per run (Eq. 18) keeps them within the tested range"),
            "like": {"test": self.layout.test_name,
                     "bundle": str(self.layout.source) if self.layout.source else None},
            "runs": self.runs,
            "dispersion": "independent per parameter (joint=False) in both modes; identical draws of every "
                          "other parameter and of the stage starts",
            "fraction_definition": "share of (run, canopy) peak fill times t_fp outside the memo's t_fp bounds "
                                   "(the range of peak fill times seen in the pooled tests)",
            "groups": groups,
            "runtime_s": self.runtime_s,
        }


def compare_fill_time_dispersion(memo: Memo, like: FlightTest, runs: int, rng: np.random.Generator, batch=None,
                                 progress=None, options: SimulationOptions = SimulationOptions(),
                                 engine="auto", executor=None) -> FillTimeComparison:
    """Run the same Monte Carlo with n_p and with n dispersed; t_fp outside the tested range per kind and stage.

    Both modes draw every parameter independently from its memo family
    (``joint=False``, the classic dispersion, in which C_k and expopen are
    free of n) from one seed, so every drawn value except the fill constant
    and every stage start are the same in both; the only difference is
    whether the fill constant drawn is n_p (n then derived by Eq. 18) or n.
    The tested range of each kind and stage is the memo's ``t_fp`` bounds.
    """
    layout = ClusterLayout.from_test(like)
    groups_needed = {}
    for i, kind in enumerate(layout.kinds):
        for k in range(int(layout.stages_per_chute[i])):
            groups_needed.setdefault((kind, layout.stage_key(i, k)), []).append((i, k))
    bounds = {}
    for kind, key in groups_needed:
        lo, hi = memo.entry(kind, key, "t_fp").bounds
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise InputError(memo.folder / MEMO_NAME if memo.folder else MEMO_NAME, f"key '{kind}.{key}.t_fp'",
                             f"bounds {[lo, hi]} are not a finite range of peak fill times",
                             "give t_fp bounds = [shortest, longest] peak fill time seen in the pooled tests")
        bounds[(kind, key)] = (float(lo), float(hi))
    seed = int(rng.integers(2**63))
    clock = _time.perf_counter()
    results = {mode: run_monte_carlo(memo, like, runs, np.random.default_rng(seed), mode=mode, joint=False,
                                     batch=batch, progress=progress, options=options, engine=engine,
                                     executor=executor)
               for mode in MODES}
    runtime = _time.perf_counter() - clock
    groups = []
    for (kind, key), members in groups_needed.items():
        t_fp = {mode: np.concatenate([res.outputs.t_fp[:, i, k] for i, k in members]) for mode, res in results.items()}
        labels = tuple(dict.fromkeys(layout.stage_labels[i][k] for i, k in members))
        groups.append(FillTimeGroup(kind, key, labels, bounds[(kind, key)], t_fp))
    return FillTimeComparison(layout, runs, tuple(groups), results, runtime)

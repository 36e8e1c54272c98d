"""Population inference from many per-test posteriors: the model memo's dispersions.

Every fitted test gives posterior draws of each inflation parameter under the
prior that fit used. Pooling asks what *population* of parachutes of one kind
the tests were drawn from, per stage key (``first``, ``reefed1``…,
``full_open``) and parameter, and returns the answer as memo entries and
population-predictive draws for Monte Carlo (:meth:`PoolResult.to_memo`;
:mod:`cpas_bayes.outputs.memo` writes the memo folder). This module turns fits
into that population; the method lives in

* :mod:`cpas_bayes.population.families` — the population families p(x | λ);
* :mod:`cpas_bayes.population.reweighting` — per-test draws, the fit's prior
  divided out by importance reweighting, ESS guard and scale floor;
* :mod:`cpas_bayes.population.hyper_posterior` — grid hyper-posterior,
  predictive draws, family choice by leave-one-test-out elpd;
* :mod:`cpas_bayes.population.copula` — the correlated (n_p, expopen) pair.

Fits come as :class:`~cpas_bayes.inference.fit_folder.FitRecord` (read from
fit folders by :func:`pool_folders`, or made in memory from a
:class:`~cpas_bayes.inference.fit.Fit` by ``FitRecord.from_fit``); both pool
alike.

Which parameters and which per-test prior
-----------------------------------------
* sampled parameters (``n_p``, ``expopen``, ``ck``, ``tk``, ``eps`` of
  non-final stages): π_i is the fit's prior of that parameter;
* ``cd_o = CDS_o / S_o`` with S_o = π·D_o²/4 per canopy; the fit's prior on
  CDS_o is the kind's cd_o prior scaled by S_o, so
  π_i(cd_o) = π_CDS(cd_o·S_o)·S_o;
* the derived fill constant ``n = n_p·S^(−1/expopen)`` (Eq. 18) has no prior of
  its own. The population model for n replaces the prior of n_p *given
  everything else* o (C_k, expopen, eps, the starts…): at fixed o the map
  n_p ↦ n is linear, n_p = n·k(o) with k = S^(1/expopen), so the induced
  conditional prior is exact::

      π_i(n | o) = π_np(n_p)·k = π_np(n_p)·n_p/n

  evaluated on each draw's own (n_p, n). Reweighting by p(n | λ)/π_i(n | o)
  is exact (the other parameters keep their fit priors), with no density
  estimate;
* ``t_fp`` (peak fill time) is derived from the flight condition and not
  pooled: the per-canopy posterior medians and their range are recorded.

Population predictive and the memo
----------------------------------
Predictive draws: λ from the hyper-posterior, then x from p(x | λ) (a
correlated pair jointly through the copula). Naive pooling of the per-test
draws would ignore how few tests there are; this folds the hyper-parameter
uncertainty into the tails. One row of ``memo_draws.csv`` is one parachute:
every column of its kind is a predictive draw, the correlated pair jointly, the
rest independently. The derived n and t_fp are not columns: a Monte Carlo
computes n from the row's n_p by Eq. 18 with the drag area it holds at the
disreef. Each memo entry's ``params`` are the chosen family fitted by
maximum likelihood to its predictive draws (so ``joint=False`` sampling
reproduces the predictive, hyper-uncertainty included); ``quantiles`` are the
draws' 1/5/50/95/99 %; ``criterion`` holds the elpd_LOO of every family
(and, for n_p and expopen, the correlation's). ``bounds`` are the
truncation (truncnormal), the beta's range, or else the fit prior's support;
draws are clipped to them, as :meth:`~cpas_bayes.population.memo.MemoEntry.sample` does.
The t_fp entry is ``uniform`` over the range of the per-canopy posterior
medians; its quantiles are those of the medians, which its ``criterion``
lists by test and canopy.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.summaries import quantile_summary
from cpas_bayes.inference.fit_folder import POSTERIOR_NAME, FitRecord, load_fit
from cpas_bayes.population.copula import PAIR, pool_pair
from cpas_bayes.population.families import FAMILY_NAMES, make_family
from cpas_bayes.population.hyper_posterior import FamilySelection, ParameterPool, default_hyper_scale, select_family
from cpas_bayes.population.memo import Memo, MemoEntry
from cpas_bayes.stats.psis import PARETO_K_MAX
from cpas_bayes.population.reweighting import ESS_MIN, PerTestDraws, PoolWarning

POOLED_PARAMETERS = ("n_p", "n", "expopen", "ck", "tk", "eps")   # pooled per stage (n derived by Eq. 18)
DRAWN_PARAMETERS = ("n_p", "expopen", "ck", "tk", "eps")   # columns of memo_draws.csv per stage
PARACHUTE_STAGE = "parachute"
MEMO_QUANTILE_LEVELS = (0.01, 0.05, 0.5, 0.95, 0.99)      # a memo entry's quantiles: q01 … q99
CRITERION_NAME = "loo_test"
METHOD = ("hierarchical population per kind/stage/parameter: per-test posterior draws reweighted by "
          "population/prior (Thrane & Talbot 2019), grid hyper-posterior with flat location and half-Cauchy "
          "scale hyper-priors, family by leave-one-test-out elpd; (n_p, expopen) Gaussian-copula pair "
          "(Laplace + PSIS importance sampling, emcee fallback) kept when its PSIS-LOO elpd beats rho = 0; "
          "population-predictive draws")


@dataclass
class EntryPool:
    """The pooled population of one (kind, stage, parameter)."""

    kind: str
    stage: str
    parameter: str
    selection: FamilySelection
    per_canopy: pd.DataFrame       # test, canopy, median, q05, q95 (posterior, natural units)
    n_tests: int
    bounds: tuple                  # support written to the memo
    predictive: np.ndarray = None  # the memo column (the pair's when the correlation is kept)
    memo_params: dict = None
    quantiles: dict = None
    correlation: dict | None = None

    @property
    def family(self):
        return self.selection.chosen

    @property
    def pool(self) -> ParameterPool:
        return self.selection.pool

    @property
    def criterion(self):
        return self.selection.criterion

    def population(self, level=0.90):
        """{'mean': (lo, med, hi), 'sd': (...)} of the hyper-posterior."""
        return {"mean": self.pool.interval("mean", level), "sd": self.pool.interval("sd", level)}


@dataclass
class PeakFillTimes:
    """t_fp of one kind and stage: per-canopy posterior medians (s) and their range."""

    kind: str
    stage: str
    per_canopy: pd.DataFrame      # test, canopy, median, q05, q95
    n_tests: int

    @property
    def range(self):
        m = self.per_canopy["median"].to_numpy()
        return float(m.min()), float(m.max())

    def quantiles(self):
        """The memo's quantiles (q01 … q99) of the per-canopy medians."""
        return quantile_summary(self.per_canopy["median"], MEMO_QUANTILE_LEVELS, mean=False, sd=False)


@dataclass
class PoolResult:
    """Everything pooling found: entries, correlated pairs, peak fill times, draws, provenance."""

    entries: dict                 # (kind, stage, parameter) -> EntryPool
    pairs: dict                   # (kind, stage) -> PairPool
    peak_fill: dict               # (kind, stage) -> PeakFillTimes
    draws: pd.DataFrame           # memo_draws.csv
    tests: list
    seeds: list
    folders: list                 # each test's fit folder (None for a fit pooled from memory)
    warnings: list
    skipped: list
    method: str = METHOD

    def ess_table(self):
        """Per test and entry: ESS at the inferred population (chosen family)."""
        rows = []
        for (kind, stage, param), e in sorted(self.entries.items()):
            for t, ess in zip(e.pool.tests, e.pool.ess):
                rows.append({"kind": kind, "stage": stage, "parameter": param, "test": t, "ess": float(ess)})
        return pd.DataFrame(rows)

    def summary_table(self):
        """One row per memo entry: family, parameters, population quantiles, hyper-posterior of mean and sd."""
        rows = []
        for (kind, stage, param), e in sorted(self.entries.items()):
            pop = e.population()
            rows.append({"kind": kind, "stage": stage, "parameter": param, "family": e.family,
                         "params": e.memo_params, **e.quantiles, "n_tests": e.n_tests,
                         "mean_q05": pop["mean"][0], "mean_q50": pop["mean"][1], "mean_q95": pop["mean"][2],
                         "sd_q05": pop["sd"][0], "sd_q50": pop["sd"][1], "sd_q95": pop["sd"][2],
                         "criterion": dict(e.criterion), "min_ess": float(np.min(e.pool.ess))})
        for (kind, stage), p in sorted(self.peak_fill.items()):
            rows.append({"kind": kind, "stage": stage, "parameter": "t_fp", "family": "uniform",
                         "params": {"low": p.range[0], "high": p.range[1]}, **p.quantiles(), "n_tests": p.n_tests})
        return pd.DataFrame(rows)

    def to_memo(self, provenance=None) -> Memo:
        """The :class:`~cpas_bayes.population.memo.Memo` (entries, joint draws, provenance)."""
        from cpas_bayes import __version__

        prov = {"package_version": __version__,
                "created": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "tests": list(self.tests), "seeds": [int(s) for s in self.seeds], "method": self.method}
        if self.warnings:
            prov["warnings"] = list(self.warnings)
        prov.update(provenance or {})
        entries = {}
        for key, e in self.entries.items():
            crit = {"name": CRITERION_NAME, "values": {k: float(v) for k, v in e.criterion.items()}}
            if e.correlation is not None:
                crit["correlation"] = e.correlation
            entries[key] = MemoEntry(e.kind, e.stage, e.parameter, e.family, dict(e.memo_params),
                                     tuple(float(b) for b in e.bounds), dict(e.quantiles), int(e.n_tests), crit)
        for (kind, stage), p in self.peak_fill.items():
            lo, hi = p.range
            entries[(kind, stage, "t_fp")] = MemoEntry(
                kind, stage, "t_fp", "uniform", {"low": lo, "high": hi}, (lo, hi), p.quantiles(), int(p.n_tests),
                {"name": "per-canopy posterior medians (bounds: their range; quantiles: theirs)",
                 "values": {f"{r.test} {r.canopy}": float(r.median) for r in p.per_canopy.itertuples()}})
        return Memo(entries, self.draws.copy(), prov)


def _prior_width(prior, family):
    """sd of the prior in the family's coordinate (from its quantile function): the half-Cauchy s₀."""
    if prior is None:
        return None
    x = prior.ppf(np.linspace(0.005, 0.995, 199))
    z = family.coordinate(x)
    z = z[np.isfinite(z)]
    width = float(np.std(z)) if z.size > 1 else 0.0
    return width if width > 0 else None


def _families_for(parameter):
    return FAMILY_NAMES if parameter == "eps" else ("normal", "truncnormal", "lognormal")


@dataclass
class _Unit:
    """One canopy's draws of one parameter (subsampled indices of its record applied)."""

    test: str
    canopy: str
    values: np.ndarray
    log_prior: np.ndarray
    full: np.ndarray          # all draws, for the per-canopy summary
    prior: object             # the prior in natural units (for the support and s₀), or None
    support: tuple


def _gather(records, rng, max_samples):
    """{(kind, stage, parameter): {test: [_Unit]}} plus t_fp medians; draws aligned per record."""
    groups, tfp = {}, {}
    s_common = min(min(v.size for v in r.draws.values()) for r in records)
    s_common = min(s_common, max_samples)
    for r in records:
        n = min(v.size for v in r.draws.values())
        pick = np.sort(rng.choice(n, size=s_common, replace=False)) if n > s_common else np.arange(n)
        where = r.source_file(POSTERIOR_NAME)
        seen = set()
        for pid, kind, _inflation, diameter, keys in r.parachutes():
            area = math.pi / 4 * float(diameter) ** 2
            # a composite fit's group is one canopy of the population, pooled once (its members' variables
            # repeat the group's draws); derived quantities (n, t_fp) keep the member's name
            prefix = r.parameter_prefix(pid)
            if prefix in seen:
                continue
            seen.add(prefix)
            label = pid if prefix == pid else prefix

            def add(stage, param, full, log_prior_full, prior, support, name):
                if not np.all(np.isfinite(full)):
                    raise InputError(where, f"variable '{name}'", "non-finite posterior draws", "rerun the fit")
                if not np.all(np.isfinite(log_prior_full)):
                    raise InputError(where, f"variable '{name}'", "posterior draws outside the fit's prior support",
                                     "rerun the fit with this version of cpas_bayes (summary.json priors must be "
                                     "those the fit used)")
                unit = _Unit(r.test, label, full[pick], log_prior_full[pick], full, prior, support)
                groups.setdefault((kind, stage, param), {}).setdefault(r.test, []).append(unit)

            name = f"{prefix}.cds_o"
            if name in r.draws and name in r.priors:
                prior = r.priors[name].scaled(1.0 / area)
                cd = r.draws[name] / area
                add(PARACHUTE_STAGE, "cd_o", cd, r.priors[name].logpdf(cd * area) + math.log(area), prior,
                    prior.support, name)
            for k, key in enumerate(keys):
                pre, own = f"{prefix}.s{k + 1}", f"{pid}.s{k + 1}"
                for param in POOLED_PARAMETERS:
                    name = f"{own if param == 'n' else pre}.{param}"
                    if name not in r.draws:
                        continue
                    if param == "n":
                        np_name = f"{pre}.n_p"
                        if np_name not in r.priors or np_name not in r.draws:
                            continue
                        n_p, n_ = r.draws[np_name], r.draws[name]
                        if np.any(n_ <= 0) or np.any(n_p <= 0):
                            raise InputError(where, f"variable '{name}'", "non-positive fill constant draws",
                                             "rerun the fit")
                        prior = r.priors[np_name]
                        lp = prior.logpdf(n_p) + np.log(n_p) - np.log(n_)   # π(n | o) = π(n_p)·n_p/n
                        add(key, "n", n_, lp, prior, (0.0, prior.support[1]), name)
                    elif name in r.priors:
                        prior = r.priors[name]
                        add(key, param, r.draws[name], prior.logpdf(r.draws[name]), prior, prior.support, name)
                t_name = f"{own}.t_fp"
                if t_name in r.draws:
                    tfp.setdefault((kind, key), []).append((r.test, label, r.draws[t_name]))
    return groups, tfp


def _stack(by_test, tests_order):
    tests = [t for t in tests_order if t in by_test]
    values = [np.stack([u.values for u in by_test[t]]) for t in tests]
    log_prior = [np.stack([u.log_prior for u in by_test[t]]) for t in tests]
    data = PerTestDraws.from_arrays(values, log_prior, None, None, tests)
    data.canopies = [[u.canopy for u in by_test[t]] for t in tests]
    return data


def _per_canopy_table(by_test, tests_order):
    rows = []
    for t in tests_order:
        for u in by_test.get(t, []):
            q = quantile_summary(u.full, mean=False, sd=False)
            rows.append({"test": t, "canopy": u.canopy, "median": q["q50"], "q05": q["q05"], "q95": q["q95"]})
    return pd.DataFrame(rows)


def _support_union(units):
    lo = min(u.support[0] for u in units)
    hi = max(u.support[1] for u in units)
    return float(lo), float(hi)


def _clip_to(x, bounds):
    return np.clip(x, bounds[0], bounds[1])


def _selection_task(job):
    """One kind/stage/parameter's family selection (a task of an executor): (selection, its warnings)."""
    data, candidates, bounds, scales, seed, n_draws, ess_min = job
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        selection = select_family(data, None, candidates, np.random.default_rng(seed), bounds=bounds,
                                  hyper_scale=scales, n_draws=n_draws, ess_min=ess_min)
    return selection, [(w.category, str(w.message)) for w in caught]


def pool_fits(records, rng, *, n_draws=10000, max_samples=500, ess_min=ESS_MIN, min_tests=2, correlate=True,
              families=None, executor=None) -> PoolResult:
    """Pool fitted tests into population distributions.

    ``records``: :class:`~cpas_bayes.inference.fit_folder.FitRecord` (from
    :func:`~cpas_bayes.inference.fit_folder.load_fit` or ``FitRecord.from_fit``)
    or :class:`~cpas_bayes.inference.fit.Fit` results held in memory, which are
    taken through ``FitRecord.from_fit``; a fit pools the same either way.

    Per parachute kind and stage key: n_p, n, expopen, ck, tk, eps (where the
    fits sampled them) and per canopy cd_o, each with the family chosen by
    leave-one-test-out elpd among ``families`` (default: normal, truncnormal,
    lognormal; beta too for eps); (n_p, expopen) as a Gaussian-copula pair when
    ``correlate``; t_fp medians and range. ``max_samples`` draws per test
    enter the reweighting sums; ``n_draws`` population-predictive draws per
    kind become memo_draws.csv rows. Entries with fewer than ``min_tests``
    tests are skipped (listed in ``skipped``, with a warning).

    ``executor`` (:mod:`cpas_bayes.core.executor`) runs the kind/stage/parameter
    selections, which are independent, as tasks; each has its own random stream
    drawn from ``rng`` in key order, so the result does not depend on it.
    """
    from cpas_bayes.core.executor import Executor

    records = [r if isinstance(r, FitRecord) else FitRecord.from_fit(r) for r in records]
    if not records:
        raise InputError("(no folders)", "", "no fits to pool", "pass at least two fit folders")
    seen = {}
    for r in records:
        if r.test in seen:
            raise InputError(r.source, "summary.json key 'test'",
                             f"test '{r.test}' is already pooled from {seen[r.test]}",
                             "pool each test once (one fit folder per test)")
        seen[r.test] = r.source
    tests_order = [r.test for r in records]
    seeds = [int(r.summary.get("sampler", {}).get("seed", -1)) for r in records]
    groups, tfp = _gather(records, rng, max_samples)
    notes, skipped = [], []
    entries, pairs, peak = {}, {}, {}
    jobs, keys = [], []
    for key in sorted(groups):
        kind, stage, param = key
        by_test = groups[key]
        if len(by_test) < min_tests:
            skipped.append(f"{kind}.{stage}.{param}: {len(by_test)} test(s), need {min_tests}")
            continue
        units = [u for us in by_test.values() for u in us]
        support = _support_union(units)
        cands = families or _families_for(param)
        fam_bounds = {name: (0.0, 1.0) if name == "beta" else support for name in cands}
        s0 = {name: _prior_width(units[0].prior, make_family(name, *fam_bounds[name])) for name in cands}
        jobs.append((_stack(by_test, tests_order), cands, fam_bounds, s0, int(rng.integers(2**63 - 1)), n_draws,
                     ess_min))
        keys.append((key, support))
    selections = (executor or Executor()).map(_selection_task, jobs, desc="pool", progress=False)
    for (key, support), (selection, caught) in zip(keys, selections):
        kind, stage, param = key
        by_test = groups[key]
        for category, message in caught:
            warnings.warn(message, category, stacklevel=2)
        chosen = selection.pool
        label = f"{kind}.{stage}.{param}"
        if chosen.low_ess:
            msg = (f"{label}: ESS < {ess_min:g} at the inferred {chosen.family.name} population for "
                   f"{', '.join(chosen.low_ess)} (smallest {np.min(chosen.ess):.0f}); their reweighting sums are noisy")
            notes.append(msg)
            warnings.warn(msg, PoolWarning, stacklevel=2)
        for note in chosen.notes:
            notes.append(f"{label}: {note}")
            warnings.warn(f"{label}: {note}", PoolWarning, stacklevel=2)
        bounds = (chosen.family.low, chosen.family.high) if chosen.family.name in ("truncnormal", "beta") \
            else support
        entries[key] = EntryPool(kind, stage, param, selection, _per_canopy_table(by_test, tests_order),
                                 len(by_test), bounds)
    for msg in skipped:
        warnings.warn(f"skipped {msg}", PoolWarning, stacklevel=2)

    # correlated pairs
    if correlate:
        for (kind, stage) in sorted({(k, s) for k, s, _ in entries}):
            k1, k2 = (kind, stage, PAIR[0]), (kind, stage, PAIR[1])
            if k1 not in entries or k2 not in entries:
                continue
            g1, g2 = groups[k1], groups[k2]
            tests = [t for t in tests_order if t in g1 and t in g2
                     and [u.canopy for u in g1[t]] == [u.canopy for u in g2[t]]]
            if len(tests) < max(min_tests, 3):
                continue
            values = [np.stack([np.stack([a.values, b.values], axis=-1) for a, b in zip(g1[t], g2[t])])
                      for t in tests]
            log_prior = [np.stack([a.log_prior + b.log_prior for a, b in zip(g1[t], g2[t])]) for t in tests]
            data = PerTestDraws.from_arrays(values, log_prior, None, None, tests)
            marg = (entries[k1].pool, entries[k2].pool)
            s0 = tuple(_prior_width(g[tests[0]][0].prior, m.family)
                       or default_hyper_scale(data.component(j), m.family)
                       for j, (g, m) in enumerate(((g1, marg[0]), (g2, marg[1]))))
            pair = pool_pair(data, marg, rng, hyper_scales=s0, n_draws=n_draws)
            pairs[(kind, stage)] = pair
            for model, info in pair.sampler.items():
                if info["method"] != "laplace-importance":
                    msg = (f"{kind}.{stage}.(n_p, expopen), {model} model: the Laplace importance sampler failed "
                           f"(k̂ > {PARETO_K_MAX}); sampled with emcee instead")
                    notes.append(msg)
                    warnings.warn(msg, PoolWarning, stacklevel=2)

    # predictive columns, memo params and quantiles
    columns = {}
    for key, e in sorted(entries.items()):
        kind, stage, param = key
        pair = pairs.get((kind, stage))
        if pair is not None and pair.keep and param in PAIR:
            j = PAIR.index(param)
            x = pair.predictive[:, j]
        else:
            x = e.pool.predictive
        x = _clip_to(x, e.bounds)
        e.predictive = x
        loc, scale = e.pool.family.fit(x, loc_range=e.pool.grid.get("loc_prior_box", (-math.inf, math.inf)))
        e.memo_params = e.pool.family.memo_params(loc, scale)
        e.quantiles = quantile_summary(x, MEMO_QUANTILE_LEVELS, mean=False, sd=False)
        if pair is not None and param in PAIR:
            corr = pair.criterion()
            corr["with"] = PAIR[1 - PAIR.index(param)]
            e.correlation = corr
        if param in DRAWN_PARAMETERS or param == "cd_o":
            columns.setdefault(kind, {})[f"{stage}.{param}"] = x
    frames = []
    for kind in sorted(columns):
        cols = columns[kind]
        n = min(len(v) for v in cols.values())
        frame = pd.DataFrame({"kind": [kind] * n, **{c: v[:n] for c, v in sorted(cols.items())}})
        frames.append(frame)
    draws = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame({"kind": []})

    for (kind, stage), items in sorted(tfp.items()):
        by_test = {}
        for test, pid, d in items:
            by_test.setdefault(test, []).append(_Unit(test, pid, d, d, d, None, (0, math.inf)))
        if len(by_test) < min_tests:
            continue
        peak[(kind, stage)] = PeakFillTimes(kind, stage, _per_canopy_table(by_test, tests_order), len(by_test))
    if not entries:
        raise InputError(records[0].source, "", f"nothing to pool: every parameter has fewer than {min_tests} tests",
                         f"pass at least {min_tests} fits of the same parachute kind")
    return PoolResult(entries, pairs, peak, draws, tests_order, seeds, [r.folder for r in records], notes, skipped)


# ---------------------------------------------------------------------------
# fit folders in


def pool_folders(folders, seed=0, executor=None, **kwargs) -> PoolResult:
    """Load fit folders (refusing clearly any that is not one) and pool them.

    ``executor`` loads the folders and runs the selections as tasks (see :func:`pool_fits`)."""
    from cpas_bayes.core.executor import Executor

    records = (executor or Executor()).map(load_fit, [Path(f) for f in folders], desc="fit folders", progress=False)
    return pool_fits(records, np.random.default_rng(seed), executor=executor, **kwargs)

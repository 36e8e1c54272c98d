"""A fitted test on disk and in memory: ArviZ DataTree, ``summary.json``, loader.

Fit folder layout (written by ``cpas-bayes fit``)::

    FIT/
      posterior.nc     ArviZ DataTree (netCDF4 via h5netcdf), groups:
                       posterior            every sampled parameter by name
                                            (e.g. ``D3.s1.n_p``) and the derived
                                            ``<chute>.s<k>.{n,eps,cds,t_f,t_fp}``,
                                            dims (chain, draw); coordinate
                                            ``ensemble`` on chain
                       sample_stats         lp (log posterior)
                       log_likelihood       pointwise, on a thinned subset of draws:
                                            ``total`` (chain, draw, time) — all
                                            channels at a time bin — plus ``acc``
                                            and ``lc`` (…, load_cell, time)
                       posterior_predictive ``acc`` and ``lc`` with noise
                       observed_data        ``acc`` (time), ``lc`` (load_cell, time)
                       constant_data        sigmas, bin sizes, time
      summary.json     the issue-5 schema plus the priors used (``priors``)
      checkpoint/      emcee HDF5 chains, one per ensemble (resumable)

Values are SI inside the files; ``summary.json`` also carries each
parachute's ``units`` so reports can convert back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.summaries import quantile_summary
from cpas_bayes.core.files import atomic_path, jsonable, write_json
from cpas_bayes.core.inputs import broken_link, name_problem, read_json
from cpas_bayes.physics.inflation import stage_key
from cpas_bayes.inference.rank_diagnostics import chain_diagnostics
from cpas_bayes.inference.stopping import TAIL_QUANTILES
from cpas_bayes.stats.priors import prior_from_table

SUMMARY_NAME = "summary.json"
POSTERIOR_NAME = "posterior.nc"
QUANTILES = (0.05, 0.5, 0.95)
STAGE_FIELDS = ("start", "n_p", "n", "t_f", "t_fp", "expopen", "ck", "tk", "cds", "eps")   # t_f, t_fp in s


def save_datatree(tree, target):
    """Write a DataTree as netCDF atomically."""
    with atomic_path(target) as tmp:
        tree.to_netcdf(tmp, engine="h5netcdf")


def _refit(folder):
    """What rewrites a damaged fit folder."""
    return (f"re-run 'cpas-bayes fit BUNDLE --out {folder}' (in a campaign: delete {folder} and re-run the "
            "campaign)")


def load_datatree(path):
    """The DataTree in ``posterior.nc``; an InputError naming the file and what to re-run if it is missing,
    empty, truncated or not a posterior (no ``posterior`` group with variables)."""
    path = Path(path)
    fix = _refit(path.parent)
    if not path.is_file():
        raise InputError(path, "", "posterior file not found", "run 'cpas-bayes fit' into this folder first")
    if path.stat().st_size == 0:
        raise InputError(path, "", "empty (a fit interrupted while writing it?)", fix)
    try:
        tree = xr.open_datatree(path, engine="h5netcdf").load()
    except Exception as exc:  # noqa: BLE001 - whatever h5py/h5netcdf/xarray say about a damaged file
        raise InputError(path, "", f"not a readable netCDF posterior ({type(exc).__name__}: {str(exc)[:160]})",
                         fix) from None
    if "posterior" not in tree.children or not tree["posterior"].to_dataset().data_vars:
        raise InputError(path, "group 'posterior'", "missing or without variables", fix)
    return tree


@dataclass(frozen=True)
class FitRecord:
    """What later steps need of a fit: identity, draws and priors of each parameter.

    Read from a fit folder (:func:`load_fit`) or made from a fit held in memory
    (:meth:`from_fit`, ``folder`` None); the two hold the same summary, draws and
    priors.
    """

    folder: Path | None
    summary: dict          # summary.json's content
    draws: dict            # parameter name -> 1-D array of posterior draws (chains × draws flattened)
    priors: dict           # sampled parameter name -> prior used in the fit

    @classmethod
    def from_fit(cls, fit) -> FitRecord:
        """The record of a :class:`~cpas_bayes.inference.fit.Fit` held in memory (``fit_model`` without
        ``out``): what :func:`load_fit` reads back from the folder that fit writes."""
        summary = jsonable(fit.summary)   # the plain values summary.json would hold
        return _record(None, summary, fit.tree, f"in-memory fit of test '{summary['test']}'")

    @property
    def test(self):
        return self.summary["test"]

    @property
    def source(self):
        """Where the fit comes from, for messages: its folder, or the in-memory fit's test."""
        return self.folder if self.folder is not None else f"in-memory fit of test '{self.test}'"

    def source_file(self, name):
        """A file of the fit folder (e.g. ``posterior.nc``), for messages; :attr:`source` for a fit in memory."""
        return self.folder / name if self.folder is not None else self.source

    def parachutes(self):
        """[(id, kind, inflation, diameter_m, [stage keys])] in fit order."""
        out = []
        for pid, info in self.summary["parachutes"].items():
            out.append((pid, info["kind"], info["inflation"], info["diameter_m"],
                        [s["key"] for s in info["stages"]]))
        return out

    def parameter_prefix(self, pid):
        """The prefix of parachute ``pid``'s sampled parameters: its id, or in a composite fit its group's
        (``cluster.<kind>``), whose draws every member's variables repeat."""
        return self.summary["parachutes"][pid].get("parameters", pid)


def load_fit(folder) -> FitRecord:
    """Read a fit folder written by ``cpas-bayes fit``; refuse clearly if it is not one or is damaged."""
    folder = Path(folder)
    summary = read_summary(folder)
    return _record(folder, summary, load_datatree(folder / POSTERIOR_NAME), folder / SUMMARY_NAME)


def read_summary(folder) -> dict:
    """``summary.json`` of a fit folder, checked for what later steps read of it (test, parachutes with
    their stages, priors, sampler); an InputError naming the key and what to re-run otherwise."""
    folder = Path(folder)
    path = folder / SUMMARY_NAME
    if not path.exists():
        problem = ("is a link to nothing (a broken symbolic link, or a loop of links)" if broken_link(folder) else
                   "not found" if not folder.exists() else
                   "is a file, not a fit folder" if not folder.is_dir() else f"no {SUMMARY_NAME}: not a fit folder")
        raise InputError(folder, "", problem, "pass folders written by 'cpas-bayes fit BUNDLE --out FOLDER'")
    fix = _refit(folder)
    summary = read_json(path, fix, what="fit summary")

    def refuse(where, problem):
        raise InputError(path, f"key '{where}'", problem, fix)

    for key in ("test", "parachutes", "priors"):
        if key not in summary:
            refuse(key, "missing")
    if name_problem(summary["test"]) is not None:
        refuse("test", f"test name {summary['test']!r:.60} cannot be used: {name_problem(summary['test'])}")
    chutes = summary["parachutes"]
    if not isinstance(chutes, dict) or not chutes:
        refuse("parachutes", "must be a non-empty table of parachutes")
    for pid, info in chutes.items():
        where = f"parachutes.{pid}"
        if name_problem(pid) is not None:
            refuse(where, f"parachute id cannot be used: {name_problem(pid)}")
        if not isinstance(info, dict):
            refuse(where, "must be a table")
        for key in ("kind", "inflation", "diameter_m", "stages"):
            if key not in info:
                refuse(f"{where}.{key}", "missing")
        if name_problem(info["kind"]) is not None:
            refuse(f"{where}.kind", f"parachute kind cannot be used: {name_problem(info['kind'])}")
        if info["inflation"] not in ("finite", "infinite"):
            refuse(f"{where}.inflation", f"{info['inflation']!r:.40} is not 'finite' or 'infinite'")
        d = info["diameter_m"]
        if isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or d <= 0:
            refuse(f"{where}.diameter_m", f"{d!r:.40} is not a positive number")
        stages = info["stages"]
        if not isinstance(stages, list) or not stages:
            refuse(f"{where}.stages", "must be a non-empty list of stages")
        for k, st in enumerate(stages):
            expected = stage_key(k, len(stages))
            if not isinstance(st, dict) or st.get("key") != expected:
                refuse(f"{where}.stages[{k}].key", f"must be '{expected}' (stage {k + 1} of {len(stages)})")
    if not isinstance(summary["priors"], dict) or not summary["priors"]:
        refuse("priors", "must be a non-empty table of the priors the fit used")
    sampler = summary.get("sampler", {})
    seed = sampler.get("seed", 0) if isinstance(sampler, dict) else None
    if isinstance(seed, bool) or not isinstance(seed, int):
        refuse("sampler.seed", "must be a table with the fit's whole-number seed")
    return summary


def _record(folder, summary, tree, summary_source):
    """A :class:`FitRecord` from a summary and a DataTree (draws flattened, priors rebuilt from their tables).

    For a folder, the posterior must hold numeric draws of one common size for every parameter
    whose prior the summary lists.
    """
    post = tree["posterior"].to_dataset()
    draws = {name: np.asarray(post[name].values).reshape(-1) for name in post.data_vars}
    if folder is None:
        priors = {name: prior_from_table(table, summary_source, f"priors.{name}")
                  for name, table in summary["priors"].items()}
        return FitRecord(folder=folder, summary=summary, draws=draws, priors=priors)
    fix = _refit(folder)
    try:
        priors = {name: prior_from_table(table, summary_source, f"priors.{name}")
                  for name, table in summary["priors"].items()}
    except InputError as exc:   # the same problem, with what rewrites a fit folder as the fix
        raise InputError(exc.file, exc.where, exc.problem, fix) from None
    where = folder / POSTERIOR_NAME
    # the posterior names its test: a file copied from another fit would pool one test's draws twice
    if tree.attrs.get("test", summary["test"]) != summary["test"]:
        raise InputError(where, "attribute 'test'", f"the posterior is of test {str(tree.attrs['test'])!r:.60}, but "
                                                    f"{SUMMARY_NAME} is of {summary['test']!r:.60}", fix)
    sizes = set()
    for name, values in draws.items():
        if values.dtype.kind not in "fiu":
            raise InputError(where, f"variable '{name}'", f"holds {values.dtype} values, not numbers", fix)
        sizes.add(values.size)
    if len(sizes) != 1 or 0 in sizes:
        raise InputError(where, "group 'posterior'", f"variables of different or zero sizes {sorted(sizes)}", fix)
    missing = [name for name in priors if name not in draws]
    if missing:
        raise InputError(where, f"variable '{missing[0]}'", f"missing; {SUMMARY_NAME} lists a prior for it", fix)
    return FitRecord(folder=folder, summary=summary, draws=draws, priors=priors)


def write_fit_files(fit, folder):
    """A fit's ``posterior.nc`` and ``summary.json`` into ``folder`` (claimed by the caller)."""
    save_datatree(fit.tree, Path(folder) / POSTERIOR_NAME)
    write_summary(folder, fit.summary)


def write_summary(folder, summary):
    write_json(Path(folder) / SUMMARY_NAME, summary)


def fill_time_table(summary):
    """Per stage: n_p, n and the fill times t_f and t_fp in seconds (posterior medians), as text."""
    lines = [f"{'stage':<22}{'n_p':>8}{'n':>8}{'t_f [s]':>10}{'t_fp [s]':>10}"]
    for pid, info in summary["parachutes"].items():
        for k, st in enumerate(info["stages"]):
            cells = [f"{st[f]['q50']:.3g}" if isinstance(st.get(f), dict) else "-"
                     for f in ("n_p", "n", "t_f", "t_fp")]
            lines.append(f"{pid + ' ' + str(k + 1) + ' ' + st['label']:<22.22}{cells[0]:>8}{cells[1]:>8}"
                         f"{cells[2]:>10}{cells[3]:>10}")
    return "\n".join(lines)


def pairing_note(summary):
    """A line on the label exchanges of like canopies without a load cell and the mode jumps between their
    pairings (:mod:`cpas_bayes.inference.mode_jumps`), or None where the model has none."""
    exchanges = summary.get("sampler", {}).get("label_exchanges") or []
    if not exchanges:
        return None
    gaps = summary.get("diagnostics", {}).get("mode_jump_gaps") or []
    whose = "s, whose optima lie" if len(gaps) != 1 else ", whose optimum lies"
    jumps = (f"mode jumps to {len(gaps)} other pairing{whose} " + ", ".join(f"{g:.3g}" for g in gaps)
             + " below the MAP in log posterior") if gaps else \
        "no other pairing's optimum within reach of a mode jump"
    return (f"like canopies that no channel tells apart: label exchanges {', '.join(exchanges)}; {jumps} "
            "(a pairing's share of the draws is in posterior.nc: the order of the stage starts)")


def record_checks(fit, checks, out=None):
    """Add the warnings that need the fit's checks (PPC) to ``fit.summary`` and, with ``out``, rewrite
    its ``summary.json``; returns the warnings."""
    from cpas_bayes.inference.fit_health import fit_warnings

    diagnostics = {**fit.summary["diagnostics"], "per_parameter": fit.summary["diagnostics_per_parameter"]}
    fit.summary["warnings"] = fit_warnings(fit.model, fit.tree, diagnostics, checks.ppc.table)
    if checks.loo_pit.not_computed:   # said where a reader of summary.json looks, not only on loo_pit.png
        fit.summary["checks_not_computed"] = {"loo_pit": checks.loo_pit.not_computed}
    if out is not None:
        write_summary(out, fit.summary)
    return fit.summary["warnings"]


# ---------------------------------------------------------------------------
# assembling a fit


def _subset_indices(n_chains, n_draws, budget):
    """Every k-th draw so that chains × draws stays within ``budget`` samples."""
    step = max(1, int(np.ceil(n_chains * n_draws / budget)))
    return np.arange(n_draws - 1, -1, -step)[::-1]


def build_datatree(model, sampling, rng, budget=1000):
    """The ArviZ DataTree of a fit: posterior (+ derived), stats, pointwise log-likelihood,
    posterior predictive, observed and constant data."""
    import arviz_base as azb

    chains, lp, ensemble = sampling.stacked()
    n_chain, n_draw, _ = chains.shape
    flat = chains.reshape(-1, chains.shape[-1])
    posterior = {name: chains[:, :, i] for i, name in enumerate(model.names)}
    derived = model.derived(flat)
    for name, values in derived.items():
        if name not in posterior:
            posterior[name] = values.reshape(n_chain, n_draw)

    obs = model.obs
    lc_ids = [model.parachutes[i].id for i in obs.lc_index]
    # One subset of draws serves log_likelihood and posterior_predictive, so that
    # LOO-PIT lines them up; it is a thinned copy of the posterior's draws.
    ll_idx = _subset_indices(n_chain, n_draw, budget)
    sub = chains[:, ll_idx, :].reshape(-1, chains.shape[-1])
    pred = _predict_in_batches(model, sub)
    total = model.pointwise_log_likelihood(sub, pred)
    shape = (n_chain, ll_idx.size)
    log_likelihood = {"total": total.reshape(shape + total.shape[1:])}
    if not model.replaces_error_model:   # an AR(1) error model has no per-channel marginal
        ll_acc, ll_lc = model.pointwise_log_likelihood(sub, pred, by_channel=True)
        log_likelihood.update(acc=ll_acc.reshape(shape + ll_acc.shape[1:]), lc=ll_lc.reshape(shape + ll_lc.shape[1:]))
    # Replicated data with the likelihood's error structure: independent parts plus
    # one shared q̄ draw per bin.
    acc_noise, lc_noise = model.replicated_noise(rng, pred.acc.shape[0])
    acc_pp = pred.acc + pred.noise_acc[:, None] * acc_noise
    lc_pp = pred.lc + pred.noise_lc[:, None, None] * lc_noise
    acc_pp = acc_pp.reshape(shape + acc_pp.shape[1:])
    lc_pp = lc_pp.reshape(shape + lc_pp.shape[1:])

    coords = {"chain": np.arange(n_chain), "time": obs.time, "load_cell": lc_ids}
    tree = azb.from_dict(
        {
            "posterior": posterior,
            "sample_stats": {"lp": lp},
            "log_likelihood": log_likelihood,
            "posterior_predictive": {"acc": acc_pp, "lc": lc_pp},
            "observed_data": {"acc": obs.acc, "lc": obs.lc},
            "constant_data": {"acc_sigma": obs.acc_sigma, "lc_sigma": obs.lc_sigma,
                              "acc_qbar": obs.acc_qbar, "lc_qbar": obs.lc_qbar,
                              "samples_per_bin": obs.samples_per_bin},
        },
        coords=coords,
        dims={"acc": ["time"], "lc": ["load_cell", "time"], "total": ["time"],
              "acc_sigma": ["time"], "lc_sigma": ["load_cell", "time"], "acc_qbar": ["time"],
              "lc_qbar": ["load_cell", "time"], "samples_per_bin": ["time"]},
        check_conventions=False,
    )
    # Draw coordinates name the stored step, so subsets line up with the posterior.
    for group in ("log_likelihood",):
        tree[group] = tree[group].to_dataset().assign_coords(draw=ll_idx)
    tree["posterior_predictive"] = tree["posterior_predictive"].to_dataset().assign_coords(draw=ll_idx)
    tree["posterior"] = tree["posterior"].to_dataset().assign_coords(ensemble=("chain", ensemble))
    tree.attrs.update({"test": model.test.name, "model": model.name, "decay": model.decay,
                       "below_previous": model.below_previous, "cluster": model.cluster})
    return tree


def _predict_in_batches(model, theta, batch=256):
    """Predictions for many rows without holding huge temporaries at once."""
    parts = [model.predict(theta[i:i + batch]) for i in range(0, theta.shape[0], batch)]
    first = parts[0]
    out = type(first)(**{f: np.concatenate([getattr(p, f) for p in parts], axis=0)
                         if isinstance(getattr(first, f), np.ndarray) else getattr(first, f)
                         for f in first.__dataclass_fields__})
    return out


def convergence(tree, sampling, rhat_max=1.01, ess_min=400):
    """R-hat across ensembles (nested R-hat: walkers grouped by ensemble), ESS, τ, acceptance.

    ArviZ's numbers (rank-normalised bulk and tail ESS, nested R-hat; one ensemble: the plain rank R-hat,
    optimistic since walkers share the ensemble's moves), computed by :mod:`cpas_bayes.inference.rank_diagnostics`
    for all parameters at once: equal to ``arviz_stats`` to 1e-9 (tested), in 0.05 s instead of its 0.3-0.5 s
    loop over parameters, which a fit command's main process spent while the workers waited for the figures.
    """
    post = tree["posterior"]
    names = list(sampling.names)
    draws = np.stack([np.asarray(post[n].values, float) for n in names])       # (D, chain, draw)
    # the 90 % interval's endpoints, as the ESS stopping rule (ArviZ 1.x's default reads 0.89 as quantiles)
    bulk, tail, rhat = chain_diagnostics(draws, np.asarray(post["ensemble"].values), TAIL_QUANTILES)
    rhat_v, bulk_v, tail_v = (dict(zip(names, map(float, v))) for v in (rhat, bulk, tail))
    tau_max = float(max(np.max(r.tau) for r in sampling.runs))
    out = {
        "rhat_max": max(rhat_v.values()),
        "ess_bulk_min": min(bulk_v.values()),
        "ess_tail_min": min(tail_v.values()),
        "tau_max": tau_max,
        "acceptance": float(np.mean([r.acceptance for r in sampling.runs])),
        "steps": [int(r.steps) for r in sampling.runs],
        "ensembles_converged": [bool(r.converged) for r in sampling.runs],
        # the adaptive proposal's warm-up, dropped (inference.warm_up); 0 without one, None under the τ rule
        "warm_up_steps": sampling.extras.get("stopping", {}).get("warm_up_steps"),
        # like canopies: how far below the MAP each other pairing's optimum lies (inference.mode_jumps)
        "mode_jump_gaps": [float(g) for g in sampling.extras.get("mode_jump_gaps", [])],
        "per_parameter": {n: {"rhat": rhat_v[n], "ess_bulk": bulk_v[n], "ess_tail": tail_v[n]} for n in names},
    }
    out["converged"] = bool(all(out["ensembles_converged"]) and out["rhat_max"] < rhat_max
                            and out["ess_bulk_min"] >= ess_min)
    return out


def build_summary(model, tree, diagnostics, options, ppc_table=None):
    """``summary.json`` content (issue-5 schema, SI) plus priors, provenance and the fit's health
    ``warnings`` (:mod:`cpas_bayes.inference.fit_health`; the PPC ones only with ``ppc_table``)."""
    from cpas_bayes import __version__
    from cpas_bayes.inference.fit_health import fit_warnings

    post = tree["posterior"]

    def stats(name):
        return quantile_summary(post[name].values, QUANTILES) if name in post else None

    chutes = {}
    for i, p in enumerate(model.parachutes):
        n = len(p.stages)
        stages = []
        for k, st in enumerate(p.stages):
            entry = {"label": st.label, "key": stage_key(k, n)}
            for field in STAGE_FIELDS:
                s = stats(f"{p.id}.s{k + 1}.{field}")
                if s is not None:
                    entry[field] = s
            stages.append(entry)
        chutes[p.id] = {"kind": p.kind, "inflation": p.inflation, "diameter_m": p.diameter,
                        "cds_o": stats(f"{p.id}.cds_o"), "stages": stages}
        prefix = model.chute_prefix[i] if hasattr(model, "chute_prefix") else p.id
        if prefix != p.id:   # composite: the parameters are the group's (the pool takes them once)
            chutes[p.id]["parameters"] = prefix
    nuisance = {prm.name: stats(prm.name) for prm in model.parameters if prm.group != "inflation"}
    diag = {k: v for k, v in diagnostics.items() if k != "per_parameter"}
    return {
        "test": model.test.name,
        "model": model.name,
        "decay": model.decay,
        "below_previous": model.below_previous,
        "cluster": model.cluster,
        "units": "SI",
        "bundle_units": model.test.units.name,
        "parachutes": chutes,
        "nuisance": nuisance,
        "diagnostics": diag,
        "diagnostics_per_parameter": diagnostics.get("per_parameter", {}),
        "warnings": fit_warnings(model, tree, diagnostics, ppc_table),
        "priors": {prm.name: prm.prior.describe() for prm in model.parameters},
        "sampler": {"seed": options.seed, "ensembles": options.n_ensembles, "walkers": options.walkers,
                    "check_every": options.check_every, "max_steps": options.max_steps, "stop": options.stop,
                    "ess_target": options.ess_target, "rhat_target": options.rhat_target,
                    # like canopies no channel tells apart: the stage pairings the sampler exchanges
                    "label_exchanges": [f"{a}<->{b} s{k + 1}" for (a, b), k in
                                        ((e.pair, e.stage) for e in model.exchanges())]},
        "version": __version__,
    }

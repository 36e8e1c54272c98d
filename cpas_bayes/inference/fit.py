"""Posterior sampling of one flight test: MAP start, emcee ensembles, convergence.

Procedure
---------
1. A data-driven first guess (stage levels from the reduced drag areas,
   nominal start times, prior medians for the shape parameters), then the
   maximum a posteriori point from several starts with L-BFGS-B. Gradients are
   central differences evaluated as *one* batched call of the vectorised
   log posterior (2·D + 1 rows), which is why a MAP costs a few hundred calls.
2. The Laplace covariance at the MAP (finite-difference Hessian, batched the
   same way) shapes the walkers' initial ball: N(MAP, Σ), redrawn where
   the prior is zero. Starting at the posterior's own width (not a tiny ball) spares
   the thousands of steps an ensemble needs to expand.
3. ``n_ensembles`` independent emcee ensembles, each with its own random
   state (``sampler.random_state`` from the ensemble's seed; numpy's global
   generator is never touched). Walkers of one ensemble are not independent
   chains, so R-hat is the nested R-hat over ensembles. Moves
   (:mod:`cpas_bayes.inference.moves`): differential evolution, which mixes far
   better than the stretch move in 30–40 dimensions but, on these near-normal
   posteriors, only at the random-walk rate (τ ≈ D/0.3 steps: 90 for a
   two-Drogue test, 140 for a three-Main one, whatever the coordinates; measured
   alike in log coordinates). Under the ESS rule with ``proposal="adaptive"``
   (the default) each ensemble then fits a multivariate-t independence proposal
   to its own draws and mixes it in (70 %), which leaves τ at 5–20 steps
   (:mod:`cpas_bayes.inference.warm_up`): one DE chunk of warm-up, adaptation chunks until the
   acceptance stops rising, then the proposal frozen, the warm-up dropped and the
   ESS rule run on the rest. The
   τ rule keeps DE alone (its 50 τ criterion is for one kernel from the start).
   The walkers move in :mod:`cpas_bayes.inference.coordinates`' u (``SamplerOptions.coordinates``;
   by default ``"grown"``: each reefed stage's drag area ε·CDS_o in place of ε and each stage's time to
   peak — or, cut short before its peak, the drag area it grew — in place of n_p, the Jacobian in the
   density); the draws and their log density are mapped back to θ before anything else reads them.
4. When to stop (``SamplerOptions.stop``, :mod:`cpas_bayes.inference.stopping`):
   ``"ess"`` (the default) -- the ensembles advance in lockstep chunks (one
   task per ensemble and chunk, so the workers stay busy) and stop when every
   parameter's rank-normalised bulk and tail ESS reach ``ess_target`` and its
   nested R-hat over ensembles is at most ``rhat_target`` on the draws the fit
   keeps (burn-in half the chain, thin = ½·min τ), and τ has stopped growing
   (less than ``tau_rtol`` above its value at the last chunk); τ is reported.
   ``"tau"`` -- each ensemble runs in chunks, as its own task, until its chain
   is longer than ``tau_factor`` (50) integrated autocorrelation times τ and τ
   has changed by less than 5 % since the last chunk; burn-in = 2·max τ,
   thin = ½·min τ. The chain of an ensemble does not depend on the rule, only
   its length: a chunk continues from the last state and random state either way.
5. Checkpoints: every chunk is appended to an emcee HDF5 backend (by the worker
   under the τ rule, by the main process under the ESS rule); the file is
   rewritten and renamed over the old one, so a kill at any instant leaves the
   last complete chunk. A rerun on the same folder replays the stopping checks
   on the chunks it holds, resumes from them and, because emcee stores its
   random state with every step, ends with the same chain as an uninterrupted
   run, under either rule.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import emcee
import numpy as np

from cpas_bayes.core.interrupts import raise_if_requested
from cpas_bayes.inference.coordinates import COORDINATES, SamplerTarget, sampling_coordinates
from cpas_bayes.inference.ensemble_store import EnsembleStore, exchanges_of
from cpas_bayes.inference.mode_jumps import mode_jumps, other_pairings, refit_jumps
from cpas_bayes.inference.start import find_map, initial_walkers, laplace_covariance
from cpas_bayes.inference.stopping import (ESS_TARGET, RHAT_TARGET, STOP_RULES, burn_and_thin, ess_check,
                                           integrated_time, pool_kept)
from cpas_bayes.inference.warm_up import WARM_UPS, fit_proposals, warm_up_done, warm_up_schedule
from cpas_bayes.stats.model import TestModel


PROPOSALS = ("de", "adaptive", "pooled")


@dataclass(frozen=True)
class SamplerOptions:
    """Knobs of the sampler; defaults suit a two-Drogue or three-Main test."""

    seed: int = 0
    n_ensembles: int = 4
    walkers: int | None = None        # default: 2·D + 2, even
    check_every: int = 500            # steps between convergence checks and checkpoints (adaptive: inference.warm_up)
    max_steps: int = 20000
    store_every: int = 5              # keep every k-th step in the chain file
    stop: str = "ess"                 # "ess": ESS and R-hat targets (module docstring); "tau": the τ rule below
    tau_factor: float = 50.0          # τ rule: converged when steps > tau_factor·τ ...
    tau_rtol: float = 0.05            # ... and τ moved less than this since the last check (ESS rule: grew)
    ess_target: float = ESS_TARGET    # ESS rule: bulk and tail ESS of every parameter at least this ...
    rhat_target: float = RHAT_TARGET  # ... and its R-hat at most this
    stop_on: tuple = ()               # ESS rule: only these parameters' ESS and R-hat (default: every one)
    proposal: str = "adaptive"        # ESS rule: an independence move after a warm-up (inference.warm_up); "de" alone
    coordinates: str = "grown"        # where the walkers move (inference.coordinates): "model" is θ itself
    warm_up: str = "plateau"          # the adaptive proposal's warm-up (inference.warm_up): "plateau" or "fixed"
    map_starts: int = 4
    workers: int = 2
    progress: bool = True

    def __post_init__(self):
        if self.stop not in STOP_RULES:
            raise ValueError(f"stop must be one of {', '.join(STOP_RULES)}, not {self.stop!r}")
        if self.coordinates not in COORDINATES:
            raise ValueError(f"coordinates must be one of {', '.join(COORDINATES)}, not {self.coordinates!r}")
        if self.warm_up not in WARM_UPS:
            raise ValueError(f"warm_up must be one of {', '.join(WARM_UPS)}, not {self.warm_up!r}")
        if self.proposal not in PROPOSALS:
            raise ValueError(f"proposal must be one of {', '.join(PROPOSALS)}, not {self.proposal!r}")
        if not self.ess_target > 0 or not self.rhat_target > 1:
            raise ValueError(f"ess_target must be positive and rhat_target above 1, not {self.ess_target!r} and "
                             f"{self.rhat_target!r}")


@dataclass
class EnsembleRun:
    """One ensemble's thinned post-burn-in draws and diagnostics."""

    draws: np.ndarray                 # (walkers, S, D)
    log_prob: np.ndarray              # (walkers, S)
    tau: np.ndarray                   # (D,) in steps
    steps: int
    acceptance: float
    converged: bool
    burn: int
    thin: int


@dataclass
class SamplingResult:
    """All ensembles of one fit, the MAP and the options used."""

    names: list
    runs: list
    theta_map: np.ndarray
    log_post_map: float
    options: SamplerOptions
    extras: dict = field(default_factory=dict)

    def stacked(self, draws_per_ensemble=None):
        """Draws (E·W chains, S, D) with a common number S of draws per chain; ensemble id per chain."""
        s = min(r.draws.shape[1] for r in self.runs)
        if draws_per_ensemble is not None:
            s = min(s, draws_per_ensemble)
        chains, ensemble = pool_kept([np.swapaxes(r.draws[:, -s:, :], 0, 1) for r in self.runs])
        lp = np.concatenate([r.log_prob[:, -s:] for r in self.runs], axis=0)
        return chains, lp, ensemble


# ---------------------------------------------------------------------------
# ensembles


def _moves(proposal=None, exchanges=(), jumps=()):
    """Differential evolution (:mod:`cpas_bayes.inference.moves`), mixed with the adaptive independence
    move once a proposal is fitted, and with label exchanges when the model has any. The snooker variant,
    meant for multimodal targets, gave no shorter τ on these posteriors and costs a Python loop per walker:
    their one multimodality, which canopy is which, has an exact move of its own."""
    from cpas_bayes.inference.moves import ensemble_moves

    return ensemble_moves(proposal, exchanges, jumps)


def _check(chain, steps, tau_prev, options):
    """The convergence check after a chunk: (τ, converged, stop)."""
    tau = integrated_time(chain, options.store_every)
    settled = tau_prev is not None and np.all(np.abs(tau - tau_prev) < options.tau_rtol * tau)
    converged = bool(steps > options.tau_factor * np.max(tau) and settled)
    return tau, converged, converged or steps >= options.max_steps


def _replay(store, options):
    """The checks an uninterrupted run made at the chunk ends a checkpoint holds: (last τ, stopped state or None).

    A resumed ensemble continues with the same τ history; one whose checkpoint reached its end adds no chunk.
    """
    backend = store.sampler.backend
    per_chunk, tau_prev = max(1, options.check_every // options.store_every), None
    if backend.iteration == 0:
        return None, None
    chain, log_prob = backend.get_chain(), backend.get_log_prob()
    acceptance = float(np.mean(backend.accepted) / max(backend.iteration, 1))
    for end in range(per_chunk, backend.iteration + 1, per_chunk):
        steps = end * options.store_every
        tau, converged, stop = _check(chain[:end], steps, tau_prev, options)
        if stop:
            return tau, (steps, chain[:end], log_prob[:end], acceptance, tau, converged)
        tau_prev = tau
    return tau_prev, None


def run_ensemble(model, init, seed, options: SamplerOptions, checkpoint=None, label="", report=None):
    """Run one ensemble to convergence (or ``max_steps``); resumable from ``checkpoint``.

    While it runs, the ensemble holds the checkpoint's lock: a second process
    (a rerun while a killed run's worker still ends) waits or is refused
    instead of writing beside it.
    """
    from cpas_bayes.core.files import exclusive_writer

    with exclusive_writer(checkpoint or None):
        store = EnsembleStore(model, init, seed, options, checkpoint)
        tau_prev, stopped = _replay(store, options)
        while stopped is None:
            raise_if_requested()  # between chunks: the checkpoint is complete
            steps, chain, log_prob, acceptance = store.advance()
            tau, converged, stop = _check(chain, steps, tau_prev, options)
            if stop:
                stopped = (steps, chain, log_prob, acceptance, tau, converged)
            elif report is not None:
                report(label, steps, float(np.max(tau)), converged)
            tau_prev = tau
    steps, chain, log_prob, acceptance, tau, converged = stopped
    if report is not None:
        report(label, steps, float(np.max(tau)), converged)
    return _ensemble_run(chain, log_prob, tau, burn_and_thin(tau, options.store_every), steps, acceptance,
                         converged, options.store_every)


def _ensemble_run(chain, log_prob, tau, burn_thin, steps, acceptance, converged, store_every):
    burn, thin = burn_thin
    return EnsembleRun(draws=np.swapaxes(chain[burn::thin], 0, 1), log_prob=log_prob[burn::thin].T, tau=tau,
                       steps=steps, acceptance=acceptance, converged=converged, burn=burn * store_every,
                       thin=thin * store_every)


def _ensemble_task(job, report=None):
    model, init, seed, options, checkpoint, label = job
    return run_ensemble(model, init, seed, options, checkpoint, label, report)


def sample_posterior(model: TestModel, options: SamplerOptions = SamplerOptions(), checkpoint_dir=None,
                     echo=None, guesses=None, executor=None) -> SamplingResult:
    """MAP, Laplace ball and ``options.n_ensembles`` ensembles; returns all draws.

    ``guesses``: starting points for the MAP search (see :func:`find_map`).
    ``executor`` (:mod:`cpas_bayes.core.executor`) runs the ensembles; default a
    local pool of ``options.workers`` processes. The draws do not depend on it.
    """
    from cpas_bayes.core.executor import make_executor

    own = executor is None
    if own:  # made before the MAP search, so that the workers start while it runs
        executor = make_executor(min(options.workers, options.n_ensembles))
    try:
        rng = np.random.default_rng(options.seed)
        theta_map, lp_map = find_map(model, rng, options.map_starts, guesses)
        theta_map, lp_map, optima = other_pairings(model, theta_map, lp_map, executor)
        cov = laplace_covariance(model, theta_map)
        n_walkers = options.walkers or 2 * model.ndim + 2
        n_walkers += n_walkers % 2
        inits = [initial_walkers(model, theta_map, cov, n_walkers, np.random.default_rng([options.seed, e]))
                 for e in range(options.n_ensembles)]
        seeds = [int(np.random.default_rng([options.seed, e, 1]).integers(2**31 - 1))
                 for e in range(options.n_ensembles)]
        ckpts = [Path(checkpoint_dir) / f"ensemble_{e}.h5" if checkpoint_dir else None
                 for e in range(options.n_ensembles)]
        coords = sampling_coordinates(model, options.coordinates, theta_map)
        target = SamplerTarget(model, coords) if coords else model
        jumps = mode_jumps(target, coords.to_sampler if coords else np.asarray, theta_map, lp_map, cov, optima)
        started = time.perf_counter()
        if coords:
            inits = [coords.to_sampler(i) for i in inits]
            if hasattr(coords, "spread_along_ridges"):   # cut-short stages' walkers along their ridge
                inits = [coords.spread_along_ridges(i, np.random.default_rng([options.seed, e, 2]), target)
                         for e, i in enumerate(inits)]
            inits = [_inside_coordinates(i, target, np.random.default_rng([options.seed, e, 3]))
                     for e, i in enumerate(inits)]
        runs, stopping = run_ensembles(target, inits, seeds, options, ckpts, executor, jumps)
        seconds = time.perf_counter() - started
        for run in runs if coords else ():   # back to θ: the draws and their log density
            theta, log_jacobian = coords.inverse(run.draws)
            run.log_prob = run.log_prob - log_jacobian
            run.draws = theta
    finally:
        if own:
            executor.close()
    return SamplingResult(names=list(model.names), runs=runs, theta_map=theta_map, log_post_map=float(lp_map),
                          options=options, extras={"stopping": stopping, "sampling_seconds": seconds,
                                                   "mode_jump_gaps": [j.log_post_gap for j in jumps]})


def run_ensembles(model, inits, seeds, options: SamplerOptions, checkpoints=None, executor=None, jumps=()):
    """Run one ensemble per initial ball ``inits[e]`` (walkers, D) and seed under ``options.stop``'s rule.

    ``model`` is the vectorised log posterior (with ``names``, and optionally ``log_scale``: the parameters
    whose adaptive proposal works in log θ); ``checkpoints`` one file (or None) per
    ensemble; ``executor`` default this process; ``jumps`` the label exchanges' mode jumps
    (:mod:`cpas_bayes.inference.mode_jumps`; the ESS rule's chunks only). Returns ([:class:`EnsembleRun`],
    what the ESS rule saw at its last check, empty under the τ rule).
    """
    from cpas_bayes.core.executor import Executor

    executor = executor or Executor()
    ckpts = list(checkpoints) if checkpoints is not None else [None] * len(inits)
    labels = [f"ensemble {e + 1}/{len(inits)}" for e in range(len(inits))]
    bars = _ProgressBars(labels, options) if options.progress and sys.stderr.isatty() else None
    try:
        if options.stop == "ess":
            return _run_lockstep(model, inits, seeds, ckpts, options, executor, labels, bars, jumps)
        jobs = [(model, i, s, options, c, lab) for i, s, c, lab in zip(inits, seeds, ckpts, labels)]
        return executor.map(_ensemble_task, jobs, desc="ensembles", progress=False,
                            on_report=bars.update if bars else None), {}
    finally:
        if bars:
            bars.close()


def _chunk_task(job):
    """Advance one ensemble from a state by ``n_stored`` stored steps: (chain, log_prob, accepted, random state).

    The same steps as continuing one sampler: emcee takes the walkers, their log posterior and its random
    state from the :class:`emcee.State`, and the moves hold no state of their own (the independence
    proposal, if any, is fixed for the chunk).
    """
    model, (coords, log_prob, random_state), n_stored, store_every, proposal, jumps = job
    sampler = emcee.EnsembleSampler(*coords.shape, model, vectorize=True,
                                    moves=_moves(proposal, exchanges_of(model), jumps))
    # emcee's check that the walkers are linearly independent is for a fresh start (log_prob None); a chain
    # continued from its last state is not one: the check raised mid-run on Main SBC replica 13, ending the fit
    # where the convergence checks over the ensembles should judge it
    sampler.run_mcmc(emcee.State(coords, log_prob=log_prob, random_state=random_state), n_stored,
                     thin_by=store_every, progress=False, skip_initial_state_check=log_prob is not None)
    b = sampler.backend
    return b.get_chain(), b.get_log_prob(), b.accepted.copy(), sampler.random_state


def _run_lockstep(model, inits, seeds, ckpts, options, executor, labels, bars, jumps=()):
    """The ESS rule: all ensembles one chunk further, then :func:`ess_check` on the common length (after the
    adaptive proposal's warm-up, :mod:`cpas_bayes.inference.warm_up`), until met or ``max_steps``. Chunks a checkpoint already
    holds are not rerun but checked again (the replay), and the proposals are refitted from the same stored
    draws, so a resumed run stops where an uninterrupted one does. The main process holds every checkpoint's
    lock."""
    from contextlib import ExitStack

    from cpas_bayes.core.files import exclusive_writer

    if exchanges_of(model):   # DE and exchanges only (ensemble_moves): no proposal to adapt, no warm-up to drop
        options = replace(options, proposal="de")
    schedule = warm_up_schedule(options)
    max_stored = options.max_steps // options.store_every
    with ExitStack() as held:
        for ckpt in ckpts:
            held.enter_context(exclusive_writer(ckpt or None))
        columns = _stop_columns(model, options.stop_on)
        stores = [EnsembleStore(model, i, s, options, c) for i, s, c in zip(inits, seeds, ckpts)]
        proposals = [None] * len(stores)
        # warm: where the kept chain starts (None while the warm-up runs); 0 without one. With mode jumps the
        # warm-up is one chunk with the Laplace jumps, which are then refitted to its second half
        start, warm, tau_prev, acceptance = 0, (None if schedule.de or jumps else 0), None, None
        while True:
            raise_if_requested()  # between chunks: every checkpoint is complete
            end = schedule.de if start == 0 and schedule.de else start + schedule.step
            if warm is None and start > 0:   # an adaptation chunk: refit to the chunk before
                window = (schedule.de // 2, schedule.de) if start == schedule.de else (start - schedule.step, start)
                proposals = fit_proposals(stores, window, pooled=options.proposal == "pooled")
            behind = [(st, p) for st, p in zip(stores, proposals) if st.stored < end]
            jobs = [(model, st.next_state(), end - st.stored, options.store_every, p, jumps) for st, p in behind]
            for (st, _), piece in zip(behind, executor.map(_chunk_task, jobs, desc="chunk", progress=False)):
                st.append(*piece)
            steps = end * options.store_every
            if warm is None and not schedule.de:   # (jumps) frozen at their fit to the warm-up chunk
                jumps = refit_jumps(jumps, [st.sampler.backend.get_chain()[end // 2:end] for st in stores])
                warm = start = end
                continue
            if warm is None:
                if start > 0:
                    done, acceptance = warm_up_done(stores, start, end, schedule, acceptance, max_stored,
                                                     options.store_every)
                    if done:   # freeze the proposal at its fit to this last adaptation chunk
                        warm = end
                        proposals = fit_proposals(stores, (start, end), pooled=options.proposal == "pooled")
                        # this chunk's τ: what the first check's τ must settle against
                        tau_prev = [integrated_time(st.sampler.backend.get_chain()[start:end], options.store_every)
                                    for st in stores]
                start = end
                continue
            start = end
            chains = [st.sampler.backend.get_chain()[warm:end] for st in stores]
            check = ess_check([_in_theta(model, c) for c in chains], options.store_every, options.ess_target,
                              options.rhat_target, tau_prev, options.tau_rtol, columns)
            tau_prev = check.taus
            for label, tau in zip(labels, check.taus) if bars else ():
                bars.update(label, steps, float(np.max(tau)), check.met)
            if check.met or steps >= options.max_steps:
                break
    runs = []
    for st, chain, tau, (burn, thin) in zip(stores, chains, check.taus, check.burn_thin):
        run = _ensemble_run(chain, st.sampler.backend.get_log_prob()[warm:end], tau, (burn, thin), steps,
                            st.acceptance(), check.met, options.store_every)
        run.burn += warm * options.store_every
        runs.append(run)
    worst = check.statistics.worst() if check.statistics else (np.nan, np.nan, np.nan)
    return runs, {"stop": "ess", "ess_bulk_min": worst[0], "ess_tail_min": worst[1], "rhat_max": worst[2],
                  "proposal": options.proposal, "warm_up_steps": int(warm) * options.store_every}


def _inside_coordinates(u, density, rng):
    """Starting walkers u (W, D) with each one that ``density`` rules out (a Laplace-ball point where a grown
    drag area is undefined: the stage does not grow there) replaced by a walker that it allows, nudged by 1e-3
    of the walkers' spread so that no two coincide; emcee refuses NaN and dependent walkers as a start (Main SBC
    replica 13)."""
    bad = ~np.isfinite(density(u))
    good = np.flatnonzero(~bad)
    if not bad.any() or good.size < 2:
        return u
    out = np.array(u, dtype=float, copy=True)
    spread = np.std(out[good], axis=0)
    out[bad] = out[rng.choice(good, bad.sum())] + 1e-3 * spread * rng.normal(size=(bad.sum(), out.shape[1]))
    return out


def _in_theta(model, chain):
    """A chain (T, W, D) as θ: the rule judges the parameters the fit reports, not the sampler's coordinates (an
    R-hat of 1.0095 in u read 1.0105 in θ on a Main SBC replica, and the fit said NOT converged as it stopped)."""
    coords = getattr(model, "coords", None)
    return chain if coords is None else coords.to_model(chain)


def _stop_columns(model, names):
    """Indices in θ of the parameters ``names`` the ESS rule asks (None: all)."""
    if not names:
        return None
    model = getattr(model, "model", model) if hasattr(model, "coords") else model   # θ's names, not u's
    unknown = [n for n in names if n not in model.names]
    if unknown:
        raise ValueError(f"stop_on names {unknown[0]!r}, not a parameter of the model ({', '.join(model.names)})")
    return np.array([list(model.names).index(n) for n in names])


class _ProgressBars:
    """One tqdm bar per ensemble: steps done, current max τ, converged flag."""

    def __init__(self, labels, options):
        from tqdm import tqdm

        self.bars = {lab: tqdm(total=options.max_steps, desc=lab, position=i, leave=False, unit="step")
                     for i, lab in enumerate(labels)}

    def update(self, label, steps, tau, converged):
        bar = self.bars[label]
        bar.update(steps - bar.n)
        bar.set_postfix(tau=f"{tau:.0f}", done=converged)

    def close(self):
        for bar in self.bars.values():
            bar.close()


# ---------------------------------------------------------------------------
# one test, end to end


@dataclass
class Fit:
    """A fitted test: the model, the sampler's draws, the DataTree and the summary."""

    model: TestModel
    sampling: SamplingResult
    tree: object
    summary: dict


def prepare_model(test, reduction, priors=None, decay="linear", extensions=(), native_rate=False,
                  cluster="individual", below_previous="drop"):
    """The :class:`TestModel` of a test from its reduction (:func:`cpas_bayes.data.reduction.reduce_test`).

    The reduction is an argument, not redone here: a command reduces a bundle
    once and builds every model it needs (baseline, extensions) from that.
    ``decay`` is one of :data:`cpas_bayes.physics.inflation.DECAY_SHAPES` and ``below_previous``
    one of :data:`~cpas_bayes.physics.inflation.BELOW_PREVIOUS_RULES`; ``cluster``
    "individual" (each parachute its own inflation) or "composite" (parachutes of one
    kind in lockstep, see :mod:`cpas_bayes.stats.cluster_form`).
    """
    from cpas_bayes.stats.observations import build_observations
    from cpas_bayes.stats.priors import priors_of_test

    kind_priors, nuisance = priors_of_test(test, priors)
    if not test.measured_qbar:   # a logger bundle: air data fitted with the inflation
        from cpas_bayes.stats.logger_model import LoggerModel
        return LoggerModel(test, kind_priors, nuisance, decay=decay, extensions=extensions, cluster=cluster,
                           below_previous=below_previous, estimate=reduction.air_estimate)
    obs = build_observations(test, reduction.frame, native_rate=native_rate)
    return TestModel(test, obs, kind_priors, nuisance, decay=decay, extensions=extensions, cluster=cluster,
                     below_previous=below_previous)


def fit_model(model: TestModel, options: SamplerOptions = SamplerOptions(), out=None, echo=None,
              guesses=None, checkpoint_dir=None, executor=None, on_sampled=None) -> Fit:
    """Sample ``model``'s posterior; write ``posterior.nc`` and ``summary.json`` into ``out`` if given.

    Checkpoints go to ``checkpoint_dir`` (default ``out/checkpoint``); none without either.
    ``executor`` runs the ensembles (see :func:`sample_posterior`). ``on_sampled(sampling)`` is called with
    the draws before the DataTree is assembled (work for idle workers: the fit command's corner figures).
    """
    from cpas_bayes.inference.fit_folder import build_datatree, build_summary, convergence, write_fit_files

    from cpas_bayes.core.ownership import claim_folder

    out = claim_folder(out) if out else None
    if checkpoint_dir is None and out is not None:
        checkpoint_dir = out / "checkpoint"
    sampling = sample_posterior(model, options, checkpoint_dir=checkpoint_dir, echo=echo, guesses=guesses,
                                executor=executor)
    if on_sampled:
        on_sampled(sampling)
    tree = build_datatree(model, sampling, np.random.default_rng([options.seed, 99]))
    diagnostics = convergence(tree, sampling)
    fit = Fit(model, sampling, tree, summary=build_summary(model, tree, diagnostics, options))
    if out:
        write_fit_files(fit, out)
    return fit


def fit_test(test, options: SamplerOptions = SamplerOptions(), out=None, priors=None, decay="linear",
             extensions=(), echo=None, cluster="individual", below_previous="drop") -> Fit:
    """Reduce, model and sample one flight test (the baseline model unless extensions are given)."""
    from cpas_bayes.data.reduction import reduce_test

    model = prepare_model(test, reduce_test(test), priors=priors, decay=decay, extensions=extensions,
                          cluster=cluster, below_previous=below_previous)
    return fit_model(model, options, out, echo)

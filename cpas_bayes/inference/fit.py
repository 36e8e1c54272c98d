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
3. ``n_ensembles`` independent emcee ensembles (differential-evolution moves,
   80 % DE / 20 % snooker, which mix far better than the stretch move in 30–40
   dimensions), each with its own random state (``sampler.random_state`` from
   the ensemble's seed; numpy's global generator is never touched). Walkers of
   one ensemble are not independent chains, so R-hat is the nested R-hat over
   ensembles.
4. Each ensemble runs in chunks until the chain is longer than 50 integrated
   autocorrelation times τ and τ has changed by less than 5 % since the last
   chunk; burn-in = 2·max τ, thin = ½·min τ.
5. Checkpoints: every chunk is appended to an emcee HDF5 backend; the file is
   copied, extended and renamed back, so a kill at any instant leaves the last
   complete chunk. A rerun on the same folder resumes from it and, because emcee
   stores its random state with every step, ends with the same chain as an
   uninterrupted run.
"""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import emcee
import numpy as np
from scipy import optimize

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.files import atomic_path
from cpas_bayes.stats.model import TestModel


@dataclass(frozen=True)
class SamplerOptions:
    """Knobs of the sampler; defaults suit a two-Drogue or three-Main test."""

    seed: int = 0
    n_ensembles: int = 4
    walkers: int | None = None        # default: 2·D + 2, even
    check_every: int = 500            # steps between convergence checks (and checkpoints)
    max_steps: int = 20000
    store_every: int = 5              # keep every k-th step in the chain file
    tau_factor: float = 50.0          # converged when steps > tau_factor·τ ...
    tau_rtol: float = 0.05            # ... and τ moved less than this since the last check
    map_starts: int = 4
    workers: int = 2
    progress: bool = True


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
        chains = np.concatenate([r.draws[:, -s:, :] for r in self.runs], axis=0)
        lp = np.concatenate([r.log_prob[:, -s:] for r in self.runs], axis=0)
        ensemble = np.concatenate([np.full(r.draws.shape[0], e) for e, r in enumerate(self.runs)])
        return chains, lp, ensemble


# ---------------------------------------------------------------------------
# starting point


def first_guess(model: TestModel):
    """A physically sensible θ from the data: stage levels, nominal starts, prior medians."""
    obs = model.obs
    theta = np.array([p.prior.ppf(0.5) for p in model.parameters], dtype=float)
    idx = model.index
    for ext in model.extensions:
        for name, value in ext.initial_values(model).items():
            theta[idx[name]] = value
    t = obs.time
    total_late = np.median(obs.acc[t > t[-1] - 0.15 * (t[-1] - t[0])]) + obs.stated_vehicle_cds
    lc_rows = {int(c): r for r, c in enumerate(obs.lc_index)}
    scale = 1.0
    if obs.lc_index.size:
        late = t > t[-1] - 0.15 * (t[-1] - t[0])
        lc_sum = obs.lc[:, late].sum(axis=0).mean()
        scale = float(np.clip(total_late / max(lc_sum, 1e-9), 0.85, 1.5))
        theta[idx["load_scale"]] = scale
    for i, p in enumerate(model.parachutes):
        def level(t0, t1, i=i):
            window = (t >= t0 + 0.6 * (t1 - t0)) & (t < t1)
            if not window.any():
                window = (t >= t0) & (t < t1)
            if i in lc_rows:
                return float(np.median(obs.lc[lc_rows[i], window])) * scale
            return float(np.median(obs.acc[window]) + obs.stated_vehicle_cds) / model.n_chutes
        starts = [s.start for s in p.stages] + [t[-1] + 1e-9]
        cds_o = max(level(starts[-2], starts[-1]), 1e-3)
        prior = model.parameters[idx[f"{p.id}.cds_o"]].prior
        lo, hi = prior.support
        theta[idx[f"{p.id}.cds_o"]] = float(np.clip(cds_o, lo + 1e-6 * (hi - lo), hi - 1e-6 * (hi - lo)))
        for k, st in enumerate(p.stages):
            theta[idx[f"{p.id}.s{k + 1}.start"]] = st.start
            key = f"{p.id}.s{k + 1}.eps"
            if key in idx:
                eps = level(starts[k], starts[k + 1]) / theta[idx[f"{p.id}.cds_o"]]
                lo, hi = model.parameters[idx[key]].prior.support
                theta[idx[key]] = float(np.clip(eps, lo + 0.01 * (hi - lo), hi - 0.01 * (hi - lo)))
    return theta


def _bounds(model):
    out = []
    for p in model.parameters:
        lo, hi = p.prior.support
        out.append((lo if np.isfinite(lo) else None, hi if np.isfinite(hi) else None))
    return out


def _batched_gradient(model, theta, h):
    """Value and central-difference gradient of −log p at θ, steps ``h`` (D,), in one batched call."""
    d = theta.size
    rows = np.repeat(theta[None, :], 2 * d + 1, axis=0)
    rows[1:d + 1][np.arange(d), np.arange(d)] += h
    rows[d + 1:][np.arange(d), np.arange(d)] -= h
    lp = model(rows)
    f0 = -lp[0]
    if not np.isfinite(f0):
        return np.inf, np.zeros(d)
    fp, fm = -lp[1:d + 1], -lp[d + 1:]
    # One-sided differences at a bound, where one neighbour leaves the prior.
    grad = np.where(np.isfinite(fp) & np.isfinite(fm), (fp - fm) / (2 * h),
                    np.where(np.isfinite(fp), (fp - f0) / h, (f0 - fm) / h))
    return f0, np.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)


_FD_STEP = 1e-4       # gradient step, in curvature-scaled units
_HESSIAN_STEP = 1e-2  # Hessian step, in curvature-scaled units


def _curvature_scale(model, theta):
    """Per-parameter length scale 1/sqrt(∂²(−log p)/∂θ_i²) at θ, capped by the prior width.

    Optimising in θ/scale makes the problem roughly isotropic: the raw
    parameters span eight orders of magnitude (newtons of vehicle weight
    against reefing ratios known to 1e-3), which stalls a quasi-Newton method.
    """
    d = theta.size
    prior_scale = np.array([_prior_scale(p.prior) for p in model.parameters])
    h = 1e-3 * prior_scale
    rows = np.repeat(theta[None, :], 2 * d + 1, axis=0)
    rows[1:d + 1][np.arange(d), np.arange(d)] += h
    rows[d + 1:][np.arange(d), np.arange(d)] -= h
    f = -model(rows)
    curv = (f[1:d + 1] + f[d + 1:] - 2 * f[0]) / h**2
    ok = np.isfinite(curv) & (curv > 0)
    scale = np.where(ok, 1.0 / np.sqrt(np.where(ok, curv, 1.0)), prior_scale)
    return np.minimum(scale, prior_scale)


def find_map(model: TestModel, rng, starts=6, guesses=None):
    """Maximum a posteriori θ from a data-driven guess and up to ``starts − 1`` jittered copies.

    ``guesses`` (rows of θ) replace the data-driven guess: the first is jittered,
    all are tried first — an extended model starts from its baseline's MAP.

    Each start runs L-BFGS-B in scaled coordinates z = (θ − θ₀)/scale. The
    search stops early once a second start reaches the best optimum again
    (within 0.05 in log p): that optimum is then not a lucky local one.
    """
    candidates = [np.asarray(g, float) for g in guesses] if guesses is not None else [first_guess(model)]
    guess = candidates[0]
    prior_scale = np.array([_prior_scale(p.prior) for p in model.parameters])
    while len(candidates) < starts:
        trial = guess + 0.1 * prior_scale * rng.standard_normal(guess.size)
        if np.isfinite(model(trial[None])[0]):
            candidates.append(trial)
    best_x, best_f = None, np.inf
    for x0 in candidates:
        x, f = _polished_minimum(model, x0)
        confirmed = abs(f - best_f) < 0.05
        if f < best_f:
            best_x, best_f = x, f
        if confirmed:
            break
    return best_x, -best_f


_POLISH_GAIN = 0.05   # restart L-BFGS-B from its result while a run gains more than this in log p
_MAX_POLISH = 6


def _polished_minimum(model, x0):
    """L-BFGS-B in coordinates scaled by the curvature at the start, restarted from its result (with
    the curvature there) while that gains: on these correlated posteriors one run often stops early,
    its quasi-Newton memory fitted to the curvature where it began."""
    f_prev = np.inf
    x = x0
    for _ in range(_MAX_POLISH):
        scale = _curvature_scale(model, x)
        bounds = [(None if lo is None else (lo - c) / s, None if hi is None else (hi - c) / s)
                  for (lo, hi), c, s in zip(_bounds(model), x, scale)]

        def objective(z, x=x, scale=scale):
            f, g = _batched_gradient(model, x + scale * z, _FD_STEP * scale)
            return f, g * scale

        res = optimize.minimize(objective, np.zeros_like(x), jac=True, method="L-BFGS-B", bounds=bounds,
                                options={"maxiter": 2000})
        if res.fun < f_prev:
            x = x + scale * res.x
        gained = f_prev - res.fun
        f_prev = min(f_prev, res.fun)
        if gained < _POLISH_GAIN:
            break
    return x, f_prev


def _prior_scale(prior):
    """A width of the prior for jitter: its central 68 % interval."""
    lo, hi = prior.ppf(0.16), prior.ppf(0.84)
    return float(hi - lo) / 2


def laplace_covariance(model: TestModel, theta):
    """Inverse Hessian of −log p at θ (the Laplace approximation's covariance).

    The Hessian is differenced in curvature-scaled coordinates z = θ/scale,
    where it is close to the identity, so rounding cannot swamp the weakly
    constrained directions. Directions that are not curved upwards (a bound,
    a kink) keep the diagonal scale.
    """
    scale = _curvature_scale(model, theta)
    grads = []
    for sign in (+1, -1):
        rows = theta[None, :] + sign * _HESSIAN_STEP * np.diag(scale)
        grads.append(np.array([_batched_gradient(model, r, _FD_STEP * scale)[1] * scale for r in rows]))
    hess = (grads[0] - grads[1]) / (2 * _HESSIAN_STEP)
    hess = 0.5 * (hess + hess.T)
    w, v = np.linalg.eigh(hess)
    w = np.where(w > 1e-6, w, 1.0)
    cov_z = (v / w) @ v.T
    return cov_z * np.outer(scale, scale)


def _reflect_into(x, lo, hi):
    """Reflect coordinates that left [lo, hi] back inside (a MAP on a bound keeps its spread)."""
    x = np.where(x < lo, 2 * lo - x, x)
    x = np.where(x > hi, 2 * hi - x, x)
    return np.clip(x, lo, hi)


def initial_walkers(model, theta_map, cov, n_walkers, rng, spread=1.0):
    """Walkers drawn from N(MAP, spread²·Σ), reflected into the prior's support, redrawn where the
    posterior is still zero.

    Reflection (not rejection) keeps the ball's width along a parameter whose
    MAP sits on a bound; rejecting there and shrinking the ball would make the
    walkers nearly collinear, which emcee refuses.
    """
    chol = np.linalg.cholesky(cov + 1e-12 * np.eye(cov.shape[0]) * np.max(np.diag(cov)))
    support = np.array([p.prior.support for p in model.parameters], dtype=float)
    out = np.empty((n_walkers, theta_map.size))
    filled = 0
    for _ in range(1000):
        trial = theta_map + spread * rng.standard_normal((n_walkers, theta_map.size)) @ chol.T
        trial = _reflect_into(trial, support[:, 0], support[:, 1])
        ok = np.isfinite(model(trial))
        take = trial[ok][: n_walkers - filled]
        out[filled:filled + take.shape[0]] = take
        filled += take.shape[0]
        if filled == n_walkers:
            return out
        spread *= 0.7
    raise RuntimeError("could not place the walkers inside the prior around the MAP")


# ---------------------------------------------------------------------------
# ensembles


def _moves():
    """Differential evolution. The snooker variant, meant for multimodal targets, gave no
    shorter τ on these unimodal posteriors and costs a Python loop per walker."""
    return [(emcee.moves.DEMove(), 1.0)]


def _fingerprint(model, init, options):
    h = hashlib.sha256()
    h.update(json.dumps(model.names).encode())
    h.update(np.ascontiguousarray(init).tobytes())
    h.update(json.dumps([options.seed, options.store_every]).encode())
    return h.hexdigest()[:16]


def _autocorr(chain, store_every):
    """Integrated autocorrelation time (steps) of a stored (S, W, D) chain."""
    return store_every * emcee.autocorr.integrated_time(chain, tol=0)


class _EnsembleStore:
    """An ensemble advanced chunk by chunk in memory, checkpointed after every chunk.

    The checkpoint is written in emcee's HDF5 layout (readable with
    ``emcee.backends.HDFBackend(path, read_only=True)``) once per chunk, to a
    temporary file renamed over the old one: a kill leaves the last complete
    chunk. Writing per chunk rather than per step (emcee's own HDF5 backend
    opens the file at every step) keeps checkpointing under 1 % of the run.
    On restart the walkers, log-probabilities, acceptance counts and emcee's
    random state are restored, so the resumed chain equals an uninterrupted one.
    """

    def __init__(self, model, init, seed, options, checkpoint):
        self.model, self.init, self.seed, self.options = model, init, seed, options
        self.checkpoint = Path(checkpoint) if checkpoint else None
        self.fingerprint = _fingerprint(model, init, options)
        backend = emcee.backends.Backend()
        if self.checkpoint and self.checkpoint.exists():
            backend = self._load(backend)
        n_walkers, ndim = init.shape
        self.sampler = emcee.EnsembleSampler(n_walkers, ndim, model, vectorize=True, moves=_moves(),
                                             backend=backend)
        if backend.iteration == 0:
            # emcee would start from numpy's global state; give it the ensemble's own instead
            self.sampler.random_state = np.random.RandomState(self.seed).get_state()

    def _load(self, backend):
        import h5py

        try:
            with h5py.File(self.checkpoint, "r") as f:
                if f.attrs.get("fingerprint") != self.fingerprint:
                    raise InputError(self.checkpoint, "attribute 'fingerprint'",
                                     "the checkpoint belongs to another model, data or seed",
                                     "delete the checkpoint folder or fit into a new --out folder")
                g = f["mcmc"]
                backend.reset(int(g.attrs["nwalkers"]), int(g.attrs["ndim"]))
                backend.chain = g["chain"][...]
                backend.log_prob = g["log_prob"][...]
                backend.accepted = g["accepted"][...]
                backend.iteration = int(g.attrs["iteration"])
                backend.random_state = tuple(v for k, v in sorted(g.attrs.items())
                                             if k.startswith("random_state_"))
        except (OSError, KeyError, ValueError, TypeError) as exc:  # truncated, garbage or incomplete file
            raise InputError(self.checkpoint, "", f"not a readable checkpoint ({type(exc).__name__}: "
                             f"{str(exc)[:120]})", f"delete {self.checkpoint} (that ensemble starts again) and "
                             "re-run the same command") from None
        return backend

    def _save(self):
        import h5py

        b = self.sampler.backend
        with atomic_path(self.checkpoint) as tmp:
            with h5py.File(tmp, "w") as f:
                f.attrs["fingerprint"] = self.fingerprint
                f.attrs["parameters"] = json.dumps(self.model.names)
                f.attrs["store_every"] = self.options.store_every
                g = f.create_group("mcmc")
                g.attrs.update({"version": emcee.__version__, "nwalkers": b.nwalkers, "ndim": b.ndim,
                                "has_blobs": False, "iteration": b.iteration})
                g.create_dataset("chain", data=b.chain[: b.iteration], maxshape=(None, b.nwalkers, b.ndim))
                g.create_dataset("log_prob", data=b.log_prob[: b.iteration], maxshape=(None, b.nwalkers))
                g.create_dataset("accepted", data=b.accepted)
                for i, v in enumerate(b.random_state):
                    g.attrs[f"random_state_{i}"] = v

    def advance(self):
        """Run one chunk; return (steps, chain (S, W, D), log_prob (S, W), acceptance)."""
        backend = self.sampler.backend
        first = backend.iteration == 0
        self.sampler.run_mcmc(self.init if first else None, self.options.check_every // self.options.store_every,
                              thin_by=self.options.store_every, progress=False)
        if self.checkpoint:
            self._save()
        steps = backend.iteration * self.options.store_every
        # emcee adds one acceptance per stored step, not per thinned-away step
        acceptance = float(np.mean(backend.accepted) / max(backend.iteration, 1))
        return steps, backend.get_chain(), backend.get_log_prob(), acceptance


def run_ensemble(model, init, seed, options: SamplerOptions, checkpoint=None, label="", report=None):
    """Run one ensemble to convergence (or ``max_steps``); resumable from ``checkpoint``."""
    store = _EnsembleStore(model, init, seed, options, checkpoint)
    tau_prev = None
    while True:
        steps, chain, log_prob, acceptance = store.advance()
        tau = _autocorr(chain, options.store_every)
        settled = tau_prev is not None and np.all(np.abs(tau - tau_prev) < options.tau_rtol * tau)
        converged = bool(steps > options.tau_factor * np.max(tau) and settled)
        if report is not None:
            report(label, steps, float(np.max(tau)), converged)
        if converged or steps >= options.max_steps:
            break
        tau_prev = tau
    burn = int(np.ceil(2 * np.max(tau) / options.store_every))
    thin = max(1, int(0.5 * np.min(tau) / options.store_every))
    kept = chain[burn::thin]
    return EnsembleRun(draws=np.swapaxes(kept, 0, 1), log_prob=log_prob[burn::thin].T, tau=tau, steps=steps,
                       acceptance=acceptance, converged=converged, burn=burn * options.store_every,
                       thin=thin * options.store_every)


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
        cov = laplace_covariance(model, theta_map)
        n_walkers = options.walkers or 2 * model.ndim + 2
        n_walkers += n_walkers % 2
        inits = [initial_walkers(model, theta_map, cov, n_walkers, np.random.default_rng([options.seed, e]))
                 for e in range(options.n_ensembles)]
        seeds = [int(np.random.default_rng([options.seed, e, 1]).integers(2**31 - 1))
                 for e in range(options.n_ensembles)]
        ckpts = [Path(checkpoint_dir) / f"ensemble_{e}.h5" if checkpoint_dir else None
                 for e in range(options.n_ensembles)]
        runs = _run_all(model, inits, seeds, ckpts, options, executor)
    finally:
        if own:
            executor.close()
    return SamplingResult(names=list(model.names), runs=runs, theta_map=theta_map, log_post_map=float(lp_map),
                          options=options)


def _run_all(model, inits, seeds, ckpts, options, executor):
    labels = [f"ensemble {e + 1}/{len(inits)}" for e in range(len(inits))]
    jobs = [(model, i, s, options, c, lab) for i, s, c, lab in zip(inits, seeds, ckpts, labels)]
    bars = _ProgressBars(labels, options) if options.progress and sys.stderr.isatty() else None
    try:
        return executor.map(_ensemble_task, jobs, desc="ensembles", progress=False,
                            on_report=bars.update if bars else None)
    finally:
        if bars:
            bars.close()


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


def prepare_model(test, reduction, priors=None, decay="linear", extensions=(), native_rate=False):
    """The :class:`TestModel` of a test from its reduction (:func:`cpas_bayes.data.reduction.reduce_test`).

    The reduction is an argument, not redone here: a command reduces a bundle
    once and builds every model it needs (baseline, extensions) from that.
    """
    from cpas_bayes.stats.observations import build_observations
    from cpas_bayes.stats.priors import load_kind_priors, load_nuisance_priors

    obs = build_observations(test, reduction.frame, native_rate=native_rate)
    kind_priors = {p.kind: load_kind_priors(p.kind, priors) for p in test.parachutes}
    return TestModel(test, obs, kind_priors, load_nuisance_priors(priors), decay=decay, extensions=extensions)


def fit_model(model: TestModel, options: SamplerOptions = SamplerOptions(), out=None, echo=None,
              guesses=None, checkpoint_dir=None, executor=None) -> Fit:
    """Sample ``model``'s posterior; write ``posterior.nc`` and ``summary.json`` into ``out`` if given.

    Checkpoints go to ``checkpoint_dir`` (default ``out/checkpoint``); none without either.
    ``executor`` runs the ensembles (see :func:`sample_posterior`).
    """
    from cpas_bayes.inference.fit_folder import POSTERIOR_NAME, build_datatree, build_summary, convergence, save_datatree, write_summary

    out = Path(out) if out else None
    if checkpoint_dir is None and out is not None:
        checkpoint_dir = out / "checkpoint"
    sampling = sample_posterior(model, options, checkpoint_dir=checkpoint_dir, echo=echo, guesses=guesses,
                                executor=executor)
    tree = build_datatree(model, sampling, np.random.default_rng([options.seed, 99]))
    diagnostics = convergence(tree, sampling)
    summary = build_summary(model, tree, diagnostics, options)
    if out:
        save_datatree(tree, out / POSTERIOR_NAME)
        write_summary(out, summary)
    return Fit(model, sampling, tree, summary)


def fit_test(test, options: SamplerOptions = SamplerOptions(), out=None, priors=None, decay="linear",
             extensions=(), echo=None) -> Fit:
    """Reduce, model and sample one flight test (the baseline model unless extensions are given)."""
    from cpas_bayes.data.reduction import reduce_test

    model = prepare_model(test, reduce_test(test), priors=priors, decay=decay, extensions=extensions)
    return fit_model(model, options, out, echo)

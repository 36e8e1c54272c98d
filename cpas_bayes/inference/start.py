"""Where sampling starts: a data-driven first guess, the MAP point and the Laplace ball of walkers.

1. A first guess from the data (stage levels from the reduced drag areas,
   nominal start times, prior medians for the shape parameters).
2. The maximum a posteriori point from several starts with L-BFGS-B in
   curvature-scaled coordinates; gradients are central differences evaluated
   as *one* batched call of the vectorised log posterior (2·D + 1 rows), which
   is why a MAP costs a few hundred calls. Each start is restarted from its
   own result with the curvature there while it still gains.
3. The Laplace covariance at the MAP (finite-difference Hessian, batched the
   same way) shapes the walkers' initial ball: N(MAP, Σ), redrawn where the
   prior is zero.
"""

from __future__ import annotations

import numpy as np
from scipy import optimize

from cpas_bayes.core.errors import InputError
from cpas_bayes.stats.model import TestModel


def first_guess(model: TestModel):
    """A physically sensible θ from the data: stage levels, nominal starts, prior medians."""
    obs = model.obs
    theta = np.array([p.prior.ppf(0.5) for p in model.parameters], dtype=float)
    idx = model.index
    for ext in model.extensions:
        for name, value in ext.initial_values(model).items():
            theta[idx[name]] = value
    for name, value in model.initial_values().items():
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
    guesses = {}   # parameter -> guesses of its parachutes (several in a composite group: averaged)
    for i, p in enumerate(model.parachutes):
        def level(t0, t1, i=i):
            window = (t >= t0 + 0.6 * (t1 - t0)) & (t < t1)
            if not window.any():
                window = (t >= t0) & (t < t1)
            if i in lc_rows:
                return float(np.median(obs.lc[lc_rows[i], window])) * scale
            return float(np.median(obs.acc[window]) + obs.stated_vehicle_cds) / model.n_chutes
        starts = [s.start for s in p.stages] + [t[-1] + 1e-9]
        key = model.parameter_name(i, "cds_o")
        lo, hi = model.parameters[idx[key]].prior.support
        cds_o = float(np.clip(max(level(starts[-2], starts[-1]), 1e-3), lo + 1e-6 * (hi - lo), hi - 1e-6 * (hi - lo)))
        guesses.setdefault(key, []).append(cds_o)
        for k, st in enumerate(p.stages):
            guesses.setdefault(model.parameter_name(i, f"s{k + 1}.start"), []).append(st.start)
            key = model.parameter_name(i, f"s{k + 1}.eps")
            if key is not None:
                eps = level(starts[k], starts[k + 1]) / cds_o
                lo, hi = model.parameters[idx[key]].prior.support
                guesses.setdefault(key, []).append(float(np.clip(eps, lo + 0.01 * (hi - lo), hi - 0.01 * (hi - lo))))
    for key, values in guesses.items():
        theta[idx[key]] = np.mean(values)
    return theta


def _bounds(model):
    out = []
    for p in model.parameters:
        lo, hi = p.prior.support
        out.append((lo if np.isfinite(lo) else None, hi if np.isfinite(hi) else None))
    return out


def _forward_gradient(model, theta, h):
    """Value and forward-difference gradient of −log p at θ, steps ``h`` (D,): D + 1 rows in one batched call,
    half the central difference's; backward where a step leaves the prior (one more call, rare)."""
    d = theta.size
    rows = np.repeat(theta[None, :], d + 1, axis=0)
    rows[1:][np.arange(d), np.arange(d)] += h
    lp = model(rows)
    f0 = -lp[0]
    if not np.isfinite(f0):
        return np.inf, np.zeros(d)
    fp = -lp[1:]
    grad = (fp - f0) / h
    out = ~np.isfinite(fp)
    if out.any():
        back = np.repeat(theta[None, :], int(out.sum()), axis=0)
        back[np.arange(back.shape[0]), np.flatnonzero(out)] -= h[out]
        grad[out] = (f0 + model(back)) / h[out]
    return f0, np.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)


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
    tries = 0
    while len(candidates) < starts and tries < _MAX_JITTER_TRIES * starts:   # a bounded search, never a hang
        tries += 1
        trial = guess + 0.1 * prior_scale * rng.standard_normal(guess.size)
        if np.isfinite(model(trial[None])[0]):
            candidates.append(trial)
    if len(candidates) < starts and not np.isfinite(model(np.array(candidates))).any():
        with np.errstate(all="ignore"):
            bad = [p.name for p, x in zip(model.parameters, guess) if not np.isfinite(p.prior.logpdf(x))]
        # bad input, not a fault of the program: said as a refusal (exit status 2), not an internal error
        test = model.test
        raise InputError(test.source if test.source else test.label, "",
                         f"no start with a finite log posterior found near the first guess ({tries} jittered "
                         "draws): " + (f"the prior density is not finite there for {', '.join(bad)}" if bad else
                                       "every prior is finite there, the likelihood is not"),
                         "check the priors (the test's prior files, a --priors file) and the bundle's stated values "
                         "(weights, drag areas, stage starts)")
    best_x, best_f = None, np.inf
    for x0 in candidates:
        x, f = _polished_minimum(model, x0)
        confirmed = abs(f - best_f) < 0.05
        if f < best_f:
            best_x, best_f = x, f
        if confirmed:
            break
    return best_x, -best_f


def local_map(model: TestModel, x0):
    """The optimum of the log posterior nearest ``x0`` (the search of :func:`find_map` from one start):
    ``(θ, log p)``."""
    x, f = _polished_minimum(model, np.asarray(x0, float))
    return x, -f


_MAX_JITTER_TRIES = 100   # jittered draws per wanted start before find_map gives up looking for more
_POLISH_GAIN = 0.05   # restart L-BFGS-B from its result while a run gains more than this in log p
_MAX_POLISH = 6
_MIN_MEMORY = 10     # L-BFGS-B correction pairs at least (scipy's default)


def _polished_minimum(model, x0):
    """L-BFGS-B in coordinates scaled by the curvature at the start, restarted from its result (with
    the curvature there) while that gains: on these correlated posteriors one run often stops early,
    its quasi-Newton memory fitted to the curvature where it began.

    The runs use forward differences (D + 1 rows per gradient) until a run gains less than
    ``_POLISH_GAIN``; the last runs use central differences (2·D + 1), whose accuracy only the end of the
    search needs: near the optimum a forward difference's bias (h/2 times the curvature) is as large as
    the gradient itself, far from it irrelevant."""
    f_prev = np.inf
    x = x0
    gradient = _forward_gradient
    for i in range(_MAX_POLISH):
        if i == _MAX_POLISH - 1:
            gradient = _batched_gradient     # the last run is central whatever came before
        scale = _curvature_scale(model, x)
        bounds = [(None if lo is None else (lo - c) / s, None if hi is None else (hi - c) / s)
                  for (lo, hi), c, s in zip(_bounds(model), x, scale)]

        def objective(z, x=x, scale=scale, gradient=gradient):
            f, g = gradient(model, x + scale * z, _FD_STEP * scale)
            return f, g * scale

        # A memory as long as the dimension: with the default 10 pairs the quasi-Newton model never
        # holds the trade-offs between stage parameters, and a Main's added-mass search took 1,500
        # iterations instead of ~350 (45 parameters).
        res = optimize.minimize(objective, np.zeros_like(x), jac=True, method="L-BFGS-B", bounds=bounds,
                                options={"maxiter": 2000, "maxcor": max(_MIN_MEMORY, x.size)})
        if res.fun < f_prev:
            x = x + scale * res.x
        gained = f_prev - res.fun
        f_prev = min(f_prev, res.fun)
        if gained < _POLISH_GAIN:
            if gradient is _batched_gradient:
                break
            gradient = _batched_gradient     # the end of the search: central differences
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

"""Mode jumps between the pairings of like canopies: each pairing's optimum and Laplace shape.

Without a load cell per canopy, which canopy opened first at a stage is not known, and the posterior has one
mode per pairing. A label exchange E (:class:`cpas_bayes.stats.cluster_form.Exchange`) maps a point of one
pairing to the other, but it lands on the other mode only where the data see nothing but the sum. They
often see more: on a two-Drogue logger test the two disreefs, 0.5 s apart, show which canopy held which
reefed drag area, so the exchange of a median walker costs 44–77 log-units and is almost never accepted,
while the two pairings' optima differ by less than 1.

So the other pairing's optimum is found once, before sampling (a local MAP search started from E(MAP)), and
with the Laplace covariances of both optima in the sampler's coordinates, Σ_A = L_A·L_Aᵀ and Σ_B = L_B·L_Bᵀ,
a walker of the MAP's pairing A jumps by the affine map that carries N(μ_A, Σ_A) onto N(μ_B, Σ_B):
q = μ_B + L_B·L_A⁻¹·(s − μ_A); from B, by its inverse (mode jumping with a deterministic map, Tjelmeland &
Hegstad 2001). A q that does not land in the other pairing is refused; the rest are accepted with
min(1, p(q)·|det L_B / det L_A|^(±1) / p(s)) (:class:`cpas_bayes.inference.moves.ModeJumpMove`). On two
Gaussian modes that is min(1, w_B/w_A): the move crosses as often as the modes' weights allow. The
Laplace shapes serve the sampler's first chunk only: they fit these modes poorly, so after it each jump is
refitted to its draws' own mean and covariance in each pairing (:func:`refit_jumps`) and frozen.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import linalg

from cpas_bayes.inference.ensemble_store import exchanges_of
from cpas_bayes.inference.start import laplace_covariance, local_map

# No jump is learnt to a pairing whose optimum lies this far below the MAP in log posterior: its share of
# the mass is negligible, and a jump there would only be refused.
JUMP_RANGE = 40.0


@dataclass(frozen=True)
class ModeJump:
    """The jump across one label exchange's pairings, in the sampler's coordinates.

    ``order``: the columns of the exchanged stage's two starts, whose order tells the pairing; ``side``: the
    MAP's pairing (whether the first start is earlier); ``mean_a``, ``chol_a`` and ``mean_b``, ``chol_b``:
    the centre and the Cholesky factor of the covariance of the MAP's pairing and of the other (the optima
    and their Laplace covariances, or the draws' moments once refitted).
    """

    order: tuple
    side: bool
    mean_a: np.ndarray
    chol_a: np.ndarray
    mean_b: np.ndarray
    chol_b: np.ndarray
    log_post_gap: float   # log p(MAP) − log p(the other pairing's optimum)

    @property
    def log_det(self):
        """log|det(L_B·L_A⁻¹)|: the log Jacobian of the jump from A to B."""
        return float(np.sum(np.log(np.diag(self.chol_b))) - np.sum(np.log(np.diag(self.chol_a))))

    def apply(self, s):
        """(q, crossed, log|∂q/∂s|) of rows ``s``: each row moved to the other pairing's mode; ``crossed``
        whether q lies in the other pairing (the map is an involution only for those)."""
        s = np.atleast_2d(s)
        from_a = pairing_of(s, self.order) == self.side
        q = np.empty_like(s)
        if from_a.any():
            z = linalg.solve_triangular(self.chol_a, (s[from_a] - self.mean_a).T, lower=True)
            q[from_a] = self.mean_b + (self.chol_b @ z).T
        if (~from_a).any():
            z = linalg.solve_triangular(self.chol_b, (s[~from_a] - self.mean_b).T, lower=True)
            q[~from_a] = self.mean_a + (self.chol_a @ z).T
        crossed = pairing_of(q, self.order) != pairing_of(s, self.order)
        return q, crossed, np.where(from_a, self.log_det, -self.log_det)


def pairing_of(x, order):
    """Whether each row of ``x`` has the exchange's first start earlier than its second (its pairing)."""
    x = np.atleast_2d(x)
    return x[:, order[0]] < x[:, order[1]]


def _other_optimum(job):
    """Local MAP from the exchanged MAP and its Laplace covariance: (θ*, log p(θ*), Σ*)."""
    model, theta0 = job
    theta, lp = local_map(model, theta0)
    return theta, lp, laplace_covariance(model, theta)


def other_pairings(model, theta_map, log_post_map, executor=None):
    """Each label exchange's other-pairing optimum: ``(θ_map, log p, [(exchange index, θ*, log p*, Σ*)])``.

    One local MAP search per exchange of ``model`` that tells its pairing (its stage starts), started from
    the exchanged MAP, as one task each on ``executor``; Σ* is the Laplace covariance there. Where one of
    them is higher than the MAP in the other pairing, it is the MAP (the walkers start there) and the
    searches are made again from it.
    """
    from cpas_bayes.core.executor import Executor

    exchanges = [(i, e) for i, e in enumerate(exchanges_of(model)) if e.order is not None]
    if not exchanges:
        return theta_map, log_post_map, []
    executor = executor or Executor()
    found = executor.map(_other_optimum, [(model, e.apply(theta_map[None])[0]) for _, e in exchanges],
                         desc="pairings", progress=False)
    optima = [(i, *f) for (i, e), f in zip(exchanges, found)
              if pairing_of(f[0], e.order)[0] != pairing_of(theta_map, e.order)[0]]   # not fallen back
    higher = [o for o in optima if o[2] > log_post_map]
    if higher:
        _, theta, lp, _ = max(higher, key=lambda o: o[2])
        return other_pairings(model, theta, lp, executor)
    return theta_map, log_post_map, optima


def _sampler_laplace(to_sampler, theta, cov):
    """(u, Cholesky factor of the covariance in u) of a Laplace approximation N(θ, Σ) carried by the
    sampler's map: Σ_u = J·Σ·Jᵀ, J the map's Jacobian by differences (steps 1e-4 of each sd; one-sided
    where a step leaves the map's domain, a bound). None where J or the factor cannot be had: no jump."""
    h = 1e-4 * np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    d = theta.size
    u0 = to_sampler(theta[None])[0]
    with np.errstate(all="ignore"):
        up, down = to_sampler(theta + np.diag(h)), to_sampler(theta - np.diag(h))
    ok_up, ok_down = np.isfinite(up).all(axis=1), np.isfinite(down).all(axis=1)
    steps = np.where(ok_up & ok_down, 2 * h, h)[:, None]
    jac = (np.where(ok_up[:, None], up, u0) - np.where(ok_down[:, None], down, u0)) / steps
    if not (ok_up | ok_down).all() or not np.isfinite(jac).all() or jac.shape != (d, d):
        return None
    cov_u = jac.T @ cov @ jac
    w, v = np.linalg.eigh(0.5 * (cov_u + cov_u.T))
    cov_u = (v * np.maximum(w, 1e-12 * w.max())) @ v.T      # rounding must not make it indefinite
    try:
        return u0, np.linalg.cholesky(cov_u)
    except np.linalg.LinAlgError:
        return None


def mode_jumps(target, to_sampler, theta_map, log_post_map, cov_map, optima):
    """The :class:`ModeJump` of each optimum of :func:`other_pairings` within :data:`JUMP_RANGE` of the
    MAP, in the coordinates of ``target`` (the log density the sampler moves in; its ``exchanges()`` in the
    model's order), with ``to_sampler`` mapping θ rows there (the identity when the sampler moves in θ);
    ``cov_map`` the Laplace covariance at the MAP."""
    exchanges = exchanges_of(target)
    optima = [o for o in optima if log_post_map - o[2] <= JUMP_RANGE]
    if not optima:
        return []
    at_map = _sampler_laplace(to_sampler, theta_map, cov_map)
    jumps = []
    for i, theta, lp, cov in optima if at_map is not None else ():
        order = exchanges[i].order
        other = _sampler_laplace(to_sampler, theta, cov)
        if other is not None:
            jumps.append(ModeJump(tuple(order), bool(pairing_of(at_map[0], order)[0]), *at_map, *other,
                                  float(log_post_map - lp)))
    return jumps


def refit_jumps(jumps, chains):
    """``jumps`` with each pairing's mean and covariance those of the draws in it, where it holds at least
    :data:`MIN_REFIT_DRAWS` per dimension; ``chains`` (S, W, D) per ensemble, in the sampler's coordinates.

    The Laplace approximation is a poor picture of these modes (on a two-Drogue logger test: some sds 2–12
    times its, a mean 14 of its sds away, the MAP on a kink), and the jump between two Laplace fits was
    accepted 0.1 % of the time from walkers past the warm-up; between the draws' own moments, 4.6 %.
    """
    draws = np.concatenate([c.reshape(-1, c.shape[-1]) for c in chains])
    out = []
    for j in jumps:
        side = pairing_of(draws, j.order) == j.side
        fitted = [_moments(draws[rows]) if rows.sum() >= MIN_REFIT_DRAWS * draws.shape[1] else None
                  for rows in (side, ~side)]
        (mean_a, chol_a), (mean_b, chol_b) = [f if f is not None else old for f, old in
                                              zip(fitted, ((j.mean_a, j.chol_a), (j.mean_b, j.chol_b)))]
        out.append(replace(j, mean_a=mean_a, chol_a=chol_a, mean_b=mean_b, chol_b=chol_b))
    return out


MIN_REFIT_DRAWS = 5    # per dimension, for a covariance estimate whose sds are within ~10 %


def _moments(x):
    """(mean, Cholesky factor of the covariance) of rows ``x``, or None where the covariance is singular."""
    cov = np.cov(x.T)
    try:
        return x.mean(axis=0), np.linalg.cholesky(cov + 1e-10 * np.diag(np.diag(cov)))
    except np.linalg.LinAlgError:
        return None

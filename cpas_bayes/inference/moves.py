"""The ensemble move of every fit: emcee's differential-evolution move with the bookkeeping vectorised.

emcee's :class:`emcee.moves.DEMove` (ter Braak 2006; Nelson et al. 2013)
proposes, for each walker s of one half of the ensemble,

    q = s + γ·(c_a − c_b),   γ = γ₀·(1 + σ·N(0, 1)),   γ₀ = 2.38/√(2·D),  σ = 10⁻⁵,

with c_a ≠ c_b two walkers of the other half, and accepts q with probability
min(1, p(q)/p(s)). The proposal is symmetric, so there is no Hastings factor.

What this class changes is only how the step is computed, not the chain's law:

* the Metropolis test of a half is one comparison of arrays (emcee's
  ``RedBlueMove.propose`` loops over the walkers in Python, one ``rand()``
  each);
* the pair (a, b) is drawn as a ~ U{0..n−1}, b ~ U{0..n−2} shifted past a —
  uniform over the n(n−1) ordered pairs, as emcee's choice from an explicit
  pair table is;
* the vectorised log posterior is called directly, without emcee's per-walker
  conversion of the results to Python floats (our model returns one float64
  array; a NaN log posterior is rejected, as the comparison rejects it in
  emcee).

Measured on the two-Drogue example (60 walkers, 29 parameters; ``python
benchmarks/run.py --only step_cost``): beside 0.42 ms of log posterior per
step, the sampler's own work is 0.31 ms with emcee's DEMove and 0.20 ms with
this move, at the same acceptance (0.243 / 0.238).
"""

from __future__ import annotations

import emcee
import numpy as np


class VectorisedDEMove(emcee.moves.DEMove):
    """:class:`emcee.moves.DEMove` whose proposal and acceptance are array operations (two halves)."""

    def __init__(self, sigma=1.0e-5, gamma0=None):
        super().__init__(sigma=sigma, gamma0=gamma0, nsplits=2, randomize_split=True)

    def draw_pairs(self, ns, nc, random):
        """For each of ``ns`` walkers, the pair (a, b) of the ``nc`` others and its γ (ns, 1)."""
        a = random.randint(nc, size=ns)
        b = random.randint(nc - 1, size=ns)
        b += b >= a                                   # b ≠ a, uniform over the others
        return a, b, self.g0 * (1.0 + self.sigma * random.randn(ns, 1))

    def get_proposal(self, s, c, random):
        c = np.concatenate(c, axis=0)
        a, b, gamma = self.draw_pairs(s.shape[0], c.shape[0], random)
        return s + gamma * (c[b] - c[a]), np.zeros(s.shape[0])

    def propose(self, model, state):
        nwalkers, ndim = state.coords.shape
        if nwalkers < 2 * ndim:
            raise RuntimeError(f"{nwalkers} walkers for {ndim} parameters: a red-blue move needs at least "
                               "twice as many walkers as parameters")
        self.setup(state.coords)
        accepted = np.zeros(nwalkers, dtype=bool)
        halves = np.arange(nwalkers) % 2
        model.random.shuffle(halves)
        for half in (0, 1):
            mine = halves == half
            q, factors = self.get_proposal(state.coords[mine], [state.coords[~mine]], model.random)
            new_log_prob = np.asarray(model.log_prob_fn(q), dtype=float)
            take = factors + new_log_prob - state.log_prob[mine] > np.log(model.random.rand(q.shape[0]))
            accepted[mine] = take
            state = self.update(state, emcee.State(q, log_prob=new_log_prob), accepted, mine)
        return state, accepted


class AlignedDEMove(VectorisedDEMove):
    """Differential evolution within one pairing of like canopies (:class:`ExchangeMove` crosses between them).

    Where like canopies trade places, the walkers of the other half sit in several pairings, and a
    difference of two walkers in different pairings is a jump between modes that is almost always refused
    (a two-Drogue logger fit: acceptance 0.02–0.03). So the pair c_a, c_b is first brought into the pairing
    of the walker s it moves: the pairing is read from the order of each exchanged stage's two starts, and
    an exchange is applied wherever that order differs from s's, until none does (each exchange of an
    inverted pair removes an inversion, so this ends). q = s + γ·(c'_b − c'_a) is refused when its own
    pairing is not s's. From q the same walkers are aligned alike (their alignment reads only s's pairing,
    which q shares), so the proposal stays symmetric and the Metropolis ratio is p(q)/p(s).
    """

    def __init__(self, exchanges, **kwargs):
        super().__init__(**kwargs)
        self.exchanges = tuple(e for e in exchanges if e.order is not None)

    def pairing(self, x):
        """(n, E) bool: for each exchange, whether its first canopy's stage starts before the second's."""
        return np.stack([x[:, e.order[0]] < x[:, e.order[1]] for e in self.exchanges], axis=1) \
            if self.exchanges else np.zeros((x.shape[0], 0), bool)

    def align(self, x, pairing):
        """Rows of ``x`` exchanged into ``pairing`` (one row each)."""
        x = np.array(x, float)
        for _ in range(len(self.exchanges)):
            changed = False
            for k, e in enumerate(self.exchanges):
                rows = (x[:, e.order[0]] < x[:, e.order[1]]) != pairing[:, k]
                if rows.any():
                    x[rows] = e.apply(x[rows])
                    changed = True
            if not changed:
                break
        return x

    def get_proposal(self, s, c, random):
        c = np.concatenate(c, axis=0)
        a, b, gamma = self.draw_pairs(s.shape[0], c.shape[0], random)
        pairing = self.pairing(s)
        q = s + gamma * (self.align(c[b], pairing) - self.align(c[a], pairing))
        return q, np.where((self.pairing(q) == pairing).all(axis=1), 0.0, -np.inf)


# ---------------------------------------------------------------------------
# the adaptive independence proposal

PROPOSAL_DOF = 30.0      # ν of the multivariate t: tails a little heavier than the near-normal posteriors
EXCHANGE_SHARE = 0.1     # of the moves, when like canopies can trade places (ExchangeMove)
JUMP_SHARE = 0.1         # of the moves, when the pairings' modes are known (ModeJumpMove; the exchange then 0.05)
PROPOSAL_SHARE = 0.7     # of the moves; differential evolution keeps the rest (any posterior shape)


class IndependenceMove(emcee.moves.Move):
    r"""Independence Metropolis–Hastings with a fixed multivariate-t proposal, in coordinates u = T(θ).

    u = log θ for the parameters of ``log_columns`` (those with a lognormal prior), u = θ for the others;
    the proposal is u′ ~ t_ν(μ, LLᵀ), θ′ = T⁻¹(u′), so its density in θ is
    q(θ) = t_ν(T(θ); μ, LLᵀ)·Π_log 1/θ_j. Every walker proposes whatever its position and accepts with
    probability min(1, p(θ′)·q(θ) / (p(θ)·q(θ′))), so with q close to the posterior successive draws are
    nearly independent: on the two-Drogue example τ falls from ~90 steps (differential evolution, the
    random-walk limit ≈ D/0.3 of a near-normal posterior in D = 29 dimensions) to ~5.

    Why log coordinates: a parameter the data barely constrain keeps its lognormal prior's skewed tail; a
    symmetric t fitted to it in θ is too thin there, and a walker that reaches the tail is seldom left
    (seen: a walker that did not move for a whole 250-step window on a three-Main calibration replica with a
    stage below its predecessor's drag area, whose n_p and expopen the data cannot see; measured on a toy
    with four such parameters: τ 12–30 steps in θ against 2 in log θ). In log θ that tail is normal. (That
    replica's low acceptance, 0.04, has another cause and stayed.) q does not depend on the walkers, so each
    walker's chain keeps the posterior invariant on its own; the acceptance is one array comparison.
    """

    def __init__(self, mean, chol, log_columns=None, dof=PROPOSAL_DOF):
        self.mean = np.asarray(mean, float)
        self.chol = np.asarray(chol, float)
        self.log_columns = (np.zeros(self.mean.size, bool) if log_columns is None
                            else np.asarray(log_columns, bool))
        self.dof = float(dof)
        self._chol_inv = np.linalg.inv(self.chol)

    def log_q(self, theta):
        """log q(θ) up to its constant (which cancels in the Hastings ratio); −inf outside T's domain."""
        u, log_jacobian = to_proposal_coordinates(theta, self.log_columns)
        z = (u - self.mean) @ self._chol_inv.T
        return -0.5 * (self.dof + self.mean.size) * np.log1p(np.sum(z * z, axis=1) / self.dof) + log_jacobian

    def propose(self, model, state):
        n, d = state.coords.shape
        z = model.random.randn(n, d) / np.sqrt(model.random.chisquare(self.dof, size=n) / self.dof)[:, None]
        u = self.mean + z @ self.chol.T
        # exp of a far tail draw would overflow: such a θ is outside every prior's support anyway
        q = np.where(self.log_columns, np.exp(np.minimum(u, 700.0)), u)
        new_log_prob = np.asarray(model.log_prob_fn(q), dtype=float)
        with np.errstate(invalid="ignore"):
            log_ratio = new_log_prob - state.log_prob + self.log_q(state.coords) - self.log_q(q)
        accepted = log_ratio > np.log(model.random.rand(n))   # NaN: rejected
        state = self.update(state, emcee.State(q, log_prob=new_log_prob), accepted)
        return state, accepted


def to_proposal_coordinates(theta, log_columns):
    """(u, log|du/dθ|) of draws θ (N, D): u = log θ on ``log_columns``, θ elsewhere; NaN and −inf where a log
    column is not positive."""
    theta = np.atleast_2d(np.asarray(theta, float))
    logged = theta[:, log_columns]
    with np.errstate(invalid="ignore", divide="ignore"):
        log_values = np.where(logged > 0, np.log(np.where(logged > 0, logged, 1.0)), np.nan)
    u = theta.copy()
    u[:, log_columns] = log_values
    log_jacobian = -np.sum(log_values, axis=1)
    return u, np.where(np.isnan(log_jacobian), -np.inf, log_jacobian)


def fit_proposal(draws, log_columns=None):
    """(μ, L, log columns) of the independence proposal from draws θ (N, D): the mean and covariance's
    Cholesky factor of u = T(θ) (:class:`IndependenceMove`).

    None when the draws cannot define one (too few, a parameter that did not move, or a log column not
    positive): the chunk then runs differential evolution alone.
    """
    draws = np.asarray(draws, float)
    n, d = draws.shape
    log_columns = np.zeros(d, bool) if log_columns is None else np.asarray(log_columns, bool)
    if n < 2 * d or not np.all(np.isfinite(draws)):
        return None
    u, _ = to_proposal_coordinates(draws, log_columns)
    if not np.all(np.isfinite(u)):
        return None
    cov = np.cov(u, rowvar=False)
    scale = np.sqrt(np.diag(cov))
    if not np.all(scale > 0):
        return None
    corr = cov / np.outer(scale, scale)
    try:
        # a little ridge on the correlations: a nearly singular estimate would give a proposal too thin to move
        chol = np.linalg.cholesky(corr + 1e-6 * np.eye(d)) * scale[:, None]
    except np.linalg.LinAlgError:
        return None
    return u.mean(axis=0), chol, log_columns


class ExchangeMove(emcee.moves.Move):
    """Label exchanges of like canopies that no channel tells apart
    (:class:`cpas_bayes.stats.cluster_form.Exchange`).

    Each walker takes one exchange drawn uniformly. An exchange is an involution with unit Jacobian and the
    same exchange undoes it, so the proposal is symmetric and q is accepted with probability
    min(1, p(q)/p(s)). Differential evolution and the independence proposal move within one pairing of
    the canopies' stages; this move crosses to the other, which without it no ensemble would visit.
    """

    def __init__(self, exchanges):
        if not exchanges:
            raise ValueError("an exchange move needs at least one exchange")
        self.exchanges = tuple(exchanges)

    def propose(self, model, state):
        s = state.coords
        n = s.shape[0]
        pick = model.random.randint(len(self.exchanges), size=n)
        q = s.copy()
        factor = np.zeros(n)     # log|∂q/∂s|: 0 for an exchange of θ, not always for one carried into u
        for e, exchange in enumerate(self.exchanges):
            rows = pick == e
            if rows.any():
                q[rows] = exchange.apply(s[rows])
                if hasattr(exchange, "log_factor"):
                    factor[rows] = exchange.log_factor(s[rows], q[rows])
        return _involution_step(self, model, state, q, np.ones(n, bool), factor)


def _involution_step(move, model, state, q, valid, factor):
    """Metropolis for deterministic proposals: each walker's q (an involution's image where ``valid``) is
    accepted with min(1, p(q)·e^factor / p(s)), factor its log|∂q/∂s|; the others stay. (state, accepted)."""
    n = q.shape[0]
    new_log_prob = np.full(n, -np.inf)
    if valid.any():
        new_log_prob[valid] = np.asarray(model.log_prob_fn(q[valid]), dtype=float)
    with np.errstate(invalid="ignore"):
        accepted = valid & (new_log_prob - state.log_prob + factor > np.log(model.random.rand(n)))  # NaN: refused
    return move.update(state, emcee.State(q, log_prob=new_log_prob), accepted), accepted


class ModeJumpMove(emcee.moves.Move):
    """Jumps between the pairings of like canopies (:class:`cpas_bayes.inference.mode_jumps.ModeJump`).

    Each walker s takes one jump drawn uniformly: the affine map that carries the Gaussian of its pairing's
    mode (Laplace's in the warm-up, the draws' moments after it) onto the other's. The map is an involution
    where it crosses between the pairings, so a q that stays in s's own pairing is refused and the rest
    accepted with min(1, p(q)·|∂q/∂s| / p(s)).
    """

    def __init__(self, jumps):
        if not jumps:
            raise ValueError("a mode-jump move needs at least one jump")
        self.jumps = tuple(jumps)

    def propose(self, model, state):
        s = state.coords
        n = s.shape[0]
        pick = model.random.randint(len(self.jumps), size=n)
        q = s.copy()
        factor = np.zeros(n)
        crossed = np.zeros(n, bool)
        for k in range(len(self.jumps)):
            rows = pick == k
            if rows.any():
                q[rows], crossed[rows], factor[rows] = self.jumps[k].apply(s[rows])
        return _involution_step(self, model, state, q, crossed, factor)


def ensemble_moves(proposal=None, exchanges=(), jumps=()):
    """emcee's moves for one chunk: differential evolution, mixed with label exchanges (a share of
    :data:`EXCHANGE_SHARE`, half of it where ``jumps`` between the pairings' modes take :data:`JUMP_SHARE`)
    when the model has any, else with the independence move when a proposal (μ, L, log columns) is given."""
    if exchanges:
        # Not with the independence move: one t fitted to draws of several pairings sits between them, and
        # was almost never accepted (a two-Drogue logger fit: 0.016 overall acceptance against 0.07).
        crossing = [(ExchangeMove(exchanges), EXCHANGE_SHARE)]
        if jumps:
            crossing = [(ExchangeMove(exchanges), EXCHANGE_SHARE / 2), (ModeJumpMove(jumps), JUMP_SHARE)]
        return [(AlignedDEMove(exchanges), 1.0 - sum(w for _, w in crossing))] + crossing
    if proposal is None:
        return [(VectorisedDEMove(), 1.0)]
    return [(VectorisedDEMove(), 1.0 - PROPOSAL_SHARE), (IndependenceMove(*proposal), PROPOSAL_SHARE)]

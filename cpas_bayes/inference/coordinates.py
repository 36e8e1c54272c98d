"""Sampler coordinates: where the ensemble moves, as opposed to the parameters the model and its priors use.

A reefed stage's drag area is what the data measure (a load cell reads CDS directly; the accelerometer
the cluster's sum), but the model holds it as a reefing ratio ε_k times the full-open drag area CDS_o.
So the posterior of (ε_k, CDS_o) is a curved ridge along ε_k·CDS_o = const, which the ensemble's moves
cross slowly. The sampler therefore moves in

    u = θ with every ε_k replaced by R_k = ε_k·CDS_o        (the stage's drag area, m²)

and targets p(u) = p(θ(u))·|∂θ/∂u|, where ε_k = R_k/CDS_o gives log|∂θ/∂u| = −Σ_k log CDS_o (the map is
triangular: each R_k column divides by its own parachute's CDS_o column). Draws are mapped back to θ,
and their log density back to θ's, before anything downstream reads them: the posterior is the same
distribution, only the sampler's path through it changes (tested: the sampled law matches in both).

``"peak_time"`` (:class:`PeakTimeCoordinates`) replaces each stage's n_p by its time from start to peak
instead, for the same reason: the data fix when a stage peaks, and n_p trades off with the stage's start
along that constraint (what the diagnosis' fits use). ``"grown"``, the fit's default, does both, and a
stage cut short before its peak moves in the drag area it has grown by then, its walkers started along
the ridge that leaves open. Every coordinate object has ``names``, ``to_sampler``, ``to_model``,
``log_jacobian`` and ``inverse`` (θ and log|∂θ/∂u| in one pass).
"""

from __future__ import annotations

import numpy as np

COORDINATES = ("drag_area", "grown", "model", "peak_time")   # R_k; R_k and fills; θ as written; times to peak
# A stage whose MAP peak comes this late in its span moves in its grown drag area: the MAP of a stage cut
# short sits at the kink where its peak meets the next start (replica 0 of the Main SBC: exactly 1.0), and the
# posterior runs from there along the cut-short ridge, which the time to peak bends (see PeakTimeCoordinates).
NEAR_CUT_OFF = 0.8
# A starting walker spread along such a stage's ridge keeps the spread point if its log density is at most this
# far below its start's (2.4 sd in one dimension): along a real ridge it is flat (0.1 nat over replica 0's).
RIDGE_DROP = 3.0
RIDGE_ROOM = 0.99   # ... and draws its drag area from its prior's quantiles between its own and this one


class DragAreaCoordinates:
    """The map θ ↔ u of the module docstring for one model (``names``, ``index``, ``chute_prefix``)."""

    def __init__(self, model):
        eps, cds = [], []
        for prefix in dict.fromkeys(model.chute_prefix):
            c = model.index.get(f"{prefix}.cds_o")
            if c is None:                       # a model without full-open drag areas has nothing to scale
                continue
            for name in model.names:
                if name.startswith(f"{prefix}.s") and name.endswith(".eps"):
                    eps.append(model.index[name])
                    cds.append(c)
        self.eps_columns = np.array(eps, dtype=int)
        self.cds_columns = np.array(cds, dtype=int)
        names = list(model.names)
        for j in eps:
            names[j] = names[j][: -len("eps")] + "cds_reefed"
        self.names = names

    def __bool__(self):
        return self.eps_columns.size > 0

    def to_sampler(self, theta):
        """u from θ (…, D)."""
        u = np.array(theta, dtype=float, copy=True)
        u[..., self.eps_columns] = u[..., self.eps_columns] * u[..., self.cds_columns]
        return u

    def to_model(self, u):
        """θ from u (…, D)."""
        theta = np.array(u, dtype=float, copy=True)
        theta[..., self.eps_columns] = theta[..., self.eps_columns] / theta[..., self.cds_columns]
        return theta

    def log_jacobian(self, u):
        """log|∂θ/∂u| (…,): −Σ_k log CDS_o; −inf where a CDS_o is not positive (outside every prior)."""
        cds = np.asarray(u, float)[..., self.cds_columns]
        positive = cds > 0
        out = -np.log(np.where(positive, cds, 1.0)).sum(axis=-1)   # no log of ≤ 0, no errstate (slow per call)
        return np.where(np.all(positive, axis=-1), out, -np.inf)

    def inverse(self, u):
        """(θ, log|∂θ/∂u|) from u (…, D)."""
        return self.to_model(u), self.log_jacobian(u)


class PeakTimeCoordinates:
    """u = θ with each stage's n_p replaced by what the data fix of its fill, and each ε_k by its drag area
    R_k = ε_k·CDS_o (:class:`DragAreaCoordinates`). A stage's fill is the time from its start to its peak,
    t_fp = n_p·s (seconds, ``…t_peak``) — or, for a stage cut short before it peaks (by the next stage's
    start, or the record's end), the drag area grown by then, g = (CDS_i − CDS_start)·(t_ref/t_f)^expopen
    with t_ref = T_ref − start (m², ``…cds_grown``; T_ref on the record's clock). Which stages are cut short,
    and their T_ref, are read at ``reference`` (the MAP) and then fixed, so the map is one bijection for the
    whole run; without a reference every stage is t_fp. Without ``drag_areas`` each ε_k stays (``"peak_time"``,
    which takes no reference).

    s = D_o·sqrt(|CDS_i − CDS_start|/CDS_o)/V_i and t_f = t_fp/(…)^(1/expopen) depend on the stage's start,
    its drag areas, its expopen and the earlier stages, not on its n_p, so the map is triangular and
    log|∂θ/∂u| = Σ log|∂n_p/∂u| − Σ_k log CDS_o: −log s for t_fp, log(n_p/(expopen·g)) for g
    (:func:`cpas_bayes.physics.inflation.stage_fill_map`). Why: the data fix when a stage peaks, and n_p
    trades off with the stage's start along that constraint (n_p = (T_peak − start)/s(start)), a curved
    ridge that the moves cross slowly; measured on a three-Main added-mass fit (45 parameters, an
    independence proposal fitted to half of 2,024 posterior draws, tried on the other half): acceptance
    0.026 in θ against 0.28 in u. A stage cut short never shows its peak: the data see only its growing
    curve, along which n_p, ε and CDS_o trade off (correlations 0.98–1.0 on slow Main SBC replicas), and g
    is what they fix.
    """

    def __init__(self, model, reference=None, drag_areas=True):
        if reference is not None and not drag_areas:
            raise ValueError("a stage's grown drag area moves beside its reefed drag area: give drag_areas=True")
        self.model = model
        self.names = list(model.names)
        P, K = len(model.chute_prefix), int(np.max(model.stages_per_chute))
        self.kind, self.ref_time = np.zeros((P, K), dtype=np.int64), np.ones((P, K))
        columns, chute, stage = [], [], []
        first = {}
        for p, prefix in enumerate(model.chute_prefix):
            first.setdefault(prefix, p)        # a composite group's stages are its first member's
        members = {prefix: [p for p, x in enumerate(model.chute_prefix) if x == prefix] for prefix in first}
        cut_short = self._cut_short(model, reference) if reference is not None else {}
        for prefix, p in first.items():
            for k in range(int(model.stages_per_chute[p])):
                name = f"{prefix}.s{k + 1}.n_p"
                if name in model.index:
                    columns.append(model.index[name])
                    chute.append(p)
                    stage.append(k)
                    if (p, k) in cut_short and _starts_before(model, f"{prefix}.s{k + 1}.start", cut_short[p, k]):
                        self.kind[members[prefix], k], self.ref_time[members[prefix], k] = 2, cut_short[p, k]
                        self.names[model.index[name]] = f"{prefix}.s{k + 1}.cds_grown"
                    else:
                        self.kind[members[prefix], k] = 1
                        self.names[model.index[name]] = f"{prefix}.s{k + 1}.t_peak"
        self.columns, self._chute, self._stage = (np.array(a, dtype=int) for a in (columns, chute, stage))
        self._grown = self.kind[self._chute, self._stage] == 2
        # and each ε_k as its drag area R_k = ε_k·CDS_o
        self.drag_area = DragAreaCoordinates(model) if drag_areas else _KeptReefingRatios(model)
        for j in self.drag_area.eps_columns:
            self.names[j] = self.drag_area.names[j]

    @staticmethod
    def _cut_short(model, reference):
        """{(p, k): t_ref} of the stages whose peak falls late in their span at ``reference`` (after
        ``NEAR_CUT_OFF`` of the time to the next stage's start, or for the last, to the record's end); t_ref
        is that next start (or the record's end): where the data last see the stage grow, and the drag area
        the next stage starts from."""
        theta = np.atleast_2d(np.asarray(reference, float))
        start = model.gather_stages(theta)["start"][0]
        record = getattr(getattr(model, "obs", None), "time", None)
        end = float(np.max(record)) if record is not None and np.size(record) else np.inf
        seen = np.full(start.shape, np.inf)       # where the data stop seeing each stage grow
        for p, n in enumerate(model.stages_per_chute):
            seen[p, :n] = np.append(start[p, 1:n], end)
        fmap = model.fill_map(theta, 0, np.where(np.isfinite(seen), seen, 0.0))   # n_p and s do not read T_ref
        t_fp, grown = fmap.n_p[0] * fmap.scale[0], fmap.grown[0]
        short = (seen > start) & np.isfinite(seen) & (t_fp > NEAR_CUT_OFF * (seen - start)) & np.isfinite(grown) & (grown > 0)
        return {(int(p), int(k)): float(seen[p, k]) for p, k in zip(*np.nonzero(short))}

    def __bool__(self):
        return self.columns.size > 0

    def ridge_columns(self):
        """[(drag-area column, CDS_o column or None, prior)] of the stages that move in their grown drag area:
        holding g, the stage's drag area runs from where it fills just by T_ref up a ridge the data cannot see.
        A reefed stage's is R_k = ε_k·CDS_o (ε_k's prior, scaled by the CDS_o column); the last stage's, cut
        short by the record's end, is CDS_o itself (its own prior, None)."""
        out, index = [], self.model.index
        for p, k in zip(self._chute[self._grown], self._stage[self._grown]):
            prefix = self.model.chute_prefix[p]
            eps, c = index.get(f"{prefix}.s{k + 1}.eps"), index.get(f"{prefix}.cds_o")
            if c is None or not hasattr(self.model, "parameters"):
                continue
            if eps is not None:
                out.append((eps, c, self.model.parameters[eps].prior))
            elif k + 1 == self.model.stages_per_chute[p]:
                out.append((c, None, self.model.parameters[c].prior))
        return out

    def spread_along_ridges(self, u, rng, density):
        """Starting walkers u (W, D) with each cut-short stage's drag area (R_k = ε_k·CDS_o, or the last stage's
        CDS_o) drawn from its prior above the walker's own, its grown drag area g held, so that the data fit is
        kept (up to the prior's RIDGE_ROOM quantile); a walker whose spread point the posterior ``density`` (in u) puts more than ``RIDGE_DROP`` below its
        start keeps its start (the data see most of a stage that peaks late in its span: no ridge to spread on).

        Why: the MAP of such a stage sits at the ridge's end (the fill just done at T_ref, the kink where the
        peak meets the next start) and its Laplace ball is tiny along the ridge, so differential evolution,
        whose steps are the walkers' differences, never learns the ridge's length: on the slow Main SBC replica
        0 every ensemble held ε at 0.161 ± 0.001 for 20,000 steps while a mode at 0.227, the truth, lay 0.1 nat
        lower along a straight line in u (145 nats below it on the line in time to peak). The convergence
        checks over independent ensembles judge the result as for any start."""
        ridges = self.ridge_columns()
        if not ridges:
            return u
        spread = np.array(u, dtype=float, copy=True)
        for j, c, prior in ridges:
            scale = spread[:, c] if c is not None else 1.0
            with np.errstate(invalid="ignore"):
                above = np.clip(prior.cdf(spread[:, j] / scale), 0.0, 1.0)
            # a start within the prior's last 1 % stays: every such walker would land on the bound alike, and
            # walkers that share a value, or a ratio to CDS_o, are linearly dependent (emcee refuses the state)
            room = np.isfinite(above) & (above < RIDGE_ROOM)
            q = rng.uniform(np.where(room, above, 0.0), RIDGE_ROOM)
            spread[:, j] = np.where(room, np.asarray(prior.ppf(q), float) * scale, spread[:, j])
        new = np.asarray(density(spread), float)
        ok = np.isfinite(new) & (new >= np.asarray(density(u), float) - RIDGE_DROP)
        return np.where(ok[:, None], spread, u)

    def _pick(self, x, values):
        return values[:, self._chute, self._stage].reshape(np.shape(x)[:-1] + (self.columns.size,))

    def to_sampler(self, theta):
        """u from θ (…, D)."""
        u = np.array(theta, dtype=float, copy=True)
        fmap = self.model.fill_map(np.reshape(theta, (-1, len(self.names))), 0, self.ref_time)
        peak = self._pick(theta, fmap.n_p * fmap.scale)
        u[..., self.columns] = np.where(self._grown, self._pick(theta, fmap.grown), peak)
        return self.drag_area.to_sampler(u)

    def inverse(self, u):
        """(θ, log|∂θ/∂u|) from u (…, D); −inf where the map is undefined (outside every prior)."""
        theta, drag_jac = self.drag_area.inverse(u)
        fmap = self.model.fill_map(np.reshape(theta, (-1, len(self.names))), self.kind, self.ref_time)
        n_p, jac = self._pick(u, fmap.n_p), self._pick(u, fmap.log_jacobian)
        theta[..., self.columns] = n_p
        total = np.sum(jac, axis=-1) + drag_jac          # NaN or ±inf wherever any term is not finite
        return theta, np.where(np.isfinite(total) & np.all(np.isfinite(n_p), axis=-1), total, -np.inf)

    def to_model(self, u):
        """θ from u (…, D)."""
        return self.inverse(u)[0]

    def log_jacobian(self, u):
        """log|∂θ/∂u| (…,)."""
        return self.inverse(u)[1]


class _KeptReefingRatios:
    """The identity in place of :class:`DragAreaCoordinates`: every ε_k stays as the model has it."""

    eps_columns = np.array([], dtype=int)

    def __init__(self, model):
        self.names = list(model.names)

    def to_sampler(self, theta):
        return np.array(theta, dtype=float, copy=True)

    def inverse(self, u):
        return np.array(u, dtype=float, copy=True), np.zeros(np.shape(u)[:-1])


def _starts_before(model, name, time):
    """Whether the stage start ``name`` lies before ``time`` under its prior (to 1 − 1e-9), so that its grown
    drag area, undefined for a start after ``time``, cuts off none of the posterior; a start the model does
    not sample is fixed, and its reference was read at it."""
    j = getattr(model, "index", {}).get(name)
    if j is None or not hasattr(model, "parameters"):
        return True
    return bool(model.parameters[j].prior.ppf(1.0 - 1e-9) < time)


def sampling_coordinates(model, choice="drag_area", reference=None):
    """The coordinates ``choice`` (one of ``COORDINATES``) for ``model``, or None where the sampler moves in
    θ itself: ``"model"``, a bare log density, or a model without reefed stages."""
    if choice not in COORDINATES:
        raise ValueError(f"coordinates must be one of {', '.join(COORDINATES)}, not {choice!r}")
    if choice == "model" or not all(hasattr(model, a) for a in ("chute_prefix", "index", "names")):
        return None
    if choice in ("peak_time", "grown"):
        if not hasattr(model, "fill_map"):
            return None
        coords = PeakTimeCoordinates(model, reference, True) if choice == "grown" else PeakTimeCoordinates(model,
                                                                                                          None, False)
    else:
        coords = DragAreaCoordinates(model)
    return coords if coords else None


class SamplerTarget:
    """The log density the ensemble samples: ``model``'s posterior in ``coords``' u, with the Jacobian.

    Callable on (B, D) like the model (emcee's ``vectorize=True``); carries what the sampler reads of the
    model: ``names`` (u's), ``log_scale`` (R_k on the log scale where ε_k is) and ``exchanges`` (each label
    exchange carried into u, :class:`_ExchangeInSampler`).
    """

    def __init__(self, model, coords):
        self.model, self.coords = model, coords
        self.names = coords.names

    @property
    def log_scale(self):
        return getattr(self.model, "log_scale", None)

    def exchanges(self):
        exchanges = getattr(self.model, "exchanges", None)
        return [_ExchangeInSampler(e, self.coords) for e in exchanges()] if exchanges is not None else []

    def __call__(self, u):
        u = np.atleast_2d(np.asarray(u, float))
        theta, jac = self.coords.inverse(u)
        ok = np.isfinite(jac)
        if ok.all():
            return self.model(theta) + jac
        out = np.full(u.shape[0], -np.inf)
        if ok.any():
            out[ok] = self.model(theta[ok]) + jac[ok]
        return out


class _ExchangeInSampler:
    """A label exchange of θ (:class:`cpas_bayes.stats.cluster_form.Exchange`) acting on u: u → g(T(g⁻¹(u))).

    Still an involution with unit Jacobian: |∂u/∂θ| = Π CDS_o over the reefed stages, and an exchange either
    leaves every CDS_o in place (a reefed stage) or swaps two like parachutes' CDS_o, whose reefed stages
    are equally many (the last stage). At a reefed stage it is now a plain swap of the two drag areas R_k.
    The stage starts, which tell the pairing, are the same columns in u as in θ.
    """

    def __init__(self, exchange, coords):
        self.exchange, self.coords = exchange, coords
        self.order = exchange.order

    def apply(self, u):
        return self.coords.to_sampler(self.exchange.apply(self.coords.to_model(u)))

    def log_factor(self, u, u_new):
        """log|∂u′/∂u| of the exchange in u, the Metropolis ratio's factor: |∂u/∂θ| need not be the same at
        θ and at its exchange (peak-time coordinates: a stage's scale reads the drag area held from the
        stage before, which the exchange of one stage does not carry along)."""
        return self.coords.log_jacobian(u) - self.coords.log_jacobian(u_new)

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

The other choice, ``"peak_time"`` (:class:`PeakTimeCoordinates`), replaces each stage's n_p by its time
from start to peak, for the same reason: the data fix when a stage peaks, and n_p trades off with the
stage's start along that constraint. Every coordinate object has ``names``, ``to_sampler``,
``to_model``, ``log_jacobian`` and ``inverse`` (θ and log|∂θ/∂u| in one pass).
"""

from __future__ import annotations

import numpy as np

COORDINATES = ("drag_area", "model", "peak_time")   # reefed drag areas R_k, θ as the model has it, times to peak


class DragAreaCoordinates:
    """The map θ ↔ u of the module docstring for one model (``names``, ``index``, ``chute_prefix``)."""

    def __init__(self, model):
        eps, cds = [], []
        for prefix in dict.fromkeys(model.chute_prefix):
            c = model.index[f"{prefix}.cds_o"]
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
        with np.errstate(divide="ignore", invalid="ignore"):
            out = -np.log(cds).sum(axis=-1)
        return np.where(np.all(cds > 0, axis=-1), out, -np.inf)

    def inverse(self, u):
        """(θ, log|∂θ/∂u|) from u (…, D)."""
        return self.to_model(u), self.log_jacobian(u)


class PeakTimeCoordinates:
    """u = θ with each stage's n_p replaced by its time from start to peak, t_fp = n_p·s (seconds).

    s = D_o·sqrt(|CDS_i − CDS_start|/CDS_o)/V_i (:meth:`TestModel.fill_scales`) depends on the stage's
    start, its drag areas and the earlier stages, not on its n_p, so the map is triangular and
    log|∂θ/∂u| = −Σ log s. Why: the data fix when a stage peaks, and n_p trades off with the stage's start
    along that constraint (n_p = (T_peak − start)/s(start)); the posterior of (start, n_p, expopen) is a
    curved ridge that the moves cross slowly. Measured on a three-Main added-mass fit (45 parameters, an
    independence proposal fitted to half of 2,024 posterior draws, tried on the other half): acceptance
    0.026 in θ against 0.28 in u.
    """

    def __init__(self, model):
        self.model = model
        self.names = list(model.names)
        columns, chute, stage = [], [], []
        first = {}
        for p, prefix in enumerate(model.chute_prefix):
            first.setdefault(prefix, p)        # a composite group's stages are its first member's
        for prefix, p in first.items():
            for k in range(int(model.stages_per_chute[p])):
                name = f"{prefix}.s{k + 1}.n_p"
                if name in model.index:
                    columns.append(model.index[name])
                    chute.append(p)
                    stage.append(k)
                    self.names[model.index[name]] = f"{prefix}.s{k + 1}.t_peak"
        self.columns, self._chute, self._stage = (np.array(a, dtype=int) for a in (columns, chute, stage))

    def __bool__(self):
        return self.columns.size > 0

    def _scales(self, x, peak_times):
        flat = np.asarray(x, float).reshape(-1, len(self.names))
        n_p, scale = self.model.fill_scales(flat, peak_times=peak_times)
        pick = (slice(None), self._chute, self._stage)
        shape = np.shape(x)[:-1] + (self.columns.size,)
        return n_p[pick].reshape(shape), scale[pick].reshape(shape)

    def to_sampler(self, theta):
        """u from θ (…, D)."""
        u = np.array(theta, dtype=float, copy=True)
        _, scale = self._scales(theta, False)
        u[..., self.columns] = u[..., self.columns] * scale
        return u

    def inverse(self, u):
        """(θ, log|∂θ/∂u|) from u (…, D); −inf where a scale is not a positive number (outside every prior)."""
        theta = np.array(u, dtype=float, copy=True)
        n_p, scale = self._scales(u, True)
        theta[..., self.columns] = n_p
        good = np.all(np.isfinite(scale) & (scale > 0), axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            jac = -np.log(np.where(good[..., None], scale, 1.0)).sum(axis=-1)
        return theta, np.where(good, jac, -np.inf)

    def to_model(self, u):
        """θ from u (…, D)."""
        return self.inverse(u)[0]

    def log_jacobian(self, u):
        """log|∂θ/∂u| (…,): −Σ log s."""
        return self.inverse(u)[1]


def sampling_coordinates(model, choice="drag_area"):
    """The coordinates ``choice`` (one of ``COORDINATES``) for ``model``, or None where the sampler moves in
    θ itself: ``"model"``, a bare log density, or a model without reefed stages."""
    if choice not in COORDINATES:
        raise ValueError(f"coordinates must be one of {', '.join(COORDINATES)}, not {choice!r}")
    if choice == "model" or not all(hasattr(model, a) for a in ("chute_prefix", "index", "names")):
        return None
    if choice == "peak_time":
        if not hasattr(model, "fill_scales"):
            return None
        coords = PeakTimeCoordinates(model)
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
        out = np.full(u.shape[0], -np.inf)
        ok = np.isfinite(jac)
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

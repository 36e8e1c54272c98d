"""One parameter's population: grid hyper-posterior, population predictive and the family choice.

Hyper-priors and the hyper-posterior
------------------------------------
Hyper-priors are weak and proper: loc flat over the tests' medians ± 10
spreads (spread = sd of the canopies' posterior medians + the largest
posterior sd; the bound keeps the truncated normal proper, whose likelihood is
flat along μ as σ → ∞); scale half-Cauchy above the floor
(:func:`~cpas_bayes.population.reweighting.scale_floor`),
p(σ) = 2/(π s₀ (1 + σ²/s₀²)), s₀ = the width of the fit prior in the family's
coordinate (else twice the tests' spread); beta also needs ν > 0.

The hyper-posterior p(λ | d) ∝ p(λ)·L(λ), L(λ) from the reweighting sums of
:mod:`cpas_bayes.population.reweighting`, is evaluated on grids in
(loc, log scale): a coarse rectangle grown until it holds every cell within
e^−20 of the maximum of the full or of any leave-one-test-out hyper-posterior,
then twice a "sheared" grid whose every log σ row has its own location range
(hierarchical posteriors are funnels: the location is known to ∝ σ + the
tests' widths). Draws are cells drawn by posterior mass, jittered uniformly
within the cell; population-predictive draws are λ from those, then x from
p(x | λ).

Choosing the family: leave-one-test-out predictive density
-----------------------------------------------------------
elpd_LOO = Σ_i log p(d_i | d_−i), with p(d_i | d_−i) = ∫ L_i(λ) p(λ | d_−i) dλ.
On the grid this needs no refit: p(λ | d_−i) ∝ p(λ | d)/L_i(λ), so::

    log p(d_i | d_−i) = logsumexp_g(log post_g) − logsumexp_g(log post_g − log L_i(λ_g))

with log post_g the cell's log mass, exactly up to the grid (tested against
refitting without test i) (the constants Z_i are the same for every family, so
the differences are meaningful). The family with the largest elpd_LOO is
chosen; all values are reported.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy import special

from cpas_bayes.population.families import BetaFamily, Family, make_family
from cpas_bayes.population.reweighting import (ESS_MIN, PerTestDraws, PoolWarning, effective_sample_sizes,
                                               log_test_likelihoods, prepare_reweighting, scale_floor)

GRID_THRESHOLD = 20.0      # keep grid points within e^-20 of the maximum
LOC_BOX_SPREADS = 10.0     # the flat location hyper-prior spans the tests' medians ± 10 spreads


def half_cauchy_logpdf(sigma, s0):
    """log of p(σ) = 2/(π s₀ (1 + σ²/s₀²)), σ > 0."""
    return math.log(2.0 / (math.pi * s0)) - np.log1p((sigma / s0) ** 2)


@dataclass
class ParameterPool:
    """Hyper-posterior and population predictive of one parameter under one family."""

    family: Family
    hyper_draws: np.ndarray        # (N, 2): loc, scale
    hyper_median: np.ndarray       # (2,)
    elpd_loo: float
    elpd_pointwise: np.ndarray     # (T,)
    ess: np.ndarray                # (T,) smallest canopy ESS of each test at hyper_median
    low_ess: list                  # "test canopy" labels with ESS < ess_min
    mean_draws: np.ndarray         # (N,) population mean at each hyper draw
    sd_draws: np.ndarray           # (N,) population sd at each hyper draw
    predictive: np.ndarray         # (N,) population-predictive draws
    tests: list
    scale_floor: float = 0.0       # lower end of the scale hyper-prior (see :func:`scale_floor`)
    grid: dict = field(default_factory=dict, repr=False)
    notes: list = field(default_factory=list)

    @property
    def hyper_names(self):
        return self.family.hyper_names

    def interval(self, what="mean", level=0.90):
        """(low, median, high) of the hyper-posterior of the population ``mean`` or ``sd``."""
        x = self.mean_draws if what == "mean" else self.sd_draws
        a = (1 - level) / 2
        return tuple(float(v) for v in np.quantile(x, [a, 0.5, 1 - a]))


def default_hyper_scale(data, family):
    """s₀ of the half-Cauchy scale hyper-prior when the fit prior gives none: twice the spread of the
    canopies' posterior medians plus their median width (in the family's coordinate)."""
    medians, widths = data.summaries(family)
    spread = float(np.std(medians)) if medians.size > 1 else 0.0
    value = 2.0 * (spread + float(np.median(widths)))
    return value if value > 0 else 1.0


def _location_prior_box(data, family):
    """Support of the flat hyper-prior on ``loc``: the tests' medians ± 10 spreads, within the family's limits.

    spread = sd of the canopies' posterior medians + their largest posterior sd
    (in the family's coordinate). Bounding the location keeps the hyper-posterior
    proper where the likelihood is flat along it (a truncated normal with
    σ → ∞ tends to the uniform whatever μ is).
    """
    medians, widths = data.summaries(family)
    spread = (float(np.std(medians)) if medians.size > 1 else 0.0) + float(np.max(widths))
    if spread <= 0:
        spread = 1e-3 * max(1.0, float(np.max(np.abs(medians))))
    lo, hi = float(np.min(medians)) - LOC_BOX_SPREADS * spread, float(np.max(medians)) + LOC_BOX_SPREADS * spread
    lim = family.loc_limits()
    margin = 1e-9 * (lim[1] - lim[0]) if math.isfinite(lim[1] - lim[0]) else 0.0
    return (max(lo, lim[0] + margin), min(hi, lim[1] - margin)), spread, medians


def _initial_box(data, family, floor):
    """First grid: the medians ± 4 spreads (inside the prior box); σ from max(1e-3·6 spreads, σ_floor)
    to 6 spreads."""
    (lo_box, hi_box), spread, medians = _location_prior_box(data, family)
    lo_loc = max(float(np.min(medians)) - 4 * spread, lo_box)
    hi_loc = min(float(np.max(medians)) + 4 * spread, hi_box)
    scale_hi = 6 * spread
    if isinstance(family, BetaFamily):
        scale_hi = min(scale_hi, 0.5 * family.width)
    scale_lo = max(1e-3 * scale_hi, floor)
    scale_hi = max(scale_hi, 10 * scale_lo)
    return [lo_loc, hi_loc, math.log(scale_lo), math.log(scale_hi)], (lo_box, hi_box)


def _evaluate_points(data, family, prepared, hyper_scale, loc, log_scale, dloc, dls, row):
    """Hyper-posterior mass of grid cells centred at (loc, log σ) with sides (dloc, dls).

    log_post = log p(λ) + Σ_i log L_i(λ) + log(cell area): flat loc,
    half-Cauchy σ, and the Jacobian σ of a grid uniform in log σ.
    """
    scale = np.exp(log_scale)
    ok = family.feasible(loc, scale)
    log_lik = np.full((loc.size, data.n_tests), -np.inf)
    if ok.any():
        log_lik[ok] = log_test_likelihoods(data, family, loc[ok], scale[ok], prepared)
    log_hyper_prior = half_cauchy_logpdf(scale, hyper_scale) + log_scale
    total = log_lik.sum(axis=1)
    log_post = np.where(ok & np.isfinite(total), log_hyper_prior + total + np.log(dloc * dls), -np.inf)
    return {"loc": loc, "log_scale": log_scale, "scale": scale, "dloc": dloc, "dls": dls, "row": row,
            "log_lik": log_lik, "log_post": log_post}


def _rectangular_grid(data, family, prepared, hyper_scale, box, n):
    locs = np.linspace(box[0], box[1], n)
    log_scales = np.linspace(box[2], box[3], n)
    loc, log_scale = (a.ravel() for a in np.meshgrid(locs, log_scales, indexing="ij"))
    row = np.tile(np.arange(n), n)
    dloc = np.full(loc.size, (box[1] - box[0]) / (n - 1))
    return _evaluate_points(data, family, prepared, hyper_scale, loc, log_scale, dloc,
                            (box[3] - box[2]) / (n - 1), row)


def _occupied(g):
    """Cells within e^−20 of the maximum of the full or of any leave-one-test-out hyper-posterior."""
    ok = np.isfinite(g["log_post"])
    keep = np.zeros(ok.shape, dtype=bool)
    lp = g["log_post"][ok]
    loo = lp[:, None] - g["log_lik"][ok]
    keep[ok] = (lp > lp.max() - GRID_THRESHOLD) | np.any(loo > loo.max(axis=0) - GRID_THRESHOLD, axis=1)
    return keep


def _sheared_grid(data, family, prepared, hyper_scale, g, loc_box, log_floor, n):
    """A finer grid with its own location range in every log σ row.

    Hierarchical hyper-posteriors are funnels: the location is known to a
    width ∝ σ + (the tests' own widths), so one rectangle resolves either the
    narrow neck or the wide mouth, not both. Each row of ``g``'s occupied cells
    gives a location interval (padded by that row's cell); the n new rows
    (uniform in log σ over the occupied rows, padded by one) take the union of
    the intervals of the two source rows around them, with n cells each.
    """
    keep = _occupied(g)
    rows = np.unique(g["row"][keep])
    ls_rows = np.array([g["log_scale"][g["row"] == r][0] for r in rows])
    lo_rows = np.array([np.min(g["loc"][keep & (g["row"] == r)] - g["dloc"][keep & (g["row"] == r)])
                        for r in rows])
    hi_rows = np.array([np.max(g["loc"][keep & (g["row"] == r)] + g["dloc"][keep & (g["row"] == r)])
                        for r in rows])
    ls_lo, ls_hi = max(ls_rows.min() - g["dls"], log_floor), ls_rows.max() + g["dls"]
    new_ls = np.linspace(ls_lo, ls_hi, n)
    # source rows bracketing each new row (the nearest at the ends)
    j1 = np.clip(np.searchsorted(ls_rows, new_ls), 0, rows.size - 1)
    j0 = np.clip(j1 - 1, 0, rows.size - 1)
    lo = np.maximum(np.minimum(lo_rows[j0], lo_rows[j1]), loc_box[0])
    hi = np.minimum(np.maximum(hi_rows[j0], hi_rows[j1]), loc_box[1])
    frac = np.linspace(0.0, 1.0, n)
    loc = (lo[:, None] + (hi - lo)[:, None] * frac[None, :]).ravel()
    log_scale = np.repeat(new_ls, n)
    dloc = np.repeat((hi - lo) / (n - 1), n)
    row = np.repeat(np.arange(n), n)
    return _evaluate_points(data, family, prepared, hyper_scale, loc, log_scale, dloc, new_ls[1] - new_ls[0], row)


def grid_hyper_posterior(data, family, prepared, hyper_scale, floor=0.0, coarse=28, fine=40, max_expansions=5):
    """Coarse rectangular grid grown until it holds the mass, then two sheared refinements.

    "Occupied" cells are those within e^−20 of the maximum of the full
    hyper-posterior *or of any leave-one-test-out one* (log post − log L_i), so
    that the final grid also holds each p(λ | d_−i) the LOO criterion
    integrates over (with few tests they can sit far from p(λ | d)). The
    coarse grid grows (by its own width) on any side where an occupied cell
    touches the edge — up to the location prior's box, and not on the
    small-scale side, where the half-Cauchy prior times the log-grid Jacobian σ
    makes the mass vanish. Then :func:`_sheared_grid` twice (the second pass
    sharpens the row intervals the coarse cells could only bracket).
    """
    box, loc_box = _initial_box(data, family, floor)
    log_floor = box[2]
    notes = []
    for attempt in range(max_expansions + 1):
        g = _rectangular_grid(data, family, prepared, hyper_scale, box, coarse)
        if not np.isfinite(g["log_post"]).any():
            raise ValueError(f"the {family.name} population has zero likelihood everywhere on the grid")
        il, js = np.nonzero(_occupied(g).reshape(coarse, coarse))
        width_loc, width_ls = box[1] - box[0], box[3] - box[2]
        grow = False
        if il.min() == 0 and box[0] > loc_box[0]:
            box[0], grow = max(box[0] - width_loc, loc_box[0]), True
        if il.max() == coarse - 1 and box[1] < loc_box[1]:
            box[1], grow = min(box[1] + width_loc, loc_box[1]), True
        if js.max() == coarse - 1:
            box[3], grow = box[3] + 0.5 * width_ls, True
        if not grow:
            break
        if attempt == max_expansions:
            notes.append(f"{family.name}: hyper-posterior of the scale still reaches the grid edge after "
                         f"{max_expansions} expansions (weakly identified)")
    for _ in range(2):
        g = _sheared_grid(data, family, prepared, hyper_scale, g, loc_box, log_floor, fine)
    g["box"] = [float(np.min(g["loc"])), float(np.max(g["loc"])), float(np.min(g["log_scale"])),
                float(np.max(g["log_scale"]))]
    g["loc_prior_box"] = loc_box
    g["log_floor"] = log_floor
    return g, notes


def _grid_loo(log_post, log_lik):
    """Exact leave-one-test-out elpd on the grid: log Σ post − log Σ post/L_i, per test."""
    ok = np.isfinite(log_post)
    lp, ll = log_post[ok], log_lik[ok]
    return special.logsumexp(lp) - special.logsumexp(lp[:, None] - ll, axis=0)


def _draw_from_grid(g, family, n, rng):
    """Cells drawn by posterior mass, each draw jittered uniformly within its cell."""
    ok = np.isfinite(g["log_post"])
    idx = np.flatnonzero(ok)
    p = np.exp(g["log_post"][idx] - np.max(g["log_post"][idx]))
    pick = idx[rng.choice(idx.size, size=n, p=p / p.sum())]
    loc = g["loc"][pick] + g["dloc"][pick] * (rng.uniform(size=n) - 0.5)
    loc = np.clip(loc, *g.get("loc_prior_box", (-np.inf, np.inf)))
    scale = np.exp(np.maximum(g["log_scale"][pick] + g["dls"] * (rng.uniform(size=n) - 0.5),
                              g.get("log_floor", -np.inf)))
    bad = ~family.feasible(loc, scale)
    loc[bad], scale[bad] = g["loc"][pick[bad]], g["scale"][pick[bad]]
    return np.column_stack([loc, scale])


def _hyper_median(family, draws):
    med = np.median(draws, axis=0)
    if family.feasible(med[0], med[1]):
        return med
    return draws[np.argmin(np.sum(((draws - med) / draws.std(axis=0)) ** 2, axis=1))]


def _pool_stacked(data: PerTestDraws, family: Family, rng, hyper_scale=None, n_draws=4000, ess_min=ESS_MIN):
    """Grid hyper-posterior, exact grid LOO, hyper draws, ESS and predictive of one family (see the module doc)."""
    prepared = prepare_reweighting(data, family)
    hyper_scale = hyper_scale if hyper_scale is not None else default_hyper_scale(data, family)
    floor = scale_floor(data, family, ess_min)
    g, notes = grid_hyper_posterior(data, family, prepared, hyper_scale, floor)
    elpd = _grid_loo(g["log_post"], g["log_lik"])
    hyper = _draw_from_grid(g, family, n_draws, rng)
    med = _hyper_median(family, hyper)
    ess_canopy = effective_sample_sizes(data, family, med[0], med[1])
    low = [f"{t} {c}" for t, cs, es in zip(data.tests, data.canopy_labels(), ess_canopy)
           for c, e in zip(cs, es) if e < ess_min]
    mean, sd = family.moments(hyper[:, 0], hyper[:, 1])
    predictive = family.ppf(rng.uniform(size=n_draws), hyper[:, 0], hyper[:, 1])
    return ParameterPool(family=family, hyper_draws=hyper, hyper_median=med, elpd_loo=float(elpd.sum()),
                         elpd_pointwise=elpd, ess=np.nanmin(ess_canopy, axis=1), low_ess=low,
                         mean_draws=np.asarray(mean, float), sd_draws=np.asarray(sd, float),
                         predictive=np.asarray(predictive, float), tests=list(data.tests), scale_floor=floor,
                         grid=g, notes=notes)


def pool_parameter(samples_per_test, log_prior_per_test, family, rng, *, bounds=(-math.inf, math.inf),
                   hyper_scale=None, n_draws=4000, max_samples=500, ess_min=ESS_MIN, tests=None) -> ParameterPool:
    """Population of one parameter from per-test posterior draws, under one ``family``.

    ``samples_per_test[i]``: test i's draws, (S,) or (C, S) for C canopies that
    share the draw index; ``log_prior_per_test[i]``: log π_i at those draws.
    ``bounds``: the family's support (truncation of ``truncnormal``, range of
    ``beta``). ``hyper_scale``: s₀ of the half-Cauchy prior on the scale (default:
    twice the spread of the tests' medians plus their typical width).
    Returns a :class:`ParameterPool`; see the module docstring for the method.
    A test whose effective sample size at the inferred population is below
    ``ess_min`` is listed in ``low_ess`` and warned about (:class:`PoolWarning`).
    """
    data = samples_per_test if isinstance(samples_per_test, PerTestDraws) else PerTestDraws.from_arrays(
        samples_per_test, log_prior_per_test, rng, max_samples, tests)
    fam = make_family(family, *bounds)
    pool = _pool_stacked(data, fam, rng, hyper_scale, n_draws, ess_min)
    if pool.low_ess:
        warnings.warn(f"ESS < {ess_min:g} at the inferred {fam.name} population for {', '.join(pool.low_ess)}: "
                      "their reweighting sums are noisy", PoolWarning, stacklevel=2)
    return pool


@dataclass
class FamilySelection:
    """Every candidate family's pool, their elpd_LOO and the chosen family."""

    pools: dict
    criterion: dict          # family name -> elpd_LOO (sum over tests)
    chosen: str

    @property
    def pool(self) -> ParameterPool:
        return self.pools[self.chosen]


def select_family(samples_per_test, log_prior_per_test, families, rng, *, bounds=(-math.inf, math.inf),
                  hyper_scale=None, n_draws=4000, max_samples=500, ess_min=ESS_MIN, tests=None) -> FamilySelection:
    """Pool under each of ``families`` on the same draws; choose the largest leave-one-test-out elpd.

    ``bounds`` and ``hyper_scale`` may be one value for all families or
    {family name: value}. A family that cannot describe the draws (draws
    outside its support) is skipped with a :class:`PoolWarning`.
    """
    data = samples_per_test if isinstance(samples_per_test, PerTestDraws) else PerTestDraws.from_arrays(
        samples_per_test, log_prior_per_test, rng, max_samples, tests)
    pools = {}
    for name in families:
        fam_bounds = bounds.get(name, (-math.inf, math.inf)) if isinstance(bounds, dict) else bounds
        fam = make_family(name, *fam_bounds)
        s0 = hyper_scale.get(fam.name) if isinstance(hyper_scale, dict) else hyper_scale
        try:
            pools[fam.name] = _pool_stacked(data, fam, rng, s0, n_draws, ess_min)
        except ValueError as exc:
            warnings.warn(f"{fam.name} family skipped: {exc}", PoolWarning, stacklevel=2)
    if not pools:
        raise ValueError("no candidate family could describe the draws")
    criterion = {k: p.elpd_loo for k, p in pools.items()}
    chosen = max(criterion, key=criterion.get)
    return FamilySelection(pools, criterion, chosen)

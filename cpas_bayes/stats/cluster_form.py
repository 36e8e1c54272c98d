"""Cluster forms of the model: each parachute individually, or a composite of lockstep canopies.

``individual`` (the default, the seed's choice) gives each parachute of a
cluster its own inflation parameters, named ``<chute>.cds_o`` and
``<chute>.s<k>.<name>``. ``composite`` is the "one summed canopy" model: the
parachutes of one kind, inflation mode, diameter and stage count inflate in
lockstep on ONE set of inflation parameters (cds_o; per stage start, n_p,
expopen, ck, tk, eps), named ``cluster.<kind>.cds_o`` and
``cluster.<kind>.s<k>.<name>``; when one kind forms several such groups
(say two canopy sizes) they are ``cluster.<kind>-<j>``, j = 1, 2, ... in
parachute order. Every canopy of a group has the shared drag area, so the
accelerometer sees n times it and each load cell sees it.

:class:`cpas_bayes.stats.model.TestModel` ties the parameters through its gather
arrays alone (several parachutes read the same θ columns), so its numpy
pipeline and the compiled kernel need nothing else.

The prior of a tied stage start is Normal(mean of the stated starts,
sqrt(mean of the stated sd² + variance of the stated starts)): the stated
uncertainty widened by the spread between the canopies. For one parachute it
is that parachute's own prior, so the composite model of a single canopy is the
individual one under other names.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cpas_bayes.stats.distributions import Normal

CLUSTER_FORMS = ("individual", "composite")


def like_key(parachute):
    """What makes parachutes alike (one composite group, or exchangeable): kind, inflation, diameter, stages."""
    return parachute.kind, parachute.inflation, parachute.diameter, len(parachute.stages)


def chute_prefixes(parachutes, cluster):
    """The parameter prefix of each parachute: its id, or in the composite form its group's name."""
    if cluster not in CLUSTER_FORMS:
        raise ValueError(f"cluster must be one of {CLUSTER_FORMS}, got {cluster!r}")
    if cluster == "individual":
        return [p.id for p in parachutes]
    keys = [like_key(p) for p in parachutes]
    groups = list(dict.fromkeys(keys))
    per_kind = {}
    for key in groups:
        per_kind.setdefault(key[0], []).append(key)
    names = {key: f"cluster.{key[0]}" if len(per_kind[key[0]]) == 1
             else f"cluster.{key[0]}-{per_kind[key[0]].index(key) + 1}" for key in groups}
    return [names[key] for key in keys]


def start_prior(stages):
    """Prior of a stage start shared by ``stages`` (one stage of each parachute of a group)."""
    starts = np.array([s.start for s in stages])
    sd = math.sqrt(np.mean([s.start_sigma ** 2 for s in stages]) + starts.var())
    return Normal(float(starts.mean()), max(sd, 1e-3))


# ---------------------------------------------------------------------------
# label exchanges of like canopies that no channel tells apart


@dataclass(frozen=True)
class Exchange:
    """One label exchange between two like parachutes at one stage: an involution of θ with unit Jacobian.

    θ'[swap_a] = θ[swap_b] and θ'[swap_b] = θ[swap_a] (the stage's start, expopen, ck, tk, and at a
    stage whose drag area is CDS_o itself the CDS_o and n_p); then θ'[dst] = θ[src]·(θ[num]/θ[den])^power
    for the rest: at a reefed stage eps_i' = eps_j·CDS_o,j/CDS_o,i, so that the stage's drag area eps·CDS_o
    changes hands, and n_p,i' = n_p,j·(CDS_o,i/CDS_o,j)^½, so that its fill time
    t_f = n·D_o·sqrt(eps·CDS_o/CDS_o)/V does too (exact at a first stage: the cluster's drag area is the
    same until a canopy leaves it); at the last stage CDS_o changes hands and the other stages stay where
    they were: eps·CDS_o kept, and n_p,i' = n_p,i·(CDS_o,j/CDS_o,i)^½ so that their fill times are kept
    too. The exchanges of every stage of a pair, composed, are then a plain relabelling of the canopies.
    Each rescaled pair multiplies to what it was, so |∂θ'/∂θ| = 1 and the Metropolis ratio of the exchange
    is the posterior ratio alone.
    """

    pair: tuple
    stage: int
    swap_a: np.ndarray
    swap_b: np.ndarray
    dst: np.ndarray
    src: np.ndarray
    num: np.ndarray
    den: np.ndarray
    power: np.ndarray
    order: tuple | None = None   # the θ columns of the two stage starts: which pairing a walker is in

    def apply(self, theta):
        """θ' of each row of ``theta`` (B, D); applying it twice gives θ back."""
        theta = np.asarray(theta, float)
        out = theta.copy()
        out[:, self.swap_a], out[:, self.swap_b] = theta[:, self.swap_b], theta[:, self.swap_a]
        if self.dst.size:
            out[:, self.dst] = theta[:, self.src] * (theta[:, self.num] / theta[:, self.den]) ** self.power
        return out


def stage_exchanges(parachutes, column):
    """The :class:`Exchange` of every stage of every pair of like parachutes without a load cell.

    ``column(i, field)`` is the θ column of parachute i's ``field`` (``cds_o``, ``s<k>.<name>``) or None.
    Like: same kind, inflation, diameter and stage count. Without a channel of their own (a logger bundle,
    a cluster without load cells) the data see only their sum, so which canopy opened first at a stage is
    not known: the posterior holds both pairings, and an exchange is the move that crosses between them.
    """
    out = []
    for i, p in enumerate(parachutes):
        for j in range(i + 1, len(parachutes)):
            o = parachutes[j]
            if p.load_cell or o.load_cell or like_key(p) != like_key(o):
                continue
            ci, cj = column(i, "cds_o"), column(j, "cds_o")
            eps = [(column(i, f"s{m + 1}.eps"), column(j, f"s{m + 1}.eps")) for m in range(len(p.stages))]
            # each stage's fill constant (n_p, or n in the other parameterisation), a column of each or None
            fills = [next((c for c in ((column(i, f"s{m + 1}.{f}"), column(j, f"s{m + 1}.{f}")) for f in ("n_p", "n"))
                           if None not in c), None) for m in range(len(p.stages))]
            for k in range(len(p.stages)):
                swaps = [(column(i, f"s{k + 1}.{f}"), column(j, f"s{k + 1}.{f}"))
                         for f in ("start", "expopen", "ck", "tk")]
                swaps = [s for s in swaps if None not in s]
                rescale = []                       # (dst, src, num, den, power)
                ei, ej = eps[k]
                fill = fills[k]
                has_cds_o = None not in (ci, cj)
                if has_cds_o and None not in (ei, ej):     # reefed: eps·CDS_o and the fill time change hands
                    rescale += [(ei, ej, cj, ci, 1.0), (ej, ei, ci, cj, 1.0)]
                    if fill is not None:
                        rescale += [(fill[0], fill[1], ci, cj, 0.5), (fill[1], fill[0], cj, ci, 0.5)]
                elif has_cds_o and (ei, ej) == (None, None):   # the drag area is CDS_o: it changes hands,
                    swaps += [(ci, cj)] + ([fill] if fill is not None else [])   # the other stages' stay
                    for m, (em_i, em_j) in enumerate(eps):
                        if m != k and None not in (em_i, em_j):
                            rescale += [(em_i, em_i, ci, cj, 1.0), (em_j, em_j, cj, ci, 1.0)]
                            # and its fill time: t_f ∝ n·sqrt(ΔCDS/CDS_o) with ΔCDS kept and CDS_o changed
                            fm = fills[m]
                            if fm is not None:
                                rescale += [(fm[0], fm[0], cj, ci, 0.5), (fm[1], fm[1], ci, cj, 0.5)]
                else:
                    swaps += [c for c in ((ei, ej), fill) if c is not None and None not in c]
                if not swaps and not rescale:
                    continue
                a, b = (np.array(c, int) for c in zip(*swaps)) if swaps else (np.empty(0, int),) * 2
                cols = list(zip(*rescale)) if rescale else [()] * 5
                r = [np.array(c, int) for c in cols[:4]]
                starts = (column(i, f"s{k + 1}.start"), column(j, f"s{k + 1}.start"))
                out.append(Exchange((p.id, o.id), k, a, b, *r, np.array(cols[4], float),
                                    starts if None not in starts else None))
    return out

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

import numpy as np

from cpas_bayes.stats.distributions import Normal

CLUSTER_FORMS = ("individual", "composite")


def chute_prefixes(parachutes, cluster):
    """The parameter prefix of each parachute: its id, or in the composite form its group's name."""
    if cluster not in CLUSTER_FORMS:
        raise ValueError(f"cluster must be one of {CLUSTER_FORMS}, got {cluster!r}")
    if cluster == "individual":
        return [p.id for p in parachutes]
    keys = [(p.kind, p.inflation, p.diameter, len(p.stages)) for p in parachutes]
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

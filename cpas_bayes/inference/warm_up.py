"""The adaptive independence proposal's warm-up: how long, and the proposals it fits.

The ESS rule's ensembles (:func:`cpas_bayes.inference.fit.run_ensembles`) advance in lockstep chunks; under the
adaptive (or pooled) proposal the first chunks are a warm-up whose draws are dropped: one chunk of differential
evolution, then adaptation chunks, each with the multivariate-t independence proposal
(:class:`cpas_bayes.inference.moves.IndependenceMove`) fitted to the draws of the chunk before. The proposal is
then frozen, so every kept draw comes from one fixed kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

WARM_UPS = ("plateau", "fixed")

# warm_up="plateau": the warm-up ends when the independence proposal stops improving, the chunk's acceptance
# risen by less than this share over the chunk before's (on the examples, seed 0, 125-step chunks: the Drogue's
# rose 0.20 → 0.26 → 0.34 → 0.38 → 0.41 → 0.42, the Main's by 8–30 % a chunk until its sixth), after at least
# MIN_ADAPTATIONS chunks and at most MAX_ADAPTATIONS (a posterior the proposal never fits keeps DE's share).
ACCEPTANCE_RTOL = 0.10
MIN_ADAPTATIONS = 2
MAX_ADAPTATIONS = 12
# Its chunks are at least this many stored steps: each proposal is fitted to one chunk's draws, 25·W ≈ 50·D of
# them (W = 2·D + 2 walkers). At 12 stored steps (check_every 250) the composite two-Drogue fit froze a proposal
# that left τ at 93 steps and ran to max_steps; at 25 it stopped at 2,750 steps, as under the fixed warm-up.
PLATEAU_CHUNK = 25


@dataclass(frozen=True)
class Schedule:
    """The lockstep chunks in stored steps. ``de``: the differential-evolution chunk that starts the adaptive
    proposal's warm-up (0: no warm-up, DE alone in chunks of ``step``); ``step``: each adaptation and check chunk;
    the warm-up has ``adaptations`` = (fewest, most) adaptation chunks."""

    de: int
    step: int
    adaptations: tuple = (MIN_ADAPTATIONS, MAX_ADAPTATIONS)


def warm_up_schedule(options):
    """The chunks of ``options``' ESS rule, in stored steps (C = ``check_every``).

    ``proposal="de"``: chunks of C, no warm-up beyond the ESS rule's burn-in. Under the adaptive (or pooled)
    proposal a warm-up of one differential-evolution chunk, then adaptation chunks, each with the independence
    proposal fitted to the draws of the chunk before (the DE chunk's second half for the first); then the proposal
    is frozen at its fit to the last adaptation chunk, the warm-up's draws are dropped and the ESS rule is checked
    after every further chunk on what follows, so every kept draw comes from one fixed kernel.

    ``warm_up="plateau"`` (the default): chunks of C/4 (at least :data:`PLATEAU_CHUNK` stored steps), the DE
    chunk twice that, and adaptation until the acceptance stops rising (:data:`ACCEPTANCE_RTOL`). The fixed
    warm-up before it spent 1,000 of the two-Drogue example's 1,250 steps; this one stops after 875.
    ``"fixed"``: a DE chunk of C, exactly two adaptation chunks of C/2, checks every C/2 (the diagnosis's short
    fits, whose detection rates were measured with it).
    """
    full = max(1, options.check_every // options.store_every)
    if options.proposal == "de":
        return Schedule(de=0, step=full)
    if options.warm_up == "fixed":
        step, adaptations = max(1, full // 2), (2, 2)
    else:
        step, adaptations = max(PLATEAU_CHUNK, full // 4), (MIN_ADAPTATIONS, MAX_ADAPTATIONS)
    if options.max_steps < (2 + adaptations[0] + 1) * step * options.store_every:
        # a run too short for the warm-up: DE alone, its chain what the adaptive run's first chunk would be
        return Schedule(de=0, step=2 * step)
    return Schedule(de=2 * step, step=step, adaptations=adaptations)


def _window_draws(store, window):
    lo, hi = window
    # the window only: the chain before it is not copied
    return store.sampler.backend.get_chain(discard=lo)[:hi - lo].reshape(-1, store.sampler.ndim)


def fit_proposals(stores, window, pooled=False):
    """Each ensemble's independence proposal fitted to its draws of ``window`` (stored steps lo, hi).
    ``pooled``: one proposal fitted to every ensemble's window.

    Pooled, an ensemble that has not yet crossed a slow direction of the posterior gets a proposal that
    reaches where the others are; each chain's kernel is still fixed after the warm-up (its draws are
    dropped), so every kept draw comes from one valid kernel, and R-hat still compares ensembles started
    apart."""
    from cpas_bayes.inference.moves import fit_proposal

    log_columns = getattr(stores[0].model, "log_scale", None)   # a bare log density: θ coordinates
    if pooled:
        proposal = fit_proposal(np.concatenate([_window_draws(st, window) for st in stores]), log_columns)
        return [proposal] * len(stores)
    return [fit_proposal(_window_draws(st, window), log_columns) for st in stores]


def chain_acceptance(stores, lo, hi, store_every):
    """The moves' acceptance over stored steps [lo, hi) of every ensemble, read from the chain itself (so a
    resumed run reads what an uninterrupted one did, whatever chunks its checkpoint holds): the share a of
    walkers that moved between stored steps, 1 − (1 − a_step)^store_every, solved for a_step."""
    moved = np.mean([np.any(np.diff(st.sampler.backend.get_chain()[lo - 1:hi], axis=0) != 0, axis=-1).mean()
                     for st in stores])
    return 1.0 - (1.0 - min(moved, 1.0 - 1e-12)) ** (1.0 / store_every)


def warm_up_done(stores, start, end, schedule, acceptance_before, max_stored, store_every):
    """(done, this chunk's acceptance) after the adaptation chunk [start, end): done when the acceptance, over
    all ensembles, rose less than :data:`ACCEPTANCE_RTOL` over the chunk before's, or the warm-up is at its
    longest."""
    acceptance = chain_acceptance(stores, start, end, store_every)
    adaptations = (end - schedule.de) // schedule.step
    fewest, most = schedule.adaptations
    if adaptations < fewest:
        return False, acceptance
    done = (acceptance < (1.0 + ACCEPTANCE_RTOL) * acceptance_before or adaptations >= most
            or end + 2 * schedule.step > max_stored)
    return done, acceptance

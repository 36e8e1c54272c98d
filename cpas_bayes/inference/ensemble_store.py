"""One ensemble advanced chunk by chunk and checkpointed in emcee's HDF5 layout (:class:`EnsembleStore`).

A checkpoint carries a fingerprint of what its chain depends on (parameters, initial walkers, seed,
storage, the adaptive proposal's schedule, the moves, the sampler's coordinates), so a rerun resumes only
a chain it would have drawn itself.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import emcee
import numpy as np

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.files import atomic_path


def _moves():
    """Differential evolution alone: the moves of a chunk the store runs itself (the τ rule's tasks)."""
    from cpas_bayes.inference.moves import ensemble_moves

    return ensemble_moves(None, ())


def exchanges_of(model):
    """The model's label exchanges (like canopies no channel tells apart); none for a bare log density."""
    exchanges = getattr(model, "exchanges", None)
    return exchanges() if exchanges is not None else []


def fingerprint(model, init, options):
    h = hashlib.sha256()
    h.update(json.dumps(model.names).encode())
    h.update(np.ascontiguousarray(init).tobytes())
    key = [options.seed, options.store_every]
    if options.proposal != "de" and options.stop == "ess":  # the adaptive chain depends on its chunks too
        key += [options.proposal, options.check_every, "log θ for lognormal priors"]  # the proposal's coordinates
        if options.warm_up != "fixed":   # (the fixed warm-up's checkpoints, from before the choice, stay valid)
            key.append(f"warm-up: {options.warm_up}")
    if exchanges_of(model):   # the chain depends on the moves
        key.append("label exchanges, the last stage's keeping the other stages' fill times, and mode jumps")
    h.update(json.dumps(key).encode())
    return h.hexdigest()[:16]


class EnsembleStore:
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
        self.fingerprint = fingerprint(model, init, options)
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
        return steps, backend.get_chain(), backend.get_log_prob(), self.acceptance()

    def acceptance(self):
        backend = self.sampler.backend
        # emcee adds one acceptance per stored step, not per thinned-away step
        return float(np.mean(backend.accepted) / max(backend.iteration, 1))

    @property
    def stored(self):
        """Stored steps so far."""
        return self.sampler.backend.iteration

    def next_state(self):
        """(walkers, their log posterior or None, emcee's random state): where the next chunk starts."""
        if self.stored == 0:
            return self.init, None, np.random.RandomState(self.seed).get_state()
        last = self.sampler.backend.get_last_sample()
        return last.coords, last.log_prob, last.random_state

    def append(self, chain, log_prob, accepted, random_state):
        """Add a chunk run elsewhere (:func:`_chunk_task`) from :meth:`next_state`, and checkpoint."""
        b = self.sampler.backend
        b.chain = np.concatenate([b.chain[: b.iteration], chain])
        b.log_prob = np.concatenate([b.log_prob[: b.iteration], log_prob])
        b.accepted = b.accepted + accepted
        b.iteration += chain.shape[0]
        b.random_state = random_state
        if self.checkpoint:
            self._save()

"""The pieces a :class:`~cpas_bayes.stats.model.TestModel` shares with its extensions.

:class:`Parameter` (a name, a prior, a unit, a group), :class:`Prediction`
(what the forward model returns for a batch), :class:`Context` (what the
pipeline hands the extension hooks) and :class:`Extension`, the base class of
every term a diagnosis adds (:mod:`cpas_bayes.stats.model_terms`), whose hooks
are documented here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Parameter:
    """A named model parameter with its prior."""

    name: str
    prior: object
    unit: str = ""
    group: str = "inflation"


@dataclass
class Prediction:
    """Predicted observations for a batch: ``acc`` (B, N), ``lc`` (B, L, N), and the parts."""

    acc: np.ndarray
    lc: np.ndarray
    cds: np.ndarray               # (B, P, N) drag area of each parachute at the bin times
    timing: object                # inflation.StageTiming, fields (B, P, K)
    noise_acc: np.ndarray         # (B,) error multipliers
    noise_lc: np.ndarray


@dataclass
class Context:
    """What the pipeline passes to extensions for one batch."""

    model: object                 # the TestModel running the pipeline
    theta: np.ndarray
    values: dict                  # parameter name -> (B,) array
    time: np.ndarray              # (N,) bin times
    stage: dict = field(default_factory=dict)   # start, cds_stage, ... each (B, P, K)
    law: tuple | None = None      # (drag areas, their rate) of the stage law at ``time``, (B, P, N) each, when a
    #                               term needs the rate (the model computes both in one pass)
    air: tuple | None = None      # (ρ, V, q̄, γ rad, dρ/dt) at ``time``, (B, 1, N) each, when the model has them
    #                               at hand: a logger bundle's reconstruction per walker, or the measured ones at a
    #                               lagged load cell's times; None: the term reads the measured ones


class Extension:
    """A term added to the baseline model. Override the hooks you need.

    ``parameters(model)`` returns the extension's :class:`Parameter` list. The
    hooks receive a :class:`Context` and return arrays broadcastable to the
    shapes named.
    """

    name = "extension"
    # (parameter, size): a fitted |median| below size is practically no effect (a region of
    # practical equivalence around the neutral value); None for terms without a physical size.
    practical_floor = None
    physical_lower_limits = ()    # parameters whose prior's lower bound is a physical limit (a lag of 0), not an edge
    periodic = ()                 # name prefixes of angles: a circle has no edge
    needs_load_cells = False      # a term acting on load cells only does not apply without them
    reads_air_data = False        # reads ρ, V, q̄, γ: given in Context.air (a logger's walkers', a lagged load cell's)
    needs_drag_area_rate = False  # reads Context.law: the model then gives the stage law's rate with its drag areas

    @classmethod
    def brings_error_model(cls):
        """Whether the term replaces the independent errors with its own error model (a model takes one)."""
        return cls.log_likelihood is not Extension.log_likelihood

    def parameters(self, model):
        return []

    def initial_values(self, model):
        """Starting values {name: value} for the MAP search (default: prior medians)."""
        return {}

    def start_points(self, model):
        """Starting values of this term's parameters when it is added to a fitted baseline:
        a list of {name: value}, each one MAP start (default: ``initial_values``)."""
        return [self.initial_values(model)]

    def reshape_drag_area(self, ctx, cds, t):
        """Return a modified (B, P, N) drag area evaluated at times ``t``."""
        return cds

    def apparent_drag_area(self, ctx, t):
        """Extra drag area (B, P, N) seen by both channels (momentum terms), or None."""
        return None

    def load_cell_lag(self, ctx):
        """Load-cell delays behind the IMU time base: ((B, K) delays in s, (K,) weights summing to 1), K = 1 for
        a pure delay; or None."""
        return None

    def friction_factor(self, ctx, t):
        """Load-cell friction factor (B, N) at times ``t``, or None to keep the constant one."""
        return None

    def log_likelihood(self, ctx, pred, obs):
        """Pointwise log-likelihood (B, N) replacing the independent Gaussian, or None."""
        return None

    def total_log_likelihood(self, ctx, pred, obs):
        """Joint log-likelihood (B,) when it is not the sum of the pointwise values (e.g. a
        marginalised discrepancy, whose pointwise values are leave-one-out conditionals), or None."""
        return None


def own_error_models(terms):
    """Names of ``terms`` (extensions, or their classes) that bring their own error model."""
    return [term.name for term in terms if term.brings_error_model()]


def one_error_model(extensions):
    """``extensions`` as a tuple, refused when two of them bring their own error model: only the first would
    be used, the other's parameters left to their prior."""
    extensions = tuple(extensions)
    own = own_error_models(extensions)
    if len(own) > 1:
        raise ValueError(f"{' and '.join(own)} each bring their own error model; a model takes one of them")
    return extensions

"""Drag-area growth of one parachute, stage by stage (the seed's §IV–VI).

"The seed" throughout the package is the paper whose equations this module
implements: E. S. Ray (Jacobs Engineering, Houston), "Reconstruction of Orion
EDU Parachute Inflation Loads", AIAA conference paper. Equation, section and
figure numbers cited anywhere in the package are that paper's.

Pure numpy; every function broadcasts over leading batch axes (walkers, Monte
Carlo runs) and over time.

Notation (seed nomenclature): ``cds_start`` is the drag area the canopy holds
when the stage begins ((C_D S)_{i-1}; 0 at bag strip, the retained value at a
disreef), ``cds_i`` the stage's steady drag area, ``cds_o`` the full-open drag
area and ``eps_i = cds_i / cds_o`` the reefing ratio.

Equations
---------
Fill time (Eq. 14)::

    t_f = n · D_o · sqrt((CDS_i − CDS_start) / CDS_o) / V_i

Over-inflation ratio and peak fill time (Eq. 15)::

    S    = (C_k·CDS_i − CDS_start) / (CDS_i − CDS_start)
    t_fp = t_f · S^(1/expopen)

Growth for 0 ≤ τ < t_fp (τ = time since the stage started)::

    CDS(τ) = CDS_start + (CDS_i − CDS_start) · (τ / t_f)^expopen

which passes CDS_i at t_f and reaches C_k·CDS_i at t_fp. Decay to CDS_i over
t_k after the peak (``decay``, one of :data:`DECAY_SHAPES`):

* ``"linear"`` (default): a linear ramp from C_k·CDS_i (the papers' "ramp-down
  time");
* ``"exponential"``: C_k·CDS_i·C_k^(−(τ−t_fp)/t_k), the form of NASA's DCLDYN
  model;
* ``"cml_linear"``: NASA CML's linear mode. The growth law stops at t_f (at
  CDS_i), the drag area JUMPS to C_k·CDS_i there and ramps linearly down to
  CDS_i over t_k: the peak is at t_f, so ``t_fp = t_f``.

All three end exactly at CDS_i at τ = t_fp + t_k.

Re-parameterisation (Eq. 16–18)::

    n_p = n · S^(1/expopen)          n = n_p · S^(−1/expopen)

so that n_p fixes the time to the peak drag area: t_fp = n_p·D_o·sqrt(...)/V_i.
Under ``"cml_linear"`` the growth ends at the peak instant t_f, so the same
statement gives ``n_p = n`` (the exponent 1/expopen becomes 0, see
:func:`peak_exponent`): the sampled and dispersed parameter stays n_p, still
the fill distance to the peak, and t_fp = t_f = n_p·D_o·sqrt(...)/V_i.

Finite-mass stages use the same law with C_k = 1 (then S = 1, n = n_p and the
three decay shapes coincide).

Retain-at-disreef (seed Fig. 29): a stage starts from the drag area actually
held at its start, so a stage cut short by the next disreef gives no
discontinuity. A stage whose drag area is not above the held one (nothing to
fill) has zero fill time; what it shows then is ``below_previous`` (one of
:data:`BELOW_PREVIOUS_RULES`): ``"drop"`` (default) snaps to its own value,
``"hold"`` (NASA CML) keeps the larger drag area already held.

Peer semantics: NASA's CML chute model, run side by side on 35 cases, matches
the ``"exponential"`` decay to its time step; its linear mode and its rule for
a stage below the held area are ``decay="cml_linear"`` and
``below_previous="hold"`` here. The compiled kernels (this module's, the
Monte Carlo engine's, the fused likelihood's) take the integer codes of
:data:`DECAY_CODES` and :data:`BELOW_PREVIOUS_CODES`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

# The one place the option names map to the integer codes the compiled kernels take.
DECAY_LINEAR, DECAY_EXPONENTIAL, DECAY_CML_LINEAR = 0, 1, 2
DECAY_CODES = {"linear": DECAY_LINEAR, "exponential": DECAY_EXPONENTIAL, "cml_linear": DECAY_CML_LINEAR}
DECAY_SHAPES = tuple(DECAY_CODES)

BELOW_PREVIOUS_DROP, BELOW_PREVIOUS_HOLD = 0, 1
BELOW_PREVIOUS_CODES = {"drop": BELOW_PREVIOUS_DROP, "hold": BELOW_PREVIOUS_HOLD}
BELOW_PREVIOUS_RULES = tuple(BELOW_PREVIOUS_CODES)


def decay_code(decay):
    """Integer code of the decay shape ``decay``; ValueError naming :data:`DECAY_SHAPES` for anything else."""
    if not isinstance(decay, str) or decay not in DECAY_CODES:
        raise ValueError(f"decay must be one of {DECAY_SHAPES}, got {decay!r}")
    return DECAY_CODES[decay]


def below_previous_code(below_previous):
    """Integer code of a stage-below-previous rule; ValueError naming :data:`BELOW_PREVIOUS_RULES` otherwise."""
    if not isinstance(below_previous, str) or below_previous not in BELOW_PREVIOUS_CODES:
        raise ValueError(f"below_previous must be one of {BELOW_PREVIOUS_RULES}, got {below_previous!r}")
    return BELOW_PREVIOUS_CODES[below_previous]


# ---------------------------------------------------------------------------
# Stage names: one scheme for priors, model parameters, fit summaries and the memo


def stage_key(index, n_stages):
    """Stage identity shared across tests (memo, pooling): ``first``, ``reefed1``…, ``full_open``."""
    if index == n_stages - 1:
        return "full_open"
    return "first" if index == 0 else f"reefed{index}"


def stage_role(index, n_stages):
    """Which prior table a stage takes: ``first``, ``reefed`` or ``full_open`` (the key without its number)."""
    return stage_key(index, n_stages).rstrip("0123456789")


def stage_tag(index):
    """Short name of stage ``index`` in parameter and column names: ``s1``, ``s2``…"""
    return f"s{index + 1}"



def fill_time(n, diameter, cds_start, cds_i, cds_o, v_i):
    """Eq. 14: time from stage start to reaching CDS_i. Zero when nothing fills."""
    growth = np.maximum(np.asarray(cds_i, float) - cds_start, 0.0)
    return n * diameter * np.sqrt(growth / cds_o) / v_i


def overinflation_ratio(ck, cds_i, cds_start):
    """S of Eq. 15–17; 1 where the stage has nothing to fill (then unused)."""
    cds_i = np.asarray(cds_i, float)
    growth = cds_i - cds_start
    safe = np.where(growth > 0, growth, 1.0)
    return np.where(growth > 0, (ck * cds_i - cds_start) / safe, 1.0)


def peak_exponent(expopen, decay="linear"):
    """The exponent e of t_fp/t_f = n_p/n = S^e (Eq. 15–18).

    1/expopen where the growth law runs on from CDS_i to the peak; 0 under
    ``"cml_linear"``, whose growth stops at t_f and jumps to the peak there.
    """
    if decay_code(decay) == DECAY_CML_LINEAR:
        return 0.0
    return 1.0 / expopen


def peak_fill_time(t_f, ratio, expopen, decay="linear"):
    """Eq. 15: t_fp = t_f · S^(1/expopen) (t_f under ``"cml_linear"``)."""
    return t_f * ratio ** peak_exponent(expopen, decay)


def n_p_from_n(n, ratio, expopen, decay="linear"):
    """Eq. 17: fill distance to the peak drag area (n itself under ``"cml_linear"``)."""
    return n * ratio ** peak_exponent(expopen, decay)


def n_from_n_p(n_p, ratio, expopen, decay="linear"):
    """Eq. 18: fill constant for a simulation given a dispersed n_p (n_p itself under ``"cml_linear"``)."""
    return n_p * ratio ** -peak_exponent(expopen, decay)


def stage_drag_area(tau, cds_start, cds_i, t_f, expopen, ck, t_k, decay="linear", below_previous="drop"):
    """Drag area ``tau`` seconds after a stage starts (tau ≥ 0).

    All arguments broadcast together. ``t_f`` ≤ 0 means a stage with nothing
    to fill: its drag area is CDS_i at once, or under ``below_previous="hold"``
    the larger of CDS_i and the held CDS_start. ``decay`` is one of
    :data:`DECAY_SHAPES`.
    """
    code = decay_code(decay)
    hold = below_previous_code(below_previous) == BELOW_PREVIOUS_HOLD
    tau = np.asarray(tau, float)
    cds_i = np.asarray(cds_i, float)
    filling = t_f > 0
    safe_tf = np.where(filling, t_f, 1.0)
    ratio = overinflation_ratio(ck, cds_i, cds_start)
    t_fp = np.where(filling, peak_fill_time(safe_tf, ratio, expopen, decay), 0.0)

    x = np.clip(tau, 0.0, None) / safe_tf
    growth = cds_start + (cds_i - cds_start) * x**expopen

    after = np.clip(tau - t_fp, 0.0, None)
    has_decay = t_k > 0
    frac = np.where(has_decay, after / np.where(has_decay, t_k, 1.0), 1.0)
    frac = np.clip(frac, 0.0, 1.0)
    peak = ck * cds_i
    if code == DECAY_EXPONENTIAL:
        decayed = peak * np.asarray(ck, float) ** (-frac)
    else:  # linear and cml_linear ramp alike; cml_linear's starts at t_fp = t_f, a jump up from CDS_i
        decayed = peak - (peak - cds_i) * frac

    out = np.where(tau < t_fp, growth, decayed)
    nothing_to_fill = np.maximum(cds_i, cds_start) if hold else cds_i
    return np.where(filling, out, nothing_to_fill)


@dataclass(frozen=True)
class StageTiming:
    """Derived quantities of every stage, shape (..., n_stages) each."""

    cds_start: np.ndarray  # drag area held when the stage started
    t_f: np.ndarray        # fill time, Eq. 14
    t_fp: np.ndarray       # time from stage start to the peak, Eq. 15
    n: np.ndarray          # fill constant, Eq. 18
    n_p: np.ndarray        # fill distance to peak, Eq. 17


def _stage_parameters(k, start, cds_stage, n_fill, expopen, ck, t_k):
    return (start[..., k], cds_stage[..., k], n_fill[..., k], expopen[..., k],
            ck[..., k], t_k[..., k])


def parachute_drag_area(t, start, cds_stage, cds_o, diameter, n_fill, expopen,
                        ck, t_k, v_start, decay="linear", fill_constant="n_p", below_previous="drop"):
    """Drag-area history of one parachute through all its stages.

    Parameters
    ----------
    t : array (T,) or broadcastable to (..., T)
        Times at which to evaluate.
    start, cds_stage, n_fill, expopen, ck, t_k, v_start : arrays (..., K)
        Per stage: start time (bag strip or disreef), steady drag area CDS_i,
        fill constant (``n_p`` or ``n``, see ``fill_constant``), shape
        exponent, over-inflation factor, decay time and the airspeed at the
        stage start. Stages must be in time order.
    cds_o, diameter : arrays (...,)
        Full-open drag area and nominal diameter D_o.
    decay, below_previous : str
        Decay shape (:data:`DECAY_SHAPES`) and the rule for a stage whose drag
        area is not above the held one (:data:`BELOW_PREVIOUS_RULES`).

    Returns
    -------
    cds : array (..., T)
        Zero before the first stage starts.
    timing : StageTiming
        Each field (..., K).
    """
    if fill_constant not in ("n", "n_p"):
        raise ValueError("fill_constant must be 'n' or 'n_p'")
    decay_code(decay), below_previous_code(below_previous)  # refuse a bad option before any work
    start, cds_stage, n_fill, expopen, ck, t_k, v_start = np.broadcast_arrays(
        *(np.asarray(a, float) for a in (start, cds_stage, n_fill, expopen, ck, t_k, v_start)))
    batch = start.shape[:-1]
    n_stages = start.shape[-1]
    cds_o = np.asarray(cds_o, float)[..., None]
    diameter = np.asarray(diameter, float)[..., None]
    t = np.asarray(t, float)

    out = np.zeros(np.broadcast_shapes(batch + (1,), t.shape))
    held = np.zeros(batch)
    fields = {name: np.zeros(batch + (n_stages,)) for name in ("cds_start", "t_f", "t_fp", "n", "n_p")}
    for k in range(n_stages):
        t0, cds_i, fc, expo, c_k, tk = _stage_parameters(k, start, cds_stage, n_fill, expopen, ck, t_k)
        ratio = overinflation_ratio(c_k, cds_i, held)
        if fill_constant == "n_p":
            n_p, n = fc, n_from_n_p(fc, ratio, expo, decay)
        else:
            n, n_p = fc, n_p_from_n(fc, ratio, expo, decay)
        t_f = fill_time(n, diameter[..., 0], held, cds_i, cds_o[..., 0], v_start[..., k])
        t_fp = np.where(t_f > 0, peak_fill_time(t_f, ratio, expo, decay), 0.0)
        for name, value in zip(fields, (held, t_f, t_fp, n, n_p)):
            fields[name][..., k] = value

        stage_args = (held[..., None], cds_i[..., None], t_f[..., None], expo[..., None],
                      c_k[..., None], tk[..., None])
        tau = t - t0[..., None]
        values = stage_drag_area(tau, *stage_args, decay=decay, below_previous=below_previous)
        active = tau >= 0
        if k + 1 < n_stages:
            t_next = start[..., k + 1]
            active = active & (t < t_next[..., None])
            # Retain-at-disreef: the next stage begins from what is held now.
            held = stage_drag_area((t_next - t0)[..., None], *stage_args, decay=decay,
                                   below_previous=below_previous)[..., 0]
        out = np.where(active, values, out)
    return out, StageTiming(**fields)


# ---------------------------------------------------------------------------
# Compiled kernel for the likelihood's hot path.
#
# Same law as parachute_drag_area, fused into one loop per (walker, parachute)
# so that the samples after a stage has settled cost a comparison instead of a
# power: measured 10-20x faster than the numpy form on a walker batch. The
# numpy form above stays the reference; tests hold the two equal.

import numba  # noqa: E402


@numba.njit(cache=True)
def compiled_peak_exponent(expopen, decay):
    """Compiled scalar :func:`peak_exponent` for a decay code of :data:`DECAY_CODES`."""
    if decay == DECAY_CML_LINEAR:
        return 0.0
    return 1.0 / expopen


@numba.njit(cache=True)
def compiled_stage_drag_area(tau, held, cds_i, t_f, t_fp, expopen, ck, t_k, decay, below_previous):
    """Compiled scalar :func:`stage_drag_area`: drag area ``tau`` s after the stage started.

    Takes the stage's timing already derived (``held`` = CDS_start, ``t_f``,
    ``t_fp``) so a caller evaluating many instants derives it once; ``decay``
    and ``below_previous`` are codes of :data:`DECAY_CODES` and
    :data:`BELOW_PREVIOUS_CODES`.
    """
    if t_f <= 0.0:
        if below_previous == BELOW_PREVIOUS_HOLD and held > cds_i:
            return held
        return cds_i
    if tau < t_fp:
        x = tau / t_f if tau > 0.0 else 0.0
        return held + (cds_i - held) * x**expopen
    if t_k <= 0.0:
        return cds_i
    frac = (tau - t_fp) / t_k
    if frac >= 1.0:
        return cds_i
    peak = ck * cds_i
    if decay == DECAY_EXPONENTIAL:
        return peak * ck ** (-frac)
    return peak - (peak - cds_i) * frac   # linear; cml_linear from its jump at t_fp = t_f


RATE_STEP = 1e-3   # s, half-width of the central difference that gives dCDS/dt (cluster_drag_area's with_rate)


@numba.njit(cache=True)
def _law_at(time, start, cds_stage, expopen, ck, t_k, n_stages, decay, below_previous, t_f, t_fp, held):
    """The stage law at one instant from the stage timing :func:`parachute_stage_law` wrote; 0 before
    the first stage."""
    for k in range(n_stages - 1, -1, -1):
        if time >= start[k]:
            return compiled_stage_drag_area(time - start[k], held[k], cds_stage[k], t_f[k], t_fp[k], expopen[k],
                                            ck[k], t_k[k], decay, below_previous)
    return 0.0


@numba.njit(cache=True)
def parachute_stage_rate(t, start, cds_stage, expopen, ck, t_k, n_stages, decay, below_previous, t_f, t_fp, held,
                         steps, out):
    """One parachute's dCDS/dt at ``t`` (N,) into ``out`` (N,): the law's central difference over ±``steps``
    ((N,), or (1,) for every time), from the stage timing (``t_f``, ``t_fp``, ``held``: (K,)) that
    :func:`parachute_stage_law` wrote. Over a bin's own half-width the difference is the mean rate over the
    bin, exactly: what a channel of bin means sees.

    A difference, not the law's derivative: that jumps at the law's kinks (t_fp, a stage's start), so the
    added mass' force would jump whenever a kink crossed a bin and the likelihood with it (by 33 in log p
    for a 3e-5 change of a Main's reefing ratio, which stopped the MAP search where it began)."""
    # Where the law is one constant over ±step the difference is exactly 0: before the first stage, and in
    # each stage's settled part (from t_fp + t_k after its start, or its start when it does not grow, to the
    # next start): most bins of a record. The stage _law_at picks for a time is the last one started.
    settle = np.empty(n_stages)
    until = np.empty(n_stages)
    first = np.inf
    for k in range(n_stages):
        settle[k] = start[k] + (t_fp[k] + max(t_k[k], 0.0) if t_f[k] > 0.0 else 0.0)
        until[k] = np.inf
        for j in range(k + 1, n_stages):
            until[k] = min(until[k], start[j])
        first = min(first, start[k])
    for i in range(t.shape[0]):
        step = steps[i] if steps.shape[0] > 1 else steps[0]
        lo, hi = t[i] - step, t[i] + step
        constant = hi < first
        if not constant:
            for k in range(n_stages - 1, -1, -1):
                if lo >= start[k]:
                    constant = lo >= settle[k] and hi < until[k]
                    break
        if constant:
            out[i] = 0.0
            continue
        ahead = _law_at(t[i] + step, start, cds_stage, expopen, ck, t_k, n_stages, decay, below_previous, t_f,
                        t_fp, held)
        behind = _law_at(t[i] - step, start, cds_stage, expopen, ck, t_k, n_stages, decay, below_previous, t_f,
                         t_fp, held)
        out[i] = (ahead - behind) / (2.0 * step)


@numba.njit(cache=True)
def parachute_stage_law(t, start, cds_stage, cds_o, diameter, n_fill, expopen, ck, t_k, v_start,
                        n_stages, decay, below_previous, fill_is_np, t_sorted, out, t_f_out, t_fp_out, n_out,
                        held_out):
    """One parachute's stages (arrays (K,)): drag area at ``t`` (N,) into ``out`` (N,), timing into (K,).

    Writes only the bins inside a stage, so ``out`` must hold zeros before the first
    start. With ``t_sorted`` (ascending ``t``) each stage visits only its own bins.
    Shared by :func:`_drag_area_kernel` and the model's fused likelihood, so the
    stage law has one compiled form.
    """
    N = t.shape[0]
    held = 0.0
    for k in range(n_stages):
        cds_i = cds_stage[k]
        growth = cds_i - held
        if growth > 0.0:
            ratio = (ck[k] * cds_i - held) / growth
        else:
            ratio = 1.0
        r_pow = ratio ** compiled_peak_exponent(expopen[k], decay)   # t_fp/t_f = n_p/n
        if fill_is_np:
            n = n_fill[k] / r_pow
        else:
            n = n_fill[k]
        if growth > 0.0:
            t_f = n * diameter * np.sqrt(growth / cds_o) / v_start[k]
        else:
            t_f = 0.0
        t_fp = t_f * r_pow if t_f > 0.0 else 0.0
        t_f_out[k] = t_f
        t_fp_out[k] = t_fp
        n_out[k] = n
        held_out[k] = held
        t0 = start[k]
        t1 = start[k + 1] if k + 1 < n_stages else np.inf
        if t_sorted:
            i = np.searchsorted(t, t0)
            while i < N and t[i] < t1:
                out[i] = compiled_stage_drag_area(t[i] - t0, held, cds_i, t_f, t_fp, expopen[k], ck[k], t_k[k],
                                                  decay, below_previous)
                i += 1
        else:
            for i in range(N):
                ti = t[i]
                if ti >= t0 and ti < t1:
                    out[i] = compiled_stage_drag_area(ti - t0, held, cds_i, t_f, t_fp, expopen[k], ck[k], t_k[k],
                                                      decay, below_previous)
        if k + 1 < n_stages:
            held = compiled_stage_drag_area(t1 - t0, held, cds_i, t_f, t_fp, expopen[k], ck[k], t_k[k],
                                            decay, below_previous)


@numba.njit(cache=True)
def _drag_area_kernel(t, start, cds_stage, cds_o, diameter, n_fill, expopen, ck, t_k, v_start,
                      n_stages, decay, below_previous, fill_is_np, t_sorted, out, t_f_out, t_fp_out, n_out,
                      held_out, with_rate, rate_steps, rate_out):
    B, P = start.shape[:2]
    per_walker_time = t.shape[0] > 1
    for b in range(B):
        tb = b if per_walker_time else 0
        for p in range(P):
            parachute_stage_law(t[tb], start[b, p], cds_stage[b, p], cds_o[b, p], diameter[p], n_fill[b, p],
                                expopen[b, p], ck[b, p], t_k[b, p], v_start[b, p], n_stages[p], decay,
                                below_previous, fill_is_np, t_sorted, out[b, p], t_f_out[b, p], t_fp_out[b, p],
                                n_out[b, p], held_out[b, p])
            if with_rate:
                parachute_stage_rate(t[tb], start[b, p], cds_stage[b, p], expopen[b, p], ck[b, p], t_k[b, p],
                                     n_stages[p], decay, below_previous, t_f_out[b, p], t_fp_out[b, p],
                                     held_out[b, p], rate_steps, rate_out[b, p])


def cluster_drag_area(t, start, cds_stage, cds_o, diameter, n_fill, expopen, ck, t_k, v_start,
                      n_stages=None, decay="linear", fill_constant="n_p", below_previous="drop", with_rate=False,
                      rate_half_width=None):
    """Compiled :func:`parachute_drag_area` for a cluster: stage arrays (B, P, K), ``cds_o`` (B, P).

    ``t`` is (N,) shared by all rows, or (B, N) one time base per row (for a
    shifted sensor). ``n_stages`` (P,) gives each parachute's real stage count
    (extra stage slots are ignored). Returns ``cds`` (B, P, N) and a
    :class:`StageTiming` with fields (B, P, K); ``with_rate`` also dCDS/dt
    (B, P, N) between them, the law's central difference over ±``rate_half_width``
    ((N,) per time, or one for all; default :data:`RATE_STEP`: :func:`parachute_stage_rate`), for the
    added mass, in the same pass.
    """
    codes = decay_code(decay), below_previous_code(below_previous)
    start = np.ascontiguousarray(start, dtype=float)
    B, P, K = start.shape
    stage = [np.ascontiguousarray(np.broadcast_to(np.asarray(a, float), (B, P, K)))
             for a in (cds_stage, n_fill, expopen, ck, t_k, v_start)]
    t2 = np.ascontiguousarray(np.atleast_2d(np.asarray(t, float)))
    cds_o = np.ascontiguousarray(np.broadcast_to(np.asarray(cds_o, float), (B, P)))
    diameter = np.ascontiguousarray(np.broadcast_to(np.asarray(diameter, float), (P,)))
    n_stages = np.full(P, K, dtype=np.int64) if n_stages is None else np.asarray(n_stages, dtype=np.int64)
    out = np.zeros((B, P, t2.shape[1]))
    fields = [np.zeros((B, P, K)) for _ in range(4)]
    # Ascending times (every caller's but a user's own) let each stage visit only its own bins.
    t_sorted = bool(np.all(t2[:, 1:] >= t2[:, :-1]))
    rate = np.zeros_like(out) if with_rate else np.zeros((1, 1, 1))
    steps = np.atleast_1d(np.asarray(RATE_STEP if rate_half_width is None else rate_half_width, float))
    if steps.size not in (1, t2.shape[1]) or not np.all(steps > 0):
        raise ValueError(f"rate_half_width must be positive, one value or one per time ({t2.shape[1]}), "
                         f"not {steps.size} values")
    _drag_area_kernel(t2, start, stage[0], cds_o, diameter, *stage[1:], n_stages, *codes,
                      fill_constant == "n_p", t_sorted, out, *fields, with_rate, np.ascontiguousarray(steps), rate)
    t_f, t_fp, n, held = fields
    if fill_constant == "n_p":
        n_p = stage[1]
    else:
        n_p = n * np.where(t_f > 0, t_fp / np.where(t_f > 0, t_f, 1.0), 1.0)
    timing = StageTiming(cds_start=held, t_f=t_f, t_fp=t_fp, n=n, n_p=n_p)
    return (out, rate, timing) if with_rate else (out, timing)


def _kernel_array(a, shape, dtype=np.float64):
    """``a`` as the compiled kernels take it: of ``dtype`` and ``shape`` (broadcast, then contiguous); an array
    that already has both is passed through in its own layout (the sampler's coordinates call this map once
    per walker batch, where copying a dozen small arrays cost three times the kernel)."""
    if isinstance(a, np.ndarray) and a.shape == shape and a.dtype == dtype:
        return a
    return np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype), shape))


FILL_KINDS = {"n_p": 0, "peak_time": 1, "grown": 2}   # what a stage's fill column holds (stage_fill_map)


class FillMap(NamedTuple):
    """Each stage's fill constant and the map to it (B, P, K): ``n_p``; ``scale`` s, the seconds to peak per
    unit n_p; ``log_jacobian`` log|∂n_p/∂u| of the column u that held it; ``grown``, the drag area the
    unsaturated growth law gains by the stage's reference time T_ref, g = (CDS_i − CDS_start)·(t_ref/t_f)^expopen
    with t_ref = T_ref − the stage's start (NaN where t_ref ≤ 0)."""

    n_p: np.ndarray
    scale: np.ndarray
    log_jacobian: np.ndarray
    grown: np.ndarray


@numba.njit(cache=True, error_model="numpy")   # 0/0 and x/0 as NaN and ±inf: a walker's, not an error
def _fill_map_kernel(start, cds_stage, cds_o, diameter, fill, expopen, ck, t_k, v_start, n_stages, decay,
                     below_previous, kind, ref_time, n_p_out, scale_out, jac_out, grown_out):
    B, P = start.shape[:2]
    for b in range(B):
        for p in range(P):
            held = 0.0
            for k in range(n_stages[p]):
                cds_i = cds_stage[b, p, k]
                growth = cds_i - held
                e = expopen[b, p, k]
                scale = diameter[p] * np.sqrt(abs(growth) / cds_o[b, p]) / v_start[b, p, k]
                ratio = (ck[b, p, k] * cds_i - held) / growth if growth > 0.0 else 1.0
                r_pow = ratio ** compiled_peak_exponent(e, decay)
                u = fill[b, p, k]
                t_ref = ref_time[p, k] - start[b, p, k]
                if kind[p, k] == 1:            # seconds to peak: n_p = t_fp/s
                    n_p = u / scale
                    jac = -np.log(scale)
                elif kind[p, k] == 2:          # drag area grown by t_ref: t_f = t_ref·(growth/g)^(1/expopen)
                    if growth > 0.0 and u > 0.0 and e > 0.0 and t_ref > 0.0:
                        n_p = t_ref * (growth / u) ** (1.0 / e) * r_pow / scale
                        jac = np.log(n_p) - np.log(e) - np.log(u)
                    else:
                        n_p = np.nan
                        jac = np.nan
                else:
                    n_p = u
                    jac = 0.0
                t_fp = n_p * scale if growth > 0.0 else 0.0
                t_f = t_fp / r_pow if growth > 0.0 else 0.0
                n_p_out[b, p, k] = n_p
                scale_out[b, p, k] = scale
                jac_out[b, p, k] = jac
                grown_out[b, p, k] = growth * (t_ref / t_f) ** e if growth > 0.0 and t_ref > 0.0 else np.nan
                if k + 1 < n_stages[p]:     # the drag area the next stage starts from, as the law holds it
                    held = compiled_stage_drag_area(start[b, p, k + 1] - start[b, p, k], held, cds_i, t_f, t_fp,
                                                    e, ck[b, p, k], t_k[b, p, k], decay, below_previous)


def stage_fill_map(start, cds_stage, cds_o, diameter, fill, expopen, ck, t_k, v_start, n_stages, decay="linear",
                   below_previous="drop", kind=0, ref_time=1.0):
    """:class:`FillMap` of every stage (B, P, K) whose fill column (``fill``) holds, per stage, what ``kind``
    (P, K, codes of :data:`FILL_KINDS`) says: n_p; the seconds from the stage's start to its peak,
    t_fp = n_p·s with s = D_o·sqrt(|CDS_i − CDS_start|/CDS_o)/V_i (Eqs. 14, 15 and 17: t_f·(…)^(1/expopen)
    is n_p's fill time); or the drag area grown by the time ``ref_time`` (P, K; on the record's clock, so that
    it is where the data see it whatever the stage's start).

    A stage's s, its over-inflation ratio and CDS_start depend on the earlier stages only, so one pass in
    stage order inverts the map. The sampler's coordinates (:mod:`cpas_bayes.inference.coordinates`) move
    in t_fp where the data see a stage's peak, and in the drag area grown where the stage is cut short by the
    next before it fills: there the data see only the growing curve, whose n_p and ε trade off along it. At
    a stage that does not grow (t_fp = 0 in the law) s uses |CDS_i − CDS_start|, which keeps the peak-time
    map a bijection; the grown drag area is then undefined (NaN: outside the coordinates' support).
    """
    start = np.ascontiguousarray(start, dtype=float)
    B, P, K = start.shape
    stage = [_kernel_array(a, (B, P, K)) for a in (cds_stage, fill, expopen, ck, t_k, v_start)]
    cds_o, diameter = _kernel_array(cds_o, (B, P)), _kernel_array(diameter, (P,))
    kind, ref_time = _kernel_array(kind, (P, K), np.int64), _kernel_array(ref_time, (P, K))
    n_stages = np.asarray(n_stages, dtype=np.int64)
    out = [np.zeros((B, P, K)), np.ones((B, P, K)), np.zeros((B, P, K)), np.full((B, P, K), np.nan)]
    # error_model="numpy": a walker's 0/0 is NaN, and compiled code raises no numpy warnings to silence
    _fill_map_kernel(start, stage[0], cds_o, diameter, *stage[1:], n_stages, decay_code(decay),
                     below_previous_code(below_previous), kind, ref_time, *out)
    return FillMap(*out)

"""Properties of the stage law (cpas_bayes.physics.inflation), checked on generated parameters.

Each property is one of the seed's statements about the law (Eq. 14–18,
retain-at-disreef of Fig. 29), over the realistic ranges of Drogue and Main
stages.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cpas_bayes.physics.inflation import (fill_time, n_from_n_p, n_p_from_n, overinflation_ratio, parachute_drag_area,
                                  peak_fill_time, stage_drag_area)

SETTINGS = settings(max_examples=60, deadline=None)

finite = dict(allow_nan=False, allow_infinity=False)
cds_o_values = st.floats(20.0, 600.0, **finite)            # m², Drogue to Main
eps_values = st.floats(0.03, 1.0, **finite)
expopen_values = st.floats(0.5, 3.5, **finite)
ck_values = st.floats(1.0, 1.6, **finite)
tk_values = st.floats(0.05, 1.5, **finite)
n_values = st.floats(2.0, 25.0, **finite)
speed_values = st.floats(5.0, 150.0, **finite)            # m/s
diameter_values = st.floats(3.0, 40.0, **finite)          # m
decays = st.sampled_from(["linear", "exponential"])


@st.composite
def one_stage(draw):
    """A stage starting from a held drag area below its own (a fill to do)."""
    cds_o = draw(cds_o_values)
    cds_i = draw(eps_values) * cds_o
    held = draw(st.floats(0.0, 0.9, **finite)) * cds_i
    ck = draw(ck_values)
    expopen = draw(expopen_values)
    ratio = overinflation_ratio(ck, cds_i, held)
    t_f = float(fill_time(draw(n_values), draw(diameter_values), held, cds_i, cds_o, draw(speed_values)))
    return dict(cds_start=held, cds_i=cds_i, t_f=t_f, expopen=expopen, ck=ck, t_k=draw(tk_values),
                t_fp=float(peak_fill_time(t_f, ratio, expopen)))


def _stage(stage, tau, decay):
    return float(stage_drag_area(tau, stage["cds_start"], stage["cds_i"], stage["t_f"], stage["expopen"],
                                 stage["ck"], stage["t_k"], decay=decay))


@SETTINGS
@given(one_stage(), decays)
def test_drag_area_passes_cds_i_at_fill_time(stage, decay):
    assert _stage(stage, stage["t_f"], decay) == pytest.approx(stage["cds_i"], rel=1e-9)


@SETTINGS
@given(one_stage(), decays)
def test_drag_area_peaks_at_ck_cds_i_at_peak_fill_time(stage, decay):
    peak = stage["ck"] * stage["cds_i"]
    assert _stage(stage, stage["t_fp"], decay) == pytest.approx(peak, rel=1e-9)
    # and the growth reaches the same value from below: no jump at the peak
    assert _stage(stage, stage["t_fp"] * (1 - 1e-9), decay) == pytest.approx(peak, rel=1e-6)


@SETTINGS
@given(one_stage(), decays, st.floats(0.0, 5.0, **finite))
def test_decay_ends_at_cds_i_and_stays(stage, decay, extra):
    end = stage["t_fp"] + stage["t_k"]
    assert _stage(stage, end, decay) == pytest.approx(stage["cds_i"], rel=1e-9)
    assert _stage(stage, end + extra, decay) == pytest.approx(stage["cds_i"], rel=1e-9)
    # the decay is monotone from the peak down to CDS_i
    taus = stage["t_fp"] + np.linspace(0.0, stage["t_k"], 50)
    values = stage_drag_area(taus, stage["cds_start"], stage["cds_i"], stage["t_f"], stage["expopen"],
                             stage["ck"], stage["t_k"], decay=decay)
    assert np.all(np.diff(values) <= 1e-9 * stage["cds_i"])


@SETTINGS
@given(one_stage(), decays)
def test_growth_starts_from_the_held_drag_area(stage, decay):
    assert _stage(stage, 0.0, decay) == pytest.approx(stage["cds_start"], rel=1e-12, abs=1e-12)


@SETTINGS
@given(n_values, ck_values, eps_values, st.floats(0.0, 0.95, **finite), expopen_values)
def test_n_to_n_p_round_trip(n, ck, eps, held_fraction, expopen):
    cds_i = eps * 100.0
    ratio = overinflation_ratio(ck, cds_i, held_fraction * cds_i)
    n_p = n_p_from_n(n, ratio, expopen)
    assert n_from_n_p(n_p, ratio, expopen) == pytest.approx(n, rel=1e-12)
    assert n_p >= n  # over-inflation (S ≥ 1) only lengthens the distance to the peak


def test_first_stage_ratio_is_ck():
    assert overinflation_ratio(1.3, 120.0, 0.0) == pytest.approx(1.3)


@st.composite
def parachute(draw, n_stages=None):
    """One parachute, K stages, growing eps, realistic starts; arrays (K,)."""
    k = n_stages or draw(st.integers(2, 3))
    cds_o = draw(cds_o_values)
    eps = np.sort(np.array([draw(st.floats(0.04, 0.6, **finite)) for _ in range(k - 1)] + [1.0]))
    gaps = np.array([draw(st.floats(0.3, 12.0, **finite)) for _ in range(k - 1)])
    start = draw(st.floats(0.0, 2.0, **finite)) + np.concatenate([[0.0], np.cumsum(gaps)])
    return dict(
        start=start, cds_stage=eps * cds_o, cds_o=cds_o, diameter=draw(diameter_values),
        n_fill=np.array([draw(n_values) for _ in range(k)]),
        expopen=np.array([draw(expopen_values) for _ in range(k)]),
        ck=np.array([draw(ck_values) for _ in range(k)]),
        t_k=np.array([draw(tk_values) for _ in range(k)]),
        v_start=np.array([draw(speed_values) for _ in range(k)]),
    )


def _drag_area(chute, t, decay="linear", fill_constant="n_p"):
    return parachute_drag_area(t, chute["start"], chute["cds_stage"], chute["cds_o"], chute["diameter"],
                               chute["n_fill"], chute["expopen"], chute["ck"], chute["t_k"], chute["v_start"],
                               decay=decay, fill_constant=fill_constant)


@SETTINGS
@given(parachute(), decays, st.sampled_from(["n", "n_p"]))
def test_retain_at_disreef_is_continuous(chute, decay, fill_constant):
    """A disreef starts from the drag area held then: no jump (unless the stage has nothing to fill)."""
    _, timing = _drag_area(chute, np.array([0.0]), decay, fill_constant)
    for k in range(1, len(chute["start"])):
        t_next = chute["start"][k]
        before, at = _drag_area(chute, np.array([t_next * (1 - 1e-12) - 1e-12, t_next]), decay, fill_constant)[0]
        held = timing.cds_start[k]
        assert before == pytest.approx(held, rel=1e-6, abs=1e-9)
        if chute["cds_stage"][k] > held:
            assert at == pytest.approx(held, rel=1e-9, abs=1e-9)
        else:  # nothing to fill: snaps to the stage value
            assert at == pytest.approx(chute["cds_stage"][k], rel=1e-12)


@SETTINGS
@given(parachute(n_stages=2), decays, st.floats(0.0, 1.0, **finite))
def test_skipped_stage_snaps_to_its_value(chute, decay, below):
    """A stage whose drag area is not above the held one has zero fill time and is its value at once."""
    _, timing = _drag_area(chute, np.array([0.0]), decay)
    held = timing.cds_start[1]
    chute = dict(chute, cds_stage=np.array([chute["cds_stage"][0], below * held]))
    t = chute["start"][1] + np.array([0.0, 0.01, 1.0, 10.0])
    cds, timing = _drag_area(chute, t, decay)
    assert timing.t_f[1] == 0.0 and timing.t_fp[1] == 0.0
    np.testing.assert_allclose(cds, chute["cds_stage"][1], rtol=1e-12)


@SETTINGS
@given(parachute(), decays)
def test_zero_before_first_start_and_settles_at_full_open(chute, decay):
    t = np.array([chute["start"][0] - 0.5, chute["start"][0] - 1e-9])
    cds, _ = _drag_area(chute, t, decay)
    np.testing.assert_array_equal(cds, 0.0)
    cds_late, timing = _drag_area(chute, np.array([chute["start"][-1] + 1e4]), decay)
    if chute["cds_stage"][-1] > timing.cds_start[-1]:
        assert cds_late[0] == pytest.approx(chute["cds_stage"][-1], rel=1e-9)


@SETTINGS
@given(st.lists(parachute(n_stages=3), min_size=2, max_size=5), decays, st.sampled_from(["n", "n_p"]))
def test_batch_evaluation_equals_row_by_row(chutes, decay, fill_constant):
    t = np.linspace(0.0, 40.0, 400)
    stacked = {key: np.stack([np.asarray(c[key], float) for c in chutes]) for key in chutes[0]}
    batch, batch_timing = _drag_area(stacked, t, decay, fill_constant)
    for b, chute in enumerate(chutes):
        row, timing = _drag_area(chute, t, decay, fill_constant)
        np.testing.assert_allclose(batch[b], row, rtol=1e-13, atol=0)
        for name in ("cds_start", "t_f", "t_fp", "n", "n_p"):
            np.testing.assert_allclose(getattr(batch_timing, name)[b], getattr(timing, name), rtol=1e-13)


def test_two_batch_axes_broadcast_against_shared_times():
    rng = np.random.default_rng(3)
    shape = (4, 3, 2)  # walkers, parachutes, stages
    start = np.sort(rng.uniform(0.5, 12.0, shape), axis=-1)
    cds = np.sort(rng.uniform(10.0, 200.0, shape), axis=-1)
    args = (start, cds, cds[..., -1] * 1.05, 7.0, rng.uniform(5, 15, shape), rng.uniform(1, 3, shape),
            rng.uniform(1.0, 1.4, shape), rng.uniform(0.2, 0.8, shape), rng.uniform(40, 120, shape))
    t = np.linspace(0, 20, 50)
    out, timing = parachute_drag_area(t, *args)
    assert out.shape == (4, 3, 50) and timing.t_f.shape == shape
    single, _ = parachute_drag_area(t, *(a[2, 1] if np.ndim(a) >= 2 else a for a in args))
    np.testing.assert_allclose(out[2, 1], single, rtol=1e-13)


def test_fill_time_is_eq_14():
    # t_f = n·D_o·sqrt((CDS_i − CDS_start)/CDS_o)/V_i
    assert fill_time(10.0, 7.0, 20.0, 120.0, 250.0, 100.0) == pytest.approx(10 * 7 * np.sqrt(100 / 250) / 100)
    assert fill_time(10.0, 7.0, 130.0, 120.0, 250.0, 100.0) == 0.0

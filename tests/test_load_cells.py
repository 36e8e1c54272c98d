"""The load cells' reading at lagged times: the shared interpolation walk, and the law and air data handed to
the terms there."""

from dataclasses import replace

import numpy as np
import pytest

from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.data.synth import synthesize
from cpas_bayes.inference.fit import prepare_model
from cpas_bayes.stats.likelihood_kernel import interp_rows
from cpas_bayes.stats.model_parts import Context
from cpas_bayes.stats.model_terms import make_extension


def test_one_walk_gives_what_np_interp_gives_each_series():
    rng = np.random.default_rng(3)
    xp = np.cumsum(rng.uniform(0.005, 0.02, 300))
    fps = rng.standard_normal((3, xp.size))
    base = np.sort(rng.uniform(xp[0] - 0.2, xp[-1] + 0.2, 150))
    shifts = np.array([0.0, 0.013, -0.4, 0.35])
    x = base[None, :] - shifts[:, None]
    x[0, 10] = xp[40]                       # a point on a sample
    x[2, 5:8] = x[2, 5:8][::-1].copy()      # a row that is not increasing: searched afresh, still right
    out = interp_rows(x, xp, fps, np.empty((3,) + x.shape))
    for s in range(3):
        for r in range(x.shape[0]):
            np.testing.assert_array_equal(out[s, r], np.interp(x[r], xp, fps[s]))


@pytest.fixture(scope="module")
def lagged_drogue():
    test, _ = synthesize("drogue", "sensor_lag+added_mass", 30015)
    model = prepare_model(test, reduce_test(test), extensions=[make_extension("added_mass"),
                                                               make_extension("sensor_lag")])
    theta = np.array([p.prior.ppf(0.5) for p in model.parameters])
    rows = np.repeat(theta[None], 3, axis=0)
    rows[:, model.index["k_a"]] = [0.3, 0.8, 1.2]
    rows[:, model.index["mass_lag"]] = [0.0, 0.05, 0.2]
    return model, rows


def test_the_law_and_air_data_handed_to_the_added_mass_at_lagged_times_are_what_it_would_read(lagged_drogue):
    model, rows = lagged_drogue
    values = model.values(rows)
    stage = model.gather_stages(rows)
    ctx = Context(model, rows, values, model.obs.time, stage)
    ctx.stage["timing"] = model.drag_areas(stage, model.obs.time)[1]
    tt = (model.obs.time[None, :] - np.array([0.0, 0.021, 0.3])[:, None])[:, None, :]
    cds, rate, _ = model.drag_areas(stage, tt, with_rate=True)
    obs = model.obs      # each series by name with np.interp: Context.air's order (ρ, V, q̄, γ, dρ/dt)
    air = (obs.density_at(tt), obs.airspeed_at(tt), obs.qbar_at(tt), obs.gamma_at(tt),
           np.interp(tt, obs.native_time, obs.native_density_rate))
    handed = model.apparent_drag_area(replace(ctx, time=tt, law=(cds, rate), air=air), tt)
    computed = model.apparent_drag_area(replace(ctx, time=model.obs.time, law=None), tt)
    np.testing.assert_allclose(handed, computed, rtol=0, atol=1e-12)
    assert np.abs(handed).max() > 0.01     # an added mass there to compare


def test_a_lag_of_zero_reads_as_no_lag(lagged_drogue):
    model, rows = lagged_drogue
    plain = prepare_model(model.test, reduce_test(model.test), extensions=[make_extension("added_mass")])
    at_zero = rows.copy()
    at_zero[:, model.index["lag"]] = 0.0
    at_zero[:, model.index["lag_response"]] = 0.0
    keep = [model.index[n] for n in plain.names]
    np.testing.assert_allclose(model.predict(at_zero).lc, plain.predict(at_zero[:, keep]).lc, rtol=1e-12, atol=1e-12)
    lagged = model.predict(rows).lc
    assert np.abs(lagged - plain.predict(rows[:, keep]).lc).max() > 0.1    # the prior's median lag shows

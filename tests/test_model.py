"""The test model: compiled stage law, likelihood identities, batching, consistency with data."""

import dataclasses
import json

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.data.bundle import example_bundles, read_bundle
from cpas_bayes.inference.fit import prepare_model
from cpas_bayes.inference.start import first_guess
from cpas_bayes.physics.inflation import DECAY_SHAPES, cluster_drag_area, parachute_drag_area
from cpas_bayes.stats.model import TestModel
from cpas_bayes.stats.model_parts import Extension
from cpas_bayes.data.synth import truth_parameter_values


@pytest.fixture(scope="module")
def examples():
    out = {}
    for path in example_bundles():
        test = read_bundle(path)
        truth = json.loads((path / "truth.json").read_text())
        out[path.name] = (test, prepare_model(test, reduce_test(test)), truth_parameter_values(test, truth))
    return out


def _theta(model, values, rest=1.0):
    return np.array([values.get(n, rest) for n in model.names])


@pytest.mark.parametrize("decay", DECAY_SHAPES)
@pytest.mark.parametrize("fill_constant", ["n_p", "n"])
def test_compiled_kernel_equals_numpy_stage_law(decay, fill_constant):
    rng = np.random.default_rng(4)
    B, P, K = 7, 3, 3
    start = np.sort(rng.uniform(0.5, 20.0, (B, P, K)), axis=-1)
    cds_o = rng.uniform(20.0, 500.0, (B, P))
    eps = np.concatenate([np.sort(rng.uniform(0.05, 0.9, (B, P, K - 1)), axis=-1), np.ones((B, P, 1))], axis=-1)
    args = dict(start=start, cds_stage=eps * cds_o[..., None], cds_o=cds_o, diameter=np.array([7.0, 20.0, 35.0]),
                n_fill=rng.uniform(3, 20, (B, P, K)), expopen=rng.uniform(0.5, 3.0, (B, P, K)),
                ck=rng.uniform(1.0, 1.6, (B, P, K)), t_k=rng.uniform(0.0, 1.0, (B, P, K)),
                v_start=rng.uniform(20, 150, (B, P, K)))
    t = np.linspace(0.0, 25.0, 3001)
    fast, fast_timing = cluster_drag_area(t, decay=decay, fill_constant=fill_constant, **args)
    reference, ref_timing = parachute_drag_area(t, *(args[k] for k in ("start", "cds_stage")),
                                                args["cds_o"], args["diameter"][None, :],
                                                *(args[k] for k in ("n_fill", "expopen", "ck", "t_k", "v_start")),
                                                decay=decay, fill_constant=fill_constant)
    np.testing.assert_allclose(fast, reference, rtol=1e-12, atol=1e-9)
    for field in ("t_f", "t_fp", "n", "n_p", "cds_start"):
        np.testing.assert_allclose(getattr(fast_timing, field), getattr(ref_timing, field), rtol=1e-12, atol=1e-12)
    # One time base per row (a shifted sensor) gives row-by-row the same law.
    shifted, _ = cluster_drag_area(t[None, :] - 0.05 * np.arange(B)[:, None], decay=decay,
                                   fill_constant=fill_constant, **args)
    for b in (0, 3, 6):
        row, _ = cluster_drag_area(t - 0.05 * b, decay=decay, fill_constant=fill_constant,
                                   **{k: (v[b:b + 1] if k != "diameter" else v) for k, v in args.items()})
        np.testing.assert_allclose(shifted[b], row[0], rtol=1e-12)


@pytest.mark.parametrize("name", ["drogue-clean", "main-clean"])
def test_data_of_the_independent_simulator_fit_the_model_at_truth(examples, name):
    """At the true parameters the normalised residuals of every channel have unit variance."""
    test, model, truth = examples[name]
    theta = _theta(model, truth)[None]
    pred = model.predict(theta)
    obs = model.obs
    r_acc = (obs.acc - pred.acc[0]) / np.hypot(obs.acc_sigma, obs.acc_qbar)
    r_lc = (obs.lc - pred.lc[0]) / np.hypot(obs.lc_sigma, obs.lc_qbar)
    assert 0.85 < np.mean(r_acc**2) < 1.2
    for row in r_lc:
        assert 0.85 < np.mean(row**2) < 1.2
        assert abs(np.mean(row)) < 0.25


def test_joint_likelihood_equals_dense_multivariate_normal(examples):
    test, model, truth = examples["main-clean"]
    theta = _theta(model, truth)[None].repeat(3, axis=0)
    theta[:, model.index["noise_acc"]] = [1.0, 1.3, 0.8]
    theta[:, model.index["noise_lc"]] = [1.0, 0.7, 1.6]
    theta[1, model.index["M2.s2.n_p"]] *= 1.05
    pointwise = model.pointwise_log_likelihood(theta)
    np.testing.assert_allclose(model.log_likelihood(theta), pointwise.sum(axis=1), rtol=1e-12)
    pred, obs = model.predict(theta), model.obs
    for b, t in [(0, 10), (1, 200), (2, obs.n_bins - 1)]:
        lam = np.r_[theta[b, model.index["noise_acc"]], np.full(obs.lc.shape[0], theta[b, model.index["noise_lc"]])]
        u = np.r_[obs.acc_qbar[t], obs.lc_qbar[:, t]]
        cov = np.outer(lam, lam) * (np.diag(np.r_[obs.acc_sigma[t], obs.lc_sigma[:, t]] ** 2) + np.outer(u, u))
        y = np.r_[obs.acc[t], obs.lc[:, t]]
        mean = np.r_[pred.acc[b, t], pred.lc[b, :, t]]
        assert pointwise[b, t] == pytest.approx(multivariate_normal(mean, cov).logpdf(y), rel=1e-10)


def test_any_batch_size_gives_the_same_rows(examples):
    _, model, _ = examples["drogue-clean"]
    rng = np.random.default_rng(2)
    theta = first_guess(model) * (1 + 1e-3 * rng.standard_normal((64, model.ndim)))
    full = model(theta)
    assert np.isfinite(full).all()
    pieces = np.concatenate([model(theta[i:i + n]) for i, n in zip((0, 1, 8, 37), (1, 7, 29, 27))])
    np.testing.assert_array_equal(full, pieces)
    assert model(theta[5]) == pytest.approx(full[5], rel=0, abs=0)


def test_posterior_is_minus_inf_outside_the_prior_never_nan(examples):
    _, model, _ = examples["main-clean"]
    rng = np.random.default_rng(3)
    draws = model.sample_prior(rng, 200)
    lp = model(draws)
    assert not np.isnan(lp).any()
    bad = draws[:3].copy()
    bad[0, model.index["M1.s1.eps"]] = 1.5                          # outside its uniform prior
    bad[1, model.index["M1.s2.start"]] = bad[1, model.index["M1.s1.start"]] - 0.1   # stages out of order
    bad[2, model.index["noise_acc"]] = -1.0
    assert (model(bad) == -np.inf).all()


def test_a_hookless_extension_leaves_the_model_unchanged(examples):
    test, model, truth = examples["drogue-clean"]
    extended = TestModel(test, model.obs, model.kind_priors, model.nuisance_priors, extensions=[Extension()])
    theta = _theta(model, truth)[None]
    assert extended.names == model.names
    assert extended.log_posterior(theta)[0] == pytest.approx(model.log_posterior(theta)[0], rel=1e-14)


def test_derived_n_matches_the_truth_files(examples):
    """n from the sampled n_p by Eq. 18, with the retained drag area, equals the simulator's n."""
    for test, model, truth in examples.values():
        derived = model.derived(_theta(model, truth)[None])
        for name, value in truth.items():
            if name.endswith(".n"):
                assert derived[name][0] == pytest.approx(value, rel=1e-6)


# ---------------------------------------------------------------------------
# The fused baseline likelihood against the numpy pipeline


def _with_chutes(test, **options):
    """The model of ``test`` with edited parachutes: {index: dataclasses.replace changes}."""
    chutes = list(test.parachutes)
    for i, changes in options.pop("chutes", {}).items():
        chutes[i] = dataclasses.replace(chutes[i], **changes)
    edited = dataclasses.replace(test, parachutes=tuple(chutes))
    return prepare_model(edited, reduce_test(edited), **options)


def _rows_near_first_guess(model, rng, n=40):
    x = first_guess(model)
    rows = x + 1e-3 * rng.standard_normal((n, model.ndim)) * np.abs(x + 1e-3)
    # Edge cases of the stage law: a stage with nothing to fill (the first stage of row 0
    # held at full open, over-inflated above the second), no decay time, a bin exactly at a start.
    for name in model.names:
        if name.endswith(".s1.eps"):
            rows[0, model.index[name]] = 1.0
        if name.endswith(".s1.ck"):
            rows[0, model.index[name]] = 1.4
        if name.endswith(".tk"):
            rows[1, model.index[name]] = 0.0
        if name.endswith(".s2.start"):
            rows[2, model.index[name]] = model.obs.time[np.searchsorted(model.obs.time, rows[2, model.index[name]])]
    return rows


def _assert_fused_equals_numpy(model, rows):
    fused = model.log_likelihood(rows)
    reference = model.pointwise_log_likelihood(rows).sum(axis=1)
    finite = np.isfinite(reference)
    assert finite.any()
    np.testing.assert_array_equal(np.isfinite(fused), finite)
    np.testing.assert_allclose(fused[finite], reference[finite], rtol=1e-10)
    # The posterior: the prior plus that likelihood, −inf (never NaN) outside the prior.
    lp = model.log_prior(rows)
    post = model.log_posterior(rows)
    assert not np.isnan(post).any()
    inside = np.isfinite(lp) & finite
    np.testing.assert_allclose(post[inside], lp[inside] + reference[inside], rtol=1e-10)
    assert (post[~np.isfinite(lp)] == -np.inf).all()


@pytest.mark.parametrize("name", ["drogue-clean", "main-clean"])
def test_fused_baseline_likelihood_equals_the_numpy_pipeline(examples, name):
    test, model, _ = examples[name]
    assert model.extensions == ()
    rng = np.random.default_rng(11)
    _assert_fused_equals_numpy(model, _rows_near_first_guess(model, rng))
    draws = model.sample_prior(rng, 64)
    assert np.isfinite(model.log_prior(draws)).sum() > 32
    _assert_fused_equals_numpy(model, draws)
    exponential = prepare_model(test, reduce_test(test), decay="exponential")
    _assert_fused_equals_numpy(exponential, _rows_near_first_guess(exponential, rng))


def test_fused_stage_with_nothing_to_fill_snaps_to_its_value(examples):
    _, model, _ = examples["drogue-clean"]
    rows = _rows_near_first_guess(model, np.random.default_rng(5), n=3)
    pred = model.predict(rows)
    assert (pred.timing.t_f[0, :, 1] == 0).all() and (pred.timing.t_f[1:, :, 1] > 0).all()


def test_fused_likelihood_of_the_accelerometer_alone(examples):
    test, _, _ = examples["drogue-clean"]
    model = _with_chutes(test, chutes={i: {"load_cell": None} for i in range(len(test.parachutes))})
    assert model.obs.lc.shape[0] == 0 and "load_scale" not in model.index and "noise_lc" not in model.index
    rng = np.random.default_rng(6)
    _assert_fused_equals_numpy(model, _rows_near_first_guess(model, rng))
    _assert_fused_equals_numpy(model, model.sample_prior(rng, 64))


def test_parachutes_with_different_stage_counts(examples):
    """A one-stage canopy beside three-stage ones: padded stage slots neither fail the stage-order
    check of the prior nor enter the fused likelihood."""
    test, _, _ = examples["main-clean"]
    model = _with_chutes(test, chutes={0: {"stages": test.parachutes[0].stages[-1:]}})
    np.testing.assert_array_equal(model.stages_per_chute, [1, 3, 3])
    rng = np.random.default_rng(8)
    draws = model.sample_prior(rng, 64)
    assert np.isfinite(model.log_prior(draws)).sum() > 32
    assert np.isfinite(model(first_guess(model))).all()
    _assert_fused_equals_numpy(model, _rows_near_first_guess(model, rng))
    _assert_fused_equals_numpy(model, draws)


def test_log_prior_is_the_prior_set_plus_the_stage_order(examples):
    for _, model, _ in examples.values():
        draws = model.sample_prior(np.random.default_rng(9), 200)
        draws[::7, 3] = np.nan
        draws[1::7, model.index["noise_acc"]] = -1.0
        reference = model.prior_set.logpdf(draws)
        lp = model.log_prior(draws)
        assert not np.isnan(lp).any()
        finite = np.isfinite(lp)
        assert finite.sum() > 100 and not finite[::7].any() and not finite[1::7].any()
        np.testing.assert_allclose(lp[finite], reference[finite], rtol=1e-12)
        # What the model's prior refuses beyond the prior set is the stage order alone.
        earlier, later = model._start_order
        out_of_order = ~np.all(draws[:, later] > draws[:, earlier], axis=1)
        np.testing.assert_array_equal(~finite, out_of_order | ~np.isfinite(reference))


def test_compiled_point_interpolation_equals_numpy():
    from cpas_bayes.stats.likelihood_kernel import interp
    xp = np.cumsum(np.random.default_rng(1).uniform(0.01, 0.1, 50))
    fp = np.sin(xp)
    for x in np.r_[xp[0] - 1, xp[0], xp[[3, 17]], 0.5 * (xp[20] + xp[21]), xp[-1], xp[-1] + 1,
                   np.random.default_rng(2).uniform(xp[0], xp[-1], 20)]:
        assert interp(x, xp, fp) == np.interp(x, xp, fp)
    assert np.isnan(interp(np.nan, xp, fp))


# ---------------------------------------------------------------------------
# cluster form and decay shape


def test_composite_of_one_parachute_is_the_individual_model(examples):
    test, _, _ = examples["drogue-clean"]
    one = dataclasses.replace(test, parachutes=test.parachutes[:1])
    reduction = reduce_test(one)
    individual = prepare_model(one, reduction)
    composite = prepare_model(one, reduction, cluster="composite")
    pid = one.parachutes[0].id
    rename = {n: n.replace(f"{pid}.", "cluster.drogue.", 1) if n.startswith(f"{pid}.") else n
              for n in individual.names}
    assert sorted(rename.values()) == sorted(composite.names)
    for name in individual.names:   # the same priors under the other names
        assert (individual.parameters[individual.index[name]].prior.describe()
                == composite.parameters[composite.index[rename[name]]].prior.describe())
    rng = np.random.default_rng(21)
    draws = np.vstack([individual.sample_prior(rng, 48), _rows_near_first_guess(individual, rng, n=16)])
    columns = [individual.index[n] for n in (next(i for i, r in rename.items() if r == c) for c in composite.names)]
    np.testing.assert_array_equal(composite(draws[:, columns]), individual(draws))
    np.testing.assert_array_equal(composite.pointwise_log_likelihood(draws[:, columns]),
                                  individual.pointwise_log_likelihood(draws))


@pytest.mark.parametrize("name", ["drogue-clean", "main-clean"])
def test_composite_cluster_inflates_in_lockstep(examples, name):
    test, individual, _ = examples[name]
    composite = prepare_model(test, reduce_test(test), cluster="composite")
    kind = test.parachutes[0].kind
    assert composite.chute_prefix == [f"cluster.{kind}"] * len(test.parachutes)
    per_chute = 1 + sum(1 for n in individual.names if n.startswith(f"{test.parachutes[0].id}.s"))
    assert composite.ndim == individual.ndim - (len(test.parachutes) - 1) * per_chute
    # The tied stage start: the mean of the stated starts, sd from their stated sd and their spread.
    starts = np.array([[s.start for s in p.stages] for p in test.parachutes])
    sigmas = np.array([[s.start_sigma for s in p.stages] for p in test.parachutes])
    prior = composite.parameters[composite.index[f"cluster.{kind}.s2.start"]].prior.describe()
    assert prior["mu"] == pytest.approx(starts[:, 1].mean())
    assert prior["sigma"] == pytest.approx(np.sqrt(np.mean(sigmas[:, 1] ** 2) + starts[:, 1].var()))
    rng = np.random.default_rng(12)
    draws = composite.sample_prior(rng, 32)
    pred = composite.predict(draws)
    np.testing.assert_array_equal(pred.cds, np.repeat(pred.cds[:, :1], len(test.parachutes), axis=1))
    # Every parachute's view of the shared parameters, under the individual form's names.
    derived = composite.derived(draws)
    for i, p in enumerate(test.parachutes):
        assert composite.parameter_name(i, "s1.n_p") == f"cluster.{kind}.s1.n_p"
        np.testing.assert_array_equal(derived[f"{p.id}.cds_o"], draws[:, composite.index[f"cluster.{kind}.cds_o"]])
        np.testing.assert_array_equal(derived[f"{p.id}.s1.start"],
                                      draws[:, composite.index[f"cluster.{kind}.s1.start"]])
    assert np.isfinite(composite(first_guess(composite)[None])).all()


@pytest.mark.parametrize("cluster", ["individual", "composite"])
@pytest.mark.parametrize("decay", DECAY_SHAPES)
@pytest.mark.parametrize("name", ["drogue-clean", "main-clean"])
def test_fused_likelihood_equals_numpy_for_each_decay_and_cluster_form(examples, name, decay, cluster):
    test, _, _ = examples[name]
    model = prepare_model(test, reduce_test(test), decay=decay, cluster=cluster)
    assert model.decay == decay and model.cluster == cluster
    rng = np.random.default_rng(13)
    draws = model.sample_prior(rng, 48)
    draws = draws[np.isfinite(model.log_prior(draws))]
    assert draws.shape[0] > 24
    fused = model.log_likelihood(draws)
    reference = model.pointwise_log_likelihood(draws).sum(axis=1)
    np.testing.assert_allclose(fused, reference, rtol=1e-8)
    _assert_fused_equals_numpy(model, _rows_near_first_guess(model, rng))


def test_unknown_cluster_form_is_refused(examples):
    test, _, _ = examples["drogue-clean"]
    with pytest.raises(ValueError, match="cluster must be one of"):
        prepare_model(test, reduce_test(test), cluster="summed")


@pytest.mark.parametrize("name, cells", [("main-clean", True), ("drogue-clean", False)])
def test_fused_whitened_residuals_equal_whitening_the_residuals(examples, name, cells):
    """The compiled whitened residuals (the discrepancy's every call) are :meth:`whiten` of the residuals over
    their multipliers, and their squares sum per bin to the likelihood's quadratic form; also without load
    cells (one channel)."""
    test, model, truth = examples[name]
    if not cells:
        model = _with_chutes(test, chutes={i: {"load_cell": None} for i in range(len(test.parachutes))})
    theta = _rows_near_first_guess(model, np.random.default_rng(12), n=5)
    pred, obs = model.predict(theta), model.obs
    z, _ = model.whitened_residuals(theta, pred)
    r = np.concatenate([((obs.acc[None] - pred.acc) / pred.noise_acc[:, None])[:, None],
                        (obs.lc[None] - pred.lc) / pred.noise_lc[:, None, None]], axis=1)
    np.testing.assert_allclose(z, model.whiten(r), rtol=1e-12, atol=1e-12 * np.abs(z).max())
    quad, _, _ = model._quadratic_form(theta, pred)
    np.testing.assert_allclose((z**2).sum(axis=1), quad, rtol=1e-10)

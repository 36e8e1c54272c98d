"""The vectorised rank diagnostics equal ArviZ's, parameter by parameter, on draws with the features
MCMC output has: autocorrelation of either sign, ties (rejected moves repeat a value), a parameter that
never moves, chains too short for the initial sequence, and NaN."""

import numpy as np
import pytest
from arviz_stats.base import array_stats

from cpas_bayes.inference import rank_diagnostics as rd
from cpas_bayes.inference.stopping import chain_statistics


def _ar1(rng, d, c, s, phi):
    e = rng.standard_normal((d, c, s))
    x = np.empty_like(e)
    x[..., 0] = e[..., 0]
    for t in range(1, s):
        x[..., t] = phi * x[..., t - 1] + e[..., t]
    return x


def _cases(n=120, seed=7):
    rng = np.random.default_rng(seed)
    for i in range(n):
        d, c, s = int(rng.integers(1, 5)), int(rng.integers(1, 9)), int(rng.integers(4, 90))
        x = _ar1(rng, d, c, s, float(rng.uniform(-0.6, 0.99)))
        if i % 5 == 0:
            x = np.round(x)            # many ties
        if i % 9 == 0:
            x[0] = 2.5                 # a parameter that never moves
        if i % 13 == 0 and d > 1:
            x[1, 0, 0] = np.nan
        yield i, x


@pytest.mark.parametrize("method", ["bulk", "tail"])
def test_ess_equals_arviz(method):
    for i, x in _cases():
        ours = rd.ess_bulk(x) if method == "bulk" else rd.ess_tail(x, (0.05, 0.95))
        ref = np.asarray(array_stats.ess(x, method=method, **({"prob": (0.05, 0.95)} if method == "tail" else {})),
                         float)
        np.testing.assert_allclose(ours, ref, rtol=1e-9, equal_nan=True, err_msg=f"case {i}, shape {x.shape}")


@pytest.mark.filterwarnings("ignore:invalid value")
def test_rhat_equals_arviz_nested_and_plain():
    for i, x in _cases():
        c = x.shape[1]
        if c < 2:
            continue
        if c % 2 == 0:
            ids = np.repeat([0, 1], c // 2)
            ref = np.asarray(array_stats.rhat_nested(x, superchain_ids=ids), float)
            np.testing.assert_allclose(rd.rhat_nested(x, ids), ref, rtol=1e-9, equal_nan=True, err_msg=f"case {i}")
        ref = np.asarray(array_stats.rhat(x), float)
        np.testing.assert_allclose(rd.rhat_nested(x, np.zeros(c, int)), ref, rtol=1e-9, equal_nan=True,
                                   err_msg=f"case {i}")


def test_average_ranks_share_ties():
    v = np.array([[3.0, 1.0, 3.0, 2.0, 3.0]])
    np.testing.assert_array_equal(rd.average_ranks(v), [[4.0, 1.0, 4.0, 2.0, 4.0]])


def test_chain_statistics_of_the_stopping_rule_are_arviz_numbers():
    rng = np.random.default_rng(3)
    chains = np.moveaxis(_ar1(rng, 5, 24, 60, 0.8), 0, -1)          # (C, S, D) as the sampler stores them
    ensemble = np.repeat(np.arange(4), 6)
    st = chain_statistics(chains, ensemble)
    by = np.moveaxis(chains, -1, 0)
    np.testing.assert_allclose(st.ess_bulk, array_stats.ess(by, method="bulk"), rtol=1e-9)
    np.testing.assert_allclose(st.ess_tail, array_stats.ess(by, method="tail", prob=(0.05, 0.95)), rtol=1e-9)
    np.testing.assert_allclose(st.rhat, array_stats.rhat_nested(by, superchain_ids=ensemble), rtol=1e-9)


def test_unequal_superchains_are_refused():
    x = np.random.default_rng(0).standard_normal((2, 3, 20))
    with pytest.raises(ValueError, match="same number of chains"):
        rd.rhat_nested(x, np.array([0, 0, 1]))


@pytest.mark.parametrize("ensembles", [1, 3])
def test_fit_convergence_reports_arviz_numbers(ensembles):
    """A fit's summary diagnostics (fit_folder.convergence) equal arviz_stats' own on the fit's DataTree:
    nested R-hat over ensembles (plain rank R-hat for one), bulk ESS and the 5 %/95 % tail ESS."""
    import types

    import arviz_base as azb
    import arviz_stats as azs

    from cpas_bayes.inference.fit_folder import convergence

    rng = np.random.default_rng(11)
    walkers, draws, names = 6, 60, ["a", "b.s1.n_p", "c"]
    x = _ar1(rng, len(names), ensembles * walkers, draws, 0.7)
    x[2] = np.round(x[2])                                   # ties, as rejected moves repeat a value
    ensemble = np.repeat(np.arange(ensembles), walkers)
    tree = azb.from_dict({"posterior": {n: x[i] for i, n in enumerate(names)}})
    tree["posterior"] = tree["posterior"].to_dataset().assign_coords(ensemble=("chain", ensemble))
    runs = [types.SimpleNamespace(tau=np.ones(3), acceptance=0.3, steps=draws, converged=True)] * ensembles
    got = convergence(tree, types.SimpleNamespace(names=names, runs=runs, extras={}))["per_parameter"]
    rhat = (azs.rhat_nested(tree, var_names=names, superchain_ids=ensemble) if ensembles > 1
            else azs.rhat(tree, var_names=names))
    bulk = azs.ess(tree, var_names=names, method="bulk")
    tail = azs.ess(tree, var_names=names, method="tail", prob=(0.05, 0.95))
    for n in names:
        np.testing.assert_allclose([got[n]["rhat"], got[n]["ess_bulk"], got[n]["ess_tail"]],
                                   [float(rhat[n]), float(bulk[n]), float(tail[n])], rtol=1e-9, err_msg=n)

"""The notebook route: the whole chain through ``import cpas_bayes`` alone, in memory.

Read the bundled two-Drogue example and a synthetic two-Drogue test, reduce,
fit, diagnose, pool the two fits into a memo, run the Monte Carlo and compare
the measured peak loads — without writing a file. Asserts what each step must
get right: the fit's 90 % intervals contain the example's true values, the
clean example is diagnosed ``none``, the memo's Drogue n_p population holds
both tests' fitted values, and the measured peak loads sit inside the
predicted distributions.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

import cpas_bayes as cb
from cpas_bayes.data.synth import truth_parameter_values

pytestmark = pytest.mark.slow

OPTIONS = dict(n_ensembles=2, max_steps=3000, check_every=500, map_starts=2, workers=1, progress=False)


def test_every_public_name_resolves():
    missing = [name for name in cb.__all__ if getattr(cb, name, None) is None]
    assert not missing
    with pytest.raises(AttributeError, match="no attribute 'not_a_step'"):
        cb.not_a_step  # noqa: B018


def test_whole_chain_in_memory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # anything written by accident lands here
    example = next(p for p in cb.example_bundles() if p.name.startswith("drogue"))
    test = cb.read_bundle(example)
    truth = truth_parameter_values(test, json.loads((example / "truth.json").read_text()))
    other, _ = cb.synthesize("drogue", "none", 11)

    fits = []
    for i, t in enumerate((test, other)):
        reduction = cb.reduce_test(t)
        fits.append(cb.fit_model(cb.prepare_model(t, reduction), cb.SamplerOptions(seed=i, **OPTIONS)))
    fit = fits[0]

    # the fit recovers the example's truth: 90 % intervals cover >= 80 % of the inflation parameters
    post = fit.tree["posterior"]
    names = [n for n in truth if n in post and "." in n]
    assert len(names) >= 20
    covered = [np.quantile(post[n].values, 0.05) <= truth[n] <= np.quantile(post[n].values, 0.95) for n in names]
    assert np.mean(covered) >= 0.8, dict(zip(names, covered))

    # one candidate: the chain's hand-over from fit to diagnosis, not the catalogue (tests/test_diagnose.py)
    diagnosis = cb.diagnose_test(test, cb.DiagnoseOptions(seed=0, mode="screen", model_forms=False,
                                                          candidates=("sensor_lag",),
                                                          sampler=cb.SamplerOptions(seed=0, **OPTIONS)),
                                 reduction=cb.reduce_test(test), baseline_fit=fit)
    assert diagnosis.cause == "none"

    pooled = cb.pool_fits([cb.FitRecord.from_fit(f) for f in fits], np.random.default_rng(0), n_draws=2000)
    memo = pooled.to_memo()
    entry = memo.entry("drogue", "first", "n_p")
    fitted = [f.summary["parachutes"][pid]["stages"][0]["n_p"]["q50"]
              for f in fits for pid in f.summary["parachutes"]]
    assert entry.n_tests == 2
    assert entry.quantiles["q01"] < min(fitted) and max(fitted) < entry.quantiles["q99"]

    comparison = cb.compare_loads(test, memo, cb.FitRecord.from_fit(fit), runs=1000,
                                  rng=np.random.default_rng(1))
    assert comparison.comparisons
    for c in comparison.comparisons:
        assert 0.5 < c.percentile < 99.5, c  # percent

    assert not os.listdir(tmp_path), "the in-memory chain wrote files"

"""PSIS: the vectorised smoothing against ArviZ's one-row-at-a-time implementation, and the fit's LOO through it."""

import warnings

import numpy as np
import pytest
from arviz_stats.base import array_stats

from cpas_bayes.stats.psis import arviz_tail, paper_tail, psis_log_weights


@pytest.mark.parametrize("sd, n_draws, r_eff", [(0.5, 2000, 1.0), (3.0, 4000, 1.0), (1.0, 400, 0.6), (2.0, 150, 1.0)])
def test_smoothed_weights_match_arviz_row_by_row(sd, n_draws, r_eff):
    rng = np.random.default_rng(7)
    log_lik = rng.normal(0.0, sd, (40, n_draws))
    lw, k = psis_log_weights(-log_lik, tail=arviz_tail(n_draws, r_eff))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lw_ref, k_ref = array_stats.psislw(log_lik, r_eff=r_eff, axis=-1)
    np.testing.assert_allclose(lw, lw_ref, atol=1e-10)
    np.testing.assert_allclose(k, k_ref, atol=1e-10)
    # heavier ratios, larger k̂: the diagnostic itself is exercised, not only the arithmetic
    if sd >= 3.0:
        assert np.median(k) > 0.7
    if sd <= 1.0:
        assert np.median(k) < 0.7


def test_rows_are_smoothed_independently_and_normalised():
    rng = np.random.default_rng(3)
    rows = np.stack([rng.normal(0.0, 0.3, 1000), rng.normal(0.0, 4.0, 1000), np.zeros(1000)])
    lw, k = psis_log_weights(rows)
    for i, row in enumerate(rows):
        lw_i, k_i = psis_log_weights(row)
        np.testing.assert_allclose(lw[i], lw_i, atol=1e-12)
        assert k[i] == pytest.approx(k_i) or (np.isinf(k[i]) and np.isinf(k_i))
    np.testing.assert_allclose(np.exp(lw).sum(axis=1), 1.0)
    assert k[0] < 0.5 < 0.7 < k[1]
    assert k[2] == -np.inf                      # equal weights: nothing to smooth, only normalised
    assert np.allclose(lw[2], -np.log(1000))


def test_tail_rules():
    assert paper_tail(2000) == 135 and arviz_tail(2000) == 134
    assert paper_tail(400) == arviz_tail(400) == 60
    assert arviz_tail(200, 1.0) == 40 and arviz_tail(4000, 0.25) == 379


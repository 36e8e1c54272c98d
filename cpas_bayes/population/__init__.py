"""Pooling many tests' posteriors into population distributions: the model memo for Monte Carlo.

``pool`` turns fits (folders or in memory) into a population; ``families``,
``reweighting``, ``hyper_posterior`` and ``copula`` hold the method (importance
weights smoothed by :mod:`cpas_bayes.stats.psis`);
``memo`` is the memo's data and file format (the memo folder is written by
:mod:`cpas_bayes.outputs.memo`).
"""

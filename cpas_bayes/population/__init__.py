"""Pooling many tests' posteriors into population distributions: the model memo for Monte Carlo.

``pool`` turns fits (folders or in memory) into a population; ``families``,
``reweighting``, ``hyper_posterior``, ``copula`` and ``psis`` hold the method;
``memo`` is the memo's data and file format (the memo folder is written by
:mod:`cpas_bayes.outputs.memo`).
"""

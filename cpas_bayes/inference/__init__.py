"""Posterior inference: MAP and emcee ensembles with checkpoints (fit), the fit folder's files
(fit_folder), posterior predictive checks and the diagnosis of what the simulation gets wrong.
"""

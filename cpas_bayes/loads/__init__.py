"""Loads from the memo: Monte Carlo of a cluster configuration, the n_p vs n fill-time study and the
comparison of measured peak loads with predicted distributions.
"""

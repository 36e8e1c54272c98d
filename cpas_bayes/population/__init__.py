"""Pooling many tests' posteriors into population distributions: the model memo for Monte Carlo.
"""

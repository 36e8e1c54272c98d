"""The statistical model: prior distributions and prior files, observations built from a reduction, the
batched test model (likelihood), and the optional model terms that extend it.
"""

"""Flight-test data: the bundle format (read, validate, write), the reduction of measurements to loads
and drag areas with 1-sigma (seed Eq. 6-13), synthetic tests with known truth, and the package data
(example bundles, the shipped prior files).
"""

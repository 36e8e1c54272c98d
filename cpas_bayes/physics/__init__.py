"""Physics as pure functions: the 1976 standard atmosphere, the stage law of inflation (seed Eq. 14-18),
simulated physical and sensor effects, the point-mass trajectory and the compiled batch simulation that
the Monte Carlo flies (engine). Knows only :mod:`cpas_bayes.core`.
"""

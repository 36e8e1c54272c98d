"""cpas_bayes: parachute flight-test reduction, Bayesian inflation reconstruction,
pooling into model-memo dispersions, Monte Carlo loads and model diagnosis."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("cpas_bayes")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+source"

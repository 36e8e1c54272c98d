"""cpas_bayes: parachute flight-test reduction, Bayesian inflation reconstruction,
pooling into model-memo dispersions, Monte Carlo loads and model diagnosis.

The main steps, for a notebook or a script::

    import cpas_bayes as cb

    test = cb.read_bundle("tests/EDU-D1")                  # a bundle folder
    reduction = cb.reduce_test(test)                        # loads, drag areas, 1-sigma
    fit = cb.fit_model(cb.prepare_model(test, reduction), cb.SamplerOptions(seed=1))
    diagnosis = cb.diagnose_test(test, cb.DiagnoseOptions(seed=1), reduction=reduction)
    pooled = cb.pool_fits([cb.FitRecord.from_fit(fit), ...], np.random.default_rng(0))
    mc = cb.run_monte_carlo(pooled.to_memo(), test, 10_000, np.random.default_rng(1))

Names load on first use (PEP 562), so ``import cpas_bayes`` stays light. The
layers they come from are subpackages: ``core``, ``physics``, ``data``, ``stats``,
``inference``, ``population``, ``loads``, ``outputs``, ``app`` (see the README).
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("cpas_bayes")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+source"

# public name -> module that defines it
_API = {
    # data
    "FlightTest": "cpas_bayes.data.bundle",
    "read_bundle": "cpas_bayes.data.bundle",
    "write_bundle": "cpas_bayes.data.bundle_write",
    "example_bundles": "cpas_bayes.data.bundle",
    "reduce_test": "cpas_bayes.data.reduction",
    "Reduction": "cpas_bayes.data.reduction",
    "synthesize": "cpas_bayes.data.synth",
    "synthesize_logger": "cpas_bayes.data.synth_logger",
    "best_estimate_trajectory": "cpas_bayes.data.air_reconstruction",
    "import_bundle": "cpas_bayes.data.importer",
    # inference
    "SamplerOptions": "cpas_bayes.inference.fit",
    "prepare_model": "cpas_bayes.inference.fit",
    "fit_model": "cpas_bayes.inference.fit",
    "fit_test": "cpas_bayes.inference.fit",
    "Fit": "cpas_bayes.inference.fit",
    "load_fit": "cpas_bayes.inference.fit_folder",
    "FitRecord": "cpas_bayes.inference.fit_folder",
    "run_checks": "cpas_bayes.inference.predictive_checks",
    "DiagnoseOptions": "cpas_bayes.inference.candidate_fits",
    "diagnose_test": "cpas_bayes.inference.diagnose",
    # population
    "pool_fits": "cpas_bayes.population.pool",
    "pool_folders": "cpas_bayes.population.pool",
    "Memo": "cpas_bayes.population.memo",
    "load_memo": "cpas_bayes.population.memo",
    # loads
    "run_monte_carlo": "cpas_bayes.loads.montecarlo",
    "compare_fill_time_dispersion": "cpas_bayes.loads.fill_time",
    "compare_loads": "cpas_bayes.loads.compare",
    # outputs
    "write_reduction": "cpas_bayes.outputs.reduction",
    "write_fit_figures": "cpas_bayes.outputs.fit_figures",
    "write_diagnosis": "cpas_bayes.outputs.diagnosis",
    "write_pool": "cpas_bayes.outputs.memo",
    "write_monte_carlo": "cpas_bayes.outputs.montecarlo",
    "write_comparison": "cpas_bayes.outputs.compare",
    # app
    "CampaignConfig": "cpas_bayes.app.campaign",
    "run_campaign": "cpas_bayes.app.campaign",
    "make_executor": "cpas_bayes.core.executor",
    "InputError": "cpas_bayes.core.errors",
}

__all__ = ["__version__", *_API]


def __getattr__(name):
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'cpas_bayes' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(__all__)

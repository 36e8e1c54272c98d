"""Files of a comparison of measured peak loads with predicted ones (``cpas-bayes compare``).

:func:`write_comparison` writes a :class:`cpas_bayes.loads.compare.LoadComparison`:
``compare.json`` (``comparison.to_json()`` plus the caller's extra entries;
non-finite numbers become null) and ``compare.png``
(:func:`cpas_bayes.outputs.plots.montecarlo.plot_load_comparison`), each atomically.
"""

from __future__ import annotations

from cpas_bayes.loads.compare import LoadComparison
from cpas_bayes.outputs.figures import write_document
from cpas_bayes.outputs.plots.montecarlo import plot_load_comparison


def write_comparison(comparison: LoadComparison, out, extra=None):
    """Write compare.json and compare.png into ``out`` (atomically); return their paths."""
    return write_document(out, comparison.to_json(), extra, "compare.json", "compare.png",
                          plot_load_comparison(comparison))

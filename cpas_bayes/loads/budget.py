"""How many Monte Carlo runs a command may keep, checked before anything is drawn.

A Monte Carlo keeps every run's inputs and outputs (its quantiles, figures and
``runs.csv`` need them all), so it holds a fixed number of bytes per run.
:func:`run_bytes` counts them from the configuration flown — P canopies, K
stages, 8 bytes per number:

* run inputs  7·P·K + P + 2 (stage starts, drag areas, fill constants, expopen,
  C_k, t_k, ε per canopy stage; CDS_o per canopy; vehicle weight and CDS_V);
* run outputs 2·K + K·P + 7·P·K (cluster-stage peaks and times, the tensions
  at them; per canopy stage peak, time, t_f, t_fp, n, n_p, V_i);
* per result held, inputs + outputs, plus one more set of outputs: the
  batches' outputs and their concatenation exist together for a moment;

times ``MEMORY_OVERHEAD`` for temporaries: 1.04 kB per run for two two-stage
Drogues and 2.24 kB for three three-stage Mains (measured peaks above the
process's own ~300 MB, 200,000 runs: 1.65 kB per Main run, 1.9 kB per Drogue
run with ``--compare-np``, estimated 2.24 and 2.4 kB). ``runs.csv`` is built
and written ``TABLE_CHUNK`` runs at a time, so its table adds a fixed amount
(its columns twice, built as arrays and then framed, for one slice). A
``--compare-np`` Monte Carlo holds three results, a load comparison two (memo
and fit), a campaign's pooled steps as many at once as it has workers.

:func:`check_runs` refuses a run count below 1, above ``MAX_RUNS`` (ten
million: hours of simulation already), or whose memory exceeds
:func:`cpas_bayes.core.resources.check_memory`'s budget (half the memory
available now), saying how many runs fit. Refused up front, a run count that
would have filled the machine costs a fraction of a second instead of being
killed by the kernel after minutes of work.
"""

from __future__ import annotations

import numpy as np

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.resources import check_memory

MAX_RUNS = 10_000_000         # runs of one Monte Carlo, whatever the memory
MAX_BATCH = 100_000           # runs simulated at once (--batch)
MEMORY_OVERHEAD = 1.25        # temporaries beyond the arrays run_bytes counts
TABLE_CHUNK = 20_000          # runs per slice of runs.csv built at once (≤ 50 MB for three three-stage Mains)


def run_bytes(layout, results=1) -> int:
    """Bytes one run of ``layout`` (a :class:`~cpas_bayes.loads.montecarlo.ClusterLayout`) holds: ``results``
    × (inputs + outputs) + outputs (batches and their concatenation), × ``MEMORY_OVERHEAD``."""
    P, K = layout.n_chutes, layout.n_stages
    inputs = 7 * P * K + P + 2
    outputs = 2 * K + K * P + 7 * P * K
    return int(8 * (results * (inputs + outputs) + outputs) * MEMORY_OVERHEAD)


def _row_bytes(layout) -> int:
    """Bytes of one runs.csv row while its slice is built: its columns twice (arrays, then the frame)."""
    columns = (1 + layout.n_stages * (2 + layout.n_chutes) + layout.n_chutes
               + 12 * int(np.sum(layout.stages_per_chute)) + 2)
    return int(8 * 2 * columns * MEMORY_OVERHEAD)


def table_bytes(layout, runs) -> int:
    """Bytes of the runs.csv table while one slice of at most ``TABLE_CHUNK`` runs is built and written."""
    return _row_bytes(layout) * min(int(runs), TABLE_CHUNK)


def check_runs(layout, runs, results=1, table=False, parallel=1, source="run_monte_carlo", where="argument runs",
               what="Monte Carlo"):
    """Refuse (InputError at ``source``, ``where``) ``runs`` below 1, above ``MAX_RUNS``, or more than fit in
    memory with ``parallel`` steps side by side, each holding ``results`` results (and the runs.csv table
    when ``table``). Returns the bytes they would hold."""
    if isinstance(runs, bool) or not isinstance(runs, (int, np.integer)) or not 1 <= runs <= MAX_RUNS:
        raise InputError(source, where, f"{runs!r} runs; a {what} takes 1 to {MAX_RUNS:,} runs",
                         f"give a whole number of runs from 1 to {MAX_RUNS:,}")
    parallel = max(1, int(parallel))
    per_run = run_bytes(layout, results) * parallel
    per_row = _row_bytes(layout) * parallel if table else 0

    def fitting(budget):
        """The most runs n with n·per_run + per_row·min(n, TABLE_CHUNK) within ``budget``."""
        if budget >= TABLE_CHUNK * (per_run + per_row):
            return (budget - TABLE_CHUNK * per_row) // per_run
        return budget // (per_run + per_row)

    need = int(runs) * per_run + per_row * min(int(runs), TABLE_CHUNK)
    side = f", {parallel} at once" if parallel > 1 else ""
    check_memory(need, source, where,
                 f"{int(runs):,} runs of {layout.test_name}'s configuration ({layout.n_chutes} canopies × "
                 f"{layout.n_stages} stages{side})",
                 lambda budget: f"give at most {fitting(budget):,} runs (or free memory); for more, run several "
                                "Monte Carlos with different seeds")
    return need

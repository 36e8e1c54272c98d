"""``make demo``: the main job (a campaign) on a bundled demo campaign.

The demo campaign is generated reproducibly by the package's own simulator
with fixed seeds on first run (``<out>/bundles``): six two-Drogue tests and
three three-Main tests, one of them hiding an effect that the diagnosis must
find (which one is in that bundle's ``truth.json``; the package never reads
it). The campaign then runs with the settings of :data:`DEMO_CONFIG` —
shorter sampling than the defaults (two ensembles, 20 τ) so that the whole
demo finishes in minutes; ``cpas-bayes campaign`` on the same bundles with
the defaults gives memo-grade posteriors.
"""

from __future__ import annotations

import json
from pathlib import Path

from cpas_bayes.app.campaign import CampaignConfig, run_campaign
from cpas_bayes.core.inputs import inside
from cpas_bayes.core.ownership import check_output, claim_folder

# (bundle name, scenario, hidden effect, seed, magnitude)
DEMO_TESTS = (
    ("DEMO-D1", "drogue", "none", 11, None),
    ("DEMO-D2", "drogue", "none", 12, None),
    ("DEMO-D3", "drogue", "sensor_lag", 13, 0.05),
    ("DEMO-D4", "drogue", "none", 14, None),
    ("DEMO-D5", "drogue", "none", 15, None),
    ("DEMO-D6", "drogue", "none", 16, None),
    ("DEMO-M1", "main", "none", 21, None),
    ("DEMO-M2", "main", "none", 22, None),
    ("DEMO-M3", "main", "none", 23, None),
)

DEMO_CONFIG = CampaignConfig(name="demo: six two-Drogue and three three-Main synthetic tests", seed=0,
                             fit_ensembles=2, fit_max_steps=4000, fit_ess_target=400, diagnose="screen",
                             montecarlo_runs=10000, compare_runs=1000, pool_draws=4000)


def write_demo_bundles(folder, echo=print):
    """Simulate the demo campaign's bundles into ``folder`` (skipping those already there)."""
    from cpas_bayes.data.bundle_write import write_bundle
    from cpas_bayes.data.synth import synthesize

    folder = Path(folder)
    for name, scenario, effect, seed, magnitude in DEMO_TESTS:
        target = inside(folder, name)
        if (target / "test.toml").is_file():
            continue
        test, truth = synthesize(scenario, effect, seed, magnitude, name=name)
        write_bundle(test, target, extra_files={"truth.json": json.dumps(truth, indent=1) + "\n"})  # atomic
        echo(f"simulated {name} ({scenario})")
    return folder


def run_demo(out, echo=print):
    """Generate the demo bundles (first run) and run the campaign into ``out``; return the report path."""
    out = claim_folder(check_output(out))  # new, empty or an earlier demo's: never anyone else's files
    bundles = write_demo_bundles(out / "bundles", echo)
    result = run_campaign(bundles, out, DEMO_CONFIG, echo=echo)
    return result.report

"""Output of a reduction: ``reduced.csv``, ``reduction.json`` and ``reduction.png``; for a logger bundle also
``air_data.csv`` and ``air_data.png`` (the best-estimate trajectory).

The tables and the JSON are in the bundle's units (γ in degrees); the columns and keys are
those of :class:`cpas_bayes.data.reduction.Reduction` (``csv_columns``,
``to_json``), the figure that of :mod:`cpas_bayes.outputs.plots.reduction`.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt

from cpas_bayes.core.files import write_csv, write_json
from cpas_bayes.core.ownership import claim_folder
from cpas_bayes.data.reduction import Reduction
from cpas_bayes.outputs.figures import save_figure
from cpas_bayes.outputs.plots.air_data import plot_air_data
from cpas_bayes.outputs.plots.reduction import plot_reduction


# air_data.csv's columns and their quantities (the bundle's units); gamma is in degrees in every system
AIR_QUANTITIES = {"time": "time", "airspeed": "speed", "airspeed_sigma": "speed", "altitude": "length",
                  "density": "density", "qbar": "pressure", "qbar_sigma": "pressure"}


def air_data_table(reduction: Reduction):
    """The best-estimate trajectory in the bundle's units (a US bundle's q̄ in psf, as its reduced.csv)."""
    frame = reduction.air_estimate.frame.copy()
    units = reduction.test.units
    for column, quantity in AIR_QUANTITIES.items():
        if column in frame:
            frame[column] = units.from_si(frame[column].to_numpy(), quantity)
    return frame


def write_reduction(reduction: Reduction, out):
    """Write reduced.csv, reduction.json and reduction.png into folder ``out``; return their paths."""
    out = Path(out)
    claim_folder(out)
    # Build everything before writing anything, so a failure leaves no partial output.
    table = reduction.to_bundle_units(reduction.csv_columns)
    summary = reduction.to_json()
    fig = plot_reduction(reduction)
    paths = {"csv": out / "reduced.csv", "json": out / "reduction.json", "png": out / "reduction.png"}
    air = reduction.air_estimate
    air_fig = plot_air_data(air, reduction.test.name) if air is not None else None
    air_table = air_data_table(reduction) if air is not None else None
    try:
        write_csv(paths["csv"], table, float_format="%.9g")
        write_json(paths["json"], summary)
        save_figure(fig, paths["png"], dpi=110)
        if air is not None:   # a logger bundle: its best-estimate trajectory
            paths["air_csv"], paths["air_png"] = out / "air_data.csv", out / "air_data.png"
            write_csv(paths["air_csv"], air_table, float_format="%.9g")
            save_figure(air_fig, paths["air_png"], dpi=110)
    finally:
        plt.close(fig)
        if air_fig is not None:
            plt.close(air_fig)
    return paths

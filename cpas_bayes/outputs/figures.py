"""Saving figures: atomic like every other output, and the figure closed after it is written."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt

from cpas_bayes.core.files import atomic_path, jsonable, write_json
from cpas_bayes.core.ownership import claim_folder


def save_figure(fig, target, **kwargs):
    """Save a matplotlib figure atomically (format from the target's suffix)."""
    target = Path(target)
    with atomic_path(target) as tmp:
        fig.savefig(tmp, format=target.suffix.lstrip(".") or "png", **kwargs)


def write_json_and_figure(json_target, doc, figure_target, fig, dpi=110):
    """Write a JSON document and a matplotlib figure atomically, then close the figure."""
    try:
        write_json(json_target, doc)
        save_figure(fig, figure_target, dpi=dpi)
    finally:
        plt.close(fig)


def write_document(out, doc, extra, json_name, figure_name, fig):
    """``doc`` plus the caller's ``extra`` entries as JSON and ``fig`` as a figure, into output folder ``out``.

    Returns ``{"json": path, "png": path}``.
    """
    try:
        out = claim_folder(out)
    except BaseException:
        plt.close(fig)  # drawn by the caller, never saved
        raise
    doc = {**doc, **(extra or {})}
    paths = {"json": out / json_name, "png": out / figure_name}
    write_json_and_figure(paths["json"], jsonable(doc), paths["png"], fig)
    return paths

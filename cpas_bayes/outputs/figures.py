"""Saving figures: atomic like every other output, and the figure closed after it is written."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt

from cpas_bayes.core.files import atomic_path, write_json


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

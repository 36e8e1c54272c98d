"""One summary of a sample of draws: mean, sd and named quantiles.

Quantile keys are ``q`` and the level in percent, two digits: ``q01``, ``q05``,
``q50``, ``q95``, ``q99`` — the names every JSON and TOML file of the package
uses.
"""

from __future__ import annotations

import numpy as np

CREDIBLE_90 = (0.05, 0.5, 0.95)


def quantile_key(level: float) -> str:
    """``0.05`` → ``"q05"``."""
    return f"q{round(100 * level):02d}"


def quantile_summary(values, levels=CREDIBLE_90, *, mean=True, sd=True, finite_only=False):
    """``{"mean", "sd", "q05", ...}`` of a sample; ``None`` when it has no (finite) value.

    ``finite_only`` drops NaN and infinities first (a Monte Carlo run that did
    not reach a stage has no peak there); ``sd`` is the sample sd (ddof 1, 0 for
    one value).
    """
    x = np.asarray(values, float).ravel()
    if finite_only:
        x = x[np.isfinite(x)]
    if x.size == 0:
        return None
    out = {}
    if mean:
        out["mean"] = float(x.mean())
    if sd:
        out["sd"] = float(x.std(ddof=1)) if x.size > 1 else 0.0
    out.update({quantile_key(q): float(v) for q, v in zip(levels, np.quantile(x, levels))})
    return out

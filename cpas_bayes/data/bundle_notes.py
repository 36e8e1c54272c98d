"""What ``cpas-bayes validate`` and ``reduce`` say about a bundle's readings beyond its layout: the air data's line
(a logger bundle) and warnings a user can act on before fitting.

A clipped accelerometer: a logger's MEMS sensor saturates at its full scale, often in the opening shock, and
then reports the same full-scale value sample after sample. A fit would read that flat top as the peak and
bend the inflation to it. Blank readings are left out of the fit (the peak is then the model's), so the warning
names the readings to blank.
"""

from __future__ import annotations

import numpy as np

from cpas_bayes.data.bundle_air import air_summary

CLIP_RUN = 3          # readings holding the record's largest value in a row: noise repeats a value once at most
CLIP_FLOOR_G = 2.0    # only above this: a sensor at rest reads about 1 g, and a coarse one repeats it


def clipped_run(time, g):
    """(value, n, t_start, t_end) of the longest run of readings equal to the largest reading ``g`` (in g), when
    it is at least :data:`CLIP_RUN` long and above :data:`CLIP_FLOOR_G`; else None. Blank readings are skipped."""
    time, g = np.asarray(time, float), np.asarray(g, float)
    keep = np.isfinite(g)
    time, g = time[keep], g[keep]
    if g.size < CLIP_RUN or g.max() < CLIP_FLOOR_G:
        return None
    at_top = np.concatenate([[False], g == g.max(), [False]])
    edges = np.flatnonzero(np.diff(at_top.astype(int)))
    starts, ends = edges[::2], edges[1::2]
    longest = int(np.argmax(ends - starts))
    a, b = starts[longest], ends[longest]
    if b - a < CLIP_RUN:
        return None
    return float(g.max()), int(b - a), float(time[a]), float(time[b - 1])


def clipping_warnings(test):
    """The warning of a bundle whose accelerometer (``G``) holds its largest reading for several readings."""
    if "G" not in test.data:
        return []
    found = clipped_run(test.data["time"], test.data["G"])
    if found is None:
        return []
    value, n, t0, t1 = found
    return [f"data.csv G holds its largest reading, {value:.6g} g, for {n} readings in a row ({t0:.3f}-{t1:.3f} s): "
            "the accelerometer probably clipped at its full scale, and a fit would take that flat top for the peak. "
            "Blank those G cells to leave them out (the fit then draws the peak from the rest of the fill)"]


def summary_notes(test):
    """``validate``'s summary entries beyond the layout: ``air_data`` (logger bundles) and ``warnings``."""
    out = dict(air_summary(test)) if test.air_data is not None else {}
    warnings = list(out.pop("warnings", [])) + clipping_warnings(test)
    return {**out, **({"warnings": warnings} if warnings else {})}

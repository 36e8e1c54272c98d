"""What ``cpas-bayes validate`` and ``reduce`` say about a bundle's readings beyond its layout: the air data's line
(a logger bundle) and warnings a user can act on before fitting.

A clipped accelerometer: a logger's MEMS sensor saturates at its full scale, often in the opening shock, and
then reports the same full-scale value sample after sample. A fit would read that flat top as the peak and
bend the inflation to it. Blank readings are left out of the fit (the peak is then the model's), so the warning
names the readings to blank.

A dead load cell: a channel unplugged, or its bridge not excited, reads a constant or its own noise while the
canopy carries thousands of newtons. A fit reads it as a canopy carrying no load and bends every parameter to
that (on the two-Drogue example with one cell zeroed: error multipliers 9.6 and 10, eight parameters against
their priors' bounds, no word of the cause).

A load before the first stage: stage starts written on another time base than the readings (a record that
begins 5 s earlier than the clock the starts were read from) put the canopies' loads seconds before any stage
starts. The starts' priors (1-sigma 0.1 s) then hold the fill where no load is: the two-Drogue example so
shifted ran to its 20,000-step cap, R-hat 1.7, error multipliers of 9.4 and 9.9, and nothing said why.

Air data in another unit: with density and airspeed in the bundle, q̄ must be ½·ρ·V². A channel written in
another unit (q̄ in kPa in a US bundle, an airspeed in knots, an equivalent airspeed where the fill time needs
the true one) passes every range check and makes every drag area and fill time wrong by the same factor.

A unit off by a factor: G in m/s², a diameter in feet in an SI bundle, a weight in kN. Each passes its range
check, and together the readings then give the cluster a drag coefficient no canopy has: W_T·G/q̄ − CDS_V over
the constructed area π·D_o²/4 is 0.5-0.75 at its highest full open on the examples and synthetic tests.

An accelerometer that disagrees with the airspeed's rate (:mod:`cpas_bayes.data.kinematics`, which argues its
thresholds): a drifting zero, saturation or a lagging pitot line, which no fitted term changes.

A fly-out angle from the horizontal: the riser's angle is measured from the vehicle's axis (a cluster's risers
fly out 8-15°); its complement, written by mistake, is 75-82°, and F·cos θ then reads a quarter of the load.
"""

from __future__ import annotations

import numpy as np

from cpas_bayes.data.bundle_air import air_summary
from cpas_bayes.data.kinematics import kinematic_warning

CLIP_RUN = 3          # readings holding the record's largest value in a row: a noisy peak seldom repeats its top twice
CLIP_FLOOR_G = 2.0    # only above this: a sensor at rest reads about 1 g, and a coarse one repeats it
# a load cell whose readings span less than this many of its stated 1-sigma reads noise alone: Gaussian noise
# over 1,000 readings spans about 6.5 sigma, and a riser's load in a deployment is hundreds of sigma
DEAD_SPAN_SIGMAS = 10.0
# the load factor (5-reading running median) before the first stage start may rise by this share of its rise
# over the record: on the examples it rises by 0.4-3 % before it, and by 70 % on the shifted record above
EARLY_RISE = 0.25
EARLY_MARGIN_S = 0.05   # beyond the first start's 3-sigma: a fill begins at its start, and readings are stamped late
# q̄ / (½·ρ·V²) outside this band (its median over the record; 1.000 on the examples, their 1-99 % points
# 0.94-1.06) is a unit, not a sensor: the factors of a knot, ft/s, kPa or lbf/ft² are 1.7 and beyond, and an
# equivalent airspeed gives ρ₀/ρ, 1.25 at 7,500 ft
AIR_DATA_RATIO = (1 / 1.25, 1.25)
# the cluster's drag coefficient on its constructed area beyond these (after the last stage starts, its highest
# 5-reading running median): a canopy's is 0.3-1.2 full open and up to ~3 at an over-inflation peak
CD_RANGE = (0.1, 4.0)
CD_AFTER_S = 0.5        # from the last stage start: the fill has begun
# notes that explain an accelerometer the airspeed's rate contradicts (data.kinematics), which is then not said
EXPLAIN_KINEMATICS = ("clipped_accelerometer", "air_data_units", "drag_coefficient")
FLYOUT_MAX_DEG = 45.0   # a median fly-out angle beyond this: a riser that far off the axis carries no cluster


def _longest_run_at(time, g, value):
    """(n, t_start, t_end) of the longest run of readings equal to ``value``."""
    at = np.concatenate([[False], g == value, [False]])
    edges = np.flatnonzero(np.diff(at.astype(int)))
    starts, ends = edges[::2], edges[1::2]
    longest = int(np.argmax(ends - starts))
    a, b = starts[longest], ends[longest]
    return int(b - a), float(time[a]), float(time[b - 1])


def clipped_run(time, g):
    """(value, n, t_start, t_end) of the longest run of readings equal to the largest or the smallest reading
    ``g`` (in g; an axis clips at both ends of its scale), when it is at least :data:`CLIP_RUN` long and that
    value at least :data:`CLIP_FLOOR_G` in size; else None. Blank readings are skipped."""
    time, g = np.asarray(time, float), np.asarray(g, float)
    keep = np.isfinite(g)
    time, g = time[keep], g[keep]
    if g.size < CLIP_RUN:
        return None
    runs = [(value, *_longest_run_at(time, g, value)) for value in (g.max(), g.min())
            if abs(value) >= CLIP_FLOOR_G]
    runs = [r for r in runs if r[1] >= CLIP_RUN]
    return max(runs, key=lambda r: r[1]) if runs else None


def clipped_channels(test):
    """[(column, warning)] of each accelerometer column (``G``, or a body axis) that holds its largest (or
    smallest) reading for several readings in a row."""
    out = []
    for column in ("G", "accel_x", "accel_y", "accel_z"):
        found = clipped_run(test.data["time"], test.data[column]) if column in test.data else None
        if found is not None:
            value, n, t0, t1 = found
            out.append((column, f"data.csv {column} holds its {'largest' if value > 0 else 'smallest'} reading, "
                                f"{value:.6g} g, for {n} readings in a row ({t0:.3f}-{t1:.3f} s): the accelerometer "
                                "probably clipped at its full scale, and a fit would take that flat top for the "
                                f"peak. Blank those {'G cells' if column == 'G' else 'rows of the three axes'} to "
                                "leave them out (the fit then draws the peak from the rest of the fill)"))
    return out


def clipping_warnings(test):
    """The warnings of :func:`clipped_channels`, as ``validate`` and ``reduce`` say them."""
    return [text for _, text in clipped_channels(test)]


def dead_load_cells(test):
    """[(column, warning)] of each parachute's load cell whose readings stay within its noise over the whole
    record: they span less than :data:`DEAD_SPAN_SIGMAS` times its median stated 1-sigma, or nothing at all."""
    out = []
    units = test.units
    for p in test.parachutes:
        column = p.load_column
        if column is None or column not in test.data:
            continue
        values = np.asarray(test.data[column], float)
        values = values[np.isfinite(values)]
        sigma_column = f"{column}_sigma"
        sigma = float(np.nanmedian(test.data[sigma_column])) if sigma_column in test.data else 0.0
        span = float(np.ptp(values)) if values.size else 0.0
        if values.size and (span == 0.0 or span < DEAD_SPAN_SIGMAS * sigma):
            force = units.label("force")
            noise = f" against a stated 1-sigma of {units.from_si(sigma, 'force'):.4g} {force}" if sigma else ""
            out.append((column, f"data.csv {p.load_cell}, the load cell of parachute '{p.id}', stays within its "
                                f"noise over the whole record (its readings span {units.from_si(span, 'force'):.4g} "
                                f"{force}{noise}): a dead or unplugged channel, which a fit reads as a canopy "
                                f"carrying no load. Repair the column, or remove the load_cell of "
                                f"{'every parachute' if len(test.parachutes) > 1 else 'the parachute'} in "
                                "test.toml (a cluster is reduced from all its cells or none; without them the "
                                "loads come from the accelerometer alone)"))
    return out


def _running_median(x, width=5):
    """Running medians of ``width`` readings (len(x) − width + 1 of them): a single spike does not move them."""
    return np.median(np.lib.stride_tricks.sliding_window_view(x, width), axis=1)


def _load_factor(test):
    """(time, load factor in g) of the accelerometer's readings (``G``, or the body axes' magnitude), blanks
    left out; None without an accelerometer."""
    data = test.data
    if "G" in data:
        g = np.asarray(data["G"], float)
    elif all(f"accel_{a}" in data for a in "xyz"):
        g = np.sqrt(sum(np.asarray(data[f"accel_{a}"], float) ** 2 for a in "xyz"))
    else:
        return None
    time = np.asarray(data["time"], float)
    keep = np.isfinite(g)
    return time[keep], g[keep]


def load_before_first_stage(test):
    """A warning when the load factor rises by more than :data:`EARLY_RISE` of its rise over the record (from
    its first readings' level to its highest, 5-reading running medians) before the first stage start, beyond
    that start's 3-sigma; else None."""
    found = _load_factor(test)
    if found is None or found[1].size < 20:
        return None
    time, g = found
    smooth, time = _running_median(g), time[2:-2]
    base = float(np.median(smooth[:max(5, smooth.size // 20)]))
    rise = float(smooth.max()) - base
    first = min((p.stages[0] for p in test.parachutes), key=lambda st: st.start)
    before = time < first.start - 3.0 * first.start_sigma - EARLY_MARGIN_S
    if rise <= 0 or not before.any():
        return None
    early = smooth[before] - base > EARLY_RISE * rise
    if not early.any():
        return None
    t_rise = float(time[before][np.argmax(early)])
    return (f"the accelerometer's load rises before any stage starts: at {t_rise:.3f} s it is already "
            f"{EARLY_RISE:.0%} of its rise over the record ({base:.3g} to {base + rise:.3g} g), "
            f"{first.start - t_rise:.2f} s before the first stated stage start ({first.label!r} at "
            f"{first.start:.3f} s, 1-sigma "
            f"{first.start_sigma:g} s). Are the stage starts in test.toml on the time base of data.csv's time column? "
            "Shift them (or the column) so that each start is its stage's line stretch, or start the record after "
            "a load the bundle does not model")


def air_data_mismatch(test):
    """A warning when the measured q̄ is not ½·ρ·V² of the bundle's density and airspeed (median ratio outside
    :data:`AIR_DATA_RATIO`); None when it is, or when the bundle lacks one of the three."""
    data = test.data
    if test.air_data is not None or not all(c in data for c in ("qbar", "density", "airspeed")):
        return None   # a logger bundle's (even at its best estimate, whose q̄ is ½·ρ·V² by construction)
    ratio = np.asarray(data["qbar"], float) / (0.5 * np.asarray(data["density"], float)
                                                 * np.asarray(data["airspeed"], float) ** 2)
    ratio = float(np.nanmedian(ratio))
    if AIR_DATA_RATIO[0] <= ratio <= AIR_DATA_RATIO[1]:
        return None
    return (f"data.csv qbar is {ratio:.3g}× ½·density·airspeed² (the median over the record; within a few % "
            "when the three agree): one of them is probably in another unit (a knot is 0.514 m/s, a ft/s "
            "0.3048 m/s, a kPa 1,000 Pa, a lbf/ft² 47.9 Pa, a slug/ft³ 515 kg/m³), or airspeed is an equivalent "
            "airspeed where the fill time needs the true one. Check the units of qbar, density and airspeed "
            f"against the bundle's units ({test.units.name})")


def _highest_cd(values, area):
    """The highest 5-reading running median of a drag area over ``area``; None with fewer than 10 readings."""
    values = values[np.isfinite(values)]
    return float(_running_median(values).max()) / area if values.size >= 10 else None


def implausible_drag_coefficient(test):
    """A warning when a bundle with measured q̄ gives its cluster (W_T·G/q̄ − CDS_V over Σ π·D_o²/4), or one of
    its parachutes with a load cell (F_i/q̄ over its π·D_o²/4), a drag coefficient outside :data:`CD_RANGE`: the
    highest 5-reading running median from :data:`CD_AFTER_S` after the last stage start. None when all are
    inside, without measured q̄ (a logger bundle, even at its best estimate) or enough readings there."""
    data = test.data
    if not test.measured_qbar or test.air_data is not None or "G" not in data:
        return None   # a logger bundle's q̄ is reconstructed: a trajectory that misses its receiver is said so
    time = np.asarray(data["time"], float)
    after = time >= max(p.stages[-1].start for p in test.parachutes) + CD_AFTER_S
    qbar = np.asarray(data["qbar"], float)[after]
    total = test.vehicle.weight + sum(p.weight for p in test.parachutes)
    areas = {p.id: np.pi * p.diameter ** 2 / 4 for p in test.parachutes}
    dead = {column for column, _ in dead_load_cells(test)}   # said on their own
    found = [("the cluster", _highest_cd(total * np.asarray(data["G"], float)[after] / qbar - test.vehicle.cds,
                                         sum(areas.values())))]
    found += [(f"parachute '{p.id}' (its load cell)",
               _highest_cd(np.asarray(data[p.load_column], float)[after] / qbar, areas[p.id]))
              for p in test.parachutes if p.load_column in data and p.load_column not in dead]
    off = [(who, cd) for who, cd in found if cd is not None and not CD_RANGE[0] <= cd <= CD_RANGE[1]]
    if not off:
        return None
    high = off[0][1] > CD_RANGE[1]
    likely = ("G in m/s² or ft/s² rather than g (9.8×, 32.2×), a diameter in m in a US bundle (10.8× less area)"
              if high else "a diameter in ft in an SI bundle (10.8× the area), a weight in kN or kip "
              "(or a canopy that never opened: a streamer's is below 0.1)")
    return ("the readings give " + ", ".join(f"{who} a drag coefficient of {cd:.3g}" for who, cd in off)
            + " on the constructed area π·D_o²/4 (the highest after the last stage starts of W_T·G/q̄ − CDS_V "
            "for the cluster, F/q̄ for a load cell): a canopy's is 0.3-1.2 full open, up to ~3 at an over-inflation "
            f"peak. A unit is probably off: {likely}, or a weight, load or q̄ in another unit than the bundle's "
            f"({test.units.name}). Check G, the weights, the diameters, the load cells and qbar")


def wide_flyout_angles(test):
    """[(column, warning)] of each fly-out angle whose median over the readings after its parachute's first
    stage start is beyond :data:`FLYOUT_MAX_DEG`."""
    out = []
    time = np.asarray(test.data["time"], float)
    for p in test.parachutes:
        column = p.angle_column
        if column is None or column not in test.data:
            continue
        theta = np.asarray(test.data[column], float)[time >= p.stages[0].start]
        theta = np.abs(theta[np.isfinite(theta)])
        median = float(np.median(theta)) if theta.size else 0.0
        if median > FLYOUT_MAX_DEG:
            out.append((column, f"data.csv {p.flyout_angle}, the fly-out angle of parachute '{p.id}', reads "
                                f"{median:.1f}° (median after its first stage starts): the angle is measured from "
                                "the vehicle's axis, where a cluster's risers fly out 8-15°, and the reduction "
                                f"takes F·cos θ, {np.cos(np.radians(median)):.2f} of the riser's tension here. "
                                "Is it the angle from the horizontal (then write 90° minus it: "
                                f"{90 - median:.1f}°)?"))
    return out


def reading_notes(test):
    """[(code, column or None, warning)] of what the bundle's readings themselves show, in the order said: a
    clipped accelerometer, a dead load cell, a fly-out angle from the horizontal (each naming its column), a load
    before the first stage, air data in another unit, a drag coefficient no canopy has, an accelerometer that
    disagrees with the airspeed's rate (naming G). The codes are the fit health's
    (:mod:`cpas_bayes.inference.fit_health`)."""
    out = [("clipped_accelerometer", column, text) for column, text in clipped_channels(test)]
    out += [("dead_load_cell", column, text) for column, text in dead_load_cells(test)]
    out += [("flyout_angle", column, text) for column, text in wide_flyout_angles(test)]
    said = (("load_before_first_stage", load_before_first_stage(test)), ("air_data_units", air_data_mismatch(test)),
            ("drag_coefficient", implausible_drag_coefficient(test)))
    out += [(code, None, text) for code, text in said if text]
    if any(code in EXPLAIN_KINEMATICS for code, _, _ in out):
        return out   # a unit off or a flat top breaks the balance too: said once, by its cause
    kinematics = kinematic_warning(test)
    return out + ([("accelerometer_kinematics", "G", kinematics)] if kinematics else [])


def reading_warnings(test):
    """The warnings of :func:`reading_notes`, as ``validate`` and ``reduce`` say them."""
    return [text for _, _, text in reading_notes(test)]


def summary_notes(test):
    """``validate``'s summary entries beyond the layout: ``air_data`` (logger bundles) and ``warnings``."""
    out = dict(air_summary(test)) if test.air_data is not None else {}
    warnings = list(out.pop("warnings", [])) + reading_warnings(test)
    return {**out, **({"warnings": warnings} if warnings else {})}

"""Independent-simulator check of `cpas-bayes fit` on logger bundles.

A drop simulator written here from scratch (numpy/scipy only; nothing from
cpas_bayes.physics, cpas_bayes.data.synth* or cpas_bayes.stats) produces
logger bundles (accelerometer G, GNSS ground velocity, baro altitude, a wind
table; no measured dynamic pressure) in the format of docs/test-bundle.md.
The canopy opens with a logistic-in-time law with a Gaussian over-inflation
bump, not the package's power law of time. Each bundle is then checked with
`cpas-bayes validate`, fitted with `cpas-bayes fit`, and optionally diagnosed
with `cpas-bayes diagnose`; the study asks whether the fits converge, whether
the 90 % interval of the full-open drag area covers the simulated truth, and
whether two drops of the same canopy design agree.

    python benchmarks/independent_drops.py --out /tmp/independent_drops [--designs N] [--quick]

Physics (SI, earth axes north, east, up):

    w(h)   wind, piecewise linear in altitude between levels, held beyond them
    v_a  = v_g - w(h),  qbar = 0.5 rho(h) |v_a|^2
    rho  = 1.225 (1 - 2.25577e-5 h)^4.25588          (ISA troposphere)
    m dv_g/dt = -qbar (CDS_V + CDS_c(t)) v_a/|v_a| - m g0 z,  m = (W_V + W_p)/g0
    CDS_c(t) = 0 for t < t_open, else
             CDS_o (1 + A exp(-((t - t_p)/w)^2)) / (1 + exp(-(t - t_half)/s))
    G_true = qbar (CDS_V + CDS_c) / (m g0)            sensed load factor, g

Sensors: G is the box-car mean of G_true over each accelerometer interval
(integrated as an extra state, so the mean is as exact as the integration)
plus Gaussian noise; GNSS velocity at 5 Hz reports the state `latency`
seconds before its stamp (before release: the carrier's constant velocity);
baro altitude at 10 Hz is instantaneous (no latency).
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

G0 = 9.80665  # m/s^2
CD_NOMINAL_MAIN = 0.52  # the package's prior mean of cd_o for kind "main" (cpas_bayes/data/priors/main.toml)


# ----------------------------------------------------------------------------
# Atmosphere, wind, inflation law
# ----------------------------------------------------------------------------

def isa_density(h):
    """ISA troposphere density, kg/m^3, h in m."""
    return 1.225 * (1.0 - 2.25577e-5 * np.asarray(h, dtype=float)) ** 4.25588


@dataclass
class Wind:
    altitude: list[float]
    north: list[float]
    east: list[float]

    def at(self, h):
        return (float(np.interp(h, self.altitude, self.north)),
                float(np.interp(h, self.altitude, self.east)))


@dataclass
class Canopy:
    """One canopy design: nominal diameter and the logistic inflation law."""
    label: str
    cds_o: float          # true full-open drag area, m^2
    cd_true: float        # cds_o / (pi/4 D^2)
    w_vehicle: float      # N, suspended weight without the canopy
    w_parachute: float    # N
    cds_vehicle: float    # m^2
    rise: float           # t_half - t_open, s
    slope: float          # s of the logistic, s
    bump: float           # A, over-inflation amplitude
    bump_delay: float     # t_p - t_half, s
    bump_width: float     # w, s

    @property
    def diameter(self):
        return math.sqrt(self.cds_o / self.cd_true / (math.pi / 4.0))

    def cds(self, t, t_open):
        """Canopy drag area at time t (s after release) for line stretch at t_open."""
        if t < t_open:
            return 0.0
        t_half = t_open + self.rise
        t_p = t_half + self.bump_delay
        grow = 1.0 / (1.0 + math.exp(-(t - t_half) / self.slope))
        over = 1.0 + self.bump * math.exp(-((t - t_p) / self.bump_width) ** 2)
        return self.cds_o * over * grow


@dataclass
class Drop:
    design: str
    drop: int
    seed: int
    altitude0: float      # m, release altitude
    airspeed0: float      # m/s, horizontal airspeed of the carrier at release
    heading_deg: float    # carrier heading, deg from north toward east
    t_open: float         # s after release, line stretch
    duration: float       # s, record length
    latency: float        # s, GNSS latency
    gnss_phase: float     # s, offset of the GNSS stamps on the 5 Hz grid
    wind: Wind = field(default=None)
    wind_offset: tuple = (0.0, 0.0)   # stated minus true (north, east), m/s


ACCEL_RATE = 50.0       # Hz
GNSS_RATE = 5.0         # Hz
BARO_RATE = 10.0        # Hz
SIGMA_G = 0.03          # g
SIGMA_VH = 0.08         # m/s
SIGMA_VU = 0.10         # m/s
SIGMA_H = 1.5           # m
WIND_SIGMA_STATED = 1.5  # m/s, stated 1-sigma of the wind table
WIND_OFFSET_SIGMA = 1.0  # m/s, true error of the stated table (one offset per component)


DESIGNS = [
    # 15 m^2: nominal 0.52*S_o is 13 % below the truth
    Canopy("A", cds_o=15.0, cd_true=0.60, w_vehicle=820.0, w_parachute=30.0, cds_vehicle=0.15,
           rise=0.55, slope=0.12, bump=0.20, bump_delay=0.30, bump_width=0.18),
    # 40 m^2: nominal 13 % below the truth
    Canopy("B", cds_o=40.0, cd_true=0.60, w_vehicle=2200.0, w_parachute=80.0, cds_vehicle=0.30,
           rise=0.85, slope=0.18, bump=0.15, bump_delay=0.40, bump_width=0.25),
    # 90 m^2: nominal 16 % above the truth
    Canopy("C", cds_o=90.0, cd_true=0.45, w_vehicle=4900.0, w_parachute=170.0, cds_vehicle=0.50,
           rise=1.30, slope=0.28, bump=0.12, bump_delay=0.60, bump_width=0.35),
]

# (design, drop, seed, altitude0, airspeed0, heading, t_open, duration, latency, gnss phase)
DROP_TABLE = [
    ("A", 1, 101, 1800.0, 45.0, 30.0, 1.5, 30.0, 0.20, 0.013),
    ("A", 2, 102, 2600.0, 62.0, 200.0, 2.4, 30.0, 0.35, 0.071),
    ("B", 1, 201, 2200.0, 55.0, 110.0, 1.2, 32.0, 0.15, 0.037),
    ("B", 2, 202, 1600.0, 40.0, 300.0, 2.8, 32.0, 0.30, 0.155),
    ("C", 1, 301, 2900.0, 68.0, 250.0, 2.0, 36.0, 0.25, 0.089),
    ("C", 2, 302, 2000.0, 50.0, 60.0, 1.4, 36.0, 0.12, 0.121),
]


def make_drops(designs):
    wanted = {c.label for c in designs}
    drops = []
    for design, k, seed, h0, v0, psi, t_open, dur, lat, phase in DROP_TABLE:
        if design not in wanted:
            continue
        rng = np.random.default_rng(seed)
        # wind: 5 levels from 700 m below to 100 m above the release, sheared
        levels = list(np.linspace(h0 - 700.0, h0 + 100.0, 5))
        base_n, base_e = rng.uniform(-10.0, 10.0, 2)
        shear_n, shear_e = rng.uniform(-8.0, 8.0, 2) / 1000.0  # per m
        north = [float(base_n + shear_n * (h - h0) + rng.normal(0, 0.7)) for h in levels]
        east = [float(base_e + shear_e * (h - h0) + rng.normal(0, 0.7)) for h in levels]
        offset = tuple(float(x) for x in rng.normal(0.0, WIND_OFFSET_SIGMA, 2))
        drops.append(Drop(design, k, seed, h0, v0, psi, t_open, dur, lat, phase,
                          wind=Wind([float(h) for h in levels], north, east), wind_offset=offset))
    return drops


# ----------------------------------------------------------------------------
# Trajectory
# ----------------------------------------------------------------------------

@dataclass
class Trajectory:
    sol_pre: object
    sol_post: object
    t_open: float
    v0: np.ndarray            # ground velocity at release (n, e, u)
    h0: float

    def state(self, t):
        """[n, e, h, vn, ve, vu, intG] at t >= 0; before release the carrier's level flight."""
        t = float(t)
        if t < 0.0:
            return np.array([self.v0[0] * t, self.v0[1] * t, self.h0, *self.v0, 0.0])
        sol = self.sol_pre if t <= self.t_open else self.sol_post
        return sol.sol(t)


def simulate(canopy: Canopy, drop: Drop) -> Trajectory:
    m = (canopy.w_vehicle + canopy.w_parachute) / G0
    wind = drop.wind
    psi = math.radians(drop.heading_deg)
    wn0, we0 = wind.at(drop.altitude0)
    v0 = np.array([drop.airspeed0 * math.cos(psi) + wn0, drop.airspeed0 * math.sin(psi) + we0, 0.0])

    def rhs(t, y):
        h = y[2]
        wn, we = wind.at(h)
        va = np.array([y[3] - wn, y[4] - we, y[5]])
        speed = math.sqrt(va @ va)
        qbar = 0.5 * float(isa_density(h)) * speed * speed
        drag = qbar * (canopy.cds_vehicle + canopy.cds(t, drop.t_open))
        acc = -drag / (m * speed) * va if speed > 0 else np.zeros(3)
        acc[2] -= G0
        return [y[3], y[4], y[5], acc[0], acc[1], acc[2], drag / (m * G0)]

    y0 = [0.0, 0.0, drop.altitude0, *v0, 0.0]
    opts = dict(method="DOP853", rtol=1e-8, atol=1e-9, dense_output=True, max_step=0.01)
    pre = solve_ivp(rhs, (0.0, drop.t_open), y0, **opts)
    post = solve_ivp(rhs, (drop.t_open, drop.duration + 0.5), pre.y[:, -1], **opts)
    if not (pre.success and post.success):
        raise RuntimeError(f"integration failed: {pre.message} / {post.message}")
    return Trajectory(pre, post, drop.t_open, v0, drop.altitude0)


# ----------------------------------------------------------------------------
# Sensors and bundle writer
# ----------------------------------------------------------------------------

def sample(canopy: Canopy, drop: Drop, traj: Trajectory):
    rng = np.random.default_rng(drop.seed + 7)
    dt = 1.0 / ACCEL_RATE
    n_g = int(round(drop.duration * ACCEL_RATE))
    t_g = np.round(np.arange(1, n_g + 1) * dt, 6)
    integral = np.array([traj.state(t)[6] for t in np.concatenate([[0.0], t_g])])
    g_mean = np.diff(integral) / dt
    g_meas = g_mean + rng.normal(0.0, SIGMA_G, g_mean.size)

    t_v = np.round(np.arange(drop.gnss_phase, drop.duration, 1.0 / GNSS_RATE), 6)
    v_true = np.array([traj.state(t - drop.latency)[3:6] for t in t_v])
    v_meas = v_true + rng.normal(0.0, 1.0, v_true.shape) * np.array([SIGMA_VH, SIGMA_VH, SIGMA_VU])

    t_h = np.round(np.arange(0.05, drop.duration, 1.0 / BARO_RATE), 6)
    h_true = np.array([traj.state(t)[2] for t in t_h])
    h_meas = h_true + rng.normal(0.0, SIGMA_H, h_true.size)
    return dict(t_g=t_g, g=g_meas, g_mean=g_mean, t_v=t_v, v=v_meas, t_h=t_h, h=h_meas)


def _fmt(x):
    return f"{x:.9g}"


def _toml_list(values):
    return "[" + ", ".join(_fmt(v) for v in values) + "]"


def write_bundle(folder: Path, canopy: Canopy, drop: Drop, traj: Trajectory, data) -> dict:
    """Write test.toml and data.csv of one drop into folder, and truth.json beside it."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(drop.seed + 11)
    w_total = canopy.w_vehicle + canopy.w_parachute
    stated = dict(
        weight=canopy.w_vehicle + rng.normal(0, 0.015 * canopy.w_vehicle),
        weight_sigma=0.015 * canopy.w_vehicle,
        cds=canopy.cds_vehicle * (1 + rng.normal(0, 0.15)),
        cds_sigma=0.3 * canopy.cds_vehicle,
        chute_weight=canopy.w_parachute * (1 + rng.normal(0, 0.05)),
        chute_weight_sigma=0.1 * canopy.w_parachute,
        start=round(drop.t_open + rng.normal(0, 0.05), 3),
        start_sigma=0.1,
    )
    name = f"IND-{canopy.label}{drop.drop}"
    wind_n = [v + drop.wind_offset[0] for v in drop.wind.north]
    wind_e = [v + drop.wind_offset[1] for v in drop.wind.east]
    toml = f"""name = "{name}"
units = "SI"
phase = "independent-drop"

[vehicle]
weight = {_fmt(stated['weight'])}
weight_sigma = {_fmt(stated['weight_sigma'])}
cds = {_fmt(stated['cds'])}
cds_sigma = {_fmt(stated['cds_sigma'])}

[[parachute]]
id = "M{canopy.label}"
kind = "main"
inflation = "finite"
diameter = {canopy.diameter:.3f}
weight = {_fmt(stated['chute_weight'])}
weight_sigma = {_fmt(stated['chute_weight_sigma'])}
stage = [
    {{ label = "full open", start = {stated['start']:.3f}, start_sigma = {stated['start_sigma']} }},
]

[sigma]
G = {SIGMA_G}
v_north = {SIGMA_VH}
v_east = {SIGMA_VH}
v_up = {SIGMA_VU}
altitude = {SIGMA_H}

[wind]
altitude = {_toml_list(drop.wind.altitude)}
north = {_toml_list(wind_n)}
east = {_toml_list(wind_e)}
sigma = {WIND_SIGMA_STATED}

[rate]
G = {ACCEL_RATE}
"""
    (folder / "test.toml").write_text(toml)

    rows: dict[float, dict] = {}
    for t, g in zip(data["t_g"], data["g"]):
        rows.setdefault(float(t), {})["G"] = g
    for t, v in zip(data["t_v"], data["v"]):
        rows.setdefault(float(t), {}).update(v_north=v[0], v_east=v[1], v_up=v[2])
    for t, h in zip(data["t_h"], data["h"]):
        rows.setdefault(float(t), {})["altitude"] = h
    columns = ["G", "v_north", "v_east", "v_up", "altitude"]
    with open(folder / "data.csv", "w", newline="") as fh:
        fh.write("time," + ",".join(columns) + "\n")
        for t in sorted(rows):
            cells = [f"{t:.3f}"] + [(_fmt(rows[t][c]) if c in rows[t] else "") for c in columns]
            fh.write(",".join(cells) + "\n")

    # truth beside the bundle (never inside it)
    t_fine = np.arange(drop.t_open, min(drop.t_open + 5.0, drop.duration), 0.001)
    cds_fine = np.array([canopy.cds(t, drop.t_open) for t in t_fine])
    g_true = []
    for t in t_fine:
        s = traj.state(t)
        wn, we = drop.wind.at(s[2])
        va2 = (s[3] - wn) ** 2 + (s[4] - we) ** 2 + s[5] ** 2
        g_true.append(0.5 * float(isa_density(s[2])) * va2 * (canopy.cds_vehicle + canopy.cds(t, drop.t_open)) / w_total)
    s_open = traj.state(drop.t_open)
    wn, we = drop.wind.at(s_open[2])
    truth = dict(
        simulator="benchmarks/independent_drops.py (logistic inflation + Gaussian bump)",
        name=name, design=canopy.label, drop=drop.drop, seed=drop.seed,
        cds_o=canopy.cds_o, cd_o=canopy.cd_true, diameter=canopy.diameter,
        nominal_cds_o=CD_NOMINAL_MAIN * math.pi / 4 * canopy.diameter ** 2,
        vehicle_weight=canopy.w_vehicle, vehicle_cds=canopy.cds_vehicle, parachute_weight=canopy.w_parachute,
        law=dict(t_open=drop.t_open, t_half=drop.t_open + canopy.rise, slope=canopy.slope,
                 bump=canopy.bump, t_peak_bump=drop.t_open + canopy.rise + canopy.bump_delay,
                 bump_width=canopy.bump_width),
        fill_time_10_90=float(t_fine[np.argmax(cds_fine >= 0.9 * canopy.cds_o)] - t_fine[np.argmax(cds_fine >= 0.1 * canopy.cds_o)]),
        fill_time_to_cds_o=float(t_fine[np.argmax(cds_fine >= canopy.cds_o)] - drop.t_open),
        peak_cds_over_cds_o=float(cds_fine.max() / canopy.cds_o),
        peak_G_true=float(max(g_true)),
        peak_G_sampled=float(data["g_mean"].max()),
        airspeed_at_open=float(math.sqrt((s_open[3] - wn) ** 2 + (s_open[4] - we) ** 2 + s_open[5] ** 2)),
        release=dict(altitude=drop.altitude0, airspeed=drop.airspeed0, heading_deg=drop.heading_deg,
                     ground_velocity=[float(x) for x in traj.v0]),
        final=dict(altitude=float(traj.state(drop.duration)[2]), v_up=float(traj.state(drop.duration)[5])),
        gnss_latency=drop.latency, gnss_phase=drop.gnss_phase,
        true_wind=asdict(drop.wind), stated_wind_offset=list(drop.wind_offset),
        stated=stated,
        sensors=dict(accel_rate=ACCEL_RATE, gnss_rate=GNSS_RATE, baro_rate=BARO_RATE, sigma_G=SIGMA_G,
                     sigma_vh=SIGMA_VH, sigma_vu=SIGMA_VU, sigma_h=SIGMA_H),
    )
    return truth


# ----------------------------------------------------------------------------
# Running cpas-bayes
# ----------------------------------------------------------------------------

def cpas_bayes_exe():
    exe = Path(sys.executable).parent / "cpas-bayes"
    return str(exe) if exe.exists() else "cpas-bayes"


def run(cmd, log: Path):
    t0 = time.monotonic()
    with open(log, "w") as fh:
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, text=True)
    return proc.returncode, time.monotonic() - t0


def tail(path: Path, n=6):
    try:
        lines = path.read_text(errors="replace").strip().splitlines()
    except OSError:
        return ""
    return "\n".join(lines[-n:])


def cds_o_parameter(summary: dict, posterior_path: Path, chute_weight: float):
    """Name of the full-open drag-area parameter, its 5/50/95 % quantiles and sd from the draws, the
    medians of every parameter, and the 5/50/95 % quantiles of CDS_o per total weight
    (cds_o / (vehicle_weight + the stated parachute weight)), m^2/N."""
    import xarray as xr
    tree = xr.open_datatree(posterior_path, engine="h5netcdf")
    try:
        post = tree["posterior"].to_dataset()
        names = list(post.data_vars)
        target = [n for n in names if n.endswith("cds_o")]
        if len(target) != 1:
            raise RuntimeError(f"expected one parameter ending in cds_o, found {target} among {names}")
        draws = np.asarray(post[target[0]].values, dtype=float).ravel()
        medians = {n: float(np.median(np.asarray(post[n].values, dtype=float))) for n in names
                   if post[n].values.dtype.kind == "f"}
        # 90 % intervals of the systematic sensor terms (truth: latency as simulated, scale 1, bias 0)
        sensors = {n: tuple(float(x) for x in np.quantile(np.asarray(post[n].values, float), [0.05, 0.95]))
                   for n in ("gnss_latency", "accel_scale", "accel_bias") if n in names}
        ratio = None
        if "vehicle_weight" in names:
            w = np.asarray(post["vehicle_weight"].values, dtype=float).ravel() + chute_weight
            ratio = tuple(float(x) for x in np.quantile(draws / w, [0.05, 0.5, 0.95]))
    finally:
        tree.close()
    q05, q50, q95 = np.quantile(draws, [0.05, 0.5, 0.95])
    return target[0], (float(q05), float(q50), float(q95)), float(np.std(draws)), medians, ratio, sensors


def diagnostics(summary: dict):
    d = summary.get("diagnostics", {})
    return d.get("converged"), d.get("rhat_max"), d.get("ess_bulk_min")


# ----------------------------------------------------------------------------
# Study
# ----------------------------------------------------------------------------

FIELDS = ["design", "drop", "bundle", "true_cds_o", "nominal_cds_o", "parameter", "q05", "q50", "q95", "sd",
          "covered", "converged", "rhat_max", "ess_bulk_min", "wall_s", "fit_rc", "peak_G", "fill_10_90_s",
          "airspeed_open", "true_cds_per_weight", "cds_per_weight_q05", "cds_per_weight_q50",
          "cds_per_weight_q95", "ratio_covered", "true_vehicle_weight", "stated_vehicle_weight",
          "fitted_vehicle_weight", "true_latency", "fitted_latency", "fitted_noise_acc", "fitted_noise_gnss",
          "gnss_latency_q05", "gnss_latency_q95", "latency_covered", "accel_scale_q05", "accel_scale_q95",
          "scale_covered", "accel_bias_q05", "accel_bias_q95", "warnings",
          "other_medians", "error"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="scratch folder for bundles, fits and the CSV")
    ap.add_argument("--designs", type=int, default=3, help="how many of the 3 canopy designs (A, B, C)")
    ap.add_argument("--quick", action="store_true", help="--max-steps 2000 and no diagnose (a smoke run)")
    ap.add_argument("--max-steps", type=int, default=20000)
    ap.add_argument("--no-diagnose", action="store_true", help="skip cpas-bayes diagnose")
    ap.add_argument("--with", dest="terms", default=None,
                    help="terms every fit carries beside the stage law (cpas-bayes fit --with), e.g. discrepancy")
    ap.add_argument("--bundles-only", action="store_true", help="write and validate the bundles, fit nothing")
    ap.add_argument("--diagnose-only", action="store_true",
                    help="skip the fits (use those already under --out) and run only the diagnoses")
    ap.add_argument("--fresh", action="store_true",
                    help="rewrite the bundles even if --out already holds them (default: reuse, they are seeded)")
    args = ap.parse_args(argv)

    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    exe = cpas_bayes_exe()
    designs = DESIGNS[:max(1, min(args.designs, len(DESIGNS)))]
    by_label = {c.label: c for c in designs}
    drops = make_drops(designs)
    max_steps = 2000 if args.quick else args.max_steps

    results = []
    # --- bundles --------------------------------------------------------------
    bundles = {}
    for drop in drops:
        canopy = by_label[drop.design]
        bundle = out / "bundles" / f"{drop.design}{drop.drop}"
        truth_file = out / "bundles" / f"{drop.design}{drop.drop}.truth.json"
        if not args.fresh and truth_file.exists() and (bundle / "test.toml").exists() and (bundle / "data.csv").exists():
            truth = json.loads(truth_file.read_text())     # same seeds: the bundle would be written identically
        else:
            traj = simulate(canopy, drop)
            data = sample(canopy, drop, traj)
            truth = write_bundle(bundle, canopy, drop, traj, data)
            truth_file.write_text(json.dumps(truth, indent=1))
        rc, _ = run([exe, "validate", str(bundle)], out / "bundles" / f"{drop.design}{drop.drop}.validate.log")
        print(f"bundle {bundle.name}: CDS_o {canopy.cds_o} (nominal {truth['nominal_cds_o']:.1f}), "
              f"D_o {canopy.diameter:.2f} m, V_open {truth['airspeed_at_open']:.1f} m/s, "
              f"peak G {truth['peak_G_true']:.2f}, fill10-90 {truth['fill_time_10_90']:.2f} s, "
              f"stretch-to-CDS_o {truth['fill_time_to_cds_o']:.2f} s, "
              f"h_end {truth['final']['altitude']:.0f} m, v_up_end {truth['final']['v_up']:.1f} m/s; "
              f"validate rc={rc}", flush=True)
        if rc != 0:
            print(tail(out / "bundles" / f"{drop.design}{drop.drop}.validate.log", 20))
        bundles[(drop.design, drop.drop)] = (bundle, truth, rc)
    if args.bundles_only:
        return 0

    # --- fits -----------------------------------------------------------------
    print("\n" + " ".join(f"{h:>10}" for h in ["bundle", "true", "q05", "q50", "q95", "covered", "conv",
                                                "rhat", "ess", "wall_s"]), flush=True)
    for (design, k), (bundle, truth, vrc) in bundles.items():
        row = dict(design=design, drop=k, bundle=str(bundle), true_cds_o=truth["cds_o"],
                   nominal_cds_o=round(truth["nominal_cds_o"], 3), peak_G=round(truth["peak_G_true"], 3),
                   fill_10_90_s=round(truth["fill_time_10_90"], 3),
                   airspeed_open=round(truth["airspeed_at_open"], 2), error="")
        fit_out = out / "fits" / f"{design}{k}"
        if vrc != 0:
            row["error"] = "validate refused: " + tail(out / "bundles" / f"{design}{k}.validate.log", 3)
            results.append(row)
            continue
        fit_out.parent.mkdir(parents=True, exist_ok=True)
        cmd = [exe, "fit", str(bundle), "--out", str(fit_out), "--seed", "0", "--workers", "1",
               "--max-steps", str(max_steps)] + (["--with", args.terms] if args.terms else [])
        wall_file = out / "fits" / f"{design}{k}.wall_s"
        if (fit_out / "summary.json").exists() and wall_file.exists():
            rc, wall = 0, float(wall_file.read_text())
        elif args.diagnose_only:
            continue
        else:
            rc, wall = run(cmd, out / "fits" / f"{design}{k}.log")
            wall_file.write_text(f"{wall:.1f}")
        row.update(fit_rc=rc, wall_s=round(wall, 1))
        try:
            summary = json.loads((fit_out / "summary.json").read_text())
            name, (q05, q50, q95), sd, medians, ratio, sensors = cds_o_parameter(
                summary, fit_out / "posterior.nc", truth["stated"]["chute_weight"])
            w_true = truth["vehicle_weight"] + truth["parachute_weight"]
            if ratio is not None:
                row.update(true_cds_per_weight=round(1e3 * truth["cds_o"] / w_true, 5),
                           cds_per_weight_q05=round(1e3 * ratio[0], 5), cds_per_weight_q50=round(1e3 * ratio[1], 5),
                           cds_per_weight_q95=round(1e3 * ratio[2], 5),
                           ratio_covered=bool(ratio[0] <= truth["cds_o"] / w_true <= ratio[2]))
            row.update(true_vehicle_weight=truth["vehicle_weight"],
                       stated_vehicle_weight=round(truth["stated"]["weight"], 1),
                       fitted_vehicle_weight=round(medians.get("vehicle_weight", float("nan")), 1),
                       true_latency=truth["gnss_latency"],
                       fitted_latency=round(medians.get("gnss_latency", float("nan")), 4),
                       fitted_noise_acc=round(medians.get("noise_acc", float("nan")), 3),
                       fitted_noise_gnss=round(medians.get("noise_gnss", float("nan")), 3),
                       **{f"{n}_q{q}": round(v, 4) for n, iv in sensors.items() for q, v in zip(("05", "95"), iv)},
                       latency_covered=bool(sensors["gnss_latency"][0] <= truth["gnss_latency"]
                                            <= sensors["gnss_latency"][1]),
                       scale_covered=bool(sensors["accel_scale"][0] <= 1.0 <= sensors["accel_scale"][1]),
                       warnings=";".join(w.get("code", "?") for w in summary.get("warnings", [])))
            conv, rhat, ess = diagnostics(summary)
            row.update(parameter=name, q05=round(q05, 3), q50=round(q50, 3), q95=round(q95, 3), sd=round(sd, 3),
                       covered=bool(q05 <= truth["cds_o"] <= q95), converged=conv,
                       rhat_max=None if rhat is None else round(float(rhat), 4),
                       ess_bulk_min=None if ess is None else round(float(ess), 1),
                       other_medians=json.dumps({n: round(v, 4) for n, v in medians.items() if n != name}))
        except Exception as exc:  # a failed fit is a result, not a reason to stop the study
            row["error"] = f"rc={rc}: {type(exc).__name__}: {exc} | log: " + tail(out / "fits" / f"{design}{k}.log", 4)
        results.append(row)
        print(" ".join(f"{str(row.get(h, '')):>10}" for h in
                       ["bundle", "true_cds_o", "q05", "q50", "q95", "covered", "converged", "rhat_max",
                        "ess_bulk_min", "wall_s"]).replace(str(bundle), f"{design}{k}"), flush=True)
        if row["error"]:
            print("   ", row["error"], flush=True)

    if args.diagnose_only:
        results = []          # fits still running elsewhere: leave results.csv to the full run
    with open(out / "results.csv" if not args.diagnose_only else os.devnull, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=FIELDS)
        writer.writeheader()
        for row in results:
            writer.writerow({f: row.get(f, "") for f in FIELDS})

    # --- same-canopy agreement -------------------------------------------------
    pairs = []
    print("\ndesign  overlap  |dmedian|/combined_sd")
    for canopy in designs:
        rows = [r for r in results if r["design"] == canopy.label and "q50" in r]
        if len(rows) != 2:
            continue
        a, b = rows
        overlap = bool(a["q05"] <= b["q95"] and b["q05"] <= a["q95"])
        z = abs(a["q50"] - b["q50"]) / math.hypot(a["sd"], b["sd"])
        pairs.append(dict(design=canopy.label, overlap=overlap, z=round(z, 2),
                          median_1=a["q50"], median_2=b["q50"], true_cds_o=canopy.cds_o))
        print(f"{canopy.label:>6}  {str(overlap):>7}  {z:.2f}", flush=True)
    with open(out / "pairs.csv" if not args.diagnose_only else os.devnull, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=["design", "overlap", "z", "median_1", "median_2", "true_cds_o"])
        writer.writeheader()
        writer.writerows(pairs)

    # --- diagnose one bundle per design ---------------------------------------
    if not (args.quick or args.no_diagnose):
        print("\ndiagnose (drop 1 of each design)")
        verdicts = []
        for canopy in designs:
            key = (canopy.label, 1)
            if key not in bundles or bundles[key][2] != 0:
                continue
            dout = out / "diagnose" / f"{canopy.label}1"
            dout.parent.mkdir(parents=True, exist_ok=True)
            wall_file = out / "diagnose" / f"{canopy.label}1.wall_s"
            if (dout / "diagnosis.json").exists() and wall_file.exists():
                rc, wall = 0, float(wall_file.read_text())
            else:
                rc, wall = run([exe, "diagnose", str(bundles[key][0]), "--out", str(dout), "--workers", "1"],
                               out / "diagnose" / f"{canopy.label}1.log")
                wall_file.write_text(f"{wall:.1f}")
            try:
                diag = json.loads((dout / "diagnosis.json").read_text())
                causes = diag.get("causes")
            except Exception as exc:
                causes = f"rc={rc}: {exc} | " + tail(out / "diagnose" / f"{canopy.label}1.log", 4)
            verdicts.append(dict(bundle=f"{canopy.label}1", rc=rc, wall_s=round(wall, 1), causes=json.dumps(causes)))
            print(f"  {canopy.label}1: rc={rc} wall {wall:.0f} s causes={causes}", flush=True)
        with open(out / "diagnose.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=["bundle", "rc", "wall_s", "causes"])
            writer.writeheader()
            writer.writerows(verdicts)
    if not args.diagnose_only:
        print(f"\nwrote {out / 'results.csv'} and {out / 'pairs.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

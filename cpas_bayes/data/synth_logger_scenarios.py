"""Scenario library and measurement ranges of the synthetic logger tests (:mod:`cpas_bayes.data.synth_logger`)."""

ACCEL_RATES = (20.0, 50.0, 100.0, 200.0)   # Hz
GNSS_RATES = (1.0, 2.0, 5.0, 10.0)         # Hz
WIND_LIMIT = 15.0                          # m/s, each stated component
WIND_SHEAR = 0.010                         # (m/s)/m, largest stated shear
WIND_SIGMA = (0.5, 3.0)                    # m/s
WIND_LEVELS = (3, 6)
ACCEL_SCALE_SIGMA, ACCEL_BIAS_SIGMA, ACCEL_NOISE = 0.01, 0.02, (0.01, 0.05)   # -, g, g
GNSS_SIGMA_H, GNSS_SIGMA_V, ALTITUDE_SIGMA, LATENCY = (0.05, 0.3), (0.1, 0.5), (2.0, 5.0), (0.0, 0.6)
DENSITY_GRID = 1.0                         # m, spacing of the tabulated log ρ

# Scenario library, SI (m, m/s, deg, N, m²). Stage values lie inside the shipped priors' support
# (data/priors/<kind>.toml): cd_o, n_p, expopen, ck, tk, eps of each stage's role. "first" is the
# first stage's start drawn per test, "jitter" the per-canopy spread added, "after" each later
# stage's start after the canopy's first. "descent" (logger-drop) draws the vehicle weight so the
# full-open sea-level descent rate lies in that range (within "vehicle_weight"): a 15 m canopy under
# a 500 N payload would be no drop test; its CDS_V = W_V / "vehicle_loading" (Pa: free-fall terminal
# speeds of 57–114 m/s at sea level). "drop": how far below altitude0 the wind profile reaches.
SCENARIOS = {
    "logger-drop": dict(
        duration=20.0, kind="main", inflation="finite", ids=("M1",), diameter=(5.0, 15.0),
        airspeed0=(40.0, 90.0), gamma0_deg=(-30.0, 0.0), altitude0=(1_200.0, 3_500.0), drop=600.0,
        vehicle_weight=(500.0, 5_000.0), descent=(5.0, 12.0), vehicle_cds=None, vehicle_loading=(2_000.0, 8_000.0),
        canopy_loading=(1.0, 1.5),
        cd_o=(0.45, 0.60), labels=("full open",), eps=(None,), first=(0.5, 2.0), jitter=0.0, after=(),
        n_p=((5.0, 12.0),), expopen=((1.4, 2.4),), ck=(None,), tk=(None,),
        weight_sigma=20.0, cds_sigma=0.05, parachute_weight_sigma=5.0),
    "logger-drogue": dict(   # synth "drogue" in SI: 23 ft, 240–265 ft², 19,000–21,500 lbf
        duration=25.0, kind="drogue", inflation="infinite", ids=("D1", "D2"), diameter=(7.0104, 7.0104),
        airspeed0=(100.0, 150.0), gamma0_deg=(-55.0, -40.0), altitude0=(6_000.0, 8_000.0), drop=3_000.0,
        vehicle_weight=(84_500.0, 95_600.0), descent=None, vehicle_cds=(1.30, 2.04), vehicle_loading=None,
        canopy_loading=(8.6, 10.4),
        cd_o=(0.58, 0.635), labels=("reefed 1", "full open"), eps=((0.42, 0.46), None), first=(0.6, 2.5),
        jitter=0.3, after=((8.0, 9.2),), n_p=((9.0, 13.5), (8.5, 12.0)), expopen=((2.0, 2.5), (1.9, 2.5)),
        ck=((1.15, 1.45), (1.10, 1.30)), tk=((0.35, 0.70), (0.40, 0.70)),
        weight_sigma=445.0, cds_sigma=0.186, parachute_weight_sigma=8.9),
    "logger-main": dict(     # synth "main" in SI: 116 ft, 5,350–5,850 ft², 16,500–18,500 lbf
        duration=45.0, kind="main", inflation="finite", ids=("M1", "M2", "M3"), diameter=(35.357, 35.357),
        airspeed0=(56.4, 65.5), gamma0_deg=(-72.0, -62.0), altitude0=(3_350.0, 3_800.0), drop=1_500.0,
        vehicle_weight=(73_400.0, 82_300.0), descent=None, vehicle_cds=(3.16, 3.90), vehicle_loading=None,
        canopy_loading=(1.31, 1.49),
        cd_o=(0.506, 0.553), labels=("reefed 1", "reefed 2", "full open"), eps=((0.05, 0.07), (0.18, 0.20), None),
        first=(0.8, 2.4), jitter=0.2, after=((9.2, 10.2), (19.1, 20.4)),
        n_p=((14.0, 21.0), (8.0, 13.0), (6.0, 7.5)), expopen=((1.6, 2.9), (1.6, 2.9), (1.4, 1.8)),
        ck=(None, None, None), tk=(None, None, None),
        weight_sigma=445.0, cds_sigma=0.186, parachute_weight_sigma=8.9),
}
# logger-drop with body axes and attitude in place of G (cpas_bayes.data.synth_attitude): a slow yaw spin (deg/s,
# either sense), a pendulum pitch and roll (deg amplitude) and a swing across v_air (fraction of the drag reading)
# at one frequency (Hz).
SCENARIOS["logger-attitude"] = dict(SCENARIOS["logger-drop"],
                                    attitude=dict(spin=(2.0, 20.0), tilt=(5.0, 20.0), frequency=(0.2, 0.5),
                                                  swing=(0.1, 0.3)))

"""truth.json of a synthetic logger test (:mod:`cpas_bayes.data.synth_logger`): what it records of the
simulated flight, when the logger sampled it, and the truth read back under the model's parameter names.

``truth`` is a :class:`~cpas_bayes.data.synth_logger.LoggerTruth`, ``trajectory`` a
:class:`~cpas_bayes.data.synth_logger.LoggerTrajectory` (not imported: that module imports this one)."""

from __future__ import annotations

import math
import numpy as np

from cpas_bayes.data.air_reconstruction import AIR_PARAMETERS as AIR_DATA_KEYS
from cpas_bayes.data.synth_attitude import attitude_document
from cpas_bayes.data.synth_logger_effects import effect_fields

def _sample_times(rate, first, duration):
    """k/rate for k from the first k with k/rate ≥ first to the last inside the record."""
    k = np.arange(math.ceil(first * rate - 1e-9), math.floor(duration * rate + 1e-9) + 1)
    return k / rate


def sample_times(truth):
    """(accelerometer times, GNSS times), s: j/r_a for j ≥ 1; k/r_g once t − latency ≥ 0."""
    return (_sample_times(truth.accel_rate, 1.0 / truth.accel_rate, truth.duration),
            _sample_times(truth.gnss_rate, truth.gnss_latency, truth.duration))


def first_reading_state(truth, trajectory) -> dict:
    """The air-relative state at the first accelerometer reading: where the fit's air parameters are defined."""
    t0 = sample_times(truth)[0][:1]
    position, velocity = trajectory.state_at(t0)
    wind = np.array([np.interp(t0[0], trajectory.time, trajectory.wind[:, i]) for i in range(2)] + [0.0])
    va = velocity[0] - wind
    speed = float(np.linalg.norm(va))
    return {"time": float(t0[0]), "airspeed": speed, "flight_path_angle": math.degrees(math.asin(va[2] / speed)),
            "heading": math.degrees(math.atan2(va[1], va[0])), "altitude": float(position[0, 2])}


def logger_truth_document(truth, trajectory) -> dict:
    """truth.json: synth's layout (SI, the bundle's units) plus the ``air_data`` table.

    ``air_data`` holds the release state (``airspeed_0`` ... at time 0) and, under
    ``first_reading``, the state at the first accelerometer reading, which is
    what the fit's air parameters of the same names describe."""
    chutes, peak_total = [], np.zeros(len(trajectory.time))
    qbar = trajectory.qbar
    for p, c in enumerate(truth.chutes):
        tension = qbar * trajectory.cds[p] - c.weight * trajectory.load_factor   # riser tension (Eq. 10)
        peak_total = peak_total + tension
        stages = [{"eps": s.eps, "start": s.start, "n": float(trajectory.timing[p].n[k]), "n_p": s.n_p,
                   "expopen": s.expopen, "ck": s.ck, "tk": s.tk, "cds_end": s.eps * c.cds_o,
                   "airspeed_start": float(trajectory.stage_airspeed[p, k])} for k, s in enumerate(c.stages)]
        chutes.append({"id": c.id, "cds_o": c.cds_o, "stages": stages, "peak_load": float(tension.max())})
    w = truth.wind
    air = {"airspeed_0": truth.airspeed_0, "flight_path_angle_0": truth.flight_path_angle_0,
           "heading_0": truth.heading_0, "altitude_0": truth.altitude_0, "wind_north": truth.wind_north,
           "wind_east": truth.wind_east, "accel_scale": truth.accel_scale, "accel_bias": truth.accel_bias,
           "gnss_latency": truth.gnss_latency, "accel_rate": truth.accel_rate, "gnss_rate": truth.gnss_rate,
           "accel_sigma": truth.accel_sigma, "gnss_sigma_horizontal": truth.gnss_sigma_horizontal,
           "gnss_sigma_up": truth.gnss_sigma_up, "altitude_sigma": truth.altitude_sigma,
           "wind_sigma": float(w.sigma), "first_reading": first_reading_state(truth, trajectory),
           "stated_wind": {"altitude": [float(v) for v in w.altitude], "north": [float(v) for v in w.north],
                           "east": [float(v) for v in w.east]}}
    return {"scenario": truth.scenario, "units": "SI", **effect_fields(truth.breathing, truth.added_mass),
            "vehicle_weight": truth.vehicle_weight, "vehicle_cds": truth.vehicle_cds,
            "chutes": chutes, "peak_total_load": float(peak_total.max()), "air_data": air,
            **attitude_document(truth.attitude)}


def logger_truth_parameters(truth_doc: dict) -> dict:
    """The truth under the model's parameter names, SI (truth.json of a logger test is SI).

    Air data: ``airspeed_0, flight_path_angle_0, heading_0, altitude_0, wind_north, wind_east,
    accel_scale, accel_bias, gnss_latency``; ``vehicle_weight``, ``vehicle_cds``; per canopy
    ``<id>.cds_o`` and ``<id>.s<k>.{start,n_p,expopen,ck,tk,eps}`` (k 1-based).
    """
    out = {key: float(truth_doc["air_data"][key]) for key in AIR_DATA_KEYS}
    first = truth_doc["air_data"]["first_reading"]
    for key in ("airspeed", "flight_path_angle", "heading", "altitude"):
        out[f"{key}_0"] = float(first[key])
    out["vehicle_weight"], out["vehicle_cds"] = float(truth_doc["vehicle_weight"]), float(truth_doc["vehicle_cds"])
    for c in truth_doc["chutes"]:
        out[f"{c['id']}.cds_o"] = float(c["cds_o"])
        for k, s in enumerate(c["stages"]):
            for name in ("start", "n_p", "expopen", "ck", "tk", "eps"):
                out[f"{c['id']}.s{k + 1}.{name}"] = float(s[name])
    return out

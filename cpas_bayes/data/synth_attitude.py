"""Body-axis accelerometer with attitude for the synthetic logger tests (scenario ``logger-attitude``).

:mod:`cpas_bayes.data.synth_logger` calls these functions when a
:class:`~cpas_bayes.data.synth_logger.LoggerTruth` has an :class:`AttitudeTruth`:
it then writes ``accel_x, accel_y, accel_z`` and the attitude quaternion
``q_w, q_x, q_y, q_z`` (docs/test-bundle.md; convention in
:mod:`cpas_bayes.data.attitude`) in place of ``G``.

Attitude (body to NED, aerospace yaw–pitch–roll, R = R_z(ψ)·R_y(θ)·R_x(φ))::

    ψ(t) = ψ0 + ω_s·t                                   a slow yaw spin
    θ(t) = A_θ·sin(2π·f·t + φ_θ),  φ(t) = A_φ·sin(2π·f·t + φ_φ)   the pendulum's pitch and roll

Specific force (g, NED), the point-mass drag plus a swing across the air-relative velocity::

    f(t) = G_true(t)·(−v̂_air) + s·G_true(t)·sin(2π·f·t + φ_s)·ê(t)

ê(t) ⟂ v̂_air turns with the yaw from a frame carried along v̂_air without twist
(parallel transport). The swing is sensed but not flown: the trajectory stays
the point-mass one the fit models, so the projection's truth is G_true. Each
axis is the box-car average over the reading's interval of R(t)ᵀ·f(t)
(trapezoid on the integration grid), times accel_scale, plus accel_bias along
−v̂_air at the reading (the fit's scalar bias means the same) and N(0, σ_G) per
axis; the quaternion is the one at the reading's time.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from cpas_bayes.data.attitude import quaternion_product, rotation_matrix

QUATERNION_COLUMNS = ("q_w", "q_x", "q_y", "q_z")
AXIS_COLUMNS = ("accel_x", "accel_y", "accel_z")


@dataclass(frozen=True)
class AttitudeTruth:
    """The attitude history and the swing of one synthetic test; angles in degrees."""

    yaw_0: float            # ψ0, deg from north toward east
    spin_rate: float        # ω_s, deg/s
    pitch_amplitude: float  # A_θ, deg
    roll_amplitude: float   # A_φ, deg
    frequency: float        # f, Hz: the pendulum's and the swing's
    pitch_phase: float      # φ_θ, rad
    roll_phase: float       # φ_φ, rad
    swing_amplitude: float  # s: lateral specific force / drag reading
    swing_phase: float      # φ_s, rad
    swing_angle: float      # ê's angle at release in the transported frame, deg


def draw_attitude_truth(spec: dict, rng: np.random.Generator) -> AttitudeTruth:
    """Uniform draws within a scenario's ``attitude`` ranges (``spin``, ``tilt``, ``frequency``, ``swing``)."""
    def uniform(bounds):
        return float(rng.uniform(*bounds))

    spin = uniform(spec["spin"]) * (1.0 if rng.random() < 0.5 else -1.0)
    return AttitudeTruth(
        yaw_0=uniform((0.0, 360.0)), spin_rate=spin, pitch_amplitude=uniform(spec["tilt"]),
        roll_amplitude=uniform(spec["tilt"]), frequency=uniform(spec["frequency"]),
        pitch_phase=uniform((0.0, 2 * math.pi)), roll_phase=uniform((0.0, 2 * math.pi)),
        swing_amplitude=uniform(spec["swing"]), swing_phase=uniform((0.0, 2 * math.pi)),
        swing_angle=uniform((0.0, 360.0)))


def attitude_document(attitude: AttitudeTruth | None) -> dict:
    """truth.json's ``attitude`` table (swing amplitude and frequency among it); none without attitude."""
    return {} if attitude is None else {"attitude": asdict(attitude)}


def _axis_quaternion(angle, axis):
    q = np.zeros((np.size(angle), 4))
    q[:, 0] = np.cos(0.5 * angle)
    q[:, axis] = np.sin(0.5 * angle)
    return q


def attitude_quaternions(attitude: AttitudeTruth, t) -> np.ndarray:
    """Body-to-NED unit quaternions (N, 4), scalar first, at times ``t`` (N,)."""
    t = np.asarray(t, float)
    omega = 2 * math.pi * attitude.frequency
    yaw = np.radians(attitude.yaw_0 + attitude.spin_rate * t)
    pitch = np.radians(attitude.pitch_amplitude) * np.sin(omega * t + attitude.pitch_phase)
    roll = np.radians(attitude.roll_amplitude) * np.sin(omega * t + attitude.roll_phase)
    return quaternion_product(quaternion_product(_axis_quaternion(yaw, 3), _axis_quaternion(pitch, 2)),
                              _axis_quaternion(roll, 1))


def _transported_frame(direction):
    """(e1, e2) (N, 3) ⟂ each row of ``direction`` (N, 3), e1 carried from row to row without twist."""
    n = direction.shape[0]
    e1 = np.empty((n, 3))
    seed = np.zeros(3)
    seed[int(np.argmin(np.abs(direction[0])))] = 1.0   # the axis least along v̂ at release
    e = seed - (seed @ direction[0]) * direction[0]
    rows = direction.tolist()
    e = e.tolist()
    for k in range(n):   # plain floats: ~10⁵ grid points
        d = rows[k]
        dot = e[0] * d[0] + e[1] * d[1] + e[2] * d[2]
        e = [e[0] - dot * d[0], e[1] - dot * d[1], e[2] - dot * d[2]]
        norm = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        e = [e[0] / norm, e[1] / norm, e[2] / norm]
        e1[k] = e
    return e1, np.cross(direction, e1)


def swing_force(attitude: AttitudeTruth, t, direction, load_factor):
    """The swing's specific force (N, 3), g, NED, at times ``t`` (N,): ⟂ v̂_air (``direction`` (N, 3)),
    amplitude ``swing_amplitude``·G_true (``load_factor`` (N,))."""
    t = np.asarray(t, float)
    e1, e2 = _transported_frame(direction)
    angle = np.radians(attitude.swing_angle + attitude.spin_rate * t)[:, None]
    size = attitude.swing_amplitude * load_factor * np.sin(2 * math.pi * attitude.frequency * t
                                                           + attitude.swing_phase)
    return size[:, None] * (np.cos(angle) * e1 + np.sin(angle) * e2)


def body_axis_readings(attitude: AttitudeTruth, grid, air_velocity, load_factor, reading_times, interval, scale,
                       bias, noise) -> dict:
    """The logged columns at ``reading_times`` (n,): ``accel_x, accel_y, accel_z`` (g) and ``q_w ... q_z``.

    ``air_velocity`` (N, 3) north, east, up and ``load_factor`` (N,) G_true on the uniform ``grid`` (N,), on
    which the readings' times and their averaging ``interval`` (s) before each fall; ``noise`` (n, 3) is
    added to the axes.
    """
    step = grid[1] - grid[0]
    rows = np.round((np.asarray(reading_times) - grid[0]) / step).astype(int)
    span = int(round(interval / step))
    ned = air_velocity * np.array([1.0, 1.0, -1.0])
    direction = ned / np.linalg.norm(ned, axis=1, keepdims=True)
    force = -load_factor[:, None] * direction + swing_force(attitude, grid, direction, load_factor)
    rotation = rotation_matrix(attitude_quaternions(attitude, grid))
    body = np.einsum("nji,nj->ni", rotation, force)   # Rᵀ·f
    integral = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * step * (body[1:] + body[:-1]), axis=0)])
    mean = (integral[rows] - integral[rows - span]) / (span * step)
    q = attitude_quaternions(attitude, grid[rows])
    drag_axis = np.einsum("nji,nj->ni", rotation_matrix(q), -direction[rows])   # −v̂_air in body axes
    axes = scale * mean + bias * drag_axis + noise
    out = {c: axes[:, i] for i, c in enumerate(AXIS_COLUMNS)}
    out.update({c: q[:, i] for i, c in enumerate(QUATERNION_COLUMNS)})
    return out


def write_body_axes(data: dict, truth, trajectory, reading_times, rows, noise):
    """Replace ``G`` and ``G_sigma`` in the logger's ``data`` (column -> (rows,) array, NaN blank) by the
    body axes, their sigmas and the attitude (:func:`body_axis_readings`) on the readings' ``rows``.

    ``truth`` is the :class:`~cpas_bayes.data.synth_logger.LoggerTruth` (with ``attitude``), ``trajectory``
    its :class:`~cpas_bayes.data.synth_logger.LoggerTrajectory`; ``noise`` (n, 3) is added to the axes.
    """
    logged = body_axis_readings(truth.attitude, trajectory.time, trajectory.air_velocity, trajectory.load_factor,
                                reading_times, 1.0 / truth.accel_rate, truth.accel_scale, truth.accel_bias, noise)
    logged.update({f"{c}_sigma": np.full(len(reading_times), truth.accel_sigma) for c in AXIS_COLUMNS})
    columns = {}
    for c in AXIS_COLUMNS + tuple(f"{c}_sigma" for c in AXIS_COLUMNS) + QUATERNION_COLUMNS:
        columns[c] = np.full(len(data["time"]), np.nan)
        columns[c][rows] = logged[c]
    rest = {c: v for c, v in data.items() if c not in ("time", "G", "G_sigma")}
    time = data["time"]
    data.clear()
    data.update({"time": time, **columns, **rest})

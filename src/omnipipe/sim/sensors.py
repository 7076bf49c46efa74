"""The robot's own sensors in a simulated run: odometry and an IMU (contract section 1).

``odometry.txt`` (``<time s> <distance_mm> <sigma_mm>``): the cumulative travel along
the pipe, i.e. the centreline arc length of the rig's station since frame 0, as a
cable counter or stroke actuator reports it: a run-wide slip (U(1, 3) %: the counter
reads more than the robot advanced), a random walk that grows only while the robot
moves (a counter at rest does not change; it never counts backwards), and
quantisation. ``sigma_mm`` states the reading's 1-sigma uncertainty:
hypot(``sigma_rel`` x distance, walk x sqrt(distance), quantum / sqrt(12)), with
``sigma_rel`` = 3 % covering the slip.

``imu.txt`` (``<time s> ax ay az wx wy wz``): specific force (m/s^2; the accelerometer
reads a - g, so +9.81 m/s^2 "up" at rest) and angular rate (rad/s) in the rig frame,
from the true trajectory between frames (:func:`omnipipe.sim.motion.travel_at_times`),
each axis with a constant bias and white noise. Gravity (9.80665 m/s^2) points along
the scene's gravity (``Pipe.features.gravity``: world -y unless the scenario says
otherwise), or along ``SensorConfig.gravity_world`` when that is set. The IMU covers
the run from a second before the first frame to a second after the last (the robot at rest), the odometry
from the first frame to a second after the last.

Sensor draws come from their own seed (``SeedSequence([seed, 0x53454E53])``), so
switching a sensor off changes nothing else in the run.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from omnipipe.sim.motion import poses_at_travel, travel_at_times
from omnipipe.sim.sensor_config import SensorConfig

if TYPE_CHECKING:
    from omnipipe.sim.scenario import Scenario

STANDARD_GRAVITY = 9.80665  # m/s^2
_SENSOR_SEED_TAG = 0x53454E53  # "SENS"
SENSOR_MARGIN_S = 1.0  # the sensors record this long before (IMU) and after the frames


@dataclass(frozen=True)
class SimulatedSensors:
    """A run's sensor readings and their truth.

    Attributes:
        odometry: (K, 3) time (s), reading (mm), stated sigma (mm); None when off.
        imu: (M, 7) time (s), specific force (m/s^2, rig frame), rate (rad/s); None when off.
        truth: scene.json's ``sensors``: the drawn slip and biases, the error model, the
            true travel and gravity direction (rig frame) at every frame.
    """

    odometry: np.ndarray | None
    imu: np.ndarray | None
    truth: dict


def simulate_sensors(
    scenario: Scenario, frame_times_s: np.ndarray, sigma_mm: np.ndarray, poses: np.ndarray
) -> SimulatedSensors:
    """Odometry and IMU readings of ``scenario``'s run (frames at ``frame_times_s``,
    stations ``sigma_mm``, true poses ``poses`` (N, 4, 4))."""
    cfg = scenario.sensors
    seq = np.random.SeedSequence([int(scenario.seed), _SENSOR_SEED_TAG])
    rng, rng_odo, rng_imu = (np.random.default_rng(s) for s in seq.spawn(3))
    travel = np.asarray(sigma_mm, float) - float(sigma_mm[0])
    g_world = gravity_world(scenario)
    g_rig = np.einsum("nji,j->ni", poses[:, :3, :3], g_world / np.linalg.norm(g_world))
    truth: dict = {
        "config": asdict(cfg),
        "distance_at_frames_mm": travel.round(6).tolist(),
        "gravity_in_rig_at_frames": g_rig.round(9).tolist(),
        "conventions": "odometry distance: centreline arc length since frame 0 (mm); "
        "gravity_in_rig_at_frames: unit vector of gravity (pointing down) in each frame's rig frame",
    }
    odo = imu = None
    # The run's constants are drawn whatever is switched off; each sensor's noise from
    # its own stream, so switching one off changes nothing in the other.
    slip = float(rng.uniform(*cfg.slip_range))
    accel_bias = rng.normal(0.0, cfg.accel_bias_sigma, 3)
    gyro_bias = rng.normal(0.0, cfg.gyro_bias_sigma, 3)
    if cfg.odometry:
        odo = _odometry(cfg, rng_odo, frame_times_s, travel, slip)
        truth["odometry"] = {"slip": slip}
    if cfg.imu:
        imu = _imu(scenario, rng_imu, frame_times_s, travel, accel_bias, gyro_bias)
        truth["imu"] = {"accel_bias": accel_bias.tolist(), "gyro_bias": gyro_bias.tolist()}
    return SimulatedSensors(odo, imu, truth)


def gravity_world(scenario: Scenario) -> np.ndarray:
    """(3,) gravity (m/s^2) in the world frame of ``scenario``'s run."""
    if scenario.sensors.gravity_world is not None:
        return np.asarray(scenario.sensors.gravity_world, float)
    return STANDARD_GRAVITY * np.asarray(scenario.pipe.features.gravity, float)


def _knots(frame_t: np.ndarray, travel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frame times and travel extended by virtual frames: at rest before the first frame,
    and after the last a stroke in progress eases to a stop (one more frame step, spread
    over three frames), so the sensors see no jump in velocity at the run's ends."""
    dt = float(frame_t[1] - frame_t[0]) if len(frame_t) > 1 else 1.0
    last = float(travel[-1] - travel[-2]) if len(travel) > 1 else 0.0
    t = np.concatenate([[frame_t[0] - 2 * dt, frame_t[0] - dt], frame_t,
                        frame_t[-1] + dt * np.arange(1, 5)])  # fmt: skip
    d = np.concatenate([[travel[0]] * 2, travel, travel[-1] + last * np.array([0.6, 0.9, 1.0, 1.0])])
    return t, d


def _odometry(
    cfg: SensorConfig, rng: np.random.Generator, frame_t: np.ndarray, travel: np.ndarray, slip: float
) -> np.ndarray:
    t = np.arange(float(frame_t[0]), float(frame_t[-1]) + SENSOR_MARGIN_S, 1.0 / cfg.odometry_rate_hz)
    true = travel_at_times(*_knots(frame_t, travel), t)
    inc = np.diff(true, prepend=true[0])
    walk = cfg.odometry_walk_mm * np.sqrt(inc) * rng.standard_normal(len(t))
    reading = np.cumsum(np.maximum((1.0 + slip) * inc + walk, 0.0))  # never backwards
    q = cfg.odometry_quantum_mm
    if q > 0:
        reading = np.round(reading / q) * q
    d = np.abs(reading)
    sigma = np.sqrt(
        (cfg.odometry_sigma_rel * d) ** 2 + cfg.odometry_walk_mm**2 * d + q * q / 12.0
    )
    return np.stack([t, reading, sigma], axis=1)


def _imu(
    scenario: Scenario,
    rng: np.random.Generator,
    frame_t: np.ndarray,
    travel: np.ndarray,
    accel_bias: np.ndarray,
    gyro_bias: np.ndarray,
) -> np.ndarray:
    """IMU samples: specific force and rate from the trajectory by central differences."""
    cfg = scenario.sensors
    step = 1.0 / cfg.imu_rate_hz
    t = np.arange(float(frame_t[0]) - SENSOR_MARGIN_S, float(frame_t[-1]) + SENSOR_MARGIN_S, step)
    h = 2e-3  # s: difference step, well below the gait's time scale
    stacked = np.concatenate([t - h, t, t + h])
    poses = poses_at_travel(
        scenario.pipe, scenario.motion, scenario.frames, scenario.seed,
        travel_at_times(*_knots(frame_t, travel), stacked),
    )  # fmt: skip
    n = len(t)
    p = poses[:, :3, 3].reshape(3, n, 3) * 1e-3  # m
    rot = poses[:, :3, :3].reshape(3, n, 3, 3)
    acc_world = (p[0] - 2.0 * p[1] + p[2]) / (h * h)
    f_world = acc_world - gravity_world(scenario)
    f_rig = np.einsum("nji,nj->ni", rot[1], f_world)
    rel = np.einsum("nji,njk->nik", rot[0], rot[2])  # R(t-h)^T R(t+h)
    omega = Rotation.from_matrix(rel).as_rotvec() / (2.0 * h)
    f_meas = f_rig + accel_bias + rng.normal(0.0, cfg.accel_noise, (n, 3))
    w_meas = omega + gyro_bias + rng.normal(0.0, cfg.gyro_noise, (n, 3))
    return np.concatenate([t[:, None], f_meas, w_meas], axis=1)


def write_sensor_files(out_dir: Path, sensors: SimulatedSensors) -> None:
    """odometry.txt and imu.txt (the ones simulated) in ``out_dir``."""
    if sensors.odometry is not None:
        lines = "".join(f"{t:.6f} {d:.3f} {s:.3f}\n" for t, d, s in sensors.odometry)
        (out_dir / "odometry.txt").write_text(
            "# time_s distance_mm sigma_mm (omnipipe simulate)\n" + lines, encoding="utf-8"
        )
    if sensors.imu is not None:
        lines = "".join(
            f"{r[0]:.6f} " + " ".join(f"{v:.6f}" for v in r[1:]) + "\n" for r in sensors.imu
        )
        (out_dir / "imu.txt").write_text(
            "# time_s ax ay az (m/s^2) wx wy wz (rad/s), rig frame (omnipipe simulate)\n" + lines,
            encoding="utf-8",
        )


__all__ = ["SensorConfig", "SimulatedSensors", "simulate_sensors", "write_sensor_files"]

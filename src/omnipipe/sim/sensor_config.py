"""What a simulated run's robot sensors are and how they err (:class:`SensorConfig`).

The config lives apart from :mod:`omnipipe.sim.sensors` (which draws the readings
from a scenario) so that a scenario can hold its sensors' config without importing
the code that reads the scenario.
"""

from __future__ import annotations

from dataclasses import dataclass

from omnipipe.errors import ConfigError


@dataclass(frozen=True)
class SensorConfig:
    """Which robot sensors a simulated run writes, and their error model.

    Attributes:
        odometry: write odometry.txt.
        imu: write imu.txt.
        odometry_rate_hz: odometry readings per second.
        slip_range: the run's slip is drawn from U(lo, hi) (fraction; reading = (1 + slip)
            x true travel).
        odometry_walk_mm: random walk of the count (mm per sqrt(mm) travelled, 1 sigma).
        odometry_quantum_mm: resolution of the counter (mm).
        odometry_sigma_rel: relative part of the stated sigma (covers the slip).
        imu_rate_hz: IMU samples per second.
        accel_noise: accelerometer white noise (m/s^2, 1 sigma per axis and sample).
        accel_bias_sigma: each axis' constant bias ~ N(0, this) (m/s^2).
        gyro_noise: gyro white noise (rad/s, 1 sigma).
        gyro_bias_sigma: each gyro axis' constant bias ~ N(0, this) (rad/s).
        gravity_world: gravity in the world frame (m/s^2); None: the scene's gravity
            direction (``Pipe.features.gravity``) x 9.80665 m/s^2.
    """

    odometry: bool = True
    imu: bool = True
    odometry_rate_hz: float = 20.0
    slip_range: tuple[float, float] = (0.01, 0.03)
    odometry_walk_mm: float = 0.1
    odometry_quantum_mm: float = 0.1
    odometry_sigma_rel: float = 0.03
    imu_rate_hz: float = 100.0
    accel_noise: float = 0.02
    accel_bias_sigma: float = 0.03
    gyro_noise: float = 0.002
    gyro_bias_sigma: float = 0.0005
    gravity_world: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        for name in ("odometry_rate_hz", "imu_rate_hz"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"sensors.{name}", f"must be > 0, got {getattr(self, name)}")
        if not 0 <= self.slip_range[0] <= self.slip_range[1] <= self.odometry_sigma_rel:
            raise ConfigError(
                "sensors.slip_range", "must satisfy 0 <= lo <= hi <= odometry_sigma_rel"
            )

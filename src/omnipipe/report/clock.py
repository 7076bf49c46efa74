"""Where 12 o'clock is: the clock positions an inspector reads.

A clock position is an angle around the pipe, viewed looking in the direction of travel,
clockwise from 12:00 = the top of the pipe. omnipipe's own angle (report.json
``angle_deg``) runs from the first rig frame's x axis towards y; 12:00 is one such angle,
taken from (first found):

1. survey.yaml ``clock_reference_deg`` (the inspector's statement);
2. gravity: the accelerometer of ``imu.txt`` or the bag's IMU topic (``Dataset.imu``)
   around the first frame's time (:func:`omnipipe.inputs.sensors.gravity_at`): at rest it
   measures the specific force, which points up;
3. otherwise the first rig frame's -y axis (image up), said once in the report and in
   defects.csv ("clock from image up: no gravity reference").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from omnipipe.inputs.sensors import Imu
    from omnipipe.survey import Survey

NO_GRAVITY = "image up in the first frame: no gravity reference"


@dataclass(frozen=True)
class ClockReference:
    """The omnipipe angle that is 12:00 and where it came from.

    Attributes:
        angle_deg: omnipipe angle (deg from the first rig frame's x axis towards y, around
            the travel direction) that is 12:00.
        source: "survey.yaml clock_reference_deg", "gravity (imu.txt)" or :data:`NO_GRAVITY`.
        gravity: True when 12:00 is the top of the pipe by a stated or measured reference.
        sigma_deg: 1-sigma of ``angle_deg`` (0: stated, or image up by definition).
    """

    angle_deg: float
    source: str
    gravity: bool
    sigma_deg: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """report.json ``clock_reference``."""
        return {
            "angle_deg": round(self.angle_deg, 3),
            "sigma_deg": round(self.sigma_deg, 3),
            "source": self.source,
            "gravity": self.gravity,
        }

    @staticmethod
    def from_dict(data: dict[str, Any] | None) -> ClockReference | None:
        """Read report.json ``clock_reference`` back (None when absent or malformed)."""
        if not isinstance(data, dict) or not isinstance(data.get("angle_deg"), int | float):
            return None
        sigma = data.get("sigma_deg")
        return ClockReference(
            float(data["angle_deg"]),
            str(data.get("source") or ""),
            bool(data.get("gravity")),
            float(sigma) if isinstance(sigma, int | float) else 0.0,
        )


def image_up_angle_deg(travel_along_rig_z: float = 1.0) -> float:
    """The omnipipe angle of the first rig frame's -y axis (image up).

    The angle runs around the direction of travel from x towards the axis that completes
    a right-handed frame: y when the robot moves along +z of its rig frame, -y when along -z.
    """
    return -90.0 if travel_along_rig_z >= 0 else 90.0


def angle_of_rig_vector(vector: np.ndarray, travel_along_rig_z: float = 1.0) -> float:
    """The omnipipe angle (deg) of a rig-frame direction's component across the axis."""
    x, y = float(vector[0]), float(vector[1])
    return math.degrees(math.atan2(y if travel_along_rig_z >= 0 else -y, x))


def imu_up(imu: Imu, t0_s: float) -> tuple[np.ndarray, float] | None:
    """(unit up direction in the rig frame, its 1-sigma angle in rad) at ``t0_s`` from the
    accelerometer (:func:`omnipipe.inputs.sensors.gravity_at`; when the recording starts at
    the first frame, the first whole window after it), or None: no usable window, or up
    along the mirror axis (no clock position across the axis)."""
    from omnipipe.inputs.sensors import GRAVITY_WINDOW_S, gravity_at

    times = np.array([float(t0_s), float(t0_s) + 0.5 * GRAVITY_WINDOW_S])
    down, sigma = gravity_at(imu, times)
    usable = np.isfinite(down).all(axis=1) & np.isfinite(sigma)
    if not usable.any():
        return None
    k = int(np.argmax(usable))
    down, sigma = down[k:k + 1], sigma[k:k + 1]
    up = -down[0]
    if math.hypot(up[0], up[1]) < 0.1:
        return None
    return up, float(sigma[0])


def clock_reference(
    survey: Survey | None,
    up_in_rig: np.ndarray | None = None,
    travel_along_rig_z: float = 1.0,
    up_sigma_rad: float = 0.0,
) -> ClockReference:
    """12:00 of a run: the survey's statement, else gravity (``up_in_rig``, the first
    frame's up direction in its rig frame, 1-sigma ``up_sigma_rad``), else image up."""
    if survey is not None and survey.clock_reference_deg is not None:
        return ClockReference(float(survey.clock_reference_deg), "survey.yaml clock_reference_deg", True)
    if up_in_rig is not None:
        across = math.hypot(float(up_in_rig[0]), float(up_in_rig[1])) / float(np.linalg.norm(up_in_rig))
        return ClockReference(
            angle_of_rig_vector(up_in_rig, travel_along_rig_z),
            "gravity (imu.txt)",
            True,
            math.degrees(up_sigma_rad) / max(across, 1e-6),
        )
    return ClockReference(image_up_angle_deg(travel_along_rig_z), NO_GRAVITY, False)


def clock_position(angle_deg: float, reference_deg: float) -> tuple[str, float]:
    """(``"hh:mm"``, degrees clockwise from 12) of an omnipipe angle.

    Args:
        angle_deg: report.json ``angle_deg``; increasing angles run clockwise as seen
            looking along the travel direction.
        reference_deg: the angle that is 12 o'clock.
    """
    clock_deg = (angle_deg - reference_deg) % 360.0
    minutes = round(clock_deg * 2.0) % 720  # 0.5 degree per clock minute
    hours, mins = divmod(minutes, 60)
    return f"{hours or 12:02d}:{mins:02d}", clock_deg

"""Where 12 o'clock is: the clock positions an inspector reads.

A clock position is an angle around the pipe, viewed looking in the direction of travel,
clockwise from 12:00 = the top of the pipe. omnipipe's own angle (report.json
``angle_deg``) runs from the first rig frame's x axis towards y; 12:00 is one such angle,
taken from (first found):

1. survey.yaml ``clock_reference_deg`` (the inspector's statement);
2. gravity: the accelerometer of ``imu.txt`` (DATA_CONTRACT.md section 1) around the
   first frame's time: at rest it measures the specific force, which points up;
3. otherwise the first rig frame's -y axis (image up), said once in the report and in
   defects.csv ("clock from image up: no gravity reference").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from omnipipe.survey import Survey

IMU_FILE = "imu.txt"
# Accelerometer samples averaged for the up direction: those within this many seconds of
# the first frame (the rig's attitude then defines the angles' frame).
IMU_WINDOW_S = 1.0
NO_GRAVITY = "image up in the first frame: no gravity reference"


@dataclass(frozen=True)
class ClockReference:
    """The omnipipe angle that is 12:00 and where it came from.

    Attributes:
        angle_deg: omnipipe angle (deg from the first rig frame's x axis towards y, around
            the travel direction) that is 12:00.
        source: "survey.yaml clock_reference_deg", "gravity (imu.txt)" or :data:`NO_GRAVITY`.
        gravity: True when 12:00 is the top of the pipe by a stated or measured reference.
    """

    angle_deg: float
    source: str
    gravity: bool

    def to_dict(self) -> dict[str, Any]:
        """report.json ``clock_reference``."""
        return {"angle_deg": round(self.angle_deg, 3), "source": self.source, "gravity": self.gravity}

    @staticmethod
    def from_dict(data: dict[str, Any] | None) -> ClockReference | None:
        """Read report.json ``clock_reference`` back (None when absent or malformed)."""
        if not isinstance(data, dict) or not isinstance(data.get("angle_deg"), int | float):
            return None
        return ClockReference(float(data["angle_deg"]), str(data.get("source") or ""), bool(data.get("gravity")))


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


def read_imu_up(path: Path, t0_s: float, window_s: float = IMU_WINDOW_S) -> np.ndarray | None:
    """Unit up direction in the rig frame from ``imu.txt`` (mean specific force of the
    samples within ``window_s`` of ``t0_s``), or None: no file, no usable samples, or an
    up direction along the mirror axis (no clock position across the axis)."""
    if not path.is_file():
        return None
    rows = []
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        parts = line.split()
        if len(parts) < 4 or line.lstrip().startswith("#"):
            continue
        try:
            rows.append([float(v) for v in parts[:4]])
        except ValueError:
            continue
    if not rows:
        return None
    a = np.asarray(rows)
    a = a[np.isfinite(a).all(axis=1)]
    near = a[np.abs(a[:, 0] - t0_s) <= window_s]
    if not len(near):
        return None
    up = near[:, 1:4].mean(axis=0)
    norm = float(np.linalg.norm(up))
    if not norm > 0 or math.hypot(up[0], up[1]) < 0.1 * norm:
        return None
    return up / norm


def clock_reference(
    survey: Survey | None,
    up_in_rig: np.ndarray | None = None,
    travel_along_rig_z: float = 1.0,
) -> ClockReference:
    """12:00 of a run: the survey's statement, else gravity (``up_in_rig``, the first
    frame's up direction in its rig frame), else image up."""
    if survey is not None and survey.clock_reference_deg is not None:
        return ClockReference(float(survey.clock_reference_deg), "survey.yaml clock_reference_deg", True)
    if up_in_rig is not None:
        return ClockReference(angle_of_rig_vector(up_in_rig, travel_along_rig_z), "gravity (imu.txt)", True)
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

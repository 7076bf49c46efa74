"""The simulator's run record (:class:`Scenario`) and the paper-like rig: a Hyper70-like
mirror whose rim fills the image height (:func:`paper_rig`, :func:`rim_focal_px`).

Every scenario module builds its runs from these; the registry is :mod:`omnipipe.sim.scenarios`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from omnipipe.errors import ConfigError
from omnipipe.rig import CameraIntrinsics, LaserPlane, Mirror, Rig
from omnipipe.sim.motion import MotionConfig
from omnipipe.sim.render import RenderConfig, blind_radius_px
from omnipipe.sim.scene import Pipe
from omnipipe.sim.sensor_config import SensorConfig
from omnipipe.sim.texture import TextureConfig

# Hyper70-like mirror: a published parameter set of the maker's hyperboloid mirror.
HYPER70_A_MM = 21.57
HYPER70_B_MM = 32.49
HYPER70_RIM_RADIUS_MM = 35.0


def check_size_frames(size: tuple[int, int] | None, frames: int | None) -> None:
    """Refuse an image ``size`` (width, height px) under 64x48 or a frame count under 1
    (None: the scenario's own), naming the option."""
    if size is not None and (size[0] < 64 or size[1] < 48):
        raise ConfigError("size", f"must be at least 64x48, got {size[0]}x{size[1]}")
    if frames is not None and frames < 1:
        raise ConfigError("frames", f"must be >= 1, got {frames}")


def rim_focal_px(mirror: Mirror, rim_radius_mm: float, rim_image_radius_px: float) -> float:
    """Image distance f (px) that puts the mirror rim at ``rim_image_radius_px``.

    The rim point (rim_radius, Z) lies on the mirror sheet (Z + c)^2 = b^2 (1 + r^2/a^2);
    seen from the lens centre at Z = -2c it images at f r / (Z + 2c).
    """
    c = mirror.c
    z_rim = mirror.b * math.sqrt(1.0 + (rim_radius_mm / mirror.a) ** 2) - c
    return rim_image_radius_px * (z_rim + 2.0 * c) / rim_radius_mm


def paper_rig(
    width: int = 1600,
    height: int = 1200,
    baseline_mm: float = 82.0,
    render: RenderConfig | None = None,
    principal_offset_px: tuple[float, float] = (0.0, 0.0),
    mirror: Mirror | None = None,
    rim_radius_mm: float = HYPER70_RIM_RADIUS_MM,
) -> Rig:
    """The paper's rangefinder: Hyper70-like mirror whose 70 mm rim fills the image height.

    ``mirror``, ``rim_radius_mm``, ``baseline_mm`` and ``principal_offset_px`` make other rigs.
    """
    mirror = mirror or Mirror(HYPER70_A_MM, HYPER70_B_MM)
    rim_px = height / 2.0 - max(abs(principal_offset_px[0]), abs(principal_offset_px[1]))
    f = rim_focal_px(mirror, rim_radius_mm, rim_px)
    cam = CameraIntrinsics(
        width=width,
        height=height,
        cx=(width - 1) / 2.0 + principal_offset_px[0],
        cy=(height - 1) / 2.0 + principal_offset_px[1],
        f=f,
        pixel_pitch=0.0044 * 1600 / width,
        radius_min=None,
        radius_max=rim_px - 1.0,
    )
    rig = Rig(cam, mirror, LaserPlane((0.0, 0.0, 1.0, baseline_mm), "red"))
    r_min = blind_radius_px(rig, render or RenderConfig())
    return Rig(replace(cam, radius_min=round(r_min, 1)), mirror, rig.laser)


@dataclass
class Scenario:
    """Everything the simulator needs for one run.

    Attributes:
        name: scenario name.
        rig: the rangefinder calibration written to rig.yaml.
        pipe: the true pipe.
        motion: the earthworm gait.
        render: light, optics, sensor.
        texture: procedural wall texture.
        frames: number of frames.
        seed: master seed (texture, motion, noise).
        fps: frame rate for timestamps.txt (frames per second).
        dark_frames: also write each station's laser-only frame (LED off) to frames_noled/.
        random: for ``random`` scenarios, the drawn parameters (family, diameter, bend,
            gait, rig), written to scene.json's ``random``; None otherwise.
        sensors: the robot's odometry and IMU (omnipipe.sim.sensors).
    """

    name: str
    rig: Rig
    pipe: Pipe
    motion: MotionConfig = field(default_factory=MotionConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    texture: TextureConfig = field(default_factory=TextureConfig)
    frames: int = 100
    seed: int = 0
    fps: float = 8.0
    dark_frames: bool = False
    random: dict[str, Any] | None = None
    sensors: SensorConfig = field(default_factory=SensorConfig)

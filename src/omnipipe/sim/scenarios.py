"""Named simulation scenarios and the paper-like rig.

``paper`` reproduces the paper's experiment (Sec. VII, Table I); ``bend`` is a bent
pipe of another size with a dent and a bulge; ``other-rig`` has another mirror, an
off-centre principal point and a smaller pipe; ``*-small`` are the same scenes
400 px wide with short runs, for tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from omnipipe.errors import ConfigError
from omnipipe.rig import CameraIntrinsics, LaserPlane, Mirror, Rig
from omnipipe.sim.motion import MotionConfig
from omnipipe.sim.render import RenderConfig, blind_radius_px
from omnipipe.sim.scene import Centreline, Defect, Pipe
from omnipipe.sim.texture import TextureConfig

# Hyper70-like mirror: a published parameter set of the maker's hyperboloid mirror.
HYPER70_A_MM = 21.57
HYPER70_B_MM = 32.49
HYPER70_RIM_RADIUS_MM = 35.0


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


def _paper(width: int, height: int, frames: int) -> Scenario:
    bulge = Defect(
        kind="bulge",
        height_mm=5.0,
        width_mm=5.0,
        length_mm=100.0,
        axial_start_mm=150.0,
        angle_deg=60.0,
    )
    pipe = Pipe(inner_diameter_mm=202.0, defects=[bulge])
    return Scenario(
        "paper", paper_rig(width, height), pipe, MotionConfig(start_mm=200.0, frames_per_cycle=24),
        frames=frames,
    )


def _bend(width: int, height: int, frames: int) -> Scenario:
    pipe = Pipe(
        inner_diameter_mm=160.0,
        centreline=Centreline(
            straight_mm=330.0, bend_radius_mm=650.0, bend_angle_deg=40.0, bend_direction_deg=30.0
        ),
        defects=[
            Defect(
                kind="dent",
                height_mm=3.0,
                width_mm=20.0,
                length_mm=30.0,
                axial_start_mm=200.0,
                angle_deg=200.0,
            ),
            Defect(
                kind="bulge",
                height_mm=4.0,
                width_mm=8.0,
                length_mm=40.0,
                axial_start_mm=330.0,
                angle_deg=300.0,
            ),
        ],
    )
    motion = MotionConfig(start_mm=180.0, stroke_mm=22.0, frames_per_cycle=24)
    return Scenario("bend", paper_rig(width, height), pipe, motion, frames=frames)


def _other_rig(width: int, height: int, frames: int) -> Scenario:
    """Another rig and pipe: the contract's example mirror, an off-centre principal
    point, a 150 mm pipe, a 70 mm baseline and a dent: nothing tuned to the paper."""
    s = width / 1280.0
    rig = paper_rig(
        width,
        height,
        baseline_mm=70.0,
        principal_offset_px=(11.7 * s, -8.3 * s),
        mirror=Mirror(20.0, 30.0),
        rim_radius_mm=30.0,
    )
    pipe = Pipe(
        inner_diameter_mm=150.0,
        defects=[
            Defect(
                kind="dent",
                height_mm=2.5,
                width_mm=15.0,
                length_mm=40.0,
                axial_start_mm=170.0,
                angle_deg=130.0,
            )
        ],
    )
    motion = MotionConfig(start_mm=220.0, stroke_mm=18.0, frames_per_cycle=6, n_units=3)
    return Scenario("other-rig", rig, pipe, motion, frames=frames)


_BUILDERS = {
    # Full-size runs sample the gait finely (24 frames per cycle: 6 while the head
    # moves, 1.6-6 mm apart), as a video camera would; 300 mm of travel.
    "paper": (_paper, 1600, 1200, 300),
    "bend": (_bend, 1600, 1200, 330),
    "other-rig": (_other_rig, 1280, 1024, 90),
}
SCENARIOS = ("paper", "bend", "other-rig", "paper-small", "bend-small", "other-rig-small")


def make_scenario(
    name: str,
    *,
    frames: int | None = None,
    size: tuple[int, int] | None = None,
    seed: int = 0,
) -> Scenario:
    """Build a named scenario; ``frames`` and ``size`` override its defaults."""
    base = name.removesuffix("-small")
    if name not in SCENARIOS:
        raise ConfigError(
            "scenario", f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}"
        )
    builder, width, height, n = _BUILDERS[base]
    if name.endswith("-small"):
        width, height, n = 400, int(round(400 * height / width)), 24
    if size is not None:
        width, height = size
        if width < 64 or height < 48:
            raise ConfigError("size", f"must be at least 64x48, got {width}x{height}")
    if frames is not None:
        if frames < 1:
            raise ConfigError("frames", f"must be >= 1, got {frames}")
        n = frames
    scenario = builder(width, height, n)
    if name.endswith("-small"):
        # Short test runs sample the gait coarsely (8 frames per cycle) to travel further.
        scenario.motion = replace(scenario.motion, frames_per_cycle=8)
    scenario.name = name
    scenario.seed = seed
    return scenario

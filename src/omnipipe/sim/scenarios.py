"""Named simulation scenarios and the paper-like rig.

``paper`` reproduces the paper's experiment (Sec. VII, Table I); ``bend`` is a bent
pipe of another size with a dent and a bulge; ``other-rig`` has another mirror, an
off-centre principal point and a smaller pipe; ``random`` draws pipe, wall family,
gait, rig and defects from the seed (docs/simulator.md); ``*-small`` are the same
scenes 400 px wide with short runs, for tests.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.baseline import optimal_baseline
from omnipipe.errors import ConfigError
from omnipipe.rig import Mirror, Rig
from omnipipe.sim.features import Joint, Lateral, Ovality, PipeFeatures, Taper, Water
from omnipipe.sim.motion import MotionConfig
from omnipipe.sim.random_family import (
    BRICK_COLOURS,
    PLASTIC_COLOURS,
    RANDOM_MAX_FRAMES,
    RANDOM_TRAVEL_MM,
    SMOOTH_COLOURS,
    TILE_COLOURS,
    draw_defects,
    draw_random,
    log_uniform,
    make_random_scenario,
    ring_band,
)
from omnipipe.sim.render import RenderConfig
from omnipipe.sim.scenario import HYPER70_A_MM, HYPER70_B_MM, Scenario, paper_rig
from omnipipe.sim.scene import Centreline, Defect, Pipe
from omnipipe.sim.texture import TextureConfig


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
        "paper",
        paper_rig(width, height),
        pipe,
        MotionConfig(start_mm=200.0, frames_per_cycle=24),
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


def _continuous(width: int, height: int, frames: int) -> Scenario:
    """A robot that never stops: every frame moves (about 3.3 mm a frame), a straight
    160 mm pipe with one dent; the throughput case bend's rest frames hide."""
    pipe = Pipe(
        inner_diameter_mm=160.0,
        defects=[
            Defect(
                kind="dent",
                height_mm=3.0,
                width_mm=20.0,
                length_mm=30.0,
                axial_start_mm=200.0,
                angle_deg=120.0,
            )
        ],
    )
    motion = MotionConfig(
        start_mm=200.0, stroke_mm=20.0, frames_per_cycle=6, moving_frames=6, min_rest_frames=0
    )
    return Scenario("continuous", paper_rig(width, height), pipe, motion, frames=frames)


# Scenarios of real pipes (issue 30): built by make_feature_scenario.
FEATURE_SCENARIOS = (
    "sewer",
    "elbow",
    "reducer",
    "oval",
    "random-features",
    "sewer-small",
    "elbow-small",
    "reducer-small",
    "oval-small",
    "random-features-small",
)


_BUILDERS = {
    # Full-size runs sample the gait finely (24 frames per cycle: 6 while the head
    # moves, 1.6-6 mm apart), as a video camera would; 300 mm of travel.
    "paper": (_paper, 1600, 1200, 300),
    "bend": (_bend, 1600, 1200, 330),
    "other-rig": (_other_rig, 1280, 1024, 90),
    "continuous": (_continuous, 1600, 1200, 300),
}
# The -small runs (24 frames, 8 per gait cycle) sweep only 50-70 mm of wall: their
# defects (same kind, height, width and angle as the full-size scenario's) are moved and
# shortened to lie inside the stretch their laser ring measures, so that a short test run
# measures whole defects (centreline arc length, mm; the ring lies `baseline` behind the
# rig origin: paper 118-187, bend 98-161, other-rig 150-202).
_SMALL_DEFECTS: dict[str, tuple[tuple[float, float], ...]] = {
    "paper": ((130.0, 40.0),),
    "bend": ((108.0, 22.0), (135.0, 18.0)),
    "other-rig": ((162.0, 28.0),),
    "continuous": ((140.0, 30.0),),
}
SCENARIOS = (
    "paper",
    "bend",
    "other-rig",
    "continuous",
    "random",
    "paper-small",
    "bend-small",
    "other-rig-small",
    "continuous-small",
    "random-small",
    "random-wide",
    "brick-bend",
    "tiled-culvert",
    "random-wide-small",
    "brick-bend-small",
    "tiled-culvert-small",
    *FEATURE_SCENARIOS,
)


def make_scenario(
    name: str,
    *,
    frames: int | None = None,
    size: tuple[int, int] | None = None,
    seed: int = 0,
) -> Scenario:
    """Build a named scenario; ``frames`` and ``size`` override its defaults.

    ``random`` / ``random-small`` draw the scene from ``seed`` (the same scene for both;
    -small: 400x300, 24 frames); the other scenarios' scenes do not depend on ``seed``.
    """
    base = name.removesuffix("-small")
    if name in FEATURE_SCENARIOS:
        return make_feature_scenario(name, frames, size, seed)
    if name not in SCENARIOS:
        raise ConfigError(
            "scenario", f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}"
        )
    if base == "random":
        return make_random_scenario(name, frames, size, seed)
    if base in ("random-wide", *_NAMED_WIDE):
        return make_wide_scenario(name, frames, size, seed)
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
        if scenario.motion.moving_frames is None:
            scenario.motion = replace(scenario.motion, frames_per_cycle=8)
        moved = [
            replace(d, axial_start_mm=start, length_mm=length)
            for d, (start, length) in zip(scenario.pipe.defects, _SMALL_DEFECTS[base], strict=True)
        ]
        scenario.pipe = replace(scenario.pipe, defects=moved)
    scenario.name = name
    scenario.seed = seed
    return scenario


# -- the wide random family and the issue-32 walls (docs/simulator.md) ------------------
# Distributions of ``random-wide``: the walls real pipes have (periodic ones at many
# periods), pipes of 100-1000 mm, sensors of 640x480-2448x2048, mirrors b/a 1.2-1.6,
# laser planes at 0.5-1.0 x the wall distance, short and long strokes with 0-3 rest frames.
WIDE_FAMILIES = ("brick", "tiles", "mosaic", "corrugated", "joints", "photo", "steel", "smooth")
WIDE_FAMILY_WEIGHTS = (0.18, 0.14, 0.12, 0.12, 0.10, 0.14, 0.10, 0.10)
WIDE_PERIODIC = ("brick", "tiles", "mosaic", "corrugated", "joints")
WIDE_SENSORS = (
    (640, 480), (800, 600), (1024, 768), (1280, 960), (1280, 1024),
    (1600, 1200), (2048, 1536), (2448, 2048),
)  # fmt: skip
WIDE_MAX_STEP_MM = 20.0
_MOSAIC_COLOURS = ((0.78, 0.80, 0.82), (0.55, 0.66, 0.78), (0.70, 0.74, 0.62), (0.82, 0.76, 0.66))
_PHOTO_COLOURS = ((0.50, 0.48, 0.44), (0.46, 0.42, 0.36), (0.58, 0.57, 0.54), (0.40, 0.40, 0.42))


def _pick(rng: np.random.Generator, colours: tuple) -> tuple[float, float, float]:
    return tuple(float(v) for v in colours[int(rng.integers(len(colours)))])  # type: ignore[return-value]


def _draw_wide_texture(rng: np.random.Generator, diameter_mm: float) -> tuple[str, TextureConfig]:
    """(wide family, texture) of ``random-wide``: periodic walls at several periods."""
    family = str(rng.choice(WIDE_FAMILIES, p=WIDE_FAMILY_WEIGHTS))
    texel = 0.25 * max(1.0, diameter_mm / 202.0)
    stains = float(rng.uniform(0.15, 0.6)) if rng.uniform() < 0.3 else 0.0
    contrast = float(rng.uniform(0.4, 0.8)) if rng.uniform() < 0.15 else 1.0
    common = {"texel_mm": texel, "stain_strength": stains, "contrast": contrast}
    if family == "brick":
        cfg = TextureConfig(
            family="brick",
            period_mm=float(rng.uniform(60.0, 300.0)),
            course_mm=float(rng.uniform(30.0, 100.0)),
            joint_mm=float(rng.uniform(4.0, 15.0)),
            variant="along" if rng.uniform() < 0.7 else "around",
            base_rgb=_pick(rng, BRICK_COLOURS),
            **common,
        )
    elif family in ("tiles", "mosaic"):
        mosaic = family == "mosaic"
        cfg = TextureConfig(
            family="tiles",
            period_mm=log_uniform(rng, 10.0, 40.0) if mosaic else log_uniform(rng, 20.0, 200.0),
            joint_mm=float(rng.uniform(1.0, 3.0) if mosaic else rng.uniform(1.5, 6.0)),
            variant="mosaic" if mosaic else ("grid" if rng.uniform() < 0.7 else "offset"),
            base_rgb=_pick(rng, _MOSAIC_COLOURS if mosaic else TILE_COLOURS),
            **common,
        )
    elif family == "corrugated":
        cfg = TextureConfig(
            family="joints",
            period_mm=log_uniform(rng, 10.0, 150.0),
            joint_mm=5.0,
            variant="corrugated",
            **common,
        )
    elif family == "joints":
        variant = "concrete" if rng.uniform() < 0.6 else "plastic"
        cfg = TextureConfig(
            family="joints",
            period_mm=float(rng.uniform(50.0, 1000.0)),
            joint_mm=float(rng.uniform(3.0, 20.0)),
            variant=variant,
            base_rgb=_pick(rng, PLASTIC_COLOURS) if variant == "plastic" else None,
            **common,
        )
    elif family == "photo":
        cfg = TextureConfig(family="photo", base_rgb=_pick(rng, _PHOTO_COLOURS), **common)
    elif family == "steel":
        cfg = TextureConfig(
            rust_cover=float(rng.uniform(0.05, 0.7)),
            pit_density_per_cm2=float(rng.uniform(0.1, 1.0)),
            girth_weld_spacing_mm=float(rng.choice([0.0, rng.uniform(300.0, 1200.0)])),
            seam_angle_deg=float(rng.uniform(0, 360)) if rng.uniform() < 0.6 else None,
            **common,
        )
    else:
        cfg = TextureConfig(
            texel_mm=texel,
            family="smooth",
            variant=str(rng.choice(["pvc", "lined"])),
            base_rgb=_pick(rng, SMOOTH_COLOURS),
            contrast=float(rng.uniform(0.05, 0.3)),
            stain_strength=stains,
        )
    return family, cfg


def _draw_wide_gait(rng: np.random.Generator) -> MotionConfig:
    """Short and long strokes, 1-8 moving frames, 0-3 rest frames; wider disturbances."""
    stroke = log_uniform(rng, 3.0, 60.0)
    allowed = [m for m in range(1, 9) if stroke * math.sin(math.pi / (2 * m)) <= WIDE_MAX_STEP_MM]
    moving = int(rng.choice(allowed))
    rest = int(rng.integers(0, 4))
    return MotionConfig(
        n_units=int(rng.integers(2, 5)),
        stroke_mm=stroke,
        frames_per_cycle=moving + rest,
        moving_frames=moving,
        rest_jitter_frames=int(rng.integers(0, 2)) if rng.uniform() < 0.5 else 0,
        min_rest_frames=0,
        speed_jitter=float(rng.uniform(0.0, 0.2)),
        lateral_mm=float(rng.uniform(0.5, 5.0)),
        tilt_deg=float(rng.uniform(0.3, 2.0)),
        roll_drift_deg_per_m=float(rng.uniform(-20.0, 20.0)),
        roll_wobble_deg=float(rng.uniform(0.2, 1.5)),
    )


def _draw_wide_rig(
    rng: np.random.Generator, radius_mm: float
) -> tuple[tuple[int, int], Mirror, float, float, tuple[float, float], RenderConfig]:
    """Sensor size, mirror, rim, baseline (0.5-1.0 x the wall distance), principal-point
    offset (fraction of the height) and render settings; redrawn until the laser ring's
    image lies in the mirror's useful band on the drawn sensor (``ring_band``)."""
    w, h = WIDE_SENSORS[int(rng.integers(len(WIDE_SENSORS)))]
    render = RenderConfig(
        laser_power=2.5 * log_uniform(rng, 0.5, 2.0), body_radius_mm=0.61 * radius_mm
    )
    for _ in range(200):
        a = float(rng.uniform(15.0, 30.0))
        mirror = Mirror(a, a * float(rng.uniform(1.2, 1.6)))
        rim = float(rng.uniform(25.0, 40.0))
        off_r, off_a = 0.02 * math.sqrt(rng.uniform()), rng.uniform(0.0, 2.0 * math.pi)
        frac = (off_r * math.cos(off_a), off_r * math.sin(off_a))
        baseline = radius_mm * float(rng.uniform(0.5, 1.0))
        rig = paper_rig(w, h, baseline, render, (frac[0] * h, frac[1] * h), mirror, rim)
        r_ring, lo, hi = ring_band(rig, render, radius_mm)
        if lo <= r_ring <= hi:
            return (w, h), mirror, rim, baseline, frac, render
    raise ConfigError("seed", "no rig puts the laser ring inside the mirror's band")  # pragma: no cover


def _random_wide(size: tuple[int, int] | None, frames: int | None, seed: int) -> Scenario:
    """A ``random-wide`` run drawn from ``seed`` (docs/simulator.md, "The wide family")."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x57494445]))
    diameter = log_uniform(rng, 100.0, 1000.0)
    radius = 0.5 * diameter
    family, texture = _draw_wide_texture(rng, diameter)
    motion = _draw_wide_gait(rng)
    sensor, mirror, rim, baseline, frac, render = _draw_wide_rig(rng, radius)
    width, height = size or sensor
    rig = paper_rig(width, height, baseline, render, (frac[0] * height, frac[1] * height), mirror, rim)
    start = max(200.0, baseline + 100.0)
    motion = replace(motion, start_mm=start)
    fpc = motion.frames_per_cycle
    default_frames = min(RANDOM_MAX_FRAMES, 1 + math.ceil(RANDOM_TRAVEL_MM / motion.stroke_mm) * fpc)
    travel = motion.stroke_mm * (default_frames - 1) / fpc
    centreline, bend_info = Centreline(), None
    if rng.uniform() < 0.5:
        bend_r = diameter * float(rng.uniform(3.0, 15.0))
        enter = start + travel * float(rng.uniform(0.1, 0.4))
        leave = start + travel * float(rng.uniform(0.6, 0.95))
        angle = min(math.degrees((leave - enter) / bend_r), 90.0)
        direction = float(rng.uniform(0.0, 360.0))
        centreline = Centreline(enter, bend_r, angle, direction)
        bend_info = {"radius_mm": bend_r, "angle_deg": angle, "direction_deg": direction,
                     "start_sigma_mm": enter}  # fmt: skip
    defects = draw_defects(rng, start - baseline, start + travel - baseline, radius)
    pipe = Pipe(inner_diameter_mm=diameter, centreline=centreline, defects=defects)
    info = {
        "family": family,
        "texture_family": texture.family,
        "variant": texture.variant,
        "periodic": family in WIDE_PERIODIC,
        "axial_period_mm": texture.axial_period_mm,
        "inner_diameter_mm": diameter,
        "bent": bend_info is not None,
        "bend": bend_info,
        "gait": {
            "stroke_mm": motion.stroke_mm,
            "moving_frames": motion.moving_frames,
            "rest_frames": fpc - int(motion.moving_frames or 0),
            "rest_jitter_frames": motion.rest_jitter_frames,
        },
        "rig": {
            "sensor": list(sensor),
            "mirror_a_mm": mirror.a,
            "mirror_b_mm": mirror.b,
            "rim_radius_mm": rim,
            "principal_offset_frac": list(frac),
            "baseline_mm": baseline,
            "baseline_wall_ratio": baseline / radius,
            "laser_power": render.laser_power,
        },
        "defects": len(defects),
        "expected_travel_mm": travel,
    }
    n = default_frames if frames is None else frames
    return Scenario("random-wide", rig, pipe, motion, render, texture, n, seed, random=info)


def _brick_bend(width: int, height: int, frames: int) -> Scenario:
    """A 200 mm brick-lined pipe (running bond, bricks along the axis) turning on a 1.5 m
    radius: the issue-32 wall where a third of the steps were flagged."""
    pipe = Pipe(
        inner_diameter_mm=200.0,
        centreline=Centreline(
            straight_mm=260.0, bend_radius_mm=1500.0, bend_angle_deg=20.0, bend_direction_deg=120.0
        ),
    )
    texture = TextureConfig(
        family="brick", period_mm=215.0, course_mm=65.0, joint_mm=10.0, variant="along",
        base_rgb=BRICK_COLOURS[0],
    )  # fmt: skip
    motion = MotionConfig(
        start_mm=200.0, stroke_mm=20.0, frames_per_cycle=6, moving_frames=4, rest_jitter_frames=1
    )
    return Scenario("brick-bend", paper_rig(width, height), pipe, motion, texture=texture, frames=frames)


def _tiled_culvert(width: int, height: int, frames: int) -> Scenario:
    """A 600 mm culvert lined with glazed mosaic tiles 30 mm apart, all of one glaze (+-4 %
    per tile: the wall repeats every 30 mm along and around); 22 mm strokes over 5
    frames (2-7 mm between frames); another mirror on a 1280x1024 sensor; the laser plane
    235 mm behind the focus."""
    s = height / 1024.0
    render = RenderConfig(body_radius_mm=0.61 * 300.0)
    rig = paper_rig(
        width, height, baseline_mm=235.0, render=render, principal_offset_px=(6.0 * s, -4.0 * s),
        mirror=Mirror(24.0, 33.6), rim_radius_mm=32.0,
    )  # fmt: skip
    texture = TextureConfig(
        texel_mm=0.25 * 600.0 / 202.0, family="tiles", period_mm=30.0, joint_mm=2.5,
        variant="grid", base_rgb=_MOSAIC_COLOURS[0],
    )  # fmt: skip
    motion = MotionConfig(start_mm=335.0, stroke_mm=22.0, frames_per_cycle=6, moving_frames=5)
    pipe = Pipe(inner_diameter_mm=600.0)
    return Scenario("tiled-culvert", rig, pipe, motion, render, texture, frames=frames)


_NAMED_WIDE = {
    # (builder, width, height, default frames): about 400 mm of travel.
    "brick-bend": (_brick_bend, 1600, 1200, 121),
    "tiled-culvert": (_tiled_culvert, 1280, 1024, 109),
}


def make_wide_scenario(
    name: str, frames: int | None, size: tuple[int, int] | None, seed: int
) -> Scenario:
    """``random-wide[-small]`` from ``seed`` or the named ``brick-bend[-small]`` and
    ``tiled-culvert[-small]`` (-small: 400 px wide, 24 frames; ``size`` and ``frames``
    override; the scene never depends on them)."""
    small = name.endswith("-small")
    base = name.removesuffix("-small")
    if size is not None and (size[0] < 64 or size[1] < 48):
        raise ConfigError("size", f"must be at least 64x48, got {size[0]}x{size[1]}")
    if frames is not None and frames < 1:
        raise ConfigError("frames", f"must be >= 1, got {frames}")
    if frames is None and small:
        frames = 24
    if base == "random-wide":
        if seed < 0:
            raise ConfigError("seed", f"must be >= 0 for {name}, got {seed}")
        drawn = _random_wide(None, 1, seed).rig.camera
        if size is None and small:
            size = (400, int(round(400 * drawn.height / drawn.width)))
        scenario = _random_wide(size, frames, seed)
    else:
        builder, width, height, n = _NAMED_WIDE[base]
        if small:
            width, height = 400, int(round(400 * height / width))
        width, height = size or (width, height)
        scenario = builder(width, height, frames or n)
        scenario.seed = seed
    scenario.name = name
    return scenario


# -- real pipes: joints, laterals, elbows, reducers, ovality, water (docs/simulator.md) --
# Feature draws of random-features: their own stream, so `random` is unchanged.
_FEATURE_STREAM = 0x46454154
# A random-features lateral's diameter: U(a, b) x the pipe's (most of them in the issue's
# class, >= 0.2 D; a few under it).
LATERAL_DIAMETERS = (0.15, 0.4)
# The share of the expected travel the window relies on (the gait's speed and rest jitter).
_TRAVEL_SHARE = 0.85


def clock_to_angle_deg(clock_deg: float) -> float:
    """Pipe angle (deg, N towards B) of a clock position (0 = 12:00, clockwise looking
    downstream) in a pipe whose axis starts along world +z with gravity world -y:
    12:00 is B (+y, 90 deg), 3:00 is -N (-x, 180 deg), 10:00 is 30 deg."""
    return (90.0 + clock_deg) % 360.0


def _feature_rig(width: int, height: int, diameter_mm: float) -> tuple[Rig, RenderConfig]:
    """The paper's rangefinder with the Sec. IV optimal baseline for this pipe, and a robot
    body scaled to the pipe as in the random family (0.61 x the radius)."""
    render = RenderConfig(body_radius_mm=0.61 * 0.5 * diameter_mm)
    mirror = Mirror(HYPER70_A_MM, HYPER70_B_MM)
    baseline = round(optimal_baseline(0.5 * diameter_mm, mirror), 1)
    return paper_rig(width, height, baseline, render), render


def _sewer(width: int, height: int, frames: int, small: bool) -> Scenario:
    """300 mm sewer: 40 mm of standing water, three joints (an 8 mm open one,
    one whose next section is offset 5 mm towards 3:00), a 100 mm lateral at 10:00
    entering at 60 deg, and 4 % ovality (horizontal major axis) over 200 mm."""
    features = PipeFeatures(
        joints=(
            Joint(140.0, gap_mm=8.0, depth_mm=12.0),
            Joint(
                290.0,
                gap_mm=3.0,
                depth_mm=8.0,
                offset_mm=5.0,
                offset_angle_deg=clock_to_angle_deg(90.0),
            ),
            Joint(380.0, gap_mm=4.0, depth_mm=8.0),
        ),
        laterals=(Lateral(210.0, clock_to_angle_deg(300.0), 100.0, branch_angle_deg=60.0),),
        ovalities=(Ovality(230.0, 430.0, 4.0, angle_deg=0.0, blend_mm=40.0),),
        water=Water(40.0),
    )
    pipe = Pipe(inner_diameter_mm=300.0, features=features)
    rig, render = _feature_rig(width, height, 300.0)
    # Corroded cast-iron-like wall with deposits: the aggregate of the `joints`
    # family's concrete is too faint at 400x300 for the pipeline to register the small
    # run (14 of 24 frames); no girth welds or seam, whose albedo rings and line could
    # pass for joints.
    texture = TextureConfig(
        texel_mm=0.25 * 300.0 / 202.0,
        girth_weld_spacing_mm=0.0,
        seam_angle_deg=None,
        stain_strength=0.3,
    )
    motion = MotionConfig(start_mm=240.0, stroke_mm=40.0 if small else 24.0, frames_per_cycle=8)
    return Scenario("sewer", rig, pipe, motion, render, texture, frames=frames)


def _elbow(width: int, height: int, frames: int, small: bool) -> Scenario:
    """200 mm pipe with a tight 90 deg elbow: bend radius 1.5 D (300 mm), straight again
    after it; the full run crosses the whole elbow, the small one its entry."""
    pipe = Pipe(
        inner_diameter_mm=200.0,
        centreline=Centreline(
            straight_mm=260.0, bend_radius_mm=300.0, bend_angle_deg=90.0, bend_direction_deg=0.0
        ),
    )
    rig, render = _feature_rig(width, height, 200.0)
    motion = MotionConfig(
        start_mm=330.0 if small else 200.0, stroke_mm=40.0 if small else 24.0, frames_per_cycle=8
    )
    return Scenario("elbow", rig, pipe, motion, render, frames=frames)


def _reducer(width: int, height: int, frames: int, small: bool) -> Scenario:
    """Concentric reducer from 250 to 180 mm over 150 mm; the robot crawls into the small end."""
    pipe = Pipe(
        inner_diameter_mm=250.0,
        features=PipeFeatures(tapers=(Taper(220.0, 370.0, 180.0),)),
    )
    rig, render = _feature_rig(width, height, 215.0)
    render = replace(render, body_radius_mm=0.61 * 90.0)  # fits the small end
    rig = paper_rig(width, height, rig.laser.distance_mm, render)
    motion = MotionConfig(
        start_mm=280.0 if small else 200.0, stroke_mm=40.0 if small else 24.0, frames_per_cycle=8
    )
    return Scenario("reducer", rig, pipe, motion, render, frames=frames)


def _oval(width: int, height: int, frames: int, small: bool) -> Scenario:
    """250 mm pipe, 6 % ovality along its whole length (major axis at 30 deg), and a 2 mm
    bulge 60 mm long."""
    bulge = Defect("bulge", 2.0, 30.0, 60.0, axial_start_mm=170.0, angle_deg=100.0)
    pipe = Pipe(inner_diameter_mm=250.0, defects=[bulge], ovality=0.06, ovality_angle_deg=30.0)
    rig, render = _feature_rig(width, height, 250.0)
    motion = MotionConfig(start_mm=200.0, stroke_mm=40.0 if small else 24.0, frames_per_cycle=8)
    return Scenario("oval", rig, pipe, motion, render, frames=frames)


# name: (builder, width, height, default frames at full size)
_FEATURE_BUILDERS = {
    "sewer": (_sewer, 1600, 1200, 1 + 13 * 8),
    "elbow": (_elbow, 1600, 1200, 1 + 30 * 8),
    "reducer": (_reducer, 1600, 1200, 1 + 13 * 8),
    "oval": (_oval, 1600, 1200, 1 + 13 * 8),
}


def make_feature_scenario(
    name: str, frames: int | None, size: tuple[int, int] | None, seed: int
) -> Scenario:
    """A scenario of :data:`FEATURE_SCENARIOS` (-small: 400x300, 24 frames, longer strokes)."""
    small = name.endswith("-small")
    base = name.removesuffix("-small")
    if base == "random-features":
        width, height = (400, 300) if small else (1600, 1200)
    else:
        builder, width, height, n_default = _FEATURE_BUILDERS[base]
        if small:
            width, height = 400, int(round(400 * height / width))
    if size is not None:
        width, height = size
        if width < 64 or height < 48:
            raise ConfigError("size", f"must be at least 64x48, got {width}x{height}")
    if frames is not None and frames < 1:
        raise ConfigError("frames", f"must be >= 1, got {frames}")
    if base == "random-features":
        if seed < 0:
            raise ConfigError("seed", f"must be >= 0 for {name}, got {seed}")
        scenario = _random_features(width, height, frames, seed, small)
    else:
        if frames is None and small:
            frames = 24
        scenario = builder(width, height, n_default if frames is None else frames, small)
        scenario.seed = seed
    scenario.name = name
    return scenario


def _place(
    rng: np.random.Generator, lo: float, hi: float, half: float, taken: list[tuple[float, float]]
) -> float | None:
    """A centre in [lo + half, hi - half] whose extent +-half keeps 15 mm from ``taken``."""
    for _ in range(30):
        if hi - lo < 2.0 * half:
            return None
        c = float(rng.uniform(lo + half, hi - half))
        if all(c + half + 15.0 < a or c - half - 15.0 > b for a, b in taken):
            taken.append((c - half, c + half))
            return c
    return None


def _draw_features(
    rng: np.random.Generator, lo: float, hi: float, diameter: float
) -> tuple[PipeFeatures, dict]:
    """Joints, ovality, a taper and water inside [lo, hi] (arc length, mm); a lateral
    beyond ``hi`` (its hole 15-35 mm past it: the run sweeping it is lengthened)."""
    kinds = ("joints", "lateral", "ovality", "taper", "water")
    on = {k: bool(rng.uniform() < p) for k, p in zip(kinds, (0.6, 0.5, 0.5, 0.3, 0.4), strict=True)}
    if not any(on.values()):
        on[kinds[int(rng.integers(len(kinds)))]] = True
    taken: list[tuple[float, float]] = []
    water = Water(diameter * float(rng.uniform(0.05, 0.2))) if on["water"] else None
    laterals: tuple[Lateral, ...] = ()
    if on["lateral"]:
        beta = float(rng.uniform(45.0, 135.0))
        d_b = diameter * float(rng.uniform(*LATERAL_DIAMETERS))
        clock = float(rng.uniform(-100.0, 100.0)) if water else float(rng.uniform(0.0, 360.0))
        # Beyond the window, 15 mm clear of the others (the run is lengthened to sweep it).
        half = 0.5 * d_b / math.sin(math.radians(beta))
        c = hi + 15.0 + half + float(rng.uniform(0.0, 20.0))
        laterals = (Lateral(c, clock_to_angle_deg(clock), d_b, branch_angle_deg=beta),)
    joints = []
    for _ in range(int(rng.integers(1, 4)) if on["joints"] else 0):
        gap = float(rng.uniform(2.0, 15.0))
        c = _place(rng, lo, hi, 0.5 * gap + 1.0, taken)
        offset = float(rng.uniform(1.0, 8.0)) if rng.uniform() < 0.5 else 0.0
        if c is not None:
            joints.append(
                Joint(c, gap, float(rng.uniform(3.0, 15.0)), offset, float(rng.uniform(0.0, 360.0)))
            )
    ovalities: tuple[Ovality, ...] = ()
    if on["ovality"]:
        length = (hi - lo) * float(rng.uniform(0.4, 0.9))
        start = float(rng.uniform(lo, hi - length))
        ovalities = (
            Ovality(
                start,
                start + length,
                float(rng.uniform(1.0, 8.0)),
                float(rng.uniform(0.0, 180.0)),
                length * float(rng.uniform(0.1, 0.3)),
            ),
        )
    tapers: tuple[Taper, ...] = ()
    if on["taper"]:
        length = (hi - lo) * float(rng.uniform(0.3, 0.8))
        start = float(rng.uniform(lo, hi - length))
        tapers = (Taper(start, start + length, diameter * float(rng.uniform(0.8, 0.95))),)
    features = PipeFeatures(
        tuple(sorted(joints, key=lambda j: j.axial_mm)), laterals, tapers, ovalities, water
    )
    info = {
        "kinds": [k for k in kinds if on[k]],
        "joints": len(joints),
        "laterals": len(laterals),
        "window_mm": [lo, hi],
    }
    return features, info


def _random_features(
    width: int, height: int, frames: int | None, seed: int, small: bool
) -> Scenario:
    """The `random` scene of ``seed`` (wall, gait, rig) with features of real pipes drawn
    from their own stream, inside what the short (24-frame) run's laser ring sweeps: from
    its first station (start - baseline) over 0.85 of the expected 23 frames of travel
    (the gait's jitter), 3 mm in from either end (docs/simulator.md). A lateral lies beyond
    that window, and the run (``frames`` None: 24 frames for ``small``, else the random
    family's) is lengthened until its ring sweeps the whole hole likewise. The camera sees
    further ahead, but only the ring measures: a feature beyond the sweep is not measured."""
    sc = draw_random(width, height, frames if frames is not None or not small else 24, seed)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _FEATURE_STREAM]))
    diameter = sc.pipe.inner_diameter_mm
    m = sc.motion
    short_travel = m.stroke_mm * 23.0 / m.frames_per_cycle
    lo = m.start_mm - sc.rig.laser.distance_mm + 3.0
    hi = lo + max(_TRAVEL_SHARE * short_travel - 6.0, 1.0)
    features, info = _draw_features(rng, lo, hi, diameter)
    if frames is None and features.laterals:
        v = features.laterals[0]
        end = v.axial_mm + 0.5 * v.diameter_mm / math.sin(math.radians(v.branch_angle_deg))
        need = 1 + math.ceil(23.0 * (end + 3.0 - (lo - 3.0)) / (_TRAVEL_SHARE * short_travel))
        sc.frames = max(sc.frames, need)
        info["frames"] = sc.frames
    centreline = sc.pipe.centreline
    if rng.uniform() < 0.3:  # a tight elbow starting inside the window
        radius = diameter * float(rng.uniform(1.5, 3.0))
        centreline = Centreline(
            float(rng.uniform(lo, hi)),
            radius,
            float(rng.uniform(30.0, 90.0)),
            float(rng.uniform(0.0, 360.0)),
        )
        info["elbow"] = True
    if features.water is not None and centreline.has_bend:
        # Water stays level only where the pipe does: bends turn sideways (0 or 180 deg).
        centreline = replace(centreline, bend_direction_deg=180.0 * float(rng.integers(0, 2)))
    keep = [d for d in sc.pipe.defects if not _touches(d, features)]
    sc.pipe = Pipe(diameter, centreline, keep, features=features)
    sc.render = replace(
        sc.render,
        exposure=0.9 * log_uniform(rng, 0.6, 1.5),
        vignetting=float(rng.uniform(0.1, 0.4)),
    )
    info["exposure"] = sc.render.exposure
    info["vignetting"] = sc.render.vignetting
    info["defects_kept"] = len(keep)
    sc.random = {**(sc.random or {}), "features": info}
    return sc


def _touches(d: Defect, features: PipeFeatures) -> bool:
    """True if a defect's axial extent comes within 10 mm of a joint or a lateral's hole."""
    a = d.axial_centre_mm - 0.5 * (d.length_mm + d.ramp_length_mm) - 10.0
    b = d.axial_centre_mm + 0.5 * (d.length_mm + d.ramp_length_mm) + 10.0
    spots = [(j.axial_mm, 0.5 * j.gap_mm) for j in features.joints]
    spots += [
        (v.axial_mm, 0.5 * v.diameter_mm / math.sin(math.radians(v.branch_angle_deg)))
        for v in features.laterals
    ]
    return any(c + h > a and c - h < b for c, h in spots)

"""The ``random-wide`` family and the issue-32 walls (docs/simulator.md, "The wide
family"): walls at many periods, pipes of 100-1000 mm, sensors of 640x480-2448x2048, and the
named ``brick-bend`` and ``tiled-culvert`` runs (:func:`make_wide_scenario`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.errors import ConfigError
from omnipipe.rig import Mirror
from omnipipe.sim.motion import MotionConfig
from omnipipe.sim.random_family import (
    BRICK_COLOURS,
    PLASTIC_COLOURS,
    RANDOM_MAX_FRAMES,
    RANDOM_TRAVEL_MM,
    SMOOTH_COLOURS,
    TILE_COLOURS,
    draw_defects,
    log_uniform,
    ring_band,
)
from omnipipe.sim.render import RenderConfig
from omnipipe.sim.scenario import Scenario, check_size_frames, paper_rig
from omnipipe.sim.scene import Centreline, Pipe
from omnipipe.sim.texture import TextureConfig

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


NAMED_WIDE = {
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
    check_size_frames(size, frames)
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
        builder, width, height, n = NAMED_WIDE[base]
        if small:
            width, height = 400, int(round(400 * height / width))
        width, height = size or (width, height)
        scenario = builder(width, height, frames or n)
        scenario.seed = seed
    scenario.name = name
    return scenario

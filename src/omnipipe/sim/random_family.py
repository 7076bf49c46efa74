"""The ``random`` family (docs/simulator.md): pipe, wall family, gait, rig and defects
drawn from the seed (:func:`draw_random`), its distributions' constants, and the draws the
wide and feature families share (:func:`log_uniform`, :func:`ring_band`,
:func:`draw_defects`, the wall colours).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.baseline import optimal_baseline
from omnipipe.camera import OmniCamera
from omnipipe.errors import ConfigError
from omnipipe.rig import Mirror, Rig
from omnipipe.sim.motion import MotionConfig
from omnipipe.sim.render import RenderConfig
from omnipipe.sim.scenario import Scenario, check_size_frames, paper_rig
from omnipipe.sim.scene import Centreline, Defect, Pipe
from omnipipe.sim.texture import TextureConfig

# -- randomised scenarios (docs/simulator.md) -------------------------------------------
# Distributions of the random family; docs/simulator.md has them as a table.
RANDOM_FAMILIES = ("steel", "brick", "tiles", "joints", "smooth")
RANDOM_FAMILY_WEIGHTS = (0.2, 0.25, 0.2, 0.2, 0.15)
PERIODIC_FAMILIES = ("brick", "tiles", "joints")
RANDOM_TRAVEL_MM = 300.0
RANDOM_MAX_FRAMES = 600
RANDOM_MAX_STEP_MM = 20.0
BRICK_COLOURS = ((0.55, 0.27, 0.18), (0.46, 0.30, 0.21), (0.62, 0.50, 0.34), (0.45, 0.44, 0.42))
TILE_COLOURS = ((0.80, 0.78, 0.72), (0.72, 0.70, 0.60), (0.55, 0.68, 0.60), (0.60, 0.66, 0.74))
PLASTIC_COLOURS = ((0.72, 0.45, 0.22), (0.55, 0.55, 0.55), (0.40, 0.55, 0.40))
SMOOTH_COLOURS = ((0.60, 0.58, 0.55), (0.70, 0.70, 0.66), (0.52, 0.56, 0.62), (0.70, 0.48, 0.30))


def log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    """One draw, uniform in log between ``lo`` and ``hi`` (both > 0, same unit)."""
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _draw_texture(rng: np.random.Generator, diameter_mm: float) -> TextureConfig:
    """Wall appearance: a family and its parameters (texel scaled with the pipe size)."""
    family = str(rng.choice(RANDOM_FAMILIES, p=RANDOM_FAMILY_WEIGHTS))
    # Pixel footprints grow with the wall distance: coarser texels in larger pipes.
    texel = 0.25 * max(1.0, diameter_mm / 202.0)
    stains = float(rng.uniform(0.15, 0.6)) if rng.uniform() < 0.4 else 0.0
    contrast = float(rng.uniform(0.35, 0.7)) if rng.uniform() < 0.15 else 1.0

    def pick(colours: tuple) -> tuple[float, float, float]:
        return tuple(float(v) for v in colours[int(rng.integers(len(colours)))])  # type: ignore[return-value]

    if family == "steel":
        return TextureConfig(
            texel_mm=texel,
            rust_cover=float(rng.uniform(0.05, 0.6)),
            pit_density_per_cm2=float(rng.uniform(0.1, 1.0)),
            girth_weld_spacing_mm=float(rng.choice([0.0, rng.uniform(300.0, 1200.0)])),
            seam_angle_deg=float(rng.uniform(0, 360)) if rng.uniform() < 0.6 else None,
            stain_strength=stains,
            contrast=contrast,
        )
    if family == "brick":
        return TextureConfig(
            texel_mm=texel,
            family="brick",
            period_mm=float(rng.uniform(60.0, 250.0)),
            course_mm=float(rng.uniform(30.0, 80.0)),
            joint_mm=float(rng.uniform(5.0, 14.0)),
            variant="along" if rng.uniform() < 0.7 else "around",
            base_rgb=pick(BRICK_COLOURS),
            stain_strength=stains,
            contrast=contrast,
        )
    if family == "tiles":
        return TextureConfig(
            texel_mm=texel,
            family="tiles",
            period_mm=float(rng.uniform(20.0, 150.0)),
            joint_mm=float(rng.uniform(1.5, 5.0)),
            variant="grid" if rng.uniform() < 0.7 else "offset",
            base_rgb=pick(TILE_COLOURS),
            stain_strength=stains,
            contrast=contrast,
        )
    if family == "joints":
        variant = str(rng.choice(["concrete", "plastic", "corrugated"]))
        if variant == "corrugated":
            period, colour = float(rng.uniform(10.0, 70.0)), None  # HDPE/culvert pitch
        else:
            period = float(rng.uniform(50.0, 500.0))
            colour = pick(PLASTIC_COLOURS) if variant == "plastic" else None
        return TextureConfig(
            texel_mm=texel,
            family="joints",
            period_mm=period,
            joint_mm=float(rng.uniform(3.0, 15.0)),
            variant=variant,
            base_rgb=colour,
            stain_strength=stains,
            contrast=contrast,
        )
    return TextureConfig(
        texel_mm=texel,
        family="smooth",
        variant=str(rng.choice(["pvc", "lined"])),
        base_rgb=pick(SMOOTH_COLOURS),
        contrast=float(rng.uniform(0.05, 0.3)),
        stain_strength=stains,
    )


def _draw_gait(rng: np.random.Generator) -> MotionConfig:
    """Stroke, moving frames per stroke, rest per stop, units; disturbances as default."""
    stroke = float(rng.uniform(5.0, 40.0))
    # Peak frame-to-frame step of the smooth profile with m moving frames (m=1: the stroke).
    peak = {
        m: stroke * max(np.diff(0.5 * (1 - np.cos(np.pi * np.arange(m + 1) / m))))
        for m in range(1, 7)
    }
    allowed = [m for m in range(1, 7) if peak[m] <= RANDOM_MAX_STEP_MM]
    moving = int(rng.choice(allowed))
    rest = int(rng.integers(1, 9))
    jitter = int(rng.integers(0, 3)) if rng.uniform() < 0.5 else 0
    return MotionConfig(
        n_units=int(rng.integers(2, 5)),
        stroke_mm=stroke,
        frames_per_cycle=moving + rest,
        moving_frames=moving,
        rest_jitter_frames=jitter,
        speed_jitter=float(rng.uniform(0.0, 0.2)),
    )


def ring_band(rig: Rig, render: RenderConfig, radius_mm: float) -> tuple[float, float, float]:
    """(ring image radius, lowest, highest allowed) px of the laser ring on a wall at
    ``radius_mm``: inside the band between the body silhouette and the rim, with margins."""
    cam = OmniCamera(rig.camera, rig.mirror)
    px, valid = cam.project(np.array([[radius_mm, 0.0, -rig.laser.distance_mm]]))
    r_ring = float(np.hypot(px[0, 0] - cam.cx, px[0, 1] - cam.cy)) if valid[0] else -1.0
    r_lo = float(rig.camera.radius_min or 0.0)
    r_hi = float(rig.camera.radius_max or 0.0)
    span = r_hi - r_lo
    return r_ring, r_lo + 0.08 * span, r_hi - 0.1 * span


def _draw_rig(
    rng: np.random.Generator, width: int, height: int, radius_mm: float
) -> tuple[Rig, RenderConfig, dict]:
    """Mirror, rim, principal point, laser baseline and power; the robot body scaled to the
    pipe. The baseline is drawn around Sec. IV's optimum until the ring lies in the band."""
    render = RenderConfig(
        laser_power=2.5 * log_uniform(rng, 0.5, 2.0),
        body_radius_mm=0.61 * radius_mm,
    )
    for _ in range(50):
        a = float(rng.uniform(15.0, 30.0))
        b = a * float(rng.uniform(1.2, 1.8))
        rim = float(rng.uniform(25.0, 40.0))
        off_r = 0.02 * math.sqrt(rng.uniform())  # fraction of the image height
        off_a = rng.uniform(0.0, 2.0 * math.pi)
        frac = (off_r * math.cos(off_a), off_r * math.sin(off_a))
        mirror = Mirror(a, b)
        l_opt = optimal_baseline(radius_mm, mirror)
        for _ in range(10):
            baseline = l_opt * log_uniform(rng, 0.8, 1.25)
            # Checked on the reference 1600x1200 image, so the draws do not depend on size.
            ref_offset = (frac[0] * 1200.0, frac[1] * 1200.0)
            ref = paper_rig(1600, 1200, baseline, render, ref_offset, mirror, rim)
            r_ring, lo, hi = ring_band(ref, render, radius_mm)
            if lo <= r_ring <= hi:
                offset = (frac[0] * height, frac[1] * height)
                rig = paper_rig(width, height, baseline, render, offset, mirror, rim)
                info = {
                    "mirror_a_mm": a,
                    "mirror_b_mm": b,
                    "rim_radius_mm": rim,
                    "principal_offset_frac": list(frac),
                    "baseline_mm": baseline,
                    "baseline_optimal_mm": l_opt,
                    "laser_power": render.laser_power,
                    "laser_power_rel": render.laser_power / RenderConfig().laser_power,
                    "body_radius_mm": render.body_radius_mm,
                    "ring_radius_frac": r_ring / ref.camera.radius_max,
                }
                return rig, render, info
    raise ConfigError(
        "seed", "no rig puts the laser ring inside the mirror's band"
    )  # pragma: no cover


def draw_defects(
    rng: np.random.Generator, lo_mm: float, hi_mm: float, radius_mm: float
) -> list[Defect]:
    """0-3 bulges/dents fully inside [lo, hi] (centreline arc length), not overlapping."""
    defects: list[Defect] = []
    n = int(rng.integers(0, 4))
    for _ in range(n):
        for _ in range(30):
            length = float(rng.uniform(10.0, 150.0))
            if hi_mm - lo_mm < length + 10.0:
                break
            d = Defect(
                kind=str(rng.choice(["bulge", "dent"])),
                height_mm=float(rng.uniform(0.5, 8.0)),
                width_mm=float(rng.uniform(3.0, 40.0)),
                length_mm=length,
                axial_start_mm=float(rng.uniform(lo_mm + 5.0, hi_mm - 5.0 - length)),
                angle_deg=float(rng.uniform(0.0, 360.0)),
            )
            if not any(_defects_overlap(d, e, radius_mm) for e in defects):
                defects.append(d)
                break
    return defects


def _defects_overlap(d: Defect, e: Defect, radius_mm: float, margin_mm: float = 10.0) -> bool:
    """True if the full extents (ramps included) of two defects come within ``margin_mm``."""
    half_d = 0.5 * (d.length_mm + d.ramp_length_mm)
    half_e = 0.5 * (e.length_mm + e.ramp_length_mm)
    axial = abs(d.axial_centre_mm - e.axial_centre_mm) < half_d + half_e + margin_mm
    dth = abs((d.angle_deg - e.angle_deg + 180.0) % 360.0 - 180.0)
    arc = math.radians(dth) * radius_mm
    circ = arc < 0.5 * (d.width_mm + d.ramp_width_mm + e.width_mm + e.ramp_width_mm) + margin_mm
    return axial and circ


def draw_random(width: int, height: int, frames: int | None, seed: int) -> Scenario:
    """A random pipe, wall, gait, rig and defects drawn from ``seed`` (docs/simulator.md)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x52414E44]))
    diameter = float(rng.uniform(100.0, 600.0))
    radius = 0.5 * diameter
    texture = _draw_texture(rng, diameter)
    motion = _draw_gait(rng)
    rig, render, rig_info = _draw_rig(rng, width, height, radius)
    baseline = rig.laser.distance_mm
    start = max(200.0, baseline + 100.0)
    motion = replace(motion, start_mm=start)
    fpc_mean = motion.frames_per_cycle + 0.0
    n_cycles = math.ceil(RANDOM_TRAVEL_MM / motion.stroke_mm)
    default_frames = min(RANDOM_MAX_FRAMES, 1 + int(n_cycles * fpc_mean))
    travel = motion.stroke_mm * (default_frames - 1) / fpc_mean  # expected, at the default
    bent = bool(rng.uniform() < 0.5)
    bend_info: dict | None = None
    centreline = Centreline()
    bend_r = diameter * float(rng.uniform(3.0, 15.0))
    direction = float(rng.uniform(0.0, 360.0))
    enter = start + travel * float(rng.uniform(0.1, 0.4))
    leave = start + travel * float(rng.uniform(0.6, 0.95))
    if bent:
        angle = min(math.degrees((leave - enter) / bend_r), 90.0)
        centreline = Centreline(
            straight_mm=enter,
            bend_radius_mm=bend_r,
            bend_angle_deg=angle,
            bend_direction_deg=direction,
        )
        bend_info = {
            "radius_mm": bend_r,
            "radius_diameters": bend_r / diameter,
            "angle_deg": angle,
            "direction_deg": direction,
            "start_sigma_mm": enter,
        }
    # Defects inside what the laser ring sweeps (it lies `baseline` behind the rig origin).
    defects = draw_defects(rng, start - baseline, start + travel - baseline, radius)
    pipe = Pipe(inner_diameter_mm=diameter, centreline=centreline, defects=defects)
    n = default_frames if frames is None else frames
    family = texture.family
    info = {
        "family": family,
        "variant": texture.variant,
        "periodic": family in PERIODIC_FAMILIES,
        "axial_period_mm": texture.axial_period_mm,
        "stains": texture.stain_strength,
        "contrast": texture.contrast,
        "inner_diameter_mm": diameter,
        "bent": bent,
        "bend": bend_info,
        "gait": {
            "stroke_mm": motion.stroke_mm,
            "moving_frames": motion.moving_frames,
            "rest_frames": motion.frames_per_cycle - int(motion.moving_frames or 0),
            "rest_jitter_frames": motion.rest_jitter_frames,
            "n_units": motion.n_units,
            "speed_jitter": motion.speed_jitter,
        },
        "rig": rig_info,
        "defects": len(defects),
        "expected_travel_mm": travel,
    }
    return Scenario("random", rig, pipe, motion, render, texture, frames=n, seed=seed, random=info)


def make_random_scenario(
    name: str, frames: int | None, size: tuple[int, int] | None, seed: int
) -> Scenario:
    width, height = (400, 300) if name.endswith("-small") else (1600, 1200)
    check_size_frames(size, frames)
    if size is not None:
        width, height = size
    if seed < 0:
        raise ConfigError("seed", f"must be >= 0 for {name}, got {seed}")
    if frames is None and name.endswith("-small"):
        frames = 24
    scenario = draw_random(width, height, frames, seed)
    scenario.name = name
    return scenario

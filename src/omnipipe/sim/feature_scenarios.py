"""Scenarios of real pipes (issue 30, docs/simulator.md): ``sewer``, ``elbow``,
``reducer``, ``oval`` and ``random-features`` (joints, laterals, tapers, ovality and water
drawn on the ``random`` scene from their own stream), built by
:func:`make_feature_scenario`; :func:`clock_to_angle_deg` turns clock positions into pipe
angles.
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
from omnipipe.sim.random_family import draw_random, log_uniform
from omnipipe.sim.render import RenderConfig
from omnipipe.sim.scenario import HYPER70_A_MM, HYPER70_B_MM, Scenario, check_size_frames, paper_rig
from omnipipe.sim.scene import Centreline, Defect, Pipe
from omnipipe.sim.texture import TextureConfig

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
    check_size_frames(size, frames)
    if size is not None:
        width, height = size
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

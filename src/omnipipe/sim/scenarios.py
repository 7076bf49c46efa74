"""Named simulation scenarios: the registry (:data:`SCENARIOS`, :func:`make_scenario`).

``paper`` reproduces the paper's experiment (Sec. VII, Table I); ``bend`` is a bent
pipe of another size with a dent and a bulge; ``other-rig`` has another mirror, an
off-centre principal point and a smaller pipe; ``random`` draws pipe, wall family,
gait, rig and defects from the seed (docs/simulator.md); ``*-small`` are the same
scenes 400 px wide with short runs, for tests.

The named scenes are built here; the run record and the paper rig are in
:mod:`.scenario`, the random family in :mod:`.random_family`, the wide family and the
issue-32 walls in :mod:`.wide_family`, the real pipes' features in :mod:`.feature_scenarios`.
"""

from __future__ import annotations

from dataclasses import replace

from omnipipe.errors import ConfigError
from omnipipe.rig import Mirror
from omnipipe.sim.feature_scenarios import FEATURE_SCENARIOS, make_feature_scenario
from omnipipe.sim.motion import MotionConfig
from omnipipe.sim.random_family import make_random_scenario
from omnipipe.sim.scenario import Scenario, check_size_frames, paper_rig
from omnipipe.sim.scene import Centreline, Defect, Pipe
from omnipipe.sim.wide_family import NAMED_WIDE, make_wide_scenario


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
    if base in ("random-wide", *NAMED_WIDE):
        return make_wide_scenario(name, frames, size, seed)
    builder, width, height, n = _BUILDERS[base]
    if name.endswith("-small"):
        width, height, n = 400, int(round(400 * height / width)), 24
    check_size_frames(size, frames)
    if size is not None:
        width, height = size
    if frames is not None:
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

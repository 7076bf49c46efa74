"""Creeping runs: the frames between two keyframes placed by the wall's own shift.

On a near-plain wall a robot that creeps (well under a pixel of image motion a frame)
never lifts the stationary test's ratio over its threshold, and the ratio's bound on
a hidden step (:func:`omnipipe.sfm.stations.hidden_steps`) is millimetres: every step
of such a run was flagged (random-wide seeds 3 and 24, "joints" walls, 0.2-2.4 mm
frame steps), and the frames between keyframes were a staircase (the creeps of the
frames taken for standing landing in the next moving frame's step). The wall itself
still moves past the rig: its unrolled, band-passed image
(:func:`omnipipe.sfm.wall_shift.wall_shift`) sees a joint ring and faint tone shift by
a tenth of a millimetre.

A stretch the stationary test cannot verify runs from keyframe a to keyframe b
(:func:`omnipipe.sfm.stations.unverified_stations`). Each frame step i-1 -> i of it
is read off the wall (axial shift d_i, mm: two frames a creep apart, the reading's
precision a few hundredths of a millimetre) and the frames are placed along the
keyframes' travel T at ``g * (d_1 + ... + d_i)``, g = T / (d_1 + ... + d_n): the
adjusted keyframe step is the ruler, so a reading's gain (a rig-fixed shading pulls a
faint wall's shift towards zero: seed 3 read 10-12 % short) cancels, and the frame
steps sum to the keyframe step. The stretch is placed only when every step is read
(no ambiguity, sectors and halves agree: ``wall_shift``'s tests) and its gain g lies
within :data:`MAX_GAIN_LOG` of 1, within :data:`MAX_GAIN_SPREAD_LOG` of the run's
median and within :data:`GAIN_SIGMAS` of the ruler's and the readings' sigmas (where
the wall and the keyframe step disagree beyond them, one of them is wrong); else it
stays as it was, flagged. The gain test is also the closure test: a
reading biased by a constant b (random-wide seed 10, a smooth wall with axial streaks:
-0.4 to -0.9 mm on every pair, standing frames included) moves the sum by n b, and
the gain with it (a bias within the tests is at most a fifth of the mean step).

The run's last stretch, without a keyframe after it, takes the run's median gain with
its spread (at least :data:`MIN_RULERS` stretches with a ruler). A placed stretch is
verified when every frame step's bound (:data:`~omnipipe.sfm.stations.FLOW_SIGMAS`
times its sigma) stays within :data:`~omnipipe.sfm.stations.HIDDEN_STEP_MM`. A frame
within :data:`REST_SIGMAS` of its station's first frame stays a stationary frame of
that station (its measured position kept: the noise of a reading, not a creep lost).

Conventions: rig frames as everywhere (z along the rig axis), world = rig of frame 0,
mm.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.inputs.sensors import odometry_at
from omnipipe.sfm.robot_sensors import odometry_noise, stated_error_model
from omnipipe.sfm.scale_check import StepCheck, UnreliableStretch, WallCylinder
from omnipipe.sfm.stations import FLOW_SIGMAS, HIDDEN_STEP_MM, flow_fraction
from omnipipe.sfm.types import SfmInputs, SfmResult
from omnipipe.sfm.wall_shift import WallShift, wall_shift

# A frame-to-frame reading's 1-sigma floor as a fraction of the unrolled wall's grid
# step (keyframe steps: wall_shift.GRID_SIGMA_FLOOR, 0.25): frames a creep apart show
# the same texture a sub-pixel shift apart, read to a few hundredths of a grid step.
CREEP_GRID_FLOOR = 0.1
# Shortest keyframe travel a -> b (mm, along rig a's axis) used as a ruler.
MIN_RULER_MM = 0.5
# Largest |log| of a stretch's gain (its keyframes' travel over the wall's shift), and
# of its difference from the run's median gain; and within GAIN_SIGMAS of the ruler's
# and the wall's relative sigmas (the run's stated scale sigma, the readings' sum's)
# with GAIN_FLOOR (the wall's own gain: seed 3's frame steps read 3 % short).
MAX_GAIN_LOG = 0.25
MAX_GAIN_SPREAD_LOG = 0.15
GAIN_SIGMAS = 3.0
GAIN_FLOOR = 0.03
# The ruler's relative sigma when the run states none.
DEFAULT_SCALE_SIGMA = 0.05
# Fewest stretches with a ruler for a run-wide gain (the run's last stretch).
MIN_RULERS = 2
# A frame within this many sigmas of its station's first frame stays standing.
REST_SIGMAS = 2.0
# The window searched for a frame step (mm): back this far, ahead this factor of the
# longest step it may be (its vision-placed step, the stationary test's bound), plus
# the back margin.
WINDOW_BACK_MM = 2.0
WINDOW_AHEAD = 1.3
# A frame's position from the tracked flow (:func:`_flow_refined`): its fraction's
# 1-sigma floor as a share of the keyframe step (three times the fraction's RMS error
# measured on the robustness bench: benchmarks/RESULTS.md, mot32's entry), and the
# largest disagreement with the wall's shift (sigmas of both) for the two to be combined.
FLOW_FLOOR_REL = 0.015
FLOW_AGREE_SIGMAS = 3.0


# What :func:`omnipipe.sfm.wall_resolve.resolve_by_wall` writes into the reason of a
# step whose length the wall's shift decided.
WALL_REASON = "the wall's own shift"


def wall_resolved(check: StepCheck) -> bool:
    """Whether a trusted keyframe step's length was decided by the wall's shift
    (:func:`omnipipe.sfm.wall_resolve.resolve_by_wall`). Such a step was flagged before:
    the frames inside it are not verified by its length (with odometry, random-wide
    seed 25s, a smooth wall: two resected frames 1.3-1.6 mm off and two 1 mm creeps
    the odometry took for standing inside a step the wall measured right)."""
    return (
        check.reliable and check.confidence == "resolved" and WALL_REASON in check.reason
        and not check.bridged_from  # its frames follow the odometry's travel
    )


@dataclass(frozen=True)
class CreepPlacement:
    """Stretches measured by the wall (:func:`place_creeps`).

    Attributes:
        world_from_rig: (N, 4, 4) the frames' poses, the placed frames moved along
            their stretch's travel.
        moved: (N,) the frames with a pose of their own: the input's moving frames and
            the placed frames that did not stand.
        unverified: (first, last, longest hidden step mm) of the stretches still
            unverified (the input's not placed, and the placed whose bound exceeds
            :data:`~omnipipe.sfm.stations.HIDDEN_STEP_MM`).
        placed: (first, last) of every stretch placed by the wall.
        bound_mm: (N,) each placed frame's step bound (mm: the step from the frame
            before it; NaN where not placed).
    """

    world_from_rig: np.ndarray
    moved: np.ndarray
    unverified: list[tuple[int, int, float]]
    placed: list[tuple[int, int]]
    bound_mm: np.ndarray


@dataclass(frozen=True)
class _Stretch:
    """One stretch a..b: its keyframes' axial travel (mm along rig a's z; NaN: the
    run's end, b its last frame) and every frame step's reading (frames a+1..b)."""

    a: int
    b: int
    travel_mm: float
    steps: list[WallShift]

    def gain(self) -> float:
        """The keyframes' travel over the sum of the wall's frame steps (NaN: none)."""
        total = sum(r.shift_mm for r in self.steps)
        if not (math.isfinite(self.travel_mm) and total > 0):
            return math.nan
        return self.travel_mm / total


def place_creeps(
    spans: list[tuple[int, int, float]],
    moved: np.ndarray,
    world_from_rig: np.ndarray,
    registered: np.ndarray,
    read_gray: Callable[[int], np.ndarray],
    read_wall: Callable[[int], WallCylinder | None],
    camera: CameraModel,
    scale_sigma_rel: float = math.nan,
) -> CreepPlacement:
    """The unverified ``spans`` (:func:`omnipipe.sfm.stations.unverified_stations`:
    first, last frame, bound mm) measured and placed by the wall's shift (module
    docstring).

    Args:
        moved: (N,) the stationary test's result.
        world_from_rig: (N, 4, 4) the frames' poses (a station's frames share its pose).
        registered: (N,) True where the pose is valid.
        read_gray: frame index -> its (H, W) grey image without the laser.
        read_wall: frame index -> its wall cylinder (rig frame), None without one.
        camera: the rig's camera model.
        scale_sigma_rel: the run's stated relative scale sigma (the ruler's; NaN:
            :data:`DEFAULT_SCALE_SIGMA`).
    """
    m = np.asarray(moved, bool)
    ruler_rel = scale_sigma_rel if math.isfinite(scale_sigma_rel) else DEFAULT_SCALE_SIGMA
    pose = np.array(world_from_rig, float, copy=True)
    out_moved = m.copy()
    worst: dict[tuple[int, int], float] = {}
    for a, b, w in spans:
        worst[(a, b)] = max(worst.get((a, b), 0.0), w)
    gray: dict[int, np.ndarray] = {}

    def g_of(i: int) -> np.ndarray:
        # Steps are read in order (i - 1, i): only frame i - 1 is kept for the next
        # step (a whole run's images kept grew the memory with the run).
        if i not in gray:
            last = gray.get(i - 1)
            gray.clear()
            if last is not None:
                gray[i - 1] = last
            gray[i] = read_gray(i)
        return gray[i]

    stretches = []
    for (a, b), w in sorted(worst.items()):
        if b > a and registered[a : b + 1].all():
            s = _read(a, b, w, m, pose, g_of, read_wall, camera)
            if s is not None:
                stretches.append(s)
    gray.clear()  # the flow (_flow_refined) reads its stretch's frames again
    gains = np.array([s.gain() for s in stretches])
    ok = np.isfinite(gains) & (gains > 0)
    ok[ok] = np.abs(np.log(gains[ok])) <= MAX_GAIN_LOG
    run_gain = float(np.median(gains[ok])) if ok.any() else math.nan
    spread = _gain_spread(gains[ok])
    unverified = dict(worst)
    placed = []
    bounds = np.full(len(m), math.nan)
    for s, gain in zip(stretches, gains, strict=True):
        pos = _positions(s, gain, run_gain, spread, int(ok.sum()), ruler_rel)
        if pos is None:
            continue
        pos = _flow_refined(s, pos, read_gray, camera.valid_mask())
        bound = _apply(s, pos, m, pose, out_moved, bounds)
        placed.append((s.a, s.b))
        if bound > HIDDEN_STEP_MM:
            unverified[(s.a, s.b)] = bound
        else:
            del unverified[(s.a, s.b)]
    left = [(a, b, w) for (a, b), w in sorted(unverified.items())]
    return CreepPlacement(pose, out_moved, left, placed, bounds)


def _read(
    a: int,
    b: int,
    bound_mm: float,
    moved: np.ndarray,
    pose: np.ndarray,
    gray: Callable[[int], np.ndarray],
    read_wall: Callable[[int], WallCylinder | None],
    camera: CameraModel,
) -> _Stretch | None:
    """Stretch a..b with every frame step read (``bound_mm``: the stationary test's
    bound on a hidden step, which widens each window); None when a reading fails or
    the ruler is too short."""
    at_end = b == len(moved) - 1 and not moved[b]
    travel = math.nan
    if not at_end:
        travel = float((pose[a, :3, :3].T @ (pose[b, :3, 3] - pose[a, :3, 3]))[2])
        if not travel >= MIN_RULER_MM:
            return None
    reach = bound_mm if math.isfinite(bound_mm) else travel
    if not math.isfinite(reach):
        return None
    steps = []
    for i in range(a + 1, b + 1):
        seen = float(np.linalg.norm(pose[i, :3, 3] - pose[i - 1, :3, 3]))
        window = (-WINDOW_BACK_MM, WINDOW_AHEAD * max(seen, reach) + WINDOW_BACK_MM)
        r = wall_shift(
            camera,
            gray(i - 1),
            gray(i),
            read_wall(i - 1),
            read_wall(i),
            window,
            CREEP_GRID_FLOOR,
            True,
        )
        if not r.measured:
            return None
        steps.append(r)
    return _Stretch(a, b, travel, steps)


def _gain_spread(gains: np.ndarray) -> float:
    """The relative 1-sigma of one stretch's gain about the run's median (MAD; at
    least 3 %); NaN with fewer than two."""
    if len(gains) < 2:
        return math.nan
    logs = np.log(gains)
    return max(1.4826 * float(np.median(np.abs(logs - np.median(logs)))), 0.03)


def _positions(
    s: _Stretch, gain: float, run_gain: float, spread: float, rulers: int, ruler_rel: float
) -> dict[int, tuple[float, float]] | None:
    """Frame -> (position along the stretch's travel mm, its step's 1-sigma mm) for
    a..b, or None when a check fails (module docstring)."""
    if math.isfinite(s.travel_mm):
        if not (math.isfinite(gain) and gain > 0 and abs(math.log(gain)) <= MAX_GAIN_LOG):
            return None
        if math.isfinite(run_gain) and abs(math.log(gain / run_gain)) > MAX_GAIN_SPREAD_LOG:
            return None
        total = s.travel_mm / gain
        wall_rel = math.sqrt(sum(r.sigma_mm**2 for r in s.steps)) / total
        if abs(math.log(gain)) > GAIN_SIGMAS * math.hypot(ruler_rel, wall_rel, GAIN_FLOOR):
            return None  # the wall and the keyframe step disagree: one of them is wrong
        g, rel = gain, 0.0
    elif rulers >= MIN_RULERS and math.isfinite(run_gain):
        g, rel = run_gain, spread
    else:
        return None
    pos = {s.a: (0.0, 0.0)}
    x = 0.0
    for i, r in enumerate(s.steps, start=s.a + 1):
        x += g * r.shift_mm
        pos[i] = (x, math.hypot(g * r.sigma_mm, rel * g * r.shift_mm))
    if math.isfinite(s.travel_mm):
        pos[s.b] = (s.travel_mm, pos[s.b][1])
    return pos


def _flow_refined(
    s: _Stretch,
    pos: dict[int, tuple[float, float]],
    read_gray: Callable[[int], np.ndarray],
    mask: np.ndarray,
) -> dict[int, tuple[float, float]]:
    """``pos`` (:func:`_positions`) with each inner frame's position combined with the
    tracked flow's (:func:`omnipipe.sfm.stations.flow_fraction` from keyframe a into the
    frame, the whole step a -> b the ruler): inverse-variance weights, the wall's
    position's variance its step sigmas summed from both keyframes (a bridge), the
    flow's its standard error with :data:`FLOW_FLOOR_REL`. The wall's shift adds one
    reading's error a frame; the flow reads every frame against the same keyframe, its
    error does not add up. A frame whose two positions disagree beyond
    :data:`FLOW_AGREE_SIGMAS` keeps the wall's; the step sigmas are kept (the bounds).
    The run's last stretch (no keyframe b) is not refined."""
    if not math.isfinite(s.travel_mm) or s.b - s.a < 2:
        return pos
    inner = range(s.a + 1, s.b)
    fractions = flow_fraction(read_gray(s.b), read_gray(s.a), (read_gray(i) for i in inner), mask)
    var = np.cumsum([pos[i][1] ** 2 for i in range(s.a + 1, s.b + 1)])
    total = float(var[-1])
    out = dict(pos)
    for k, (i, (f, se)) in enumerate(zip(inner, fractions, strict=True)):
        if not math.isfinite(f):
            continue
        x_wall, step_sigma = pos[i]
        var_wall = float(var[k]) * (total - float(var[k])) / total if total > 0 else 0.0
        x_flow = -f * s.travel_mm  # the fraction of the step b -> a, measured from a
        var_flow = (se**2 + FLOW_FLOOR_REL**2) * s.travel_mm**2
        if var_wall <= 0 or abs(x_flow - x_wall) > FLOW_AGREE_SIGMAS * math.sqrt(var_wall + var_flow):
            continue
        w = var_flow / (var_wall + var_flow)
        out[i] = (w * x_wall + (1.0 - w) * x_flow, step_sigma)
    return out


def _apply(
    s: _Stretch,
    pos: dict[int, tuple[float, float]],
    moved: np.ndarray,
    pose: np.ndarray,
    out_moved: np.ndarray,
    bounds: np.ndarray,
) -> float:
    """Stretch ``s``'s frames a+1..b-1 (and b at the run's end) placed in place along
    its travel (keyframes a -> b; rig a's axis at the run's end), each frame step's
    bound into ``bounds`` (N,); returns the largest (mm). A frame within
    :data:`REST_SIGMAS` of its station's first frame (the step sigmas between them
    added in quadrature) is stationary."""
    last = s.b if not math.isfinite(s.travel_mm) else s.b - 1
    origin = pose[s.a, :3, 3].copy()
    if math.isfinite(s.travel_mm):
        direction = (pose[s.b, :3, 3] - origin) / s.travel_mm
    else:
        direction = pose[s.a, :3, 2]
    station_x, var = 0.0, 0.0  # the station's first frame's position, the steps' variance since
    worst = 0.0
    for i in range(s.a + 1, s.b + 1):
        x, sig = pos[i]
        bounds[i] = FLOW_SIGMAS * sig
        worst = max(worst, bounds[i])
        if i > last:
            break
        var += sig**2
        if moved[i] or abs(x - station_x) > REST_SIGMAS * math.sqrt(var):
            station_x, var = x, 0.0
            out_moved[i] = True
        else:
            out_moved[i] = False
        pose[i, :3, 3] = origin + x * direction
    return worst


# Said of a stretch inside a wall-resolved keyframe step whose frames the wall's shift
# could not place (:func:`place_creeps` with odometry).
WALL_FRAMES_REASON = (
    "the frames inside a step the wall's own shift measured could not be placed by it: "
    "a frame may be off its step"
)


def odometry_verified_steps(
    world_from_rig: np.ndarray, a: int, b: int, travel_mm: np.ndarray, noise_mm: np.ndarray
) -> np.ndarray:
    """(b - a,) True where frame step i-1 -> i (i = a+1..b) inside the trusted keyframe
    step a..b agrees with the odometry: the frame's advance along the step (mm, on the
    keyframes' chord) against the odometry's advance scaled to the keyframe step (its
    slip cancels), within :data:`~omnipipe.sfm.stations.FLOW_SIGMAS` of the odometry's
    frame-step noise (``noise_mm`` (b - a,): resolution, walk, lag at stops:
    :func:`omnipipe.sfm.robot_sensors.odometry_noise`), that bound itself within
    :data:`~omnipipe.sfm.stations.HIDDEN_STEP_MM`.

    Args:
        world_from_rig: (N, 4, 4) poses.
        a, b: the keyframes.
        travel_mm: (N,) the odometry's travel at each frame (mm).
        noise_mm: (b - a,) its 1-sigma over each frame step.
    """
    chord = world_from_rig[b, :3, 3] - world_from_rig[a, :3, 3]
    length = float(np.linalg.norm(chord))
    odo = np.asarray(travel_mm, float)[a : b + 1] - float(travel_mm[a])
    out = np.zeros(b - a, bool)
    if length <= 0 or not np.isfinite(odo).all() or odo[-1] <= 0:
        return out
    along = (world_from_rig[a : b + 1, :3, 3] - world_from_rig[a, :3, 3]) @ (chord / length)
    gain = length / odo[-1]
    bound = FLOW_SIGMAS * gain * np.asarray(noise_mm, float)
    return (np.abs(np.diff(along) - gain * np.diff(odo)) <= bound) & (bound <= HIDDEN_STEP_MM)


def unverified_runs(ok: np.ndarray, first: int) -> list[tuple[int, int]]:
    """(first frame, last frame) of every run of False in ``ok`` (frame steps
    ``first + j`` -> ``first + j + 1``)."""
    out: list[tuple[int, int]] = []
    for j in np.flatnonzero(~np.asarray(ok, bool)):
        f = first + int(j)
        if out and out[-1][1] == f:
            out[-1] = (out[-1][0], f + 1)
        else:
            out.append((f, f + 1))
    return out


def verify_wall_frames(result: SfmResult, inputs: SfmInputs) -> None:
    """With odometry: a stretch flagged only because the wall's shift could not place
    the frames inside a wall-resolved keyframe step (:data:`WALL_FRAMES_REASON` alone)
    keeps flagged only the frame steps the odometry does not confirm
    (:func:`odometry_verified_steps`), in place. (random-wide features bench, at
    640x480 with sensors: 4 of 33 runs flagged so, e.g. seed 21's 19-frame step of a
    brick wall from 198 feature matches, its frames resected, one frame step the
    periodic wall could not read.)"""
    if inputs.odometry is None or inputs.timestamps is None:
        return
    times = np.asarray(inputs.timestamps, float)
    travel = odometry_at(inputs.odometry, times)[0]
    _, walk, floor = stated_error_model(inputs.odometry)
    noise = odometry_noise(inputs.odometry, times, walk, floor)
    steps = [c for c in result.step_checks if wall_resolved(c)]
    out: list[UnreliableStretch] = []
    for u in result.unreliable:
        if u.reason != WALL_FRAMES_REASON or u.last_frame <= u.first_frame:
            out.append(u)
            continue
        ok = np.zeros(u.last_frame - u.first_frame, bool)
        for c in steps:
            a, b = c.first_frame, c.last_frame
            if u.first_frame <= a and b <= u.last_frame and result.registered[a : b + 1].all():
                ok[a - u.first_frame : b - u.first_frame] = odometry_verified_steps(
                    result.world_from_rig, a, b, travel, noise[a:b]
                )
        out += [UnreliableStretch(f, g, u.reason) for f, g in unverified_runs(ok, u.first_frame)]
    result.unreliable = out

"""Camera motion of a whole sequence (paper Sec. V): every frame's metric pose.

:func:`run` reads as the paper's steps:

1. Stations: frames taken while the earthworm robot stood still are found from the
   images (:mod:`omnipipe.sfm.stations`); each stop is one station, its frames share
   one pose and are flagged ``stationary``.
2. Keyframes: the last keyframe's SIFT features (perspective views,
   :mod:`omnipipe.sfm.features`) are tracked by optical flow from each moving frame
   into the next (:mod:`omnipipe.sfm.tracking`: no track skips a period of a periodic
   wall); the station becomes a keyframe once the rays turned
   ``keyframe_min_parallax_deg`` (rotation removed), and only then is SIFT run on it
   and matched with the last keyframe, over the whole frame or guided by the tracks, or
   the tracks themselves taken as its correspondences, whichever RANSAC verifies best
   (also when too few features were tracked: descriptors alone).
3. Relative motion: eight-point algorithm on ray vectors with RANSAC (Eq. 10-16);
   near-pure rotations are recognised and keep a zero translation.
   Steps 1-3 are the frame loop, :mod:`omnipipe.sfm.keyframes`.
4. Scale: the laser points of the earlier keyframe are found again in the later one
   by template matching along the epipolar curve (Sec. V-D, Eq. 17), which makes
   each step metric; the feature depths on the light-section wall check each step
   (:mod:`omnipipe.sfm.step_scale`, :mod:`omnipipe.sfm.scale_check`).
5. Bundle adjustment over all keyframes (:mod:`omnipipe.sfm.adjust`,
   :mod:`omnipipe.sfm.bundle`): reprojection errors of the feature tracks in pixels
   through the hyperboloid model, plus the laser points' matches as metric anchors,
   which keep the scale from drifting; then the run's scale is combined with the
   wall-placed features'.
6. The stations that are not keyframes are resected against the adjusted tracks
   (:mod:`omnipipe.sfm.adjust`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from contextlib import nullcontext
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from threadpoolctl import threadpool_limits

from omnipipe.camera import camera_from_rig
from omnipipe.errors import ReconstructionError
from omnipipe.executor import InlineExecutor, opencv_threads
from omnipipe.image import gray_without_laser
from omnipipe.inputs.sensors import odometry_at
from omnipipe.memory import release_freed_memory
from omnipipe.sfm.adjust import Adjusted, Resected, adjust_keyframes, resect_pending
from omnipipe.sfm.adjusted_steps import confirm_adjusted
from omnipipe.sfm.creep import WALL_FRAMES_REASON, place_creeps, verify_wall_frames, wall_resolved
from omnipipe.sfm.creep_odometry import place_odometry_creeps
from omnipipe.sfm.external import external_motion, trajectory_path
from omnipipe.sfm.features import view_size
from omnipipe.sfm.flow_contrast import TEXTURE_FLOOR
from omnipipe.sfm.image_store import ImageStore
from omnipipe.sfm.keyframes import follow_keyframes
from omnipipe.sfm.lagging_tracks import kept, lags, plain_config
from omnipipe.sfm.motion_trust import run_texture, untrusted_motions
from omnipipe.sfm.odometry_scale import with_odometry_scale
from omnipipe.sfm.path_smooth import smooth_path
from omnipipe.sfm.ransac import RansacConfig
from omnipipe.sfm.ring_follow import add_ring_follow
from omnipipe.sfm.robot_sensors import (
    OdometrySteps,
    gravity_world,
    odometry_steps,
    rotation_linked,
)
from omnipipe.sfm.rotation_check import gyro_check, gyro_warnings
from omnipipe.sfm.scale_check import (
    StepCheck,
    UnreliableStretch,
    WallCylinder,
    merge_stretches,
    wall_cylinder,
)
from omnipipe.sfm.stations import (
    flow_hidden_steps,
    hidden_steps,
    texture_gain,
    unverified_stations,
)
from omnipipe.sfm.step_priors import WallPriors, bridged_priors, wall_priors
from omnipipe.sfm.step_records import Followed
from omnipipe.sfm.step_scale import (
    ChainedSteps,
    RunLength,
    RunScale,
    chain_steps,
    check_adjusted,
    run_length,
    run_scale,
)
from omnipipe.sfm.step_window import moving_counts
from omnipipe.sfm.tracking import is_large_view, sized_for_views
from omnipipe.sfm.types import (
    ODOMETRY_ONLY,
    Keyframes,
    SfmConfig,
    SfmContext,
    SfmInputs,
    SfmResult,
)
from omnipipe.spill import Pack

if TYPE_CHECKING:
    from omnipipe.laser.ring import LaserRing

__all__ = ["SfmConfig", "SfmInputs", "SfmResult", "run"]


def run(
    config: SfmConfig,
    inputs: SfmInputs,
    progress: Callable[[int], None] | None = None,
    executor: Executor | None = None,
) -> SfmResult:
    """Estimate every frame's metric pose (world = rig frame of frame 0).

    ``executor`` (:mod:`omnipipe.executor`) does the frame-parallel work: the moving
    frames' features (with ``inputs.moved`` and ``inputs.dataset``) and each keyframe
    step's scale evidence (Eq. 17 template matching, feature depths), while this
    process chains the steps in frame order. Without one, everything runs here; the
    result is the same.

    Raises:
        ReconstructionError: no frame could be read.
    """
    if inputs.n_frames < 1:
        raise ReconstructionError("no frames")
    if config.trajectory_from:  # poses given (a total station, a simulator's truth)
        return external_motion(trajectory_path(config.trajectory_from, inputs), inputs)
    # Single-threaded BLAS: this process's products are small or short (descriptor
    # distances, RANSAC's eight-point fits); a second OpenBLAS thread mostly spins, on
    # cores the workers and this process's SIFT and flow threads need (a descriptor
    # match 15 CPU-ms with one thread, 33 with two), and the motion does not depend on
    # the machine's core count. OpenCV likewise beside workers: its calls here then run
    # on the views' threads (:func:`~omnipipe.executor.thread_map`), its own pool would
    # split them again (inline, one thread takes the views: OpenCV keeps its pool).
    parallel = executor is not None and not isinstance(executor, InlineExecutor)
    with threadpool_limits(limits=1, user_api="blas"), opencv_threads(1) if parallel else nullcontext():
        result = _run(config, inputs, progress, executor)
        # Tracks held back by the views' contrast (sfm.lagging_tracks): once more on their
        # local contrast, where the wall has the texture for it.
        plain = plain_config(config)
        if lags(config, result) and _flow_views(plain, inputs).features.flow_plain:
            result = kept(config, result, _run(plain, inputs, None, executor))
        return result


def _run(
    config: SfmConfig,
    inputs: SfmInputs,
    progress: Callable[[int], None] | None,
    executor: Executor | None,
) -> SfmResult:
    """:func:`run` with the poses estimated here (not given)."""
    ctx = _context(_sized_views(_flow_views(config, inputs), inputs), inputs, executor)
    with ImageStore() as grays:  # keyframe grey images, on disk until the run is decided
        # Steps 1-3: stations, keyframes and their relative motions; each step's two
        # scale measurements (step 4) in the workers.
        ratio = _station_ratio(inputs)
        followed = follow_keyframes(ctx, inputs, grays, progress, ratio)
        # Steps whose relative motion a plain wall's few matches cannot hold: lost, with
        # or without the robot's sensors (sfm.motion_trust).
        untrusted_motions(ctx, inputs, followed)
        kf = followed.keyframes
        # Step 4: every step's length decided with the whole run's evidence (the two
        # sources' systematic offset), then chained.
        scale = run_scale(kf.evidence, config.scale_check, ctx.warnings)
        odometry = (
            odometry_steps(inputs.odometry, inputs.timestamps, kf.frames)
            if inputs.odometry is not None and inputs.timestamps is not None
            else None
        )
        chain = _chain_held(chain_steps(ctx, kf, scale, odometry, moving_counts(followed.moved, kf.frames)))
        # The frame loop's freed blocks and the keyframes' arrays the chain read (pages of
        # the run's scratch) handed back before the adjustment: they grew with the keyframes.
        release_freed_memory()
        # Step 5: bundle adjustment; steps it moved away from their sources are flagged,
        # and the run's scale is combined with the wall's (one similarity of the run).
        adjusted, chain, walls = _adjusted_and_checked(ctx, config, kf, chain, scale, followed.moved, odometry)
        length = run_length(ctx, adjusted.world_from_kf, chain, kf, scale, walls.readings)
        length = with_odometry_scale(length, adjusted.world_from_kf, chain.checks, odometry, ctx.warnings)
        if not math.isnan(length.correction_log):
            adjusted = adjusted.scaled(math.exp(length.correction_log))
        # Step 6: the other moving frames, resected against the adjusted tracks; one that
        # cannot be is placed between its keyframes by the odometry, else by the gait.
        with_odometry = inputs.odometry is not None and inputs.timestamps is not None
        travel = (
            odometry_at(inputs.odometry, inputs.timestamps)[0]
            if with_odometry
            else np.cumsum(followed.moved).astype(float)
        )
        resected = resect_pending(
            ctx, adjusted, kf, followed.pending, followed.next_matches, inputs.n_frames, travel,
            "odometry" if with_odometry else "gait (moving frames)",
            # Inside a bridged step the frames follow the travel, not the wall points.
            {k: c.bridged_sigma_mm for k, c in enumerate(chain.checks) if c.bridged_from},
        )
        if kf.flats is not None:
            kf.flats.close()  # the steps' flat fields (sfm.flat_field): read no more
    if not chain.checks and with_odometry:
        # No keyframe step (a plain wall): the odometry placed the moving frames.
        length = replace(length, source=ODOMETRY_ONLY)
    # The odometry moves frames the images cannot (stations.odometry_moved): it verifies
    # the stationary ones.
    def read_gray(i: int) -> np.ndarray:
        return gray_without_laser(inputs.read_frame(i), inputs.rig.laser.channel)

    read_wall = nearest_wall(inputs.rings.rings)
    result = _result(
        ctx, followed, adjusted, resected, chain.checks, scale, length,
        None if with_odometry else ratio, read_gray, read_wall,
    )
    if inputs.odometry is not None and inputs.timestamps is not None:
        verify_wall_frames(result, inputs)  # the odometry confirms frames the wall could not place
        # Frames the odometry counted creeping: placed by the wall, else by it (flagged).
        place_odometry_creeps(
            result, inputs.odometry, inputs.timestamps, ctx.camera, read_gray, read_wall, ctx.warnings
        )
    add_ring_follow(result, inputs)  # bridged steps: the gyro's turn, the ring's centre
    smooth_path(result)  # the resected frames' scatter across the path
    untrusted = [c.first_frame for c in chain.checks if not c.reliable]
    _add_gravity(result, inputs, untrusted + [u.first_frame for u in resected.unreliable], kf.frames)
    result.gyro_check = gyro_check(inputs.imu, inputs.timestamps, result.world_from_rig, result.registered)
    result.warnings.extend(gyro_warnings(result.gyro_check))
    return result


def nearest_wall(rings: Sequence[LaserRing]) -> Callable[[int], WallCylinder | None]:
    """Frame index -> the wall cylinder (rig frame) of its own ring or, for a frame
    without one, of the nearest frame's ring (ties: the earlier); None when no frame
    has one. ``reconstruct``'s decoding pass extracts no ring at a frame it takes for
    standing, and the wall's shift between such frames still needs the wall around
    the rig (a creep moves it by a few mm: robustness seeds 3 and 24, joints walls,
    every frame step flagged by the stationary test without it)."""
    cache: dict[int, WallCylinder | None] = {}
    # Each cylinder's ring points in the run's scratch (the same values): a ring read back
    # is its whole record (every per-sample array), which a cylinder kept per frame held.
    pack = Pack()

    def own(i: int) -> WallCylinder | None:
        if i not in cache:
            wall = wall_cylinder(rings[i].points_in_rig)
            if wall is not None and wall.ring_points is not None:
                wall = replace(wall, ring_points=pack.put(wall.ring_points))
            cache[i] = wall
        return cache[i]

    def read(i: int) -> WallCylinder | None:
        for d in range(len(rings)):
            for j in (i - d, i + d):
                if 0 <= j < len(rings) and (w := own(j)) is not None:
                    return w
        return None

    return read


def _adjusted_and_checked(
    ctx: SfmContext,
    config: SfmConfig,
    kf: Keyframes,
    chain: ChainedSteps,
    scale: RunScale,
    moved: np.ndarray,
    odometry: OdometrySteps | None = None,
) -> tuple[Adjusted, ChainedSteps, WallPriors]:
    """Step 5: the bundle adjustment of the chained keyframes (again with the wall's step
    lengths as priors where it left them: :func:`omnipipe.sfm.step_priors.wall_priors`),
    and the chain's checks with the steps it moved away from their sources flagged (in a
    wall-anchored run, where the feature depths are the anchors, the gait judges such
    steps too; the robot's ``odometry`` per step, where it has one, confirms moves too);
    the wall's readings on the returned poses."""
    # A bridged step is held to its estimate (odometry, gait): nothing else measures it.
    bridged = bridged_priors(chain.checks)
    adjusted = adjust_keyframes(
        ctx, chain.world_from_kf, kf, chain.pair_matches, chain.anchors, scale.wall_anchored, bridged
    )
    # Where the adjustment left the wall's own shift, the wall's step lengths hold it.
    walls = wall_priors(ctx, kf, adjusted.world_from_kf, chain.checks) if config.scale_from_wall else WallPriors()
    if walls.priors:
        held = walls.priors + bridged_priors(chain.checks, {p.a for p in walls.priors})
        adjusted = adjust_keyframes(
            ctx, chain.world_from_kf, kf, chain.pair_matches, chain.anchors, scale.wall_anchored, held
        )
        ctx.warnings.append(
            f"bundle adjustment held to the wall's own shift on {len(walls.priors)} steps (it "
            "had moved a step away from the wall's reading)"
        )
        walls = WallPriors(walls.priors)  # read on the poses before: not the new ones'
    offset = math.exp(scale.offset_log)
    checks = check_adjusted(
        chain.checks,
        adjusted.world_from_kf,
        config.scale_check,
        offset if scale.wall_anchored else 1.0,
        None if scale.wall_anchored else offset,
        {p.a: (p.length_mm, p.sigma_mm) for p in walls.priors},
        odometry,
    )
    if scale.wall_anchored:
        checks = confirm_adjusted(
            checks, adjusted.world_from_kf, moving_counts(moved, kf.frames), config.scale_check, ctx.warnings
        )
    return adjusted, replace(chain, checks=checks), walls


def _chain_held(chain: ChainedSteps) -> ChainedSteps:
    """``chain`` with each step's inlier matches and its anchors' arrays in the run's
    scratch (:class:`omnipipe.spill.Pack`: the same values, resident only while read):
    they wait for the adjustment and the resection, and held in memory they grew the
    camera motion's memory with the run."""
    pack = Pack()
    return replace(
        chain,
        pair_matches=[replace(p, matches=pack.put(p.matches)) for p in chain.pair_matches],
        anchors=[
            replace(
                q, points_in_a=pack.put(q.points_in_a), pixels_b=pack.put(q.pixels_b),
                log_lengths=pack.put(q.log_lengths),
            )
            for q in chain.anchors
        ],
    )


def _station_ratio(inputs: SfmInputs) -> np.ndarray:
    """(N,) the stationary test's ratio of each frame; NaN where it was not recorded."""
    if inputs.station_ratio is not None:
        return np.asarray(inputs.station_ratio, float)
    return np.full(inputs.n_frames, math.nan)


def _add_gravity(
    result: SfmResult, inputs: SfmInputs, untrusted_from: list[int], kf_frames: list[int]
) -> None:
    """Gravity in the world frame (and its 1-sigma, rad) from the IMU, when there is one,
    over the frames linked to frame 0 by trusted steps (``untrusted_from``: where the
    untrusted stretches begin; :func:`omnipipe.sfm.robot_sensors.rotation_linked`), each
    weighted by its keyframe steps from frame 0 (``kf_frames``: the keyframes)."""
    if inputs.imu is None or inputs.timestamps is None:
        return
    linked = rotation_linked(result.station, untrusted_from)
    steps = np.searchsorted(np.asarray(kf_frames, int), np.arange(len(result.station)), side="left")
    gravity = gravity_world(
        inputs.imu, inputs.timestamps, result.world_from_rig, result.registered & linked, steps
    )
    if gravity is not None:
        result.gravity_world, result.gravity_sigma_rad = gravity


def _flow_views(config: SfmConfig, inputs: SfmInputs) -> SfmConfig:
    """``config`` with ``features.flow_plain`` off when the wall is plain: its views'
    local contrast before CLAHE (:func:`~omnipipe.sfm.flow_contrast.wall_texture`, the
    median over the first, middle and last frames) below
    :data:`~omnipipe.sfm.flow_contrast.TEXTURE_FLOOR`. The local contrast would stretch
    such a wall's shading and noise into tracks it cannot hold (robustness seeds 10, 19,
    28: refused on CLAHE'd views, 5-79 mm per 300 mm on the local contrast); on CLAHE'd
    views a plain wall is refused without odometry and bridged by it."""
    if not config.features.flow_plain or not config.tracking.enabled:
        return config
    if run_texture(config, inputs) >= TEXTURE_FLOOR:
        return config
    return replace(config, features=replace(config.features, flow_plain=False))


def _sized_views(config: SfmConfig, inputs: SfmInputs) -> SfmConfig:
    """``config`` with the tracking's settings and the keyframes' parallax for the size
    of the run's views (:func:`~omnipipe.sfm.tracking.sized_for_views`,
    ``keyframe_min_parallax_large_deg``)."""
    shape = view_size(camera_from_rig(inputs.rig), config.features)
    sized = replace(config, tracking=sized_for_views(config.tracking, shape))
    if is_large_view(config.tracking, shape):
        sized = replace(sized, keyframe_min_parallax_deg=config.keyframe_min_parallax_large_deg)
    return sized


def _context(config: SfmConfig, inputs: SfmInputs, executor: Executor | None) -> SfmContext:
    """The run's camera, RANSAC settings (threshold as an angle) and executor."""
    camera = camera_from_rig(inputs.rig)
    ex = executor or InlineExecutor()
    ransac = RansacConfig(
        threshold_rad=config.ransac_threshold_px * camera.angular_resolution(),
        max_iterations=config.ransac_iterations,
        min_inliers=config.min_inliers,
        rotation_only_ratio=config.rotation_only_ratio,
        seed=config.seed,
    )
    return SfmContext(config, camera, ransac, ex, not isinstance(ex, InlineExecutor), [])


def _result(
    ctx: SfmContext,
    followed: Followed,
    adjusted: Adjusted,
    resected: Resected,
    checks: list[StepCheck],
    scale: RunScale,
    length: RunLength,
    ratio: np.ndarray | None = None,
    read_gray: Callable[[int], np.ndarray] | None = None,
    read_wall: Callable[[int], WallCylinder | None] | None = None,
) -> SfmResult:
    """Every frame's pose: each station's from its keyframe (adjusted) or its resection;
    the steps' checks and the unreliable stretches (steps not trusted, frames not
    resected, stationary frames whose stationary-test ``ratio`` (N,) could hide a step
    on this wall: :func:`omnipipe.sfm.stations.unverified_stations`; the tracked flow of
    ``read_gray``'s grey images may verify them: :func:`omnipipe.sfm.stations.flow_hidden_steps`,
    and the wall's shift (``read_wall``: a frame's wall cylinder) measure and place their
    frames: :func:`omnipipe.sfm.creep.place_creeps`), merged."""
    release_freed_memory()  # the adjustment's and the resection's freed blocks: not under the creeps
    moved = followed.moved
    station = np.cumsum(moved) - 1
    first = np.flatnonzero(moved)
    kf_of = {f: k for k, f in enumerate(followed.keyframes.frames)}
    world_from_station = np.empty((len(first), 4, 4))
    for s_idx, f in enumerate(first):
        world_from_station[s_idx] = (
            adjusted.world_from_kf[kf_of[f]] if f in kf_of else resected.world_from_rig[f]
        )
    # A lost step bridged by the odometry places its frame along the axis (flagged).
    odometry_placed = {c.last_frame for c in checks if c.bridged_from == "odometry"}
    lost = followed.lost.copy()
    lost[list(odometry_placed)] = False
    stretches = [
        UnreliableStretch(c.first_frame, c.last_frame, c.reason or c.confidence)
        for c in checks
        if not c.reliable
    ]
    world_from_rig = world_from_station[station]
    registered = ~lost[first[station]]
    placed = _Placed(world_from_rig, moved, [])
    if ratio is not None and not moved.all():
        placed = _place_unverified(ctx, followed, placed, registered, ratio, length, read_gray, read_wall)
    elif ratio is None and read_gray is not None and read_wall is not None:
        placed = _place_wall_resolved(ctx, checks, placed, registered, length, read_gray, read_wall)
    world_from_rig, moved_out = placed.world_from_rig, placed.moved
    station = np.cumsum(moved_out) - 1
    stretches += placed.stretches
    return SfmResult(
        world_from_rig=world_from_rig,
        registered=registered,
        keyframe=followed.keyframe,
        stationary=~moved_out,
        station=station,
        wall_scale_log=length.wall_log,
        scale_correction_log=length.correction_log,
        warnings=ctx.warnings,
        bundle=adjusted.results[-1] if adjusted.results else None,
        bundle_windows=len(adjusted.results),
        scale_sigma_rel=length.sigma_rel,
        step_checks=checks,
        unreliable=merge_stretches(stretches + resected.unreliable),
        scale_source=length.source,
        laser_offset=math.exp(scale.offset_log) - 1.0,
        tracked=followed.tracked,
    )


@dataclass
class _Placed:
    """Every frame's pose (N, 4, 4) world_from_rig, which frames moved (N,) and the
    stretches left unreliable by :func:`_place_unverified` / :func:`_place_wall_resolved`."""

    world_from_rig: np.ndarray
    moved: np.ndarray
    stretches: list[UnreliableStretch]


def _place_unverified(
    ctx: SfmContext,
    followed: Followed,
    placed: _Placed,
    registered: np.ndarray,
    ratio: np.ndarray,
    length: RunLength,
    read_gray: Callable[[int], np.ndarray] | None,
    read_wall: Callable[[int], WallCylinder | None] | None,
) -> _Placed:
    """Without odometry: the stationary frames whose test ``ratio`` could hide a step on
    this wall (:func:`omnipipe.sfm.stations.unverified_stations`), verified by the
    tracked flow (:func:`omnipipe.sfm.stations.flow_hidden_steps`) or measured and placed
    by the wall's shift (:func:`omnipipe.sfm.creep.place_creeps`); the rest flagged."""
    moved, world_from_rig = placed.moved, placed.world_from_rig
    gain = texture_gain(ratio, world_from_rig[:, :3, 3], registered, ctx.config.stations)
    hidden = hidden_steps(ratio, moved, gain)
    if read_gray is not None:
        hidden = flow_hidden_steps(
            hidden, moved, world_from_rig[:, :3, 3], registered, read_gray, ctx.camera.valid_mask()
        )
    spans = unverified_stations(hidden, moved, followed.keyframes.frames)
    if read_gray is not None and read_wall is not None and spans:
        crept = place_creeps(
            spans, moved, world_from_rig, registered, read_gray, read_wall, ctx.camera, length.sigma_rel
        )
        spans, world_from_rig, moved = crept.unverified, crept.world_from_rig, crept.moved
        ctx.warnings.extend(
            f"frames {a}->{b}: the frames between the keyframes placed by the wall's own "
            "shift (the stationary test could not tell standing from creeping)"
            for a, b in crept.placed
        )
    stretches = [
        UnreliableStretch(
            a, b, "the stationary test cannot rule out "
            + (f"a {worst:.1f} mm step" if math.isfinite(worst) else "a step of any length")
            + " on this wall: a frame taken for standing may have moved",
        )
        for a, b, worst in spans
    ]
    return _Placed(world_from_rig, moved, stretches)


def _place_wall_resolved(
    ctx: SfmContext,
    checks: list[StepCheck],
    placed: _Placed,
    registered: np.ndarray,
    length: RunLength,
    read_gray: Callable[[int], np.ndarray],
    read_wall: Callable[[int], WallCylinder | None],
) -> _Placed:
    """With odometry: the frames inside a step the wall's shift decided, placed by it
    (:func:`omnipipe.sfm.creep.place_creeps`); those it cannot place flagged."""
    inside = [(c.first_frame, c.last_frame, math.inf) for c in checks if wall_resolved(c)]
    if not inside:
        return placed
    crept = place_creeps(
        inside, placed.moved, placed.world_from_rig, registered, read_gray, read_wall, ctx.camera,
        length.sigma_rel,
    )
    stretches = [UnreliableStretch(a, b, WALL_FRAMES_REASON) for a, b, _ in crept.unverified]
    return _Placed(crept.world_from_rig, crept.moved, stretches)

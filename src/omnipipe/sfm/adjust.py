"""Bundle adjustment of the keyframes and resection of the other stations (paper Sec. V,
steps 5 and 6).

- :func:`adjust_keyframes`: reprojection errors of the feature tracks in pixels through
  the hyperboloid model plus the metric anchors (laser points found again, Eq. 17, or
  wall-placed features), over all keyframes or, on a long run, in consecutive windows
  (:func:`omnipipe.sfm.bundle.keyframe_windows`); laser points are also matched to the
  keyframes further ahead with the adjusted motion (``anchor_reach``), then adjusted
  again.
- :func:`resect_pending`: each moving frame that is not a keyframe is placed against the
  adjusted tracks of its keyframe and the next (in the executor's workers); inside a
  keyframe step whose length was bridged, at its fraction of the travel unless the
  resection agrees within the step's sigma.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, replace

import numpy as np

from omnipipe.errors import ReconstructionError
from omnipipe.executor import ordered_map, parallelism, shares_files
from omnipipe.geometry import interpolated_pose, invert
from omnipipe.memory import release_freed_memory
from omnipipe.progress import phase
from omnipipe.sfm.bundle import (
    BundleConfig,
    BundleProblem,
    BundleResult,
    LengthPrior,
    build_problem,
    bundle_adjust,
    epipolar_rows,
    keyframe_windows,
    resect_rays,
    set_priors,
)
from omnipipe.sfm.flat_field import FlatFields, as_field, divided
from omnipipe.sfm.laser_scale import LaserMatches
from omnipipe.sfm.ring_axis import (
    RING_TRIGGER_SIGMAS,
    RingCentre,
    axis_rows,
    fit_ring_centre,
    ring_offsets,
)
from omnipipe.sfm.scale_check import UnreliableStretch
from omnipipe.sfm.schur import warm_in_worker
from omnipipe.sfm.tasks import laser_matches
from omnipipe.sfm.types import (
    Anchor,
    KeyframeRays,
    Keyframes,
    PairMatches,
    PendingFrame,
    SfmContext,
)
from omnipipe.spill import Pack

# Fewest tracked points to resect a frame, in all and on its keyframe's side.
MIN_RESECTION_POINTS = 12
MIN_RESECTION_POINTS_OWN_SIDE = 6


@dataclass(frozen=True)
class WindowTracks:
    """The feature tracks of one adjustment window (for the resection of the frames
    between its keyframes).

    Attributes:
        first: the window's first keyframe.
        feature_point: per keyframe of the window, (N_k,) each feature's track (-1: none).
        points_in_world: (P, 3) the adjusted track points, mm.
    """

    first: int
    feature_point: list[np.ndarray]
    points_in_world: np.ndarray


@dataclass(frozen=True)
class Adjusted:
    """The keyframes after the bundle adjustment.

    Attributes:
        world_from_kf: (K, 4, 4) adjusted keyframe poses, mm.
        tracks: per window, its tracks (None: not adjusted); empty without adjustment.
        window_of: (K,) the window that adjusted each keyframe.
        results: each adjusted window's result, in order.
    """

    world_from_kf: np.ndarray
    tracks: list[WindowTracks | None]
    window_of: np.ndarray
    results: list[BundleResult]

    def scaled(self, gain: float) -> Adjusted:
        """The same run with every length multiplied by ``gain`` (positions and track
        points alike: one similarity)."""
        world_from_kf = self.world_from_kf.copy()
        world_from_kf[:, :3, 3] *= gain
        pack = Pack()  # the scaled track points in the run's scratch, as the adjustment's
        tracks = [
            None if t is None else replace(t, points_in_world=pack.put(t.points_in_world * gain))
            for t in self.tracks
        ]
        return replace(self, world_from_kf=world_from_kf, tracks=tracks)


@dataclass(frozen=True)
class _Observations:
    """What the adjustment fits the keyframe poses to.

    Attributes:
        kf: the keyframes (features; grey images and ring points for far anchors).
        pair_matches: each step's inlier matches (the tracks).
        anchors: each step's metric anchors.
        far: with the laser's anchors and ``anchor_reach`` > 1, laser points are also
            matched to the keyframes further ahead.
        priors: steps whose length the wall's shift measured
            (:mod:`omnipipe.sfm.step_priors`).
        centres: per keyframe, its laser ring's centre (None: no ring, or the ring
            rows are off), :mod:`omnipipe.sfm.ring_axis`.
    """

    kf: Keyframes
    pair_matches: list[PairMatches]
    anchors: list[Anchor]
    far: bool
    priors: tuple[LengthPrior, ...] = ()
    centres: tuple[RingCentre | None, ...] = ()


def adjust_keyframes(
    ctx: SfmContext,
    world_from_kf: np.ndarray,
    kf: Keyframes,
    pair_matches: list[PairMatches],
    anchors: list[Anchor],
    wall_anchored: bool,
    priors: tuple[LengthPrior, ...] = (),
) -> Adjusted:
    """Bundle adjustment of the chained keyframe poses ``world_from_kf`` ((K, 4, 4) mm)
    with the steps' ``pair_matches`` and ``anchors``; unchanged when off or with one
    keyframe. Two keyframes are adjusted too: the tracks it leaves are what the frames
    between them are resected against (random-wide seed 1, a 963 mm pipe whose 29 frames
    made one keyframe step: without them every frame was unresected and flagged).
    ``wall_anchored``: the anchors are wall-placed features (no laser matches further
    ahead then); ``priors``: steps' lengths the adjustment is held to
    (:class:`omnipipe.sfm.bundle.LengthPrior`)."""
    config = ctx.config
    if not (config.bundle.enabled and len(world_from_kf) >= 2):
        return Adjusted(world_from_kf, [], np.zeros(len(world_from_kf), int), [])
    # Longer baselines measure the scale better: laser points of keyframe k are also
    # found in k + 2 ... k + reach with the adjusted motion, then adjusted again.
    far = config.anchor_reach > 1 and not wall_anchored
    centres = (
        tuple(fit_ring_centre(p) for p in kf.ring_points)
        if config.bundle.ring_weight > 0 and len(kf.ring_points) == len(world_from_kf)
        else ()
    )
    return _adjust_windows(ctx, world_from_kf, _Observations(kf, pair_matches, anchors, far, priors, centres))


def _adjust_windows(ctx: SfmContext, world_from_kf: np.ndarray, obs: _Observations) -> Adjusted:
    """Bundle adjustment of the keyframes, in consecutive windows on a long run.

    A run of up to 1.25 ``config.window_keyframes`` keyframes is adjusted at once (the
    global adjustment, keyframe 0 fixed). A longer one window by window
    (:func:`omnipipe.sfm.bundle.keyframe_windows`): each window starts from the chained
    poses carried on from its first keyframes, which the window before adjusted and
    which it holds fixed; its tracks and laser anchors are those within it. Cost and
    memory grow linearly with the run.
    """
    config = ctx.config.bundle
    K = len(world_from_kf)
    adjusted = world_from_kf.copy()
    tracks: list[WindowTracks | None] = []
    window_of = np.zeros(K, int)
    stats: list[BundleResult] = []
    pack = Pack()
    windows = keyframe_windows(K, config.window_keyframes, config.window_overlap)
    # Progress: three steps a window (adjust, far laser anchors, adjust again).
    tick = phase("bundle", 3 * len(windows))
    if len(windows) > 1 and config.solver == "auto":
        config = replace(config, solver="schur")  # see BundleConfig.solver
    if config.solver == "schur":
        warm_in_worker(ctx.executor)  # its kernels compiled by a worker, not here
    for w, (s, e, fixed) in enumerate(windows):
        init = adjusted[s:e].copy()
        if w > 0:
            # The chain carried on from the last held keyframe's adjusted pose.
            j = s + fixed - 1
            carry = adjusted[j] @ invert(world_from_kf[j])
            init[fixed:] = np.einsum("ij,njk->nik", carry, world_from_kf[s + fixed : e])
        window_of[s + (fixed if w else 0) : e] = w
        ba, problem = _adjust_window(
            ctx, config, init, obs, (s, e, fixed), lambda k, w=w: tick(3 * w + k)
        )
        tick(3 * w + 3)
        # The window's transient (its Jacobians, the reduced systems: tens of MB) freed
        # back to the system: glibc kept it, and the heap grew window by window.
        release_freed_memory()
        if ba is None:
            where = "" if len(windows) == 1 else f" of keyframes {s}-{e - 1}"
            ctx.warnings.append(
                f"bundle adjustment{where} skipped: too few feature tracks or laser anchors"
            )
            adjusted[s:e] = init
            tracks.append(None)
            continue
        adjusted[s:e] = ba.world_from_rig
        # The window's tracks wait for the resection in the run's scratch (the same
        # values): held in memory, every window's grew the run's memory with its length.
        points = pack.put(ba.points_in_world)
        stats.append(replace(ba, points_in_world=points))
        tracks.append(WindowTracks(s, [pack.put(f) for f in problem.feature_point], points))
    tick(3 * len(windows))
    return Adjusted(adjusted, tracks, window_of, stats)


def _adjust_window(
    ctx: SfmContext,
    config: BundleConfig,
    init: np.ndarray,
    obs: _Observations,
    window: tuple[int, int, int],
    steps_done: Callable[[int], None],
) -> tuple[BundleResult | None, BundleProblem]:
    """One window ``(start, end, fixed)`` of keyframes adjusted from ``init`` ((W, 4, 4)
    mm), its first ``fixed`` held; (None, the problem) when it has too few tracks or no
    anchors. ``steps_done(k)`` after its first adjustment (1) and its far anchors (2)."""
    s, e, fixed = window
    features = obs.kf.features[s:e]
    anchors = [q for q in obs.anchors if q.a >= s and q.b < e]
    problem = build_problem(
        ctx.camera,
        init,
        [f.pixels for f in features],
        [f.rays_in_rig for f in features],
        [(p.a - s, p.b - s, p.matches) for p in obs.pair_matches if p.a >= s and p.b < e],
        [(q.a - s, q.b - s, q.points_in_a, q.pixels_b) for q in anchors],
        config,
    )
    problem.fixed = fixed
    if config.epipolar_anchors:
        local = [replace(q, a=q.a - s, b=q.b - s) for q in _along_only(anchors, obs.pair_matches, config.along_min_matches)]
        problem.anchor_rows = _anchor_rows(ctx, init, problem, local)
    set_priors(problem, [replace(p, a=p.a - s, b=p.b - s) for p in obs.priors if p.a >= s and p.b < e])
    if len(problem.points_in_world) < 10 or not len(problem.anchor_a):
        return None, problem
    ba = bundle_adjust(ctx.camera, problem, config)
    steps_done(1)
    extra = _far_anchors(ctx, ba.world_from_rig, obs.kf, s, fixed) if obs.far else []
    steps_done(2)
    if extra:
        problem.world_from_rig, problem.points_in_world = ba.world_from_rig, ba.points_in_world
        if problem.anchor_rows is not None:  # matched along the adjusted motion's curves
            shifted = [replace(q, a=q.a + s, b=q.b + s) for q in extra]
            extra = [replace(q, a=q.a - s, b=q.b - s) for q in _along_only(shifted, obs.pair_matches, config.along_min_matches)]
            extra_rows = _anchor_rows(ctx, ba.world_from_rig, None, extra)
            problem.anchor_rows = np.concatenate([problem.anchor_rows, extra_rows])
        _append_anchors(problem, extra)
        ba = bundle_adjust(ctx.camera, problem, config)
    if obs.centres:
        ba = _held_to_rings(ctx, config, problem, ba, list(obs.centres[s:e]), obs.kf.frames[s:e])
    return ba, problem


def _held_to_rings(
    ctx: SfmContext,
    config: BundleConfig,
    problem: BundleProblem,
    ba: BundleResult,
    centres: list[RingCentre | None],
    frames: list[int],
) -> BundleResult:
    """``ba`` adjusted again with the laser rings' centres as rows
    (:mod:`omnipipe.sfm.ring_axis`) when it left a keyframe's centre off its neighbours'
    chord by more than :data:`~omnipipe.sfm.ring_axis.RING_TRIGGER_SIGMAS` of its sigma
    (a kink across the pipe's axis that the rings rule out); else ``ba``. ``frames``: the
    window's keyframes' frame indices (for the warning)."""
    rows = axis_rows(ba.world_from_rig, centres)
    if not len(rows):
        return ba
    z = np.linalg.norm(ring_offsets(ba.world_from_rig, rows), axis=1) / rows.sigma_mm
    if z.max() <= RING_TRIGGER_SIGMAS:
        return ba
    worst = int(np.argmax(z))
    problem.world_from_rig, problem.points_in_world = ba.world_from_rig, ba.points_in_world
    problem.rings = rows
    held = bundle_adjust(ctx.camera, problem, config)
    after = np.linalg.norm(ring_offsets(held.world_from_rig, rows), axis=1) / rows.sigma_mm
    ctx.warnings.append(
        f"bundle adjustment held to the laser rings' centres on {len(rows)} keyframes (it had "
        f"left frame {frames[int(rows.kf[worst, 1])]}'s centre {z[worst]:.1f} sigma "
        f"({z[worst] * rows.sigma_mm[worst]:.2f} mm) off the pipe's axis; now {after[worst]:.1f} sigma)"
    )
    return held


def _along_only(anchors: list[Anchor], pair_matches: list[PairMatches], min_matches: int) -> list[Anchor]:
    """``anchors`` with ``epipolar`` kept only where every keyframe step between a and b
    had at least ``min_matches`` RANSAC inliers (``BundleConfig.along_min_matches``) (a wall whose feature tracks
    fix the steps' directions); across fewer the across-curve component stays, holding
    the step near its RANSAC motion (benchmarks/RESULTS.md)."""
    count: dict[int, int] = {}
    for p in pair_matches:
        if p.b == p.a + 1:
            count[p.a] = len(p.matches)
    return [
        replace(q, epipolar=q.epipolar and all(
            count.get(k, 0) >= min_matches for k in range(q.a, q.b)
        ))
        for q in anchors
    ]


def _anchor_rows(
    ctx: SfmContext, world_from_rig: np.ndarray, problem: BundleProblem | None, anchors: list[Anchor]
) -> np.ndarray:
    """(L, 2, 2) the rows of ``anchors`` (keyframes counted from the window's first;
    :func:`omnipipe.sfm.bundle.epipolar_rows`): a laser match measures its pixel only
    along the epipolar curve of the poses ``world_from_rig`` ((W, 4, 4), the motion it
    was searched along), a wall-placed feature in 2-D. ``problem``: its stacked anchors
    are ``anchors`` (None: stack them here)."""
    if problem is None:
        a = np.concatenate([np.full(len(q.points_in_a), q.a) for q in anchors]) if anchors else np.zeros(0, int)
        b = np.concatenate([np.full(len(q.points_in_a), q.b) for q in anchors]) if anchors else np.zeros(0, int)
        pts = np.concatenate([q.points_in_a for q in anchors]) if anchors else np.zeros((0, 3))
    else:
        a, b, pts = problem.anchor_a, problem.anchor_b, problem.anchor_points_in_a
    along = (
        np.concatenate([np.full(len(q.points_in_a), q.epipolar) for q in anchors])
        if anchors else np.zeros(0, bool)
    )
    return epipolar_rows(ctx.camera, world_from_rig, a.astype(int), b.astype(int), pts, along)


def _append_anchors(problem: BundleProblem, extra: list[Anchor]) -> None:
    """Add ``extra`` anchors (keyframes counted from the problem's first) to ``problem``."""
    problem.anchor_a = np.concatenate(
        [problem.anchor_a] + [np.full(len(q.points_in_a), q.a) for q in extra]
    )
    problem.anchor_b = np.concatenate(
        [problem.anchor_b] + [np.full(len(q.points_in_a), q.b) for q in extra]
    )
    problem.anchor_points_in_a = np.concatenate(
        [problem.anchor_points_in_a] + [q.points_in_a for q in extra]
    )
    problem.anchor_pixels_b = np.concatenate(
        [problem.anchor_pixels_b] + [q.pixels_b for q in extra]
    )


@dataclass(frozen=True)
class _FarPair:
    """Keyframes a -> b (counted from a window's first) whose laser points are matched
    with the adjusted relative pose ``b_from_a`` ((4, 4), its translation ``length``
    mm)."""

    a: int
    b: int
    points_in_a: np.ndarray
    b_from_a: np.ndarray
    length: float


def _far_anchors(
    ctx: SfmContext, world_from_kf: np.ndarray, kf: Keyframes, first: int, fixed: int
) -> list[Anchor]:
    """Laser matches from keyframe k to k + 2 .. k + anchor_reach (adjusted relative
    poses), matched in the executor's workers, a bounded number at a time (each task
    holds two images, or for a local pool their files' paths); in (k, k + j) order. Both
    images of a pair (a, b) are divided by step a's flat field where the run has one
    (:mod:`omnipipe.sfm.flat_field`), as the steps' own Eq. 17 readings are.

    ``world_from_kf``: (W, 4, 4) the poses of keyframes ``first .. first + W - 1`` (an
    adjustment window; ``kf`` counts from keyframe 0); pairs of two of its first
    ``fixed`` keyframes (held fixed there) are left out. The anchors' keyframes count
    from ``first``.
    """
    config = ctx.config
    pairs = []
    for a in range(len(world_from_kf)):
        pts = kf.ring_points[first + a]
        if len(pts) == 0:
            continue
        for b in range(max(a + 2, fixed), min(a + config.anchor_reach, len(world_from_kf) - 1) + 1):
            b_from_a = invert(world_from_kf[b]) @ world_from_kf[a]
            length = float(np.linalg.norm(b_from_a[:3, 3]))
            if length >= 1e-6:
                pairs.append(_FarPair(a, b, pts, b_from_a, length))
    # The adjusted length is known to a few per cent: search only around it, so that a
    # periodic wall cannot offer the next course.
    w = math.exp(config.scale_check.agree_log)
    # A local pool's workers read the images themselves (the files' paths, not the pixels).
    shares = shares_files(ctx.executor)
    gray = kf.grays.ref if shares else kf.grays.__getitem__
    flats = kf.flats if kf.flats is not None else FlatFields()  # pair (a, b): step a's field
    jobs = (
        (
            gray(first + p.a),
            gray(first + p.b),
            ctx.camera,
            p.points_in_a,
            p.b_from_a[:3, :3],
            p.b_from_a[:3, 3] / p.length,
            config.laser_scale,
            (p.length / w, p.length * w),
            flats.for_worker(first + p.a, shares),
        )
        for p in pairs
    )
    out = []
    for p, lm in zip(pairs, ordered_map(ctx.executor, _laser_job, jobs), strict=True):
        if len(lm.index):
            out.append(Anchor(p.a, p.b, p.points_in_a[lm.index], lm.pixels_b, epipolar=True))
    return out


def _laser_job(job: tuple) -> LaserMatches:
    """Executor task: :func:`omnipipe.sfm.tasks.laser_matches` of one argument tuple,
    whose last item is the flat field both images are divided by first (or a reference
    to its file; None: none, :mod:`omnipipe.sfm.flat_field`)."""
    *args, flat = job
    field = as_field(flat)
    if field is None:
        return laser_matches(*args)
    return laser_matches(divided(args[0], field), divided(args[1], field), *args[2:])


@dataclass(frozen=True)
class Resected:
    """The moving frames that are not keyframes, placed.

    Attributes:
        world_from_rig: frame index -> its (4, 4) pose, mm.
        unreliable: the stretches around frames that could not be resected (their
            keyframe's pose is used).
    """

    world_from_rig: dict[int, np.ndarray]
    unreliable: list[UnreliableStretch]


def resect_pending(
    ctx: SfmContext,
    adjusted: Adjusted,
    kf: Keyframes,
    pending: list[PendingFrame],
    next_matches: dict[int, Future[KeyframeRays]],
    n_frames: int,
    travel_mm: np.ndarray | None = None,
    travel_source: str = "odometry",
    bridged_sigma_mm: dict[int, float] | None = None,
) -> Resected:
    """Every pending frame resected in the workers against the adjusted tracks of its
    keyframe k and of k + 1 (``next_matches``: its correspondences with k + 1),
    gathered in frame order. A frame that cannot be resected is placed between its
    keyframes at its fraction of ``travel_mm`` (the ``travel_source``'s cumulative
    travel, e.g. the odometry's or the gait's count of moving frames) or takes its
    keyframe's pose, with a warning, and the stretch from k to k + 1 is unreliable.

    ``bridged_sigma_mm``: keyframe k -> the 1-sigma (mm) of step k -> k + 1 when its
    length was bridged (vision's was not taken, e.g. the odometry overruled a step a
    wall period off). The frames inside such a step are placed at their fraction of
    ``travel_mm`` with the rotation slerped between the keyframes
    (:func:`omnipipe.geometry.interpolated_pose`): the wall points they would be resected against
    follow vision's wrong period. The resected pose is kept only where it agrees with
    that placement within the step's sigma. The step itself is flagged already.

    At most a few resections wait in the executor at a time (each holds its rays and
    points): what is held does not grow with the run's pending frames."""
    placed: dict[int, np.ndarray] = {}
    stretches: list[UnreliableStretch] = []
    inside = _BridgedPlacement(adjusted.world_from_kf, kf.frames, travel_mm, bridged_sigma_mm)
    jobs: deque[tuple[PendingFrame, Future | None]] = deque()
    most = 2 * parallelism(ctx.executor) + 2
    for p in pending:
        # The next keyframe's tracks too: points on both sides of the frame fix its
        # position better than the few tracks of one keyframe (a joints wall: 0.5-0.9 mm
        # off with one side's 15-40 points).
        # The window that adjusted keyframe k + 1 holds k too (its first keyframes are the
        # window before's last): both sides' tracks in one frame of reference.
        window_of = adjusted.window_of
        t = (
            adjusted.tracks[int(window_of[min(p.keyframe + 1, len(window_of) - 1)])]
            if adjusted.tracks
            else None
        )
        nxt = next_matches[p.frame].result() if t is not None and p.frame in next_matches else None
        job = None if t is None else _submit_resection(ctx, p, t, adjusted.world_from_kf, nxt)
        jobs.append((p, job))
        while len(jobs) > most:
            _place_pending(ctx, kf, *jobs.popleft(), inside, travel_mm, travel_source, n_frames, placed, stretches)
    while jobs:
        _place_pending(ctx, kf, *jobs.popleft(), inside, travel_mm, travel_source, n_frames, placed, stretches)
    ctx.warnings.extend(inside.summary(travel_source))
    return Resected(placed, stretches)


def _place_pending(
    ctx: SfmContext,
    kf: Keyframes,
    p: PendingFrame,
    job: Future | None,
    inside: _BridgedPlacement,
    travel_mm: np.ndarray | None,
    travel_source: str,
    n_frames: int,
    placed: dict[int, np.ndarray],
    stretches: list[UnreliableStretch],
) -> None:
    """Pending frame ``p``'s pose into ``placed``: its resection (``job``), or, when it
    could not be resected, placed between its keyframes (:func:`resect_pending`), its
    stretch into ``stretches``."""
    pose = inside.place(p.keyframe, p.frame, _resection_result(ctx, p.frame, job))
    if pose is None:
        k = p.keyframe
        pose, how = _unresected_pose(inside.world_from_kf, kf.frames, k, p.frame, travel_mm, travel_source)
        ctx.warnings.append(f"frame {p.frame}: too few tracked points to resect; {how}")
        # The steps into and out of it are both estimates.
        end = kf.frames[k + 1] if k + 1 < len(kf.frames) else n_frames - 1
        stretches.append(UnreliableStretch(kf.frames[k], end, "frame could not be resected"))
    placed[p.frame] = pose


class _BridgedPlacement:
    """The frames inside bridged keyframe steps, placed at their fraction of the
    travel (see :func:`resect_pending`); counts what was done per step."""

    def __init__(
        self,
        world_from_kf: np.ndarray,
        frames: list[int],
        travel_mm: np.ndarray | None,
        sigma_mm: dict[int, float] | None,
    ) -> None:
        self.world_from_kf, self.frames, self.travel = world_from_kf, frames, travel_mm
        self.sigma = sigma_mm or {}
        self.counts: dict[int, list[int]] = {}  # k -> [by travel, resection kept]

    def place(self, k: int, frame: int, resected: np.ndarray | None) -> np.ndarray | None:
        """The pose of ``frame`` (a frame after keyframe k): ``resected`` (None: not
        resected) unless step k was bridged and travel is known; then the travel's
        placement, or ``resected`` when it lies within the step's sigma of it."""
        sigma = self.sigma.get(k, math.nan)
        if self.travel is None or k + 1 >= len(self.frames) or not sigma > 0:
            return resected
        f = travel_fraction(self.travel, self.frames[k], self.frames[k + 1], frame)
        if f is None:
            return resected
        pose = interpolated_pose(self.world_from_kf[k], self.world_from_kf[k + 1], f)
        count = self.counts.setdefault(k, [0, 0])
        if resected is not None and np.linalg.norm(resected[:3, 3] - pose[:3, 3]) <= sigma:
            count[1] += 1
            return resected
        count[0] += 1
        return pose

    def summary(self, source: str) -> list[str]:
        """One warning per bridged step with frames inside it."""
        return [
            f"frames {self.frames[k]}->{self.frames[k + 1]}: length bridged; {n} frame(s) "
            f"inside placed at the {source}'s fraction of the step, {m} resected within "
            f"its {self.sigma[k]:.1f} mm sigma"
            for k, (n, m) in sorted(self.counts.items())
        ]


def travel_fraction(travel: np.ndarray, first: int, last: int, frame: int) -> float | None:
    """``frame``'s share (0..1) of the travel from frame ``first`` to ``last``
    (``travel`` (N,) cumulative, any unit); None when not finite or not increasing."""
    d0, d1, d = travel[first], travel[last], travel[frame]
    if not (np.isfinite([d0, d1, d]).all() and d1 - d0 > 0):
        return None
    return float(np.clip((d - d0) / (d1 - d0), 0.0, 1.0))


def _unresected_pose(
    world_from_kf: np.ndarray,
    frames: list[int],
    k: int,
    frame: int,
    travel_mm: np.ndarray | None,
    source: str = "odometry",
) -> tuple[np.ndarray, str]:
    """A frame that could not be resected: between keyframes k and k + 1 at the
    ``source``'s fraction of their travel (``travel_mm`` (N,) cumulative; mm for the
    odometry, any unit otherwise), rotation of keyframe k; past the last keyframe, the
    odometry's travel beyond it along the last step's direction (:func:`_beyond_last`);
    without travel (or past the last keyframe without odometry) keyframe k's pose.
    The pose and what was done, in words."""
    pose = world_from_kf[k].copy()
    if travel_mm is None:
        return pose, "pose of its keyframe used"
    if k + 1 >= len(frames):
        if source != "odometry":  # not a length
            return pose, "pose of its keyframe used"
        return _beyond_last(world_from_kf, frames, k, travel_mm[frame] - travel_mm[frames[k]])
    f = travel_fraction(travel_mm, frames[k], frames[k + 1], frame)
    if f is None:
        return pose, "pose of its keyframe used"
    pose[:3, 3] = (1 - f) * world_from_kf[k][:3, 3] + f * world_from_kf[k + 1][:3, 3]
    return pose, f"placed between its keyframes at the {source}'s fraction {f:.2f}"


def _beyond_last(
    world_from_kf: np.ndarray, frames: list[int], k: int, travel_mm: float
) -> tuple[np.ndarray, str]:
    """A frame after the last keyframe k, ``travel_mm`` (odometry, mm) beyond it: moved
    that far along the last keyframe step's direction (the rig's +z axis when k is the
    only keyframe), rotation of keyframe k. The pose and what was done, in words."""
    pose = world_from_kf[k].copy()
    if not np.isfinite(travel_mm):
        return pose, "pose of its keyframe used"
    step = world_from_kf[k][:3, 3] - world_from_kf[k - 1][:3, 3] if k > 0 else np.zeros(3)
    norm = float(np.linalg.norm(step))
    direction = step / norm if norm > 1e-9 else world_from_kf[k][:3, 2]
    pose[:3, 3] += max(float(travel_mm), 0.0) * direction
    return pose, f"placed {travel_mm:.1f} mm beyond its keyframe by the odometry"


def _submit_resection(
    ctx: SfmContext,
    frame: PendingFrame,
    tracks: WindowTracks,
    world_from_kf: np.ndarray,
    next_matches: KeyframeRays | None,
) -> Future | None:
    """Resection of a non-keyframe from its matches to the tracks of keyframes k and k + 1
    (of the window ``tracks``; ``world_from_kf`` (K, 4, 4) all keyframes' poses),
    submitted to the executor (None: too few tracked points).

    ``frame.inliers``: RANSAC-verified matches to keyframe k; ``next_matches``: the
    frame's correspondences with keyframe k + 1 from descriptor matching or tracking,
    verified by the resection itself (rays more than 2 deg off are refitted without).
    """
    k = frame.keyframe - tracks.first  # counted from the window's first keyframe
    inl = frame.inliers
    sides: list[tuple[int, np.ndarray, np.ndarray]] = []
    if inl is not None and len(inl):
        sides.append((k, inl[:, 0], frame.features.rays_in_rig[inl[:, 1]]))
    if next_matches is not None and len(next_matches.feature):
        sides.append((k + 1, next_matches.feature, next_matches.rays_in_rig))
    rays, points = [], []
    for kk, idx, frame_rays in sides:
        if kk >= len(tracks.feature_point):
            continue
        pid = tracks.feature_point[kk][idx]
        ok = pid >= 0
        rays.append(frame_rays[ok])
        points.append(tracks.points_in_world[pid[ok]])
    n_first = len(points[0]) if points and inl is not None and len(inl) else 0
    if (
        rays
        and sum(len(r) for r in rays) >= MIN_RESECTION_POINTS
        and n_first >= MIN_RESECTION_POINTS_OWN_SIDE
    ):
        return ctx.executor.submit(
            resect_rays,
            np.concatenate(rays),
            np.concatenate(points),
            world_from_kf[tracks.first + k],
        )
    return None


def _resection_result(ctx: SfmContext, frame: int, job: Future | None) -> np.ndarray | None:
    """The pose of a non-keyframe from :func:`_submit_resection`; None (with a warning
    when the resection failed) when it could not be resected."""
    if job is not None:
        try:
            return job.result()
        except ReconstructionError as exc:
            ctx.warnings.append(f"frame {frame}: {exc}")
    return None

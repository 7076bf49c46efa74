"""End to end: light section + camera motion on a short simulated stop-and-go run."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from omnipipe.evaluation.trajectory import trajectory_errors
from omnipipe.laser import LaserConfig, LaserResult
from omnipipe.laser import run as laser_run
from omnipipe.sfm import SfmConfig, SfmInputs
from omnipipe.sfm import run as sfm_run
from omnipipe.sfm.robot_sensors import bridge_estimate
from omnipipe.sfm.scale_check import StepCheck
from omnipipe.sfm.step_scale import bridge_lost_steps, bridge_steps, confirmed_candidates
from omnipipe.sfm.tracking import TrackConfig
from omnipipe.sfm.types import StepEvidence
from omnipipe.sim import make_scenario
from omnipipe.sim.scenario import Scenario
from omnipipe.sim.writer import build_renderer


@pytest.fixture(scope="module")
def short_run() -> Callable[[str], tuple[Scenario, np.ndarray, np.ndarray, list[np.ndarray], LaserResult]]:
    """``short_run(name)``: (scenario, true poses, moving, frames, rings) of a 20-frame run at
    640x480 (seed 1), rendered once per scenario for the module."""
    made: dict[str, tuple[Scenario, np.ndarray, np.ndarray, list[np.ndarray], LaserResult]] = {}

    def get(name: str) -> tuple[Scenario, np.ndarray, np.ndarray, list[np.ndarray], LaserResult]:
        if name not in made:
            # The small variants sample the gait coarsely (8 frames per cycle): 60 mm in 20 frames.
            scenario = make_scenario(name, frames=20, size=(640, 480), seed=1)
            renderer, poses, _, moving = build_renderer(scenario)
            frames, irradiance = [], None
            for i, p in enumerate(poses):
                if i == 0 or moving[i]:  # a standing robot sees the same scene: new sensor noise only
                    irradiance = renderer.irradiance(p, seed=50 + i)[0]
                frames.append(renderer.expose(irradiance, seed=50 + i))
            made[name] = (scenario, poses, moving, frames, laser_run(LaserConfig(), scenario.rig, frames))
        return made[name]

    return get


# bend-small and tracking off: 5 s each; paper-small with tracking keeps the sfm stage
# covered end to end under -m 'not slow'.
@pytest.mark.parametrize(
    ("name", "tracking"),
    [
        ("paper-small", True),
        pytest.param("bend-small", True, marks=pytest.mark.slow),
        pytest.param("paper-small", False, marks=pytest.mark.slow),
    ],
)
def test_short_run_trajectory_within_band(short_run, name: str, tracking: bool) -> None:
    scenario, poses, moving, frames, rings = short_run(name)
    # With tracking, the frames between keyframes are followed by optical flow; without,
    # every moving frame gets SIFT: the same bands.
    config = SfmConfig(tracking=TrackConfig(enabled=tracking))
    res = sfm_run(config, SfmInputs(scenario.rig, lambda i: frames[i], len(frames), rings))
    assert np.all(np.isfinite(res.world_from_rig))
    # Stops are found: every truly stationary frame shares its station's pose.
    assert np.array_equal(res.stationary[1:], ~moving[1:])
    errs = trajectory_errors(res.world_from_rig, poses)
    print(name, errs.to_dict())
    assert errs.path_length_mm > 50
    assert errs.ate_rmse_mm < 1.0  # mm over ~60 mm of travel at 640x480
    # Each step's laser scale is good to a few tenths of a mm at 640x480 (2-4 % of a
    # 12 mm step); full size: 0.4 % over 300 mm (benchmarks/bench_sfm.py, omnipipe demo).
    assert errs.scale_error < 0.05
    assert errs.rotation_rmse_deg < 0.3


def test_combine_scales_weights_and_widens_on_disagreement() -> None:
    from omnipipe.sfm.step_scale import combine_scales

    # Agreeing sources of equal sigma: the mean, sigma / sqrt(2).
    mean, sigma = combine_scales(0.001, 0.001, 0.001, wall_anchored=False)
    assert mean == pytest.approx(0.0005) and sigma == pytest.approx(0.001 / np.sqrt(2))
    # A precise wall against a vague laser: mostly the wall.
    mean, _ = combine_scales(-0.004, 0.001, 0.004, wall_anchored=False)
    assert -0.004 < mean < -0.0035
    # Disagreement beyond both sigmas widens the stated sigma (never hides it): the
    # gap between the sources is then within 3 combined sigmas of either source.
    mean, sigma = combine_scales(-0.02, 0.001, 0.001, wall_anchored=False)
    assert sigma > 0.001 and abs(mean - 0.0) < 3 * sigma and abs(mean + 0.02) < 3 * sigma
    # A wall-anchored run: one source, taken as is.
    assert combine_scales(0.003, 0.002, 0.0005, wall_anchored=True) == (0.003, 0.002)


def test_a_step_without_relative_motion_takes_the_typical_step() -> None:
    """A lost step (no relative motion found) is chained with the gait's estimate (the
    run's trusted steps), not as zero length: the positions after it are not
    shortened by a whole step; the estimate carries a sigma covering the true 10 mm."""
    rng = np.random.default_rng(3)
    steps, evidence, checks = [], [], []
    for k in range(7):
        lost = k in (3, 4)
        t = np.eye(4)
        if not lost:
            t[:3, 3] = [rng.normal(0, 0.1), rng.normal(0, 0.1), -10.0 + rng.normal(0, 0.2)]
        steps.append(t)
        evidence.append(StepEvidence.unmeasured(k, k + 1, t, None, "lost" if lost else "ok"))
        checks.append(
            StepCheck(k, k + 1, 10.0, 0.0, 10.0, 50, math.nan if lost else 10.0, "none" if lost else "high")
        )
    lengths = np.array([np.nan if k in (3, 4) else np.linalg.norm(t[:3, 3]) for k, t in enumerate(steps)])
    lengths, checks, _ = bridge_steps(lengths, checks, None)
    bridge_lost_steps(steps, evidence, checks, lengths)
    for k in (3, 4):
        c = checks[k]
        assert c.bridged_from == "gait" and not c.reliable
        assert 0 < c.bridged_sigma_mm < 3.0 and abs(c.bridged_mm - 10.0) <= 2 * c.bridged_sigma_mm
        assert np.allclose(steps[k][:3, :3], np.eye(3))
        assert abs(steps[k][2, 3] + 10.0) < 0.3 and np.hypot(*steps[k][:2, 3]) < 0.2
    assert steps[0][2, 3] != steps[3][2, 3]  # trusted steps untouched


@pytest.mark.slow  # 6 s: 40 frames at 640x480; tracking stays covered by the short runs above
def test_frames_between_keyframes_are_tracked_and_placed_within_band() -> None:
    # The full gait (24 frames per cycle): several moving frames per keyframe step.
    scenario = make_scenario("paper", frames=40, size=(640, 480), seed=1)
    renderer, poses, _, moving = build_renderer(scenario)
    frames, irradiance = [], None
    for i, p in enumerate(poses):
        if i == 0 or moving[i]:
            irradiance = renderer.irradiance(p, seed=50 + i)[0]
        frames.append(renderer.expose(irradiance, seed=50 + i))
    rings = laser_run(LaserConfig(), scenario.rig, frames)
    res = sfm_run(SfmConfig(), SfmInputs(scenario.rig, lambda i: frames[i], len(frames), rings))
    assert res.tracked is not None
    # Tracked frames are moving frames that are not keyframes (resected from their tracks).
    assert res.tracked.sum() >= 4
    assert not np.any(res.tracked & res.keyframe)
    assert np.all(moving[res.tracked])
    errs = trajectory_errors(res.world_from_rig, poses)
    print(errs.to_dict(), int(res.tracked.sum()), int(res.keyframe.sum()))
    assert errs.ate_rmse_mm < 0.5  # mm over 50 mm of travel at 640x480 (measured 0.23)
    assert errs.ate_max_mm < 1.0
    assert errs.scale_error < 0.05


def test_periodic_alias_one_period_too_long_is_rejected_by_the_gait() -> None:
    """Bricks every 14 mm, the robot steps ~4 mm: the laser's best consensus peak is
    one course too long (18.1 mm), its second is right (4.2 mm). The trusted
    steps' gait (bridge_estimate) confirms the right one and excludes the alias; with
    no trusted neighbours nothing is decided."""
    rng = np.random.default_rng(5)
    truth = 4.0 + rng.normal(0, 0.2, 12)
    lengths = truth.copy()
    lengths[6] = np.nan  # the ambiguous step
    trusted = np.isfinite(lengths)
    prior, sigma, source = bridge_estimate(6, lengths, trusted, None)
    assert source == "gait" and abs(prior - truth[6]) <= 2 * sigma
    candidates = np.array([truth[6] + 14.0, truth[6] + 0.1])  # alias first: it scored best
    near = confirmed_candidates(candidates, prior, sigma, agree_log=0.1)
    assert near is not None and list(near) == [1]
    assert abs(candidates[near[0]] - truth[6]) < 0.2
    # Two candidates a period apart both near a vague prior: undecided, stays flagged.
    assert confirmed_candidates(np.array([4.0, 18.0]), 11.0, 5.0, 0.1) is None
    # No trusted neighbour: no prior at all.
    assert bridge_estimate(6, lengths, np.zeros(12, bool), None)[2] == ""


def test_bridged_step_from_odometry_covers_the_truth() -> None:
    """Odometry with a 2.5 % slip: calibrated on the trusted steps, a lost step's bridged
    length is non-zero and its sigma covers the true length."""
    from omnipipe.inputs.sensors import make_odometry
    from omnipipe.sfm.robot_sensors import calibrate_odometry, odometry_steps

    rng = np.random.default_rng(7)
    truth = 5.0 + rng.normal(0, 0.5, 20)  # keyframe steps, mm
    frames = list(range(0, 41, 2))
    times = np.arange(41) * 0.1
    travel = np.concatenate([[0.0], np.cumsum(np.repeat(truth / 2, 2))])
    counted = np.round(travel * 1.025 + rng.normal(0, 0.05, len(travel)).cumsum() * 0.1, 1)
    counted = np.maximum.accumulate(counted)
    sigma = np.hypot(0.03 * counted, 0.03)
    odo = make_odometry("test", times, counted, sigma, str)
    steps = odometry_steps(odo, times, frames)
    vision = truth * (1 + rng.normal(0, 0.002, 20))
    trusted = np.ones(20, bool)
    trusted[9] = False
    steps = calibrate_odometry(steps, vision, trusted)
    assert steps.calibrated and abs(math.exp(-steps.ratio_log) - 1.025) < 0.01
    est, sig, source = bridge_estimate(9, np.where(trusted, vision, np.nan), trusted, steps)
    assert source == "odometry" and est > 0 and 0 < sig < 0.5
    assert abs(est - truth[9]) <= 2 * sig


@pytest.mark.parametrize("with_odometry", [False, True])
def test_run_ending_mid_stroke_on_stationary_frames_closes_on_the_last_moving_frame(with_odometry: bool) -> None:
    """The robot stops after 4 moving frames (frame 4 too little parallax after keyframe
    3 to be a keyframe by itself) and stands for 3 frames: the last *moving* frame is
    the closing keyframe (sfm.keyframe_loop.KeyframeLoop.finish), the stationary frames
    share its pose, and no stretch is left unresected (without the closing keyframe:
    2 keyframes, no adjustment, frame 4 placed by the gait, flagged, ATE 3.7 mm).
    With the robot's odometry too: the wall has texture there (random-wide seed 1s, a
    963 mm pipe whose 28 mm never made a second keyframe: every frame was left to the
    odometry and flagged "frame could not be resected")."""
    from omnipipe.inputs.sensors import make_odometry

    scenario = make_scenario("paper", frames=40, size=(400, 300), seed=1)  # 8 rendered
    renderer, poses, _, moving = build_renderer(scenario)
    assert np.all(moving[1:5])  # the first stroke's first four frames move
    idx = [0, 1, 2, 3, 4, 4, 4, 4]  # then the robot stands at frame 4's pose
    frames, irradiance = [], None
    for j, i in enumerate(idx):
        if j == 0 or j == i:
            irradiance = renderer.irradiance(poses[i], seed=50 + i)[0]
        frames.append(renderer.expose(irradiance, seed=50 + j))  # new sensor noise
    rings = laser_run(LaserConfig(), scenario.rig, frames)
    inputs = SfmInputs(scenario.rig, lambda i: frames[i], len(frames), rings)
    if with_odometry:  # 2 % slip, 0.1 mm counts, read at the frames' times
        times = np.arange(len(idx)) * 0.25
        travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[idx][:, :3, 3], axis=0), axis=1))])
        counted = np.round(travel * 1.02, 1)
        odo = make_odometry("test", times, counted, np.hypot(0.03 * counted, 0.03), str)
        inputs = SfmInputs(scenario.rig, lambda i: frames[i], len(frames), rings, timestamps=times, odometry=odo)
    res = sfm_run(SfmConfig(), inputs)
    assert res.keyframe[4] and not res.keyframe[5:].any()
    assert res.registered.all()
    assert not [u for u in res.unreliable if "resected" in u.reason]
    assert np.allclose(res.world_from_rig[5:], res.world_from_rig[4])
    errs = trajectory_errors(res.world_from_rig, poses[idx])
    assert errs.ate_rmse_mm < 0.5  # mm over 18 mm of travel at 400x300 (measured 0.17)


def test_steps_a_course_off_are_contradicted_by_the_odometry_and_bridged() -> None:
    """Tiles 7.7 mm apart, 8.4 mm a frame: laser and feature depths agree on a wrong
    course at 4 of 9 keyframe steps (a course short). The odometry's ratio (3 % slip)
    comes from the consensus of the right steps (not the median, pulled to 1.4 by the
    wrong ones); the wrong steps are contradicted, and bridged from the odometry with a
    sigma covering the truth; the right ones stay trusted."""
    from omnipipe.inputs.sensors import make_odometry
    from omnipipe.sfm.robot_sensors import calibrate_odometry, odometry_contradicts, odometry_steps

    rng = np.random.default_rng(11)
    truth = np.array([8.4, 33.2, 16.1, 8.1, 7.8, 15.7, 7.8, 33.3, 10.9])
    frames = list(range(len(truth) + 1))
    times = np.arange(len(frames)) * 0.5
    counted = np.concatenate([[0.0], np.cumsum(truth)]) * 0.97 + rng.normal(0, 0.05, len(frames))
    odo = make_odometry("test", times, np.maximum.accumulate(counted), np.hypot(0.03 * counted, 0.05), str)
    vision = truth.copy()
    wrong = np.array([1, 2, 5, 7])
    vision[wrong] = np.array([10.1, 7.7, 8.0, 7.8])
    steps = calibrate_odometry(odometry_steps(odo, times, frames), vision, np.ones(len(truth), bool))
    assert steps.calibrated and abs(math.exp(steps.ratio_log) - 1 / 0.97) < 0.01
    said = [bool(odometry_contradicts(steps, k, float(v))) for k, v in enumerate(vision)]
    assert [k for k, s in enumerate(said) if s] == wrong.tolist()
    # The odometry's own excursion (seed 4: 17 % over a right 7.9 mm step, 5 sigma) is
    # no wrong course.
    est0, _ = steps.estimate(0)
    assert not odometry_contradicts(steps, 0, est0 / 1.17)
    lengths = np.where(said, np.nan, vision)
    for k in wrong:
        est, sig, source = bridge_estimate(int(k), lengths, ~np.array(said), steps)
        assert source == "odometry" and abs(est - truth[k]) <= 2 * sig


@pytest.mark.slow  # 4 frames rendered at 400x300 and a whole sfm.run
def test_frames_between_the_only_two_keyframes_are_resected() -> None:
    """Four moving frames of which only the first and the last (closing) are keyframes:
    the bundle adjustment of the two leaves the tracks the two frames between them are
    resected against (without it they were placed by the gait and flagged)."""
    scenario = make_scenario("paper", frames=40, size=(400, 300), seed=1)
    renderer, poses, _, moving = build_renderer(scenario)
    assert np.all(moving[1:4])
    frames = [renderer.expose(renderer.irradiance(poses[i], seed=50 + i)[0], seed=50 + i) for i in range(4)]
    rings = laser_run(LaserConfig(), scenario.rig, frames)
    res = sfm_run(SfmConfig(), SfmInputs(scenario.rig, lambda i: frames[i], len(frames), rings))
    assert np.flatnonzero(res.keyframe).tolist() == [0, 3]
    assert res.registered.all()
    assert not [u for u in res.unreliable if "resected" in u.reason]
    errs = trajectory_errors(res.world_from_rig, poses[:4])
    assert errs.ate_rmse_mm < 0.3, errs.ate_rmse_mm  # mm over about 13 mm of travel


@pytest.mark.slow  # two sfm runs of 20 frames at 640x480
def test_keyframe_arrays_wait_on_disk_with_the_same_result(short_run, monkeypatch) -> None:
    """What the frame loop keeps for the adjustment and the resection (the slimmed
    features of every keyframe but the last and of the pending frames, the steps'
    matches, the keyframes' ring points) waits in the run's scratch
    (:class:`omnipipe.spill.Pack`), and the run's poses are those of a run that keeps
    them in memory, bit for bit."""
    from omnipipe.sfm import keyframe_loop, keyframes, pipeline
    from omnipipe.spill import is_on_disk

    scenario, _, _, frames, rings = short_run("paper-small")
    seen = []

    def follow(*args, **kwargs):
        got = keyframes.follow_keyframes(*args, **kwargs)
        seen.append(got)
        return got

    monkeypatch.setattr(pipeline, "follow_keyframes", follow)
    inputs = SfmInputs(scenario.rig, lambda i: frames[i], len(frames), rings)
    on_disk = sfm_run(SfmConfig(), inputs)
    kf = seen[0].keyframes
    assert len(kf.frames) >= 3
    for f in kf.features[:-1] + [p.features for p in seen[0].pending]:
        assert is_on_disk(f.rays_in_rig) and is_on_disk(f.pixels) and is_on_disk(f.view)
        assert len(f.descriptors) == 0
    assert all(is_on_disk(p) for p in kf.ring_points if len(p))
    assert all(is_on_disk(e.inliers) for e in kf.evidence if e.inliers is not None and len(e.inliers))

    class InMemory:
        def put(self, a: np.ndarray) -> np.ndarray:
            return np.array(a)

    monkeypatch.setattr(keyframe_loop, "Pack", InMemory)
    in_memory = sfm_run(SfmConfig(), inputs)
    assert np.array_equal(on_disk.world_from_rig, in_memory.world_from_rig)
    assert np.array_equal(on_disk.registered, in_memory.registered)


def test_a_frame_without_a_ring_reads_the_nearest_frames_wall() -> None:
    """reconstruct's decoding pass extracts no ring at a frame it takes for standing: the
    wall's shift there uses the nearest frame's wall (ties: the earlier); each frame with
    a ring keeps its own; no ring anywhere: None."""
    from types import SimpleNamespace

    from omnipipe.sfm.pipeline import nearest_wall

    rng = np.random.default_rng(3)

    def ring(radius: float) -> SimpleNamespace:
        a = rng.uniform(0, 2 * np.pi, 200)
        xyz = np.column_stack([radius * np.cos(a), radius * np.sin(a), np.full(200, 50.0)])
        return SimpleNamespace(points_in_rig=xyz)

    empty = SimpleNamespace(points_in_rig=np.zeros((0, 3)))
    rings = [ring(100.0), empty, empty, ring(110.0), empty]
    read = nearest_wall(rings)
    radii = [read(i).radius_mm for i in range(5)]
    assert np.allclose(radii, [100.0, 100.0, 110.0, 110.0, 110.0], atol=1e-9)
    assert nearest_wall([empty, empty])(1) is None


@pytest.mark.slow  # two sfm runs of 20 moving frames at 640x480
def test_the_frames_followed_back_get_the_chains_flow_images_and_the_same_poses(short_run, monkeypatch) -> None:
    """The frames followed back are sent with the flow images the frame loop's chain
    made of them (not made again in the worker): every frame has them, and the run's
    poses are those of a worker making its own, bit for bit."""
    from omnipipe.sfm import pending_matches

    scenario, _, _, frames, rings = short_run("continuous")  # every frame moves
    inputs = SfmInputs(scenario.rig, lambda i: frames[i], len(frames), rings)
    track_back = pending_matches.track_back
    given: list[bool] = []

    def own(rig, config, views, features, which, pending, tracking, key_images, images):
        given.extend([key_images is not None] + [i is not None for i in images])
        return track_back(rig, config, views, features, which, pending, tracking)

    monkeypatch.setattr(pending_matches, "track_back", own)
    made = sfm_run(SfmConfig(), inputs)
    monkeypatch.undo()
    sent = sfm_run(SfmConfig(), inputs)
    assert given and all(given)
    assert np.array_equal(made.world_from_rig, sent.world_from_rig)
    assert np.array_equal(made.registered, sent.registered)


@pytest.mark.slow  # two sfm runs of 20 moving frames at 640x480
def test_following_back_only_the_matched_features_gives_the_poses_of_following_all(short_run, monkeypatch) -> None:
    """The next keyframe's features followed back through the pending frames are only
    those its steps matched (the adjustment's tracks are made of them): fewer features
    followed, and the run's poses those of following every one within the budget, bit
    for bit."""
    from omnipipe.sfm import pending_matches

    scenario, _, _, frames, rings = short_run("continuous")  # every frame moves
    inputs = SfmInputs(scenario.rig, lambda i: frames[i], len(frames), rings)
    followed: list[int] = []
    track_back = pending_matches.track_back

    def counted(rig, config, views, features, which, pending, tracking, *images):
        followed.append(len(which) * len(pending))
        return track_back(rig, config, views, features, which, pending, tracking, *images)

    monkeypatch.setattr(pending_matches, "track_back", counted)
    narrowed = sfm_run(SfmConfig(), inputs)
    n_narrowed = sum(followed)
    followed.clear()
    monkeypatch.setattr(pending_matches, "matched_only", lambda which, matched: which)
    every = sfm_run(SfmConfig(), inputs)
    assert 0 < n_narrowed < sum(followed)
    assert np.array_equal(narrowed.world_from_rig, every.world_from_rig)
    assert np.array_equal(narrowed.registered, every.registered)

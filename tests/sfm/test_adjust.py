"""The frames between keyframes (sfm/adjust.py: resect_pending)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from omnipipe.executor import InlineExecutor
from omnipipe.sfm.adjust import Adjusted, _along_only, _BridgedPlacement, resect_pending
from omnipipe.sfm.bundle import BundleConfig
from omnipipe.sfm.types import Anchor, Keyframes, PairMatches, PendingFrame, SfmConfig, SfmContext


def _bridged_step(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """Keyframes at frames 0 and 6, 33.2 mm apart along z with a 4 deg roll between them,
    frames 1-5 at an uneven pace (seeded); odometry = true travel + 0.1 mm noise.
    Returns the (2, 4, 4) keyframe poses, the (7, 4, 4) true poses, the (7,) odometry
    and the keyframes' frames."""
    rng = np.random.default_rng(seed)
    travel = np.concatenate([[0.0], np.cumsum(rng.uniform(1.0, 10.0, 6))])
    travel *= 33.2 / travel[-1]
    roll = np.deg2rad(4.0) * travel / travel[-1]
    truth = np.tile(np.eye(4), (7, 1, 1))
    truth[:, :3, :3] = Rotation.from_rotvec(np.outer(roll, [0.0, 0.0, 1.0])).as_matrix()
    truth[:, 2, 3] = travel
    odometry = travel + rng.normal(0.0, 0.1, 7)
    odometry[0], odometry[6] = travel[0], travel[6]
    return truth[[0, 6]], truth, odometry, [0, 6]


def test_bridged_step_inner_frames_follow_the_odometry_not_the_wall() -> None:
    """A step the odometry overruled (sigma 1 mm): its inner frames, not resected, land
    at the odometry's share of it within the sigma of the truth, rotation slerped
    (< 0.05 deg off); one warning names the step."""
    world_from_kf, truth, odometry, frames = _bridged_step(seed=22)
    ctx = SfmContext(SfmConfig(), None, None, InlineExecutor(), False, [])  # type: ignore[arg-type]
    adjusted = Adjusted(world_from_kf, [], np.zeros(2, int), [])
    kf = Keyframes(frames, [], None, [], [])  # type: ignore[arg-type]
    pending = [PendingFrame(f, 0, None, None) for f in range(1, 6)]  # type: ignore[arg-type]
    out = resect_pending(ctx, adjusted, kf, pending, {}, 7, odometry, "odometry", {0: 1.0})
    for f in range(1, 6):
        pose = out.world_from_rig[f]
        assert np.linalg.norm(pose[:3, 3] - truth[f][:3, 3]) < 1.0
        angle = Rotation.from_matrix(pose[:3, :3].T @ truth[f][:3, :3]).magnitude()
        assert np.rad2deg(angle) < 0.05
    assert not out.unreliable  # the step itself is flagged already
    assert any("5 frame(s) inside placed at the odometry's fraction" in w for w in ctx.warnings)


def test_bridged_step_keeps_a_resection_only_within_the_step_sigma() -> None:
    """A resection a tile (11.8 mm) off is replaced by the odometry's placement; one
    0.3 mm off (within the 1 mm sigma) is kept; outside bridged steps the resection is
    untouched."""
    world_from_kf, truth, odometry, frames = _bridged_step(seed=5)
    place = _BridgedPlacement(world_from_kf, frames, odometry, {0: 1.0})
    wrong, near = truth[3].copy(), truth[3].copy()
    wrong[2, 3] -= 11.8
    near[0, 3] += 0.3
    got = place.place(0, 3, wrong)
    assert got is not None and np.linalg.norm(got[:3, 3] - truth[3][:3, 3]) < 1.0
    assert place.place(0, 3, near) is near
    assert _BridgedPlacement(world_from_kf, frames, odometry, {}).place(0, 3, wrong) is wrong
    assert _BridgedPlacement(world_from_kf, frames, None, {0: 1.0}).place(0, 3, wrong) is wrong


def test_anchors_measured_along_their_curve_only_across_well_matched_steps() -> None:
    """A laser anchor keeps only its along-curve component where every step it spans
    had >= along_min_matches (50) RANSAC inliers (the features fix the steps' directions); across a step
    with fewer (a plain wall) the across component stays. Wall-placed features (not
    epipolar) stay 2-D."""
    pairs = [PairMatches(k, k + 1, np.zeros((n, 2), int)) for k, n in enumerate([400, 50, 42, 300])]
    pts, px = np.zeros((3, 3)), np.zeros((3, 2))
    anchors = [
        Anchor(0, 1, pts, px, epipolar=True),
        Anchor(0, 2, pts, px, epipolar=True),  # 400 and 50
        Anchor(1, 3, pts, px, epipolar=True),  # spans the 42-match step
        Anchor(2, 3, pts, px, epipolar=True),
        Anchor(3, 4, pts, px, epipolar=True),
        Anchor(3, 4, pts, px),  # a wall-placed feature
        Anchor(4, 5, pts, px, epipolar=True),  # no step recorded
    ]
    out = _along_only(anchors, pairs, BundleConfig().along_min_matches)
    assert [q.epipolar for q in out] == [True, True, False, False, True, False, False]
    assert [q.epipolar for q in _along_only(anchors, pairs, 0)] == [True] * 5 + [False, True]
    assert [q.epipolar for q in _along_only(anchors, pairs, 51)] == [True, False, False, False, True, False, False]
    assert all(q.a == a.a and q.b == a.b and q.points_in_a is a.points_in_a for q, a in zip(out, anchors, strict=True))

"""The window of steps around a step: its pace against its neighbours' (gait)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from omnipipe.sfm.scale_check import ScaleCheckConfig, StepCheck
from omnipipe.sfm.step_scale import check_adjusted
from omnipipe.sfm.step_window import gait_agrees, moving_counts, window_pace

CFG = ScaleCheckConfig()


def test_moving_counts_skip_the_standstills() -> None:
    moved = np.array([1, 1, 1, 0, 0, 1, 1, 0, 1], bool)
    assert moving_counts(moved, [0, 2, 6, 8]).tolist() == [2, 2, 1]


def test_a_step_one_course_off_does_not_agree_with_the_gait() -> None:
    """Steps of 3 moving frames at 5 mm/frame; on a 10 mm brick wall the wrong course
    makes a step 25 mm instead of 15: its pace is off by 67 %, the right one agrees."""
    rng = np.random.default_rng(3)
    counts = np.full(9, 3)
    lengths = 15.0 * (1 + rng.uniform(-0.15, 0.15, 9))
    trusted = np.ones(9, bool)
    trusted[4] = False
    assert window_pace(4, lengths, trusted, counts)[1] == 8
    assert gait_agrees(4, 15.4, lengths, trusted, counts)
    assert not gait_agrees(4, 25.4, lengths, trusted, counts)
    assert not gait_agrees(4, 5.4, lengths, trusted, counts)
    # A step covering twice the moving frames may be twice as long.
    counts[4] = 6
    assert gait_agrees(4, 30.0, lengths, trusted, counts)
    # Without trusted neighbours the window cannot tell.
    assert not gait_agrees(4, 15.0, lengths, np.zeros(9, bool), counts)


def _check(k: int, length: float) -> StepCheck:
    return StepCheck(k, k + 1, length, 0.1, length, 50, length, "high")


@pytest.mark.parametrize(("moved_mm", "flagged"), [(0.5, False), (1.2, True)])
def test_an_adjusted_step_further_than_a_millimetre_from_its_sources_is_flagged(
    moved_mm: float, flagged: bool
) -> None:
    """A 35 mm step the adjustment moved 1.2 mm (3.4 %: under the relative limit) is
    flagged; 0.5 mm is not."""
    lengths = np.full(8, 35.0)
    checks = [_check(k, float(v)) for k, v in enumerate(lengths)]
    adjusted = lengths.copy()
    adjusted[3] += moved_mm
    adjusted[4] -= moved_mm
    world = np.tile(np.eye(4), (9, 1, 1))
    world[1:, 2, 3] = np.cumsum(adjusted)
    out = check_adjusted(checks, world, CFG)
    assert (not out[3].reliable) is flagged and (not out[4].reliable) is flagged
    assert all(c.reliable for k, c in enumerate(out) if k not in (3, 4))
    if flagged:
        assert "mm from the nearest" in out[3].reason
    assert math.isfinite(out[0].scale_mm)





def test_an_unresected_frame_is_placed_by_the_gait_not_left_at_its_keyframe() -> None:
    """Keyframes 0 and 8 (30 mm apart), frames 1-8 all moving: frame 2, not resected, is
    placed at 2/8 of the step by the count of moving frames (true 7.5 mm at an even
    pace), said so; without any travel it keeps keyframe 0's pose."""
    from omnipipe.sfm.adjust import _unresected_pose

    world = np.tile(np.eye(4), (2, 1, 1))
    world[1, 2, 3] = 30.0
    moved = np.ones(9, bool)
    pose, how = _unresected_pose(world, [0, 8], 0, 2, np.cumsum(moved).astype(float), "gait")
    assert pose[2, 3] == pytest.approx(7.5) and "gait's fraction 0.25" in how
    pose, how = _unresected_pose(world, [0, 8], 0, 2, None)
    assert pose[2, 3] == 0.0 and "keyframe" in how


def test_check_adjusted_compares_decided_lengths_in_the_chain_s_units() -> None:
    """A wall-anchored run (laser 13 % short of the feature depths, 3 steps: too few
    for a run-wide offset): the decided lengths are in laser units; given that unit no
    right step is flagged, without it every one would be."""
    lengths = np.array([21.4, 20.6, 4.9])
    gain = math.exp(-0.145)
    checks = [
        StepCheck(k, k + 1, v * gain, 0.9, v, 500, v * gain, "high") for k, v in enumerate(lengths)
    ]
    world = np.tile(np.eye(4), (4, 1, 1))
    world[1:, 2, 3] = np.cumsum(lengths * 0.98)
    assert all(c.reliable for c in check_adjusted(checks, world, CFG, gain))
    assert not any(c.reliable for c in check_adjusted(checks, world, CFG)[:2])


@pytest.mark.parametrize(
    ("feature_mm", "matches", "wall_anchored", "flagged"),
    [
        (12.02, 700, False, False),
        (12.02, 20, False, True),
        (10.7, 700, False, True),
        (12.02, 700, True, True),
    ],
)
def test_an_adjusted_step_that_is_its_feature_depths_length_is_not_flagged(
    feature_mm: float, matches: int, wall_anchored: bool, flagged: bool
) -> None:
    """Eight 12 mm steps; step 3 was decided on a laser length 1.4 mm short (11 %): the
    adjustment put it back at 12 mm, where its feature depths (700 matches) measured it:
    confirmed, not flagged. With 20 feature matches, feature depths agreeing with the
    short laser length instead, or a wall-anchored run (the feature depths are what its
    anchors used, no independent measurement) it is flagged."""
    lengths = np.full(8, 12.0)
    checks = [_check(k, float(v)) for k, v in enumerate(lengths)]
    checks[3] = StepCheck(3, 4, 10.6, 0.9, feature_mm, matches, 10.6, "high")
    world = np.tile(np.eye(4), (9, 1, 1))
    world[1:, 2, 3] = np.cumsum(lengths)
    out = check_adjusted(checks, world, CFG, feature_unit=None if wall_anchored else 1.0)
    assert (not out[3].reliable) is flagged
    assert all(c.reliable for k, c in enumerate(out) if k != 3)


def test_feature_depths_confirm_in_the_chain_s_units() -> None:
    """Three steps (too few for the feature depths' run-wide ratio to the chain),
    decided 13 % short of the adjusted lengths: feature-depth lengths confirm the adjusted
    lengths only in the chain's units (by the given unit); in a unit of their own
    (none given, or the wrong one) they do not, and the steps stay flagged."""
    lengths = np.array([21.4, 20.6, 4.9])
    checks = [
        StepCheck(k, k + 1, v * 0.87, 0.9, v, 500, v * 0.87, "high") for k, v in enumerate(lengths)
    ]
    world = np.tile(np.eye(4), (4, 1, 1))
    world[1:, 2, 3] = np.cumsum(lengths)
    assert not any(c.reliable for c in check_adjusted(checks, world, CFG)[:2])
    assert not any(c.reliable for c in check_adjusted(checks, world, CFG, 1.0, 0.87)[:2])
    assert all(c.reliable for c in check_adjusted(checks, world, CFG, 1.0, 1.0))
    # Feature depths 13 % long in their own unit, given as 0.87 of the chain's: confirmed.
    longer = [replace(c, feature_scale_mm=c.feature_scale_mm / 0.87) for c in checks]
    assert all(c.reliable for c in check_adjusted(longer, world, CFG, 1.0, 0.87))
    assert not any(c.reliable for c in check_adjusted(longer, world, CFG, 1.0, 1.0)[:2])

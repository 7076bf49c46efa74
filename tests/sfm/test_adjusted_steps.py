"""Bundle-adjusted steps of a wall-anchored run confirmed by their feature depths and the gait."""

from __future__ import annotations

import numpy as np

from omnipipe.sfm.adjusted_steps import MOVED, check_adjusted, confirm_adjusted
from omnipipe.sfm.robot_sensors import OdometrySteps
from omnipipe.sfm.scale_check import ScaleCheckConfig, StepCheck


def _poses(lengths: list[float]) -> np.ndarray:
    """(K, 4, 4) keyframes along z, the given step lengths apart (mm)."""
    z = np.concatenate([[0.0], np.cumsum(lengths)])
    out = np.tile(np.eye(4), (len(z), 1, 1))
    out[:, 2, 3] = z
    return out


def _moved(k: int, decided: float, feature: float, adjusted: float) -> StepCheck:
    reason = f"{MOVED} to {adjusted:.1f} mm, {100 * np.log(adjusted / decided):+.0f} % from its measured length"
    return StepCheck(k, k + 1, decided, 0.9, feature, 700, decided, "none", reason)


def test_a_step_moved_to_its_feature_depths_at_the_gaits_pace_is_trusted() -> None:
    """Random-wide seed 13's case: the laser's wrong peak 8.9 mm decided, the adjustment
    moved the step to its feature depths' 10.6 mm (true 10.65) at the pace of its
    neighbours: trusted. A step the adjustment moved where its feature depths do not
    put it, and one moved a wall period (+8 mm) off the gait with its feature depths
    (a wrong course both sources share), stay flagged."""
    adjusted = [10.6, 12.7, 10.3, 14.5, 12.0, 20.3, 12.1]
    checks = [StepCheck(k, k + 1, v, 0.9, v, 700, v, "high") for k, v in enumerate(adjusted)]
    checks[0] = _moved(0, 8.9, 10.64, 10.6)  # right: features and pace agree
    checks[2] = _moved(2, 8.7, 8.9, 10.3)  # the features say 8.9: stays flagged
    checks[5] = _moved(5, 12.3, 20.3, 20.3)  # a period off: pace 2x the neighbours'
    counts = np.full(len(adjusted), 3)
    warnings: list[str] = []
    out = confirm_adjusted(checks, _poses(adjusted), counts, ScaleCheckConfig(), warnings)
    assert out[0].confidence == "resolved" and "confirm the adjusted length" in out[0].reason
    assert not out[2].reliable and not out[5].reliable
    assert [c.confidence for k, c in enumerate(out) if k not in (0, 2, 5)] == ["high"] * 4
    assert len(warnings) == 1 and warnings[0].startswith("frames 0->1")


def test_other_flags_and_too_few_matches_are_left_alone() -> None:
    adjusted = [10.0, 10.0, 10.0, 10.0]
    checks = [StepCheck(k, k + 1, v, 0.9, v, 700, v, "high") for k, v in enumerate(adjusted)]
    checks[1] = StepCheck(1, 2, 8.0, 0.9, 10.0, 700, 8.0, "none", "laser scale 8.0 mm and feature depth scale 10.0 mm disagree")
    checks[2] = StepCheck(2, 3, 8.0, 0.9, 10.0, 5, 8.0, "none", f"{MOVED} to 10.0 mm, +22 % from its measured length")
    out = confirm_adjusted(checks, _poses(adjusted), np.full(4, 2), ScaleCheckConfig())
    assert out[1] == checks[1] and out[2] == checks[2]


def test_a_step_held_to_the_wall_s_reading_is_not_flagged() -> None:
    """Seed 29's case (smooth, 8 steps of 20-27 mm): two steps' sources 4-7 % short of
    the truth, the adjustment held to the wall's readings (true within 0.3 %): the
    adjusted steps lie 1.2-1.5 mm from their sources and were flagged; the wall's
    reading confirms them. A reading a wall period off (+60 %) or one the step left
    confirms nothing."""
    cfg = ScaleCheckConfig()
    rng = np.random.default_rng(29)
    truth = rng.uniform(18.0, 27.0, 8)
    measured = truth * (1 + rng.normal(0, 0.003, 8))
    measured[[2, 3]] = truth[[2, 3]] * np.array([0.93, 0.95])  # the sources short
    checks = [StepCheck(k, k + 1, v, 0.1, v, 150, v, "high") for k, v in enumerate(measured)]
    world = np.tile(np.eye(4), (9, 1, 1))
    world[1:, 2, 3] = np.cumsum(truth)  # held to the wall: right
    walls = {k: (float(v) * (1 + rng.normal(0, 0.003)), 0.37) for k, v in enumerate(truth)}
    flagged = [k for k, c in enumerate(check_adjusted(checks, world, cfg)) if not c.reliable]
    assert flagged == [2, 3]
    assert all(c.reliable for c in check_adjusted(checks, world, cfg, wall_mm=walls))
    off = dict(walls)
    off[2] = (walls[2][0] * 1.6, 0.37)  # a course off: no witness
    off[3] = (walls[3][0] + 1.5, 0.37)  # the step left the reading by 4 sigma
    flagged = [k for k, c in enumerate(check_adjusted(checks, world, cfg, wall_mm=off)) if not c.reliable]
    assert flagged == [2, 3]


def test_the_odometry_confirms_a_move_it_agrees_with() -> None:
    """Features seed 12's case (17 mm steps, odometry with a 2 % slip): the adjustment
    moved two steps off their sources (both 6 % short) to their true length; the
    odometry, its run-wide ratio removed, lies within 0.3 mm: resolved, the odometry
    named in the reason, not flagged. A move the
    odometry does not share (2 mm beyond it, 4 of its sigmas), or a run with too few
    steps to measure its ratio, stays flagged."""
    cfg = ScaleCheckConfig()
    rng = np.random.default_rng(12)
    truth = rng.uniform(15.0, 19.0, 10)
    measured = truth * (1 + rng.normal(0, 0.003, 10))
    measured[[3, 6]] = truth[[3, 6]] * 0.94
    checks = [StepCheck(k, k + 1, v, 0.1, v, 150, v, "high") for k, v in enumerate(measured)]
    adjusted = truth.copy()
    adjusted[8] = truth[8] + 2.0  # a move the odometry does not share
    measured[8] = truth[8]
    checks[8] = StepCheck(8, 9, truth[8], 0.1, truth[8], 150, truth[8], "high")
    world = _poses(list(adjusted))
    odo = OdometrySteps(truth * 1.02 * (1 + rng.normal(0, 0.005, 10)), 0.02 * truth * 1.02 + 0.1, 0.03)
    assert [k for k, c in enumerate(check_adjusted(checks, world, cfg)) if not c.reliable] == [3, 6, 8]
    got = check_adjusted(checks, world, cfg, odometry=odo)
    assert [k for k, c in enumerate(got) if not c.reliable] == [8]
    assert got[8].reason.startswith(MOVED) and got[8].confidence == "none"
    assert [got[k].confidence for k in (3, 6)] == ["resolved"] * 2
    assert all(got[k].reason.startswith(MOVED) and "odometry" in got[k].reason and not got[k].measures_scale for k in (3, 6))
    few = check_adjusted(checks[:4], _poses(list(adjusted[:4])), cfg, odometry=odo)
    assert [k for k, c in enumerate(few) if not c.reliable] == [3]

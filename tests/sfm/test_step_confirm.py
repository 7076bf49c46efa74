"""A step's length trusted on its tracked feature depths; the run's scale after the
adjustment taken back to its decided lengths."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omnipipe.geometry import make_transform
from omnipipe.sfm.scale_check import (
    ScaleCheckConfig,
    StepCheck,
    feature_depth_spread,
    feature_log_scales,
    feature_scale,
    wall_cylinder,
)
from omnipipe.sfm.step_scale import combine_scales, decided_log, tracked_depths_confirm
from omnipipe.sfm.types import StepEvidence

CFG = ScaleCheckConfig()


def _wall_points(rng: np.random.Generator, n: int, radius: float, z: tuple[float, float]) -> np.ndarray:
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([radius * np.cos(phi), radius * np.sin(phi), rng.uniform(*z, n)])


def _evidence(seed: int, n: int, noise_rad: float, length_mm: float, tracked: bool = True) -> StepEvidence:
    """A step of ``length_mm`` along a 100 mm radius pipe: n wall features matched with
    ``noise_rad`` ray noise (0.2 px about 2e-4 rad), their per-match log lengths."""
    rng = np.random.default_rng(seed)
    pts_a = _wall_points(rng, n, 100.0, (-200.0, -40.0))
    R = Rotation.from_rotvec(rng.normal(0, 0.005, 3)).as_matrix()
    direction = np.array([0.02, -0.01, -1.0])
    direction /= np.linalg.norm(direction)
    pts_b = pts_a @ R.T + length_mm * direction
    rays_a = pts_a / np.linalg.norm(pts_a, axis=1)[:, None]
    rays_b = pts_b / np.linalg.norm(pts_b, axis=1)[:, None] + rng.normal(0, noise_rad, pts_b.shape)
    rays_b /= np.linalg.norm(rays_b, axis=1)[:, None]
    ring = _wall_points(rng, 300, 100.0, (-80.0, -80.0))
    ls = feature_log_scales(rays_a, rays_b, R, direction, wall_cylinder(ring), CFG)
    s, m = feature_scale(ls, CFG)
    step = make_transform(R, direction)
    return StepEvidence(0, 4, step, np.zeros((n, 2), int), None, ls, s, m, "ok", tracked)


def test_a_textured_wall_s_tracked_feature_depths_confirm_their_step() -> None:
    """300 tracked matches at 0.2 px: the step is trusted on them, and its stated
    1-sigma covers the truth; the same matches not followed frame to frame (a
    descriptor match may be a course off) or only 60 of them are not enough."""
    ev = _evidence(1, 300, 2e-4, 18.0)
    spread, sigma_rel, n = feature_depth_spread(ev.log_scales)
    assert n >= 250 and spread < 0.04
    assert abs(math.log(ev.feature_scale_mm / 18.0)) <= 2 * sigma_rel
    assert tracked_depths_confirm(ev, ev.feature_scale_mm, 4, CFG)
    untracked = _evidence(1, 300, 2e-4, 18.0, tracked=False)
    assert not tracked_depths_confirm(untracked, untracked.feature_scale_mm, 4, CFG)
    few = _evidence(2, 60, 2e-4, 18.0)
    assert not tracked_depths_confirm(few, few.feature_scale_mm, 4, CFG)


def test_a_plain_wall_s_scattered_feature_depths_do_not_confirm_their_step() -> None:
    """Ray noise of about 3 px scatters the per-match lengths by more than 4 %: the
    step stays unconfirmed however many matches there are."""
    ev = _evidence(3, 400, 3e-3, 18.0)
    spread, _, _ = feature_depth_spread(ev.log_scales)
    assert spread > 0.04
    assert not tracked_depths_confirm(ev, 18.0, 4, CFG)


def test_a_long_step_over_one_frame_needs_a_tighter_length_than_the_floor_gives() -> None:
    """A 40 mm step in one moving frame: the 1 % floor alone makes 3 sigma 1.2 mm, more
    than a frame step may be off; over 4 frames it is 0.3 mm a frame."""
    ev = _evidence(4, 300, 2e-4, 40.0)
    assert not tracked_depths_confirm(ev, ev.feature_scale_mm, 1, CFG)
    assert tracked_depths_confirm(ev, ev.feature_scale_mm, 4, CFG)


def _chain(lengths: list[float]) -> np.ndarray:
    world = np.tile(np.eye(4), (len(lengths) + 1, 1, 1))
    world[1:, 2, 3] = np.cumsum(lengths)
    return world


def test_decided_log_measures_how_far_the_adjustment_shrank_the_run() -> None:
    """Decided lengths 10-20 mm, the adjusted run 2 % shorter: the correction is
    log(1 / 0.98); a flagged step and one 30 % off do not count."""
    rng = np.random.default_rng(5)
    decided = list(rng.uniform(10, 20, 8))
    adjusted = [0.98 * v for v in decided]
    adjusted[2] *= 1.3
    checks = [StepCheck(k, k + 1, v, 0.1, v, 100, v, "high") for k, v in enumerate(decided)]
    checks[5] = StepCheck(5, 6, 9.0, 0.9, math.nan, 0, math.nan, "none", "ambiguous")
    adjusted[5] = 3.0
    out = decided_log(checks, decided, _chain(adjusted), CFG.adjusted_agree_log)
    assert out == pytest.approx(-math.log(0.98), abs=1e-9)
    assert decided_log([], [], _chain([]), CFG.adjusted_agree_log) == 0.0


def test_combine_scales_weighs_the_laser_s_own_correction() -> None:
    """Both sources say +2 %: the combined correction is +2 % (the adjusted run is not
    taken for the laser's length); a laser at 0 against a wall at +2 % meets halfway."""
    mean, sigma = combine_scales(0.02, 0.005, 0.005, False, 0.02)
    assert mean == pytest.approx(0.02)
    assert sigma == pytest.approx(0.005 / math.sqrt(2))
    mean, sigma = combine_scales(0.02, 0.005, 0.005, False, 0.0)
    assert mean == pytest.approx(0.01)
    assert sigma > 0.005 / math.sqrt(2)  # widened by the disagreement

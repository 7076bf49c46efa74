"""The rig's path across the pipe smoothed over its neighbours (sfm.path_smooth)."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.sfm.path_smooth import smooth_across, smooth_path
from omnipipe.sfm.types import SfmResult


def _true_path(rng: np.random.Generator, n: int = 40) -> np.ndarray:
    """(n, 3) stations of a robot crawling ~2 mm a station along z with a slow sideways
    wobble (0.3 mm over ~60 mm) and a gentle bend, mm."""
    z = np.cumsum(rng.uniform(0.5, 3.0, n))
    x = 0.3 * np.sin(z / 15.0 + rng.uniform(0, 6)) + 2e-4 * z**2
    y = 0.2 * np.cos(z / 20.0 + rng.uniform(0, 6))
    return np.column_stack([x, y, z])


def _across_rms(est: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((est - truth)[:, :2] ** 2, axis=1))))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_resection_scatter_across_the_path_is_cut_and_steps_kept(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = _true_path(rng)
    noisy = truth.copy()
    noisy[:, :2] += rng.normal(0, 0.12, (len(truth), 2))  # a far wall's resections
    noisy[:, 2] += rng.normal(0, 0.01, len(truth))
    out = smooth_across(noisy)
    before, after = _across_rms(noisy, truth), _across_rms(out, truth)
    assert after < 0.6 * before, (before, after)
    # Along the path nothing moves: the step lengths stay the measured ones.
    steps_in = np.linalg.norm(np.diff(noisy, axis=0), axis=1)
    steps_out = np.linalg.norm(np.diff(out, axis=0), axis=1)
    assert np.abs(np.diff(out[:, 2]) - np.diff(noisy[:, 2])).max() < 0.02
    assert abs(steps_out.sum() - steps_in.sum()) < 0.02 * steps_in.sum()


def test_a_real_sideways_move_larger_than_the_noise_is_kept() -> None:
    rng = np.random.default_rng(7)
    truth = _true_path(rng)
    truth[20:, 0] += 2.0  # an offset joint: the robot steps 2 mm sideways
    noisy = truth.copy()
    noisy[:, :2] += rng.normal(0, 0.05, (len(truth), 2))
    out = smooth_across(noisy)
    # Each station moves at most 3 of its window's robust sigmas: the step survives.
    assert np.abs(out - noisy)[:, :2].max() < 0.5
    assert (out[20:25, 0] - out[15:20, 0]).mean() > 1.5


def test_stations_move_together_and_unregistered_frames_stay() -> None:
    rng = np.random.default_rng(3)
    truth = _true_path(rng, 30)
    noisy = truth + np.column_stack([rng.normal(0, 0.12, (30, 2)), np.zeros(30)])
    frames = np.repeat(np.arange(30), 2)  # every station: two frames
    poses = np.tile(np.eye(4), (60, 1, 1))
    poses[:, :3, 3] = noisy[frames]
    registered = np.ones(60, bool)
    registered[59] = False
    poses[59, :3, 3] = 1e3  # not registered: not a sample, not moved
    result = SfmResult(
        world_from_rig=poses.copy(),
        registered=registered,
        keyframe=np.zeros(60, bool),
        stationary=np.tile([False, True], 30),
        station=frames,
    )
    smooth_path(result)
    out = result.world_from_rig[:, :3, 3]
    assert np.array_equal(out[59], poses[59, :3, 3])
    assert np.allclose(out[0:58:2], out[1:59:2])
    assert _across_rms(out[0:58:2], truth[:29]) < 0.7 * _across_rms(noisy[:29], truth[:29])
    assert np.array_equal(result.world_from_rig[:, :3, :3], poses[:, :3, :3])

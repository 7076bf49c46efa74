"""Earthworm gait: stop-and-go, anchored frames keep their pose exactly."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.sim import MotionConfig, Pipe, simulate_trajectory
from omnipipe.sim.motion import head_travel


def test_stop_and_go_gait() -> None:
    cfg = MotionConfig(n_units=4, stroke_mm=24.0, frames_per_cycle=8, speed_jitter=0.0)
    travel, moving = head_travel(cfg, 80, np.random.default_rng(0))
    assert np.all(np.diff(travel) >= 0)
    # The front unit moves during 1/4 of each cycle and is anchored otherwise.
    assert moving.sum() == 20
    assert travel[-1] == pytest.approx(10 * 24.0)  # frame 79 ends the 10th cycle's stroke
    still = ~moving[1:]
    assert np.all(np.diff(travel)[still] == 0)


def test_anchored_frames_have_identical_poses() -> None:
    poses, sigma, moving = simulate_trajectory(Pipe(202.0), MotionConfig(), 40, seed=3)
    assert poses.shape == (40, 4, 4)
    for i in np.flatnonzero(~moving[1:]) + 1:
        assert np.array_equal(poses[i], poses[i - 1])
    R = poses[:, :3, :3]
    assert np.allclose(np.einsum("nij,nik->njk", R, R), np.eye(3), atol=1e-12)
    # The rig looks along the pipe: z within a few degrees of the axis.
    assert np.all(R[:, 2, 2] > np.cos(np.radians(5)))
    assert sigma[-1] - sigma[0] > 100.0


def test_continuous_scenarios_move_on_every_frame() -> None:
    """``continuous`` (1600x1200, 300 frames) and ``-small``: no frame at rest after the first."""
    from omnipipe.sim import make_scenario

    for name, size, n in (("continuous", (1600, 1200), 300), ("continuous-small", (400, 300), 24)):
        s = make_scenario(name)
        assert (s.rig.camera.width, s.rig.camera.height, s.frames) == (*size, n)
        travel, moving = head_travel(s.motion, s.frames, np.random.default_rng(0))
        assert moving[1:].all()
        assert np.diff(travel).min() > 0.5

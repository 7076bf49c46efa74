"""The robot's sensors in camera motion: gravity from the frames linked to frame 0."""

from __future__ import annotations

import math

import numpy as np

from omnipipe.inputs.sensors import Imu
from omnipipe.sfm.robot_sensors import gravity_world, rotation_linked


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _clock_deg(g: np.ndarray, truth: np.ndarray) -> float:
    d = math.atan2(g[1], g[0]) - math.atan2(truth[1], truth[0])
    return abs(math.degrees((d + math.pi) % (2 * math.pi) - math.pi))


def test_gravity_comes_from_the_frames_linked_to_frame_0_by_trusted_steps() -> None:
    """The rig rolls 0.5 deg a frame; the step 4 -> 5 is untrusted and its rotation is
    5 deg wrong, which every later pose carries. Averaged over every frame, gravity's
    clock is off by about 2.5 deg; over the frames linked to frame 0 (0-4), within
    0.2 deg of the truth."""
    rng = np.random.default_rng(11)
    n = 10
    g_world = np.array([0.02, -0.999, 0.03])
    g_world /= np.linalg.norm(g_world)
    true_world_from_rig = np.stack([_rot_z(0.5 * i) for i in range(n)])
    est = np.tile(np.eye(4), (n, 1, 1))
    est[:, :3, :3] = true_world_from_rig
    est[5:, :3, :3] = _rot_z(5.0) @ true_world_from_rig[5:]
    frame_t = 0.5 + 0.5 * np.arange(n)
    t = np.arange(0.0, frame_t[-1] + 0.5, 0.01)
    nearest = np.clip(np.round((t - 0.5) / 0.5).astype(int), 0, n - 1)
    g_rig = np.einsum("nji,j->ni", true_world_from_rig[nearest], g_world)  # R^T g
    accel = -9.81 * g_rig + 0.02 * rng.standard_normal((len(t), 3))
    imu = Imu("synthetic", t, accel, None)
    station = np.arange(n)
    registered = np.ones(n, bool)

    linked = rotation_linked(station, [4, 7])
    assert linked.tolist() == [True] * 5 + [False] * 5
    assert rotation_linked(station, []).all()
    all_frames, _ = gravity_world(imu, frame_t, est, registered)
    only_linked, sigma = gravity_world(imu, frame_t, est, registered & linked)
    assert _clock_deg(all_frames, g_world) > 1.5
    assert _clock_deg(only_linked, g_world) < 0.2
    assert 0 < sigma < math.radians(1.0)


def test_frames_further_from_frame_0_weigh_less() -> None:
    """Every step trusted, but one 1.5 deg off in roll (a small pipe, few matches): the
    frames after it carry it. Weighted by their keyframe steps from frame 0, the clock
    stays within 0.3 deg; averaged alike, it is off by about half the error."""
    rng = np.random.default_rng(5)
    n = 12
    g_world = np.array([-0.014, -0.9987, -0.048])
    g_world /= np.linalg.norm(g_world)
    true_world_from_rig = np.stack([_rot_z(0.3 * i) for i in range(n)])
    est = np.tile(np.eye(4), (n, 1, 1))
    est[:, :3, :3] = true_world_from_rig
    est[3:, :3, :3] = _rot_z(1.5) @ true_world_from_rig[3:]
    frame_t = 0.5 + 0.5 * np.arange(n)
    t = np.arange(0.0, frame_t[-1] + 0.5, 0.01)
    nearest = np.clip(np.round((t - 0.5) / 0.5).astype(int), 0, n - 1)
    g_rig = np.einsum("nji,j->ni", true_world_from_rig[nearest], g_world)
    imu = Imu("synthetic", t, -9.81 * g_rig + 0.02 * rng.standard_normal((len(t), 3)), None)
    registered = np.ones(n, bool)
    steps = np.arange(n)  # every frame a keyframe
    alike, _ = gravity_world(imu, frame_t, est, registered)
    weighted, _ = gravity_world(imu, frame_t, est, registered, steps)
    assert _clock_deg(alike, g_world) > 0.9
    assert _clock_deg(weighted, g_world) < 0.3

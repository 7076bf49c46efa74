"""Frames taken for standing that the odometry counted creeping (sfm.creep_odometry):
placed by the wall's own shift on a seeded synthetic joints wall rendered through the
camera model (test_creep's), else by the odometry and flagged; the truth is the axial
position each frame was rendered at."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_creep import _joints_wall, _poses, _render, _ring

from omnipipe.camera import OmniCamera
from omnipipe.inputs.sensors import Odometry
from omnipipe.sfm.creep_odometry import (
    BY_ODOMETRY,
    odometry_placed,
    place_odometry_creeps,
    widened,
)
from omnipipe.sfm.scale_check import UnreliableStretch, wall_cylinder
from omnipipe.sfm.types import SfmResult

FPS = 8.0


def _creeping(rng: np.random.Generator, n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """True axial positions (n,) mm: keyframes 0 and n-1 (a 2.5 mm stroke into the
    last), the frames between creeping 0.3-0.7 mm each (under a pixel of this rig), and
    the stationary test's result (n,): only the keyframes moved."""
    steps = np.r_[rng.uniform(0.3, 0.7, n - 2), 2.5]
    z = np.r_[0.0, np.cumsum(steps)]
    moved = np.zeros(n, bool)
    moved[[0, -1]] = True
    return z, moved


def _odometry(z: np.ndarray, rng: np.random.Generator, slip: float = 0.02) -> Odometry:
    """An odometry at 40 Hz (on the frame times) reading the true travel with ``slip``
    and 0.01 mm noise."""
    t = np.arange(-5, 5 * len(z) + 5) * 0.025
    d = np.interp(t, np.arange(len(z)) / FPS, z) * (1 + slip) + rng.normal(0, 0.01, len(t))
    return Odometry("test", t, d, np.full(len(t), 0.01))


def _result(z: np.ndarray, moved: np.ndarray) -> SfmResult:
    n = len(z)
    return SfmResult(
        world_from_rig=_poses(z, moved),
        registered=np.ones(n, bool),
        keyframe=moved.copy(),
        stationary=~moved,
        station=np.cumsum(moved) - 1,
        scale_sigma_rel=0.01,
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_creeping_frames_are_placed_by_the_wall_and_not_flagged(small_camera: OmniCamera, seed: int) -> None:
    rng = np.random.default_rng(40 + seed)
    z, moved = _creeping(rng)
    wall = _joints_wall(rng)
    images = [_render(small_camera, wall, float(zi), rng) for zi in z]
    walls = wall_cylinder(_ring())
    result, warnings = _result(z, moved), []
    before = np.abs(result.world_from_rig[:, 2, 3] - z).max()
    place_odometry_creeps(
        result, _odometry(z, rng), np.arange(len(z)) / FPS, small_camera,
        lambda i: images[i], lambda i: walls, warnings,
    )
    err = np.abs(result.world_from_rig[:, 2, 3] - z)
    assert before > 1.5  # the creeps summed at the last frame taken for standing
    assert err.max() <= 0.25, err
    assert result.unreliable == []
    assert any("placed by the wall's own shift" in w for w in warnings)
    assert (~result.stationary[1:-1]).sum() >= 3  # the creeps are motion, not standing


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_without_a_wall_reading_the_odometry_places_them_flagged(small_camera: OmniCamera, seed: int) -> None:
    """A plain wall (no wall cylinder to read): each creeping frame at its fraction of
    the odometry's travel between the keyframes (2 % slip scales out), the stretch
    flagged with the reason saying so; a truly standing station is left standing."""
    rng = np.random.default_rng(seed)
    z, moved = _creeping(rng)
    z = np.r_[z, [z[-1]] * 3, z[-1] + 3.0]  # then stands 3 frames, then a stroke
    moved = np.r_[moved, [False] * 3, True]
    result, warnings = _result(z, moved), []
    blank = np.zeros((small_camera.height, small_camera.width), np.float32)
    place_odometry_creeps(
        result, _odometry(z, rng), np.arange(len(z)) / FPS, small_camera,
        lambda i: blank, lambda i: None, warnings,
    )
    err = np.abs(result.world_from_rig[:, 2, 3] - z)
    assert err.max() <= 0.1, err
    assert len(result.unreliable) == 1
    u = result.unreliable[0]
    assert (u.first_frame, u.last_frame) == (0, 7) and BY_ODOMETRY in u.reason
    assert result.stationary[8:11].all()  # the odometry counted no creep there
    np.testing.assert_array_equal(result.station, np.cumsum(~result.stationary) - 1)


def test_inside_a_flagged_keyframe_step_the_creep_is_said_not_flagged_again(small_camera: OmniCamera) -> None:
    """The plain wall above, its one keyframe step already flagged (bridged from the
    odometry: random-wide seed 34s): the frames are placed the same, the stretch keeps
    only the step's own reason, and a warning says what the odometry counted."""
    from omnipipe.sfm.scale_check import StepCheck

    rng = np.random.default_rng(0)
    z, moved = _creeping(rng)
    step = StepCheck(0, 7, math.nan, 0.0, math.nan, 0, math.nan, "none", "relative motion not found")
    runs = []
    blank = np.zeros((small_camera.height, small_camera.width), np.float32)
    for checks in ([], [step]):
        result, warnings = _result(z, moved), []
        result.step_checks = checks
        result.unreliable = [UnreliableStretch(0, 7, step.reason)] if checks else []
        place_odometry_creeps(
            result, _odometry(z, np.random.default_rng(1)), np.arange(len(z)) / FPS, small_camera,
            lambda i: blank, lambda i: None, warnings,
        )
        runs.append((result, warnings))
    (alone, _), (inside, said) = runs
    np.testing.assert_array_equal(inside.world_from_rig, alone.world_from_rig)
    assert [u.reason for u in inside.unreliable] == ["relative motion not found"]
    assert any(w.startswith("frames 0->7: the odometry counted") and BY_ODOMETRY in w for w in said)


def test_widened_and_odometry_placed() -> None:
    keyframes = np.zeros(12, bool)
    keyframes[[0, 5, 9]] = True
    assert widened([(2, 4, 0.5), (3, 4, 0.6), (10, 11, 0.3)], keyframes, 12) == [
        (0, 5, math.inf), (9, 11, math.inf)
    ]
    poses = np.tile(np.eye(4), (6, 1, 1))
    poses[5, 2, 3] = 4.0
    still = np.array([False, True, True, True, True, False])
    travel = np.array([0.0, 1.0, 1.0, 3.0, 4.0, 8.0])
    got = odometry_placed(poses, still, travel, 0, 5)
    assert got is not None
    np.testing.assert_allclose(got[:, 2, 3], [0.0, 0.5, 0.5, 1.5, 2.0, 4.0])
    assert odometry_placed(poses, still, np.zeros(6), 0, 5) is None  # no travel
    still[5] = True
    assert odometry_placed(poses, still, travel, 0, 5) is None  # no moving frame after
    assert UnreliableStretch(0, 5, BY_ODOMETRY).reason == BY_ODOMETRY

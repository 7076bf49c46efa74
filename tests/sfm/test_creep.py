"""Creeping stretches placed by the wall's own shift (sfm.creep), on seeded synthetic
near-plain walls with a joint ring rendered through the camera model: the truth is the
axial position each frame was rendered at."""

from __future__ import annotations

import weakref
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest

from omnipipe.camera import OmniCamera
from omnipipe.sfm import creep
from omnipipe.sfm.creep import place_creeps
from omnipipe.sfm.scale_check import wall_cylinder
from omnipipe.sfm.stations import HIDDEN_STEP_MM
from omnipipe.sfm.wall_shift import WallShift

RADIUS = 101.0  # mm, the paper rig's 202 mm pipe
RING_Z = -82.0  # mm, the laser ring plane's rig z

Wall = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _joints_wall(rng: np.random.Generator) -> Wall:
    """A near-plain wall: smooth random tone of +-3 % (4-20 mm scales) and dark joint
    rings 4 mm wide every 60 mm along the axis; (z, arc) mm -> brightness."""
    k = rng.uniform(2 * np.pi / 20, 2 * np.pi / 4, (24, 2)) * rng.choice([-1, 1], (24, 2))
    ph = rng.uniform(0, 2 * np.pi, 24)
    ring0 = rng.uniform(0, 60)

    def f(z: np.ndarray, s: np.ndarray) -> np.ndarray:
        v = sum(np.cos(k[i, 0] * z + k[i, 1] * s + ph[i]) for i in range(24)) / 24
        joint = np.abs(np.mod(z - ring0, 60.0) - 30.0) > 28.0
        return 0.8 * (1 + 0.12 * v) * np.where(joint, 0.6, 1.0)

    return f


def _render(camera: OmniCamera, wall: Wall, z_mm: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) grey image of ``wall`` from a rig on the pipe axis at axial position
    ``z_mm``; the rig's light falls off with distance (rig-fixed shading), sensor noise."""
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    ray = camera.unproject(np.column_stack([cols.ravel(), rows.ravel()]).astype(float))
    ok = np.isfinite(ray).all(axis=1)
    r = np.where(ok[:, None], ray, [[1.0, 0.0, 0.0]])
    t = RADIUS / np.maximum(np.hypot(r[:, 0], r[:, 1]), 1e-9)
    arc = RADIUS * np.mod(np.arctan2(r[:, 1], r[:, 0]), 2 * np.pi)
    light = 1.0 / (1.0 + (t / 150.0) ** 2)
    img = 200 * wall(z_mm + t * r[:, 2], arc) * light + rng.normal(0, 1.0, len(t))
    img = np.where(ok & (t < 2000), img, 0.0)
    return np.clip(img, 0, 255).reshape(camera.height, camera.width).astype(np.float32)


def _ring() -> np.ndarray:
    th = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    return np.column_stack([RADIUS * np.cos(th), RADIUS * np.sin(th), np.full(360, RING_Z)])


def _poses(z: np.ndarray, moved: np.ndarray) -> np.ndarray:
    """(N, 4, 4) world_from_rig as the stationary test leaves them: each frame at its
    station's first frame's true position (the creeps unseen)."""
    out = np.tile(np.eye(4), (len(z), 1, 1))
    first = 0
    for i in range(len(z)):
        first = i if moved[i] else first
        out[i, 2, 3] = z[first]
    return out


def _run(camera: OmniCamera, z: np.ndarray, moved: np.ndarray, seed: int):
    rng = np.random.default_rng(seed)
    wall = _joints_wall(rng)
    images = [_render(camera, wall, float(zi), rng) for zi in z]
    walls = wall_cylinder(_ring())
    n = len(z)
    return place_creeps(
        [(0, n - 1, 3.0)], moved, _poses(z, moved), np.ones(n, bool),
        lambda i: images[i], lambda i: walls, camera,
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_a_creeping_stretch_is_measured_with_a_covering_bound(small_camera: OmniCamera, seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    # Sub-pixel creeps (a pixel of this rig covers about 1 mm of wall at the ring), the
    # stationary test saw only the keyframes at either end move.
    steps = rng.uniform(0.2, 0.9, 5)
    z = np.concatenate([[0.0], np.cumsum(steps)])
    moved = np.zeros(len(z), bool)
    moved[[0, -1]] = True
    got = _run(small_camera, z, moved, seed)
    assert got.placed == [(0, len(z) - 1)]
    assert got.unverified == []  # verified: every step's bound within HIDDEN_STEP_MM
    est = np.diff(got.world_from_rig[:, 2, 3])
    bound = got.bound_mm[1:]
    assert np.all(bound <= HIDDEN_STEP_MM)
    # The truth within each step's bound (3 sigma), and the whole stretch right.
    assert np.all(np.abs(est - steps) <= bound), (est, steps, bound)
    assert np.abs(est - steps).max() <= 0.25
    assert got.moved[1:-1].sum() >= 3  # the creeps are motion, not standing


def test_a_standing_stretch_is_called_standing(small_camera: OmniCamera) -> None:
    z = np.array([0.0] * 6 + [2.5])  # stands for 5 frames, then a 2.5 mm stroke
    moved = np.zeros(len(z), bool)
    moved[[0, -1]] = True
    got = _run(small_camera, z, moved, 5)
    assert got.unverified == []
    assert not got.moved[1:-1].any()  # every frame at rest kept its station's pose
    # Its measured position kept: within the readings' noise of the station's.
    assert np.abs(got.world_from_rig[:-1, 2, 3]).max() <= 0.1
    assert np.all(got.bound_mm[1:] <= HIDDEN_STEP_MM)


def test_a_biased_reading_fails_the_gain_test_and_stays_flagged(
    small_camera: OmniCamera, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every reading off by a constant (random-wide seed 10's -0.4 to -0.9 mm) would
    put the constant into every step; their sum, the keyframes' travel's ruler, moves
    by n times it and the stretch is refused."""
    real = creep.wall_shift

    def biased(*args, **kwargs) -> WallShift:
        r = real(*args, **kwargs)
        return replace(r, shift_mm=r.shift_mm - 0.6)

    monkeypatch.setattr(creep, "wall_shift", biased)
    z = np.array([0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0])
    moved = np.zeros(len(z), bool)
    moved[[0, -1]] = True
    got = _run(small_camera, z, moved, 9)
    assert got.placed == []
    assert got.unverified == [(0, len(z) - 1, 3.0)]
    np.testing.assert_array_equal(got.world_from_rig, _poses(z, moved))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_frames_inside_a_wall_resolved_step_are_verified_by_the_odometry(seed: int) -> None:
    """Frames the wall's shift could not place: the odometry (2 % slip, 0.05 mm noise)
    confirms every frame step whose advance it matches; a frame 0.8 mm off its step is
    left flagged, and so is every step when the odometry is too coarse to bound one
    within HIDDEN_STEP_MM."""
    rng = np.random.default_rng(seed)
    n = 12
    true_steps = rng.choice([0.0, 0.5, 2.0, 6.0], size=n - 1)
    along = np.r_[0.0, np.cumsum(true_steps)]
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = along
    poses[:, 0, 3] = 0.02 * along  # a travel not along the rig's z
    odometry = 5.0 + along * 1.02 + rng.normal(0, 0.05, n)
    noise = np.full(n - 1, 0.1)
    ok = creep.odometry_verified_steps(poses, 0, n - 1, odometry, noise)
    assert ok.all()
    off = poses.copy()
    off[6, 2, 3] += 0.8
    ok = creep.odometry_verified_steps(off, 0, n - 1, odometry, noise)
    assert list(np.flatnonzero(~ok)) == [5, 6]
    assert creep.unverified_runs(ok, 10) == [(15, 17)]
    assert not creep.odometry_verified_steps(poses, 0, n - 1, odometry, np.full(n - 1, 0.5)).any()


def _creeping_positions(camera: OmniCamera, seed: int, flow: bool) -> tuple[np.ndarray, np.ndarray]:
    """(true z, placed z) of a 17-frame stretch creeping 0-0.9 mm a frame (standing
    frames among them), its frames placed by the wall's shift with or without the flow."""
    rng = np.random.default_rng(200 + seed)
    z = np.concatenate([[0.0], np.cumsum(rng.choice([0.0, 0.0, 0.3, 0.6, 0.9], 16))])
    moved = np.zeros(len(z), bool)
    moved[[0, -1]] = True
    with pytest.MonkeyPatch.context() as mp:
        if not flow:
            mp.setattr(creep, "_flow_refined", lambda s, pos, read_gray, mask: pos)
        got = _run(camera, z, moved, seed)
    assert got.placed == [(0, len(z) - 1)]
    return z, got.world_from_rig[:, 2, 3]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_tracked_flow_places_creeping_frames_no_worse_than_the_shift(small_camera: OmniCamera, seed: int) -> None:
    """The wall's shift adds one reading's error a frame; the flow reads each frame
    against keyframe a (random-wide seed 24: 0.27 -> 0.13 mm). Here (400x300, 4-7 mm
    stretches) the shift's frames are 0.02-0.03 mm RMS off, combined 0.01-0.02."""
    z, shift_only = _creeping_positions(small_camera, seed, flow=False)
    _, both = _creeping_positions(small_camera, seed, flow=True)
    rms = lambda p: float(np.sqrt(np.mean((p - z) ** 2)))  # noqa: E731
    assert rms(both) <= rms(shift_only) + 1e-4, (rms(both), rms(shift_only))
    assert np.abs(both - z).max() <= 0.045
    if seed in (0, 2):
        assert rms(both) <= 0.7 * rms(shift_only)


def test_a_flow_that_disagrees_with_the_shift_is_not_used(
    small_camera: OmniCamera, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Fractions a third of the step off (a tracker on the rig's own shading) lie beyond
    3 sigma of the shift's positions: the shift's stand."""
    _, shift_only = _creeping_positions(small_camera, 0, flow=False)
    real = creep.flow_fraction

    def off(*args, **kwargs):
        return [(f - 0.33, se) for f, se in real(*args, **kwargs)]

    monkeypatch.setattr(creep, "flow_fraction", off)
    _, got = _creeping_positions(small_camera, 0, flow=True)
    np.testing.assert_allclose(got, shift_only, atol=1e-12)


def test_images_read_are_not_kept_beyond_the_next_step(small_camera: OmniCamera) -> None:
    """Each frame's image is read once and released once its step is read, and once
    more for the tracked flow (the keyframes, then each frame between them, released
    in turn): a whole run's images held grew the memory with the run (10,000 frames at
    rest: 818 MB)."""
    rng = np.random.default_rng(7)
    wall = _joints_wall(rng)
    z = np.array([0.0] * 6 + [2.5])
    moved = np.zeros(len(z), bool)
    moved[[0, -1]] = True
    images = [_render(small_camera, wall, float(zi), rng) for zi in z]
    reads: list[int] = []
    alive: list[weakref.ref] = []
    most_alive = 0

    def read(i: int) -> np.ndarray:
        nonlocal most_alive
        reads.append(i)
        img = images[i].copy()
        alive.append(weakref.ref(img))
        most_alive = max(most_alive, sum(r() is not None for r in alive))
        return img

    walls = wall_cylinder(_ring())
    n = len(z)
    place_creeps([(0, n - 1, 3.0)], moved, _poses(z, moved), np.ones(n, bool), read, lambda i: walls, small_camera)
    # every frame read once in order by the wall's shift, then the flow's: b, a, a+1..b-1
    assert reads == [*range(n), n - 1, 0, *range(1, n - 1)]
    # at most the flow's two keyframes, the frame it tracked and the next one: not the run
    assert most_alive <= 4

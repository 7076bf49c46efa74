"""The camera motion's rotation against the gyro (sfm.rotation_check) and a bend's turn
carrying it (pipeline.quality.bend_with_rotation): on a seeded synthetic run whose images'
rotation drifts through a bend (random-features seed 12: 4.5 deg over 232 mm), the
drift is found, warned of, and the bend's stated turn sigma covers the true turn;
images that follow the gyro within its noise raise nothing."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from omnipipe.analysis.feature_types import Bend
from omnipipe.contract import RotationCheck
from omnipipe.inputs.sensors import Imu
from omnipipe.pipeline.quality import bend_with_rotation
from omnipipe.sfm.rotation_check import gyro_check, gyro_warnings

FPS, IMU_HZ, DURATION = 8.0, 100.0, 15.0
TURN_RATE = math.radians(18.0) / DURATION  # rad/s about the rig's x axis (a bend)


def _run(rng: np.random.Generator, drift_deg: float) -> tuple[Imu, np.ndarray, np.ndarray, np.ndarray]:
    """An IMU (true rate + a drawn bias + noise), the frames' times (N,), the images'
    poses (N, 4, 4) whose rotation lags the truth by up to ``drift_deg`` (growing over
    the second half, about the turn's axis), and the true rotations (N, 3, 3)."""
    t_imu = np.arange(-1.0, DURATION + 1.0, 1.0 / IMU_HZ)
    moving = (t_imu >= 0) & (t_imu <= DURATION)
    rate = np.zeros((len(t_imu), 3))
    rate[moving, 0] = TURN_RATE
    bias = rng.normal(0.0, 0.0005, 3)
    gyro = rate + bias + rng.normal(0.0, 0.002, rate.shape)
    imu = Imu("test", t_imu, np.zeros((len(t_imu), 3)), gyro)
    times = np.arange(0.0, DURATION, 1.0 / FPS)
    truth = Rotation.from_rotvec(np.outer(TURN_RATE * times, [1.0, 0.0, 0.0])).as_matrix()
    lag = math.radians(drift_deg) * np.clip((times - DURATION / 2) / (DURATION / 2), 0, 1)
    wobble = rng.normal(0.0, math.radians(0.05), (len(times), 3))
    err = Rotation.from_rotvec(np.outer(-lag, [1.0, 0.0, 0.0]) + wobble).as_matrix()
    poses = np.tile(np.eye(4), (len(times), 1, 1))
    poses[:, :3, :3] = truth @ err
    poses[:, 2, 3] = 15.5 * np.arange(len(times))
    return imu, times, poses, truth


def test_a_drift_of_the_images_rotation_is_found_and_warned_of() -> None:
    rng = np.random.default_rng(12)
    imu, times, poses, _ = _run(rng, 4.5)
    check = gyro_check(imu, times, poses, np.ones(len(times), bool))
    assert check is not None
    err, sigma = check.between(0, len(times) - 1)
    assert abs(math.degrees(err) - 4.5) < 3.0 * math.degrees(sigma)
    frame, gap, _ = check.worst()
    assert frame > len(times) / 2 and math.degrees(gap) > 3.0
    warnings = gyro_warnings(check)
    assert len(warnings) == 1 and "departs from the gyro's" in warnings[0]
    # The first half follows the gyro: nothing there beyond its noise.
    err, sigma = check.between(0, len(times) // 2 - 1)
    assert err < 3.0 * sigma


def test_images_that_follow_the_gyro_raise_nothing() -> None:
    for seed in range(5):
        rng = np.random.default_rng(seed)
        imu, times, poses, _ = _run(rng, 0.0)
        check = gyro_check(imu, times, poses, np.ones(len(times), bool))
        assert check is not None
        assert gyro_warnings(check) == []
    assert gyro_check(None, times, poses, np.ones(len(times), bool)) is None
    no_gyro = Imu("test", imu.timestamps, imu.accel, None)
    assert gyro_check(no_gyro, times, poses, np.ones(len(times), bool)) is None


def test_a_bend_s_turn_sigma_covers_the_truth_with_the_drift() -> None:
    rng = np.random.default_rng(16)
    imu, times, poses, _ = _run(rng, 5.0)
    registered = np.ones(len(times), bool)
    check = gyro_check(imu, times, poses, registered)
    assert check is not None
    # Stations at every frame, 15.5 mm apart; the bend over the whole run. The
    # centreline's turn is the images' (true turn less the lag), its fit sigma small.
    axial = 15.5 * np.arange(len(times))
    true_turn = math.degrees(TURN_RATE * times[-1])
    seen = Rotation.from_matrix(poses[0, :3, :3].T @ poses[-1, :3, :3]).magnitude()
    bend = Bend(
        axial_from_mm=float(axial[0]), axial_to_mm=float(axial[-1]), radius_mm=float(axial[-1] / seen),
        radius_sigma_mm=20.0, turn_deg=math.degrees(seen), turn_sigma_deg=0.8,
    )
    assert abs(bend.turn_deg - true_turn) > 3.0 * bend.turn_sigma_deg  # the fit alone misses
    frame, gap, sig = check.worst()
    rc = RotationCheck(math.degrees(gap), frame, math.degrees(sig), check, np.arange(len(times)), axial)
    widened = bend_with_rotation(bend, rc)
    assert abs(widened.turn_deg - true_turn) < 2.0 * widened.turn_sigma_deg
    assert widened.turn_motion_sigma_deg is not None and widened.turn_motion_sigma_deg > 4.0
    true_radius = float(axial[-1]) / math.radians(true_turn)
    assert abs(widened.radius_mm - true_radius) < 2.0 * widened.radius_sigma_mm
    assert bend_with_rotation(bend, None) == bend
    # Images that follow the gyro: the departure is its own drift, the sigmas stay.
    imu, times, poses, _ = _run(np.random.default_rng(17), 0.0)
    check = gyro_check(imu, times, poses, registered)
    assert check is not None
    rc = RotationCheck(0.0, 0, 0.0, check, np.arange(len(times)), axial)
    same = bend_with_rotation(bend, rc)
    assert same.turn_motion_sigma_deg == 0.0 and same.turn_sigma_deg == bend.turn_sigma_deg

"""Simulated odometry and IMU: within their stated uncertainty of the truth, deterministic,
written by ``omnipipe simulate`` (or not, with --no-odometry / --no-imu) and read back."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from omnipipe.cli import main as cli_main
from omnipipe.dataset import open_dataset
from omnipipe.inputs.sensors import gravity_at, make_imu, odometry_at, read_imu, read_odometry
from omnipipe.sim import make_scenario, simulate_trajectory
from omnipipe.sim.sensors import simulate_sensors, write_sensor_files


def _sensors(name: str, seed: int):
    sc = make_scenario(name, seed=seed)
    poses, sigma, _ = simulate_trajectory(sc.pipe, sc.motion, sc.frames, sc.seed)
    stamps = np.arange(sc.frames) / sc.fps
    return sc, stamps, simulate_sensors(sc, stamps, sigma, poses)


@pytest.mark.parametrize("name,seed", [("brick-bend", 0), ("tiled-culvert", 1), ("random-wide", 3)])
def test_odometry_within_its_sigma_and_gravity_within_a_degree(
    name: str, seed: int, tmp_path: Path
) -> None:
    _, stamps, sim = _sensors(name, seed)
    write_sensor_files(tmp_path, sim)  # read back through the validating file readers
    odo = read_odometry(tmp_path / "odometry.txt")
    imu = read_imu(tmp_path / "imu.txt")
    assert np.all(np.diff(odo.distance_mm) >= 0)  # a counter never counts backwards
    d, s = odometry_at(odo, stamps)
    true = np.array(sim.truth["distance_at_frames_mm"])
    z = np.abs(d - true) / s
    print(f"{name}: odometry |error| / sigma: median {np.median(z):.2f}, max {z.max():.2f}")
    assert np.isfinite(d).all()
    # The slip is a bias inside the stated sigma's 3 % part; the count's walk adds its own
    # part: |error| <= 3 % d + 3 sigma_walk gives at most sqrt(10) = 3.2 stated sigma.
    assert z.max() <= 3.2
    assert 0.01 <= sim.truth["odometry"]["slip"] <= 0.03
    g, gs = gravity_at(imu, stamps)
    g_true = np.array(sim.truth["gravity_in_rig_at_frames"])
    err = np.degrees(np.arccos(np.clip(np.sum(g * g_true, axis=1), -1, 1)))
    print(f"{name}: gravity error max {err.max():.2f} deg, stated sigma max {np.degrees(gs).max():.2f}")
    assert err.max() < 1.0 and np.all(err <= 3.0 * np.degrees(gs))


def test_gyro_matches_the_trajectory_rotation() -> None:
    sc, stamps, sim = _sensors("brick-bend", 0)
    t, w = sim.imu[:, 0], sim.imu[:, 4:7]
    poses, *_ = simulate_trajectory(sc.pipe, sc.motion, sc.frames, sc.seed)
    # The integrated rate about the rig axis between the first and last frame equals the
    # true rotation about it (small angles: drift, wobble and the bend), within the bias.
    sel = (t >= stamps[0]) & (t < stamps[-1])
    turned = np.sum(w[sel], axis=0) * (t[1] - t[0])
    from scipy.spatial.transform import Rotation

    rel = Rotation.from_matrix(poses[0, :3, :3].T @ poses[-1, :3, :3]).as_rotvec()
    bias = np.array(sim.truth["imu"]["gyro_bias"]) * (stamps[-1] - stamps[0])
    assert np.linalg.norm(turned - bias - rel) < 0.1 * np.linalg.norm(rel) + 2e-3


def test_sensors_are_deterministic_per_seed() -> None:
    _, _, a = _sensors("random-wide", 5)
    _, _, b = _sensors("random-wide", 5)
    _, _, c = _sensors("random-wide", 6)
    np.testing.assert_array_equal(a.odometry, b.odometry)
    np.testing.assert_array_equal(a.imu, b.imu)
    assert a.truth["odometry"]["slip"] != c.truth["odometry"]["slip"]
    # Switching one sensor off changes nothing in the other.
    sc = make_scenario("random-wide", seed=5)
    poses, sigma, _ = simulate_trajectory(sc.pipe, sc.motion, sc.frames, sc.seed)
    sc.sensors = replace(sc.sensors, imu=False)
    no_imu = simulate_sensors(sc, np.arange(sc.frames) / sc.fps, sigma, poses)
    sc.sensors = replace(sc.sensors, imu=True, odometry=False)
    no_odo = simulate_sensors(sc, np.arange(sc.frames) / sc.fps, sigma, poses)
    assert no_imu.imu is None and no_odo.odometry is None
    np.testing.assert_array_equal(no_imu.odometry, a.odometry)
    np.testing.assert_array_equal(no_odo.imu, a.imu)


def test_simulate_writes_and_the_dataset_reads_the_sensors(tmp_path: Path) -> None:
    both, odo_only = tmp_path / "both", tmp_path / "odo"
    args = ["simulate", "--scenario", "brick-bend-small", "--frames", "3", "--size", "96x72",
            "--workers", "1", "--quiet"]  # fmt: skip
    assert cli_main([*args, "--out", str(both)]) == 0
    assert cli_main([*args, "--out", str(odo_only), "--no-imu"]) == 0
    ds = open_dataset(both)
    assert ds.odometry is not None and ds.imu is not None and ds.imu.gyro is not None
    assert ds.odometry.timestamps[0] <= ds.timestamps[0] and ds.imu.timestamps[-1] > ds.timestamps[-1]
    scene = json.loads((both / "ground_truth" / "scene.json").read_text())
    assert {"config", "odometry", "imu", "distance_at_frames_mm"} <= set(scene["sensors"])
    ds2 = open_dataset(odo_only)
    assert ds2.imu is None and not (odo_only / "imu.txt").exists()
    np.testing.assert_array_equal(ds2.odometry.distance_mm, ds.odometry.distance_mm)


def test_imu_follows_the_scene_gravity() -> None:
    """A scenario whose gravity is world +x (a pipe running down a vertical shaft's
    side): the accelerometer's gravity direction follows it, within a degree."""
    sc = make_scenario("brick-bend", seed=0, frames=40)
    sc.pipe = replace(sc.pipe, features=replace(sc.pipe.features, gravity=(1.0, 0.0, 0.0)))
    poses, sigma, _ = simulate_trajectory(sc.pipe, sc.motion, sc.frames, sc.seed)
    stamps = np.arange(sc.frames) / sc.fps
    sim = simulate_sensors(sc, stamps, sigma, poses)
    imu = make_imu("sim", sim.imu[:, 0], sim.imu[:, 1:4], sim.imu[:, 4:7], str)
    g, _ = gravity_at(imu, stamps)
    expected = np.einsum("nji,j->ni", poses[:, :3, :3], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(sim.truth["gravity_in_rig_at_frames"], expected, atol=1e-8)
    err = np.degrees(np.arccos(np.clip(np.sum(g * expected, axis=1), -1, 1)))
    assert err.max() < 1.0

"""sfm.trajectory_from: the camera motion read from a TUM file instead of estimated."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omnipipe import sfm
from omnipipe.dataset import write_tum
from omnipipe.errors import ConfigError, ReconstructionError
from omnipipe.pipeline.run_config import ReconstructConfig
from omnipipe.sfm.types import SfmConfig, SfmInputs


def _poses(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) world_from_rig in an arbitrary world frame, moving along a slow curve."""
    out = np.tile(np.eye(4), (n, 1, 1))
    world_from_start = np.eye(4)
    world_from_start[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    world_from_start[:3, 3] = rng.normal(scale=500.0, size=3)
    for i in range(n):
        local = np.eye(4)
        local[:3, :3] = Rotation.from_rotvec([0.0, 0.01 * i, 0.0]).as_matrix()
        local[:3, 3] = [0.3 * i, 0.0, 5.0 * i]
        out[i] = world_from_start @ local
    return out


def _inputs(n: int, moved: np.ndarray, times: np.ndarray, root: Path | None = None) -> SfmInputs:
    class _Root:
        def __init__(self, path: Path) -> None:
            self.root = path

    return SfmInputs(
        rig=None,  # type: ignore[arg-type]  # not read: the motion is given
        read_frame=lambda i: np.zeros((4, 4)),
        n_frames=n,
        rings=None,  # type: ignore[arg-type]
        moved=moved,
        dataset=None if root is None else _Root(root),  # type: ignore[arg-type]
        timestamps=times,
    )


def test_poses_are_read_in_the_first_frame_s_rig_frame(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 8
    poses = _poses(n, rng)
    times = 0.125 * np.arange(n)
    # The file's own clock ticks slightly off the frames' (within half a frame).
    write_tum(tmp_path / "poses.txt", times + 0.01, poses)
    moved = np.array([True, True, False, True, True, True, False, True])
    config = SfmConfig(trajectory_from=str(tmp_path / "poses.txt"))
    got = sfm.run(config, _inputs(n, moved, times))
    expected = np.linalg.inv(poses[0]) @ poses
    np.testing.assert_allclose(got.world_from_rig[0], np.eye(4), atol=1e-6)
    for i in (1, 3, 4, 5, 7):
        np.testing.assert_allclose(got.world_from_rig[i], expected[i], atol=1e-5)
    # A stationary frame keeps its station's pose.
    np.testing.assert_allclose(got.world_from_rig[2], expected[1], atol=1e-5)
    np.testing.assert_array_equal(got.stationary, ~moved)
    assert got.registered.all() and not got.unreliable
    assert np.isnan(got.scale_sigma_rel)  # its uncertainty is not known: the analysis falls back
    assert "external trajectory" in got.scale_source


def test_relative_path_is_read_from_the_dataset(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    poses = _poses(3, rng)
    times = np.array([0.0, 0.1, 0.2])
    (tmp_path / "gt").mkdir()
    write_tum(tmp_path / "gt" / "p.txt", times, poses)
    moved = np.ones(3, bool)
    got = sfm.run(SfmConfig(trajectory_from="gt/p.txt"), _inputs(3, moved, times, tmp_path))
    np.testing.assert_allclose(got.world_from_rig[2], np.linalg.inv(poses[0]) @ poses[2], atol=1e-5)
    with pytest.raises(ConfigError, match="trajectory_from"):
        sfm.run(SfmConfig(trajectory_from="gt/p.txt"), _inputs(3, moved, times))


def test_a_frame_without_a_pose_near_its_time_is_refused(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    poses = _poses(4, rng)
    write_tum(tmp_path / "p.txt", np.array([0.0, 0.1, 0.2, 0.3]), poses)
    times = np.array([0.0, 0.1, 0.2, 0.5])  # the last frame 0.2 s after the last pose
    with pytest.raises(ReconstructionError, match="frame 3"):
        sfm.run(SfmConfig(trajectory_from=str(tmp_path / "p.txt")), _inputs(4, np.ones(4, bool), times))


def test_the_setting_is_read_from_yaml(tmp_path: Path) -> None:
    (tmp_path / "c.yaml").write_text("sfm:\n  trajectory_from: ground_truth/poses.txt\n")
    assert ReconstructConfig.from_yaml(tmp_path / "c.yaml").sfm.trajectory_from == "ground_truth/poses.txt"
    (tmp_path / "bad.yaml").write_text("sfm:\n  trajectory_from: 3\n")
    with pytest.raises(ConfigError, match="trajectory_from"):
        ReconstructConfig.from_yaml(tmp_path / "bad.yaml")

"""omnipipe export-bag: a dataset folder written as MCAP, a ROS 2 bag folder and a ROS 1
bag reads back to the same frames and timestamps, and the MCAP reconstructs to the
folder's numbers."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from omnipipe.cli import main
from omnipipe.dataset import open_dataset, read_image
from omnipipe.pipeline import ReconstructConfig, run

pytest.importorskip("rosbags")


@pytest.fixture(scope="module")
def folder(eight_frames: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """paper-small, 8 frames (400x300), with epoch-like timestamps.txt (a copy)."""
    out = tmp_path_factory.mktemp("export") / "images"
    shutil.copytree(eight_frames, out)
    names = sorted(p.name for p in (out / "frames").glob("*.png"))
    (out / "timestamps.txt").write_text(
        "".join(f"{n} {1_700_000_000 + 0.125 * i:.6f}\n" for i, n in enumerate(names))
    )
    return out


def _numbers(summary: dict) -> dict:
    keep = ("frames", "frames_registered", "inner_diameter_mm", "defects", "stations", "keyframes")
    return {k: summary.get(k) for k in keep}


def test_mcap_reconstructs_to_the_folders_numbers(folder: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "run.mcap"
    assert main(["export-bag", str(folder), "--out", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    assert (tmp_path / "rig.yaml").read_bytes() == (folder / "rig.yaml").read_bytes()
    reference_ds = open_dataset(folder)
    ds = open_dataset(out)
    np.testing.assert_allclose(ds.timestamps, reference_ds.timestamps, rtol=0, atol=1e-6)
    assert not ds.warnings
    config = ReconstructConfig.default()
    reference, rec = run(config, reference_ds), run(config, ds)
    assert _numbers(rec.summary) == _numbers(reference.summary)
    np.testing.assert_allclose(rec.world_from_rig, reference.world_from_rig, atol=1e-9)
    np.testing.assert_allclose(rec.timestamps, reference.timestamps, rtol=0, atol=1e-6)


@pytest.mark.parametrize("name, raw", [("bagdir", True), ("run.bag", False)])
def test_ros2_folder_and_ros1_bag_hold_the_frames(folder: Path, tmp_path: Path, name: str, raw: bool) -> None:
    out = tmp_path / name
    assert main(["export-bag", str(folder), "--out", str(out), *(["--raw"] if raw else [])]) == 0
    ds = open_dataset(out)
    assert len(ds) == 8
    np.testing.assert_allclose(ds.timestamps, 1_700_000_000 + 0.125 * np.arange(8), rtol=0, atol=1e-6)
    for i in range(8):
        np.testing.assert_array_equal(ds.read_frame(i), read_image(folder / "frames" / f"{i:06d}.png"))


def test_nothing_is_replaced(folder: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "run.mcap"
    out.write_text("mine")
    assert main(["export-bag", str(folder), "--out", str(out)]) == 1
    assert "already exists" in capsys.readouterr().err and out.read_text() == "mine"
    other = tmp_path / "b"
    other.mkdir()
    (other / "rig.yaml").write_text("someone else's rig")
    assert main(["export-bag", str(folder), "--out", str(other / "x.mcap")]) == 1
    assert "other content" in capsys.readouterr().err
    assert sorted(p.name for p in other.iterdir()) == ["rig.yaml"]
    shutil.rmtree(other)


@pytest.mark.parametrize("name", ["sensors.mcap", "sensors.bag"])
def test_odometry_and_imu_travel_with_the_frames(folder: Path, tmp_path: Path, name: str) -> None:
    reference = open_dataset(folder)
    assert reference.odometry is not None and reference.imu is not None  # simulate writes both
    out = tmp_path / name
    assert main(["export-bag", str(folder), "--out", str(out)]) == 0
    ds = open_dataset(out)
    odo, ref_odo = ds.odometry, reference.odometry
    assert odo is not None and ds.imu is not None
    o, m = ref_odo.timestamps >= 0, reference.imu.timestamps >= 0  # a bag has no times < 0
    np.testing.assert_allclose(odo.timestamps, ref_odo.timestamps[o], rtol=0, atol=1e-6)
    travel = ref_odo.distance_mm[o] - ref_odo.distance_mm[o][0]  # path length starts at 0
    np.testing.assert_allclose(odo.distance_mm, travel, rtol=0, atol=1e-6)
    np.testing.assert_allclose(odo.sigma_mm, ref_odo.sigma_mm[o], rtol=1e-9)
    np.testing.assert_allclose(ds.imu.timestamps, reference.imu.timestamps[m], rtol=0, atol=1e-6)
    np.testing.assert_allclose(ds.imu.accel, reference.imu.accel[m], rtol=0, atol=1e-9)
    assert (ds.imu.gyro is None) == (reference.imu.gyro is None)

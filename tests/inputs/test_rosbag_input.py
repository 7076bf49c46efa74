"""ROS 1/2 bags and MCAP files as input: written with rosbags' own writers from a small
simulated run, they must give the frames and the reconstruction of the image folder."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from omnipipe.dataset import open_dataset, read_image
from omnipipe.errors import ConfigError, DatasetError
from omnipipe.pipeline import ReconstructConfig, run
from omnipipe.sim import make_scenario
from omnipipe.sim import run as simulate

rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

TOPIC = "/omni/image"
T0 = 1_700_000_000  # header stamps: an epoch time in seconds


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`omnipipe simulate --scenario paper-small --frames 8` (400x300)."""
    out = tmp_path_factory.mktemp("ros") / "images"
    simulate(make_scenario("paper-small", frames=8, seed=0), out, workers=1)
    return out


def _messages(folder: Path, store: Stores, kind: str):
    """(typestore, msgtype, [(time_ns, message)]) of the folder's frames."""
    import cv2

    ts = get_typestore(store)
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    frames = sorted((folder / "frames").glob("*.png"))
    out = []
    for i, path in enumerate(frames):
        rgb = read_image(path)
        ns = T0 * 10**9 + i * 125_000_000  # 8 frames per second
        stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
        if store == Stores.ROS1_NOETIC:
            header = Header(seq=i, stamp=stamp, frame_id="omni")
        else:
            header = Header(stamp=stamp, frame_id="omni")
        if kind == "compressed":
            ok, png = cv2.imencode(".png", rgb[:, :, ::-1])
            assert ok
            msg = ts.types["sensor_msgs/msg/CompressedImage"](
                header=header, format="png", data=png.ravel()
            )
        else:
            bgr = np.ascontiguousarray(rgb[:, :, ::-1])
            msg = ts.types["sensor_msgs/msg/Image"](
                header=header, height=rgb.shape[0], width=rgb.shape[1], encoding="bgr8",
                is_bigendian=0, step=rgb.shape[1] * 3, data=bgr.ravel(),
            )
        out.append((ns + 5_000_000, msg))  # recorded 5 ms after the exposure
    msgtype = "sensor_msgs/msg/CompressedImage" if kind == "compressed" else "sensor_msgs/msg/Image"
    return ts, msgtype, out


def _write_ros2(folder: Path, bag: Path, kind: str, storage: StoragePlugin) -> None:
    ts, msgtype, msgs = _messages(folder, Stores.ROS2_HUMBLE, kind)
    with Writer2(bag, version=8, storage_plugin=storage) as writer:
        conn = writer.add_connection(TOPIC, msgtype, typestore=ts)
        other = writer.add_connection("/other", "std_msgs/msg/String", typestore=ts)
        for t, msg in msgs:
            writer.write(conn, t, ts.serialize_cdr(msg, msgtype))
        writer.write(other, msgs[0][0], ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"))
    shutil.copy(folder / "rig.yaml", bag.parent / "rig.yaml")


def _summary_numbers(summary: dict) -> dict:
    keep = ("frames", "frames_registered", "inner_diameter_mm", "defects", "stations", "keyframes")
    return {k: summary[k] for k in keep}


def test_ros2_bag_and_mcap_reconstruct_like_the_image_folder(folder: Path, tmp_path: Path) -> None:
    config = ReconstructConfig.default()
    reference = run(config, open_dataset(folder))
    sqlite_bag = tmp_path / "sqlite" / "run_bag"
    mcap_bag = tmp_path / "mcap" / "run_bag"
    sqlite_bag.parent.mkdir()
    mcap_bag.parent.mkdir()
    _write_ros2(folder, sqlite_bag, "compressed", StoragePlugin.SQLITE3)
    _write_ros2(folder, mcap_bag, "raw", StoragePlugin.MCAP)
    mcap_file = next(mcap_bag.glob("*.mcap"))
    expected_t = T0 + 0.125 * np.arange(8)
    for path in (sqlite_bag, mcap_file):
        ds = open_dataset(path, topic=TOPIC)
        assert len(ds) == 8
        np.testing.assert_allclose(ds.timestamps, expected_t, rtol=0, atol=1e-6)
        for i in (0, 7):
            png = read_image(folder / "frames" / f"{i:06d}.png")
            np.testing.assert_array_equal(ds.read_frame(i), png)
        rec = run(config, ds)
        assert _summary_numbers(rec.summary) == _summary_numbers(reference.summary)
        np.testing.assert_allclose(rec.world_from_rig, reference.world_from_rig, atol=1e-9)
    # The MCAP bag folder opens too, and its only image topic is found without --topic.
    assert len(open_dataset(mcap_bag)) == 8


def test_ros1_bag_frames_and_stamps(folder: Path, tmp_path: Path) -> None:
    ts, msgtype, msgs = _messages(folder, Stores.ROS1_NOETIC, "raw")
    bag = tmp_path / "run.bag"
    with Writer1(bag) as writer:
        conn = writer.add_connection(TOPIC, msgtype, typestore=ts)
        for t, msg in msgs:
            writer.write(conn, t, ts.serialize_ros1(msg, msgtype))
    shutil.copy(folder / "rig.yaml", tmp_path / "rig.yaml")
    ds = open_dataset(bag)
    np.testing.assert_allclose(ds.timestamps, T0 + 0.125 * np.arange(8), rtol=0, atol=1e-6)
    for i in range(8):
        np.testing.assert_array_equal(ds.read_frame(i), read_image(folder / "frames" / f"{i:06d}.png"))


def test_topic_errors_are_one_line(folder: Path, tmp_path: Path) -> None:
    bag = tmp_path / "b" / "bag"
    bag.parent.mkdir()
    _write_ros2(folder, bag, "compressed", StoragePlugin.SQLITE3)
    with pytest.raises(ConfigError, match=r"--topic.*'/other' is not an image topic"):
        open_dataset(bag, topic="/other")
    with pytest.raises(ConfigError, match="--topic"):
        open_dataset(folder, topic=TOPIC)  # an image folder has no topics
    (tmp_path / "b" / "rig.yaml").unlink()
    with pytest.raises(ConfigError, match="rig"):
        open_dataset(bag)


def test_missing_rosbags_is_one_line(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import sys

    bag = tmp_path / "x.mcap"
    bag.write_bytes(b"not really")
    (tmp_path / "rig.yaml").write_text("")  # not reached
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    from omnipipe.inputs.rosbag import read_bag

    with pytest.raises(DatasetError, match=r"pip install 'omnipipe\[ros\]'"):
        read_bag(bag)

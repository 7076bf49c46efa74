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

rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

TOPIC = "/omni/image"
T0 = 1_700_000_000  # header stamps: an epoch time in seconds


@pytest.fixture(scope="module")
def folder(eight_frames: Path) -> Path:
    """`omnipipe simulate --scenario paper-small --frames 8` (400x300; read only)."""
    return eight_frames


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


def _sensor_messages(ts, n: int, bad_stamp: bool = False):
    """nav_msgs/Odometry moving 1 mm per message along x (covariance 0.5 mm^2 in x) and
    sensor_msgs/Imu at rest with gravity along -y, 20 per second from T0."""
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    Quat = ts.types["geometry_msgs/msg/Quaternion"]
    g = ts.types
    odo, imu = [], []
    for i in range(n):
        ns = T0 * 10**9 + i * 50_000_000
        if bad_stamp and i == 5:
            ns -= 100_000_000
        header = Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="omni")
        cov = np.zeros(36)
        cov[0] = 0.5e-6  # m^2
        pose = g["geometry_msgs/msg/PoseWithCovariance"](
            pose=g["geometry_msgs/msg/Pose"](
                position=g["geometry_msgs/msg/Point"](x=0.001 * i, y=0.0, z=0.0),
                orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
            ),
            covariance=cov,
        )
        twist = g["geometry_msgs/msg/TwistWithCovariance"](
            twist=g["geometry_msgs/msg/Twist"](linear=V3(x=0.0, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.0)),
            covariance=np.zeros(36),
        )
        odo.append((ns, g["nav_msgs/msg/Odometry"](header=header, child_frame_id="rig", pose=pose, twist=twist)))
        imu.append((ns, g["sensor_msgs/msg/Imu"](
            header=header, orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=np.zeros(9),
            angular_velocity=V3(x=0.0, y=0.0, z=0.01), angular_velocity_covariance=np.zeros(9),
            linear_acceleration=V3(x=0.0, y=9.80665, z=0.0), linear_acceleration_covariance=np.zeros(9),
        )))  # fmt: skip
    return odo, imu


def _write_ros2_with_sensors(folder: Path, bag: Path, bad_stamp: bool = False) -> None:
    ts, msgtype, msgs = _messages(folder, Stores.ROS2_HUMBLE, "compressed")
    odo, imu = _sensor_messages(ts, 30, bad_stamp)
    with Writer2(bag, version=8, storage_plugin=StoragePlugin.SQLITE3) as writer:
        conn = writer.add_connection(TOPIC, msgtype, typestore=ts)
        c_odo = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        c_imu = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=ts)
        for t, msg in msgs:
            writer.write(conn, t, ts.serialize_cdr(msg, msgtype))
        for (t, m), (_, i) in zip(odo, imu, strict=True):
            writer.write(c_odo, t + 1000, ts.serialize_cdr(m, "nav_msgs/msg/Odometry"))
            writer.write(c_imu, t + 2000, ts.serialize_cdr(i, "sensor_msgs/msg/Imu"))
    shutil.copy(folder / "rig.yaml", bag.parent / "rig.yaml")


def test_bag_odometry_and_imu_topics_are_read(folder: Path, tmp_path: Path) -> None:
    from omnipipe.inputs.sensors import gravity_at, odometry_at

    bag = tmp_path / "s" / "bag"
    bag.parent.mkdir()
    _write_ros2_with_sensors(folder, bag)
    ds = open_dataset(bag)
    assert len(ds) == 8 and ds.odometry is not None and ds.imu is not None
    np.testing.assert_allclose(ds.odometry.distance_mm, np.arange(30.0), atol=1e-9)
    np.testing.assert_allclose(ds.odometry.sigma_mm, np.sqrt(0.5), rtol=1e-9)
    d, s = odometry_at(ds.odometry, ds.timestamps)
    np.testing.assert_allclose(d, 2.5 * np.arange(8), atol=1e-6)  # frames 8/s, odometry 20/s
    np.testing.assert_allclose(s, np.sqrt(0.5), rtol=1e-9)
    np.testing.assert_allclose(ds.imu.gyro[:, 2], 0.01)
    g, _ = gravity_at(ds.imu, ds.timestamps[4:5], window_s=0.5)
    np.testing.assert_allclose(g[0], [0.0, -1.0, 0.0], atol=1e-12)
    # The simulated image folder has odometry.txt; a bag with images only has no sensors.
    assert open_dataset(folder).odometry is not None
    plain = tmp_path / "p" / "bag"
    plain.parent.mkdir()
    _write_ros2(folder, plain, "compressed", StoragePlugin.SQLITE3)
    assert open_dataset(plain).odometry is None and open_dataset(plain).imu is None


def test_bag_sensor_stamps_out_of_order_are_refused(folder: Path, tmp_path: Path) -> None:
    bag = tmp_path / "s" / "bag"
    bag.parent.mkdir()
    _write_ros2_with_sensors(folder, bag, bad_stamp=True)
    with pytest.raises(DatasetError, match=r"topic /odom message \d+: time .* increase strictly"):
        open_dataset(bag)

"""``omnipipe export-bag DATASET --out FILE.mcap|FILE.bag|DIR``: a dataset as a ROS bag.

The output reads back through ``omnipipe reconstruct`` (:mod:`omnipipe.inputs.rosbag`)
to the same frames and timestamps, so the same reconstruction:

* ``FILE.mcap``: one MCAP file (ROS 2, CDR), rig.yaml beside it;
* ``FILE.bag``: a ROS 1 bag, rig.yaml beside it;
* ``DIR``: a ROS 2 bag folder (metadata.yaml and MCAP storage), rig.yaml inside it.

Images: ``sensor_msgs/CompressedImage`` carrying each PNG / JPEG frame file's own
bytes (``format`` png / jpeg: nothing re-encoded, the frames read back bit for bit;
frames that are not such files, e.g. from a video, are PNG-encoded), or with
``--raw`` ``sensor_msgs/Image`` (rgb8, mono8 or mono16). ``header.stamp`` and the
record time are the dataset's timestamps (timestamps.txt; without it frame i at i s,
whose first stamp 0 the reader takes for unset: it then uses the equal record times,
with a warning). Topic ``--topic`` (default :data:`DEFAULT_TOPIC`), frame_id
``omnipipe_rig``.

Nothing is written until the whole bag is: it is made in a temporary sibling and
moved into place. An existing OUT, or a different rig.yaml where the bag's must go,
is refused.

The robot's sensors, when the dataset has them (DATA_CONTRACT section 1), go on their own
topics in time order with the frames: odometry.txt as ``nav_msgs/Odometry`` on
:data:`ODOMETRY_TOPIC` (the travel as the position's x in metres, its sigma as the x
variance; the reader takes the path length, so a travel that starts above 0 reads back
from 0) and imu.txt as ``sensor_msgs/Imu`` on :data:`IMU_TOPIC` (no orientation; no gyro
where the file has none: covariance[0] = -1). Sensor readings before time 0 (a simulator's
IMU starts before the first frame) cannot be stamped in a bag and are left out.
"""

from __future__ import annotations

import argparse
import heapq
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from omnipipe.errors import DatasetError, OutputError
from omnipipe.inputs.rosbag import MISSING

if TYPE_CHECKING:
    from omnipipe.dataset import Dataset

DEFAULT_TOPIC = "/omnipipe/image"
ODOMETRY_TOPIC = "/omnipipe/odometry"
IMU_TOPIC = "/omnipipe/imu"
_ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
_IMU_TYPE = "sensor_msgs/msg/Imu"
FRAME_ID = "omnipipe_rig"
_FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg"}


@dataclass(frozen=True)
class BagTarget:
    """Where and how the bag goes.

    Attributes:
        out: the bag (file or folder).
        kind: "mcap", "ros1" or "ros2-folder".
        rig_path: where rig.yaml goes (beside a file, inside a folder).
    """

    out: Path
    kind: str
    rig_path: Path


def bag_target(out: str | Path) -> BagTarget:
    """The kind of bag ``out`` names (module docstring).

    Raises:
        OutputError: ``out`` exists or its folder does not.
    """
    out = Path(out)
    if out.exists():
        raise OutputError(f"{out}: already exists (export-bag never replaces anything)")
    if not out.parent.is_dir():
        raise OutputError(f"{out}: folder {out.parent} does not exist")
    suffix = out.suffix.lower()
    if suffix == ".mcap":
        return BagTarget(out, "mcap", out.parent / "rig.yaml")
    if suffix == ".bag":
        return BagTarget(out, "ros1", out.parent / "rig.yaml")
    return BagTarget(out, "ros2-folder", out / "rig.yaml")


def _stamp_ns(t: float) -> int:
    ns = int(round(float(t) * 1e9))
    if ns < 0:
        raise DatasetError(f"timestamp {t} s is negative: a bag's times are not")
    return ns


def _image_message(
    types: dict[str, Any], header: object, path: Path, image: np.ndarray | None, raw: bool
) -> object:
    """One sensor_msgs message of a frame (``types``: a rosbags typestore's classes;
    ``image``: its decoded pixels, or None to carry the file's own PNG/JPEG bytes)."""
    if not raw:
        fmt = _FORMATS.get(path.suffix.lower())
        if image is None and fmt is not None and path.is_file():
            data = np.frombuffer(path.read_bytes(), np.uint8)
        else:
            import cv2

            rgb = np.asarray(image)
            ok, png = cv2.imencode(".png", rgb[:, :, ::-1] if rgb.ndim == 3 else rgb)
            if not ok:
                raise DatasetError(f"{path}: cannot encode the frame as PNG")
            data, fmt = png.ravel(), "png"
        return types["sensor_msgs/msg/CompressedImage"](header=header, format=fmt, data=data)
    img = np.asarray(image)
    if img.ndim == 3 and img.dtype == np.uint8:
        enc, channels = "rgb8", 3
    elif img.ndim == 2 and img.dtype in (np.uint8, np.uint16):
        enc, channels = ("mono8" if img.dtype == np.uint8 else "mono16"), 1
    else:
        raise DatasetError(
            f"{path}: {img.dtype} {'colour' if img.ndim == 3 else 'grey'} frames have no "
            "sensor_msgs/Image encoding the reader takes; export without --raw"
        )
    data = np.ascontiguousarray(img).astype(img.dtype.newbyteorder("<")).view(np.uint8).ravel()
    return types["sensor_msgs/msg/Image"](
        header=header, height=img.shape[0], width=img.shape[1], encoding=enc, is_bigendian=0,
        step=img.shape[1] * channels * img.dtype.itemsize, data=data,
    )


def export_bag(dataset_dir: str | Path, out: str | Path, topic: str = DEFAULT_TOPIC, raw: bool = False) -> BagTarget:
    """Write the dataset's frames as a bag (module docstring); returns where it went.

    Raises:
        DatasetError: the dataset cannot be read, or rosbags is missing.
        OutputError: OUT exists, or a different rig.yaml is where the bag's must go.
    """
    from omnipipe.dataset import open_dataset

    target = bag_target(out)
    dataset = open_dataset(dataset_dir)
    rig_text = dataset_rig_text(dataset)
    if target.kind != "ros2-folder" and target.rig_path.exists():
        if target.rig_path.read_bytes() != rig_text:
            raise OutputError(
                f"{target.rig_path}: exists with other content; the bag needs its rig.yaml "
                "beside it: choose another folder"
            )
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise DatasetError(MISSING) from None
    tmp = target.out.parent / f".{target.out.name}.partial-{os.getpid()}"
    tmp.mkdir()
    try:
        store = Stores.ROS1_NOETIC if target.kind == "ros1" else Stores.ROS2_HUMBLE
        written = _write(dataset, tmp, target.kind, get_typestore(store), topic, raw)
        if target.kind == "ros2-folder":
            (written / "rig.yaml").write_bytes(rig_text)
        elif not target.rig_path.exists():
            (tmp / "rig.yaml").write_bytes(rig_text)
            os.replace(tmp / "rig.yaml", target.rig_path)
        os.replace(written, target.out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def dataset_rig_text(dataset: Dataset) -> bytes:
    """The bytes of the dataset's rig.yaml."""
    path = Path(dataset.root) / "rig.yaml"
    if not path.is_file():
        raise DatasetError(f"{path}: not found (export-bag copies the dataset's rig.yaml)")
    return path.read_bytes()


def _header(ts: Any, kind: str, ns: int, seq: int) -> object:
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
    if kind == "ros1":
        return Header(seq=seq, stamp=stamp, frame_id=FRAME_ID)
    return Header(stamp=stamp, frame_id=FRAME_ID)


def _sensor_messages(dataset: Dataset, ts: Any, kind: str) -> Iterator[tuple[int, str, object]]:
    """(stamp ns, topic, message) of the dataset's odometry and IMU, each in time order."""
    t = ts.types
    vec = t["geometry_msgs/msg/Vector3"]
    quat = t["geometry_msgs/msg/Quaternion"]
    odo = dataset.odometry
    if odo is not None:
        for i, (time, d, sigma) in enumerate(
            zip(odo.timestamps, odo.distance_mm, odo.sigma_mm, strict=True)
        ):
            if time < 0:
                continue
            ns = _stamp_ns(time)
            cov = np.zeros(36)
            cov[0] = (float(sigma) / 1000.0) ** 2
            pose = t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=float(d) / 1000.0, y=0.0, z=0.0),
                orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0),
            )
            twist = t["geometry_msgs/msg/Twist"](linear=vec(x=0.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0))
            yield ns, ODOMETRY_TOPIC, t[_ODOMETRY_TYPE](
                header=_header(ts, kind, ns, i), child_frame_id=FRAME_ID,
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
                twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
            )
    imu = dataset.imu
    if imu is not None:
        no = np.zeros(9)
        no[0] = -1.0
        for i, time in enumerate(imu.timestamps):
            if time < 0:
                continue
            ns = _stamp_ns(time)
            a = imu.accel[i]
            w = imu.gyro[i] if imu.gyro is not None else np.zeros(3)
            yield ns, IMU_TOPIC, t[_IMU_TYPE](
                header=_header(ts, kind, ns, i), orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=no.copy(),
                angular_velocity=vec(x=float(w[0]), y=float(w[1]), z=float(w[2])),
                angular_velocity_covariance=np.zeros(9) if imu.gyro is not None else no.copy(),
                linear_acceleration=vec(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                linear_acceleration_covariance=np.zeros(9),
            )


def _write(dataset: Dataset, tmp: Path, kind: str, ts: Any, topic: str, raw: bool) -> Path:
    """Write the bag into ``tmp`` (``ts``: the rosbags typestore of ``kind``); the path of
    the finished bag (file or folder)."""
    msgtype = "sensor_msgs/msg/Image" if raw else "sensor_msgs/msg/CompressedImage"

    def frames() -> Iterator[tuple[int, str, object]]:
        for i, (path, t) in enumerate(zip(dataset.frame_paths, dataset.timestamps, strict=True)):
            ns = _stamp_ns(t)
            carry = not raw and Path(path).suffix.lower() in _FORMATS and Path(path).is_file()
            image = None if carry else dataset.read_frame(i)
            yield ns, topic, _image_message(ts.types, _header(ts, kind, ns, i), Path(path), image, raw)

    types = {topic: msgtype, ODOMETRY_TOPIC: _ODOMETRY_TYPE, IMU_TOPIC: _IMU_TYPE}
    used = {topic}
    if dataset.odometry is not None:
        used.add(ODOMETRY_TOPIC)
    if dataset.imu is not None:
        used.add(IMU_TOPIC)

    def messages() -> Iterator[tuple[int, str, object]]:
        sensors = sorted(_sensor_messages(dataset, ts, kind), key=lambda m: m[0])
        return heapq.merge(frames(), iter(sensors), key=lambda m: m[0])

    if kind == "ros1":
        from rosbags.rosbag1 import Writer as Writer1

        bag = tmp / "bag.bag"
        with Writer1(bag) as writer:
            conns = {name: writer.add_connection(name, types[name], typestore=ts) for name in sorted(used)}
            for ns, name, msg in messages():
                writer.write(conns[name], ns, ts.serialize_ros1(msg, types[name]))
        return bag
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    folder = tmp / "bag"
    with Writer2(folder, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {name: writer.add_connection(name, types[name], typestore=ts) for name in sorted(used)}
        for ns, name, msg in messages():
            writer.write(conns[name], ns, ts.serialize_cdr(msg, types[name]))
    if kind == "ros2-folder":
        return folder
    files = sorted(folder.glob("*.mcap"))
    if len(files) != 1:
        raise OutputError(f"{folder}: expected one MCAP file, found {len(files)}")
    return files[0]


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``export-bag`` sub-command."""
    p = sub.add_parser(
        "export-bag",
        help="write a dataset folder as a ROS 2 bag / MCAP file (or a ROS 1 .bag)",
        description="Write DATASET's frames (with their timestamps) as a ROS bag that "
        "`omnipipe reconstruct` reads back to the same run: FILE.mcap (ROS 2 MCAP), FILE.bag "
        "(ROS 1) or DIR (ROS 2 bag folder); rig.yaml is copied beside the file or into DIR.",
    )
    p.add_argument("dataset", help="dataset directory (DATA_CONTRACT section 1)")
    p.add_argument("--out", required=True, help="FILE.mcap, FILE.bag or a new folder")
    p.add_argument("--topic", default=DEFAULT_TOPIC, help=f"image topic (default {DEFAULT_TOPIC})")
    p.add_argument("--raw", action="store_true",
                   help="sensor_msgs/Image (rgb8/mono8/mono16) instead of the frames' PNG/JPEG bytes")
    p.set_defaults(func=_main)


def _main(args: argparse.Namespace) -> int:
    target = export_bag(args.dataset, args.out, args.topic, args.raw)
    print(f"wrote {target.out} ({target.kind}, topic {args.topic}); rig.yaml: {target.rig_path}")
    return 0

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

TODO: odometry.txt and imu.txt (DATA_CONTRACT section 1) are not written yet: their
readers (``omnipipe.inputs.sensors``) are not on main; with them, nav_msgs/Odometry
(or a std_msgs travel topic) and sensor_msgs/Imu topics belong here.
"""

from __future__ import annotations

import argparse
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


def _write(dataset: Dataset, tmp: Path, kind: str, ts: Any, topic: str, raw: bool) -> Path:
    """Write the bag into ``tmp`` (``ts``: the rosbags typestore of ``kind``); the path of
    the finished bag (file or folder)."""
    msgtype = "sensor_msgs/msg/Image" if raw else "sensor_msgs/msg/CompressedImage"
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]

    def messages() -> Iterator[tuple[int, object]]:
        for i, (path, t) in enumerate(zip(dataset.frame_paths, dataset.timestamps, strict=True)):
            ns = _stamp_ns(t)
            stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
            header = (Header(seq=i, stamp=stamp, frame_id=FRAME_ID) if kind == "ros1"
                      else Header(stamp=stamp, frame_id=FRAME_ID))
            carry = not raw and Path(path).suffix.lower() in _FORMATS and Path(path).is_file()
            image = None if carry else dataset.read_frame(i)
            yield ns, _image_message(ts.types, header, Path(path), image, raw)

    if kind == "ros1":
        from rosbags.rosbag1 import Writer as Writer1

        bag = tmp / "bag.bag"
        with Writer1(bag) as writer:
            conn = writer.add_connection(topic, msgtype, typestore=ts)
            for ns, msg in messages():
                writer.write(conn, ns, ts.serialize_ros1(msg, msgtype))
        return bag
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    folder = tmp / "bag"
    with Writer2(folder, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(topic, msgtype, typestore=ts)
        for ns, msg in messages():
            writer.write(conn, ns, ts.serialize_cdr(msg, msgtype))
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

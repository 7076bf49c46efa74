"""Images from ROS 1 bags, ROS 2 bags (SQLite or MCAP storage) and MCAP files.

Read with the pure-Python ``rosbags`` package (optional extra: ``pip install
'omnipipe[ros]'``). One image topic is read: ``--topic``, or the only topic of type
``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` in the bag. Frames are in the
bag's message order; their timestamps are the messages' ``header.stamp`` (seconds),
or, when a header stamp is unset (0) or the stamps do not increase strictly, the times
the messages were recorded (with a warning).

The messages' payloads are kept in memory and decoded on demand (a compressed image
is a few hundred kB; raw images take what a decoded video takes).

The robot's sensors (contract section 1), both optional, are read from the bag's only
topic of each type (:func:`read_bag_sensors`; with several topics of a type none is
read and a warning says so):

* ``nav_msgs/Odometry``: the distance travelled is the path length of
  ``pose.pose.position`` (m -> mm) summed from the first message; its sigma is the
  position's 1-sigma, sqrt(var x + var y + var z) of ``pose.covariance`` (mm), when the
  covariance is set (else the defaults of :mod:`omnipipe.inputs.sensors`).
* ``sensor_msgs/Imu``: ``linear_acceleration`` (m/s^2) and ``angular_velocity``
  (rad/s), which must be in the rig frame (no extrinsic is applied); the gyro is absent
  when ``angular_velocity_covariance[0]`` is -1 (the ROS convention for "not provided").

Their times are the header stamps; readings whose stamps do not increase strictly are
refused naming the topic and message.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omnipipe.errors import ConfigError, DatasetError, one_line, yaml_reason
from omnipipe.inputs.sensors import Imu, Odometry
from omnipipe.native import quiet_native_stderr

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
IMU_TYPE = "sensor_msgs/msg/Imu"
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
MISSING = (
    "reading ROS bags and MCAP files needs the optional package 'rosbags': "
    "pip install 'omnipipe[ros]'"
)


def is_bag(path: Path) -> bool:
    """A ROS 1 bag, an MCAP/SQLite ROS 2 storage file, or a ROS 2 bag folder."""
    if path.is_file():
        return path.suffix.lower() in BAG_SUFFIXES
    return path.is_dir() and (path / "metadata.yaml").is_file()


@dataclass(frozen=True)
class BagImages:
    """The image messages of one topic.

    Attributes:
        path: the bag.
        topic: the topic read.
        msgtype: ``sensor_msgs/msg/Image`` or ``sensor_msgs/msg/CompressedImage``.
        timestamps: (N,) seconds, strictly increasing.
        formats: per message, the CompressedImage ``format`` or the Image ``encoding``.
        warnings: problems that do not stop a run.
    """

    path: Path
    topic: str
    msgtype: str
    timestamps: np.ndarray
    formats: tuple[str, ...]
    warnings: tuple[str, ...]
    _messages: tuple[Any, ...]

    def __len__(self) -> int:
        return len(self._messages)

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` as RGB (H, W, 3) or grey (H, W), uint8 or uint16.

        Raises:
            DatasetError: an undecodable message or an unsupported encoding.
        """
        msg = self._messages[index]
        where = f"{self.path} topic {self.topic} message {index}"
        if self.msgtype.endswith("CompressedImage"):
            return decode_compressed(np.asarray(msg.data, dtype=np.uint8), where)
        return decode_raw(msg, where)


def decode_compressed(data: np.ndarray, where: str) -> np.ndarray:
    """A sensor_msgs/CompressedImage payload (JPEG, PNG, ...) as RGB or grey."""
    import cv2

    with quiet_native_stderr():
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise DatasetError(f"{where}: not a decodable compressed image")
    if img.ndim == 3:
        img = img[:, :, :3][:, :, ::-1]  # OpenCV's BGR(A) -> RGB
    return np.ascontiguousarray(img)


_BAYER = {"bayer_rggb8": "RG", "bayer_bggr8": "BG", "bayer_gbrg8": "GB", "bayer_grbg8": "GR"}


def decode_raw(msg: Any, where: str) -> np.ndarray:
    """A sensor_msgs/Image as RGB (H, W, 3) or grey (H, W).

    Encodings: rgb8, bgr8, rgba8, bgra8, mono8, 8UC1, 8UC3 (as bgr8), mono16, 16UC1,
    bayer_{rggb,bggr,gbrg,grbg}8.
    """
    import cv2

    enc = str(msg.encoding).lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    channels, dtype = {
        "rgb8": (3, np.uint8), "bgr8": (3, np.uint8), "8uc3": (3, np.uint8),
        "rgba8": (4, np.uint8), "bgra8": (4, np.uint8),
        "mono8": (1, np.uint8), "8uc1": (1, np.uint8),
        "mono16": (1, np.uint16), "16uc1": (1, np.uint16),
        **{k: (1, np.uint8) for k in _BAYER},
    }.get(enc, (0, None))
    if not channels:
        raise DatasetError(f"{where}: unsupported image encoding {msg.encoding!r}")
    item = np.dtype(dtype).itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if h <= 0 or w <= 0 or step < w * channels * item or data.size < step * h:
        raise DatasetError(f"{where}: image data does not match {w}x{h}, step {step}")
    rows = data[: step * h].reshape(h, step)[:, : w * channels * item]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    img = rows.copy().view(dt).reshape(h, w, channels).astype(dtype)
    if enc in _BAYER:
        code = getattr(cv2, f"COLOR_Bayer{_BAYER[enc]}2RGB")
        return np.ascontiguousarray(cv2.cvtColor(img[:, :, 0], code))
    if channels == 1:
        return np.ascontiguousarray(img[:, :, 0])
    if enc in ("bgr8", "bgra8", "8uc3"):
        img = img[:, :, 2::-1]
    return np.ascontiguousarray(img[:, :, :3])


def _reader_class() -> Callable[..., Any]:
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise DatasetError(MISSING) from None
    return AnyReader


def read_bag(path: Path, topic: str | None = None) -> BagImages:
    """Read the image messages of ``topic`` (or of the bag's only image topic).

    Raises:
        DatasetError: rosbags missing, unreadable bag, no or several image topics, an
            empty topic, or timestamps that do not increase.
        ConfigError: ``--topic`` names a topic that is not an image topic of the bag.
    """
    AnyReader = _reader_class()
    from rosbags.highlevel import AnyReaderError

    path = Path(path)
    try:
        reader = AnyReader([path])
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as exc:
        raise DatasetError(f"{path}: not a readable ROS bag or MCAP file ({_reason(exc)})") from None
    try:
        images = sorted({c.topic for c in reader.connections if c.msgtype in IMAGE_TYPES})
        if topic is None:
            if not images:
                all_topics = sorted({c.topic for c in reader.connections})
                raise DatasetError(
                    f"{path}: no sensor_msgs/Image or CompressedImage topic (topics: "
                    f"{', '.join(all_topics) or 'none'})"
                )
            if len(images) > 1:
                raise DatasetError(
                    f"{path}: several image topics ({', '.join(images)}); choose one with --topic"
                )
            topic = images[0]
        elif topic not in images:
            raise ConfigError(
                "--topic",
                f"{topic!r} is not an image topic of {path} (image topics: "
                f"{', '.join(images) or 'none'})",
            )
        conns = [c for c in reader.connections if c.topic == topic]
        msgtype = conns[0].msgtype
        messages, header_t, log_t, formats = [], [], [], []
        for conn, log_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            messages.append(msg)
            stamp = msg.header.stamp
            header_t.append(int(stamp.sec) + 1e-9 * int(stamp.nanosec))
            log_t.append(1e-9 * log_ns)
            formats.append(str(getattr(msg, "format", None) or getattr(msg, "encoding", "")))
    except (AnyReaderError, OSError, ValueError, KeyError, AttributeError) as exc:
        raise DatasetError(f"{path}: cannot read topic {topic} ({_reason(exc)})") from None
    finally:
        reader.close()
    if not messages:
        raise DatasetError(f"{path}: topic {topic} holds no message")
    warnings: list[str] = []
    stamps = np.array(header_t)
    if (stamps <= 0).any() or (np.diff(stamps) <= 0).any():
        stamps = np.array(log_t)
        warnings.append(
            f"{path.name} {topic}: header stamps unset or not increasing; using the times "
            "the messages were recorded"
        )
        if (np.diff(stamps) <= 0).any():
            raise DatasetError(
                f"{path}: topic {topic}: neither header stamps nor record times increase "
                "strictly; cannot order the frames"
            )
    return BagImages(
        path=path,
        topic=topic,
        msgtype=msgtype,
        timestamps=stamps,
        formats=tuple(formats),
        warnings=tuple(warnings),
        _messages=tuple(messages),
    )


def _reason(exc: BaseException) -> str:
    """A reader's error in one line: a broken metadata.yaml names the problem and its
    line, not the YAML parser's context lines."""
    problem = yaml_reason(exc)
    if problem is not None:
        return f"metadata.yaml: {problem}"
    return one_line(str(exc)) or type(exc).__name__


def find_rig(path: Path) -> Path:
    """rig.yaml of a bag: inside a ROS 2 bag folder or beside it; beside a bag file, or
    beside the ROS 2 bag folder that holds the file."""
    bag_dir = path if path.is_dir() else path.parent
    for candidate in (bag_dir / "rig.yaml", bag_dir.parent / "rig.yaml"):
        if candidate.is_file() and (candidate.parent == bag_dir or (bag_dir / "metadata.yaml").is_file()):
            return candidate
    return bag_dir / "rig.yaml"


def _sensor_topic(reader: Any, msgtype: str, path: Path, warnings: list[str]) -> str | None:
    topics = sorted({c.topic for c in reader.connections if c.msgtype == msgtype})
    if len(topics) > 1:
        warnings.append(
            f"{path.name}: several {msgtype} topics ({', '.join(topics)}); none of them read"
        )
        return None
    return topics[0] if topics else None


def _stamp(msg: Any) -> float:
    return int(msg.header.stamp.sec) + 1e-9 * int(msg.header.stamp.nanosec)


def read_bag_sensors(path: Path) -> tuple[Odometry | None, Imu | None, tuple[str, ...]]:
    """The bag's optional odometry (nav_msgs/Odometry) and IMU (sensor_msgs/Imu), see the
    module docstring; (None, None, ()) for a bag without them.

    Raises:
        DatasetError: an unreadable sensor topic, or stamps that do not increase.
    """
    from rosbags.highlevel import AnyReader, AnyReaderError

    from omnipipe.inputs.sensors import make_imu, make_odometry

    path = Path(path)
    warnings: list[str] = []
    odometry = imu = None
    try:
        with AnyReader([path]) as reader:
            for msgtype in (ODOMETRY_TYPE, IMU_TYPE):
                topic = _sensor_topic(reader, msgtype, path, warnings)
                if topic is None:
                    continue
                conns = [c for c in reader.connections if c.topic == topic]
                msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
                if not msgs:
                    continue
                t = np.array([_stamp(m) for m in msgs])
                where = f"{path} topic {topic} message {{}}".format
                if msgtype == ODOMETRY_TYPE:
                    odometry = make_odometry(f"{path} {topic}", t, *_odometry_arrays(msgs), where)
                else:
                    acc = np.array([_xyz(m.linear_acceleration) for m in msgs])
                    gyro = np.array([_xyz(m.angular_velocity) for m in msgs])
                    has_gyro = float(msgs[0].angular_velocity_covariance[0]) != -1.0
                    imu = make_imu(f"{path} {topic}", t, acc, gyro if has_gyro else None, where)
    except (AnyReaderError, OSError, ValueError, KeyError, AttributeError) as exc:
        raise DatasetError(f"{path}: cannot read the sensor topics ({_reason(exc)})") from None
    return odometry, imu, tuple(warnings)


def _xyz(v: Any) -> tuple[float, float, float]:
    return float(v.x), float(v.y), float(v.z)


def _odometry_arrays(msgs: list[Any]) -> tuple[np.ndarray, np.ndarray | None]:
    """Path length (mm) of nav_msgs/Odometry positions, and the positions' sigma (mm)
    when every message states a covariance."""
    p = np.array([_xyz(m.pose.pose.position) for m in msgs]) * 1000.0
    distance = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    var = np.array([np.asarray(m.pose.covariance, float)[[0, 7, 14]].sum() for m in msgs])
    sigma = 1000.0 * np.sqrt(var) if (var > 0).all() else None
    return distance, sigma

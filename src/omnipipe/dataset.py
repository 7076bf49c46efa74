"""Contract datasets (DATA_CONTRACT.md section 1) and TUM trajectories (section 3).

I/O lives here, at the edge: stages receive arrays and data classes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from omnipipe.errors import ConfigError, DatasetError
from omnipipe.geometry import transform_from_tum, tum_from_transform
from omnipipe.inputs.rosbag import BagImages, find_rig, is_bag, read_bag, read_bag_sensors
from omnipipe.inputs.sensors import Imu, Odometry, read_dataset_sensors
from omnipipe.native import quiet_native_stderr
from omnipipe.output import atomic_output_dir, check_output_dir  # noqa: F401 (re-exported)
from omnipipe.rig import Rig
from omnipipe.rig_yaml import load_rig

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v")


@dataclass(frozen=True)
class Dataset:
    """An opened dataset: a contract directory, or a video file with rig.yaml beside it.

    Attributes:
        root: the dataset directory (for a video: the directory holding it).
        rig: its validated calibration.
        frame_paths: image files in time order (sorted by file name); for a video,
            one pseudo path ``VIDEO#index`` per frame.
        timestamps: (N,) seconds; frame index when timestamps.txt is absent
            (for a video: from its frame rate).
        video: the video file, or None for an image folder.
        warnings: problems found while opening that do not stop a run (e.g. a video
            with fewer decodable frames than its container announces); the pipeline
            copies them into report.json ``warnings``.
        source: for a ROS bag / MCAP file, its :class:`omnipipe.inputs.rosbag.BagImages`;
            for a video, its :class:`omnipipe.inputs.video.VideoFrames` (``read(index)``
            decodes a frame); None otherwise.
        odometry, imu: the robot's optional sensors (odometry.txt, imu.txt or the bag's
            topics; :mod:`omnipipe.inputs.sensors`), None when absent.
    """

    root: Path
    rig: Rig
    frame_paths: tuple[Path, ...]
    timestamps: np.ndarray
    video: Path | None = None
    warnings: tuple[str, ...] = ()
    source: BagImages | None = None
    odometry: Odometry | None = None
    imu: Imu | None = None

    def __len__(self) -> int:
        return len(self.frame_paths)

    def read_frame(self, index: int) -> np.ndarray:
        """Frame ``index`` as an RGB (H, W, 3) or grey (H, W) array (uint8 or uint16)."""
        if self.source is not None:
            img = self.source.read(index)
            cam = self.rig.camera
            if img.shape[:2] != (cam.height, cam.width):
                raise DatasetError(
                    f"{self.frame_paths[index]}: image is {img.shape[1]}x{img.shape[0]} but "
                    f"rig.yaml says {cam.width}x{cam.height}"
                )
            return img
        return read_image(self.frame_paths[index], self.rig)

    @property
    def ground_truth_dir(self) -> Path:
        """Where simulators put ground truth (never read by reconstruction)."""
        return self.root / "ground_truth"


try:  # libspng, where pyspng ships wheels (pyproject.toml)
    import pyspng as _spng
except ImportError:  # pragma: no cover - platforms without its wheels
    _spng = None

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _decode_png8(raw: bytes) -> np.ndarray | None:
    """An 8-bit grey, RGB or RGBA PNG decoded by ISA-L's inflate
    (:func:`omnipipe.inputs.png.decode_png8`: plain files, 9-11 ms at 1600x1200) or
    libspng (21 ms; OpenCV's libpng 30 ms), (H, W) or (H, W, 3 or 4) in RGB order, the
    same pixels either way.

    None for any other file (16-bit, palette, grey with alpha, JPEG), without pyspng, or
    when libspng cannot read it: OpenCV then decodes it or reports it unreadable.
    """
    from omnipipe.inputs.png import decode_png8

    img = decode_png8(raw)  # ISA-L's inflate where installed: the same pixels, faster
    if img is not None:
        return img
    if _spng is None or len(raw) < 33 or raw[:8] != _PNG_SIGNATURE or raw[12:16] != b"IHDR":
        return None
    bit_depth, colour_type = raw[24], raw[25]
    if bit_depth != 8 or colour_type not in (0, 2, 6):  # grey, RGB, RGBA
        return None
    try:
        return _spng.load(raw)
    except RuntimeError:
        return None


def read_image(path: Path, rig: Rig | None = None) -> np.ndarray:
    """Read an image as RGB (H, W, 3) or grey (H, W), 8 or 16 bit.

    Raises:
        DatasetError: unreadable/corrupt file, or a size that differs from the rig's.
    """
    if not Path(path).is_file():
        raise DatasetError(f"{path}: image file not found")
    with open(path, "rb") as fh:
        raw = fh.read()
    img = _decode_png8(raw)
    if img is None:
        with quiet_native_stderr():
            img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED) if raw else None
        if img is None:
            raise DatasetError(f"{path}: not a readable image (corrupt or truncated?)")
        if img.ndim == 3 and img.shape[2] in (3, 4):
            # OpenCV's BGR(A) -> RGB; cvtColor is 5-10x faster than a reversed-stride copy.
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        elif img.ndim == 3:
            img = np.ascontiguousarray(img[:, :, ::-1])
    elif img.ndim == 3 and img.shape[2] == 4:
        img = np.ascontiguousarray(img[:, :, :3])  # the alpha dropped, as OpenCV's path does
    if rig is not None and img.shape[:2] != (rig.camera.height, rig.camera.width):
        raise DatasetError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]} but rig.yaml says "
            f"{rig.camera.width}x{rig.camera.height}"
        )
    return img


def write_image(path: Path, image: np.ndarray) -> None:
    """Write an RGB (H, W, 3) or grey (H, W) array as PNG."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[:, :, ::-1]
    if not cv2.imwrite(str(path), img):
        raise DatasetError(f"{path}: could not write image")


def open_video(path: Path) -> Dataset:
    """Open a video file as a dataset; its rig.yaml lies in the same directory.

    The video is decoded once here (every frame's time, the count of decodable frames)
    and then as a stream when frames are read (:class:`omnipipe.inputs.video.VideoFrames`,
    the dataset's ``source``): no decoded frame is held.
    """
    from omnipipe.inputs.video import VideoFrames, scan_video

    rig = load_rig(path.parent / "rig.yaml")
    scan = scan_video(path)
    if (scan.height, scan.width) != (rig.camera.height, rig.camera.width):
        raise DatasetError(
            f"{path}: video is {scan.width}x{scan.height} but rig.yaml says "
            f"{rig.camera.width}x{rig.camera.height}"
        )
    n = scan.frames
    names = tuple(Path(f"{path.name}#{i:06d}") for i in range(n))
    # The container's presentation times when they are usable (frame-accurate, also for
    # variable frame rates); else frame index / frame rate.
    stamps = scan.times_s
    if len(stamps) < 2 or not np.isfinite(stamps).all() or not (np.diff(stamps) > 0).all():
        stamps = np.arange(n) / scan.fps if scan.fps > 0 else np.arange(n, dtype=float)
    warnings: tuple[str, ...] = ()
    if scan.announced > n:
        warnings = (
            f"{path.name}: the container announces {scan.announced} frames but only the first "
            f"{n} could be decoded (truncated or damaged video); using those",
        )
    return Dataset(
        root=path.parent,
        rig=rig,
        frame_paths=names,
        timestamps=stamps,
        video=path,
        warnings=warnings,
        source=VideoFrames(path, n, scan.times_s),
    )


def open_bag(path: str | Path, topic: str | None = None) -> Dataset:
    """Open a bag's image topic (:mod:`omnipipe.inputs.rosbag`) as a :class:`Dataset`.

    rig.yaml lies inside a ROS 2 bag folder or beside the bag. Frames are named
    ``BAG#000000`` ...; the first is decoded here to check its size against the rig.

    Raises:
        DatasetError / ConfigError: as :func:`read_bag`, a missing rig.yaml, or frames of
            another size than the rig's.
    """
    path = Path(path)
    rig = load_rig(find_rig(path))
    images = read_bag(path, topic)
    odometry, imu, sensor_warnings = read_bag_sensors(path)
    first = images.read(0)
    cam = rig.camera
    if first.shape[:2] != (cam.height, cam.width):
        raise DatasetError(
            f"{path}: topic {images.topic} images are {first.shape[1]}x{first.shape[0]} but "
            f"rig.yaml says {cam.width}x{cam.height}"
        )
    names = tuple(Path(f"{path.name}#{i:06d}") for i in range(len(images)))
    return Dataset(
        root=find_rig(path).parent,
        rig=rig,
        frame_paths=names,
        timestamps=images.timestamps,
        warnings=images.warnings + sensor_warnings,
        source=images,
        odometry=odometry,
        imu=imu,
    )


def open_dataset(root: str | Path, topic: str | None = None) -> Dataset:
    """Open and validate a dataset: a directory (rig.yaml, frames/, timestamps.txt), a
    video file (MP4, AVI, MOV, MKV) with rig.yaml beside it, or a ROS 1 bag, ROS 2 bag
    folder or MCAP file (image ``topic``, default: its only image topic) with rig.yaml
    beside it (:mod:`omnipipe.inputs.rosbag`).

    Raises:
        DatasetError / ConfigError: naming the missing or invalid file or field.
    """
    root = Path(root)
    if is_bag(root):
        return open_bag(root, topic)
    if topic is not None:
        raise ConfigError("--topic", "applies only to ROS bags and MCAP files")
    if root.is_file() and root.suffix.lower() in VIDEO_SUFFIXES:
        return open_video(root)
    if root.is_file():
        raise DatasetError(
            f"{root}: expected a dataset directory, a video ({', '.join(VIDEO_SUFFIXES)}) or "
            "a ROS bag / MCAP file (.bag, .mcap, .db3)"
        )
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset directory not found")
    rig = load_rig(root / "rig.yaml")
    frames_dir = root / "frames"
    if not frames_dir.is_dir():
        raise DatasetError(f"{frames_dir}: frames directory not found")
    paths = tuple(
        sorted(
            p for p in frames_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
        )
    )
    if not paths:
        raise DatasetError(f"{frames_dir}: no PNG or JPEG frames")
    stamps = np.arange(len(paths), dtype=float)
    ts_file = root / "timestamps.txt"
    if ts_file.is_file():
        stamps = _read_timestamps(ts_file, paths)
    odometry, imu = read_dataset_sensors(root)
    return Dataset(root, rig, paths, stamps, odometry=odometry, imu=imu)


def _read_timestamps(path: Path, frame_paths: tuple[Path, ...]) -> np.ndarray:
    """(N,) timestamps of ``frame_paths`` from timestamps.txt.

    Lines are ``<file name> <seconds>``; blank lines and ``#`` comments are skipped
    (comments may hold any bytes). Every frame needs exactly one finite timestamp, and
    timestamps must increase strictly in frame (file name) order: otherwise a
    DatasetError names the file and line.
    """
    table: dict[str, tuple[float, int]] = {}
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    for n, raw_line in enumerate(raw.splitlines(), start=1):
        line = raw_line.decode("utf-8", errors="replace").strip()
        if not line or line.startswith("#"):
            continue
        if "\ufffd" in line:
            raise DatasetError(f"{path}:{n}: not UTF-8 text")
        parts = line.split()
        try:
            if len(parts) != 2:
                raise ValueError
            value = float(parts[1])
        except ValueError:
            raise DatasetError(
                f"{path}:{n}: expected '<file name> <seconds>', got {line[:80]!r}"
            ) from None
        if not math.isfinite(value):
            raise DatasetError(f"{path}:{n}: timestamp must be a finite number, got {parts[1]}")
        if parts[0] in table:
            raise DatasetError(
                f"{path}:{n}: second timestamp for {parts[0]} (first on line {table[parts[0]][1]})"
            )
        table[parts[0]] = (value, n)
    missing = [p.name for p in frame_paths if p.name not in table]
    if missing:
        raise DatasetError(f"{path}: no timestamp for frame {missing[0]}")
    stamps = np.array([table[p.name][0] for p in frame_paths])
    for i in range(1, len(frame_paths)):
        if not stamps[i] > stamps[i - 1]:
            name, prev = frame_paths[i].name, frame_paths[i - 1].name
            raise DatasetError(
                f"{path}:{table[name][1]}: timestamp {stamps[i]:g} s of {name} is not after "
                f"{stamps[i - 1]:g} s of the frame before it ({prev}); timestamps must "
                "increase strictly in frame order"
            )
    return stamps


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory.

    Returns:
        timestamps: (N,) seconds.
        world_from_rig: (N, 4, 4) transforms (mm).
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: trajectory file not found")
    stamps, poses = [], []
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    for n, raw_line in enumerate(raw.splitlines(), start=1):
        line = raw_line.decode("utf-8", errors="replace").strip()
        if not line or line.startswith("#"):
            continue  # comments may hold any bytes
        try:
            values = [float(v) for v in line.split()]
        except ValueError:
            raise DatasetError(f"{path}:{n}: not numbers: {line[:80]!r}") from None
        if len(values) != 8:
            raise DatasetError(
                f"{path}:{n}: expected 8 values 't tx ty tz qx qy qz qw', got {len(values)}"
            )
        q = np.array(values[4:8])
        if not np.isfinite(values).all() or abs(np.linalg.norm(q) - 1.0) > 1e-3:
            raise DatasetError(f"{path}:{n}: quaternion is not a finite unit quaternion")
        stamps.append(values[0])
        poses.append(transform_from_tum(np.array(values[1:])))
    return np.array(stamps), np.array(poses).reshape(-1, 4, 4)


def write_tum(path: str | Path, timestamps: np.ndarray, world_from_rig: np.ndarray) -> None:
    """Write (N,) timestamps and (N, 4, 4) world_from_rig transforms as TUM."""
    lines = []
    for t, T in zip(timestamps, world_from_rig, strict=True):
        row = tum_from_transform(T)
        lines.append(f"{t:.6f} " + " ".join(f"{v:.9g}" for v in row))
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def validate_frames(dataset: Dataset) -> None:
    """Check every frame's header (format and size) without decoding the pixels.

    Raises:
        DatasetError: naming the first frame that is not an image or has the wrong size.
    """
    if dataset.video is not None or dataset.source is not None:
        return  # decoded and size-checked when opened (and when read)
    from PIL import Image, UnidentifiedImageError

    cam = dataset.rig.camera
    for path in dataset.frame_paths:
        try:
            with Image.open(path) as img:
                size = img.size
        except (UnidentifiedImageError, OSError):
            raise DatasetError(f"{path}: not a readable image (corrupt or truncated?)") from None
        if size != (cam.width, cam.height):
            raise DatasetError(
                f"{path}: image is {size[0]}x{size[1]} but rig.yaml says {cam.width}x{cam.height}"
            )

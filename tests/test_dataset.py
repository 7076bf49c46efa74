"""Opening datasets: image folders, videos, and every kind of bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from omnipipe.dataset import open_dataset, read_tum, validate_frames, write_tum
from omnipipe.errors import ConfigError, DatasetError


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_simulated_dataset_follows_the_contract(small_dataset: Path) -> None:
    ds = open_dataset(small_dataset)
    assert len(ds) == 24 and ds.frame_paths[0].name == "000000.png"
    validate_frames(ds)
    img = ds.read_frame(0)
    assert img.shape == (300, 400, 3) and img.dtype == np.uint8
    stamps, poses = read_tum(small_dataset / "ground_truth" / "poses.txt")
    assert np.allclose(stamps, ds.timestamps)
    assert poses.shape == (24, 4, 4)


def test_tum_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, :3, :3] = Rotation.random(5, random_state=1).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 100, (5, 3))
    write_tum(tmp_path / "t.txt", np.arange(5) * 0.1, poses)
    stamps, back = read_tum(tmp_path / "t.txt")
    assert np.allclose(back, poses, atol=1e-7) and np.allclose(stamps, np.arange(5) * 0.1)


def test_video_source(small_dataset: Path, tmp_path: Path) -> None:
    shutil.copy(small_dataset / "rig.yaml", tmp_path / "rig.yaml")
    writer = cv2.VideoWriter(
        str(tmp_path / "run.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 8.0, (400, 300)
    )
    ds0 = open_dataset(small_dataset)
    for i in range(6):
        writer.write(ds0.read_frame(i)[:, :, ::-1])
    writer.release()
    ds = open_dataset(tmp_path / "run.mp4")
    assert len(ds) == 6 and ds.read_frame(3).shape == (300, 400, 3)
    assert ds.timestamps[1] == pytest.approx(1 / 8.0)
    # Lossy, but the same picture.
    assert np.abs(ds.read_frame(2).astype(float) - ds0.read_frame(2)).mean() < 8.0


@pytest.mark.parametrize(
    ("damage", "error", "message"),
    [
        ("no_rig", ConfigError, "rig.yaml"),
        ("no_frames", DatasetError, "frames directory not found"),
        ("empty_frames", DatasetError, "no PNG or JPEG frames"),
        ("bad_field", ConfigError, "mirror.a"),
        ("truncated", DatasetError, "000003.png"),
        ("not_image", DatasetError, "000005.png"),
        ("other_size", DatasetError, "000007.png: image is 200x150"),
        ("bad_timestamps", DatasetError, "timestamps.txt"),
    ],
)
def test_bad_datasets_name_the_file_or_field(
    small_dataset: Path, tmp_path: Path, damage: str, error: type, message: str
) -> None:
    ds = _copy(small_dataset, tmp_path / "ds")
    frames = ds / "frames"
    if damage == "no_rig":
        (ds / "rig.yaml").unlink()
    elif damage == "no_frames":
        shutil.rmtree(frames)
    elif damage == "empty_frames":
        for p in frames.iterdir():
            p.unlink()
    elif damage == "bad_field":
        text = (ds / "rig.yaml").read_text().replace("a: 21.57", "a: -1")
        (ds / "rig.yaml").write_text(text)
    elif damage == "truncated":
        data = (frames / "000003.png").read_bytes()
        (frames / "000003.png").write_bytes(data[: len(data) // 3])
    elif damage == "not_image":
        (frames / "000005.png").write_text("hello")
    elif damage == "other_size":
        img = cv2.imread(str(frames / "000007.png"))
        cv2.imwrite(str(frames / "000007.png"), cv2.resize(img, (200, 150)))
    elif damage == "bad_timestamps":
        (ds / "timestamps.txt").write_text("000000.png zero\n")
    with pytest.raises(error, match=message):
        d = open_dataset(ds)
        validate_frames(d)
        for i in range(len(d)):
            d.read_frame(i)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_read_image_gives_rgb_of_every_png_kind(tmp_path, dtype, channels) -> None:
    from omnipipe.dataset import read_image

    rng = np.random.default_rng(channels)
    shape = (7, 9) if channels == 1 else (7, 9, channels)
    stored = rng.integers(0, np.iinfo(dtype).max, shape).astype(dtype)  # OpenCV order: BGR(A)
    path = tmp_path / "frame.png"
    cv2.imwrite(str(path), stored)
    image = read_image(path)
    expected = stored if channels == 1 else stored[:, :, 2::-1]  # RGB, alpha dropped
    assert image.dtype == dtype and np.array_equal(image, expected)


def test_every_png_kind_reads_the_same_with_libspng_and_opencv(tmp_path, monkeypatch) -> None:
    """8-bit grey/RGB/RGBA PNGs go through libspng when pyspng is installed, the rest
    through OpenCV: the same pixels either way, in RGB order; a truncated 8-bit PNG is
    still one DatasetError."""
    import omnipipe.dataset as dataset_module
    from omnipipe.dataset import read_image

    rng = np.random.default_rng(21)
    cases = {
        "rgb8": rng.integers(0, 256, (30, 40, 3), dtype=np.uint8),
        "rgba8": rng.integers(0, 256, (30, 40, 4), dtype=np.uint8),
        "grey8": rng.integers(0, 256, (30, 40), dtype=np.uint8),
        "rgb16": rng.integers(0, 65536, (30, 40, 3), dtype=np.uint16),
        "grey16": rng.integers(0, 65536, (30, 40), dtype=np.uint16),
    }
    for name, bgr in cases.items():
        path = tmp_path / f"{name}.png"
        assert cv2.imwrite(str(path), bgr)
        got = read_image(path)
        want = bgr if bgr.ndim == 2 else bgr[:, :, 2::-1]  # OpenCV writes BGR(A): RGB, no alpha
        assert got.dtype == bgr.dtype and np.array_equal(got, want), name
        with monkeypatch.context() as m:
            m.setattr(dataset_module, "_spng", None)  # OpenCV alone
            assert np.array_equal(read_image(path), got), name
    raw = (tmp_path / "rgb8.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DatasetError, match="not a readable image"):
        read_image(tmp_path / "cut.png")

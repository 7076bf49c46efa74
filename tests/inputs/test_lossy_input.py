"""Lossy input is detected (block artefacts, video codec) and warned about; lossless is not.
Video frames carry their container timestamps."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from omnipipe.dataset import open_dataset, read_image
from omnipipe.inputs.lossy import BLOCKINESS_WARN, assess_input, blockiness


def _copy(small_dataset: Path, dst: Path, n: int, jpeg_quality: int | None) -> Path:
    (dst / "frames").mkdir(parents=True)
    shutil.copy(small_dataset / "rig.yaml", dst / "rig.yaml")
    for path in sorted((small_dataset / "frames").glob("*.png"))[:n]:
        if jpeg_quality is None:
            shutil.copy(path, dst / "frames" / path.name)
        else:
            bgr = cv2.imread(str(path))
            cv2.imwrite(str(dst / "frames" / f"{path.stem}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    return dst


def test_blockiness_of_a_smooth_image_and_its_jpeg() -> None:
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.normal(128, 40, (240, 320)), (0, 0), 3)
    img = np.clip(noise, 0, 255).astype(np.uint8)
    assert abs(blockiness(img) - 1.0) < 0.1
    jpeg = cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 30])[1], 0)
    assert blockiness(jpeg) > BLOCKINESS_WARN
    assert np.isnan(blockiness(np.zeros((16, 16))))


def test_blockiness_in_whole_numbers_is_the_float_ratio() -> None:
    """Integer frames (grey, colour, 8 and 16 bits, plain and JPEG'd) give the ratio the
    float64 means give, to rounding (1e-12)."""
    from omnipipe.inputs.lossy import _blockiness_float

    rng = np.random.default_rng(1)
    for shape, dtype in (((240, 320), np.uint8), ((240, 320, 3), np.uint8), ((120, 200, 3), np.uint16)):
        top = np.iinfo(dtype).max
        img = np.clip(cv2.GaussianBlur(rng.normal(0.5, 0.2, shape), (0, 0), 2) * top, 0, top).astype(dtype)
        images = [img]
        if dtype == np.uint8:
            images.append(cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 40])[1], -1))
        for im in images:
            assert blockiness(im) == pytest.approx(_blockiness_float(im, 8), rel=1e-12, abs=0.0)
    assert np.isnan(blockiness(np.zeros((16, 16, 3), np.uint8)))


def test_jpeg_frames_are_flagged_png_frames_are_not(small_dataset: Path, tmp_path: Path) -> None:
    png = assess_input(open_dataset(_copy(small_dataset, tmp_path / "png", 6, None)))
    assert not png.lossy and png.warning is None
    assert png.blockiness is not None and abs(png.blockiness - 1.0) < 0.1
    jpg = assess_input(open_dataset(_copy(small_dataset, tmp_path / "jpg", 6, 30)))
    assert jpg.lossy and jpg.frames_sampled == 5
    assert jpg.blockiness > BLOCKINESS_WARN
    assert jpg.warning is not None and jpg.warning.startswith("lossy input: 8x8 block")
    assert jpg.to_dict()["lossy"] is True


def test_mjpeg_video_flagged_with_codec_and_container_timestamps(
    small_dataset: Path, tmp_path: Path
) -> None:
    frames = sorted((small_dataset / "frames").glob("*.png"))[:10]
    first = read_image(frames[0])
    h, w = first.shape[:2]
    video = tmp_path / "run.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 8.0, (w, h))
    for path in frames:
        writer.write(cv2.imread(str(path)))
    writer.release()
    shutil.copy(small_dataset / "rig.yaml", tmp_path / "rig.yaml")
    ds = open_dataset(video)
    np.testing.assert_allclose(ds.timestamps, np.arange(10) / 8.0, atol=1e-3)
    q = assess_input(ds)
    assert q.lossy and q.codec == "MJPG"
    assert "lossy video codec MJPG" in q.warning


def test_lossless_video_codec_not_flagged(small_dataset: Path, tmp_path: Path) -> None:
    frames = sorted((small_dataset / "frames").glob("*.png"))[:4]
    h, w = read_image(frames[0]).shape[:2]
    video = tmp_path / "run.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 8.0, (w, h))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write FFV1")
    for path in frames:
        writer.write(cv2.imread(str(path)))
    writer.release()
    shutil.copy(small_dataset / "rig.yaml", tmp_path / "rig.yaml")
    q = assess_input(open_dataset(video))
    assert not q.lossy, q


def test_cli_warns_about_jpeg_frames_and_lists_the_deliverable(
    small_dataset: Path, tmp_path: Path, capsys
) -> None:
    import json

    from omnipipe.cli import main
    from omnipipe.output import read_manifest

    data = _copy(small_dataset, tmp_path / "jpg", 8, 30)
    out = tmp_path / "out"
    assert main(["reconstruct", str(data), "--out", str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    printed, errors = captured.out.splitlines(), captured.err.splitlines()
    # Warnings on stderr, the verdict alone on stdout.
    assert any(line.startswith("warning: lossy input: 8x8 block") for line in errors)
    assert not any(line.startswith("warning:") for line in printed)
    assert printed[-1].startswith(f"wrote {out}")
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert report["input_quality"]["lossy"] is True
    assert any(w.startswith("lossy input") for w in report["warnings"])
    assert [s["frame"] for s in report["stations"]] == sorted({s["frame"] for s in report["stations"]})
    assert "defects.csv" in read_manifest(out).files

"""Damaged images and videos (issue 15, "noisy errors" and "nonsense accepted silently").

A truncated PNG, a text file named .mp4 and a truncated .mp4 give exactly one line on
stderr (no libpng/FFmpeg/OpenCV chatter, checked at the file-descriptor level), exit
code 1 and nothing written. A truncated MJPG .avi is opened with what decodes and a
warning naming both frame counts (Dataset.warnings, copied into report.json).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from omnipipe.cli import main
from omnipipe.dataset import open_dataset, read_image
from omnipipe.errors import DatasetError
from omnipipe.native import quiet_native_stderr
from omnipipe.pipeline.cli import _progress, close_progress_bars

FRAMES = 24


@pytest.fixture(scope="module")
def videos(tmp_path_factory: pytest.TempPathFactory, tiny_dataset: Path) -> Path:
    """A folder with rig.yaml (64x48) and 24-frame videos: whole and cut to 60 %."""
    folder = tmp_path_factory.mktemp("videos")
    (folder / "rig.yaml").write_bytes((tiny_dataset / "rig.yaml").read_bytes())
    rng = np.random.default_rng(5)
    for fourcc, name in (("MJPG", "run.avi"), ("mp4v", "run.mp4")):
        writer = cv2.VideoWriter(str(folder / name), cv2.VideoWriter_fourcc(*fourcc), 8, (64, 48))
        for _ in range(FRAMES):
            writer.write(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
        writer.release()
        data = (folder / name).read_bytes()
        (folder / f"cut_{name}").write_bytes(data[: int(0.6 * len(data))])
    (folder / "notes.mp4").write_text("this is not a video\n")
    return folder


def truncated_copy(src: Path, dst: Path) -> Path:
    """A copy of the dataset whose second frame is cut in half."""
    (dst / "frames").mkdir(parents=True)
    (dst / "rig.yaml").write_bytes((src / "rig.yaml").read_bytes())
    for p in sorted((src / "frames").iterdir()):
        data = p.read_bytes()
        (dst / "frames" / p.name).write_bytes(
            data[: len(data) // 2] if p.stem.endswith("1") else data
        )
    return dst


def test_truncated_png_is_an_error_without_decoder_chatter(
    tiny_dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    ds = truncated_copy(tiny_dataset, tmp_path / "ds")
    capfd.readouterr()
    with pytest.raises(DatasetError, match=r"000001\.png: not a readable image"):
        read_image(ds / "frames" / "000001.png")
    assert capfd.readouterr().err == ""


def test_stderr_is_restored_after_silencing(capfd: pytest.CaptureFixture[str]) -> None:
    import os

    with quiet_native_stderr(), quiet_native_stderr():
        os.write(2, b"swallowed\n")
    os.write(2, b"visible\n")
    assert capfd.readouterr().err == "visible\n"


def test_reconstruct_truncated_png_prints_exactly_one_line(
    tiny_dataset: Path, tmp_path: Path
) -> None:
    ds = truncated_copy(tiny_dataset, tmp_path / "ds")
    out = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "omnipipe.cli",
            "reconstruct",
            str(ds),
            "--out",
            str(out),
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1
    assert proc.stderr.splitlines() == [
        f"omnipipe reconstruct: error: {ds / 'frames' / '000001.png'}: "
        "not a readable image (corrupt or truncated?)"
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_error_line_starts_on_its_own_line_with_progress_bars(
    tiny_dataset: Path, tmp_path: Path
) -> None:
    ds = truncated_copy(tiny_dataset, tmp_path / "ds")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "omnipipe.cli",
            "reconstruct",
            str(ds),
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1
    lines = proc.stderr.replace("\r", "\n").splitlines()
    errors = [line for line in lines if "error" in line]
    assert len(errors) == 1 and errors[0].startswith("omnipipe reconstruct: error: ")
    assert proc.stderr.rstrip("\n").endswith("(corrupt or truncated?)")


def test_close_progress_bars_ends_the_bar_line(capsys: pytest.CaptureFixture[str]) -> None:
    factory = _progress(quiet=False)
    factory("laser", 4)(1)  # a stage stopped early: its bar is closed by the next one
    tick = factory("sfm", 4)
    tick(2)
    close_progress_bars()
    print("omnipipe reconstruct: error: boom", file=sys.stderr)
    err = capsys.readouterr().err
    assert err.endswith("\nomnipipe reconstruct: error: boom\n")
    assert err.count("sfm") >= 1 and err.count("laser") >= 1
    close_progress_bars()  # idempotent


@pytest.mark.parametrize(
    ("name", "reason"),
    [
        ("notes.mp4", "not a readable video (not a video, or damaged)"),
        ("cut_run.mp4", "not a readable video (not a video, or damaged)"),
    ],
)
def test_unreadable_video_gives_one_line(
    videos: Path,
    tmp_path: Path,
    capfd: pytest.CaptureFixture[str],
    name: str,
    reason: str,
) -> None:
    capfd.readouterr()
    out = tmp_path / "out"
    code = main(["reconstruct", str(videos / name), "--out", str(out), "--quiet"])
    err = capfd.readouterr().err
    assert code == 1
    assert err == f"omnipipe reconstruct: error: {videos / name}: {reason}\n"
    assert not out.exists()


def test_truncated_video_is_opened_with_a_warning(
    videos: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    whole = open_dataset(videos / "run.avi")
    assert len(whole) == FRAMES and whole.warnings == ()
    capfd.readouterr()
    cut = open_dataset(videos / "cut_run.avi")
    assert capfd.readouterr().err == ""
    assert 0 < len(cut) < FRAMES
    assert len(cut.warnings) == 1
    assert f"announces {FRAMES} frames but only the first {len(cut)}" in cut.warnings[0]
    assert "cut_run.avi" in cut.warnings[0]

"""Decoded frames handed on between stages: read back as written, a budget, cleanup."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnipipe.executor import FrameSource
from omnipipe.handoff import FrameHandoff, hand_on, handed, handoff_path


def test_round_trip_budget_and_cleanup() -> None:
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (30, 40, 3)).astype(np.uint8)
    with FrameHandoff(5, budget_bytes=2 * image.nbytes) as handoff:
        folder = Path(handoff.folder)
        written = hand_on(handoff.folder, 1, image)
        assert written >= image.nbytes
        handoff.note(1, written)
        back = handed(handoff.folder, 1)
        assert back is not None and back.dtype == np.uint8 and np.array_equal(back, image)
        assert written == Path(handoff_path(handoff.folder, 1)).stat().st_size
        mapped = handed(handoff.folder, 1, mapped=True)  # the file's pages, read-only
        assert type(mapped) is np.ndarray and not mapped.flags.writeable
        assert mapped.dtype == np.uint8 and np.array_equal(mapped, image)
        assert handed(handoff.folder, 4, mapped=True) is None
        assert handed(handoff.folder, 2) is None  # never handed on
        handoff.note(2, hand_on(handoff.folder, 2, image))  # the budget is reached now
        assert hand_on(handoff.folder, 3, image) == 0
        assert not Path(handoff_path(handoff.folder, 3)).exists()
        handoff.discard(2)
        assert handed(handoff.folder, 2) is None
    assert not folder.exists()


def test_a_frame_source_reads_a_handed_frame_else_decodes(tmp_path: Path) -> None:
    from omnipipe.dataset import write_image

    rng = np.random.default_rng(4)
    on_disk = rng.integers(0, 256, (12, 16, 3)).astype(np.uint8)
    other = rng.integers(0, 256, (12, 16, 3)).astype(np.uint8)
    paths = (tmp_path / "a.png", tmp_path / "b.png")
    for p in paths:
        write_image(p, on_disk)
    with FrameHandoff(9) as handoff:
        hand_on(handoff.folder, 7, other)
        source = FrameSource(None, [7, 8], paths=paths, handoff=handoff.folder)
        assert np.array_equal(source.read(0), other)  # frame 7: handed on
        assert np.array_equal(source.read(1), on_disk)  # frame 8: decoded


def test_a_video_frame_handed_on_is_not_decoded_again() -> None:
    """A video's frames are read in the calling process: a handed-on one from the
    hand-off, without a seek and decode."""
    from types import SimpleNamespace

    rng = np.random.default_rng(6)
    decoded = rng.integers(0, 256, (12, 16, 3)).astype(np.uint8)
    other = rng.integers(0, 256, (12, 16, 3)).astype(np.uint8)
    read: list[int] = []
    video = SimpleNamespace(
        rig=None, video=Path("run.avi"), source=None,
        read_frame=lambda i: read.append(i) or decoded,
    )
    with FrameHandoff(9) as handoff:
        hand_on(handoff.folder, 7, other)
        source = FrameSource.take(video, [7, 8], handoff=handoff.folder)
        assert read == [8]
        assert np.array_equal(source.read(0), other) and np.array_equal(source.read(1), decoded)


def test_decode_hand_on_writes_the_moving_frames_as_decoded(tmp_path: Path) -> None:
    """The benchmark's floor of the laser stage (:class:`omnipipe.laser.DecodeHandOn`):
    every frame decoded (its shape returned, as ``decode_only``), only the moving ones
    handed on, each as decoded."""
    from omnipipe.dataset import write_image
    from omnipipe.laser import DecodeHandOn, decode_only

    rng = np.random.default_rng(8)
    images = [rng.integers(0, 256, (12, 16, 3)).astype(np.uint8) for _ in range(3)]
    paths = tuple(tmp_path / f"{i}.png" for i in range(3))
    for p, image in zip(paths, images, strict=True):
        write_image(p, image)
    moving = np.array([True, False, True, False])
    with FrameHandoff(4) as handoff:
        source = FrameSource(None, [0, 1, 2], paths=paths)
        assert DecodeHandOn(handoff.folder, moving)(source) == decode_only(source)
        assert np.array_equal(handed(handoff.folder, 0), images[0])
        assert handed(handoff.folder, 1) is None
        assert np.array_equal(handed(handoff.folder, 2), images[2])

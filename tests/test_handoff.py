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


def _smooth_rgb(h: int, w: int, seed: int) -> np.ndarray:
    """An (h, w, 3) uint8 frame of smooth colour (a wall under LEDs, no edges)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    out = np.empty((h, w, 3))
    for c in range(3):
        a, b, p = rng.uniform(0.02, 0.08, 3)
        out[..., c] = 128 + 90 * np.sin(a * xx + p) * np.cos(b * yy)
    return np.round(out).astype(np.uint8)


def test_a_red_laser_colour_frame_is_handed_on_planar() -> None:
    """Green whole (the grey image the camera motion reads: the same array), red and blue
    at half resolution (2x2 means): about half the bytes; the colour read back within a
    few levels of the frame's on a smooth wall, sampled where the model asks."""
    import cv2

    from omnipipe.handoff import PlanarFrame, handed_frame
    from omnipipe.sfm.tasks import frame_gray, handed_gray

    image = _smooth_rgb(30, 41, 5)  # an odd width: the last half column covers one pixel
    with FrameHandoff(3) as handoff:
        written = hand_on(handoff.folder, 0, image, "red")
        assert image.nbytes // 2 <= written < image.nbytes // 2 + 400
        mapped = handed(handoff.folder, 0, mapped=True)
        assert mapped is not None and mapped.shape == (30, 41)
        assert np.array_equal(mapped, frame_gray(image, "red"))
        assert np.array_equal(handed_gray(handoff.folder, 0, "red"), frame_gray(image, "red"))
        frame = handed_frame(handoff.folder, 0)
        assert isinstance(frame, PlanarFrame) and frame.red_blue.shape == (15, 21, 2)
        assert np.array_equal(frame.green, image[..., 1])
        block = image[:2, :2, 0].astype(float).mean()
        assert abs(int(frame.red_blue[0, 0, 0]) - block) <= 0.5
        back = handed(handoff.folder, 0)  # the whole frame: red and blue interpolated
        assert back is not None and back.shape == image.shape and np.array_equal(back[..., 1], image[..., 1])
        err = np.abs(back.astype(int) - image.astype(int))
        assert err[1:-1, 1:-1].max() <= 6 and err.mean() < 1.5
        rng = np.random.default_rng(6)
        px = rng.uniform(0, [40, 29], (200, 2)).astype(np.float32)
        want = cv2.remap(image, px[None, :, 0].copy(), px[None, :, 1].copy(), cv2.INTER_LINEAR)[0]
        got = frame.sample(px)
        assert np.array_equal(got[:, 1], want[:, 1])  # green bilinear in the whole channel
        assert np.abs(got.astype(int) - want.astype(int)).max() <= 6
        assert frame.sample(np.zeros((0, 2))).shape == (0, 3)
        for channel, other in (("green", image), ("red", image.astype(np.uint16)), ("red", image[..., 0])):
            hand_on(handoff.folder, 1, other, channel)  # not planar: as decoded
            assert np.array_equal(handed(handoff.folder, 1), other)
            assert type(handed_frame(handoff.folder, 1)) is np.ndarray


def test_the_model_samples_the_same_colours_handed_on_or_decoded() -> None:
    """The model's colours of a red laser's frame come from its planar form whether the
    frame was handed on or decoded (the same outputs with or without a hand-off, inline
    or on a pool); a green laser's frame is sampled as decoded."""
    from omnipipe.handoff import handed_frame
    from omnipipe.model.stage import _FrameWork

    image = _smooth_rgb(24, 32, 9)
    rng = np.random.default_rng(10)
    work = _FrameWork(
        rng.integers(0, [32, 24], (15, 2)), (rng.uniform(0, [31, 23], (40, 2)).astype(np.float32),)
    )
    with FrameHandoff(2) as handoff:
        hand_on(handoff.folder, 0, image, "red")
        frame = handed_frame(handoff.folder, 0)
        assert frame is not None
        via_handoff = work(frame, "red")
    decoded = work(image, "red")
    for a, b in zip(via_handoff, decoded, strict=True):
        assert a.shape == b.shape and np.array_equal(a, b)
    colours, _ = work(image, "green")
    assert np.array_equal(colours, image[work.colour_px[:, 1], work.colour_px[:, 0]])
    assert np.abs(decoded[0].astype(int) - colours.astype(int)).max() <= 6


def test_a_planar_frame_handed_on_from_its_split_is_the_same_file() -> None:
    """The pass splits a red laser's frame once (its signature reads the green plane) and
    hands the planes on: the same bytes as a frame split by :func:`hand_on` itself, a
    ``.npy`` file of the green plane and then red and blue at half resolution."""
    import io

    import cv2

    from omnipipe.handoff import PlanarFrame

    rng = np.random.default_rng(8)
    image = rng.integers(0, 256, (24, 34, 3)).astype(np.uint8)
    planar = PlanarFrame.of(image)
    want = io.BytesIO()
    for a in (planar.green, planar.red_blue):
        np.lib.format.write_array(want, a, allow_pickle=False)
    with FrameHandoff(3) as handoff:
        a = hand_on(handoff.folder, 0, image, "red")
        b = hand_on(handoff.folder, 1, image, "red", tuple(cv2.split(image)))
        assert a == b == len(want.getvalue())
        for i in (0, 1):
            assert Path(handoff_path(handoff.folder, i)).read_bytes() == want.getvalue()

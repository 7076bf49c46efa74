"""Videos decoded as a stream: any order of reads gives the frames a plain decode gives."""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from omnipipe.errors import DatasetError
from omnipipe.inputs.video import FORWARD_DECODE, VideoFrames, scan_video

FRAMES = 3 * FORWARD_DECODE  # long enough for forward decodes and seeks both


def _video(path: Path, fourcc: str) -> list[np.ndarray]:
    """Write FRAMES distinct 64x48 frames to ``path``; the RGB frames a decode returns."""
    rng = np.random.default_rng(7)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 8.0, (64, 48))
    base = np.clip(cv2.GaussianBlur(rng.uniform(0, 255, (48, 64, 3)), (0, 0), 2), 0, 255).astype(np.uint8)
    for i in range(FRAMES):
        frame = np.ascontiguousarray(np.roll(base, 2 * i, axis=1))
        cv2.putText(frame, str(i), (4, 40), cv2.FONT_HERSHEY_SIMPLEX, 1.2, (255, 255, 255), 2)
        writer.write(frame)
    writer.release()
    cap = cv2.VideoCapture(str(path))
    decoded = []
    while True:
        ok, bgr = cap.read()
        if not ok:
            break
        decoded.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    cap.release()
    return decoded


@pytest.fixture(scope="module", params=[("MJPG", "run.avi"), ("mp4v", "run.mp4")])
def video(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory):
    fourcc, name = request.param
    path = tmp_path_factory.mktemp(fourcc) / name
    return path, _video(path, fourcc)


def _order() -> list[int]:
    """In order, skips forward (short and long), backward, repeats, the ends."""
    rng = np.random.default_rng(0)
    return [
        *range(0, 20), 20 + FORWARD_DECODE // 2, FRAMES - 2, 3, 3, 0, FRAMES - 1,
        *rng.integers(0, FRAMES, 40).tolist(), *range(FRAMES - 30, FRAMES, 7),
    ]


def test_scan_counts_frames_and_times(video) -> None:
    path, decoded = video
    scan = scan_video(path)
    assert scan.frames == len(decoded) == FRAMES
    assert (scan.width, scan.height) == (64, 48)
    np.testing.assert_allclose(scan.times_s, np.arange(FRAMES) / 8.0, atol=1e-6)


def test_reads_in_any_order_give_the_decoded_frames(video) -> None:
    path, decoded = video
    scan = scan_video(path)
    frames = VideoFrames(path, scan.frames, scan.times_s)
    for i in _order():
        assert np.array_equal(frames.read(i), decoded[i]), f"frame {i}"


def test_unchecked_seeks_fall_back_to_decoding_from_the_start(video) -> None:
    """Recorded times that do not match what the decoder reports (or none at all): every
    seek is refused and the frame is reached from the first one, still the right frame."""
    path, decoded = video
    for times in (np.arange(FRAMES) / 8.0 + 0.5, np.full(FRAMES, np.nan)):
        frames = VideoFrames(path, FRAMES, times)
        for i in (FRAMES - 1, 5, FRAMES // 2, 0):
            assert np.array_equal(frames.read(i), decoded[i]), f"frame {i}"


def test_a_pickled_copy_opens_its_own_decoder(video) -> None:
    path, decoded = video
    scan = scan_video(path)
    frames = VideoFrames(path, scan.frames, scan.times_s)
    frames.read(10)
    copy = pickle.loads(pickle.dumps(frames))
    assert np.array_equal(copy.read(30), decoded[30])
    assert np.array_equal(frames.read(11), decoded[11])


def test_a_frame_past_the_decodable_ones_is_an_error(video) -> None:
    path, _ = video
    frames = VideoFrames(path, FRAMES + 5, np.full(FRAMES + 5, np.nan))
    with pytest.raises(DatasetError, match=f"frame {FRAMES + 2} does not decode"):
        frames.read(FRAMES + 2)
    with pytest.raises(IndexError):
        frames.read(FRAMES + 5)

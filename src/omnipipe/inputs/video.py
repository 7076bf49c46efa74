"""Video files decoded as a stream: memory that does not grow with the video's length.

A run reads its frames in order (the decoding pass, then the moving frames, then the
keyframes a section of the pipe at a time), so :class:`VideoFrames` keeps one decoder
open per process and decodes forward; a frame behind the decoder, or far ahead of it,
is reached by a seek. No decoded frame is held beyond the last one read (an MJPG frame
of 400x300 is 0.36 MB: a 10,000-frame video held whole was 3.6 GB).

Seeks are checked: the frame read after a seek must carry the presentation time the
opening pass recorded for that index (:func:`scan_video`), else the decoder is
re-opened and decodes forward from the first frame (slow, never wrong). Without usable
recorded times every backward step re-opens.
"""

from __future__ import annotations

import math
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omnipipe.errors import DatasetError
from omnipipe.native import quiet_native_stderr

FORWARD_DECODE = 48
"""Frames ahead of the decoder reached by decoding (``grab``) rather than by a seek."""


@dataclass(frozen=True)
class VideoScan:
    """What one decoding pass over a video found (no frame is kept).

    Attributes:
        frames: how many frames decode (the pass stops at the first that does not).
        fps: the container's frame rate (0: unknown).
        announced: the frame count the container announces (0: unknown).
        times_s: (frames,) each frame's presentation time (``CAP_PROP_POS_MSEC``),
            seconds; NaN where unknown.
        width, height: the first frame's size, px.
    """

    frames: int
    fps: float
    announced: int
    times_s: np.ndarray
    width: int
    height: int


def _capture(path: Path) -> Any:
    """An opened ``cv2.VideoCapture`` of ``path``.

    Raises:
        DatasetError: not a video OpenCV can open.
    """
    import cv2


    with quiet_native_stderr():
        cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        cap.release()
        raise DatasetError(f"{path}: not a readable video (not a video, or damaged)")
    return cap


def scan_video(path: Path) -> VideoScan:
    """Decode ``path`` once, frame by frame, keeping only each frame's time (and the
    first frame's size). The decoder's own messages are silenced.

    Raises:
        DatasetError: not a video, or no frame decodes.
    """
    import cv2


    cap = _capture(path)
    times: list[float] = []
    width = height = 0
    try:
        with quiet_native_stderr():
            fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
            announced = float(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0.0)
            ok, frame = cap.read()
            if ok and frame is not None:
                height, width = frame.shape[:2]
            while ok:
                msec = cap.get(cv2.CAP_PROP_POS_MSEC)
                times.append(float(msec) / 1000.0 if msec is not None else math.nan)
                ok = cap.grab()  # decoded, not converted: the next frame's time only
    finally:
        cap.release()
    if not times:
        raise DatasetError(f"{path}: the video holds no decodable frame")
    if not math.isfinite(fps) or fps < 0:
        fps = 0.0
    count = int(announced) if math.isfinite(announced) and 0 < announced < 1e9 else 0
    return VideoScan(len(times), fps, count, np.array(times, float), width, height)


class VideoFrames:
    """Frames of one video file, decoded on demand (the ``source`` of a video dataset).

    ``read(i)`` decodes forward from the decoder's position (up to
    :data:`FORWARD_DECODE` frames skipped by decoding alone), seeks otherwise (checked
    against ``times_s``, see the module docstring). The last frame read is kept, so
    reading it again costs nothing. Each process opens its own decoder (a forked worker
    never shares its parent's); pickling carries the path and times only.
    Thread-safe.
    """

    def __init__(self, path: Path, frames: int, times_s: np.ndarray) -> None:
        self.path = Path(path)
        self.frames = int(frames)
        times = np.asarray(times_s, float)
        # Seeks can be checked only against distinct, known times.
        usable = len(times) == frames and np.isfinite(times).all() and bool(np.all(np.diff(times) > 0))
        self._times = times if usable else None
        self._reset()

    def _reset(self) -> None:
        self._lock = threading.Lock()
        self._pid = os.getpid()
        self._cap: Any = None
        self._next = 0  # the index the decoder's next read returns
        self._last: tuple[int, np.ndarray] | None = None

    def __getstate__(self) -> dict[str, Any]:
        return {"path": self.path, "frames": self.frames, "times": self._times}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.path, self.frames, self._times = state["path"], state["frames"], state["times"]
        self._reset()

    def __len__(self) -> int:
        return self.frames

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` as RGB (H, W, 3) uint8.

        Raises:
            DatasetError: the frame does not decode (naming the video and the frame).
        """
        if not 0 <= index < self.frames:
            raise IndexError(f"frame {index} of {self.frames}")
        with self._lock:
            if self._pid != os.getpid():  # forked: the parent's decoder is not ours
                self._reset()
            if self._last is not None and self._last[0] == index:
                return self._last[1]
            frame = self._decode(index)
            self._last = (index, frame)
            return frame

    def _decode(self, index: int) -> np.ndarray:
        import cv2


        with quiet_native_stderr():
            if self._cap is None or not 0 <= index - self._next <= FORWARD_DECODE:
                self._seek(index)
            while self._next < index:
                if not self._cap.grab():
                    break
                self._next += 1
            ok, bgr = self._cap.read() if self._next == index else (False, None)
        if not ok or bgr is None:
            self.close()
            raise DatasetError(f"{self.path}: frame {index} does not decode")
        self._next += 1
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def _seek(self, index: int) -> None:
        """Place the decoder so that its next read returns frame ``index``."""
        import cv2

        if self._cap is None:
            self._cap = _capture(self.path)
            self._next = 0
        if index == self._next:
            return
        if index > 0 and self._times is not None:
            # The frame before the target, read: its time says where the seek landed.
            if self._cap.set(cv2.CAP_PROP_POS_FRAMES, float(index - 1)) and self._cap.grab():
                landed = float(self._cap.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0
                if math.isclose(landed, self._times[index - 1], rel_tol=0.0, abs_tol=1e-6):
                    self._next = index
                    return
        # No checked seek: from the first frame, decoding forward.
        self._cap.release()
        self._cap = _capture(self.path)
        self._next = 0

    def close(self) -> None:
        """Release the decoder (re-opened by the next read)."""
        with_cap, self._cap = self._cap, None
        if with_cap is not None and self._pid == os.getpid():
            with_cap.release()
        self._next = 0
        self._last = None

"""Stop-and-go: which frames were taken while the rig stood still.

An earthworm robot anchors its front unit for most of each gait cycle, so runs of
consecutive frames show the same station. Two frames of one station differ only by
sensor noise; any motion shifts the wall texture. The test compares the frames'
smoothed difference with the difference that noise alone would give, estimated
from the images themselves (Immerkaer's fast noise estimate), so no threshold
depends on the camera, exposure or pipe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np


@dataclass(frozen=True)
class StationConfig:
    """Stationary-frame detection.

    Attributes:
        downsample: images are box-filtered by this factor before comparing (noise averages out).
        noise_factor: a frame is stationary when its smoothed difference from the station's
            first frame is below this many times the difference noise alone gives (noise
            alone gives about 1.1-1.4; a 1.6 mm step of the paper rig at 640x480 gives 4).
            1.7, not 2.0: on a random 415 mm brick pipe a 0.5 mm creep after a stop gave
            1.87-1.91 and was taken for a standstill (the next step then 1.1 mm off);
            paper and bend keep the same motion.
    """

    downsample: int = 4
    noise_factor: float = 1.7


# Immerkaer's noise operator: the difference of two Laplacians.
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def noise_sigma(gray: np.ndarray, mask: np.ndarray | None = None, *, inner: np.ndarray | None = None) -> float:
    """Sensor noise sigma of an image (Immerkaer 1996: Laplacian-difference operator).

    Args:
        gray: (H, W) grey image.
        mask: (H, W) bool, the pixels to use (eroded by one pixel here), or None.
        inner: (H, W) bool, the already eroded mask (:func:`inner_mask`; saves the erosion
            when many frames share one mask). Takes precedence over ``mask``.
    """
    resp = cv2.filter2D(gray.astype(np.float32), -1, _NOISE_KERNEL, borderType=cv2.BORDER_REFLECT)
    if inner is None and mask is not None:
        inner = inner_mask(mask)
    if inner is not None:
        resp = resp[inner]
    # The operator's weights square-sum to 36: its response to noise has sigma 6 sigma.
    # The median absolute response (robust to texture edges) is 0.6745 times that.
    return float(_median_abs(resp) / (6.0 * 0.6745))


def inner_mask(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: ``mask`` eroded by one pixel (where the 3 x 3 operator sees only it)."""
    return cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0


def _median_abs(values: np.ndarray) -> np.float32:
    """``np.median(np.abs(values))`` of float32 values, exactly; by counting when the
    values are whole numbers (an integer image through an integer kernel: 8- and
    16-bit frames), 5x faster than the partition a median needs."""
    a = np.abs(values.ravel())
    if a.size == 0 or a.dtype != np.float32 or float(a.max()) >= 2**24:
        return np.float32(np.median(a))
    ints = a.astype(np.int32)
    if not np.array_equal(ints, a):
        return np.float32(np.median(a))
    counts = np.cumsum(np.bincount(ints))
    n = a.size
    hi = int(np.searchsorted(counts, n // 2, side="right"))  # value of sorted[n // 2]
    if n % 2:
        return np.float32(hi)
    lo = int(np.searchsorted(counts, n // 2 - 1, side="right"))  # sorted[n // 2 - 1]
    return np.mean(np.array([lo, hi], np.float32))


def _small(gray: np.ndarray, factor: int) -> np.ndarray:
    h, w = gray.shape
    return cv2.resize(gray.astype(np.float32), (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def frame_signature(
    image: np.ndarray,
    laser_channel: str,
    inner: np.ndarray,
    config: StationConfig | None = None,
    runs: np.ndarray | None = None,
) -> StationSignature:
    """:func:`station_signature` of a decoded frame's grey image without the laser
    (:func:`omnipipe.image.gray_without_laser`), the same bit for bit.

    A frame whose grey image is one of its 8- or 16-bit channels (a red laser: green;
    a one-channel frame) is read as that channel: the box average is the same resize of
    the same values, and the noise operator runs in integers (``cv2.filter2D``) with a
    histogram of its magnitudes over the ``inner`` pixels instead of a float32 image and
    a masked median (4.5 -> 2.8 ms at 1600x1200, the signature taken of every frame).
    Any other frame goes through the grey image.

    Args:
        image: (H, W) or (H, W, C) frame as decoded.
        laser_channel: the rig's laser channel.
        inner: (H, W) bool, the camera's valid mask eroded by :func:`inner_mask`.
        runs: :func:`mask_runs` of ``inner`` when the caller keeps it (many frames share
            one mask); None: made here.
    """
    from omnipipe.image import CHANNEL_INDEX, gray_without_laser

    cfg = config or StationConfig()
    h, w = image.shape[:2]
    if image.ndim == 2:
        channel = image
    elif image.ndim == 3 and CHANNEL_INDEX.get(laser_channel) == 0 and image.shape[2] >= 2:
        channel = cv2.extractChannel(image, 1) if image.dtype in (np.uint8, np.uint16) else None
    else:
        channel = None
    if channel is None or channel.dtype not in (np.uint8, np.uint16) or inner.shape != (h, w):
        return station_signature(gray_without_laser(image, laser_channel), inner, cfg)
    channel = np.ascontiguousarray(channel)
    small = _small(channel, cfg.downsample)
    # The operator's response is a whole number: |r| <= 16 x the channel's maximum, held
    # exactly by int16 (8-bit) or float32 (16-bit, below 2**24).
    if channel.dtype == np.uint8:
        response = cv2.filter2D(channel, cv2.CV_16S, _NOISE_KERNEL, borderType=cv2.BORDER_REFLECT)
        magnitude = np.abs(response).view(np.uint16)
        bins = 16 * 255 + 1
    else:
        response = cv2.filter2D(channel, cv2.CV_32F, _NOISE_KERNEL, borderType=cv2.BORDER_REFLECT)
        magnitude = np.abs(response).astype(np.int32)
        bins = 16 * 65535 + 1
    hist = np.zeros(bins, np.int64)
    _histogram_runs(magnitude.reshape(-1), mask_runs(inner) if runs is None else runs, hist)
    return StationSignature(small, float(_hist_median(hist) / (6.0 * 0.6745)))


def mask_runs(mask: np.ndarray) -> np.ndarray:
    """(R, 2) int64 [start, end) flat indices of the runs of True along the rows of the
    (H, W) bool ``mask`` (row-major)."""
    h, w = mask.shape
    padded = np.zeros((h, w + 2), np.int8)
    padded[:, 1:-1] = mask
    edges = np.diff(padded, axis=1)  # (H, W + 1): +1 where a run starts, -1 after it ends
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    runs = np.stack([starts // (w + 1) * w + starts % (w + 1), ends // (w + 1) * w + ends % (w + 1)], axis=1)
    return runs.astype(np.int64)


@numba.njit(cache=True)
def _histogram_runs(values, runs, hist):  # pragma: no cover - compiled
    """``hist[v] += 1`` for every ``values[i]`` with i in one of the [start, end) ``runs``."""
    for r in range(runs.shape[0]):
        for i in range(runs[r, 0], runs[r, 1]):
            hist[values[i]] += 1


def _hist_median(hist: np.ndarray) -> np.float32:
    """:func:`_median_abs` of the whole-number values counted in ``hist``."""
    counts = np.cumsum(hist)
    n = int(counts[-1]) if len(counts) else 0
    if n == 0:
        return np.float32(np.nan)
    hi = int(np.searchsorted(counts, n // 2, side="right"))
    if n % 2:
        return np.float32(hi)
    lo = int(np.searchsorted(counts, n // 2 - 1, side="right"))
    return np.mean(np.array([lo, hi], np.float32))


class StationTracker:
    """Feeds frames one at a time; tells for each whether the rig moved since the station began.

    Each frame is compared with the first frame of the current station, so a slow
    creep that no single pair of frames shows accumulates until it is detected.

    Args:
        mask: (H, W) bool, the pixels that see the wall (the camera's valid mask).
        config: detection settings.
    """

    def __init__(self, mask: np.ndarray, config: StationConfig | None = None) -> None:
        self.config = config or StationConfig()
        f = self.config.downsample
        small = _small(mask.astype(np.float32), f)
        self.mask_small = small > 0.999
        self.mask = mask
        self._inner = inner_mask(mask)
        self._prev: np.ndarray | None = None

    def update(self, gray: np.ndarray) -> tuple[bool, float]:
        """Add the next frame (grey, not the laser channel); return (moved, ratio).

        ``ratio`` is the smoothed difference over its noise-only expectation (inf for
        the first frame, which counts as moved: it starts a station).
        """
        return self.update_signature(station_signature(gray, self._inner, self.config))

    def update_signature(self, signature: StationSignature) -> tuple[bool, float]:
        """:meth:`update` from the frame's :func:`station_signature` (computed anywhere,
        e.g. in the worker that decoded the frame)."""
        prev = self._prev
        if prev is None:
            self._prev = signature.small
            return True, math.inf
        f = self.config.downsample
        sigma = max(signature.noise_sigma, 0.3)
        # Box-averaging f x f pixels divides the noise sigma by f; a difference of two
        # frames multiplies it by sqrt(2); its mean absolute value is sigma sqrt(2/pi).
        expected = sigma / f * math.sqrt(2.0) * math.sqrt(2.0 / math.pi)
        diff = float(np.mean(np.abs(signature.small - prev)[self.mask_small]))
        ratio = diff / expected
        moved = ratio > self.config.noise_factor
        if moved:
            self._prev = signature.small  # a new station starts here
        return moved, ratio


@dataclass(frozen=True)
class StationSignature:
    """What the stationary-frame test needs of one frame (a few per cent of its size).

    Attributes:
        small: (H // f, W // f) float32 grey image box-averaged by ``downsample`` f.
        noise_sigma: the frame's sensor noise sigma (grey levels, :func:`noise_sigma`).
    """

    small: np.ndarray
    noise_sigma: float


def station_signature(
    gray: np.ndarray, inner: np.ndarray, config: StationConfig | None = None
) -> StationSignature:
    """The :class:`StationSignature` of a grey frame (not the laser channel).

    Args:
        gray: (H, W) grey image.
        inner: (H, W) bool, the camera's valid mask eroded by :func:`inner_mask`.
    """
    cfg = config or StationConfig()
    return StationSignature(_small(gray, cfg.downsample), noise_sigma(gray, inner=inner))

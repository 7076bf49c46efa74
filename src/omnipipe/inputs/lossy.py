"""Is the input lossy? JPEG/MPEG block artefacts and the video codec.

Block transform codecs (JPEG, MPEG-1/2/4 part 2) quantise 8x8 pixel blocks
independently, which leaves steps at the block borders. :func:`blockiness` compares the
mean absolute difference between neighbouring pixels across the 8-pixel grid with that
inside the blocks: about 1.0 for a lossless image, 1.25 for a JPEG at quality 95, 1.7 at
quality 75, 2.3 at 50 (measured on simulator frames, `omnipipe simulate --scenario
paper-small`). The laser ring's sub-pixel position and the wall texture suffer from
such artefacts: an MPEG-4 video of a run gave a 1.2 mm smaller diameter than its PNG
frames and missed a 5 mm bulge. Codecs with deblocking filters (H.264, HEVC, AV1) hide
the grid, so a video is also judged by its codec and bit rate.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from omnipipe.native import quiet_native_stderr

if TYPE_CHECKING:
    from omnipipe.dataset import Dataset

# Median blockiness above which the input is reported as lossy (JPEG quality ~90 or lower).
BLOCKINESS_WARN = 1.3
# Frames sampled (evenly spread) to measure blockiness.
SAMPLES = 5
# Video codecs (FourCC, upper case) that are lossless.
LOSSLESS_CODECS = frozenset({"FFV1", "HFYU", "FFVH", "PNG ", "MPNG", "RAW ", "RGB ", "Y800", "I420", "YUY2", "DIB ", "\0\0\0\0"})


def blockiness(image: np.ndarray, block: int = 8) -> float:
    """Block-border step ratio of a grey (H, W) or colour (H, W, C) image (>= 1 for
    block-compressed images, about 1.0 otherwise); NaN for a flat image.

    The steps of the channels' mean, in whole numbers for an integer image: the
    channels' sum (the mean times C) and its differences' sums exact, their ratio the
    same as on the means (a 1600x1200 colour frame: 15 ms against 60-130 in float64).
    """
    a = np.asarray(image)
    if a.dtype.kind not in "ui" or a.dtype.itemsize > 2:
        return _blockiness_float(a, block)
    total = a.astype(np.int32) if a.ndim == 2 else a[..., 0].astype(np.int32)
    for c in range(1, a.shape[2] if a.ndim == 3 else 1):
        total += a[..., c]
    ratios = []
    for d in (np.abs(np.diff(total, axis=1)), np.abs(np.diff(total, axis=0)).T):
        border = (np.arange(d.shape[1]) % block) == block - 1
        n_border = int(border.sum()) * d.shape[0]
        at_border = int(d[:, border].sum(dtype=np.int64))
        inner = int(d.sum(dtype=np.int64)) - at_border
        if inner > 0 and n_border:
            ratios.append((at_border / n_border) / (inner / (d.size - n_border)))
    return float(np.mean(ratios)) if ratios else float("nan")


def _blockiness_float(image: np.ndarray, block: int) -> float:
    """:func:`blockiness` of a float (or wide integer) image, in float64."""
    g = np.asarray(image, dtype=np.float64)
    if g.ndim == 3:
        g = g.mean(axis=2)
    ratios = []
    for d in (np.abs(np.diff(g, axis=1)), np.abs(np.diff(g, axis=0)).T):
        border = (np.arange(d.shape[1]) % block) == block - 1
        inner = d[:, ~border].mean()
        if inner > 0 and border.any():
            ratios.append(d[:, border].mean() / inner)
    return float(np.mean(ratios)) if ratios else float("nan")


@dataclass(frozen=True)
class InputQuality:
    """What report.json ``input_quality`` holds.

    Attributes:
        lossy: block artefacts found, or a lossy video codec.
        blockiness: median :func:`blockiness` of the sampled frames (1.0: none).
        frames_sampled: how many frames were measured.
        codec: video FourCC, None for images and bags.
        bitrate_kbps, bits_per_pixel: the video's, where the container states them.
        warning: the one-line warning, or None.
    """

    lossy: bool
    blockiness: float | None
    frames_sampled: int
    codec: str | None = None
    bitrate_kbps: float | None = None
    bits_per_pixel: float | None = None
    warning: str | None = None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        for key in ("blockiness", "bitrate_kbps", "bits_per_pixel"):
            if d[key] is not None:
                d[key] = round(d[key], 3) if math.isfinite(d[key]) else None
        return d


def _video_codec(dataset: Dataset) -> tuple[str | None, float | None, float | None]:
    """(FourCC, bit rate kbit/s, bits per pixel per frame) of a video dataset."""
    import cv2

    with quiet_native_stderr():
        cap = cv2.VideoCapture(str(dataset.video))
        try:
            fourcc = int(cap.get(cv2.CAP_PROP_FOURCC) or 0)
            kbps = float(cap.get(cv2.CAP_PROP_BITRATE) or 0.0)
            fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        finally:
            cap.release()
    codec = fourcc.to_bytes(4, "little").decode("latin-1").upper() if fourcc > 0 else None
    cam = dataset.rig.camera
    bpp = None
    if kbps > 0 and fps > 0:
        bpp = kbps * 1000.0 / (fps * cam.width * cam.height)
    return codec, (kbps if kbps > 0 else None), bpp


def assess_input(dataset: Dataset, samples: int = SAMPLES) -> InputQuality:
    """Measure the block artefacts of a few frames (and the codec of a video)."""
    n = len(dataset)
    idx = sorted({int(i) for i in np.linspace(0, n - 1, min(samples, n))})
    values = [blockiness(dataset.read_frame(i)) for i in idx]
    values = [v for v in values if math.isfinite(v)]
    block = float(np.median(values)) if values else None
    codec = kbps = bpp = None
    if dataset.video is not None:
        codec, kbps, bpp = _video_codec(dataset)
    reasons = []
    if block is not None and block > BLOCKINESS_WARN:
        reasons.append(f"8x8 block compression artefacts (blockiness {block:.2f}; 1.00 = none)")
    if codec is not None and codec not in LOSSLESS_CODECS:
        rate = "" if kbps is None else f" at {kbps:.0f} kbit/s"
        rate += "" if bpp is None else f" ({bpp:.2f} bit/pixel)"
        reasons.append(f"lossy video codec {codec.strip()}{rate}")
    warning = None
    if reasons:
        warning = (
            "lossy input: " + "; ".join(reasons) + ": the laser ring and the texture are "
            "degraded (diameters can be off by ~1 mm, small defects missed); record "
            "lossless frames (PNG, FFV1) or at high quality"
        )
    return InputQuality(
        lossy=bool(reasons),
        blockiness=block,
        frames_sampled=len(values),
        codec=codec,
        bitrate_kbps=kbps,
        bits_per_pixel=bpp,
        warning=warning,
    )

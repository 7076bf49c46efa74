"""Image helpers shared by the stages: channel selection and bilinear sampling."""

from __future__ import annotations

import cv2
import numpy as np

CHANNEL_INDEX = {"red": 0, "green": 1, "blue": 2}

# zlib level of the PNGs omnipipe writes (textures, unrolled wall, report images).
# Measured on bend's 1107x645 texture atlas: level 6 (PIL's default) 356 ms, 758 KB;
# level 3 79 ms, 852 KB; level 1 53 ms, 891 KB. Lossless at every level.
PNG_COMPRESS_LEVEL = 3


def gray_without_laser(image: np.ndarray, laser_channel: str) -> np.ndarray:
    """(H, W) float32 grey image of the LED-lit wall without the laser's colour channel.

    Green alone for a red laser (the best signal of a Bayer sensor), the mean of the
    other two for green or blue, all three for a grey laser (nothing to leave out).
    """
    if image.ndim == 2:
        return image.astype(np.float32)
    idx = CHANNEL_INDEX.get(laser_channel)
    if idx == 0:
        return image[..., 1].astype(np.float32)
    others = [c for c in range(3) if c != idx] if idx is not None else [0, 1, 2]
    return image[..., others].astype(np.float32).mean(axis=2)


def sample_bilinear(image: np.ndarray, pixels: np.ndarray, border: int = cv2.BORDER_CONSTANT) -> np.ndarray:
    """Bilinear samples of ``image`` at (N, 2) pixels (col, row): (N,) or (N, C).

    cv2.remap wants maps under 32767 px a side: the list is folded into rows of 4096.
    Outside the image: NaN for float images with the constant border, else the border rule.
    """
    n = len(pixels)
    rows = max(-(-n // 4096), 1)
    m = np.full((rows * 4096, 2), -1.0, np.float32)
    m[:n] = pixels
    m = m.reshape(rows, 4096, 2)
    fill = np.nan if image.dtype.kind == "f" else 0
    out = cv2.remap(image, m[..., 0].copy(), m[..., 1].copy(), cv2.INTER_LINEAR, borderMode=border, borderValue=fill)
    flat = out.reshape(rows * 4096, -1)[:n]
    return flat[:, 0] if out.ndim == 2 else flat

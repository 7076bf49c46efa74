"""Texture mapping (paper Sec. VI): the unrolled wall image and the mesh's texture.

The wall is unrolled into an image whose cells are wall points
(:mod:`~omnipipe.model.texture_grid`); each cell is coloured from the keyframe that sees
it best (:mod:`~omnipipe.model.texture_sources`: visible, out of the laser's light,
sharpest and brightest), then the illumination is divided out
(:mod:`~omnipipe.model.texture_light`). This module samples a keyframe's image at its
cells' pixels and paints them (:func:`texture_samples`, :func:`paint`); the model stage
(:mod:`omnipipe.model.stage`) reads the keyframes' images in parallel and drives it.

The image is also the mesh's texture atlas: a vertex's UV is its unrolled position.
"""

from __future__ import annotations

import cv2
import numpy as np

from omnipipe.errors import ShapeError
from omnipipe.image import sample_bilinear
from omnipipe.model.texture_sources import CellChoice


def texture_samples(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 bilinear colours of ``image`` ((H, W, 3) or (H, W), uint8 or uint16)
    at (n, 2) float32 pixels (col, row); the border replicated."""
    img = image
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    return sample_bilinear(img, pixels, border=cv2.BORDER_REPLICATE)


def paint(image: np.ndarray, choice: CellChoice, k: int, samples: np.ndarray | None) -> None:
    """Write keyframe k's (n_k, 3) uint8 samples (in :meth:`CellChoice.cells` order) into
    the (H * W, 3) uint8 ``image``.

    Raises:
        ShapeError: the samples are missing or of the wrong length.
    """
    cells = choice.cells(k)  # (not :meth:`CellChoice.count`: the pixels may be dropped)
    n = len(cells)
    if not n:
        return
    if samples is None or len(samples) != n:
        raise ShapeError(f"keyframe {k}: expected {n} texture samples, got "
                         f"{'none' if samples is None else len(samples)}")
    image[cells] = samples

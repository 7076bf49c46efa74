"""Texture mapping (paper Sec. VI): the unrolled wall image and the mesh's texture.

The wall is unrolled into an image whose cells are wall points
(:mod:`~omnipipe.model.texture_grid`); each cell is coloured from the keyframe that sees
it best (:mod:`~omnipipe.model.texture_sources`: visible, out of the laser's light,
sharpest and brightest), then the illumination is divided out
(:mod:`~omnipipe.model.texture_light`). This module samples the keyframes' images and
paints the cells (:func:`texture_samples`, :func:`paint`, :func:`assemble`;
:func:`unrolled_image` does it all serially; the model stage reads the images in
parallel, :mod:`omnipipe.model.stage`).

The image is also the mesh's texture atlas: a vertex's UV is its unrolled position.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from omnipipe.errors import ShapeError
from omnipipe.image import sample_bilinear
from omnipipe.model.texture_grid import UnrolledImage, WallGrid
from omnipipe.model.texture_light import flat_field
from omnipipe.model.texture_sources import CellChoice, choose_sources
from omnipipe.rig import Rig


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


def finish(
    choice: CellChoice,
    image: np.ndarray,
    mm_per_px: float,
    axial_min_mm: float,
    circumference_mm: float,
) -> UnrolledImage:
    """The unrolled image from the choice and the (H * W, 3) uint8 painted ``image``."""
    h, w = choice.shape
    return UnrolledImage(
        image.reshape(h, w, 3),
        choice.source >= 0,
        mm_per_px,
        axial_min_mm,
        circumference_mm,
    )


def assemble(
    choice: CellChoice,
    samples: dict[int, np.ndarray],
    mm_per_px: float,
    axial_min_mm: float,
    circumference_mm: float,
) -> UnrolledImage:
    """The unrolled image from the choice and, per keyframe k, the (n_k, 3) uint8 samples
    of its cells (in the order of ``choice.cells(k)``).

    Raises:
        ShapeError: a keyframe's samples are missing or of the wrong length.
    """
    h, w = choice.shape
    image = np.zeros((h * w, 3), np.uint8)
    for k in range(len(choice.pieces)):
        paint(image, choice, k, samples.get(k))
    return finish(choice, image, mm_per_px, axial_min_mm, circumference_mm)


def unrolled_image(
    rig: Rig,
    world_from_rig: np.ndarray,
    read_frame: Callable[[int], np.ndarray],
    grid_points: np.ndarray | WallGrid,
    axial_min_mm: float,
    circumference_mm: float,
    mm_per_px: float,
    laser_band_mm: float = 3.0,
    progress: Callable[[int], None] | None = None,
) -> UnrolledImage:
    """Colour every grid cell from the keyframe that sees it best (serial image reads).

    Args:
        rig: calibration (camera model and laser plane).
        world_from_rig: (K, 4, 4) keyframe poses.
        read_frame: k -> (H, W, 3) or (H, W) image of keyframe k; read once for each
            keyframe that textures some cell.
        grid_points: (H, W, 3) wall point of each cell (NaN: none), or a :class:`WallGrid`.
        progress: called with k + 1 after keyframe k's image is sampled.
    """
    choice = choose_sources(rig, world_from_rig, grid_points, mm_per_px, laser_band_mm)
    h, w = choice.shape
    image = np.zeros((h * w, 3), np.uint8)
    for k in range(len(world_from_rig)):
        if choice.count(k):
            paint(image, choice, k, texture_samples(read_frame(k), choice.pixels(k)))
            if progress:
                progress(k + 1)
    unrolled = finish(choice, image, mm_per_px, axial_min_mm, circumference_mm)
    return unrolled if choice.light is None else flat_field(unrolled, choice.light)

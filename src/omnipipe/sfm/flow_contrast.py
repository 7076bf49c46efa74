"""The image the tracker's finest flow levels read: a view's local contrast, the same
wherever in the view the wall's pattern stands.

Lucas-Kanade assumes that a wall point keeps its brightness while it moves across the
view. Two things fixed in the view break that: the rig's own light, which falls off
across the wall and moves with the rig, and CLAHE, whose tiles (8x8 per view) each map
grey levels their own way. Both turn a pattern that moves into one that partly stays,
and on a broad, smooth pattern (a corrugation, large mosaic tiles) the tracks fall
short of the true flow: random-wide seed 18 (corrugated, 254 mm) keyframe steps
tracked 5-6 % short with the true motion.

:func:`local_contrast` removes both with operations that commute with a shift of the
image: the logarithm makes the light's gain an offset, a high-pass (two box filters of
about a Gaussian of ``sigma_px``) removes that offset (it varies slowly), and the
result is divided by its own local spread (the same filter at twice the sigma) so that
a dim or low-contrast wall fills the 8-bit range as a bright one does. A pattern moved
across the view comes out moved, not reshaded.

That stretch also lifts what a plain wall has (a few grey levels of shading and the
sensor's noise) to full contrast, where the flow then finds tracks the wall cannot hold.
:func:`wall_texture` measures the wall's own local contrast before any stretch; below
:data:`TEXTURE_FLOOR` the run keeps the CLAHE'd views for its flow
(:func:`omnipipe.sfm.pipeline.run`), as a plain wall's were before.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from omnipipe.errors import ShapeError

# Grey level g -> LOG_SCALE * log(g + LOG_OFFSET): one unit is about 3 % of brightness;
# the offset keeps the darkest levels' noise from being stretched without bound.
LOG_SCALE = 32.0
LOG_OFFSET = 4.0
# The local spread below which the contrast is no longer stretched (units of LOG_SCALE,
# about 3 % of brightness), and the output grey levels per unit of local spread.
MIN_SPREAD = 1.0
GAIN = 40.0

# The texture floor (:func:`wall_texture`): the views' median local spread of log
# brightness (LOG_SCALE units; 0.5 is about 1.6 % of brightness) after a blur of
# TEXTURE_BLUR_PX (px, the sensor's noise out), high-passed at TEXTURE_SIGMA_PX. On the
# robustness bench's 40 random-wide walls at 640x480 (frame 0): plain and nearly plain
# walls (smooth pvc / lined, plastic pipes with joints only) 0.25-0.39, every other wall
# 0.63 (a corrugation) to 4.8.
TEXTURE_FLOOR = 0.5
TEXTURE_BLUR_PX = 1.0
TEXTURE_SIGMA_PX = 4.0

_LOG = (LOG_SCALE * np.log(np.arange(256, dtype=np.float64) + LOG_OFFSET)).astype(np.float32).reshape(1, 256)


def _box_width(sigma_px: float) -> int:
    """Odd width k of a box whose square, applied twice, has about the variance of a
    Gaussian of ``sigma_px`` (two boxes of width k: variance 2 (k^2 - 1) / 12)."""
    return 2 * int(round(0.5 * (math.sqrt(6.0 * sigma_px**2 + 1.0) - 1.0))) + 1


def _smooth(x: np.ndarray, sigma_px: float) -> np.ndarray:
    """``x`` (float32) through two box filters of about a Gaussian of ``sigma_px``."""
    k = _box_width(sigma_px)
    return cv2.blur(cv2.blur(x, (k, k)), (k, k))


def local_contrast(view: np.ndarray, sigma_px: float) -> np.ndarray:
    """(height, width) uint8: ``128 + GAIN * h / sqrt(S(h^2) + MIN_SPREAD^2)``, where
    ``h = L - S_sigma(L)``, ``L = LOG_SCALE log(view + LOG_OFFSET)`` and ``S_sigma`` two
    box filters of about a Gaussian of ``sigma_px`` (``S`` at ``2 sigma_px``).

    ``view``: (height, width) uint8 grey view as rendered or captured (before any
    equalisation). Every step is a pointwise map or a filter, so a pattern shifted
    in ``view`` is shifted in the result; a gain that varies slowly across the view
    (the rig's light, vignetting) is removed.

    Raises:
        ShapeError: ``view`` is not a 2-D uint8 image."""
    if view.dtype != np.uint8 or view.ndim != 2:
        raise ShapeError(f"view: (height, width) uint8 expected, got {view.dtype} {view.shape}")
    log = cv2.LUT(view, _LOG)
    h = cv2.subtract(log, _smooth(log, sigma_px))
    spread = cv2.sqrt(cv2.add(_smooth(cv2.multiply(h, h), 2.0 * sigma_px), MIN_SPREAD**2))
    return cv2.add(cv2.divide(h, spread, scale=GAIN), 128.0, dtype=cv2.CV_8U)


def wall_texture(views: Sequence[np.ndarray], masks: Sequence[np.ndarray]) -> float:
    """The median over ``views`` of each view's median local spread of log brightness
    (LOG_SCALE units) inside its mask: ``sqrt(S_2s(h^2))``, ``h = L - S_s(L)``, ``L`` the
    log of the view blurred by :data:`TEXTURE_BLUR_PX`, ``s`` = :data:`TEXTURE_SIGMA_PX`
    (:func:`local_contrast`'s spread, without its floor). NaN when no mask has a pixel.

    ``views``: (height, width) uint8 grey views before any equalisation;
    ``masks``: the same shapes, > 0 where the wall is seen (off the laser band)."""
    spreads = []
    for view, mask in zip(views, masks, strict=True):
        inside = mask > 0
        if not inside.any():
            continue
        log = cv2.LUT(cv2.GaussianBlur(view, (0, 0), TEXTURE_BLUR_PX), _LOG)
        h = cv2.subtract(log, _smooth(log, TEXTURE_SIGMA_PX))
        spread = cv2.sqrt(_smooth(cv2.multiply(h, h), 2.0 * TEXTURE_SIGMA_PX))
        spreads.append(float(np.median(spread[inside])))
    return float(np.median(spreads)) if spreads else math.nan

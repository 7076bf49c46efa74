"""The views as the optical flow reads them (:class:`FlowImage`), and the high-pass the
tracker applies to them (:func:`highpass`). Its own module so that :mod:`.features` (whose
:class:`~omnipipe.sfm.features.FrameViews` carry them) and :mod:`.tracking` (which makes
and reads them) both import it without importing each other."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

# Pyramid levels (the view's own included) that Lucas-Kanade reads high-passed.
FINE_LEVELS = 2


@dataclass(frozen=True)
class FlowImage:
    """One view as the flow reads it.

    Attributes:
        raw: (height, width) uint8 the view as it is (CLAHE).
        highpassed: the same high-passed (:func:`~omnipipe.sfm.tracking.flow_images`),
            where the finest levels of the pyramid are tracked; None when
            ``highpass_px`` is 0.
        coarse: with ``highpassed``, ``raw`` reduced ``2 ** FINE_LEVELS`` times
            (``cv2.pyrDown``): the pyramid's coarse levels, which find displacements
            larger than the window; None when there are no levels above the fine ones.
        band_px: with ``coarse``, the high-pass sigma (view px) of the second try's
            coarse levels (:attr:`coarse_band`).
    """

    raw: np.ndarray
    highpassed: np.ndarray | None
    coarse: np.ndarray | None = None
    band_px: float = 0.0

    @cached_property
    def coarse_band(self) -> np.ndarray | None:
        """``raw`` high-passed at ``band_px`` and reduced as ``coarse`` is: the coarse
        levels of the second try for the tracks the first lost (``tracking._flow``);
        made when first asked for. None without ``coarse``."""
        if self.coarse is None or self.band_px <= 0:
            return None
        out = highpass(self.raw, self.band_px)
        for _ in range(FINE_LEVELS):
            out = cv2.pyrDown(out)
        return out


def highpass(im: np.ndarray, sigma_px: float) -> np.ndarray:
    """``2 (I - B * I) + 128`` (uint8), B two box filters of about a Gaussian of
    ``sigma_px``."""
    # Two boxes of width k: variance 2 (k^2 - 1) / 12.
    k = 2 * int(round(0.5 * (math.sqrt(6.0 * sigma_px**2 + 1.0) - 1.0))) + 1
    return cv2.addWeighted(im, 2.0, cv2.blur(cv2.blur(im, (k, k)), (k, k)), -2.0, 128.0)

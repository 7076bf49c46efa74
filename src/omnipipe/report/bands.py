"""Images drawn a band of rows at a time (the report's long figures' memory bounded).

matplotlib resamples an image into the figure through float64 arrays of every figure
pixel the image covers; :func:`imshow_in_bands` draws it in bands of rows, so that only
a band's are held, with the same pixels as one ``imshow``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.image import AxesImage


BAND_ROWS = 32
"""Image rows :func:`imshow_in_bands` draws at a time."""

BAND_PAD = 8
"""Rows of its neighbours each band carries: the bilinear filter's reach where the
image has up to about 4x the rows of the axes' pixels (the report's images are
area-averaged to at most the figure's pixels first)."""


def imshow_in_bands(
    ax: Axes,
    image: np.ndarray,
    extent: tuple[float, float, float, float],
    rows: int = BAND_ROWS,
    **style: Any,
) -> AxesImage:
    """``ax.imshow(image, extent=extent, aspect="auto", interpolation="bilinear", **style)``,
    drawn as bands of ``rows`` image rows: matplotlib resamples an image through float64
    arrays of the figure's pixels it covers (107 MB for the 12-inch unrolled wall, 45 MB
    for the relief map's colour-mapped grid), a band's only. Each band carries
    :data:`BAND_PAD` rows of its neighbours (the filter's reach) and is clipped to its
    own rows: the same pixels as one image. Returns the last band's image (its colour
    map and norm are every band's: for a colour bar).

    Args:
        image: (H, W, 3) uint8, or (H, W) values (a masked array too) with ``style``'s
            colour map; extent: (left, right, bottom, top) as imshow's, the first row
            at ``top``.
    """
    import matplotlib.patches

    left, right, bottom, top = extent
    n = image.shape[0]

    def y(r: int) -> float:
        return bottom if r == n else top + (bottom - top) * r / n

    kw = {"aspect": "auto", "interpolation": "bilinear"} | style
    if n == 0:
        return ax.imshow(image, extent=extent, **kw)
    for r0 in range(0, n, rows):
        r1 = min(r0 + rows, n)
        e0, e1 = max(r0 - BAND_PAD, 0), min(r1 + BAND_PAD, n)
        im = ax.imshow(image[e0:e1], extent=(left, right, y(e1), y(e0)), **kw)
        if e0 < r0 or r1 < e1:
            im.set_clip_path(
                matplotlib.patches.Rectangle((left, y(r0)), right - left, y(r1) - y(r0), transform=ax.transData)
            )
    # Each imshow set the view to its own band's extent; the whole image's, as one
    # imshow leaves it (else a figure with nothing autoscaled after it shows the last
    # band, and matplotlib resamples the others at that zoom: +120 MB at 538 rows).
    if ax.get_autoscalex_on():
        ax.set_xlim((left, right), auto=None)
    if ax.get_autoscaley_on():
        ax.set_ylim((bottom, top), auto=None)
    return im

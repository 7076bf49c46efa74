"""Light on the unrolled wall: the laser's band kept out of the texture, and the flat field.

Texture is not taken where the red laser dominates the LED-lit colour: within
:data:`LASER_BAND_PX` pixels of the laser line's image (:func:`laser_line_px`; the
stripe is a few pixels wide in the image whatever its width in mm). After painting, the
illumination is divided out (:func:`flat_field`): the LEDs' falloff from the range and
incidence of each cell's view (known from the reconstruction) and the mirror's
vignetting as a gain of the image radius estimated from the data.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Protocol

import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.errors import ShapeError
from omnipipe.model.texture_grid import STRIP_ROWS, UnrolledImage
from omnipipe.scratch import ScratchStore
from omnipipe.spill import drop_pages

LASER_BAND_PX = 4.0
"""Texture is not taken within this many pixels of the laser line's image (its stripe,
blurred by the optics, is a few pixels wide whatever it is in mm on the wall)."""


def laser_line_px(
    camera: CameraModel, q: np.ndarray, px: np.ndarray, n_plane: np.ndarray, o_plane: float
) -> np.ndarray:
    """(n,) distance (px) from each wall point's pixel to the laser line's image at its
    azimuth: the point moved along the rig's z axis (the pipe's direction) onto the laser
    plane ``n . x + o = 0``, projected; inf where that point does not image.

    Args:
        camera: the camera model.
        q: (n, 3) wall points in the rig frame, mm.
        px: (n, 2) their pixels (col, row).
    """
    nz = float(n_plane[2])
    if abs(nz) < 1e-6:  # a plane along the axis: no ring to keep away from
        return np.full(len(q), np.inf)
    on_plane = q.copy()
    on_plane[:, 2] -= (q @ n_plane + o_plane) / nz
    line_px, ok = camera.project(on_plane)
    d = np.linalg.norm(line_px - px, axis=1)
    return np.where(ok & np.isfinite(d), d, np.inf)


FLAT_FIELD_BINS = 32
"""Bins of image radius (equal cell counts) of the data-driven vignetting gain."""


FLAT_FIELD_LEVEL = 128.0
"""Median luminance (8-bit) of the flat-fielded unrolled wall."""


def flat_field(
    unrolled: UnrolledImage, light: np.ndarray | LightRows, in_place: bool = False
) -> UnrolledImage:
    """The unrolled wall with the LEDs' falloff and the mirror's vignetting divided out.

    Each cell was imaged with gain ``E x V``: ``E = cos(incidence) / range^2`` of its wall
    point seen from the keyframe's rig origin (:attr:`CellChoice.light`, from the
    reconstruction; the LEDs sit near the axis, close to it), and ``V(r)`` a gain of the
    image radius ``r`` of its pixel: the mirror's vignetting plus whatever ``E``'s model
    misses (the LEDs' own position and beam). ``V`` is estimated from the data, not
    from a rig's parameters: the median of ``luminance / E`` over the cells of each
    of :data:`FLAT_FIELD_BINS` radius bins (equal counts; interpolated between), over
    its overall median. Every wall point around the pipe is seen at every radius, so the
    wall's own reflectance averages out per bin. Colours are divided by ``E x V``
    (clipped to 1/10..10 of the typical gain: grazing views are not blown up) and the
    whole image scaled so its median luminance is :data:`FLAT_FIELD_LEVEL`.

    Args:
        unrolled: the painted unrolled wall.
        light: (H, W, 2) :attr:`CellChoice.light` of its cells, or its rows on disk
            (:class:`LightStore`: read a band of rows at a time, never held whole).
        in_place: correct ``unrolled.image`` itself (no second image is made).

    Returns:
        The same image, corrected (cells without ``light`` only scaled).
    """
    img = unrolled.image
    h, w = img.shape[:2]
    if tuple(light.shape) != (h, w, 2):
        raise ShapeError(f"light: expected shape ({h}, {w}, 2), got {tuple(light.shape)}")
    rows = _as_rows(light)
    stride = max(1, (h * w) // 2_000_000)  # the estimate from at most ~2 M cells
    samples = _FlatFieldCells(img, rows, unrolled.alpha, stride)
    lum, irr, r_ok = samples.usable()
    if len(lum) < 4 * FLAT_FIELD_BINS:
        return unrolled
    irr_ref = float(np.median(irr))
    # lum / (irr / irr_ref), float32, in place: no third array of the cells.
    ratio = np.divide(lum, np.divide(irr, irr_ref, out=irr), out=lum)
    del lum, irr
    edges = np.unique(np.quantile(r_ok, np.linspace(0.0, 1.0, FLAT_FIELD_BINS + 1)))
    which = np.empty(len(r_ok), np.min_scalar_type(len(edges)))
    for a in range(0, len(r_ok), _CELLS_AT_ONCE):  # the bins' int64 a chunk at a time
        b = a + _CELLS_AT_ONCE
        which[a:b] = np.clip(np.searchsorted(edges, r_ok[a:b], side="right") - 1, 0, max(len(edges) - 2, 0))
    centres = np.array([np.median(r_ok[which == b]) for b in range(len(edges) - 1) if np.any(which == b)])
    level = np.array([np.median(ratio[which == b]) for b in range(len(edges) - 1) if np.any(which == b)])
    vign = level / float(np.median(ratio))
    del ratio, r_ok, which

    def gain(cells: np.ndarray) -> np.ndarray:
        """(..., ) float32 relative gain E x V of cells' (..., 2) light."""
        cells = cells.astype(np.float32)
        g = (np.exp2(cells[..., 0]) / irr_ref) * np.interp(cells[..., 1], centres, vign)
        return np.where(np.isfinite(g), np.clip(g, 0.1, 10.0), 1.0).astype(np.float32)

    # One scale for the whole wall: its corrected median luminance to the target level.
    corrected = np.concatenate(
        [lum_c[seen] / gain(light_c[seen]) for lum_c, light_c, seen in samples.chunks()]
    )
    scale = FLAT_FIELD_LEVEL / max(float(np.median(corrected, overwrite_input=True)), 1e-6)
    del corrected
    out = img if in_place else np.empty_like(img)
    for r0 in range(0, h, STRIP_ROWS):  # float32 intermediates a strip of rows at a time
        g = gain(rows.rows(r0, min(r0 + STRIP_ROWS, h)))
        part = img[r0 : r0 + STRIP_ROWS].astype(np.float32) * (scale / g)[..., None]
        out[r0 : r0 + STRIP_ROWS] = np.clip(np.round(part), 0, 255).astype(np.uint8)
        drop_pages()  # an image in the run's scratch (omnipipe.spill): a strip resident
    return replace(unrolled, image=out)


_CELLS_AT_ONCE = 1 << 18
"""Cells of :func:`flat_field`'s estimate evaluated at once (its float intermediates a
chunk's, not the wall's)."""


class _FlatFieldCells:
    """The cells :func:`flat_field` estimates from (every ``stride``-th, row-major), a
    band of rows at a time: the same values, in the same order, as taken all at once."""

    def __init__(self, img: np.ndarray, light: LightRows, alpha: np.ndarray, stride: int) -> None:
        self.img, self.light, self.alpha, self.stride = img, light, alpha, stride

    def chunks(self) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per band of rows: (n,) float32 luminance, (n, 2) light and (n,) alpha of its
        cells (about :data:`_CELLS_AT_ONCE` of them)."""
        h, w = self.img.shape[:2]
        band = max(1, (self.stride * _CELLS_AT_ONCE) // max(w, 1))
        for r0 in range(0, h, band):
            r1 = min(r0 + band, h)
            first = (-r0 * w) % self.stride  # the band's first cell on the stride
            sl = slice(first, None, self.stride)
            img = self.img[r0:r1].reshape(-1, 3)[sl]
            light = self.light.rows(r0, r1).reshape(-1, 2)[sl]
            yield img.astype(np.float32).mean(axis=1), light, self.alpha[r0:r1].reshape(-1)[sl]
            drop_pages()  # an image in the run's scratch: a band resident at a time

    def usable(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Luminance, irradiance E (float32) and image radius of the cells fit for the
        estimate (seen, finite positive E, luminance neither dark nor saturated)."""
        lum: list[np.ndarray] = []
        irr: list[np.ndarray] = []
        rad: list[np.ndarray] = []
        for lum_c, light_c, alpha_c in self.chunks():
            irr_c = np.exp2(light_c[:, 0].astype(np.float32))
            ok = alpha_c & np.isfinite(irr_c) & (irr_c > 0) & (lum_c > 2) & (lum_c < 253)
            lum.append(lum_c[ok])
            irr.append(irr_c[ok])
            rad.append(light_c[ok, 1].astype(np.float32))
        return _joined(lum, np.float32), _joined(irr, np.float32), _joined(rad, np.float32)


def _joined(parts: list[np.ndarray], dtype: type) -> np.ndarray:
    """``np.concatenate(parts)`` (the parts released as it goes), or an empty array."""
    out = np.empty(sum(len(p) for p in parts), dtype)
    at = 0
    while parts:
        part = parts.pop(0)
        out[at : at + len(part)] = part
        at += len(part)
    return out


class LightRows(Protocol):
    """Rows of a (H, W, 2) :attr:`CellChoice.light` grid."""

    @property
    def shape(self) -> tuple[int, int, int]: ...

    def rows(self, first: int, stop: int) -> np.ndarray:
        """(stop - first, W, 2) rows [first, stop)."""
        ...


class _ArrayLight:
    """An in-memory (H, W, 2) light grid as :class:`LightRows` (rows are views)."""

    def __init__(self, light: np.ndarray) -> None:
        self._light = light
        self.shape = light.shape

    def rows(self, first: int, stop: int) -> np.ndarray:
        return self._light[first:stop]


def _as_rows(light: np.ndarray | LightRows) -> LightRows:
    return _ArrayLight(light) if isinstance(light, np.ndarray) else light


class LightStore(ScratchStore):
    """The (H, W, 2) :data:`LIGHT_DTYPE` light grid on disk (the run's scratch folder),
    written a band of rows at a time in order and read back a band at a time: the model
    stage holds a section's rows, not the run's (4 bytes a cell).

    Attributes:
        shape: (H, W, 2).
    """

    def __init__(self, h: int, w: int, dtype: type = np.float16) -> None:
        super().__init__("omnipipe-light-")
        self.shape = (h, w, 2)
        self._dtype = np.dtype(dtype)
        self._path = Path(self._dir.name) / "light.bin"
        self._written = 0
        self._path.write_bytes(b"")

    def append(self, rows: np.ndarray) -> None:
        """Write the next (n, W, 2) rows."""
        if rows.shape[1:] != self.shape[1:] or self._written + len(rows) > self.shape[0]:
            raise ShapeError(f"light rows: expected (n <= {self.shape[0] - self._written}, "
                             f"{self.shape[1]}, 2), got {rows.shape}")
        with self._path.open("ab") as fh:
            fh.write(np.ascontiguousarray(rows, self._dtype).tobytes())
        self._written += len(rows)

    def rows(self, first: int, stop: int) -> np.ndarray:
        """(stop - first, W, 2) rows [first, stop) (written ones only)."""
        first, stop = max(first, 0), min(stop, self._written)
        w = self.shape[1]
        n = max(stop - first, 0) * w * 2
        with self._path.open("rb") as fh:
            fh.seek(first * w * 2 * self._dtype.itemsize)
            data = np.fromfile(fh, self._dtype, n)
        return data.reshape(-1, w, 2)

"""The rig-fixed illumination of a run's keyframes: a flat field for Eq. 17.

The LEDs and the mirror's vignetting move with the robot; the wall does not. Over a
set of keyframes (each a different stretch of wall under the same rig) the per-pixel
median of the grey images is the illumination the rig casts, the wall's texture
averaged out. Where a laser ring sits close to the blind centre, a step of a few
pixels leaves the templates of the laser-point matching (:mod:`omnipipe.sfm.laser_scale`)
dominated by that fall-off, which is the same at every candidate length and pulls the
match short; divided by the flat field, the templates keep the wall's own texture.
The laser's own light in the grey image (colour crosstalk, blur beside the stripe) is
rig-fixed too where the wall's distance does not change; the smoothing below keeps
only its broad part.

The field is the per-pixel median of up to ``LaserScaleConfig.flat_field_keyframes``
keyframes around each step (:class:`FlatWindow`), only in the band of image radii the
steps' laser points and their matches can reach (the rings' radii widened by
:data:`BAND_SHARE` of the image's size; 1 elsewhere), smoothed by a Gaussian of
:data:`SIGMA_PX`: with a few keyframes, regular steps and a periodic wall (tiles,
bricks, corrugations) the median keeps some of the wall's pattern, which the
smoothing takes out (with the stripe's narrow light); the LEDs' fall-off stays. With
fewer than :data:`MIN_KEYFRAMES` keyframes there is no field.

Every Eq. 17 reading of a step uses the same field: the step's evidence in a worker,
the re-match around a chosen length (:func:`omnipipe.sfm.step_decide.laser_around`) and
the adjustment's far laser anchors (:mod:`omnipipe.sfm.adjust`, a pair (a, b) with step
a's field). The fields are built once, in the keyframe loop, and kept on disk
(:class:`FlatFields`); a local pool's workers read them by path.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Generic, TypeVar

import cv2
import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.errors import ReconstructionError
from omnipipe.sfm.image_store import ImageStore, StoredImage, load_image

# The band reaches this share of the image's longer side (px), plus BAND_PX, beyond
# the rings' radii: the template's patch and the step's motion in the image.
BAND_SHARE = 0.04
BAND_PX = 8.0
# Fewest keyframes a field is built from: the median of fewer keeps too much of the
# wall (random-wide seed 3, three keyframes: its laser lengths -24 -> -85 %).
MIN_KEYFRAMES = 8
# Smoothing of the median (Gaussian sigma, px).
SIGMA_PX = 3.0
# The field is clipped from below at this fraction of its median (dark corners).
FLOOR = 0.1


@dataclass(frozen=True)
class FlatField:
    """The rig-fixed illumination.

    Attributes:
        field: (H, W) float32, relative to its median in the band (1.0), at least
            :data:`FLOOR`; 1 outside the band.
    """

    field: np.ndarray

    def apply(self, gray: np.ndarray) -> np.ndarray:
        """(H, W) ``gray`` divided by the field, float32."""
        return np.asarray(gray, np.float32) / self.field


def as_field(flat: FlatField | StoredImage | None) -> FlatField | None:
    """``flat`` as a :class:`FlatField` (a stored field read from its file); None: none."""
    if flat is None or isinstance(flat, FlatField):
        return flat
    return FlatField(np.asarray(load_image(flat), np.float32))


def divided(gray: np.ndarray | StoredImage, flat: FlatField | StoredImage | None) -> np.ndarray:
    """(H, W) ``gray`` (an array or a stored one) as float32, divided by ``flat`` (none:
    as it is)."""
    g = np.asarray(load_image(gray), np.float32)
    field = as_field(flat)
    return g if field is None else field.apply(g)


class FlatFields:
    """A run's flat fields, on disk, and which one each keyframe step uses.

    Step k's field is the one :class:`FlatWindow` released it with; a keyframe index
    without one of its own (a lost step, the last keyframe) takes the nearest step's
    that has one (the lower on a tie). No field at all (too few keyframes, or off):
    every lookup gives None.
    """

    def __init__(self) -> None:
        self._store: ImageStore | None = None
        self._of_step: dict[int, int] = {}
        self._steps: np.ndarray = np.zeros(0, int)  # sorted keys of _of_step, rebuilt lazily

    def add(self, field: FlatField) -> int:
        """Store ``field``; its index."""
        if self._store is None:
            self._store = ImageStore()
        self._store.append(field.field)
        return len(self._store) - 1

    def stored(self, index: int) -> StoredImage:
        """Stored field ``index``'s file, for a worker on this file system."""
        if self._store is None:
            raise ReconstructionError(f"flat field {index} asked for before any was stored")
        return self._store.ref(index)

    def assign(self, k: int, index: int) -> None:
        """Step ``k`` uses stored field ``index``."""
        self._of_step[k] = index
        self._steps = np.zeros(0, int)

    def _index(self, k: int) -> int | None:
        if not self._of_step:
            return None
        if k in self._of_step:
            return self._of_step[k]
        if len(self._steps) != len(self._of_step):
            self._steps = np.array(sorted(self._of_step), int)
        near = int(self._steps[np.argmin(np.abs(self._steps - k))])  # argmin: the lower on a tie
        return self._of_step[near]

    def get(self, k: int) -> FlatField | None:
        """Keyframe ``k``'s step's field, read from disk (None: no field)."""
        i = self._index(k)
        return None if i is None or self._store is None else FlatField(self._store[i])

    def for_worker(self, k: int, shares_files: bool) -> FlatField | StoredImage | None:
        """Keyframe ``k``'s step's field as sent to a task: a reference to its file for a
        worker on this file system (``shares_files``), else the field itself."""
        i = self._index(k)
        if i is None or self._store is None:
            return None
        return self.stored(i) if shares_files else FlatField(self._store[i])

    def close(self) -> None:
        """Remove the stored fields' files."""
        if self._store is not None:
            self._store.close()


def flat_field(stack: np.ndarray, band: np.ndarray) -> FlatField | None:
    """The flat field of (K, H, W) grey images: their per-pixel median in the (H, W)
    ``band`` over its median there, 1 elsewhere, smoothed (Gaussian, sigma
    :data:`SIGMA_PX`). None with fewer than :data:`MIN_KEYFRAMES` images or an empty band
    (no robust statistic)."""
    if len(stack) < MIN_KEYFRAMES or not band.any():
        return None
    idx = np.flatnonzero(band)
    med = np.median(stack.reshape(len(stack), -1)[:, idx], axis=0).astype(np.float32)
    norm = float(np.median(med))
    if not norm > 0:
        return None
    field = np.ones(band.size, np.float32)
    field[idx] = np.maximum(med / norm, FLOOR)
    smooth = cv2.GaussianBlur(field.reshape(band.shape), (0, 0), SIGMA_PX, borderType=cv2.BORDER_REFLECT)
    return FlatField(smooth)


def ring_band(camera: CameraModel, radii: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels whose distance from the image centre (cx, cy) lies within
    the band of the (R,) ring radii (px; their 1st to 99th percentile) widened by
    :data:`BAND_SHARE` of the image's longer side plus :data:`BAND_PX`."""
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    r = np.hypot(cols - camera.cx, rows - camera.cy)
    radii = radii[np.isfinite(radii)]
    if len(radii) == 0:
        return np.zeros(r.shape, bool)
    lo, hi = np.percentile(radii, [1, 99])
    m = BAND_SHARE * max(camera.height, camera.width) + BAND_PX
    return (r >= lo - m) & (r <= hi + m)


T = TypeVar("T")


class _Later(Generic[T]):
    """A step's evidence future, submitted once its flat field is known (an
    :class:`omnipipe.executor.Pending`)."""

    future: Future[T] | None = None

    def done(self) -> bool:
        """True once the step was released and its worker is done."""
        return self.future is not None and self.future.done()

    def result(self) -> T:
        """The worker's result (the step must have been released)."""
        if self.future is None:
            raise ReconstructionError("a flat-fielded step's evidence asked for before it was released")
        return self.future.result()


class FlatWindow:
    """Each keyframe step's flat field from the ``size`` keyframes around it, and the
    steps' evidence held until it is known.

    Step k (keyframes k -> k + 1) is released once keyframe k + size // 2 has come
    (and at least ``size`` keyframes) at the next keyframe whose count is a multiple of
    ``max(1, size // 4)`` (one field serves that many steps), or at the end of the run:
    its field is the median of the last ``size`` keyframes then (all of them in a
    shorter run), which hold keyframes k and k + 1. The
    keyframes it uses are a function of k and the run's length only, never of when a
    worker finished. ``size`` 0: no flat field, each step submitted at once.

    Each field built is kept in :attr:`fields` (with the steps it serves) and handed to
    ``submit`` as a reference to its file when ``shares_files`` (a local pool's workers
    read it themselves), else as the field.
    """

    def __init__(self, camera: CameraModel, size: int, shares_files: bool = False) -> None:
        self.size = size
        self.shares_files = shares_files
        self.fields = FlatFields()
        self.every = max(1, size // 4)
        self.camera = camera
        self._kept: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=max(size, 1))
        self._n = 0
        self._waiting: deque[tuple[int, Callable[[FlatField | StoredImage | None], Future], _Later]] = deque()

    def add_keyframe(self, gray: np.ndarray, ring_pixels: np.ndarray) -> list[Future]:
        """The next keyframe's (H, W) grey image and its laser ring's (N, 2) pixels
        (col, row); returns the futures of the steps released by it."""
        self._n += 1
        if not self.size:
            return []
        g = np.asarray(gray)
        g = g.copy() if g.dtype in (np.uint8, np.uint16) else g.astype(np.float32)
        px = np.asarray(ring_pixels, float).reshape(-1, 2)
        self._kept.append((g, np.hypot(px[:, 0] - self.camera.cx, px[:, 1] - self.camera.cy)))
        return self._release(final=False)

    def submit(self, k: int, submit: Callable[[FlatField | StoredImage | None], Future]) -> tuple[_Later, list[Future]]:
        """Step k's ``submit(flat field)``, now or when its keyframes are known: its
        handle (``.result()``) and the futures submitted by this call."""
        later = _Later()
        if not self.size:
            later.future = submit(None)
            return later, [later.future]
        self._waiting.append((k, submit, later))
        return later, self._release(final=False)

    def finish(self) -> list[Future]:
        """Every step still waiting, released with the last keyframes' field."""
        return self._release(final=True)

    def current(self) -> FlatField | None:
        """The field of the last ``size`` keyframes (None: off, or too few)."""
        if not self.size or not self._kept:
            return None
        band = ring_band(self.camera, np.concatenate([r for _, r in self._kept]))
        return flat_field(np.stack([g for g, _ in self._kept]), band)

    def _release(self, final: bool) -> list[Future]:
        out: list[Future] = []
        sent: FlatField | StoredImage | None = None
        index: int | None = None
        built = False
        while self._waiting:
            k, submit, later = self._waiting[0]
            if not final and (
                self._n < k + 1 + self.size // 2 or self._n < self.size or self._n % self.every
            ):
                break
            if not built:
                field, built = self.current(), True
                if field is not None:
                    index = self.fields.add(field)
                    sent = self.fields.stored(index) if self.shares_files else field
            self._waiting.popleft()
            if index is not None:
                self.fields.assign(k, index)
            later.future = submit(sent)
            out.append(later.future)
        return out

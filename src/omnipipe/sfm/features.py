"""SIFT features on perspective-projected views (paper Sec. V-A), as ray vectors.

The omni image is converted to a ring of perspective views around the mirror axis
(Fig. 11), free of the mirror's distortion; OpenCV's SIFT runs on each view; every
keypoint becomes a unit ray in the rig frame (and an omni pixel). The laser band is
masked out: the laser moves with the rig and would look like a static feature.
Rays seen by two overlapping views are kept once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numba
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from omnipipe.camera import CameraModel, PerspectiveView
from omnipipe.config import bounded
from omnipipe.errors import ConfigError
from omnipipe.executor import thread_map
from omnipipe.image import CHANNEL_INDEX, gray_without_laser
from omnipipe.sfm._kernels import two_smallest_columns

if TYPE_CHECKING:
    from omnipipe.sfm.flow_image import FlowImage


@dataclass(frozen=True)
class FeatureConfig:
    """Feature extraction.

    Attributes:
        views: perspective views around the axis.
        elevation_deg: (low, high) elevation band the views cover (deg, + towards the mirror).
        max_features: SIFT budget per frame (split over the views).
        laser_margin_px: half width of the masked band around the laser ring (omni px).
        ratio: Lowe's ratio test for matching.
        contrast_threshold: SIFT's contrast threshold (OpenCV default 0.04).
        detect_scale: SIFT runs on each view resized by this factor (1: as it is);
            the keypoints are mapped back to the view's pixels, where the tracking
            follows them. OpenCV doubles its input before the first octave, so at 0.3
            the finest octave is 0.6 of the view: about as many keypoints a keyframe as
            at half size for a bit over half the cost.
        detect_min_side_px: the views are detected at full size when ``detect_scale``
            would make their shorter side smaller than this (px). 1600x1200's views
            (335x484 px) are reduced; other-rig's (285x398) and smaller ones keep every
            pixel (reduced, their runs lost accuracy: benchmarks/RESULTS.md).
        flow_plain: each frame's views also keep their images before CLAHE
            (:attr:`FrameViews.plain`), where the tracker's finest flow levels then read
            their local contrast (:func:`~omnipipe.sfm.flow_contrast.local_contrast`,
            :func:`~omnipipe.sfm.tracking.flow_images`). CLAHE's tiles are fixed in the
            view and, like the rig's light, hold a broad pattern's tracks back
            (random-wide seed 18, corrugated: every keyframe step's tracks 5 % short
            with the true motion; 0.0-0.4 % with the local contrast). False (the
            default): those levels read the CLAHE'd views high-passed. Off because the
            run's scale decisions downstream were tuned on the lagging tracks: on, the
            robustness bench gained on 11 seeds and lost on 11 (benchmarks/RESULTS.md,
            feat23's and feat24's entries). On, a run whose wall is plain keeps the
            CLAHE'd views (:func:`omnipipe.sfm.pipeline.run`, the texture floor).
    """

    views: int = bounded(8, ge=1)
    elevation_deg: tuple[float, float] = bounded((-55.0, 15.0), ge=-90, le=90)
    max_features: int = bounded(3000, ge=1)
    laser_margin_px: float = bounded(6.0, ge=0)
    ratio: float = bounded(0.8, gt=0, le=1)
    contrast_threshold: float = bounded(0.01, ge=0)
    detect_scale: float = bounded(0.3, gt=0, le=1)
    detect_min_side_px: int = bounded(96, ge=1)
    flow_plain: bool = False

    def __post_init__(self) -> None:
        if self.views < 1:
            raise ConfigError("sfm.features.views", f"must be >= 1, got {self.views}")
        if self.max_features < self.views:
            raise ConfigError(
                "sfm.features.max_features", f"must be at least the number of views ({self.views}), got {self.max_features}"
            )
        if not 0 < self.ratio <= 1:
            raise ConfigError("sfm.features.ratio", f"must be in (0, 1], got {self.ratio}")


@dataclass
class FrameFeatures:
    """Features of one frame.

    Attributes:
        rays_in_rig: (N, 3) unit rays.
        pixels: (N, 2) omni pixels (col, row).
        descriptors: (N, 128) float32 SIFT descriptors.
        view: (N,) index of the perspective view.
        view_pixels: (N, 2) float32 position in that view (col, row; px), where the
            tracking between keyframes (:mod:`omnipipe.sfm.tracking`) starts; None when
            not kept.
    """

    rays_in_rig: np.ndarray
    pixels: np.ndarray
    descriptors: np.ndarray
    view: np.ndarray
    view_pixels: np.ndarray | None = None

    @classmethod
    def empty(cls) -> FrameFeatures:
        """No features (with empty view pixels)."""
        return cls(
            np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros(0, int),
            np.zeros((0, 2), np.float32),
        )


@dataclass
class FrameViews:
    """One frame's perspective views, as SIFT and the tracker read them.

    Attributes:
        images: per view, (height, width) uint8 grey image after CLAHE.
        masks: per view, (height, width) uint8, 255 where features may be (inside the
            mirror's annulus, off the laser band, eroded by 2 px).
        plain: per view, the grey image before CLAHE, where the tracker's finest flow
            levels read (None: not kept; :attr:`FeatureConfig.flow_plain`).
        flow: per view, the tracker's :class:`~omnipipe.sfm.flow_image.FlowImage` of it
            (:func:`~omnipipe.sfm.tracking.flow_images`), made where the views were made
            (a worker, :class:`omnipipe.sfm.tasks.FeatureTask`); None: made by the
            tracker when it needs them.
    """

    images: list[np.ndarray]
    masks: list[np.ndarray]
    plain: list[np.ndarray] | None = None
    flow: list[FlowImage] | None = None

    def __getstate__(self) -> dict[str, object]:
        """Pickled with the masks one bit a pixel when they hold only 0 and 255
        (:func:`pack_masks`): the views go between processes (a worker's views to the
        frame loop, a pending frame's to the worker that follows it back), and a third
        of their bytes were the masks."""
        state = dict(self.__dict__)
        state["masks"] = pack_masks(self.masks)
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        state = dict(state)
        state["masks"] = unpack_masks(state["masks"])
        self.__dict__.update(state)


@dataclass(frozen=True)
class PackedMasks:
    """Masks of 0 and 255 only, one bit a pixel (:func:`pack_masks`).

    Attributes:
        shapes: per mask its (height, width).
        bits: per mask ``np.packbits`` of its pixels > 0, row-major.
    """

    shapes: list[tuple[int, ...]]
    bits: list[np.ndarray]


def pack_masks(masks: list[np.ndarray]) -> list[np.ndarray] | PackedMasks:
    """``masks`` (uint8 images) as :class:`PackedMasks` when every one holds only 0 and
    255 (those of :meth:`FeatureExtractor.frame_views`), else as they are;
    :func:`unpack_masks` gives back the same arrays, value for value."""
    if not all(isinstance(m, np.ndarray) and m.dtype == np.uint8 for m in masks):
        return masks
    if not all(np.count_nonzero(m) == np.count_nonzero(m == 255) for m in masks):
        return masks
    return PackedMasks([m.shape for m in masks], [np.packbits(m, axis=None) for m in masks])


def unpack_masks(packed: list[np.ndarray] | PackedMasks) -> list[np.ndarray]:
    """The masks :func:`pack_masks` was given (uint8, 0 and 255)."""
    if not isinstance(packed, PackedMasks):
        return packed
    return [
        np.unpackbits(b, count=math.prod(shape)).reshape(shape) * np.uint8(255)
        for shape, b in zip(packed.shapes, packed.bits, strict=True)
    ]


class FeatureExtractor:
    """Builds the perspective views of one camera once and extracts features per frame."""

    def __init__(self, camera: CameraModel, config: FeatureConfig | None = None) -> None:
        self.camera = camera
        self.config = cfg = config or FeatureConfig()
        mid, focal, width, height = _view_geometry(camera, cfg)
        self.views = []
        self.maps = []
        for k in range(cfg.views):
            az = 2 * math.pi * k / cfg.views
            d = np.array(
                [math.cos(az) * math.cos(mid), math.sin(az) * math.cos(mid), math.sin(mid)]
            )
            view = PerspectiveView.looking_at(d, width=width, height=height, focal_px=focal)
            mx, my, valid = view.omni_maps(camera)
            self.views.append(view)
            self.maps.append((mx, my, valid))
        # Pipe walls are dim and low in contrast: a low SIFT contrast threshold, and
        # local contrast equalisation (CLAHE) of each view before detection.
        self.sift = cv2.SIFT_create(
            nfeatures=max(1, cfg.max_features // cfg.views),
            contrastThreshold=cfg.contrast_threshold,
        )
        # One detector per view (the same settings), so that views run on threads share
        # no detector; ``threads``: how many views at once (:func:`~omnipipe.executor.thread_map`).
        self.sifts = [self.sift] + [
            cv2.SIFT_create(nfeatures=max(1, cfg.max_features // cfg.views), contrastThreshold=cfg.contrast_threshold)
            for _ in range(cfg.views - 1)
        ]
        self.threads = 1
        self.detect_scale = detection_scale(cfg, width, height)
        self.clahe = cv2.createCLAHE(clipLimit=3.0, tileGridSize=(8, 8))
        # The mirror's annulus, once (45 ms per frame at 1600x1200 when rebuilt per frame).
        self.annulus = camera.valid_mask().astype(np.uint8) * 255
        self.view_masks = [
            ViewMask.of(self.annulus, mx, my, valid, (camera.cx, camera.cy)) for mx, my, valid in self.maps
        ]

    def extract(
        self, image: np.ndarray, laser_channel: str, laser_pixels: np.ndarray | None = None
    ) -> FrameFeatures:
        """Features of one frame; ``laser_pixels`` (M, 2) are masked out."""
        return self.detect(self.frame_views(image, laser_channel, laser_pixels))

    def frame_views(
        self, image: np.ndarray, laser_channel: str, laser_pixels: np.ndarray | None = None
    ) -> FrameViews:
        """The perspective views of one frame (grey without the laser, CLAHE) and their
        feature masks; ``laser_pixels`` (M, 2) omni pixels are masked out."""
        cfg = self.config
        gray = _gray(image, laser_channel)
        mask, band = self.annulus, None
        if laser_pixels is not None and len(laser_pixels):
            mask = self.annulus.copy()
            pts = np.round(laser_pixels * 4).astype(np.int32).reshape(-1, 1, 2)
            thickness = int(2 * cfg.laser_margin_px + 1)
            cv2.polylines(mask, [pts], False, 0, thickness=thickness, shift=2)
            band = band_radii(pts.reshape(-1, 2) / 4.0, (self.camera.cx, self.camera.cy), 0.5 * thickness)
        images, masks, plain = [], [], []
        for (mx, my, valid), base in zip(self.maps, self.view_masks, strict=True):
            view = cv2.remap(gray, mx, my, cv2.INTER_LINEAR)
            images.append(self.clahe.apply(view))
            if cfg.flow_plain:
                plain.append(view)
            masks.append(base.with_band(mask, mx, my, valid, band))
        return FrameViews(images, masks, plain if cfg.flow_plain else None)

    def detect(self, views: FrameViews) -> FrameFeatures:
        """SIFT features of one frame's :meth:`frame_views`, as rays (with view pixels)."""
        cam = self.camera
        rays, descs, vidx, vpx = [], [], [], []
        scale = self.detect_scale
        found = thread_map(
            lambda sift, img, vmask: _sift_view(sift, img, vmask, scale),
            self.sifts, views.images, views.masks, threads=self.threads,
        )
        for k, (view, (pts, desc)) in enumerate(zip(self.views, found, strict=True)):
            if desc is None or not len(pts):
                continue
            rays.append(view.rays(pts))
            descs.append(desc)
            vidx.append(np.full(len(pts), k))
            vpx.append(pts.astype(np.float32))
        if not rays:
            return FrameFeatures.empty()
        r = np.concatenate(rays)
        d = np.concatenate(descs).astype(np.float32)
        v = np.concatenate(vidx)
        p = np.concatenate(vpx)
        # Overlapping views see some rays twice: keep the first of each pair closer than 0.05 deg.
        pairs = cKDTree(r).query_pairs(math.radians(0.05), output_type="ndarray")
        keep = np.ones(len(r), bool)
        if len(pairs):
            keep[np.maximum(pairs[:, 0], pairs[:, 1])] = False
        r, d, v, p = r[keep], d[keep], v[keep], p[keep]
        px, _ = cam.project(r)
        return FrameFeatures(r, px, d, v, p)


# The views' masks are eroded by this square (px): features keep off the mask's edges.
_ERODE = np.ones((5, 5), np.uint8)


@dataclass(frozen=True)
class ViewMask:
    """One view's feature mask without the laser band, and the omni radii each of its
    rows reads, so that a frame's laser band is resampled only in the rows it can reach
    (:meth:`with_band`; the ring lies in a fifth of the rows of 1600x1200's views).

    Attributes:
        base: (h, w) uint8 the annulus (0 / 255) resampled into the view (nearest
            pixel), 0 where the view sees no valid pixel.
        eroded: ``base`` eroded by :data:`_ERODE`.
        row_lo, row_hi: (h,) the smallest and largest distance (omni px) from the
            mirror's centre of the pixels a row's nearest-pixel samples can come from
            (each widened by 1 px); +inf / -inf in a row without a finite sample.
    """

    base: np.ndarray
    eroded: np.ndarray
    row_lo: np.ndarray
    row_hi: np.ndarray

    @classmethod
    def of(cls, annulus: np.ndarray, mx: np.ndarray, my: np.ndarray, valid: np.ndarray, centre: tuple[float, float]) -> ViewMask:
        """The view of maps ``mx``, ``my`` (h, w) float32 omni px and ``valid`` (h, w) bool
        over the ``annulus`` (H, W) uint8 mask; ``centre`` (col, row) omni px."""
        base = cv2.remap(annulus, mx, my, cv2.INTER_NEAREST)
        base[~valid] = 0
        r = np.hypot(mx.astype(float) - centre[0], my.astype(float) - centre[1])
        finite = np.isfinite(r)
        lo = np.where(finite, r, np.inf).min(axis=1) - 1.0
        hi = np.where(finite, r, -np.inf).max(axis=1) + 1.0
        return cls(base, cv2.erode(base, _ERODE), lo, hi)

    def with_band(
        self, mask: np.ndarray, mx: np.ndarray, my: np.ndarray, valid: np.ndarray, band: tuple[float, float] | None
    ) -> np.ndarray:
        """(h, w) uint8 the omni ``mask`` (the annulus with the frame's laser band cut
        out) resampled like :attr:`base` and eroded by :data:`_ERODE`, the same pixels
        as resampling the whole view: rows whose radii miss ``band`` (lowest, highest
        radius the cut reaches, omni px; None: no cut) read the annulus alone, so they
        are :attr:`eroded`'s rows (those within the erosion's reach of a resampled row
        eroded again)."""
        rows = np.zeros(0, int) if band is None else np.flatnonzero((self.row_hi >= band[0]) & (self.row_lo <= band[1]))
        if len(rows) == 0:
            return self.eroded.copy()
        h = len(self.base)
        r0, r1 = int(rows[0]), int(rows[-1]) + 1
        full = self.base.copy()
        part = cv2.remap(mask, mx[r0:r1], my[r0:r1], cv2.INTER_NEAREST)
        part[~valid[r0:r1]] = 0
        full[r0:r1] = part
        reach = _ERODE.shape[0] // 2
        a, b = max(r0 - reach, 0), min(r1 + reach, h)  # the rows the new ones can change
        s0, s1 = max(a - reach, 0), min(b + reach, h)  # and every row those read
        out = self.eroded.copy()
        out[a:b] = cv2.erode(full[s0:s1], _ERODE)[a - s0 : b - s0]
        return out


def band_radii(points: np.ndarray, centre: tuple[float, float], half_width: float) -> tuple[float, float]:
    """(lowest, highest) distance (px) from ``centre`` (col, row) that a polyline through
    ``points`` (N, 2) px drawn ``2 half_width`` px thick can reach, widened by 2 px (the
    drawing's rounding): each segment's nearest point to the centre, the farthest vertex."""
    d = points - np.asarray(centre, float)
    r = np.hypot(d[:, 0], d[:, 1])
    near = float(r.min())
    if len(d) > 1:
        a, e = d[:-1], np.diff(d, axis=0)
        ee = np.einsum("ij,ij->i", e, e)
        t = np.clip(-np.einsum("ij,ij->i", a, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
        closest = a + t[:, None] * e
        near = min(near, float(np.hypot(closest[:, 0], closest[:, 1]).min()))
    return near - half_width - 2.0, float(r.max()) + half_width + 2.0


def concat_features(parts: list[FrameFeatures]) -> FrameFeatures:
    """The features of ``parts`` one after the other (each with descriptors or as
    many zero rows; view pixels when every part has them)."""
    def desc(f: FrameFeatures) -> np.ndarray:
        return f.descriptors if len(f.descriptors) == len(f.view) else np.zeros((len(f.view), 128), np.float32)

    vpx = (
        np.concatenate([f.view_pixels for f in parts]).astype(np.float32)
        if all(f.view_pixels is not None for f in parts)
        else None
    )
    return FrameFeatures(
        np.concatenate([f.rays_in_rig for f in parts]),
        np.concatenate([f.pixels for f in parts]),
        np.concatenate([desc(f) for f in parts]).astype(np.float32),
        np.concatenate([f.view for f in parts]),
        vpx,
    )


def _view_geometry(camera: CameraModel, cfg: FeatureConfig) -> tuple[float, float, int, int]:
    """The views' middle elevation (rad), focal length (px, matched to the omni image's
    angular resolution in the band), width and height (px)."""
    lo, hi = (math.radians(v) for v in cfg.elevation_deg)
    lo_cam, hi_cam = camera.elevation_range()
    lo, hi = max(lo, lo_cam + 0.02), min(hi, hi_cam - 0.02)
    focal = 1.0 / max(camera.angular_resolution(), 1e-4)
    half_h = math.pi / cfg.views * 1.15  # overlap between neighbouring views
    half_v = 0.5 * (hi - lo)
    return 0.5 * (lo + hi), focal, int(2 * focal * math.tan(half_h)), int(2 * focal * math.tan(half_v))


def view_size(camera: CameraModel, config: FeatureConfig) -> tuple[int, int]:
    """(height, width) px of the perspective views :class:`FeatureExtractor` makes of
    ``camera``'s frames."""
    _, _, width, height = _view_geometry(camera, config)
    return height, width


def detection_scale(config: FeatureConfig, width: int, height: int) -> float:
    """The factor SIFT resizes a ``width`` x ``height`` px view by: ``config.detect_scale``
    unless the resized view's shorter side would fall below ``config.detect_min_side_px``
    (then 1)."""
    if config.detect_scale * min(width, height) < config.detect_min_side_px:
        return 1.0
    return float(config.detect_scale)


def _sift_view(
    sift: cv2.SIFT, image: np.ndarray, mask: np.ndarray, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray | None]:
    """``sift.detectAndCompute`` of ``image`` (H, W) uint8 and its ``mask`` resized by
    ``scale`` (area average; the mask's nearest pixel): the (N, 2) keypoint positions
    (float64 of OpenCV's float32) back in ``image``'s pixels, and their descriptors.
    OpenCV places a keypoint a quarter pixel of its input off (its doubled first
    octave): ``(p + 1/4) f - 1/2`` maps it to ``image``'s pixel centres, ``f`` the
    resize's factor per axis (at half size that is ``2 p``, where the two offsets
    cancel; at 0.3 the plain ``p f`` lay a third of a pixel off). The positions are
    read in one call (``cv2.KeyPoint_convert``) and rounded to float32 as a
    ``cv2.KeyPoint`` holds them."""
    h, w = image.shape[:2]
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    if scale != 1.0:
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        mask = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)
    kps, desc = sift.detectAndCompute(image, mask)
    if not kps:
        return np.zeros((0, 2)), desc
    pts = np.asarray(cv2.KeyPoint_convert(kps), np.float32).reshape(-1, 2).astype(np.float64)
    if scale == 1.0:
        return pts, desc
    back = (pts + 0.25) * np.array([w / size[0], h / size[1]]) - 0.5
    return back.astype(np.float32).astype(np.float64), desc


def _gray(image: np.ndarray, laser_channel: str) -> np.ndarray:
    """8-bit grey image without the laser's channel (an 8-bit frame whose grey image is
    one channel, a red laser's green or a grey frame, read as that channel directly:
    the same values without two float32 copies of the frame)."""
    if image.dtype == np.uint8 and (image.ndim == 2 or CHANNEL_INDEX.get(laser_channel) == 0):
        return np.ascontiguousarray(image if image.ndim == 2 else cv2.extractChannel(image, 1))
    g = gray_without_laser(image, laser_channel)
    if image.dtype != np.uint8:
        g = cv2.normalize(g, None, 0, 255, cv2.NORM_MINMAX)
    return np.ascontiguousarray(g.astype(np.uint8))


def match_features(f1: FrameFeatures, f2: FrameFeatures, ratio: float = 0.8) -> np.ndarray:
    """(M, 2) index pairs: Lowe's ratio test both ways and a mutual check. Features
    without a descriptor (a zero row: tracked points, corners) match nothing."""
    i1, i2 = _described(f1.descriptors), _described(f2.descriptors)
    if len(i1) < 2 or len(i2) < 2:
        return np.zeros((0, 2), int)
    if len(i1) < len(f1.descriptors) or len(i2) < len(f2.descriptors):
        sub1 = FrameFeatures(f1.rays_in_rig[i1], f1.pixels[i1], f1.descriptors[i1], f1.view[i1])
        sub2 = FrameFeatures(f2.rays_in_rig[i2], f2.pixels[i2], f2.descriptors[i2], f2.view[i2])
        m = match_features(sub1, sub2, ratio)
        return np.stack([i1[m[:, 0]], i2[m[:, 1]]], axis=1) if len(m) else m

    q = np.ascontiguousarray(f1.descriptors, np.float32)
    t = np.ascontiguousarray(f2.descriptors, np.float32)
    exact = _whole_bytes(q, t)
    if exact:  # two_nearest's exact path, its product kept for the backward search
        dot = q @ t.T
        qq, tt = np.einsum("ij,ij->i", q, q), np.einsum("ij,ij->i", t, t)
        best, d0sq, d1sq = _two_smallest(qq, tt, dot)
        d0, d1 = np.sqrt(d0sq), np.sqrt(d1sq)
    else:
        best, d0, d1 = two_nearest(q, t)
    fwd = _passed(best, d0, d1, ratio)
    # Only the features of f2 that some f1 feature chose can pass the mutual check: the
    # backward search is run for those alone. Each query's neighbours depend on its own
    # distances only, so this is the full backward search restricted to them; with
    # whole-number descriptors it reads the forward product's columns (the same whole
    # numbers a product of its own would give).
    targets = np.unique(np.fromiter(fwd.values(), int, len(fwd)))
    if len(targets) == 0:
        return np.zeros((0, 2), int)
    if exact:
        best, d0sq, d1sq = two_smallest_columns(qq, tt, dot, targets)
        d0, d1 = np.sqrt(d0sq), np.sqrt(d1sq)
    else:
        best, d0, d1 = two_nearest(t[targets], q)
    bwd = {int(targets[i]): j for i, j in _passed(best, d0, d1, ratio).items()}
    pairs = [(i, j) for i, j in fwd.items() if bwd.get(j) == i]
    return np.array(pairs, int).reshape(-1, 2)


def _passed(best: np.ndarray, d0: np.ndarray, d1: np.ndarray, ratio: float) -> dict[int, int]:
    """Query -> nearest train index for the queries whose (N,) nearest distance ``d0``
    passes Lowe's ratio test against the second ``d1`` (float32, compared in double
    precision, as the distances of cv2.DMatch compare in Python)."""
    keep = np.flatnonzero(d0.astype(np.float64) < ratio * d1.astype(np.float64))
    return dict(zip(keep.tolist(), best[keep].tolist(), strict=True))


def guided_matches(
    f1: FrameFeatures,
    f2: FrameFeatures,
    feature: np.ndarray,
    predicted_rays: np.ndarray,
    radius_rad: float,
    ratio: float = 0.8,
    most: int = 8,
) -> np.ndarray:
    """(M, 2) index pairs of descriptor matches searched only near a prediction.

    Each of ``f1``'s features ``feature`` (P,) is expected in ``f2``'s frame along
    ``predicted_rays`` (P, 3) unit rays (e.g. where its track went); only ``f2``'s
    features within ``radius_rad`` of that ray (at most ``most``, nearest first) are
    compared. Choose the radius under half the wall's texture period: a periodic wall
    then offers one candidate of each kind, where a global ratio test finds every
    period alike and matches none (or the wrong one). The nearest descriptor wins when
    it passes Lowe's ratio test against the next candidate of the window (alone in the
    window: it passes); an ``f2`` feature claimed twice goes to the closer descriptor.
    Features without a descriptor (zero rows) match nothing.
    """
    d2_ok = np.zeros(len(f2.view), bool)
    d2_ok[_described(f2.descriptors)] = True
    feature = np.asarray(feature, int)
    if len(feature) == 0 or not d2_ok.any():
        return np.zeros((0, 2), int)
    keep = np.isin(feature, _described(f1.descriptors))
    feature, predicted_rays = feature[keep], np.asarray(predicted_rays, float)[keep]
    described = np.flatnonzero(d2_ok)
    k = min(most, len(described))
    dist, nn = cKDTree(f2.rays_in_rig[described]).query(predicted_rays, k=k, distance_upper_bound=2.0 * math.sin(0.5 * radius_rad))
    dist, nn = dist.reshape(len(feature), k), nn.reshape(len(feature), k)
    found = np.isfinite(dist)
    cand = described[np.where(found, nn, 0)]
    desc = np.linalg.norm(f2.descriptors[cand] - f1.descriptors[feature][:, None, :], axis=2)
    desc[~found] = np.inf
    order = np.argsort(desc, axis=1)
    rows = np.arange(len(feature))
    best = desc[rows, order[:, 0]]
    second = desc[rows, order[:, 1]] if k > 1 else np.full(len(feature), np.inf)
    ok = np.isfinite(best) & (best < ratio * second)
    i1, i2, d = feature[ok], cand[rows, order[:, 0]][ok], best[ok]
    # One f1 feature per f2 feature: the closest descriptor.
    by = np.lexsort((d, i2))
    first = np.ones(len(by), bool)
    first[1:] = i2[by][1:] != i2[by][:-1]
    sel = by[first]
    return np.stack([i1[sel], i2[sel]], axis=1)


def _described(descriptors: np.ndarray) -> np.ndarray:
    """Indices of the (N, 128) ``descriptors`` rows that are not all zero."""
    if len(descriptors) == 0:
        return np.zeros(0, int)
    return np.flatnonzero(np.any(descriptors != 0, axis=1))


def track_labels(offset: np.ndarray, pair_matches: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    """Multi-view tracks from pairwise matches: the connected components of the graph
    whose nodes are the features of all frames and whose edges are the matches.

    Args:
        offset: (K + 1,) where each frame's features start in the concatenation of all
            frames' features (``offset[-1]``: their number F).
        pair_matches: (a, b, (M, 2) (feature in a, feature in b) index pairs).

    Returns:
        (F,) each feature's track label; the labels are numbered in the order of each
        track's first feature (a feature matched to nothing has a label of its own).
    """
    n = int(offset[-1])
    if n == 0:
        return np.zeros(0, int)
    rows = [offset[a] + m[:, 0] for a, _, m in pair_matches]
    cols = [offset[b] + m[:, 1] for _, b, m in pair_matches]
    i = np.concatenate(rows).astype(int) if rows else np.zeros(0, int)
    j = np.concatenate(cols).astype(int) if cols else np.zeros(0, int)
    graph = coo_matrix((np.ones(len(i), np.int8), (i, j)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return labels.astype(int)


def two_nearest(query: np.ndarray, train: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each query descriptor's nearest train descriptor and the two smallest L2 distances.

    OpenCV's SIFT descriptors are whole numbers in 0..255 stored as float32: their
    squared distances ``|q|^2 + |t|^2 - 2 q.t`` are then whole numbers below 2^24, which
    float32 holds exactly whatever the order of the sums, so one matrix product (BLAS)
    and a compiled pass for the two smallest give the distances of a brute-force search
    (``cv2.BFMatcher(NORM_L2).knnMatch(k=2)``) to the bit, 3x faster. Other descriptors
    go to that matcher. Ties between the two nearest give equal distances, which no
    ratio test passes, so which of them is called nearest does not matter.

    Args:
        query: (N, 128) float32; train: (M, 128) float32, M >= 2.

    Returns:
        (N,) index of the nearest, (N,) its distance and (N,) the second's, float32.
    """
    q = np.ascontiguousarray(query, np.float32)
    t = np.ascontiguousarray(train, np.float32)
    if not _whole_bytes(q, t):
        found = cv2.BFMatcher(cv2.NORM_L2).knnMatch(q, t, k=2)
        best = np.array([m[0].trainIdx for m in found], int)
        d0 = np.array([m[0].distance for m in found], np.float32)
        d1 = np.array([m[1].distance for m in found], np.float32)
        return best, d0, d1
    dot = q @ t.T
    best, d0sq, d1sq = _two_smallest(np.einsum("ij,ij->i", q, q), np.einsum("ij,ij->i", t, t), dot)
    return best, np.sqrt(d0sq), np.sqrt(d1sq)


def _whole_bytes(q: np.ndarray, t: np.ndarray) -> bool:
    """True when the float32 descriptors ``q`` and ``t`` (both non-empty) hold whole
    numbers in 0..255 only (:func:`two_nearest`'s exact path)."""
    return bool(
        q.size and t.size and float(q.min()) >= 0 and float(t.min()) >= 0
        and float(q.max()) <= 255 and float(t.max()) <= 255
        and np.array_equal(q, np.round(q)) and np.array_equal(t, np.round(t))
    )


@numba.njit(cache=True, nogil=True)
def _two_smallest(qq, tt, dot):  # pragma: no cover - compiled
    """Per row of ``qq[:, None] + tt[None, :] - 2 dot`` (float32): argmin, min, second min."""
    n, m = dot.shape
    best = np.empty(n, np.int64)
    d0 = np.empty(n, np.float32)
    d1 = np.empty(n, np.float32)
    two = np.float32(2.0)
    for i in range(n):
        b0 = np.float32(np.inf)
        b1 = np.float32(np.inf)
        k = 0
        for j in range(m):
            d = qq[i] + tt[j] - two * dot[i, j]
            if d < b0:
                b1 = b0
                b0 = d
                k = j
            elif d < b1:
                b1 = d
        best[i] = k
        d0[i] = max(b0, np.float32(0.0))
        d1[i] = max(b1, np.float32(0.0))
    return best, d0, d1

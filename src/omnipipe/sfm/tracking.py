"""Optical-flow tracking of a keyframe's features, frame to frame, into the frames after it.

A moving frame that is not a keyframe needs only two things from its image: how far the
rig moved since the last keyframe (the keyframe decision, :mod:`omnipipe.sfm.keyframes`)
and its rays to the keyframes' tracked points (its resection); the next keyframe needs
its correspondences with the last one. All come from the keyframe's features followed
by pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) on the same perspective views,
about a tenth of the cost of SIFT and descriptor matching on the frame.

:class:`TrackChain` follows them *from each moving frame into the next*, not from the
keyframe into a far frame: between consecutive frames the wall moves far less than
half the period of a periodic wall (bricks, tiles, corrugation), so a track cannot
jump a period, which neither a flow over many frames nor a descriptor's ratio test
can promise there. A track is kept only when the flow back returns to within
``max_forward_backward_px`` of where it started and it lands inside the frame's
feature mask (annulus, off the laser band); a lost track stays lost.

Where a wall has few SIFT keypoints (plain or low-contrast), the chain is seeded with
Shi-Tomasi corners too (:func:`corner_features`; no descriptors).

When too few of the keyframe's features are tracked (a blurred frame, a jump) the
caller falls back to descriptor matching.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from omnipipe.config import bounded
from omnipipe.errors import ConfigError, ShapeError
from omnipipe.executor import thread_map
from omnipipe.sfm.features import FeatureExtractor, FrameFeatures, FrameViews, concat_features
from omnipipe.sfm.flow_contrast import local_contrast
from omnipipe.sfm.flow_image import FINE_LEVELS, FlowImage, highpass


@dataclass(frozen=True)
class TrackConfig:
    """Lucas-Kanade tracking between keyframes.

    Attributes:
        enabled: track the keyframe's features into the frames after it (False: SIFT
            on every moving frame).
        window_px: side of the square flow window (view px, odd).
        levels: pyramid levels above the view's own resolution.
        max_forward_backward_px: largest distance between a keypoint and where its
            track, followed back, ends (view px).
        highpass_px: the flow's two finest pyramid levels are refined on views
            high-passed at this Gaussian sigma (view px; 0: on the views as they are),
            :func:`flow_images`.
        min_tracks: a frame where fewer of the keyframe's tracks are left than this is
            matched by SIFT descriptors instead (its tracks lost: blur, a jump).
        max_points: at most this many of the keyframe's features are followed (the
            flow's cost is proportional to their number).
        spread_px: the keyframe's features followed within ``max_points`` are spread
            over its views: the first feature in each square of this side (view px),
            then the second, and so on (:func:`spread_order`); 0: evenly over the list.
        guided_radius_px: at a keyframe, SIFT features are matched only within this
            distance of where their tracks went (view px; under half a periodic wall's
            texture period).
        chain_over_descriptors: a keyframe step's correspondences are the chained
            tracks when their RANSAC inliers are more than this many times the best
            descriptor matches' (global or guided); else those descriptor matches.
        min_corner_points: when a keyframe has fewer SIFT features than this, Shi-Tomasi
            corners are added up to it (0: never).
        corner_quality: Shi-Tomasi quality level (fraction of the view's best corner).
        min_corner_distance_px: corners keep this far from each other and from the
            keyframe's features (view px).
        renew_ratio: a frame whose RANSAC-verified tracks fell below this share of the
            last keyframe step's inliers becomes a keyframe once its rays turned half
            ``keyframe_min_parallax_deg``: the tracks are running out (large image motion
            between frames; random-wide seed 17, 11 mm frame steps in a 123 mm pipe:
            511 -> 80 -> 36 -> 16 verified tracks in three frames, the step lost). 0: off.
        back_below: a pending frame (between keyframes) is also given the next
            keyframe's new features, followed back to it frame by frame, when it has
            fewer verified tracks of its own keyframe than this (it is then resected
            from both sides; the frames after it back to the next keyframe are followed
            through on the way); 0: never by count, a large number (the default): always
            (why always: benchmarks/RESULTS.md).
        back_beyond: ... or when its rays turned at least this share of the next
            keyframe's parallax from its own keyframe (the far part of a long step,
            where its own keyframe's tracks alone let it drift; robustness seed 1, a
            31-frame step); 0: every pending frame.
        retry_lost_share: the tracks the first flow lost in a view get the second try
            (coarse levels high-passed, :func:`_flow`) only when they are at least this
            share of the view's tracks (0: always, the default in small views, where
            a looser rule let a step go wrong: benchmarks/RESULTS.md).
        retry_large_side_px: views whose shorter side is at least this (view px) take
            ``retry_lost_share_large`` instead of ``retry_lost_share`` (0: never).
        retry_lost_share_large: ``retry_lost_share`` of such large views.
        max_points_large: ``max_points`` in such large views (:func:`sized_for_views`:
            the run's config takes it before any track is followed). 1600x1200's views
            cost the flow most per frame and hold the most keypoints; the accuracy with
            the smaller number is in benchmarks/RESULTS.md (cpu28's entry). Other-rig's
            and 640x480's views keep ``max_points``, where fewer tracks moved the
            robustness bench's steps (cpu19's entry).
        back_below_large: ``back_below`` in such large views (:func:`sized_for_views`):
            their pending frames keep hundreds of verified tracks of their own keyframe,
            so only those short of tracks or in the far part of the step
            (``back_beyond``) are followed back (continuous and bend: the same accuracy
            for less CPU, benchmarks/RESULTS.md, cpu29's entry). Smaller views keep
            ``back_below``: the robustness bench's 640x480 runs lost by 200 (seeds 20
            and 37).
    """

    enabled: bool = True
    window_px: int = bounded(21, ge=5)
    levels: int = bounded(3, ge=0)
    max_forward_backward_px: float = bounded(0.5, gt=0)
    highpass_px: float = bounded(8.0, ge=0)
    min_tracks: int = bounded(40, ge=8)
    max_points: int = bounded(1000, ge=8)
    spread_px: float = bounded(0.0, ge=0)
    guided_radius_px: float = bounded(3.0, gt=0)
    chain_over_descriptors: float = bounded(2.0, ge=1)
    min_corner_points: int = bounded(400, ge=0)
    corner_quality: float = bounded(0.01, gt=0, lt=1)
    min_corner_distance_px: float = bounded(5.0, gt=0)
    renew_ratio: float = bounded(0.3, ge=0, le=1)
    back_below: int = bounded(1_000_000, ge=0)
    back_beyond: float = bounded(0.5, ge=0, le=1)
    retry_lost_share: float = bounded(0.0, ge=0, le=1)
    retry_large_side_px: int = bounded(300, ge=0)
    retry_lost_share_large: float = bounded(0.1, ge=0, le=1)
    max_points_large: int = bounded(600, ge=8)
    back_below_large: int = bounded(200, ge=0)

    def __post_init__(self) -> None:
        if self.window_px < 5 or self.window_px % 2 == 0:
            raise ConfigError("sfm.tracking.window_px", f"must be an odd number >= 5, got {self.window_px}")


@dataclass
class Tracks:
    """A keyframe's features found again in a later (or earlier) frame.

    Attributes:
        feature: (M,) index of each tracked keyframe feature.
        features: the tracks as the frame's features: (M, 3) unit rays in the frame's
            rig, (M, 2) omni pixels, no descriptors, the view and view pixels.
    """

    feature: np.ndarray
    features: FrameFeatures

    @property
    def matches(self) -> np.ndarray:
        """(M, 2) (keyframe feature, frame feature) index pairs."""
        return np.stack([self.feature, np.arange(len(self.feature))], axis=1)


# The second try's coarse levels are high-passed at this many times ``highpass_px``
# (:func:`flow_images`): at 1 they lock the tracks they alone hold 25-80 px off on a
# wall whose coarse structure is texture (other-rig); at 4 the near-field tracks of a
# dim concrete wall two 6-9 mm frame steps on are held (random-wide seed 31).
COARSE_HIGHPASS_FACTOR = 4.0


def _followed(n: int, config: TrackConfig) -> np.ndarray:
    """The indices of ``n`` features that are followed (at most ``config.max_points``,
    evenly over the list)."""
    return np.unique(np.linspace(0, n - 1, min(n, config.max_points)).round().astype(int))


def spread_order(view: np.ndarray, view_pixels: np.ndarray, cell_px: float) -> np.ndarray:
    """(N,) the order in which features (``view`` (N,), ``view_pixels`` (N, 2) view px)
    fill a budget: by their rank among the features before them in the list that fall
    in the same ``cell_px`` square of the same view, then by their place in the list
    (the first feature of every square, then the second, ...)."""
    if len(view) == 0:
        return np.zeros(0, int)
    cell = np.floor(np.asarray(view_pixels, float) / cell_px).astype(np.int64)
    _, square = np.unique(np.column_stack([np.asarray(view, np.int64), cell]), axis=0, return_inverse=True)
    square = square.ravel()
    by_square = np.argsort(square, kind="stable")  # list order within a square
    first = np.ones(len(by_square), bool)
    first[1:] = square[by_square][1:] != square[by_square][:-1]
    starts = np.maximum.accumulate(np.where(first, np.arange(len(by_square)), 0))
    rank = np.empty(len(by_square), np.int64)
    rank[by_square] = np.arange(len(by_square)) - starts
    return np.lexsort((np.arange(len(view)), rank))


def _lk(
    a: np.ndarray, b: np.ndarray, q0: np.ndarray, start: np.ndarray | None, levels: int, config: TrackConfig
) -> tuple[np.ndarray, np.ndarray]:
    """One pyramidal Lucas-Kanade of (M, 1, 2) float32 ``q0`` from ``a`` into ``b`` over
    ``levels`` pyramid levels, from ``start`` (M, 1, 2) when given: positions and (M,)
    status.

    OpenCV's third output is asked for as the window's smallest eigenvalue
    (``OPTFLOW_LK_GET_MIN_EIGENVALS``, computed anyway) rather than the window's mean
    difference, which nobody reads and which costs one more pass over every window at
    the finest level (~10 % of the flow). That pass also fails a track whose window
    ends more than a window outside ``b``: the same test is made here, so positions
    and status are OpenCV's without the flag, bit for bit."""
    win = (config.window_px, config.window_px)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    flags = (0 if start is None else cv2.OPTFLOW_USE_INITIAL_FLOW) | cv2.OPTFLOW_LK_GET_MIN_EIGENVALS
    nxt = None if start is None else start.copy()
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, q0, nxt, winSize=win, maxLevel=levels, criteria=criteria, flags=flags)
    corner = np.floor(p1.reshape(-1, 2) - np.float32(0.5 * (config.window_px - 1)))
    height, width = b.shape[:2]
    inside = (corner[:, 0] >= -config.window_px) & (corner[:, 0] < width)
    inside &= (corner[:, 1] >= -config.window_px) & (corner[:, 1] < height)
    return p1, (st.ravel() == 1) & inside


def _coarse_fine(
    a: FlowImage,
    b: FlowImage,
    q0: np.ndarray,
    start: np.ndarray,
    config: TrackConfig,
    coarse_highpassed: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """``q0`` (M, 1, 2) from ``a`` into ``b`` over ``config.levels`` pyramid levels above
    the views', from the predicted positions ``start`` (M, 1, 2): with high-passed views,
    the levels above the two finest on the views as they are (:attr:`FlowImage.coarse`;
    with ``coarse_highpassed`` on the views high-passed at a coarser scale,
    :attr:`FlowImage.coarse_band`), then the two finest on the high-passed ones
    from there (as many levels in all as one pyramid). Positions (M, 1, 2) and (M,)
    status."""
    if a.highpassed is None or b.highpassed is None:
        return _lk(a.raw, b.raw, q0, start, config.levels, config)
    if a.coarse is None or b.coarse is None:
        return _lk(a.highpassed, b.highpassed, q0, start, config.levels, config)
    f = float(1 << FINE_LEVELS)
    ca, cb = (a.coarse_band, b.coarse_band) if coarse_highpassed else (a.coarse, b.coarse)
    p1, ok = _lk(ca, cb, q0 / f, start / f, config.levels - FINE_LEVELS, config)
    p1, fine = _lk(a.highpassed, b.highpassed, q0, p1 * f, FINE_LEVELS - 1, config)
    return p1, ok & fine


def _flow(
    a: FlowImage,
    b: FlowImage,
    p0: np.ndarray,
    mask: np.ndarray,
    config: TrackConfig,
    shift: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Lucas-Kanade of (M, 2) view pixels ``p0`` from view image ``a`` into ``b`` (same
    view; :func:`_coarse_fine`), started from ``p0 + shift`` ((M, 2) predicted motion,
    view px; None: none) and forward-backward checked (back from the forward result,
    started from it minus ``shift``): (M, 2) float32 positions in ``b`` and (M,) True
    where the track holds and lands where ``mask`` (of ``b``) is set.

    The tracks the first flow lost are tried again with the coarse levels high-passed
    too (:attr:`FlowImage.coarse_band`): on a dim, fine-grained wall the coarse
    levels of the views as they are hold little but the rig's own light, which moves
    with the rig, and lose every track whose frame step the window cannot span
    (random-wide seed 31, concrete in a 108 mm pipe, 6-9 mm frame steps: 116 of 1094
    features tracked two frames on, 355 with the second try, all but 4 % consistent
    with the true motion); where the coarse structure carries the motion (``other-rig``,
    28 px a frame) the first try holds the track."""
    q0 = np.ascontiguousarray(p0, np.float32).reshape(-1, 1, 2)
    v = np.zeros_like(q0) if shift is None else np.ascontiguousarray(shift, np.float32).reshape(-1, 1, 2)
    p1, ok = _checked_flow(a, b, q0, v, config)
    retry = np.flatnonzero(~ok)
    share = _retry_share(mask.shape, config)
    if len(retry) and len(retry) >= share * len(ok) and a.band_px > 0 and b.band_px > 0 and a.coarse is not None and b.coarse is not None:
        p2, ok2 = _checked_flow(a, b, q0[retry], v[retry], config, coarse_highpassed=True)
        p1[retry[ok2]] = p2[ok2]
        ok[retry[ok2]] = True
    col, row = np.round(p1[:, 0]), np.round(p1[:, 1])
    height, width = mask.shape
    ok &= (col >= 0) & (row >= 0) & (col <= width - 1) & (row <= height - 1)
    inside = np.zeros(len(p1), bool)
    inside[ok] = mask[row[ok].astype(int), col[ok].astype(int)] > 0
    return p1, ok & inside


def is_large_view(config: TrackConfig, shape: tuple[int, ...]) -> bool:
    """True for views of ``shape`` (height, width) px whose shorter side reaches
    ``config.retry_large_side_px`` (> 0)."""
    return config.retry_large_side_px > 0 and min(shape[:2]) >= config.retry_large_side_px


def sized_for_views(config: TrackConfig, shape: tuple[int, ...]) -> TrackConfig:
    """``config`` for views of ``shape`` (height, width) px: with ``max_points_large`` as
    ``max_points`` and ``back_below_large`` as ``back_below`` in large views
    (:func:`is_large_view`), else as it is."""
    if is_large_view(config, shape):
        return replace(config, max_points=config.max_points_large, back_below=config.back_below_large)
    return config


def _retry_share(shape: tuple[int, ...], config: TrackConfig) -> float:
    """The share of a view's tracks the first flow must lose for the second try
    (:func:`_flow`): ``config.retry_lost_share_large`` in a view of ``shape`` (height,
    width) px whose shorter side is at least ``config.retry_large_side_px`` (> 0), else
    ``config.retry_lost_share``."""
    return config.retry_lost_share_large if is_large_view(config, shape) else config.retry_lost_share


def _checked_flow(
    a: FlowImage,
    b: FlowImage,
    q0: np.ndarray,
    v: np.ndarray,
    config: TrackConfig,
    coarse_highpassed: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """(M, 1, 2) ``q0`` from ``a`` into ``b`` started at ``q0 + v`` and back from there
    (started at the result minus ``v``; :func:`_coarse_fine`): (M, 2) positions in ``b``
    and (M,) True where both flows hold and the way back ends within
    ``config.max_forward_backward_px`` of ``q0``."""
    p1, ok = _coarse_fine(a, b, q0, q0 + v, config, coarse_highpassed)
    back, ok2 = _coarse_fine(b, a, p1, p1 - v, config, coarse_highpassed)
    ok &= ok2 & (np.linalg.norm((back - q0).reshape(-1, 2), axis=1) <= config.max_forward_backward_px)
    return p1.reshape(-1, 2), ok


def flow_images(views: FrameViews, sigma_px: float, levels: int = 3) -> list[FlowImage]:
    """The images the flow runs on: each view as it is and high-passed,
    ``2 (I - B * I) + 128`` (uint8), B two box filters of about a Gaussian of
    ``sigma_px`` (a tenth of the cost of the Gaussian itself at this width).

    The rig's own lighting falls off across the wall and moves with the rig: on a weakly
    textured wall (brick faces at low resolution) it holds Lucas-Kanade back to a
    fraction of the true flow (brick-bend-small, 12.7 mm: 3.4 px median error against
    the true correspondences, 1.0 px high-passed; tiled walls unchanged at 0.11 px), so
    the finest levels are refined high-passed. A high-passed view has no coarse levels
    left, though, and the pyramid's top levels are what finds a displacement larger
    than the window: ``other-rig`` (28 px per frame) kept 15 % of the tracks, a quarter
    of them 40 px wrong, on high-passed views alone, so the coarse levels read the
    views as they are, reduced (``levels``: the pyramid's levels above the view's;
    :func:`_coarse_fine`). The tracks they lose get a second try on coarse levels
    high-passed at :data:`COARSE_HIGHPASS_FACTOR` times ``sigma_px``
    (:attr:`FlowImage.coarse_band`, :func:`_flow`). Where the views kept their images
    before CLAHE (``views.plain``, ``sfm.features.flow_plain``, off by default) the fine
    levels, which place each track, read those images' local contrast
    (:func:`~omnipipe.sfm.flow_contrast.local_contrast`: log, the same high-pass,
    divided by its local spread) instead: CLAHE's gains, fixed in the view like the
    rig's light, held a broad pattern's tracks back (a corrugated wall: every keyframe
    step's tracks 5 % short, their depths 5 % deep)."""
    if sigma_px <= 0:
        return [FlowImage(im, None) for im in views.images]
    out = []
    for k, im in enumerate(views.images):
        coarse = None
        if levels >= FINE_LEVELS:
            coarse = im
            for _ in range(FINE_LEVELS):
                coarse = cv2.pyrDown(coarse)
        fine = highpass(im, sigma_px) if views.plain is None else local_contrast(views.plain[k], sigma_px)
        out.append(FlowImage(im, fine, coarse, COARSE_HIGHPASS_FACTOR * sigma_px))
    return out


def _as_tracks(
    extractor: FeatureExtractor, feature: np.ndarray, view: np.ndarray, view_pixels: np.ndarray
) -> Tracks:
    """Tracks of keyframe features ``feature`` (M,) at ``view_pixels`` (M, 2) of views
    ``view`` (M,): their rays and omni pixels through the views and the camera."""
    if len(view) == 0:
        return Tracks(np.zeros(0, int), FrameFeatures.empty())
    rays = np.empty((len(view), 3))
    for k in np.unique(view):
        sel = view == k
        rays[sel] = extractor.views[k].rays(view_pixels[sel].astype(float))
    pixels, _ = extractor.camera.project(rays)
    vpx = np.ascontiguousarray(view_pixels, np.float32)
    return Tracks(feature, FrameFeatures(rays, pixels, np.zeros((0, 128), np.float32), view, vpx))


def track_features(
    extractor: FeatureExtractor,
    key_views: FrameViews,
    key_features: FrameFeatures,
    views: FrameViews,
    config: TrackConfig,
) -> Tracks:
    """Follow ``key_features`` (with their ``view_pixels``; at most ``config.max_points``
    of them, evenly over the list) from ``key_views`` straight into ``views`` of another
    frame of the same camera (one flow, however far the frames are apart).

    Raises:
        ShapeError: ``key_features`` without view pixels.
    """
    if key_features.view_pixels is None:
        raise ShapeError("key_features.view_pixels: missing (features from FeatureExtractor.detect have them)")
    followed = _followed(len(key_features.view), config)
    chain = TrackChain(extractor, key_views, key_features, config, followed)
    return chain.advance(views)


class TrackChain:
    """A keyframe's features followed from frame to frame (:func:`_flow` between each
    pair of consecutive frames' views); the tracks lost on the way stay lost.

    ``followed``: the indices of the keyframe features to follow (default: at most
    ``config.max_points``, evenly over the list). ``key_images``: :func:`flow_images`
    of ``key_views`` when the caller has them already (the same arrays it would make).

    Each flow starts where the track's last step would take it again (constant
    velocity; ``prior``: the chain of the keyframe before, advanced into this
    keyframe's frame, lends each new track the last step of its nearest track in the
    same view, and its flow images of ``key_views`` when it ended there). The robot's gait changes speed smoothly, so the flow only has to find
    the change of the step: a periodic wall (mosaic tiles, 11.8 mm) whose frame steps
    reach 8.4 mm, more than half its period, no longer pulls a track a period back
    (random-wide seed 22).

    Raises:
        ShapeError: ``key_features`` without view pixels.
    """

    def __init__(
        self,
        extractor: FeatureExtractor,
        key_views: FrameViews,
        key_features: FrameFeatures,
        config: TrackConfig,
        followed: np.ndarray | None = None,
        prior: TrackChain | None = None,
        key_images: list[FlowImage] | None = None,
    ) -> None:
        if key_features.view_pixels is None:
            raise ShapeError("key_features.view_pixels: missing (features from FeatureExtractor.detect have them)")
        self.extractor = extractor
        self.config = config
        sel = _followed(len(key_features.view), config) if followed is None else np.asarray(followed, int)
        self.n_followed = len(sel)
        self.feature = sel
        self.view = np.asarray(key_features.view, int)[sel]
        self.view_pixels = np.asarray(key_features.view_pixels, np.float32)[sel].reshape(-1, 2)
        if prior is not None and prior.views is key_views and prior.config == config:
            self.images = prior.images  # the prior chain advanced into these views
        elif key_images is not None:
            self.images = key_images
        else:
            self.images = flow_images(key_views, config.highpass_px, config.levels)
        self.views = key_views  # the views the next flow starts from
        # Each track's last step (view px), where the next flow starts from.
        self.step = np.zeros_like(self.view_pixels)
        if prior is not None:
            self.step = _inherited_steps(prior, self.view, self.view_pixels)

    def advance(self, views: FrameViews, images: list[FlowImage] | None = None) -> Tracks:
        """The tracks followed on into ``views`` (the next frame's), which become the
        frame the next call starts from; ``images``: their :func:`flow_images` when the
        caller has them already (None: made here)."""
        if images is None:
            images = flow_images(views, self.config.highpass_px, self.config.levels)
        keep = np.zeros(len(self.feature), bool)
        moved = self.view_pixels.copy()
        ks = np.unique(self.view)
        sels = [np.flatnonzero(self.view == k) for k in ks]
        flows = thread_map(  # the views on the extractor's threads
            lambda k, sel: _flow(
                self.images[k], images[k], self.view_pixels[sel], views.masks[k], self.config, self.step[sel]
            ),
            ks, sels, threads=self.extractor.threads,
        )
        for sel, (p1, ok) in zip(sels, flows, strict=True):
            moved[sel] = p1
            keep[sel] = ok
        step = moved - self.view_pixels
        self.feature, self.view, self.view_pixels = self.feature[keep], self.view[keep], moved[keep]
        self.step = step[keep]
        self.images, self.views = images, views
        return _as_tracks(self.extractor, self.feature, self.view, self.view_pixels)


def _inherited_steps(prior: TrackChain, view: np.ndarray, view_pixels: np.ndarray) -> np.ndarray:
    """(M, 2) the last step of ``prior``'s nearest track in the same view for each of
    (M,) ``view``, (M, 2) ``view_pixels`` (zero where ``prior`` has none there)."""
    step = np.zeros_like(view_pixels)
    for k in np.unique(view):
        have = np.flatnonzero(prior.view == k)
        if len(have) == 0:
            continue
        sel = np.flatnonzero(view == k)
        _, nearest = cKDTree(prior.view_pixels[have]).query(view_pixels[sel])
        step[sel] = prior.step[have[nearest]]
    return step


def keyframe_detection(extractor: FeatureExtractor, views: FrameViews, config: TrackConfig) -> FrameFeatures:
    """A keyframe's own features on its ``views``: SIFT (``extractor.detect``), then,
    with ``config.enabled``, Shi-Tomasi corners where SIFT found few
    (:func:`corner_features`)."""
    features = extractor.detect(views)
    if config.enabled:
        corners = corner_features(extractor, views, features, config)
        if len(corners.view):
            features = concat_features([features, corners])
    return features


def corner_features(
    extractor: FeatureExtractor, views: FrameViews, taken: FrameFeatures, config: TrackConfig
) -> FrameFeatures:
    """Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) of one frame's views, as
    features without descriptors (zero rows): as many as bring ``taken`` (the frame's
    other features) up to ``config.min_corner_points``, spread over the views, each at
    least ``config.min_corner_distance_px`` from the others and from ``taken``'s."""
    missing = config.min_corner_points - len(taken.view)
    if missing <= 0 or taken.view_pixels is None:
        return FrameFeatures.empty()
    per_view = int(np.ceil(missing / len(extractor.views)))
    r = config.min_corner_distance_px
    vidx, vpx = [], []
    for k, (img, vmask) in enumerate(zip(views.images, views.masks, strict=True)):
        mask = vmask.copy()
        for x, y in taken.view_pixels[taken.view == k]:
            cv2.circle(mask, (int(round(float(x))), int(round(float(y)))), int(np.ceil(r)), 0, -1)
        pts = cv2.goodFeaturesToTrack(img, per_view, config.corner_quality, r, mask=mask, blockSize=5)
        if pts is None:
            continue
        vpx.append(pts.reshape(-1, 2).astype(np.float32))
        vidx.append(np.full(len(vpx[-1]), k))
    if not vpx:
        return FrameFeatures.empty()
    view = np.concatenate(vidx)
    tracks = _as_tracks(extractor, np.arange(len(view)), view, np.concatenate(vpx))
    f = tracks.features
    return FrameFeatures(f.rays_in_rig, f.pixels, np.zeros((len(f.view), 128), np.float32), f.view, f.view_pixels)

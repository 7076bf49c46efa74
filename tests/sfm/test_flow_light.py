"""The tracker's flow under the rig's own light: a smooth wall pattern (corrugation) lit by
a light that moves with the rig must be followed at its true shift, not held back."""

from dataclasses import replace

import cv2
import numpy as np

from omnipipe.sfm.features import FeatureConfig, FeatureExtractor, FrameViews
from omnipipe.sfm.tasks import camera_from_rig
from omnipipe.sfm.tracking import TrackConfig, _flow, flow_images
from omnipipe.sim import make_scenario

H, W = 189, 131  # a 640x480 rig's perspective view (px)
PERIOD_PX = 50.0  # the corrugation's period along the view's rows
SHIFT_PX = 3.0  # the wall's true shift between the frames (rows)


def _views(shift: float, grain: np.ndarray) -> FrameViews:
    """One view of a corrugated wall moved ``shift`` rows: albedo (a cosine along the rows
    and a faint grain) times a light fixed in the view that falls off as 1 / range^2;
    ``images`` CLAHE'd as FeatureExtractor.frame_views does, ``plain`` as rendered."""
    rows = np.arange(H + 40, dtype=np.float32)
    mx, my = np.meshgrid(np.arange(W, dtype=np.float32), rows - shift)
    moved = cv2.remap(grain, mx, my, cv2.INTER_CUBIC)
    wave = 1.0 + 0.35 * np.cos(2.0 * np.pi * (rows[:, None] - shift) / PERIOD_PX)
    albedo = (wave * (1.0 + 0.03 * moved))[20 : 20 + H]
    light = (40.0 / (np.arange(H, dtype=np.float32)[:, None] + 40.0)) ** 2
    plain = np.clip(250.0 * albedo * light / 1.35, 0, 255).astype(np.uint8)
    clahe = cv2.createCLAHE(clipLimit=3.0, tileGridSize=(8, 8))
    return FrameViews([clahe.apply(plain)], [np.full((H, W), 255, np.uint8)], [plain])


def _row_errors(views_a: FrameViews, views_b: FrameViews, plain: bool) -> np.ndarray:
    """(M,) tracked row shift minus the true one (px) of corners inside the view, the
    finest levels on the views before CLAHE (``plain``) or after."""
    cfg = TrackConfig(highpass_px=4.0)
    if not plain:
        views_a, views_b = replace(views_a, plain=None), replace(views_b, plain=None)
    pts = cv2.goodFeaturesToTrack(views_a.images[0], 200, 0.01, 5).reshape(-1, 2)
    inside = (pts[:, 1] > 20) & (pts[:, 1] < H - 20) & (pts[:, 0] > 12) & (pts[:, 0] < W - 12)
    pts = pts[inside]
    a = flow_images(views_a, cfg.highpass_px, cfg.levels)[0]
    b = flow_images(views_b, cfg.highpass_px, cfg.levels)[0]
    p1, ok = _flow(a, b, pts, views_b.masks[0], cfg)
    assert ok.sum() >= 0.5 * len(pts)
    return p1[ok, 1] - pts[ok, 1] - SHIFT_PX


def test_flow_follows_the_wall_not_the_rigs_light() -> None:
    grain = cv2.GaussianBlur(np.random.default_rng(3).normal(size=(H + 40, W)).astype(np.float32), (0, 0), 2.0)
    grain /= grain.std()
    va, vb = _views(0.0, grain), _views(SHIFT_PX, grain)
    # The finest levels on the views before CLAHE: within 0.1 px of the true shift.
    assert abs(float(np.median(_row_errors(va, vb, plain=True)))) < 0.1
    # On the CLAHE'd views (tiles fixed in the view) the same tracks lag behind.
    assert float(np.median(_row_errors(va, vb, plain=False))) < -0.2


def test_views_keep_their_plain_images_only_when_asked() -> None:
    rig = make_scenario("paper-small", frames=2, seed=0).rig
    image = np.random.default_rng(5).integers(0, 255, (rig.camera.height, rig.camera.width, 3), np.uint8)
    for flow_plain in (False, True):
        extractor = FeatureExtractor(camera_from_rig(rig), FeatureConfig(flow_plain=flow_plain))
        views = extractor.frame_views(image, rig.laser.channel)
        assert (views.plain is not None) == flow_plain
        if flow_plain:  # the same remapped view, before CLAHE
            assert all(p.shape == v.shape for p, v in zip(views.plain, views.images, strict=True))
            assert all(np.array_equal(extractor.clahe.apply(p), v) for p, v in zip(views.plain, views.images, strict=True))

"""The tracker's flow under the rig's own light and CLAHE: a broad wall pattern (corrugation,
blotches) lit by a light that moves with the rig must be followed at its true shift, not
held back."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from omnipipe import laser, sfm
from omnipipe.dataset import open_dataset
from omnipipe.errors import ShapeError
from omnipipe.pipeline import ReconstructConfig
from omnipipe.sfm.features import FeatureConfig, FeatureExtractor, FrameViews
from omnipipe.sfm.flow_contrast import TEXTURE_FLOOR, local_contrast, wall_texture
from omnipipe.sfm.pipeline import _flow_views
from omnipipe.sfm.tasks import camera_from_rig
from omnipipe.sfm.tracking import TrackConfig, _flow, flow_images
from omnipipe.sim import TextureConfig, make_scenario
from omnipipe.sim import run as simulate

H, W = 189, 131  # a 640x480 rig's perspective view (px)
PERIOD_PX = 50.0  # the corrugation's period along the view's rows
SHIFT_PX = 6.0  # the wall's true shift between the frames (rows)
PAD = 40


def _wall(rng: np.random.Generator, corrugation: float, blotches: float) -> np.ndarray:
    """(H + 2 PAD, W) float32 albedo of a broad-textured wall: a corrugation's cosine
    along the rows and blotches of about 8 px (relative amplitudes), a faint fine grain."""

    def blurred(sigma: float) -> np.ndarray:
        g = cv2.GaussianBlur(rng.normal(size=(H + 2 * PAD, W)).astype(np.float32), (0, 0), sigma)
        return g / g.std()

    rows = np.arange(H + 2 * PAD, dtype=np.float32)[:, None]
    wave = corrugation * np.cos(2.0 * np.pi * rows / PERIOD_PX)
    return (1.0 + wave + blotches * blurred(8.0) + 0.03 * blurred(1.5)).astype(np.float32)


def _views(albedo: np.ndarray, shift: float, brightness: float) -> FrameViews:
    """One view of ``albedo`` moved ``shift`` rows, lit by a light fixed in the view
    that falls off as 1 / range^2 (``brightness`` grey levels at the top row for albedo
    1); ``images`` CLAHE'd as FeatureExtractor.frame_views does, ``plain`` as rendered."""
    mx, my = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32) + PAD - shift)
    moved = cv2.remap(albedo, mx, my, cv2.INTER_CUBIC)
    light = (60.0 / (np.arange(H, dtype=np.float32)[:, None] + 60.0)) ** 2
    plain = np.clip(np.round(brightness * moved * light), 0, 255).astype(np.uint8)
    clahe = cv2.createCLAHE(clipLimit=3.0, tileGridSize=(8, 8))
    return FrameViews([clahe.apply(plain)], [np.full((H, W), 255, np.uint8)], [plain])


def _flow_ratio(views_a: FrameViews, views_b: FrameViews, plain: bool) -> tuple[float, float]:
    """Median tracked row shift over the true one of corners inside the view, and the
    share of them tracked: the finest levels on the views' local contrast (``plain``)
    or on the CLAHE'd views high-passed (the flow before the local contrast)."""
    cfg = TrackConfig()
    if not plain:
        views_a, views_b = replace(views_a, plain=None), replace(views_b, plain=None)
    pts = cv2.goodFeaturesToTrack(views_a.images[0], 200, 0.01, 5).reshape(-1, 2)
    inside = (pts[:, 1] > 15) & (pts[:, 1] < H - 15 - SHIFT_PX) & (pts[:, 0] > 12) & (pts[:, 0] < W - 12)
    pts = pts[inside]
    a = flow_images(views_a, cfg.highpass_px, cfg.levels)[0]
    b = flow_images(views_b, cfg.highpass_px, cfg.levels)[0]
    p1, ok = _flow(a, b, pts, views_b.masks[0], cfg)
    ratio = float(np.median(p1[ok, 1] - pts[ok, 1])) / SHIFT_PX if ok.any() else float("nan")
    return ratio, float(ok.mean())


@pytest.mark.parametrize(("corrugation", "blotches", "brightness"), [(0.35, 0.0, 160.0), (0.0, 0.3, 120.0)])
def test_flow_on_a_broad_textured_wall_is_its_true_shift(corrugation: float, blotches: float, brightness: float) -> None:
    new, old = [], []
    for seed in range(6):
        albedo = _wall(np.random.default_rng(seed), corrugation, blotches)
        va, vb = _views(albedo, 0.0, brightness), _views(albedo, SHIFT_PX, brightness)
        new.append(_flow_ratio(va, vb, plain=True))
        old.append(_flow_ratio(va, vb, plain=False))
    # The finest levels on the views' local contrast: every pair within 1 % of the
    # true shift, most corners tracked.
    assert all(abs(r - 1.0) < 0.01 and kept >= 0.6 for r, kept in new)
    # On the CLAHE'd views (tiles and light fixed in the view) the flow is off by more
    # than 3 % (short on the blotches, long on the corrugation) or lost.
    assert np.median([abs(r - 1.0) if kept >= 0.7 else 1.0 for r, kept in old]) > 0.03


def test_local_contrast_moves_with_the_image_and_drops_a_slow_gain() -> None:
    rng = np.random.default_rng(7)
    albedo = _wall(rng, 0.25, 0.2)[:H]
    image = np.clip(np.round(120.0 * albedo), 0, 255).astype(np.uint8)
    inner = (slice(70, H - 70), slice(None))  # beyond the filters' reach (~57 rows) of the wrapped rows
    # A whole-pixel shift of the image shifts the result.
    shifted = np.roll(image, 5, axis=0)
    moved = np.roll(local_contrast(image, 8.0), 5, axis=0)[inner].astype(int)
    assert np.abs(moved - local_contrast(shifted, 8.0)[inner]).max() <= 1  # float rounding
    # A gain falling by half across the view (a light fixed in it) hardly shows.
    ramp = np.linspace(1.0, 0.5, H, dtype=np.float32)[:, None]
    lit = np.clip(np.round(120.0 * albedo * ramp), 0, 255).astype(np.uint8)
    diff = np.abs(local_contrast(lit, 8.0).astype(int) - local_contrast(image, 8.0).astype(int))[inner]
    spread = local_contrast(image, 8.0)[inner].astype(float).std()
    assert np.median(diff) <= 0.1 * spread
    with pytest.raises(ShapeError):
        local_contrast(image.astype(np.float32), 8.0)


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


def test_wall_texture_tells_a_plain_wall_from_a_faint_pattern() -> None:
    """Under a light fixed in the view (falling to 0.4 across it) and the sensor's noise
    (1.5 grey levels), a plain wall (shading of 1 % over tens of px) measures below the
    texture floor, a faint corrugation (6 %) or faint blotches (5 %), each with a 3 %
    grain, above it: the run-level choice of the flow's images reads these numbers
    (random-wide at 640x480: plain walls 0.25-0.39, the faintest pattern 0.63)."""
    rows = np.arange(H, dtype=np.float32)[:, None]
    light = (150.0 / (rows + 150.0)) ** 2
    everywhere = [np.full((H, W), 255, np.uint8)]
    plain, textured = [], []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        noise = rng.normal(0.0, 1.5, (H, W)).astype(np.float32)
        shading = cv2.GaussianBlur(rng.normal(size=(H, W)).astype(np.float32), (0, 0), 25.0)
        flat = 1.0 + 0.01 * shading / shading.std()
        for albedo, out in ((flat, plain), (_wall(rng, 0.06, 0.0)[:H], textured), (_wall(rng, 0.0, 0.05)[:H], textured)):
            view = np.clip(np.round(140.0 * albedo * light + noise), 0, 255).astype(np.uint8)
            out.append(wall_texture([view], everywhere))
    assert max(plain) < 0.8 * TEXTURE_FLOOR and min(textured) > 1.2 * TEXTURE_FLOOR
    assert np.isnan(wall_texture([view], [np.zeros((H, W), np.uint8)]))  # no wall seen


@pytest.mark.parametrize(("texture", "local"), [(None, True), (TextureConfig(family="smooth", variant="pvc", contrast=0.15), False)])
def test_a_plain_wall_keeps_the_clahed_views_for_its_flow(tmp_path, texture, local: bool) -> None:
    """With ``features.flow_plain`` on, a run whose wall is plain (paper-small's rig,
    a pvc wall of contrast 0.15) keeps the CLAHE'd views for its flow; the paper's
    textured wall reads the local contrast; with it off nothing is measured."""
    sc = make_scenario("paper-small", frames=2, seed=1)
    if texture is not None:
        sc.texture = texture
    sc.sensors = replace(sc.sensors, odometry=False, imu=False)
    simulate(sc, tmp_path / "ds", workers=1)
    ds = open_dataset(tmp_path / "ds")
    cfg = ReconstructConfig.default()
    frames = [ds.read_frame(i) for i in range(len(ds))]
    inputs = sfm.SfmInputs.of_dataset(ds, laser.run(cfg.laser, ds.rig, iter(frames)))
    on = replace(cfg.sfm, features=replace(cfg.sfm.features, flow_plain=True))
    assert _flow_views(on, inputs).features.flow_plain == local
    off = replace(cfg.sfm, features=replace(cfg.sfm.features, flow_plain=False))
    assert _flow_views(off, replace(inputs, read_frame=None)) is off

"""The rig-fixed illumination from the keyframes (sfm.flat_field) and Eq. 17 with it."""

from __future__ import annotations

from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from omnipipe.camera import camera_from_rig
from omnipipe.executor import InlineExecutor
from omnipipe.sfm.adjust import _far_anchors
from omnipipe.sfm.flat_field import FlatWindow, flat_field, ring_band
from omnipipe.sfm.image_store import ImageStore, StoredImage
from omnipipe.sfm.laser_scale import match_laser_points
from omnipipe.sfm.step_decide import laser_around
from omnipipe.sfm.types import Keyframes, SfmConfig, SfmContext, StepEvidence
from omnipipe.sim import make_scenario

RADIUS_MM = 101.0  # the paper pipe's
LASER_Z_MM = -82.0  # its laser plane


@pytest.fixture(scope="module")
def wall_rig():
    """A straight 202 mm pipe seen through paper's mirror at 400x300 with the rig on its
    axis: each valid pixel's wall point (axial mm, angle rad), a seeded texture of
    sinusoids on the wall (weak: about +-10 % of the grey level), a strong rig-fixed
    fall-off (the LEDs' shading, halving every 14 px outwards, and 25 % around the
    mirror) and the laser's own light along the ring (additive, rig-fixed), with the
    laser ring's points and pixels."""
    camera = camera_from_rig(make_scenario("paper", frames=4, size=(400, 300), seed=1).rig)
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    px = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(float)
    valid = camera.valid_mask().ravel()
    rays = np.full((len(px), 3), np.nan)
    rays[valid] = camera.unproject(px[valid])
    t = RADIUS_MM / np.hypot(rays[:, 0], rays[:, 1])
    z, theta = t * rays[:, 2], np.arctan2(rays[:, 1], rays[:, 0])
    rng = np.random.default_rng(7)
    waves = [(rng.uniform(0.08, 0.4), int(rng.integers(5, 40)) * rng.choice([-1, 1]), rng.uniform(0, 2 * np.pi)) for _ in range(40)]
    ring_theta = np.linspace(-np.pi, np.pi, 240, endpoint=False)
    ring = np.stack([RADIUS_MM * np.cos(ring_theta), RADIUS_MM * np.sin(ring_theta), np.full(240, LASER_Z_MM)], axis=1)
    ring_px, _ = camera.project(ring)
    r = np.hypot(px[:, 0] - camera.cx, px[:, 1] - camera.cy)
    r_ring = float(np.median(np.hypot(ring_px[:, 0] - camera.cx, ring_px[:, 1] - camera.cy)))
    shading = np.exp2(-(r - r_ring) / 14.0) * (1.0 + 0.25 * np.cos(np.arctan2(px[:, 1] - camera.cy, px[:, 0] - camera.cx)))
    shading = np.where(valid, shading, 0.05).reshape(camera.height, camera.width)
    # The laser's own light in the grey image (crosstalk, blur): rig-fixed, additive.
    stripe = (0.2 * np.exp(-0.5 * ((r - r_ring) / 1.5) ** 2)).reshape(camera.height, camera.width)

    def texture(axial_mm: float) -> np.ndarray:
        """(H, W) the wall's texture (about 1 +- 0.06) with the rig at ``axial_mm``."""
        zz = z + axial_mm
        tex = sum(np.cos(f * zz + m * theta + p) for f, m, p in waves) / np.sqrt(2 * len(waves))
        return np.where(valid, 1.0 + 0.1 * np.nan_to_num(tex), 1.0).reshape(camera.height, camera.width)

    return camera, shading, texture, ring, ring_px, stripe


def _frames(wall_rig, positions_mm):
    _, shading, texture, _, _, stripe = wall_rig
    return [np.clip(np.round(120.0 * (shading * texture(s) + stripe)), 0, 255).astype(np.uint8) for s in positions_mm]


def test_flat_field_of_a_moving_wall_is_the_shading(wall_rig) -> None:
    """Sixteen keyframes 9 mm apart under the same shading: away from the laser's
    narrow light (which the smoothing spreads) and the band's edges, the field is the
    LEDs' shading over its median within 3 % at nine pixels in ten."""
    camera, shading, _, _, ring_px, _ = wall_rig
    window = FlatWindow(camera, 16)
    for frame in _frames(wall_rig, 9.0 * np.arange(16)):
        window.add_keyframe(frame, ring_px)
    got = window.current()
    assert got is not None
    radii = np.hypot(ring_px[:, 0] - camera.cx, ring_px[:, 1] - camera.cy)
    band = ring_band(camera, radii)
    assert np.allclose(got.field[~ndimage.binary_dilation(band, iterations=20)], 1.0, atol=1e-5)
    r = np.hypot(*(np.mgrid[0 : camera.height, 0 : camera.width][::-1] - np.array([camera.cx, camera.cy])[:, None, None]))
    inner = ndimage.binary_erosion(band & camera.valid_mask(), iterations=10) & (np.abs(r - np.median(radii)) > 6)
    inner &= shading > 0.3 * np.median(shading[band])
    ratio = got.field[inner] / shading[inner]
    rel = np.abs(ratio / np.median(ratio) - 1.0)
    assert inner.sum() > 1000
    assert np.quantile(rel, 0.9) < 0.03, np.quantile(rel, [0.5, 0.9])


def test_flat_fielded_eq17_finds_the_true_length(wall_rig) -> None:
    """With the fall-off and the laser's light strong beside the ring and the wall
    weakly textured, the templates follow what the rig casts, which does not move with
    the wall: the plain Eq. 17 runs about 10 % short. Divided by the keyframes' flat
    field, the lengths are within 5 % (the smoothing leaves some of the laser's narrow
    light), the error less than half the plain one's."""
    camera, _, _, ring, ring_px, _ = wall_rig
    positions = 9.0 * np.arange(16)
    frames = _frames(wall_rig, positions)
    window = FlatWindow(camera, 16)
    for frame in frames:
        window.add_keyframe(frame, ring_px)
    flat = window.current()
    plain, fielded = [], []
    for a in (2, 6, 10):
        b = a + 1
        length = positions[b] - positions[a]
        ga, gb = frames[a].astype(np.float32), frames[b].astype(np.float32)
        args = (camera, ring, np.eye(3), np.array([0.0, 0.0, -1.0]))
        plain.append(match_laser_points(ga, gb, *args).scale / length)
        m = match_laser_points(flat.apply(ga), flat.apply(gb), *args)
        assert len(m.index) > 60
        fielded.append(m.scale / length)
    assert np.median(plain) < 0.95, plain
    assert np.all(np.abs(np.array(fielded) - 1.0) < 0.05), fielded
    assert np.median(np.abs(np.array(fielded) - 1.0)) < 0.5 * np.median(np.abs(np.array(plain) - 1.0))


def test_steps_are_released_with_the_keyframes_around_them(wall_rig) -> None:
    """Step k's field is the median of the 8 keyframes before the first count n >= k +
    5 (and >= 8) that is even (the last 8 at the run's end), whenever its evidence was
    handed in: keyframe i is grey 100 with a patch of 100 + i on the ring, so the
    field there tells which were used. Every step is released once, in order, and its
    window holds both its keyframes."""
    camera, _, _, _, ring_px, _ = wall_rig
    window = FlatWindow(camera, 8)
    got: dict[int, float] = {}
    y, x = int(ring_px[0, 1]), int(ring_px[0, 0])

    def submitter(k):
        def submit(flat):
            got[k] = float(flat.field[y, x]) * 100.0 - 100.0  # the window's median index
            f: Future = Future()
            f.set_result(k)
            return f
        return submit

    handles, n = [], 20
    for i in range(n):
        frame = np.full((camera.height, camera.width), 100, np.uint16)
        frame[y - 10 : y + 11, x - 10 : x + 11] += i
        window.add_keyframe(frame, ring_px)
        if i >= 1:
            handles.append(window.submit(i - 1, submitter(i - 1))[0])
    window.finish()
    assert [h.result() for h in handles] == list(range(n - 1))
    for k, level in got.items():
        count = min(max(k + 5, 8) + max(k + 5, 8) % 2, n)
        assert level == pytest.approx(count - 8 + 3.5, abs=0.05), k
        assert count - 8 <= k and k + 1 < count
    assert flat_field(np.ones((7, 4, 4)), np.ones((4, 4), bool)) is None  # too few


def _run_of_keyframes(wall_rig, shares_files: bool, positions):
    """The 16 keyframes of ``_frames`` as a run's keyframes (rig moving along -z in its
    own frame), each step submitted to a :class:`FlatWindow` of 16 whose fields the
    run keeps; its grey images in an :class:`ImageStore` (closed by the caller)."""
    camera, _, _, ring, ring_px, _ = wall_rig
    frames = _frames(wall_rig, positions)
    grays = ImageStore()
    window = FlatWindow(camera, 16, shares_files)
    sent: dict[int, object] = {}

    def submitter(k):
        def submit(flat):
            sent[k] = flat
            f: Future = Future()
            f.set_result(k)
            return f
        return submit

    b_from_a = np.eye(4)
    b_from_a[:3, 3] = [0.0, 0.0, -1.0]
    evidence = []
    for i, frame in enumerate(frames):
        grays.append(frame)
        window.add_keyframe(frame, ring_px)
        if i >= 1:
            window.submit(i - 1, submitter(i - 1))
            evidence.append(StepEvidence.unmeasured(i - 1, i, b_from_a, None, "ok"))
    window.finish()
    kf = Keyframes(list(range(len(frames))), [], grays, [ring] * len(frames), evidence, window.fields)
    return kf, sent


def test_laser_around_with_the_steps_field_finds_the_true_length(wall_rig) -> None:
    """The re-match around a chosen length (step_decide.laser_around, searched within
    agree_log of it) divides both keyframes by the step's flat field, as the step's
    evidence did: around a prior 6 % short of the true 9 mm it finds the true length
    within 5 %, where the plain images' match stays short (the LEDs' fall-off)."""
    camera = wall_rig[0]
    kf, _ = _run_of_keyframes(wall_rig, False, 9.0 * np.arange(16))
    ctx = SfmContext(SfmConfig(), camera, None, InlineExecutor(), False, [])  # type: ignore[arg-type]
    plain_kf = replace(kf, flats=None)
    with kf.grays:
        fielded = [laser_around(ctx, kf, k, 0.94 * 9.0).scale / 9.0 for k in (2, 6, 10)]
        plain = [laser_around(ctx, plain_kf, k, 0.94 * 9.0).scale / 9.0 for k in (2, 6, 10)]
    assert np.all(np.abs(np.array(fielded) - 1.0) < 0.05), fielded
    assert np.median(plain) < 0.95, plain
    assert np.median(np.abs(np.array(fielded) - 1.0)) < 0.5 * np.median(np.abs(np.array(plain) - 1.0))


def _anchor_lengths(camera, anchors, positions) -> list[float]:
    """Each far anchor's step length (mm): the axial move of its rig-a points whose
    projections fit its matched pixels in b best (median pixel distance, 0.05 mm grid)."""
    out = []
    for an in anchors:
        true = positions[an.b] - positions[an.a]
        grid = np.arange(0.7 * true, 1.3 * true, 0.05)
        err = []
        for d in grid:
            px, _ = camera.project(an.points_in_a + np.array([0.0, 0.0, -d]))
            err.append(np.nanmedian(np.linalg.norm(px - an.pixels_b, axis=1)))
        out.append(float(grid[int(np.argmin(err))]) / true)
    return out


def test_far_anchors_divide_by_the_field_the_same_for_one_and_two_workers(wall_rig) -> None:
    """The adjustment's far anchors (keyframe a to a + 2: 9 mm, keyframes 4.5 mm apart)
    are matched around adjusted lengths 6 % short, in both images divided by step a's
    field: their matches sit near where the true move puts the ring (fitted lengths
    within 8 %, median 5 % short), the plain images' about 15 % short. A local pool of two workers (the images and fields read
    by path) gives the same anchors to the bit as inline, and its steps the same fields."""
    camera = wall_rig[0]
    positions = 4.5 * np.arange(16)
    kf, sent_inline = _run_of_keyframes(wall_rig, False, positions)
    kf2, sent_pool = _run_of_keyframes(wall_rig, True, positions)
    world = np.repeat(np.eye(4)[None], 8, axis=0)
    world[:, 2, 3] = 0.94 * positions[4:12]  # keyframes 4..11, adjusted 6 % short
    inline = SfmContext(SfmConfig(anchor_reach=2), camera, None, InlineExecutor(), False, [])  # type: ignore[arg-type]
    with kf.grays, kf2.grays, ProcessPoolExecutor(2) as pool:
        assert sorted(sent_inline) == sorted(sent_pool) == list(range(15))
        for k in range(15):
            assert isinstance(sent_pool[k], StoredImage)
            assert np.array_equal(sent_inline[k].field, StoredImage.load(sent_pool[k]))
            assert np.array_equal(kf.flats.get(k).field, kf2.flats.get(k).field)
        got = _far_anchors(inline, world, kf, 4, 0)
        plain = _far_anchors(inline, world, replace(kf, flats=None), 4, 0)
        pooled = _far_anchors(replace(inline, executor=pool, parallel=True), world, kf2, 4, 0)
    assert [(x.a, x.b) for x in got] == [(x.a, x.b) for x in pooled] == [(a, a + 2) for a in range(6)]
    for x, y in zip(got, pooled, strict=True):
        assert np.array_equal(x.points_in_a, y.points_in_a) and np.array_equal(x.pixels_b, y.pixels_b)
    assert min(len(x.pixels_b) for x in got) > 60
    fielded = np.array(_anchor_lengths(camera, [replace(x, a=x.a + 4, b=x.b + 4) for x in got], positions))
    short = np.array(_anchor_lengths(camera, [replace(x, a=x.a + 4, b=x.b + 4) for x in plain], positions))
    assert np.all(np.abs(fielded - 1.0) < 0.08), fielded
    assert np.median(short) < 0.9, short
    assert np.median(np.abs(fielded - 1.0)) < 0.4 * np.median(np.abs(short - 1.0)), (fielded, short)

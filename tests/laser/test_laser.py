"""Light section (Sec. III): sub-pixel ring extraction, Eq. (5), and bad frames."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.analysis.wall_profile import fit_wall_profile
from omnipipe.camera import OmniCamera
from omnipipe.geometry import apply
from omnipipe.laser import LaserConfig, LaserRing, RingExtractor, intersect_plane, run
from omnipipe.laser.extract import ExtractionConfig
from omnipipe.laser.triangulate import (
    centroid_ring,
    radial_mm_per_px,
    ring_roughness_px,
    triangulate_ring,
)
from omnipipe.rig import Rig
from omnipipe.sim import make_scenario
from omnipipe.sim.writer import build_renderer


def _synthetic_ring(rig: Rig, radius_mm: float, rng: np.random.Generator, sigma_px: float = 1.0):
    """An image with a Gaussian laser line through the true projection of a circle
    of ``radius_mm`` on the laser plane, on a textured, noisy background."""
    cam = OmniCamera.from_rig(rig)
    ang = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    z = -rig.laser.distance_mm
    ring = np.stack(
        [radius_mm * np.cos(ang), radius_mm * np.sin(ang), np.full_like(ang, z)], axis=1
    )
    px, _ = cam.project(ring)
    centre = np.array([cam.cx, cam.cy])
    rows, cols = np.mgrid[0 : cam.height, 0 : cam.width]
    pa = np.arctan2(rows - cam.cy, cols - cam.cx) % (2 * np.pi)
    pr = np.hypot(cols - cam.cx, rows - cam.cy)
    r_at = np.interp(pa, *_sorted(px, centre), period=2 * np.pi)
    line = 150 * np.exp(-0.5 * ((pr - r_at) / sigma_px) ** 2)
    tex = 60 + 25 * rng.standard_normal((cam.height, cam.width))
    img = np.stack([tex + line, tex, tex * 0.9], axis=2) + rng.normal(
        0, 2, (cam.height, cam.width, 3)
    )
    return np.clip(img, 0, 255).astype(np.uint8), cam


def _sorted(px: np.ndarray, centre: np.ndarray):
    a = np.arctan2(px[:, 1] - centre[1], px[:, 0] - centre[0]) % (2 * np.pi)
    r = np.hypot(*(px - centre).T)
    order = np.argsort(a)
    return a[order], r[order]


def test_subpixel_accuracy_on_a_synthetic_ring(small_rig: Rig) -> None:
    rng = np.random.default_rng(0)
    img, cam = _synthetic_ring(small_rig, 101.0, rng)
    ring = RingExtractor(cam).extract(img, "red")
    assert ring.fraction > 0.95
    centre = np.array([cam.cx, cam.cy])
    true_a, true_r = _sorted(
        cam.project(
            np.stack(
                [
                    101 * np.cos(t := np.linspace(0, 2 * np.pi, 4000)),
                    101 * np.sin(t),
                    np.full_like(t, -82.0),
                ],
                1,
            )
        )[0],
        centre,
    )
    meas_r = np.hypot(*(ring.pixels - centre).T)
    err = meas_r - np.interp(ring.angle_rad, true_a, true_r, period=2 * np.pi)
    assert np.sqrt(np.mean(err**2)) < 0.1  # px
    assert abs(np.mean(err)) < 0.03


def _overexposed_oval_ring(
    rig: Rig, radius_mm: float, ovality: float, angle: float, rng: np.random.Generator
) -> tuple[np.ndarray, OmniCamera]:
    """An image of an oval ring r(phi) = R (1 + ovality / 2 cos 2 (phi - angle)) on the
    laser plane, drawn as the renderer's: a line narrower than a pixel integrated over
    the pixel and blurred (0.7 px), far brighter than full scale (its top clipped), 5 %
    of it in the other channels (crosstalk)."""
    from scipy.special import ndtr

    cam = OmniCamera.from_rig(rig)
    a = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    r = radius_mm * (1 + 0.5 * ovality * np.cos(2 * (a - angle)))
    z = np.full_like(a, -rig.laser.distance_mm)
    px, _ = cam.project(np.stack([r * np.cos(a), r * np.sin(a), z], axis=1))
    rows, cols = np.mgrid[0 : cam.height, 0 : cam.width]
    pa = np.arctan2(rows - cam.cy, cols - cam.cx) % (2 * np.pi)
    d = np.hypot(cols - cam.cx, rows - cam.cy) - np.interp(pa, *_sorted(px, np.array([cam.cx, cam.cy])), period=2 * np.pi)
    line = 1500 * (ndtr((d + 0.5) / 0.7) - ndtr((d - 0.5) / 0.7))
    tex = 60 + 10 * rng.standard_normal((cam.height, cam.width))
    img = np.stack([tex + line, tex + 0.05 * line, 0.9 * tex + 0.05 * line], axis=2)
    img += rng.normal(0, 2, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8), cam


def _ovality_pct(ring: LaserRing) -> float:
    p = ring.points_in_rig
    c = fit_wall_profile(np.arctan2(p[:, 1], p[:, 0]), np.hypot(p[:, 0], p[:, 1]), 2, 0.5)
    return 100 * 2 * np.hypot(c[3], c[4]) / c[0]


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_oval_ring_keeps_its_ovality_when_overexposed(small_rig: Rig, seed: int) -> None:
    """A saturated ring about a pixel wide: the analysis's ring (:func:`centroid_ring`,
    clipped peaks at their centroids) keeps the section's ovality through the station fit
    (:func:`fit_wall_profile`) within 0.2 percentage points of 4 %; the three-point
    Gaussian fit's centre, which camera motion keeps, pulls the samples towards the scan
    line's samples (3.5-5.1 % on these four)."""
    rng = np.random.default_rng(seed)
    radius, angle = rng.uniform(90, 110), rng.uniform(0, np.pi)
    img, cam = _overexposed_oval_ring(small_rig, radius, 0.04, angle, rng)
    ring = triangulate_ring(RingExtractor(cam, ExtractionConfig(), small_rig.laser).extract(img, "red"), cam, small_rig.laser)
    assert ring.fraction > 0.95
    assert abs(_ovality_pct(centroid_ring(ring, cam, small_rig.laser)) - 4.0) <= 0.2


def test_centroid_moves_only_the_analysis_ring(small_rig: Rig) -> None:
    """With the centroid asked for, the ring's own positions and points (camera motion's)
    are the three-point fit's, bit for bit as without it; its clipped samples carry the
    move to their centroid (a few tenths of a px here), which :func:`centroid_ring`
    applies (each moved sample's radius grows by it) and then drops."""
    rng = np.random.default_rng(7)
    img, cam = _overexposed_oval_ring(small_rig, 100.0, 0.04, 0.3, rng)
    rings = {
        half: triangulate_ring(
            RingExtractor(cam, ExtractionConfig(centroid_half_px=half), small_rig.laser).extract(img, "red"),
            cam,
            small_rig.laser,
        )
        for half in (0.0, 3.0)
    }
    off, on = rings[0.0], rings[3.0]
    np.testing.assert_array_equal(on.pixels, off.pixels)
    np.testing.assert_array_equal(on.points_in_rig, off.points_in_rig)
    assert len(off.centroid_shift_px) == 0 and centroid_ring(off, cam, small_rig.laser) is off
    shift = on.centroid_shift_px
    assert shift.shape == (len(on.pixels),) and shift.dtype == np.float32
    assert np.mean(shift != 0) > 0.9 and 0.02 < np.median(np.abs(shift)) < 1.0
    moved = centroid_ring(on, cam, small_rig.laser)
    assert len(moved.centroid_shift_px) == 0 and len(moved.pixels) == len(on.pixels)
    centre = np.array([cam.cx, cam.cy])
    grown = np.hypot(*(moved.pixels - centre).T) - np.hypot(*(on.pixels - centre).T)
    np.testing.assert_allclose(grown, shift, atol=1e-5)
    np.testing.assert_array_equal(on.pixels, off.pixels)  # the motion's ring is untouched


def test_centroid_ring_keeps_the_three_point_ring_where_the_moves_roughen_it(small_rig: Rig) -> None:
    """Moves that would make the ring rougher (here: noise of 0.1 px on a smooth ring)
    are not applied: the analysis's ring is the three-point one, without moves; moves
    that smooth it (the same noise taken out again) are."""
    cam = OmniCamera.from_rig(small_rig)
    rng = np.random.default_rng(5)
    angle = np.arange(0, 2 * np.pi, 2 * np.pi / 720)
    centre = np.array([cam.cx, cam.cy])
    smooth = 60.0 + 2.0 * np.cos(2 * angle)
    noise = rng.normal(0, 0.1, angle.size).astype(np.float32)

    def ring(radius: np.ndarray, shift: np.ndarray) -> LaserRing:
        n = angle.size
        px = centre + radius[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
        return triangulate_ring(
            LaserRing(px, angle, np.full(n, 20.0), np.full(n, 0.05), np.full(n, 0.8), scanned=n, centroid_shift_px=shift),
            cam,
            small_rig.laser,
        )

    rough = ring(smooth, noise)
    kept = centroid_ring(rough, cam, small_rig.laser)
    np.testing.assert_array_equal(kept.points_in_rig, rough.points_in_rig)
    assert len(kept.centroid_shift_px) == 0
    noisy = ring(smooth + noise, -noise)
    moved = centroid_ring(noisy, cam, small_rig.laser)
    assert ring_roughness_px(angle, np.hypot(*(moved.pixels - centre).T)) < 0.01
    assert ring_roughness_px(angle, smooth + noise) == pytest.approx(0.1, rel=0.15)
    assert ring_roughness_px(angle, smooth) < 1e-6


def test_triangulation_drops_every_per_sample_array_alike(small_rig: Rig) -> None:
    """A sample whose ray misses the plane leaves all of the ring's per-sample arrays
    (the peak widths and the centroid moves too), so they stay aligned."""
    cam = OmniCamera.from_rig(small_rig)
    centre = np.array([cam.cx, cam.cy])
    pixels = centre + np.array([[60.0, 0.0], [0.0, 70.0], [0.0, 120.0], [-65.0, 0.0]])
    n = len(pixels)
    ring = LaserRing(
        pixels=pixels,
        angle_rad=np.arange(n, dtype=float),
        confidence=np.full(n, 20.0),
        radius_sigma_px=np.full(n, 0.1),
        peak_width_px=np.arange(n, dtype=float) + 1.0,
        scanned=n,
        centroid_shift_px=np.arange(n, dtype=np.float32) / 10,
    )
    out = triangulate_ring(ring, cam, small_rig.laser)
    kept = np.isin(np.arange(n), out.angle_rad.astype(int))
    np.testing.assert_array_equal(kept, [True, True, False, True])  # 120 px: its ray looks forward
    np.testing.assert_array_equal(out.peak_width_px, np.arange(n)[kept] + 1.0)
    np.testing.assert_array_equal(out.centroid_shift_px, (np.arange(n, dtype=np.float32) / 10)[kept])


def test_radial_pixel_scale_is_how_far_a_radial_px_moves_a_point(small_rig: Rig) -> None:
    """:func:`radial_mm_per_px`: the ring's median mm on the laser plane per px of image
    radius, as moving each sample half a px out and in and triangulating again measures
    it; NaN for a ring without samples."""
    cam = OmniCamera.from_rig(small_rig)
    img, _ = _synthetic_ring(small_rig, 100.0, np.random.default_rng(3))
    ring = triangulate_ring(RingExtractor(cam, ExtractionConfig(), small_rig.laser).extract(img, "red"), cam, small_rig.laser)
    centre = np.array([cam.cx, cam.cy])
    unit = (ring.pixels - centre) / np.linalg.norm(ring.pixels - centre, axis=1, keepdims=True)
    outer, _ = intersect_plane(cam.unproject(ring.pixels + 0.5 * unit), small_rig.laser)
    inner, _ = intersect_plane(cam.unproject(ring.pixels - 0.5 * unit), small_rig.laser)
    expected = float(np.median(np.linalg.norm(outer - inner, axis=1)))
    assert radial_mm_per_px(ring) == pytest.approx(expected, rel=0.01)
    assert 0.5 < expected < 20.0
    assert np.isnan(radial_mm_per_px(LaserRing(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0))))


def test_rendered_rings_are_metric() -> None:
    scenario = make_scenario("paper", frames=12, size=(800, 600))
    renderer, poses, _, _ = build_renderer(scenario)
    frames = [renderer.render(poses[i], seed=i)[0] for i in (0, 6)]
    res = run(LaserConfig(), scenario.rig, frames)
    errs = []
    for i, ring in zip((0, 6), res.rings, strict=True):
        assert ring.fraction > 0.85
        s, rho, th, *_ = renderer.pipe.pipe_coordinates(apply(poses[i], ring.points_in_rig))
        errs.append(rho - renderer.pipe.wall_radius(s, th))
        # Every point lies on the laser plane (Eq. 5).
        plane = scenario.rig.laser
        assert np.allclose(ring.points_in_rig @ plane.normal_in_rig + plane.offset_mm, 0.0, atol=1e-9)
        assert np.all(ring.sigma_mm > 0)
    e = np.concatenate(errs)
    assert (
        np.sqrt(np.mean(e**2)) < 0.3
    )  # mm at 800x600 (0.10 mm at full size: benchmarks/bench_laser.py)
    assert abs(e.mean()) < 0.1


def test_plane_intersection_round_trip(small_camera: OmniCamera, small_rig: Rig) -> None:
    rng = np.random.default_rng(2)
    ang = rng.uniform(0, 2 * np.pi, 100)
    pts = np.stack([90 * np.cos(ang), 90 * np.sin(ang), np.full(100, -82.0)], axis=1)
    px, ok = small_camera.project(pts)
    back, valid = intersect_plane(small_camera.unproject(px), small_rig.laser)
    assert ok.all() and valid.all() and np.abs(back - pts).max() < 1e-6


@pytest.mark.parametrize("kind", ["dark", "saturated", "wrong_size", "grey16"])
def test_bad_frames_give_empty_rings_and_warnings(small_rig: Rig, kind: str) -> None:
    cam = OmniCamera.from_rig(small_rig)
    ex = RingExtractor(cam)
    if kind == "dark":
        img = np.random.default_rng(0).integers(0, 4, (300, 400, 3), dtype=np.uint8)
    elif kind == "saturated":
        img = np.full((300, 400, 3), 255, np.uint8)
    elif kind == "wrong_size":
        img = np.zeros((100, 100, 3), np.uint8)
    else:
        img = np.zeros((300, 400), np.uint16)
    ring = ex.extract(img, "red")
    assert len(ring.pixels) == 0 and ring.warnings


def test_scan_lines_cover_every_radius_that_meets_the_plane(small_rig: Rig) -> None:
    """With the plane known, the scan skips only radii whose rays cannot meet it, and
    finds the same ring as the full scan."""
    from omnipipe.laser.triangulate import triangulate_ring

    rng = np.random.default_rng(4)
    img, cam = _synthetic_ring(small_rig, 101.0, rng)
    full = RingExtractor(cam)
    window = RingExtractor(cam, plane=small_rig.laser)
    assert len(window.radii) < 0.8 * len(full.radii)
    pixels = np.stack([full.map_x.ravel(), full.map_y.ravel()], axis=1)
    _, meets = intersect_plane(cam.unproject(pixels), small_rig.laser)
    radii = np.broadcast_to(full.radii, full.map_x.shape).ravel()[meets]
    assert window.radii[0] <= radii.min() and radii.max() <= window.radii[-1]
    a = triangulate_ring(full.extract(img, "red"), cam, small_rig.laser)
    b = triangulate_ring(window.extract(img, "red"), cam, small_rig.laser)
    assert len(a.pixels) > 0.9 * len(full.angles)
    common, ia, ib = np.intersect1d(a.angle_rad, b.angle_rad, return_indices=True)
    assert len(common) >= 0.99 * max(len(a.pixels), len(b.pixels))
    assert np.median(np.linalg.norm(a.points_in_rig[ia] - b.points_in_rig[ib], axis=1)) < 0.01  # mm


def _dark_stretch_image(
    rig: Rig, rng: np.random.Generator, sigma_px: float, half: float, centre: float, gain: float = 1.0
):
    """A synthetic ring image (radius 101 mm) whose stripe goes dark over ``centre`` +-
    ``half`` (rad) with the optics' blur ``sigma_px`` along the ring, as at a water line;
    the stripe ``gain`` times as bright (clipped at full scale)."""
    from scipy.special import ndtr

    img, cam = _synthetic_ring(rig, 101.0, rng, sigma_px=sigma_px)
    rows, cols = np.mgrid[0 : cam.height, 0 : cam.width]
    pa = np.arctan2(rows - cam.cy, cols - cam.cx)
    pr = np.hypot(cols - cam.cx, rows - cam.cy)
    into = (half - np.abs((pa - centre + np.pi) % (2 * np.pi) - np.pi)) * pr  # px into the dark
    dark = img.astype(float)
    tex = dark[..., 1]  # red is texture + stripe, green the texture (each with its noise)
    stripe = np.clip(dark[..., 0] - tex, 0, None)
    dark[..., 0] = tex + gain * stripe * ndtr(-into / sigma_px)
    return np.clip(dark, 0, 255).astype(np.uint8), cam


def test_edge_reach_is_how_far_samples_run_past_a_dark_stretch(small_rig: Rig) -> None:
    """A ring whose stripe stops over a dark 80 deg stretch (standing water), the stop
    blurred along the ring like the stripe across it: the samples run on past the stop
    by at least what :func:`edge_reach_mm` states (less one sample step) and at most half
    a blur sigma more (the texture lifts the faintest peaks over the threshold: 6.2 and
    5.3 mm against 4.0 stated here, blur 4.4 mm)."""
    from omnipipe.laser import triangulate_ring
    from omnipipe.laser.extract import edge_reach_mm, ring_blur_mm

    rng = np.random.default_rng(4)
    sigma_px, half, centre = 1.6, np.radians(40.0), np.pi / 2
    image, cam = _dark_stretch_image(small_rig, rng, sigma_px, half, centre)
    ring = triangulate_ring(RingExtractor(cam).extract(image, "red"), cam, small_rig.laser)
    reach, reach_sigma = edge_reach_mm([ring])
    assert reach > 0 and reach_sigma == 0.0
    # How far the samples run past each end of the dark stretch, along the wall (mm).
    rel = (ring.angle_rad - centre + np.pi) % (2 * np.pi) - np.pi
    mm_per_rad = 101.0
    past = [(half - np.min(rel[rel > 0])) * mm_per_rad, (half - np.min(-rel[rel < 0])) * mm_per_rad]
    step = 2 * np.pi / len(RingExtractor(cam).angles) * mm_per_rad
    blur = ring_blur_mm([ring])
    for p in past:
        assert reach - step <= p <= reach + step + 0.5 * blur


def test_station_reach_is_measured_at_the_stripes_half_height(small_rig: Rig) -> None:
    """The same dark stretch: :func:`station_edge_reach` finds where the stripe's fall-off
    halves at both ends of the cut (the stop itself) from the ring's own peaks and the
    signal in the gap, so the samples' measured reach past it is the true one (the mean
    of both ends) within its stated sigma, wherever the extractor's tests stopped."""
    from omnipipe.laser import triangulate_ring
    from omnipipe.laser.extract import station_edge_reach

    rng = np.random.default_rng(4)
    sigma_px, half, centre = 1.6, np.radians(40.0), np.pi / 2
    image, cam = _dark_stretch_image(small_rig, rng, sigma_px, half, centre)
    ring = triangulate_ring(RingExtractor(cam).extract(image, "red"), cam, small_rig.laser)
    assert len(ring.gap_edges) == 2
    reach, sigma = station_edge_reach([ring])
    rel = (ring.angle_rad - centre + np.pi) % (2 * np.pi) - np.pi
    past = [(half - np.min(rel[rel > 0])) * 101.0, (half - np.min(-rel[rel < 0])) * 101.0]
    assert abs(reach[0] - np.mean(past)) <= sigma[0]
    # A dry ring (no gap) has no measured reach.
    full, _ = _synthetic_ring(small_rig, 101.0, rng, sigma_px=sigma_px)
    dry = triangulate_ring(RingExtractor(cam).extract(full, "red"), cam, small_rig.laser)
    assert len(dry.gap_edges) == 0 and np.isnan(station_edge_reach([dry])[0][0])


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_scan_lines_sample_the_frames_part_they_reach_as_the_whole_frame(small_rig: Rig, dtype) -> None:
    """The polar resampling from the frame's part the scan lines reach (an integer colour
    frame as four channels) gives the values of OpenCV's bilinear remap of the whole frame."""
    import copy

    import cv2

    rng = np.random.default_rng(11)
    cam = OmniCamera.from_rig(small_rig)
    integer = dtype != np.float32
    top = np.iinfo(dtype).max if integer else 1.0

    def frame(shape):
        img = (rng.integers(0, top + 1, shape) if integer else rng.random(shape)).astype(dtype)
        img[rng.random(shape[:2]) < 0.1] = top  # saturated pixels
        return img

    def whole(img, extractor):
        return cv2.remap(img, extractor.map_x, extractor.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    # Scan lines within the frame, with and without the plane's radii; and reaching past
    # its edges (the mirror's centre near a corner): the constant border there as before.
    extractors = [RingExtractor(cam), RingExtractor(cam, plane=small_rig.laser)]
    for cx, cy in ((20.0, 15.0), (cam.width - 10.5, cam.height - 30.0)):
        moved = copy.copy(cam)
        moved.cx, moved.cy = cx, cy
        extractors.append(RingExtractor(moved))
        assert not extractors[-1].inside.all()
    for extractor in extractors:
        img = frame((cam.height, cam.width, 3))
        want = whole(img, extractor)
        for channel in ("red", "green", "blue"):
            got = extractor._resample(img, channel)
            assert got.shape == (*want.shape[:2], 4 if integer else 3)
            assert np.array_equal(got[..., :3], want)
        assert np.array_equal(extractor._resample(img, "gray"), want)
        grey = frame((cam.height, cam.width))
        assert np.array_equal(extractor._resample(grey, "red"), whole(grey, extractor))


def test_station_reach_of_a_clipped_stripe_is_read_on_its_flanks(small_rig: Rig) -> None:
    """The dark stretch with the stripe twice as bright, its core clipped at full scale:
    the half of the clipped plateau lies past the stop, its flanks' does not, so the
    measured reach is still the true one within its stated sigma (read on the clipped
    core it came out 1.1-1.3 sigma short on seeds 4-6, on the flanks 0.3-0.7)."""
    from omnipipe.laser import triangulate_ring
    from omnipipe.laser.extract import station_edge_reach

    rng = np.random.default_rng(4)
    sigma_px, half, centre = 1.6, np.radians(40.0), np.pi / 2
    image, cam = _dark_stretch_image(small_rig, rng, sigma_px, half, centre, gain=2.0)
    ring = triangulate_ring(RingExtractor(cam).extract(image, "red"), cam, small_rig.laser)
    assert (image[..., 0] == 255).sum() > 500  # the stripe's core is clipped
    reach, sigma = station_edge_reach([ring])
    rel = (ring.angle_rad - centre + np.pi) % (2 * np.pi) - np.pi
    past = [(half - np.min(rel[rel > 0])) * 101.0, (half - np.min(-rel[rel < 0])) * 101.0]
    assert abs(reach[0] - np.mean(past)) <= sigma[0], (reach[0], np.mean(past), sigma[0])

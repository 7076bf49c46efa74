"""Stationary-frame detection on a simulated stop-and-go run."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from omnipipe.sfm.stations import StationConfig, StationTracker, noise_sigma
from omnipipe.sim import make_scenario
from omnipipe.sim.writer import build_renderer


def test_noise_estimate_on_pure_noise() -> None:
    rng = np.random.default_rng(0)
    img = 100.0 + rng.normal(0, 2.0, (300, 400))
    assert abs(noise_sigma(img) - 2.0) < 0.1


@pytest.fixture(scope="module")
def stop_and_go() -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """A seeded bend-small run of 20 frames (two strokes, rests of 6 frames): its
    frames (H, W, 3) uint8, valid mask and true moving flags."""
    scenario = make_scenario("bend-small", frames=20, seed=2)
    renderer, poses, _, moving = build_renderer(scenario)
    images = [renderer.render(pose, seed=100 + i)[0] for i, pose in enumerate(poses)]
    return images, renderer.camera.valid_mask(), moving


def _jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)


def _flags(tracker: StationTracker, images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    out = [tracker.update(image[..., 1]) for image in images]
    return np.array([m for m, _ in out]), np.array([r for _, r in out])


def test_stops_are_found_exactly(stop_and_go) -> None:
    images, mask, moving = stop_and_go
    tracker = StationTracker(mask)
    flags, ratios = [], []
    for image in images:
        moved, ratio = tracker.update(image[..., 1])
        flags.append(moved)
        ratios.append(ratio)
    flags = np.array(flags)
    assert flags[0]  # the first frame starts a station
    assert np.array_equal(flags[1:], moving[1:])
    still = np.array(ratios[1:])[~moving[1:]]
    assert np.all(still < 2.0)  # the noise model explains stationary pairs


def test_counted_median_is_the_grouped_median_of_whole_numbers() -> None:
    from omnipipe.sfm.stations import _grouped_median, _median_abs

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 10, 999, 1000):
        half = rng.integers(-900, 900, n).astype(np.float32) + np.float32(0.5)
        assert _median_abs(half) == float(np.median(np.abs(half)))  # not whole: numpy's
    # Whole numbers, by hand: [0, 0, 0, 1] -> in [0, 1/2), 2 of its 3 counts below.
    assert _median_abs(np.array([0, 0, 0, -1], np.float32)) == 0.5 * 2 / 3
    assert _median_abs(np.array([1, 1, -2, 2], np.float32)) == 1.5  # [0.5, 1.5) filled
    assert _median_abs(np.array([3], np.float32)) == 3.0  # the middle of [2.5, 3.5)
    assert np.isnan(_grouped_median(np.zeros(5, np.int64)))
    # Rounded Gaussian magnitudes: the grouped median finds the continuous one within a
    # few hundredths where the plain median of whole numbers is up to 1/2 off.
    for sigma in (3.0, 7.4, 20.0):
        x = rng.normal(0, sigma, 400_000).astype(np.float32)
        truth = float(np.median(np.abs(x)))
        got = _median_abs(np.round(x))
        assert abs(got - truth) < 0.03, (sigma, got, truth)


def _frame_cases(rng: np.random.Generator) -> list[tuple[np.ndarray, str]]:
    """Frames of every kind the fast signature path takes, and some it must not."""
    rgb8 = rng.normal(120, 9, (64, 96, 3)).clip(0, 255).astype(np.uint8)
    rgb16 = rng.normal(30000, 900, (64, 96, 3)).clip(0, 65535).astype(np.uint16)
    return [
        (rgb8, "red"),  # fast: the green channel
        (rgb16, "red"),  # fast, 16 bit
        (rgb8[..., 1].copy(), "red"),  # fast: one channel
        (rgb8, "green"),  # slow: the mean of red and blue
        (rgb8[:63, :94], "red"),  # fast: sides not divisible by 4 (the resize handles them)
        (rgb8[:, :95], "red"),  # odd width: the last column reflected on its own
        (np.kron(rng.integers(0, 2, (32, 48, 1)), np.ones((2, 2, 3))).astype(np.uint8) * 255, "red"),  # extremes
        ((rng.integers(0, 2, (64, 96, 3)) * 65535).astype(np.uint16), "red"),  # 16-bit extremes
        (rgb8.astype(np.float32), "red"),  # slow: float frame
        (np.full((64, 96, 3), 255, np.uint8), "red"),  # saturated: all-zero response
    ]


def test_frame_signature_equals_the_grey_image_signature() -> None:
    import pickle

    from omnipipe.image import gray_without_laser
    from omnipipe.sfm.stations import (
        StationConfig,
        frame_signature,
        inner_mask,
        mask_runs,
        noise_mask,
        station_signature,
    )

    rng = np.random.default_rng(11)
    for image, channel in _frame_cases(rng):
        h, w = image.shape[:2]
        yy, xx = np.mgrid[:h, :w]
        mask = (xx - w / 2) ** 2 + (yy - h / 2) ** 2 < (0.6 * w) ** 2  # cut by the borders
        whole = np.ones((h, w), bool)  # runs along the borders: reflected neighbours
        for inner in (inner_mask(mask), noise_mask(mask, 400), noise_mask(whole, None), whole):
            for config in (StationConfig(), StationConfig(downsample=3), StationConfig(downsample=1)):
                want = station_signature(gray_without_laser(image, channel), inner, config)
                got = frame_signature(image, channel, inner, config)
                again = frame_signature(image, channel, inner, config, runs=mask_runs(inner))
                assert np.array_equal(again.small, got.small) and again.noise_sigma == got.noise_sigma
                assert got.small.dtype == want.small.dtype == np.float32
                case = (image.shape, image.dtype, channel, config.downsample, int(inner.sum()))
                assert np.array_equal(got.small, want.small), case
                assert got.noise_sigma == want.noise_sigma, case
                # Pickled as the grey image's signature is (its block sums made once).
                assert pickle.dumps(got) == pickle.dumps(want), case
                back = pickle.loads(pickle.dumps(got))
                assert np.array_equal(back.small, want.small) and back.small.dtype == np.float32


def test_noise_mask_keeps_every_kth_row_of_the_interior() -> None:
    from omnipipe.sfm.stations import inner_mask, noise_mask

    rng = np.random.default_rng(13)
    mask = rng.random((40, 30)) > 0.2
    inner = inner_mask(mask)
    count = int(inner.sum())
    assert np.array_equal(noise_mask(mask), inner) and np.array_equal(noise_mask(mask, count), inner)
    for pixels in (count // 2, count // 4, count // 7, 30):
        got = noise_mask(mask, pixels)
        kept = [k for k in range(1, 41) if inner[::k].sum() >= pixels]  # the largest: max
        rows = np.arange(40) % max(kept) == 0
        assert np.array_equal(got[rows], inner[rows]) and not got[~rows].any(), pixels
        assert got.sum() >= pixels


def test_noise_on_every_fourth_row_matches_every_row() -> None:
    """The sparser estimate's error on a textured, noisy 8-bit frame: within 3 %."""
    from omnipipe.sfm.stations import frame_signature, noise_mask

    rng = np.random.default_rng(14)
    yy, xx = np.mgrid[:480, :640]
    texture = 120 + 40 * np.sin(xx / 7.0) * np.cos(yy / 11.0)
    for sigma in (0.8, 1.5, 3.0, 6.0):
        image = (texture + rng.normal(0, sigma, texture.shape)).clip(0, 255).astype(np.uint8)
        mask = np.ones(image.shape, bool)
        every = frame_signature(image, "red", noise_mask(mask)).noise_sigma
        fourth = frame_signature(image, "red", noise_mask(mask, mask.size // 4)).noise_sigma
        assert abs(fourth / every - 1) < 0.03, (sigma, every, fourth)
        assert abs(every / sigma - 1) < 0.25, (sigma, every)  # and both measure the noise


def test_station_settings_are_validated() -> None:
    import pytest

    from omnipipe.config import dataclass_from_dict
    from omnipipe.errors import ConfigError
    from omnipipe.sfm.stations import StationConfig

    for bad, name in (
        ({"downsample": 0}, "downsample"),
        ({"noise_factor": 0.0}, "noise_factor"),
        ({"noise_pixels": 10}, "noise_pixels"),
    ):
        with pytest.raises(ConfigError, match=f"sfm.stations.{name}"):
            dataclass_from_dict(StationConfig, bad, "sfm.stations")


def test_mask_runs_cover_exactly_the_mask() -> None:
    from omnipipe.sfm.stations import mask_runs

    rng = np.random.default_rng(12)
    for shape in ((1, 1), (5, 7), (40, 33)):
        mask = rng.random(shape) > 0.4
        mask[0, :] = True  # a run to the row's end
        runs = mask_runs(mask)
        flat = np.zeros(mask.size, bool)
        for start, end in runs:
            assert start < end and start // shape[1] == (end - 1) // shape[1]  # within one row
            flat[start:end] = True
        assert np.array_equal(flat.reshape(shape), mask)


def test_signature_pickles_exactly_and_compactly() -> None:
    import pickle

    from omnipipe.sfm.stations import StationSignature

    rng = np.random.default_rng(15)
    boxed = rng.integers(0, 16 * 255 + 1, (30, 40)).astype(np.float32) / np.float32(16)  # 8-bit, f = 4
    for small in (boxed, rng.random((30, 40)).astype(np.float32), boxed.astype(np.float64), boxed * 300):
        signature = StationSignature(small, 1.25)
        back = pickle.loads(pickle.dumps(signature))
        assert back.small.dtype == small.dtype and np.array_equal(back.small, small)
        assert back.noise_sigma == 1.25
    assert len(pickle.dumps(StationSignature(boxed, 1.0))) < 0.6 * boxed.nbytes  # as uint16 sums


def test_the_creep_before_a_stroke_makes_the_stations_last_frame_moving() -> None:
    """Only a frame right before a moving one, and only above the creep factor."""
    from omnipipe.sfm.stations import promote_creep

    moved = np.array([1, 0, 0, 0, 1, 1, 0, 0, 1, 0], bool)
    ratio = np.array([np.inf, 1.3, 1.0, 1.3, 3.0, 3.0, 1.2, 1.05, 3.0, 1.4])
    out = promote_creep(moved, ratio, 1.15)
    assert out.tolist() == [1, 0, 0, 1, 1, 1, 0, 0, 1, 0]
    assert moved[3] == 0  # the input is not changed


def test_jpeg_frames_at_rest_stay_stationary(stop_and_go) -> None:
    """JPEG (quality 85) strips the fine-grain noise the spatial estimate measures
    (every frame at rest scored about 5 against the threshold 1.7): the floor set by
    three frames at rest puts them back at about 1, and every stroke is still found."""
    images, mask, moving = stop_and_go
    tracker = StationTracker(mask)
    flags, ratios = _flags(tracker, [_jpeg(image, 85) for image in images])
    assert 3.0 < tracker.rest_factor < 8.0
    first_rest = 2 + int(np.flatnonzero(~moving[2:] & ~moving[1:-1] & ~moving[:-2])[0])
    # The first rest frame before three frames at rest were seen counts as moved (one
    # extra moving frame a run); every later one is found exactly.
    assert np.array_equal(flags[first_rest:], moving[first_rest:])
    assert np.all(flags[moving])
    assert np.all(ratios[first_rest:][~moving[first_rest:]] < 1.3)
    # The same frames as PNG (lossless): the spatial estimate alone, as before.
    png = StationTracker(mask)
    flags_png, _ = _flags(png, images)
    assert png.rest_factor == 1.0
    assert np.array_equal(flags_png[1:], moving[1:])


def test_a_run_that_never_rests_stays_all_moving() -> None:
    """Constant motion makes three frames' differences unlike (the two-frame one about
    twice the others): no rest floor, lossless or JPEG."""
    scenario = make_scenario("continuous-small", frames=6, seed=2)
    renderer, poses, _, moving = build_renderer(scenario)
    images = [renderer.render(pose, seed=100 + i)[0] for i, pose in enumerate(poses)]
    assert np.all(moving[1:])
    for frames in (images, [_jpeg(image, 85) for image in images]):
        tracker = StationTracker(renderer.camera.valid_mask())
        flags, _ = _flags(tracker, frames)
        assert np.all(flags) and tracker.rest_factor == 1.0


def test_frames_that_differ_alike_by_more_than_rest_max_are_motion() -> None:
    """Frames each a texture's width apart (independent textures) differ alike, but far
    beyond any noise floor: no rest floor, every frame moving."""
    rng = np.random.default_rng(3)
    mask = np.ones((64, 64), bool)
    tracker = StationTracker(mask, StationConfig(downsample=2))
    for _ in range(6):
        gray = np.round(rng.normal(120.0, 1.0, (64, 64)) + np.kron(rng.normal(0, 30.0, (8, 8)), np.ones((8, 8))))
        moved, _ = tracker.update(gray.astype(np.uint8))
        assert moved
    assert tracker.rest_factor == 1.0


def test_a_tracker_resumed_from_the_state_decides_the_same(stop_and_go) -> None:
    """The state a resumed run restores (:attr:`StationTracker.reference`) carries the
    rest floor: the tracker goes on exactly as one that saw every frame."""
    images, mask, _ = stop_and_go
    frames = [_jpeg(image, 85) for image in images]
    whole = StationTracker(mask)
    expected = _flags(whole, frames)
    first = StationTracker(mask)
    head = _flags(first, frames[:8])
    resumed = StationTracker(mask)
    resumed.reference = first.reference
    tail = _flags(resumed, frames[8:])
    assert np.array_equal(np.concatenate([head[0], tail[0]]), expected[0])
    assert np.array_equal(np.concatenate([head[1], tail[1]]), expected[1])
    assert resumed.rest_factor == whole.rest_factor > 3.0



def _wall(rng: np.random.Generator, contrast: float, shift_px: int, size: int = 160) -> np.ndarray:
    """A grey wall texture (smooth blobs of ``contrast`` grey levels, one fixed pattern)
    shifted by ``shift_px`` columns, with sensor noise sigma 2 from ``rng``."""
    base = cv2.GaussianBlur(np.random.default_rng(7).normal(0, 1, (size, size + 64)), (0, 0), 6)
    base = 128 + contrast * base / base.std()
    return base[:, shift_px : shift_px + size] + rng.normal(0, 2.0, (size, size))


def _ratios(frames: list[np.ndarray]) -> np.ndarray:
    tracker = StationTracker(np.ones(frames[0].shape, bool))
    return np.array([tracker.update(f.astype(np.float32))[1] for f in frames])


def test_a_plain_wall_leaves_standing_frames_unverified_a_textured_one_does_not() -> None:
    """Stop and go at 0.5 mm per px: frames 0, 1 (+8 px), then frame 2 creeps 3 px
    (1.5 mm) and 3 stands there, 4 moves on (+8 px). On a plain wall the test takes
    the creep for standing (silently 1.5 mm off): the station is unverified; on a
    textured wall it sees the creep (a moving frame), and stationary frames at rest
    are verified."""
    from omnipipe.sfm.stations import hidden_steps, texture_gain, unverified_stations

    rng = np.random.default_rng(3)
    px = [0, 8, 11, 11, 19, 19, 19]
    positions = np.array([[0.0, 0.0, 0.5 * p] for p in px])
    for contrast, plain in ((1.5, True), (30.0, False)):
        ratio = _ratios([_wall(rng, contrast, p) for p in px])
        moved = ratio > StationConfig().noise_factor
        assert moved[2] != plain, ratio  # the creep, seen on texture only
        gain = texture_gain(ratio, positions, np.ones(len(px), bool))
        hidden = hidden_steps(ratio, moved, gain)
        found = unverified_stations(hidden, moved, list(np.flatnonzero(moved)))
        if plain:
            assert found and found[0][:2] == (1, 4) and found[0][2] > 1.5, (ratio, found)
        else:
            assert found == [], (ratio, hidden)


def test_hidden_steps_follow_the_quadrature_model() -> None:
    from omnipipe.sfm.stations import HIDDEN_RATIO_MARGIN, hidden_steps, texture_gain

    g = 0.2  # per mm: r^2 = 1 + (g L)^2
    positions = np.array([[0, 0, z] for z in (0.0, 10.0, 10.0, 22.0)], float)
    ratio = np.array([math.inf, math.sqrt(1 + (g * 10) ** 2), 1.2, math.sqrt(1 + (g * 12) ** 2)])
    gain = texture_gain(ratio, positions, np.ones(4, bool))
    assert gain == pytest.approx(g, rel=1e-9)
    moved = ratio > 1.7
    hidden = hidden_steps(ratio, moved, gain)
    r = 1.2 + HIDDEN_RATIO_MARGIN
    assert hidden[2] == pytest.approx(math.sqrt(r * r - 1) / g, rel=1e-9)
    assert hidden[[0, 1, 3]].tolist() == [0.0, 0.0, 0.0]
    assert math.isinf(hidden_steps(ratio, moved, math.nan)[2])


def test_unverified_stations_widen_to_the_keyframes_and_keep_the_tail() -> None:
    from omnipipe.sfm.stations import unverified_stations

    moved = np.array([1, 0, 1, 1, 0, 0, 1, 1, 1, 0], bool)
    hidden = np.array([0, 3.0, 0, 0, 0.2, 2.0, 0, 0, 0, 1.5])
    # Keyframes 0, 3, 8: station 0 (frame 1) -> 0..2 widened to 0..3; station 3
    # (frames 4, 5) -> 3..6 widened to 3..8; the tail 8..9 stays.
    assert unverified_stations(hidden, moved, [0, 3, 8]) == [(0, 3, 3.0), (3, 8, 2.0), (8, 9, 1.5)]
    assert unverified_stations(hidden, moved) == [(0, 2, 3.0), (3, 6, 2.0), (8, 9, 1.5)]
    assert unverified_stations(np.minimum(hidden, 0.9), moved, [0, 3, 8]) == []


def test_the_strokes_tail_starts_the_station_where_it_ends() -> None:
    """Frames 0, 1 (+8 px), then 2 moves 1 px on (the stroke's tail: ratio 1.4, under
    the noise factor) and stands there with 3, 4; 5 moves on (+8 px) and stands. The
    tail is a moving frame and its station's frames are compared with it (ratios of
    rest, verified); at rest right after a stroke a frame stays stationary."""
    rng = np.random.default_rng(3)
    px = [0, 8, 9, 9, 9, 17, 17, 17]
    tracker = StationTracker(np.ones((160, 160), bool))
    out = [tracker.update(_wall(rng, 6.0, p).astype(np.float32)) for p in px]
    moved = [m for m, _ in out]
    ratio = np.array([r for _, r in out])
    cfg = StationConfig()
    assert cfg.creep_factor < ratio[2] < cfg.noise_factor, ratio  # the test alone: standing
    assert moved == [True, True, True, False, False, True, False, False], ratio
    assert np.all(ratio[[3, 4, 6, 7]] < 1.1), ratio  # against the tail's frame: at rest


def test_the_tracked_flow_verifies_a_plain_walls_standing_frames_and_sees_its_creep() -> None:
    """A wall too plain for the stationary test's ratio (contrast 1.0, noise 2 grey
    levels; a 4 mm step gives 1.5, under its threshold): frames 0, 1, 2 move 8 px each
    (4 mm at 0.5 mm per px), frame 2 starts a station; frame 3 stands there, frame 4
    crept 3 px (1.5 mm) on. The ratio cannot bound either; the flow bounds frame 3's
    step well under 1 mm and frame 4's over it, near its 1.5 mm. With positions that
    contradict the flow's ruler (frame 0 placed 3 mm behind frame 2, not 8) it verifies
    nothing."""
    from omnipipe.sfm.stations import HIDDEN_STEP_MM, flow_hidden_steps, hidden_steps, texture_gain

    rng = np.random.default_rng(3)
    px = [0, 8, 16, 16, 19]
    frames = [_wall(rng, 1.0, p, size=320) for p in px]
    positions = np.array([[0.0, 0.0, 0.5 * p] for p in (0, 8, 16, 16, 16)])  # as estimated
    ratio = _ratios(frames)
    moved = np.array([True, True, True, False, False])
    registered = np.ones(5, bool)
    hidden = hidden_steps(ratio, moved, texture_gain(ratio, positions, registered))
    assert np.all(hidden[3:] > HIDDEN_STEP_MM), (ratio, hidden)  # the ratio alone: unverified
    mask = np.ones((320, 320), bool)
    out = flow_hidden_steps(hidden, moved, positions, registered, lambda i: frames[i], mask)
    assert out[3] < 0.3, out
    assert 1.5 < out[4] < 2.2, out
    assert np.all(out[:3] == 0.0)
    wrong = positions.copy()
    wrong[0, 2] = 5.0
    assert np.array_equal(flow_hidden_steps(hidden, moved, wrong, registered, lambda i: frames[i], mask), hidden)

"""Scale matching with laser points (Sec. V-D, Eq. 17) on simulated frames."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.geometry import invert
from omnipipe.sfm.laser_scale import match_laser_points
from omnipipe.sim import make_scenario
from omnipipe.sim.render import Renderer
from omnipipe.sim.scenario import Scenario
from omnipipe.sim.writer import build_renderer


def _pair(renderer, poses: np.ndarray, a: int, b: int):
    """Frames a and b rendered, a's true laser points (rig a) and the step b_from_a, length."""
    img_a, truth_a = renderer.render(poses[a], seed=1)
    img_b, _ = renderer.render(poses[b], seed=2)
    ring = truth_a["points_in_rig"][np.abs(truth_a["laser_h"]) < 0.3]
    b_from_a = invert(poses[b]) @ poses[a]
    return img_a, img_b, ring, b_from_a, float(np.linalg.norm(b_from_a[:3, 3]))


@pytest.fixture(scope="module")
def paper_800() -> tuple[Scenario, Renderer, np.ndarray, np.ndarray]:
    """paper at 800x600, 12 frames, seed 4: (scenario, renderer, poses, moving), built once
    for the module (its wall texture is most of the cost)."""
    scenario = make_scenario("paper", frames=12, size=(800, 600), seed=4)
    renderer, poses, _, moving = build_renderer(scenario)
    return scenario, renderer, poses, moving


def test_laser_points_give_the_metric_translation(paper_800) -> None:
    scenario, renderer, poses, moving = paper_800
    # A full stroke apart: frame 0 and the last frame of the first move.
    a, b = 0, int(np.flatnonzero(moving)[: scenario.motion.frames_per_cycle // scenario.motion.n_units][-1])
    img_a, img_b, ring, b_from_a, length = _pair(renderer, poses, a, b)
    m = match_laser_points(
        img_a[..., 1].astype(np.float32),
        img_b[..., 1].astype(np.float32),
        renderer.camera,
        ring,
        b_from_a[:3, :3],
        b_from_a[:3, 3] / length,
    )
    assert len(m.index) > 40
    assert abs(m.scale / length - 1.0) < 0.01, (m.scale, length)
    # The matched pixels are where the laser points really appear in frame b.
    true_px, _ = renderer.camera.project(ring[m.index] @ b_from_a[:3, :3].T + b_from_a[:3, 3])
    assert np.median(np.linalg.norm(m.pixels_b - true_px, axis=1)) < 0.5


def test_leaking_stripe_does_not_pull_short_steps_to_zero(paper_800) -> None:
    """The laser sheet moves with the robot: its light leaking into the grey image
    (colour crosstalk) sits at the same place in both frames. Left in the correlation it
    pulled every short step towards zero motion (-9 % on a 585 mm random rig)."""
    from dataclasses import replace

    from omnipipe.image import gray_without_laser

    scenario, plain, poses, moving = paper_800
    # The same scene (its texture) rendered with the laser's light leaking into the grey.
    renderer = Renderer(scenario.rig, scenario.pipe, plain.texture,
                        replace(scenario.render, laser_crosstalk=0.25))
    a = int(np.flatnonzero(moving)[0]) - 1  # at rest, then the first moving frame
    b = a + 1
    img_a, img_b, ring, b_from_a, length = _pair(renderer, poses, a, b)
    assert 1.0 < length < 12.0, length  # a short step: a few pixels in the image
    m = match_laser_points(
        gray_without_laser(img_a, "red"),
        gray_without_laser(img_b, "red"),
        renderer.camera,
        ring,
        b_from_a[:3, :3],
        b_from_a[:3, 3] / length,
    )
    assert len(m.index) > 40
    assert abs(m.scale / length - 1.0) < 0.03, (m.scale, length)


def test_compiled_ncc_is_bit_identical_to_numpy() -> None:
    from omnipipe.sfm.laser_scale import _ncc, _ncc_numpy

    rng = np.random.default_rng(3)
    # K: the default 13x13 patch, small ones (< 8: plain loop) and ones needing one and
    # several halvings of NumPy's pairwise sum (> 128, > 256, > 1024).
    for trial, k in enumerate((169, 1, 3, 9, 25, 128, 129, 441, 2000)):
        n, s = int(rng.integers(1, 30)), int(rng.integers(1, 40))
        dtype = np.float32 if trial % 2 == 0 else np.float64
        template = (rng.normal(size=(n, k)) * 30 + 100).astype(dtype)
        patches = (rng.normal(size=(n, s, k)) * 30 + 100).astype(dtype)
        template[rng.random(template.shape) < 0.05] = np.nan
        patches[rng.random(patches.shape) < 0.1 * (trial % 3)] = np.nan
        patches[:, : s // 2] = template[:, None, :] * 1.5 + 3.0  # perfectly correlated
        weight = (rng.random((n, k)) > 0.3).astype(float)
        weight[0] = 0.0  # no weight at all
        weight3 = weight[:, None, :] * (rng.random((n, s, k)) > 0.2)
        for w in (weight, weight3):
            got = _ncc(template, patches, w)
            assert np.array_equal(got, _ncc_numpy(template, patches, w), equal_nan=True)


def test_compiled_plane_ncc_equals_numpy() -> None:
    """The detrended NCC (a plane fitted and removed from template and patch) of the
    compiled closed form equals the NumPy least squares within rounding, with missing
    samples, zero weights and per-candidate weights."""
    from omnipipe.sfm.laser_scale import _ncc, _ncc_numpy

    rng = np.random.default_rng(4)
    g = np.arange(-6, 7, dtype=float)
    gu, gv = np.meshgrid(g, g)
    basis = np.vstack([gu.ravel(), gv.ravel()]) / 6.0
    for trial in range(6):
        n, s = int(rng.integers(1, 20)), int(rng.integers(1, 30))
        dtype = np.float32 if trial % 2 == 0 else np.float64
        template = (rng.normal(size=(n, 169)) * 30 + 100).astype(dtype)
        patches = (rng.normal(size=(n, s, 169)) * 30 + 100).astype(dtype)
        template[rng.random(template.shape) < 0.05] = np.nan
        patches[rng.random(patches.shape) < 0.1 * (trial % 3)] = np.nan
        # Correlated up to a brightness plane: detrended NCC 1.
        patches[:, : s // 2] = template[:, None, :] * 1.5 + 3.0 + 40.0 * basis[1] - 9.0 * basis[0]
        weight = (rng.random((n, 169)) > 0.3).astype(float)
        weight[0] = 0.0
        for w in (weight, weight[:, None, :] * (rng.random((n, s, 169)) > 0.2)):
            got = _ncc(template, patches, w, basis)
            want = _ncc_numpy(template, patches, w, basis)
            assert np.allclose(got, want, rtol=0, atol=1e-7, equal_nan=True)
        assert np.all(got[1:, : s // 2][got[1:, : s // 2] > -1] > 0.999)


def test_detrend_takes_the_brightness_falloff_out_of_the_length() -> None:
    """The LEDs' fall-off moves with the robot: on a weakly textured wall far out in the
    mirror (random-features-small seed 8: 449 mm tiles at 400x300, the ring near the
    blind centre) it dominated the templates and pulled every length 19-35 % short under
    the true motion. With ``detrend`` template and patches lose their brightness plane
    (off by default: on the robustness bench's textured walls it moved seed 3's scale
    0.01 -> 2.8 %, benchmarks/RESULTS.md)."""
    from omnipipe.image import gray_without_laser
    from omnipipe.laser.extract import RingExtractor
    from omnipipe.laser.stage import LaserConfig
    from omnipipe.laser.triangulate import triangulate_ring
    from omnipipe.sfm.laser_scale import LaserScaleConfig
    from omnipipe.sim.feature_scenarios import make_feature_scenario

    scenario = make_feature_scenario("random-features-small", 20, None, 8)
    renderer, poses, _, _ = build_renderer(scenario)
    extractor = RingExtractor(renderer.camera, LaserConfig().extraction, scenario.rig.laser)
    logs = []
    for a, b in ((0, 3), (3, 6), (17, 19)):
        img_a, _ = renderer.render(poses[a], seed=1)
        img_b, _ = renderer.render(poses[b], seed=2)
        ring = triangulate_ring(extractor.extract(img_a, "red"), renderer.camera, scenario.rig.laser)
        b_from_a = invert(poses[b]) @ poses[a]
        length = float(np.linalg.norm(b_from_a[:3, 3]))
        m = match_laser_points(
            gray_without_laser(img_a, "red"), gray_without_laser(img_b, "red"), renderer.camera,
            ring.points_in_rig, b_from_a[:3, :3], b_from_a[:3, 3] / length, LaserScaleConfig(detrend=True),
        )
        assert len(m.index) >= 8
        logs.append(np.log(m.scale / length))
    assert abs(np.median(logs)) < 0.1, np.exp(logs) - 1


def test_fused_candidates_equal_the_generic_path() -> None:
    """A camera's compiled projection (the hyperboloid's) gives, in the one-pass
    candidates (:func:`_candidate_patches`), the same matches bit for bit as
    translating, projecting and sampling each candidate through the camera's public
    ``project`` (the path of a model without one)."""
    from unittest import mock

    from omnipipe.image import gray_without_laser

    scenario = make_scenario("paper", frames=12, size=(640, 480), seed=4)
    renderer, poses, _, moving = build_renderer(scenario)
    b = int(np.flatnonzero(moving)[2])
    img_a, img_b, ring, b_from_a, length = _pair(renderer, poses, b - 2, b)
    # Points off the wall too (some candidates leave the mirror's annulus or the image).
    rng = np.random.default_rng(5)
    ring = np.vstack([ring, ring[:20] * rng.uniform(0.2, 3.0, (20, 1))])
    args = (
        gray_without_laser(img_a, "red"), gray_without_laser(img_b, "red"), renderer.camera, ring,
        b_from_a[:3, :3], b_from_a[:3, 3] / length,
    )
    fused = match_laser_points(*args)
    assert renderer.camera.compiled_projection() is not None
    # Without a compiled projection the generic path runs (as for a model that has none).
    with mock.patch.object(renderer.camera, "compiled_projection", lambda: None):
        generic = match_laser_points(*args)
    assert len(fused.index) > 20
    for name in ("index", "scale_mm", "pixels_b", "ncc", "peak_scales_mm", "peak_scores"):
        assert np.array_equal(getattr(fused, name), getattr(generic, name), equal_nan=True), name
    assert fused.scale == generic.scale


def _same(m1, m2) -> bool:
    """Every field of two LaserMatches equal, bit for bit."""
    return all(
        np.array_equal(np.asarray(getattr(m1, f)), np.asarray(getattr(m2, f)), equal_nan=True)
        for f in ("index", "scale_mm", "pixels_b", "ncc", "scale", "peak_scales_mm", "peak_scores")
    )


def test_search_near_an_expected_length_stands_or_is_the_full_search(paper_800) -> None:
    """A keyframe step's laser searched near the feature-depth length: the window's answer
    stands when it agrees with that length and its consensus peaks inside the window;
    an expected length the laser does not confirm (or none) gets the full search, bit for
    bit."""
    from omnipipe.sfm.laser_scale import LaserScaleConfig, match_laser_points_near

    scenario, renderer, poses, moving = paper_800
    a, b = 0, int(np.flatnonzero(moving)[: scenario.motion.frames_per_cycle // scenario.motion.n_units][-1])
    img_a, img_b, ring, b_from_a, length = _pair(renderer, poses, a, b)
    args = (
        img_a[..., 1].astype(np.float32), img_b[..., 1].astype(np.float32), renderer.camera,
        ring, b_from_a[:3, :3], b_from_a[:3, 3] / length,
    )
    cfg = LaserScaleConfig()
    full = match_laser_points(*args, cfg)
    near, windowed = match_laser_points_near(*args, cfg, 1.05 * length, 0.12)
    assert windowed
    assert abs(near.scale / length - 1.0) < 0.01, (near.scale, length)
    assert abs(near.scale / full.scale - 1.0) < 0.002, (near.scale, full.scale)
    assert len(near.index) >= 0.9 * len(full.index)
    assert len(near.peak_scales_mm) >= 1 and abs(near.peak_scales_mm[0] / length - 1) < 0.1
    # 40 % off: inside the window, but the laser does not confirm it -> the full search.
    off, windowed = match_laser_points_near(*args, cfg, 1.4 * length, 0.12)
    assert not windowed and _same(off, full)
    for expected in (np.nan, 0.0, 1e6):
        m, windowed = match_laser_points_near(*args, cfg, expected, 0.12)
        assert not windowed and _same(m, full)
    m, windowed = match_laser_points_near(*args, LaserScaleConfig(prior_window_log=0.0), length, 0.12)
    assert not windowed and _same(m, full)

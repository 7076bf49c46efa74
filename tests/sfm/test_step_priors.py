"""The wall's own shift as the bundle adjustment's step-length priors (sfm.step_priors,
sfm.bundle's prior rows), on seeded synthetic walls rendered through the camera model and
a seeded bundle problem: the truth is the travel the images and points were made with."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_shift_scale import _run
from test_wall_shift import _context

from omnipipe.camera import OmniCamera
from omnipipe.geometry import apply, invert
from omnipipe.sfm.bundle import BundleConfig, BundleProblem, LengthPrior, bundle_adjust, set_priors
from omnipipe.sfm.scale_check import StepCheck
from omnipipe.sfm.step_priors import bridged_priors, wall_priors
from omnipipe.sfm.types import Keyframes
from omnipipe.sim.scenario import paper_rig


def _unevenly_shortened(world_from_kf: np.ndarray, gains: list[float]) -> np.ndarray:
    """The poses with step k's length times ``gains[k]`` (an adjustment that shortened
    some steps and not others)."""
    z = np.diff(world_from_kf[:, 2, 3]) * np.array(gains)
    out = world_from_kf.copy()
    out[1:, 2, 3] = np.cumsum(z)
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_steps_the_adjustment_shortened_get_the_wall_s_length_within_its_sigma(
    small_camera: OmniCamera, seed: int
) -> None:
    kf, world_from_kf, checks, true = _run(small_camera, seed, 1.0)
    # Steps 1 and 3 12 % short (random-wide seed 32: 10-18 %), the others right.
    moved = _unevenly_shortened(world_from_kf, [1.0, 0.88, 1.0, 0.88, 1.0])
    got = wall_priors(_context(small_camera), kf, moved, checks)
    priors = got.priors
    assert len(priors) >= 4 and len(got.readings) == len(true)
    for p in priors:
        assert p.b == p.a + 1
        assert abs(p.length_mm - true[p.a]) <= 2 * p.sigma_mm, (p, true[p.a])
        assert p.sigma_mm <= 0.05 * true[p.a]
    assert {1, 3} <= {p.a for p in priors}


@pytest.mark.parametrize("gain", [1.0, 0.95])
def test_a_run_the_wall_agrees_with_is_left_alone(small_camera: OmniCamera, gain: float) -> None:
    # Every step right, or every step 5 % short (the run's scale: run_length's to
    # combine, not the steps' to move).
    kf, world_from_kf, checks, _ = _run(small_camera, 2, gain)
    got = wall_priors(_context(small_camera), kf, world_from_kf, checks)
    assert got.priors == () and len(got.readings) == 5  # the readings kept for shift_scale


def test_the_adjustment_follows_step_priors_where_nothing_else_fixes_the_scale(bundle_problem) -> None:
    camera, problem = bundle_problem(5, 1)
    true = problem.world_from_rig.copy()
    lengths = np.linalg.norm(np.diff(true[:, :3, 3], axis=0), axis=1)
    # No laser anchors (the scale is free), a start 10 % short.
    for name in ("anchor_a", "anchor_b"):
        setattr(problem, name, np.zeros(0, int))
    problem.anchor_points_in_a, problem.anchor_pixels_b = np.zeros((0, 3)), np.zeros((0, 2))
    start = true.copy()
    start[:, :3, 3] *= 0.9
    problem.world_from_rig = start
    problem.points_in_world = problem.points_in_world * 0.9
    rng = np.random.default_rng(5)
    sigma = 0.02 * lengths
    measured = lengths + rng.normal(0, 1, len(lengths)) * sigma
    set_priors(problem, [LengthPrior(k, k + 1, float(measured[k]), float(sigma[k])) for k in range(len(lengths))])
    got = bundle_adjust(camera, problem, BundleConfig(solver="trf", max_evaluations=100))
    adjusted = np.linalg.norm(np.diff(got.world_from_rig[:, :3, 3], axis=0), axis=1)
    # The run's length is the priors' (their mean's sigma: 2 % / sqrt(4)).
    assert abs(math.log(adjusted.sum() / lengths.sum())) <= 2 * 0.02 / math.sqrt(len(lengths))
    assert np.all(np.abs(adjusted - lengths) <= 2 * sigma)


@pytest.mark.parametrize(("gain", "held"), [(0.95, True), (1.0, False)])
def test_a_run_too_short_for_a_run_wide_ratio_is_held_where_the_wall_disagrees(
    small_camera: OmniCamera, gain: float, held: bool
) -> None:
    # Two steps (shift_scale needs 4: the wall has no other say on this run's scale),
    # both 5 % short (random-wide seed 24: one step, 6 % short), or both right.
    kf, world_from_kf, checks, true = _run(small_camera, 3, gain)
    kf = Keyframes(kf.frames[:3], [], kf.grays[:3], kf.ring_points[:3], kf.evidence[:2])
    got = wall_priors(_context(small_camera), kf, world_from_kf[:3], checks[:2])
    assert bool(got.priors) == held
    for p in got.priors:
        assert abs(p.length_mm - true[p.a]) <= 2 * p.sigma_mm


def _check(bridged_mm: float = math.nan, sigma_mm: float = math.nan, source: str = "") -> StepCheck:
    """A flagged step's check, bridged from ``source`` when given."""
    return StepCheck(0, 1, math.nan, 0.0, math.nan, 0, math.nan, "none", "relative motion not found",
                     (), bridged_mm, sigma_mm, source)


def test_bridged_steps_become_priors_but_where_the_wall_was_read() -> None:
    checks = [_check(10.5, 0.8, "odometry"), _check(), _check(7.2, 2.5, "gait"), _check(9.0, 0.8, "odometry"),
              _check(0.0, 0.8, "odometry")]
    got = bridged_priors(checks)
    assert [(p.a, p.b, p.length_mm, p.sigma_mm) for p in got] == [(0, 1, 10.5, 0.8), (2, 3, 7.2, 2.5), (3, 4, 9.0, 0.8)]
    assert [p.a for p in bridged_priors(checks, {2})] == [0, 3]


def test_a_bridged_step_without_anchors_is_held_to_its_estimate(pipe_scene) -> None:
    """Keyframe step 0 -> 1 has no laser anchor and only 12 tracks into keyframe 0, and
    those were matched on a wall 3 mm further (random-features seed 26: a bridged step's
    few matches pulled it 30-90 % off while the others' anchors held them): without a
    prior the adjustment follows them, with the step's bridged length (the true 12 mm,
    1-sigma 0.5) as a prior it stays within 1 sigma; the anchored steps stay right either way."""
    rng = np.random.default_rng(26)
    camera = OmniCamera.from_rig(paper_rig(800, 600))
    poses, th, pts = pipe_scene(rng, 5, 0.005, 0.5, 600, (-200.0, 150.0))
    shifted = poses.copy()
    shifted[0, 2, 3] -= 3.0  # keyframe 0's tracks seen from 3 mm further back
    f, p, px = [], [], []
    for k in range(5):
        seen = np.arange(len(pts)) if k else rng.choice(len(pts), 12, replace=False)
        uv, ok = camera.project(apply(invert(shifted[k]), pts[seen]))
        f += [k] * int(ok.sum())
        p += list(seen[ok])
        px.append(uv[ok] + rng.normal(0, 0.3, (int(ok.sum()), 2)))
    q_a = np.column_stack([101 * np.cos(th[:60]), 101 * np.sin(th[:60]), np.full(60, -82.0)])
    aa, ab, aq, apx = [], [], [], []
    for k in range(1, 4):  # no anchor on step 0
        uv, ok = camera.project(apply(invert(poses[k + 1]) @ poses[k], q_a))
        aa += [k] * int(ok.sum())
        ab += [k + 1] * int(ok.sum())
        aq.append(q_a[ok])
        apx.append(uv[ok] + rng.normal(0, 0.3, (int(ok.sum()), 2)))
    lengths = {}
    for held in (False, True):
        problem = BundleProblem(poses.copy(), pts.copy(), np.array(f), np.array(p), np.concatenate(px),
                                np.array(aa), np.array(ab), np.concatenate(aq), np.concatenate(apx))
        set_priors(problem, [LengthPrior(0, 1, 12.0, 0.5)] if held else [])
        res = bundle_adjust(camera, problem, BundleConfig(max_evaluations=100))
        lengths[held] = np.linalg.norm(np.diff(res.world_from_rig[:, :3, 3], axis=0), axis=1)
    assert abs(lengths[False][0] - 12.0) > 2.0, lengths  # the few tracks' wall (15.0 mm)
    assert abs(lengths[True][0] - 12.0) < 0.5, lengths
    for held in (False, True):
        assert np.all(np.abs(lengths[held][1:] - 12.0) < 0.3), lengths

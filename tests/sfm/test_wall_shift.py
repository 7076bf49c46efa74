"""The unrolled wall's axial shift (sfm.wall_shift) and its use in deciding a step
(sfm.step_scale.resolve_by_wall), on seeded synthetic walls rendered through the camera
model: the truth is the shift the images were rendered with."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from omnipipe.camera import OmniCamera
from omnipipe.executor import InlineExecutor
from omnipipe.sfm.ransac import RansacConfig
from omnipipe.sfm.scale_check import StepCheck, wall_cylinder
from omnipipe.sfm.step_scale import DecidedStep, RunScale, resolve_by_wall
from omnipipe.sfm.types import Keyframes, SfmConfig, SfmContext, StepEvidence
from omnipipe.sfm.wall_shift import candidate_window, step_wall_length, wall_shift

RADIUS = 101.0  # mm, the paper rig's 202 mm pipe
RING_Z = -82.0  # mm, the ring plane's rig z (the paper rig's baseline)


def _bricks(rng: np.random.Generator, period: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """A brick wall: courses ``period`` mm high along z, bricks 2.5 periods long around
    the wall (every other course offset by half a brick), a random tone per brick and a
    faint grain (:func:`_faint`) over it, dark mortar lines; (z, s) mm -> brightness (s:
    arc length)."""
    tones = rng.uniform(0.5, 1.0, (400, 400))
    grain = _faint(rng)
    length = 2.5 * period

    def f(z: np.ndarray, s: np.ndarray) -> np.ndarray:
        row = np.floor(z / period).astype(int)
        col = np.floor(s / length + 0.5 * (row % 2)).astype(int)
        zf, sf = z / period - row, s / length + 0.5 * (row % 2) - col
        mortar = (np.minimum(zf, 1 - zf) < 0.06) | (np.minimum(sf, 1 - sf) < 0.03)
        return np.where(mortar, 0.3, tones[row % 400, col % 400] * grain(z, s))

    return f


def _faint(rng: np.random.Generator) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """A faint wall: smooth random tone (sum of random cosines, 4-20 mm scales), +-10 %."""
    k = rng.uniform(2 * np.pi / 20, 2 * np.pi / 4, (24, 2)) * rng.choice([-1, 1], (24, 2))
    ph = rng.uniform(0, 2 * np.pi, 24)

    def f(z: np.ndarray, s: np.ndarray) -> np.ndarray:
        v = sum(np.cos(k[i, 0] * z + k[i, 1] * s + ph[i]) for i in range(24)) / 24
        return 0.8 * (1 + 0.4 * v)

    return f


def _render(
    camera: OmniCamera, wall: Callable[[np.ndarray, np.ndarray], np.ndarray], z_mm: float, offset_xy: tuple[float, float], roll: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """(H, W) grey image of the wall seen from a rig at axial position ``z_mm``, off the
    axis by ``offset_xy`` mm and rolled by ``roll`` rad; the rig's light falls off with
    distance (a rig-fixed shading) and the sensor adds noise."""
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    px = np.column_stack([cols.ravel(), rows.ravel()]).astype(float)
    ray = camera.unproject(px)
    ok = np.isfinite(ray).all(axis=1)
    r = np.where(ok[:, None], ray, [[1.0, 0.0, 0.0]])
    c, s = math.cos(roll), math.sin(roll)
    r = r @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]).T  # rig -> pipe frame
    o = np.array(offset_xy)
    a = r[:, 0] ** 2 + r[:, 1] ** 2
    b = 2 * (o[0] * r[:, 0] + o[1] * r[:, 1])
    t = (-b + np.sqrt(b * b - 4 * a * (o @ o - RADIUS**2))) / (2 * a)
    p = o + t[:, None] * r[:, :2]
    z = z_mm + t * r[:, 2]
    arc = RADIUS * np.mod(np.arctan2(p[:, 1], p[:, 0]), 2 * np.pi)
    light = 1.0 / (1.0 + (t / 150.0) ** 2)
    img = 200 * wall(z, arc) * light + rng.normal(0, 2.0, len(t))
    img = np.where(ok & (t < 2000), img, 0.0)
    return np.clip(img, 0, 255).reshape(camera.height, camera.width).astype(np.float32)


def _ring(offset_xy: tuple[float, float]) -> np.ndarray:
    """(N, 3) laser ring points of a rig off the axis by ``offset_xy`` (rig frame, mm)."""
    th = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    return np.column_stack(
        [RADIUS * np.cos(th) - offset_xy[0], RADIUS * np.sin(th) - offset_xy[1], np.full(360, RING_Z)]
    )


def _forward() -> np.ndarray:
    """rig_b_from_rig_a of a rig that moved along +z (unit translation, no rotation)."""
    m = np.eye(4)
    m[2, 3] = -1.0
    return m


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_wall_s_shift_and_its_sigma_cover_the_true_step(small_camera: OmniCamera, seed: int) -> None:
    rng = np.random.default_rng(seed)
    wall = _bricks(rng, rng.uniform(10, 30)) if seed % 2 else _faint(rng)
    step = rng.uniform(3.0, 15.0)
    off_a, off_b = tuple(rng.normal(0, 2, 2)), tuple(rng.normal(0, 2, 2))
    img_a = _render(small_camera, wall, 0.0, off_a, 0.0, rng)
    img_b = _render(small_camera, wall, step, off_b, rng.normal(0, 0.005), rng)
    got = wall_shift(
        small_camera, img_a, img_b, wall_cylinder(_ring(off_a)), wall_cylinder(_ring(off_b)),
        (0.5 * step, 1.6 * step),
    )
    assert got.measured, got.reason
    assert abs(got.shift_mm - step) <= 2 * got.sigma_mm, (got, step)
    assert got.sigma_mm <= 0.05 * step + 0.3  # a reading, not a shrug


def test_a_faint_wall_s_rig_fixed_shading_does_not_pull_the_shift_to_zero(small_camera: OmniCamera) -> None:
    rng = np.random.default_rng(7)
    wall = _faint(rng)
    img_a = _render(small_camera, wall, 0.0, (0.0, 0.0), 0.0, rng)
    img_b = _render(small_camera, wall, 6.0, (0.0, 0.0), 0.0, rng)
    walls = (wall_cylinder(_ring((0, 0))), wall_cylinder(_ring((0, 0))))
    got = step_wall_length(small_camera, (img_a, img_b), walls, _forward(), (0.5, 12.0))
    assert got.measured
    assert got.length_mm == pytest.approx(6.0, abs=max(2 * got.sigma_mm, 0.1))


def test_no_texture_gives_no_reading(small_camera: OmniCamera) -> None:
    rng = np.random.default_rng(3)
    plain = lambda z, s: np.full(np.shape(z), 0.8)  # noqa: E731
    img_a = _render(small_camera, plain, 0.0, (0, 0), 0.0, rng)
    img_b = _render(small_camera, plain, 5.0, (0, 0), 0.0, rng)
    w = wall_cylinder(_ring((0, 0)))
    got = wall_shift(small_camera, img_a, img_b, w, w, (1.0, 10.0))
    assert not got.measured


def _context(camera: OmniCamera) -> SfmContext:
    return SfmContext(SfmConfig(), camera, RansacConfig(), InlineExecutor(), False, [])


def _one_step(
    camera: OmniCamera, period: float, step: float, peaks: tuple[float, ...], feature: float, seed: int
) -> tuple[SfmContext, Keyframes, list[DecidedStep], np.ndarray]:
    """One flagged keyframe step of ``step`` mm on a brick wall of course ``period`` mm:
    its laser peaks and feature-depth length as given (NaN: none)."""
    rng = np.random.default_rng(seed)
    wall = _bricks(rng, period)
    grays = [_render(camera, wall, 0.0, (0, 0), 0.0, rng), _render(camera, wall, step, (0, 0), 0.0, rng)]
    ev = StepEvidence(0, 4, _forward(), None, None, np.zeros(0), feature, 40, "ok")
    check = StepCheck(0, 4, peaks[0], 0.95, feature, 40, math.nan, "none", "ambiguous laser scale", peaks)
    kf = Keyframes([0, 4], [], grays, [_ring((0, 0)), _ring((0, 0))], [ev])
    return _context(camera), kf, [DecidedStep(ev.b_from_a, math.nan, None, None, check)], np.array([math.nan])


def test_a_one_period_alias_on_a_periodic_wall_is_not_chosen(small_camera: OmniCamera) -> None:
    # Courses 15 mm apart, a 5 mm step: the laser's best peak is a course long (20 mm),
    # its second the right one; the wall's shift decides.
    ctx, kf, decided, lengths = _one_step(small_camera, 15.0, 5.0, (20.0, 5.05), math.nan, 11)
    resolve_by_wall(ctx, kf, decided, lengths, RunScale(0.0, False), np.array([4]))
    assert decided[0].check.confidence == "resolved", decided[0].check.reason
    assert lengths[0] == pytest.approx(5.0, abs=0.15)
    assert "wall's own shift" in decided[0].check.reason


def test_the_wall_withdraws_a_laser_peak_chosen_on_the_wrong_course(small_camera: OmniCamera) -> None:
    ctx, kf, decided, lengths = _one_step(small_camera, 15.0, 5.0, (20.0, 5.05), math.nan, 12)
    c = decided[0].check
    wrong = StepCheck(
        0, 4, 35.0, 0.9, 19.0, 40, 20.0, "resolved",
        "laser peak 20.0 mm chosen over 35.0 mm: it agrees with the feature depth scale 19.0 mm",
        (35.0, 20.0),
    )
    decided[0] = DecidedStep(decided[0].b_from_a, 20.0, None, None, wrong)
    lengths[0] = 20.0
    resolve_by_wall(ctx, kf, decided, lengths, RunScale(0.0, False), np.array([4]))
    assert c.first_frame == 0
    assert "disagrees" in decided[0].check.reason
    # Withdrawn, then the wall's own length (the one clear peak) or no length: never 20.
    assert not (decided[0].check.reliable and abs(lengths[0] - 20.0) < 1.0)
    if decided[0].check.reliable:
        assert lengths[0] == pytest.approx(5.0, abs=0.15)


def test_the_window_spans_the_candidates() -> None:
    assert candidate_window([4.0, math.nan, 10.0, -1.0]) == (2.0, 16.0)
    assert all(math.isnan(v) for v in candidate_window([]))


@pytest.mark.parametrize(("counted_mm", "resolved"), [(5.1, True), (8.0, False)])
def test_with_odometry_the_wall_resolves_only_what_the_odometry_confirms(
    small_camera: OmniCamera, counted_mm: float, resolved: bool
) -> None:
    """The alias step above with the robot's odometry: counting 5.1 mm (2 % slip) it
    confirms the wall's 5 mm, which resolves the step; counting 8 mm (a reading 10
    sigma off the wall's) nothing is resolved: the step stays flagged (and is bridged)."""
    from omnipipe.inputs.sensors import make_odometry
    from omnipipe.sfm.robot_sensors import odometry_steps

    ctx, kf, decided, lengths = _one_step(small_camera, 15.0, 5.0, (20.0, 5.05), math.nan, 11)
    times = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    counted = np.linspace(0.0, counted_mm, 5)
    odo = make_odometry("test", times, counted, np.hypot(0.03 * counted, 0.05), str)
    steps = odometry_steps(odo, times, [0, 4])
    resolve_by_wall(ctx, kf, decided, lengths, RunScale(0.0, False), np.array([4]), steps)
    assert (decided[0].check.confidence == "resolved") == resolved, decided[0].check.reason
    if resolved:
        assert lengths[0] == pytest.approx(5.0, abs=0.15)
    else:
        assert math.isnan(lengths[0])


def test_frames_at_rest_read_no_shift_whatever_the_window(small_camera: OmniCamera) -> None:
    """The view's rim (rig-fixed) band-passes to rows of far more energy than a faint
    wall's, whose correlation is flat in the shift: whichever part of it the window's
    template held pulled the reading (random-wide seed 10: -0.84 to -0.14 mm at rest).
    Kept off the rim, frames at rest read zero within their sigma for every window."""
    rng = np.random.default_rng(11)
    k = rng.uniform(2 * np.pi / 20, 2 * np.pi / 4, (24, 2)) * rng.choice([-1, 1], (24, 2))
    ph = rng.uniform(0, 2 * np.pi, 24)

    def faint(z: np.ndarray, s: np.ndarray) -> np.ndarray:
        return 0.8 * (1 + 0.04 * sum(np.cos(k[i, 0] * z + k[i, 1] * s + ph[i]) for i in range(24)) / 24)

    img_a = _render(small_camera, faint, 0.0, (0.0, 0.0), 0.0, rng)
    img_b = _render(small_camera, faint, 0.0, (0.0, 0.0), 0.0, rng)
    w = wall_cylinder(_ring((0, 0)))
    windows = ((-2.0, 6.0), (-4.0, 4.0), (-6.0, 2.0))
    trimmed = [wall_shift(small_camera, img_a, img_b, w, w, win, 0.1, True) for win in windows]
    untrimmed = [wall_shift(small_camera, img_a, img_b, w, w, win, 0.1) for win in windows]
    for r in trimmed:
        assert r.measured, r.reason
        assert abs(r.shift_mm) <= 2 * r.sigma_mm, r
    spread = lambda rs: max(r.shift_mm for r in rs) - min(r.shift_mm for r in rs)  # noqa: E731
    assert spread(trimmed) < 0.5 * spread(untrimmed)


def test_a_trusted_step_whose_laser_was_set_aside_is_decided_by_the_wall(small_camera: OmniCamera) -> None:
    """A ``high`` step whose laser (9.0 mm) and feature depths (10.2 mm, 2 % long)
    differ by more than anchor_agree_log (random-wide seed 3s: 26.6 and 29.7 mm for
    30.3): decide_step took the feature length without anchors. The wall's own shift (10 mm true) confirms the
    feature depths and excludes the laser: the step is resolved, its reason says why."""
    ctx, kf, decided, lengths = _one_step(small_camera, 15.0, 10.0, (9.0,), 10.2, 11)
    high = StepCheck(0, 4, 9.0, 0.2, 10.2, 400, 9.0, "high", "", (9.0,))
    decided[0] = DecidedStep(decided[0].b_from_a, 10.2, None, None, high)
    lengths[0] = 10.2
    resolve_by_wall(ctx, kf, decided, lengths, RunScale(0.0, False), np.array([4]))
    c = decided[0].check
    assert c.confidence == "resolved", c.reason
    assert c.reason.startswith("laser 9.0 mm and feature depth 10.2 mm lengths differ by -12 %")
    assert "the feature depth length agrees with the wall's own shift" in c.reason
    assert lengths[0] == pytest.approx(10.0, abs=0.4)


def test_a_high_step_whose_sources_agree_closely_is_not_read(small_camera: OmniCamera) -> None:
    ctx, kf, decided, lengths = _one_step(small_camera, 15.0, 10.0, (10.1,), 10.3, 11)
    high = StepCheck(0, 4, 10.1, 0.2, 10.3, 400, 10.1, "high", "", (10.1,))
    decided[0] = DecidedStep(decided[0].b_from_a, 10.1, None, None, high)
    lengths[0] = 10.1
    resolve_by_wall(ctx, kf, decided, lengths, RunScale(0.0, False), np.array([4]))
    assert decided[0].check == high and lengths[0] == 10.1


def test_the_odometry_and_the_wall_agreeing_measure_a_bridged_step(small_camera: OmniCamera) -> None:
    """No vision candidate near the 5 mm step (laser peaks 20 and 35 mm, no feature
    depths): with the odometry counting 5.1 mm the wall's reading is returned, and once
    the step is bridged from the odometry the two measure it: resolved (not flagged),
    their inverse-variance mean within its sigma of the truth, still bridged (its frames
    follow the travel). Counting 8 mm: nothing returned, the step stays flagged."""
    from omnipipe.inputs.sensors import make_odometry
    from omnipipe.sfm.robot_sensors import odometry_steps
    from omnipipe.sfm.step_chain import bridge_steps
    from omnipipe.sfm.wall_resolve import wall_confirms_bridged

    for counted_mm, measured in ((5.1, True), (8.0, False)):
        ctx, kf, decided, lengths = _one_step(small_camera, 15.0, 5.0, (7.5, 2.5), math.nan, 11)
        times = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
        counted = np.linspace(0.0, counted_mm, 5)
        odo = make_odometry("test", times, counted, np.hypot(0.03 * counted, 0.05), str)
        steps = odometry_steps(odo, times, [0, 4])
        agreed = resolve_by_wall(ctx, kf, decided, lengths, RunScale(0.0, False), np.array([4]), steps)
        assert (0 in agreed) == measured
        assert not decided[0].check.reliable and math.isnan(lengths[0])
        lengths, checks, _ = bridge_steps(lengths, [d.check for d in decided], steps)
        wall_confirms_bridged(ctx, checks, lengths, agreed)
        c = checks[0]
        assert c.bridged_from == "odometry"
        assert c.reliable == measured, c.reason
        if measured:
            assert c.bridged_sigma_mm < min(agreed[0][1], math.hypot(0.03 * 5.1, 0.07))
            assert abs(c.bridged_mm - 5.0) <= 2 * c.bridged_sigma_mm
            assert lengths[0] == c.bridged_mm
            assert "measured: the wall's shift" in c.reason

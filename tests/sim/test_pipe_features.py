"""Features of real pipes: rays meet joints, ovality, tapers, water and laterals where the
ground truth says; the laser ring lies where the scene puts it; scenarios are deterministic."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from scipy.optimize import brentq

from omnipipe.errors import ConfigError
from omnipipe.geometry import apply, rotate
from omnipipe.sim import make_scenario, paper_rig
from omnipipe.sim.feature_scenarios import clock_to_angle_deg
from omnipipe.sim.features import Joint, Lateral, Ovality, PipeFeatures, Taper, Water
from omnipipe.sim.motion import simulate_trajectory
from omnipipe.sim.render import SURFACE_WALL, SURFACE_WATER, RenderConfig, Renderer
from omnipipe.sim.scene import Pipe
from omnipipe.sim.texture import TextureConfig, WallTexture
from omnipipe.sim.writer import build_renderer, scene_description


def _renderer(pipe: Pipe) -> Renderer:
    """A 200x150 paper rig in ``pipe`` with a coarse texture (geometry tests only)."""
    tex = WallTexture(math.pi * pipe.inner_diameter_mm, (-200, 900), 1, TextureConfig(texel_mm=4.0))
    return Renderer(paper_rig(200, 150), pipe, tex)


def _radial_rays(n: int) -> tuple[np.ndarray, np.ndarray]:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return a, np.stack([np.cos(a), np.sin(a), np.zeros(n)], axis=1)


def test_joint_gap_and_offset_radii() -> None:
    # Gap 8 mm wide, 10 mm deep at 200 mm; the next section displaced 5 mm towards +y.
    pipe = Pipe(300.0, features=PipeFeatures(joints=(Joint(200.0, 8.0, 10.0, 5.0, 90.0),)))
    r = _renderer(pipe)
    a, rays = _radial_rays(72)
    shifted = 5.0 * np.sin(a) + np.sqrt(150.0**2 - 25.0 * np.cos(a) ** 2)
    for z, expected in ((180.0, 150.0), (197.0, 160.0), (203.0, shifted + 10.0), (220.0, shifted)):
        t, _ = r.intersect(np.array([0.0, 0.0, z]), rays)
        np.testing.assert_allclose(t, expected, atol=1e-6, err_msg=f"z = {z}")
    # Half-depth extent of the gap along the axis is the gap width.
    plain = Pipe(300.0, features=PipeFeatures(joints=(Joint(200.0, 8.0, 10.0),)))
    s = np.linspace(190, 210, 20001)
    deep = s[plain.wall_radius(s, np.full_like(s, np.pi)) >= 155.0]
    assert deep.max() - deep.min() == pytest.approx(8.0, abs=2e-3)


def test_ovality_and_taper_radii() -> None:
    ov = Ovality(100.0, 400.0, 6.0, angle_deg=30.0, blend_mm=40.0)
    pipe = Pipe(300.0, features=PipeFeatures(ovalities=(ov,), tapers=(Taper(500.0, 600.0, 200.0),)))
    r = _renderer(pipe)
    a, rays = _radial_rays(90)
    t, _ = r.intersect(np.array([0.0, 0.0, 250.0]), rays)
    np.testing.assert_allclose(t, 150.0 * (1 + 0.03 * np.cos(2 * (a - np.radians(30)))), atol=1e-6)
    t, _ = r.intersect(np.array([0.0, 0.0, 100.0]), rays)  # half-way through the blend
    np.testing.assert_allclose(t, 150.0 * (1 + 0.015 * np.cos(2 * (a - np.radians(30)))), atol=1e-6)
    for z, radius in ((450.0, 150.0), (550.0, 125.0), (700.0, 100.0)):
        t, _ = r.intersect(np.array([0.0, 0.0, z]), rays)
        np.testing.assert_allclose(t, radius, atol=1e-6)
    table = pipe.section_table(np.array([250.0, 550.0]))
    assert table[0, 0] - table[0, 1] == pytest.approx(0.06 * 300.0, rel=1e-3)
    assert np.degrees(table[0, 2]) == pytest.approx(30.0, abs=0.5)
    assert table[1, 0] == pytest.approx(250.0) and table[1, 1] == pytest.approx(250.0)


def _brute_first_hit(pipe: Pipe, o: np.ndarray, d: np.ndarray, step: float = 0.05) -> float:
    ts = np.arange(1.0, 1500.0, step)
    s, rho, th, *_ = pipe.pipe_coordinates(o + ts[:, None] * d)
    k = np.flatnonzero(rho - pipe.wall_radius(s, th) > 0)
    return float(ts[k[0]])


def test_oblique_rays_meet_the_first_wall_crossing() -> None:
    """Rays of a real frame agree with a fine march along each ray (0.05 mm steps)."""
    sc = make_scenario("sewer-small", frames=12)
    pipe = Pipe(300.0, features=replace_water(sc.pipe.features), defects=[])
    renderer = _renderer(pipe)
    poses, _, _ = simulate_trajectory(pipe, sc.motion, 12, 0)
    rng = np.random.default_rng(4)
    errors = []
    for pose in poses[[0, 6, 11]]:
        rays = rotate(pose, renderer.rays_in_rig[~renderer.body])
        pick = rays[rng.choice(len(rays), 40, replace=False)]
        t, _ = renderer.intersect(pose[:3, 3], pick)
        errors += [abs(t[i] - _brute_first_hit(pipe, pose[:3, 3], pick[i])) for i in range(40)]
    errors = np.array(errors)
    assert np.quantile(errors, 0.98) <= 0.06 and np.median(errors) < 0.05


def replace_water(features: PipeFeatures) -> PipeFeatures:
    """The features without water and laterals: the main wall alone."""
    return PipeFeatures(features.joints, (), features.tapers, features.ovalities, None)


def test_water_hides_the_invert() -> None:
    pipe = Pipe(300.0, features=PipeFeatures(water=Water(40.0)))
    assert pipe.water_level() == pytest.approx(-110.0)
    r = _renderer(pipe)
    pose = np.eye(4)
    pose[2, 3] = 300.0
    hits = r.hit(pose, r.rays_in_rig[~r.body])
    water = hits.surface == SURFACE_WATER
    down = hits.points_in_world[:, 1] < -110.0 - 1e-6
    assert water.any() and not down.any()  # nothing below the surface is seen
    np.testing.assert_allclose(hits.points_in_world[water, 1], -110.0, atol=1e-9)
    # Rays pointing down steeply enough meet the water; the others the wall.
    _, rho, *_ = pipe.pipe_coordinates(hits.points_in_world[~water])
    np.testing.assert_allclose(rho, 150.0, atol=1e-6)
    image, truth = r.render(pose, seed=0, led=False, noise=False)
    mask = np.zeros(image.shape[0] * image.shape[1], np.uint8)
    mask[truth["index"][truth["surface"] == SURFACE_WATER]] = 1
    # Away from the water line (the optics blur the wall's ring 0.7 px): no laser return.
    inner = cv2.erode(mask.reshape(image.shape[:2]), np.ones((7, 7), np.uint8)).astype(bool)
    assert inner.sum() > 500 and image[inner, 0].max() == 0


def test_stripe_ends_at_the_water_line_as_a_sensor_integrates_it() -> None:
    # The rendered stripe, sampled along the image of the sheet's centre on the wall,
    # falls to half its lit height where that curve meets the water (the pixels the water
    # line crosses lit over their wall part only). Rendering them whole by their centre
    # ray, at the frame's median sheet gradient, put it 0.6-0.9 px off here.
    from scipy.ndimage import map_coordinates

    pipe = Pipe(300.0, features=PipeFeatures(water=Water(25.0)))
    tex = WallTexture(math.pi * 300.0, (-200, 900), 1, TextureConfig(texel_mm=4.0))
    r = Renderer(paper_rig(200, 150), pipe, tex, RenderConfig(speckle_contrast=0.0))
    ang = np.linspace(-math.pi, math.pi, 200001)
    z = -r.rig.laser.distance_mm
    pts = np.stack([150.0 * np.cos(ang), 150.0 * np.sin(ang), np.full_like(ang, z)], axis=1)
    px, _ = r.camera.project(pts)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(px, axis=0), axis=1))]
    ends = []
    for axial in (300.0, 317.3):
        pose = np.eye(4)
        pose[2, 3] = axial
        image, _ = r.irradiance(pose, seed=0, led=False)
        val = map_coordinates(image[..., 0], [px[:, 1], px[:, 0]], order=1)
        height = apply(pose, pts)[:, 1] - pipe.water_level()
        for j in np.flatnonzero(np.sign(height[:-1]) != np.sign(height[1:])):
            s = (arc - arc[j]) * (1 if height[j + 1] < 0 else -1)  # px along, + into the water
            o = np.argsort(s)
            s, v = s[o], val[o]
            plateau = np.median(v[(s > -6.0) & (s < -2.5)])
            k = np.flatnonzero((s > -2.5) & (v < 0.5 * plateau))[0]
            ends.append(s[k - 1] + (v[k - 1] - 0.5 * plateau) / (v[k - 1] - v[k]) * (s[k] - s[k - 1]))
    assert len(ends) == 4
    np.testing.assert_array_less(np.abs(ends), 0.3)


def test_lateral_hole_shows_the_branch_wall() -> None:
    lat = Lateral(300.0, 30.0, 100.0, branch_angle_deg=60.0)
    pipe = Pipe(300.0, features=PipeFeatures(laterals=(lat,)))
    r = _renderer(pipe)
    origin, axis, _, radius, _ = pipe.lateral_frame(0)
    e = np.array([math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0])
    hole_centre = np.array([0.0, 0.0, 300.0]) + 150.0 * e
    np.testing.assert_allclose(origin + (150.0 / math.sin(math.radians(60))) * axis, hole_centre)
    pose = np.eye(4)
    pose[2, 3] = 420.0
    o = pose[:3, 3]
    # A ray through the hole's centre meets the branch wall, radius 50 mm from its axis.
    through = (hole_centre - o) / np.linalg.norm(hole_centre - o)
    away = np.array([-e[0], -e[1], 0.0])  # the opposite wall: no hole there
    hits = r.hit(pose, np.stack([through, away]))
    assert hits.surface[0] == 1 and hits.surface[1] == SURFACE_WALL
    v = hits.points_in_world[0] - origin
    assert np.linalg.norm(v - (v @ axis) * axis) == pytest.approx(radius, abs=1e-6)
    assert np.linalg.norm(hits.points_in_world[0] - o) > np.linalg.norm(hole_centre - o)
    assert np.hypot(*hits.points_in_world[1, :2]) == pytest.approx(150.0, abs=1e-6)


def _ring_point(renderer: Renderer, pose: np.ndarray, angle: float) -> np.ndarray:
    """The main wall's point in the laser plane at ``angle`` around the rig axis (rig frame)."""
    z = -renderer.rig.laser.distance_mm
    d = np.array([math.cos(angle), math.sin(angle), 0.0])
    pipe = renderer.pipe

    def g(r: float) -> float:
        s, rho, th, *_ = pipe.pipe_coordinates(apply(pose, (np.array([0, 0, z]) + r * d)[None]))
        return float(rho[0] - pipe.wall_radius(s, th)[0])

    return np.array([0.0, 0.0, z]) + brentq(g, 1.0, 1000.0, xtol=1e-9) * d


def test_laser_ring_where_the_scene_puts_it_and_cut_off_under_water() -> None:
    sc = make_scenario("sewer-small", frames=12, seed=2)
    renderer, poses, _, _ = build_renderer(sc)
    pose = poses[9]
    image, _ = renderer.render(pose, seed=3, led=False, noise=False)
    red = image[..., 0].astype(float)
    cam = renderer.camera
    level = renderer.pipe.water_level()
    up = renderer.pipe.up()
    found, dry, wet_max = 0, 0, 0.0
    for a in np.linspace(0, 2 * np.pi, 72, endpoint=False):
        p_rig = _ring_point(renderer, pose, a)
        px, valid = cam.project(p_rig[None])
        assert valid[0]
        u = (px[0] - [cam.cx, cam.cy]) / np.linalg.norm(px[0] - [cam.cx, cam.cy])
        offs = np.arange(-4, 5)
        xy = np.round(px[0][None] + offs[:, None] * u).astype(int)
        prof = red[xy[:, 1], xy[:, 0]]
        if apply(pose, p_rig[None])[0] @ up < level - 2.0:  # under water: no ring
            wet_max = max(wet_max, float(prof.max()))
            continue
        dry += 1
        found += abs(offs[int(np.argmax(prof))]) <= 1 and prof.max() > 20
    assert dry >= 50 and found >= dry - 6  # a few angles fall in the lateral's hole or a gap
    assert wet_max < 5.0


def test_feature_scenarios_deterministic_and_described() -> None:
    a = make_scenario("random-features", seed=11)
    b = make_scenario("random-features", seed=11)
    c = make_scenario("random-features-small", seed=11)
    assert a.pipe == b.pipe == c.pipe and a.random == b.random
    assert make_scenario("random-features", seed=12).pipe != a.pipe
    # The random family's own draws are untouched by the features' stream.
    base = make_scenario("random", seed=11).random
    assert {k: v for k, v in a.random.items() if k != "features"} == base
    kinds = set()
    for seed in range(30):
        kinds |= set(make_scenario("random-features", seed=seed).random["features"]["kinds"])
    assert kinds == {"joints", "lateral", "ovality", "taper", "water"}
    with pytest.raises(ConfigError, match="seed"):
        make_scenario("random-features", seed=-1)


def test_random_feature_laterals_lie_inside_the_lengthened_sweep() -> None:
    # Laterals of the class (>= 0.2 D) and a few smaller ones, each beyond the
    # other features' window; the short run is lengthened until its laser ring (the
    # baseline behind the rig) sweeps the whole hole; runs without one keep 24 frames.
    big = small = 0
    for seed in range(16):
        sc = make_scenario("random-features-small", seed=seed)
        lo, hi = sc.random["features"]["window_mm"]
        if not sc.pipe.features.laterals:
            assert sc.frames == 24
            continue
        (v,) = sc.pipe.features.laterals
        half = 0.5 * v.diameter_mm / math.sin(math.radians(v.branch_angle_deg))
        assert v.axial_mm - half >= hi + 15.0 - 1e-9
        _, sigma, _ = simulate_trajectory(sc.pipe, sc.motion, sc.frames, sc.seed)
        ring = sigma - sc.rig.laser.distance_mm
        assert ring[0] <= lo and ring[-1] >= v.axial_mm + half
        assert sc.random["features"]["frames"] == sc.frames > 24
        big += v.diameter_mm >= 0.2 * sc.pipe.inner_diameter_mm
        small += v.diameter_mm < 0.2 * sc.pipe.inner_diameter_mm
        # An explicit frame count is kept (the scene's features unchanged).
        short = make_scenario("random-features-small", seed=seed, frames=24)
        assert short.frames == 24 and short.pipe == sc.pipe
    assert big >= 5 and small >= 1


def test_sewer_scene_json_in_the_contract_convention() -> None:
    sc = make_scenario("sewer-small", frames=6)
    poses, sigma, moving = simulate_trajectory(sc.pipe, sc.motion, sc.frames, sc.seed)
    scene = scene_description(sc, poses, sigma, moving)
    s0 = sigma[0]
    assert scene["gravity"] == [0.0, -1.0, 0.0]
    by_kind: dict[str, list[dict]] = {}
    for f in scene["features"]:
        by_kind.setdefault(f["kind"], []).append(f)
    joints = by_kind["joint"]
    assert [j["axial_mm"] for j in joints] == pytest.approx([140 - s0, 290 - s0, 380 - s0])
    assert joints[0]["gap_mm"] == 8.0 and joints[1]["offset_mm"] == 5.0
    assert joints[1]["offset_clock_deg"] == pytest.approx(90.0)  # 3:00
    lat = by_kind["lateral"][0]
    assert lat["clock_deg"] == pytest.approx(300.0) and lat["diameter_mm"] == 100.0
    offset = scene["first_frame_angle_offset_deg"]
    assert lat["angle_deg"] == pytest.approx((clock_to_angle_deg(300.0) - offset) % 360)
    assert by_kind["ovality"][0]["percent"] == 4.0 and by_kind["water"][0]["depth_mm"] == 40.0
    rows = {round(r["axial_mm"] + s0): r for r in scene["stations"]}
    assert rows[100]["water_depth_mm"] == pytest.approx(40.0, abs=0.01)
    assert rows[100]["inner_diameter_mm"] == pytest.approx(300.0)
    mid = rows[330]  # inside the 4 % ovality (horizontal major axis): the invert rises 3 mm
    assert mid["ovality_pct"] == pytest.approx(4.0, abs=0.01)
    assert mid["inner_diameter_mm"] == pytest.approx(300.0, abs=0.01)
    assert mid["water_depth_mm"] == pytest.approx(37.0, abs=0.01)
    assert Pipe.from_dict(json.loads(json.dumps(scene["pipe"]))) == sc.pipe


def test_invalid_features_are_named() -> None:
    with pytest.raises(ConfigError, match=r"joint\.gap_mm"):
        Joint(0.0, 0.0)
    with pytest.raises(ConfigError, match=r"lateral\.branch_angle_deg"):
        Lateral(0.0, 0.0, 50.0, branch_angle_deg=5.0)
    with pytest.raises(ConfigError, match=r"laterals\[0\]\.diameter_mm"):
        Pipe(100.0, features=PipeFeatures(laterals=(Lateral(0.0, 0.0, 90.0),)))
    with pytest.raises(ConfigError, match=r"ovality\.percent"):
        Ovality(0.0, 100.0, 60.0)
    with pytest.raises(ConfigError, match=r"features\.tapers"):
        PipeFeatures(tapers=(Taper(0.0, 100.0, 90.0), Taper(50.0, 150.0, 80.0)))


def test_tight_elbow_rays_meet_the_first_wall_crossing() -> None:
    """A 90 deg elbow of radius 1.5 D: cast rays agree with a fine march (0.05 mm steps)."""
    sc = make_scenario("elbow-small", frames=24)
    pipe = sc.pipe
    assert pipe.centreline.bend_radius_mm == pytest.approx(1.5 * pipe.inner_diameter_mm)
    renderer = _renderer(pipe)
    poses, sigma, _ = simulate_trajectory(
        pipe, replace(sc.motion, start_mm=250.0, stroke_mm=40.0, frames_per_cycle=1), 24, 0
    )
    assert sigma[-1] > 260.0 + 300.0 * math.pi / 2  # the last frames are past the elbow
    rng = np.random.default_rng(5)
    errors = []
    for pose in poses[[0, 6, 12, 23]]:
        rays = rotate(pose, renderer.rays_in_rig[~renderer.body])
        pick = rays[rng.choice(len(rays), 30, replace=False)]
        t, _ = renderer.intersect(pose[:3, 3], pick)
        errors += [abs(t[i] - _brute_first_hit(pipe, pose[:3, 3], pick[i])) for i in range(30)]
    assert max(errors) <= 0.06


def test_laser_lights_the_branch_wall_through_the_hole() -> None:
    sc = make_scenario("sewer", size=(400, 300), frames=40)
    renderer, poses, sigma, _ = build_renderer(sc)
    k = int(np.argmin(np.abs(sigma - 310.0)))  # the laser sheet crosses the hole
    image, truth = renderer.render(poses[k], seed=2, led=False, noise=False)
    on_sheet = (truth["surface"] == 1) & (np.abs(truth["laser_h"]) < 1.0)
    assert on_sheet.sum() >= 5
    red = image.reshape(-1, 3)[truth["index"][on_sheet], 0]
    assert np.median(red) > 40
    # The branch wall away from the sheet (3 px from any lit pixel: the optics' blur)
    # stays dark without the LEDs.
    near = np.zeros(image.shape[0] * image.shape[1], np.uint8)
    near[truth["index"][np.abs(truth["laser_h"]) < 2.0]] = 1
    near = cv2.dilate(near.reshape(image.shape[:2]), np.ones((7, 7), np.uint8)).ravel()
    off_sheet = (truth["surface"] == 1) & (near[truth["index"]] == 0)
    assert off_sheet.sum() > 50
    assert image.reshape(-1, 3)[truth["index"][off_sheet], 0].max() < 3


@pytest.mark.parametrize("joints", [(), (Joint(145.25, 7.93, 8.14),)])
def test_rays_past_a_reducer_meet_its_narrow_wall(joints) -> None:
    """Past a 195.75 -> 164.16 mm reducer (random-features seed 18, with and without its
    joint at the ramp's start) every ray meets the narrow section's wall: the ray
    casting's bracket began on that wall itself and the rings there were drawn at up to
    93.4 mm radius (187 mm read for 164)."""
    pipe = Pipe(195.75, features=PipeFeatures(joints=joints, tapers=(Taper(142.3, 196.0, 164.16),)), defects=[])
    r = _renderer(pipe)
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 0.0, 400.0]
    hits = r.hit(pose, r.rays_in_rig[~r.body])
    _, rho, *_ = pipe.pipe_coordinates(hits.points_in_world)
    past = hits.sigma > 200.0
    assert past.sum() > 1000
    np.testing.assert_allclose(rho[past], 82.08, atol=1e-3)

"""Running a scenario: trajectory, renderer, frames, and the contract dataset on disk."""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from omnipipe.dataset import write_image, write_tum
from omnipipe.executor import open_executor, ordered_map
from omnipipe.output import atomic_output_dir
from omnipipe.rig_yaml import save_rig
from omnipipe.sim.motion import simulate_trajectory
from omnipipe.sim.render import Renderer
from omnipipe.sim.scenario import Scenario
from omnipipe.sim.scene import Pipe
from omnipipe.sim.sensors import simulate_sensors, write_sensor_files
from omnipipe.sim.texture import WallTexture


@dataclass
class SimResult:
    """What a simulation run produced.

    Attributes:
        out_dir: the dataset directory (None for in-memory runs).
        world_from_rig: (N, 4, 4) true poses (mm).
        sigma_mm: (N,) centreline station of each frame (mm).
        moving: (N,) True where the rig moved since the previous frame.
        scene: the scene.json content.
    """

    out_dir: Path | None
    world_from_rig: np.ndarray
    sigma_mm: np.ndarray
    moving: np.ndarray
    scene: dict


def build_renderer(scenario: Scenario) -> tuple[Renderer, np.ndarray, np.ndarray, np.ndarray]:
    """Trajectory and renderer of a scenario: (renderer, world_from_rig, sigma, moving)."""
    poses, sigma, moving = simulate_trajectory(
        scenario.pipe, scenario.motion, scenario.frames, scenario.seed
    )
    # Texture covers what any frame can see: from behind the robot to well ahead of it.
    lo = float(sigma.min()) - 400.0
    hi = float(sigma.max()) + 600.0
    tex_cfg = scenario.texture
    # Texels finer than a quarter of the finest pixel footprint add nothing but time:
    # the paper rig's finest footprint is about 0.2 mm/px at 1600 px width.
    auto_texel = 0.2 * 1600.0 / scenario.rig.camera.width
    if tex_cfg.texel_mm < 0.5 * auto_texel:
        tex_cfg = replace(tex_cfg, texel_mm=min(0.5 * auto_texel, 2.0))
    texture = WallTexture(
        math.pi * scenario.pipe.inner_diameter_mm, (lo, hi), scenario.seed + 1, tex_cfg
    )
    return Renderer(scenario.rig, scenario.pipe, texture, scenario.render), poses, sigma, moving


def render_sequence(scenario: Scenario) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Yield (index, RGB uint8 frame, world_from_rig) for every frame, in memory."""
    renderer, poses, _, _ = build_renderer(scenario)
    for i, pose in enumerate(poses):
        frame, _ = renderer.render(pose, seed=_frame_seed(scenario.seed, i))
        yield i, frame, pose


def _frame_seed(seed: int, index: int, dark: bool = False) -> int:
    return int(np.random.SeedSequence([seed, index, int(dark)]).generate_state(1)[0])


def scene_description(
    scenario: Scenario, poses: np.ndarray, sigma: np.ndarray, moving: np.ndarray
) -> dict:
    """scene.json: the true pipe, run and defects in the contract's report convention."""
    pipe = scenario.pipe
    # Contract convention: axial positions from the first frame's station along the
    # centreline; angles around the axis from the first rig frame's x axis towards y.
    s0 = float(sigma[0])
    _, normal, binormal, tangent = pipe.frame_at(np.array([s0]))
    x0 = poses[0][:3, 0]
    x0 = x0 - (x0 @ tangent[0]) * tangent[0]
    angle0 = math.degrees(math.atan2(x0 @ binormal[0], x0 @ normal[0]))
    defects = [
        {
            "kind": d.kind,
            "height_mm": d.height_mm,
            "width_mm": d.width_mm,
            "length_mm": d.length_mm,
            "axial_start_mm": d.axial_start_mm - s0,
            "angle_deg": (d.angle_deg - angle0) % 360.0,
        }
        for d in pipe.defects
    ]
    samples = np.linspace(float(sigma.min()) - 300.0, float(sigma.max()) + 500.0, 120)
    centre, *_ = pipe.frame_at(samples)
    return {
        "generator": "omnipipe.sim",
        "scenario": scenario.name,
        "seed": scenario.seed,
        "frames": scenario.frames,
        "inner_diameter_mm": pipe.inner_diameter_mm,
        "pipe": pipe.to_dict(),
        "defects": defects,
        "conventions": {
            "defects": "contract convention: axial_start_mm from the first frame's station along the "
            "centreline, angle_deg around the axis from the first rig frame's x axis towards y",
            "pipe.defects": "pipe convention: axial_start_mm is centreline arc length from sigma=0, "
            "angle_deg from the transported normal N (world +x at sigma=0) towards B",
            "features": "contract convention as defects; *clock_deg from 12:00 (against gravity), "
            "clockwise looking downstream; pipe.features holds them in the pipe convention",
        },
        "first_station_sigma_mm": s0,
        "first_frame_angle_offset_deg": angle0,
        "station_sigma_mm": [round(float(s), 6) for s in sigma],
        "moving": [bool(m) for m in moving],
        "centreline_polyline_mm": {
            "sigma": samples.round(3).tolist(),
            "points": centre.round(4).tolist(),
        },
        "motion": asdict(scenario.motion),
        "render": asdict(scenario.render),
        "texture": asdict(scenario.texture),
        **({"random": scenario.random} if scenario.random is not None else {}),
        **feature_description(scenario, poses, sigma),
    }


STATION_STEP_MM = 5.0


def _clock_deg(pipe: Pipe, sigma: float, theta_rad: float) -> float | None:
    """Clock position (deg, 0 = 12:00, clockwise looking downstream) of a pipe angle at
    ``sigma``; None where the axis is vertical."""
    _, n, b, t = pipe.frame_at(np.array([sigma]))
    up = pipe.up()
    up_p = up - (up @ t[0]) * t[0]
    if np.linalg.norm(up_p) < 1e-6:
        return None
    up_p /= np.linalg.norm(up_p)
    e = math.cos(theta_rad) * n[0] + math.sin(theta_rad) * b[0]
    right = np.cross(t[0], up_p)
    return math.degrees(math.atan2(e @ right, e @ up_p)) % 360.0


def feature_description(scenario: Scenario, poses: np.ndarray, sigma: np.ndarray) -> dict:
    """scene.json's ``gravity``, ``features`` and ``stations`` in the contract's convention.

    ``features`` lists joints, laterals, the bend, tapers, ovality and water (the
    DATA_CONTRACT's "Real pipes" keys, plus ``clock_deg``-style keys from 12:00 and the
    simulator's own sizes); features longer than the simulated stretch (from 300 mm
    behind the first station to 500 mm past the last) are clipped to it. ``stations``
    samples the true cross-section every 5 mm over that stretch: mean, smallest and
    largest diameter, ovality and its direction, water depth (gaps and defects are
    not part of it: they are in ``features`` and ``defects``).
    """
    pipe = scenario.pipe
    s0 = float(sigma[0])
    _, normal, binormal, tangent = pipe.frame_at(np.array([s0]))
    x0 = poses[0][:3, 0] - (poses[0][:3, 0] @ tangent[0]) * tangent[0]
    angle0 = math.degrees(math.atan2(x0 @ binormal[0], x0 @ normal[0]))
    lo, hi = float(sigma.min()) - 300.0, float(sigma.max()) + 500.0

    def ang(deg: float, period: float = 360.0) -> float:
        return (deg - angle0) % period

    def clock(s: float, deg: float) -> float | None:
        return _clock_deg(pipe, s, math.radians(deg))

    out = _feature_entries(pipe, s0, lo, hi, ang, clock)
    feats = pipe.features
    g = np.asarray(feats.gravity, float)
    return {
        "gravity": g.tolist(),
        "gravity_in_first_rig_frame": (poses[0][:3, :3].T @ g).round(12).tolist(),
        "features": out,
        "stations": _station_truth(pipe, np.arange(lo, hi + 1e-9, STATION_STEP_MM), s0, ang),
    }


def _feature_entries(
    pipe: Pipe, s0: float, lo: float, hi: float, ang: Callable, clock: Callable
) -> list[dict]:
    """scene.json's ``features`` (see :func:`feature_description`)."""
    feats = pipe.features
    out: list[dict] = []
    for j in feats.joints:
        out.append(
            {
                "kind": "joint",
                "axial_mm": j.axial_mm - s0,
                "gap_mm": j.gap_mm,
                "offset_mm": j.offset_mm,
                "offset_angle_deg": ang(j.offset_angle_deg),
                "offset_clock_deg": clock(j.axial_mm, j.offset_angle_deg),
                "depth_mm": j.depth_mm,
            }
        )
    for v in feats.laterals:
        out.append(
            {
                "kind": "lateral",
                "axial_mm": v.axial_mm - s0,
                "angle_deg": ang(v.angle_deg),
                "clock_deg": clock(v.axial_mm, v.angle_deg),
                "diameter_mm": v.diameter_mm,
                "branch_angle_deg": v.branch_angle_deg,
                "length_mm": v.length_mm,
            }
        )
    out.extend(_bend_and_taper_entries(pipe, s0, ang))
    out.extend(_ovality_and_water_entries(pipe, s0, lo, hi, ang))
    return out


def _bend_and_taper_entries(pipe: Pipe, s0: float, ang: Callable) -> list[dict]:
    """scene.json's ``bend`` and ``taper`` features (axial mm from the run's start ``s0``)."""
    feats = pipe.features
    out: list[dict] = []
    cl = pipe.centreline
    if cl.has_bend:
        arc = float(cl.bend_radius_mm) * math.radians(cl.bend_angle_deg)  # type: ignore[arg-type]
        out.append(
            {
                "kind": "bend",
                "axial_from_mm": cl.straight_mm - s0,
                "axial_to_mm": cl.straight_mm + arc - s0,
                "radius_mm": cl.bend_radius_mm,
                "turn_deg": cl.bend_angle_deg,
                "direction_deg": ang(cl.bend_direction_deg),
            }
        )
    for t in feats.tapers:
        out.append(
            {
                "kind": "taper",
                "axial_from_mm": t.axial_from_mm - s0,
                "axial_to_mm": t.axial_to_mm - s0,
                "diameter_from_mm": 2.0
                * float(pipe.nominal_radius(np.array([t.axial_from_mm]))[0]),
                "diameter_to_mm": t.diameter_to_mm,
            }
        )
    return out


def _ovality_and_water_entries(
    pipe: Pipe, s0: float, lo: float, hi: float, ang: Callable
) -> list[dict]:
    """scene.json's ``ovality`` and ``water`` features, clipped to the run [lo, hi] (mm)."""
    feats = pipe.features
    out: list[dict] = []
    ovals = [
        (o.axial_from_mm, o.axial_to_mm, o.percent, o.angle_deg, o.blend_mm)
        for o in feats.ovalities
    ]
    if pipe.ovality:
        ovals.append((lo, hi, 100.0 * pipe.ovality, pipe.ovality_angle_deg, 0.0))
    for a, b, pct, deg, blend in ovals:
        out.append(
            {
                "kind": "ovality",
                "axial_from_mm": max(a, lo) - s0,
                "axial_to_mm": min(b, hi) - s0,
                "percent": pct,
                "angle_deg": ang(deg, 180.0),
                "blend_mm": blend,
            }
        )
    if feats.water is not None:
        w = feats.water
        out.append(
            {
                "kind": "water",
                "axial_from_mm": max(w.axial_from_mm, lo) - s0,
                "axial_to_mm": min(w.axial_to_mm, hi) - s0,
                "depth_mm": w.depth_mm,
                "reference_axial_mm": w.reference_mm - s0,
            }
        )
    return out


def _station_truth(pipe: Pipe, grid: np.ndarray, s0: float, ang: Callable) -> list[dict]:
    """The true cross-section at arc lengths ``grid`` (see :func:`feature_description`)."""
    table = pipe.section_table(grid)
    level = pipe.water_level()
    water = pipe.features.water
    depth = np.zeros(len(grid))
    if level is not None and water is not None:
        wet = (grid >= water.axial_from_mm) & (grid <= water.axial_to_mm)
        depth[wet] = np.maximum(level - pipe.invert_height(grid[wet]), 0.0)
    rows = []
    for s, (dmax, dmin, amax), d in zip(grid, table, depth, strict=True):
        rows.append(
            {
                "axial_mm": round(float(s - s0), 6),
                "inner_diameter_mm": 0.5 * (dmax + dmin),
                "inner_diameter_min_mm": dmin,
                "inner_diameter_max_mm": dmax,
                "ovality_pct": 100.0 * (dmax - dmin) / (2.0 * float(pipe.nominal_radius(s)[0])),
                "ovality_angle_deg": ang(math.degrees(amax), 180.0) if dmax - dmin > 1e-9 else 0.0,
                "water_depth_mm": float(d),
            }
        )
    return rows


def run(
    scenario: Scenario,
    out_dir: str | Path,
    *,
    force: bool = False,
    workers: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> SimResult:
    """Render ``scenario`` into a contract dataset at ``out_dir``.

    The dataset is written to a temporary sibling directory and renamed into place
    when complete, so an interrupted run never leaves a dataset that looks whole; it
    carries omnipipe's manifest (:mod:`omnipipe.output`), and ``force`` replaces only
    such an earlier output.

    Raises:
        OutputError: ``out_dir`` exists and ``force`` is False, it is not omnipipe's
            output, or it cannot be written.
    """
    out = Path(out_dir)
    with atomic_output_dir(out, force=force) as tmp:
        renderer, poses, sigma, moving = build_renderer(scenario)
        (tmp / "frames").mkdir()
        (tmp / "ground_truth").mkdir()
        if scenario.dark_frames:
            (tmp / "frames_noled").mkdir()
        save_rig(scenario.rig, tmp / "rig.yaml")
        names = [f"{i:06d}.png" for i in range(scenario.frames)]
        stamps = np.arange(scenario.frames) / scenario.fps
        _render_all(renderer, scenario, poses, tmp, names, workers, progress)
        (tmp / "timestamps.txt").write_text(
            "".join(f"{n} {t:.6f}\n" for n, t in zip(names, stamps, strict=True)), encoding="utf-8"
        )
        write_tum(tmp / "ground_truth" / "poses.txt", stamps, poses)
        scene = scene_description(scenario, poses, sigma, moving)
        if scenario.sensors.odometry or scenario.sensors.imu:
            sensors = simulate_sensors(scenario, stamps, sigma, poses)
            write_sensor_files(tmp, sensors)
            scene["sensors"] = sensors.truth
        (tmp / "ground_truth" / "scene.json").write_text(
            json.dumps(scene, indent=1), encoding="utf-8"
        )
    return SimResult(out, poses, sigma, moving, scene)


def _stations(poses: np.ndarray) -> list[list[int]]:
    """Runs of consecutive frames with the same pose (the robot standing still)."""
    runs: list[list[int]] = []
    for i, pose in enumerate(poses):
        if runs and np.array_equal(poses[runs[-1][0]], pose):
            runs[-1].append(i)
        else:
            runs.append([i])
    return runs


def _render_station(args: tuple) -> int:
    """Render one station's frames: the irradiance once, the sensor noise per frame."""
    renderer, scenario, pose, path, indices = args
    first = indices[0]
    image, _ = renderer.irradiance(pose, seed=_frame_seed(scenario.seed, first))
    dark = None
    if scenario.dark_frames:
        dark, _ = renderer.irradiance(pose, seed=_frame_seed(scenario.seed, first, True), led=False)
    for index in indices:
        frame = renderer.expose(image, seed=_frame_seed(scenario.seed, index))
        write_image(path / "frames" / f"{index:06d}.png", frame)
        if dark is not None:
            frame = renderer.expose(dark, seed=_frame_seed(scenario.seed, index, True))
            write_image(path / "frames_noled" / f"{index:06d}.png", frame)
    return len(indices)


def _render_all(renderer, scenario, poses, tmp, names, workers, progress) -> None:
    """Render every station's frames into ``tmp`` on ``workers`` processes (forked: they
    take the renderer from :data:`_SHARED`, it is not pickled), ``progress(done, total)``
    after each station, in order.

    The pool is :func:`omnipipe.executor.open_executor`'s: when the run stops (an error,
    Ctrl-C, SIGTERM) its workers are killed (SIGKILL) at once, as every other command's.
    A ``multiprocessing.Pool`` ended by its ``with`` block (``terminate()``) sent them
    SIGTERM and joined them without a timeout, after taking its task queue's read lock
    (which an idle worker holds while it waits): a worker whose main thread did not get
    back to the interpreter to run its inherited handler (a long C call, a lock held by
    another thread at the fork) kept the simulator alive past the signal.
    """
    global _SHARED
    stations = _stations(poses)
    # Forked workers inherit the renderer; elsewhere the stations are rendered here.
    if not sys.platform.startswith("linux"):
        workers = 1
    done = 0
    _SHARED = (renderer, scenario, tmp)
    try:
        with open_executor(max(1, workers), tasks=len(stations)) as pool:
            items = ((poses[st[0]], st) for st in stations)
            for n in ordered_map(pool, _render_shared, items):
                done += n
                if progress:
                    progress(done, len(poses))
    finally:
        _SHARED = None


_SHARED: tuple | None = None


def _render_shared(item: tuple) -> int:
    renderer, scenario, tmp = _SHARED  # type: ignore[misc]
    pose, indices = item
    return _render_station((renderer, scenario, pose, tmp, indices))

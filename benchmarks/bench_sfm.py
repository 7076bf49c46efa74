"""Camera motion against ground truth on a simulated run: ATE, scale, rotation, speed.

Renders the scenario in memory, runs the light section and the SfM stage, aligns
the estimated trajectory to the true one (SE(3), no scale) and prints the errors.

Usage: python benchmarks/bench_sfm.py [--scenario paper] [--frames 100] [--size 1600x1200]
"""

from __future__ import annotations

import argparse
import time

from omnipipe.evaluation.trajectory import trajectory_errors
from omnipipe.laser import LaserConfig
from omnipipe.laser import run as laser_run
from omnipipe.sfm import SfmConfig, SfmInputs
from omnipipe.sfm import run as sfm_run
from omnipipe.sfm.bundle import BundleConfig
from omnipipe.sim import make_scenario
from omnipipe.sim.writer import build_renderer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenario", default="paper")
    parser.add_argument("--frames", type=int, default=None, help="default: the scenario's")
    parser.add_argument("--size", default=None, help="WxH (default: the scenario's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-bundle", action="store_true", help="pairwise chain only (no bundle adjustment)")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x")) if args.size else None
    scenario = make_scenario(args.scenario, frames=args.frames, size=size, seed=args.seed)
    renderer, poses, _, moving = build_renderer(scenario)
    t0 = time.perf_counter()
    frames, irradiance = [], None
    for i, p in enumerate(poses):
        if i == 0 or moving[i]:  # a standing robot sees the same scene: new sensor noise only
            irradiance = renderer.irradiance(p, seed=1000 + i)[0]
        frames.append(renderer.expose(irradiance, seed=1000 + i))
    t_render = time.perf_counter() - t0
    t0 = time.perf_counter()
    rings = laser_run(LaserConfig(), scenario.rig, frames)
    t_laser = time.perf_counter() - t0
    t0 = time.perf_counter()
    config = SfmConfig(bundle=BundleConfig(enabled=not args.no_bundle))
    res = sfm_run(config, SfmInputs(scenario.rig, lambda i: frames[i], len(frames), rings))
    t_sfm = time.perf_counter() - t0
    errs = trajectory_errors(res.world_from_rig, poses)
    cam = scenario.rig.camera
    print(
        f"scenario {scenario.name} {cam.width}x{cam.height}, {len(frames)} frames, "
        f"{int(res.keyframe.sum())} keyframes, {int(res.stationary.sum())} stationary "
        f"(true stationary: {int((~moving[1:]).sum())})"
    )
    print(
        f"path {errs.path_length_mm:.1f} mm: ATE {errs.ate_rmse_mm:.3f} mm RMS (max {errs.ate_max_mm:.3f}), "
        f"scale error {100 * errs.scale_error:.3f} %, rotation {errs.rotation_rmse_deg:.3f} deg RMS"
    )
    print(
        f"time: render {t_render:.1f} s, laser {t_laser:.1f} s, sfm {t_sfm:.1f} s "
        f"({len(frames) / t_sfm:.1f} frames/s)"
    )
    if res.bundle is not None:
        b = res.bundle
        print(
            f"bundle adjustment: {len(b.points_in_world)} tracks, reprojection RMS {b.rms_before_px:.2f} -> "
            f"{b.rms_after_px:.2f} px, laser anchors {b.anchor_rms_px:.2f} px, {b.evaluations} evaluations"
        )
    for w in res.warnings[:10]:
        print("warning:", w)


if __name__ == "__main__":
    main()

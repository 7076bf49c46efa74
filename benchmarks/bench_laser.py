"""Light-section accuracy and speed on simulated full-size frames (paper scenario).

Prints, per sensor noise level: RMS / bias of the radial error of the metric ring
points against the true wall, the fraction of scan lines recovered, and the same
for the points on the protuberance; then extraction + triangulation frames/s on one core.

Usage: python benchmarks/bench_laser.py [--frames 12] [--size 1600x1200]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2
import numpy as np

from omnipipe.camera import OmniCamera
from omnipipe.geometry import apply
from omnipipe.laser import LaserConfig, RingExtractor, run
from omnipipe.laser.triangulate import triangulate_ring
from omnipipe.sim import make_scenario
from omnipipe.sim.writer import build_renderer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--size", default="1600x1200")
    args = parser.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    base = make_scenario("paper", frames=100, size=(w, h), seed=7)
    # Frames spread over the run, including those whose laser crosses the bulge.
    idx = np.linspace(0, base.frames - 1, args.frames).round().astype(int)
    print(f"paper scenario {w}x{h}, {len(idx)} frames")
    print(
        f"{'read noise (DN)':>15s} {'full well (e-)':>14s} {'RMS (mm)':>9s} {'bias (mm)':>9s} {'recovered':>9s}"
        f" {'bulge RMS':>9s} {'bulge pts':>9s}"
    )
    frames_for_speed = None
    for read_noise, full_well in ((1.0, 8000.0), (3.0, 4000.0), (6.0, 2000.0)):
        scenario = replace(
            base, render=replace(base.render, read_noise_dn=read_noise, full_well_e=full_well)
        )
        renderer, poses, _, _ = build_renderer(scenario)
        frames = [renderer.render(poses[i], seed=int(i))[0] for i in idx]
        frames_for_speed = frames_for_speed or frames
        res = run(LaserConfig(), scenario.rig, frames)
        errs, bulge = [], []
        pipe = renderer.pipe
        d = pipe.defects[0]
        for i, ring in zip(idx, res.rings, strict=True):
            s, rho, th, *_ = pipe.pipe_coordinates(apply(poses[i], ring.points_in_rig))
            e = rho - pipe.wall_radius(s, th)
            errs.append(e)
            on = np.abs(pipe.defect_deviation(d, s, th)) > 0.5
            bulge.append(e[on])
        e = np.concatenate(errs)
        b = np.concatenate(bulge)
        b_rms = f"{np.sqrt(np.mean(b**2)):9.3f}" if len(b) else f"{'-':>9s}"
        print(
            f"{read_noise:15.1f} {full_well:14.0f} {np.sqrt(np.mean(e**2)):9.3f} {e.mean():+9.3f}"
            f" {res.recovered_fraction.mean():9.3f} {b_rms} {len(b):9d}"
        )
    cv2.setNumThreads(1)
    camera = OmniCamera.from_rig(base.rig)
    extractor = RingExtractor(camera)
    t0 = time.perf_counter()
    reps = 3
    for _ in range(reps):
        for f in frames_for_speed:
            triangulate_ring(extractor.extract(f, base.rig.laser.channel), camera, base.rig.laser)
    per = (time.perf_counter() - t0) / (reps * len(frames_for_speed))
    print(
        f"extraction + triangulation: {1000 * per:.1f} ms/frame = {1 / per:.0f} frames/s on one core"
    )


if __name__ == "__main__":
    main()

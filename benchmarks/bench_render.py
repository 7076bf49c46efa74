"""Simulator speed: frames rendered per second on one core, at full size.

Usage: python benchmarks/bench_render.py [--scenario paper] [--frames 5] [--size 1600x1200]
"""

from __future__ import annotations

import argparse
import os
import time

# One core: keep BLAS / OpenCV from using more threads than the measurement claims.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2

from omnipipe.sim import make_scenario
from omnipipe.sim.writer import build_renderer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenario", default="paper")
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--size", default="1600x1200")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    w, h = (int(v) for v in args.size.split("x"))
    scenario = make_scenario(args.scenario, frames=max(args.frames, 10), size=(w, h))
    t0 = time.perf_counter()
    renderer, poses, _, _ = build_renderer(scenario)
    setup = time.perf_counter() - t0
    times = []
    for i in range(args.frames):
        t = time.perf_counter()
        renderer.render(poses[i], seed=i)
        times.append(time.perf_counter() - t)
    per = sorted(times)[len(times) // 2]
    print(f"scenario {args.scenario} {w}x{h}: setup (texture, rays) {setup:.2f} s")
    print(
        f"render: median {per:.3f} s/frame = {1 / per:.2f} frames/s on one core (min {min(times):.3f} s)"
    )


if __name__ == "__main__":
    main()

"""``omnipipe simulate``: write a contract dataset of a named scenario."""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

from omnipipe import cli_values
from omnipipe.executor import check_workers
from omnipipe.output import prepare_output_dir
from omnipipe.progress import HonestBar
from omnipipe.sim.scenario import Scenario
from omnipipe.sim.scenarios import SCENARIOS, make_scenario
from omnipipe.sim.writer import run


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``simulate`` sub-command."""
    p = sub.add_parser(
        "simulate",
        help="render a simulated dataset (with ground truth) of a named scenario",
        description="Render what the rangefinder sees while the earthworm robot crawls through a "
        "pipe of known shape, and write it as a contract dataset with ground_truth/.",
    )
    p.add_argument(
        "--scenario",
        default="paper",
        choices=(*SCENARIOS, "calibration"),
        help="scene to simulate (default: paper); random draws pipe, wall, gait, rig and defects "
        "from --seed (docs/simulator.md)",
    )
    p.add_argument("--out", required=True, help="dataset directory to create")
    p.add_argument(
        "--frames",
        type=cli_values.whole("--frames", 1, 100_000),
        default=None,
        help="number of frames, 1-100000 (default: the scenario's)",
    )
    p.add_argument(
        "--size",
        type=cli_values.image_size(),
        default=None,
        metavar="WxH",
        help="image size, each side 16-8192 px (default: the scenario's)",
    )
    p.add_argument(
        "--seed",
        type=cli_values.seed(),
        default=0,
        help="random seed (texture, motion, noise; the whole scene of random)",
    )
    p.add_argument(
        "--dark-frames", action="store_true", help="also write LED-off frames to frames_noled/"
    )
    p.add_argument(
        "--workers",
        type=cli_values.workers(),
        default=None,
        metavar="N",
        help="render processes, 1 to 4 x the cores (default: every core; 1: serial)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an earlier omnipipe output in OUT (never a folder holding other files)",
    )
    p.add_argument(
        "--design",
        action="store_true",
        help="calibration scenario only: render the paper rig as designed, not a random rig",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_sensor_options(p)
    p.set_defaults(func=_main)


def _add_sensor_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--no-odometry", action="store_true", help="do not write the robot's odometry.txt"
    )
    p.add_argument("--no-imu", action="store_true", help="do not write the robot's imu.txt")


def _apply_sensor_options(scenario: Scenario, args: argparse.Namespace) -> None:
    scenario.sensors = replace(
        scenario.sensors, odometry=not args.no_odometry, imu=not args.no_imu
    )


def _main(args: argparse.Namespace) -> int:
    if args.scenario == "calibration":  # checkerboard views for calibrate (sim/calibration.py)
        from omnipipe.sim.calibration import simulate_main

        return simulate_main(args)
    scenario = make_scenario(args.scenario, frames=args.frames, size=args.size, seed=args.seed)
    scenario.dark_frames = bool(args.dark_frames)
    _apply_sensor_options(scenario, args)
    workers = check_workers(args.workers)  # None: every core
    prepare_output_dir(args.out, force=args.force)  # refuse before rendering, not after
    start = time.perf_counter()
    # Rate and ETA from the first frame on: the first carries the workers' start-up.
    bar = HonestBar(
        total=scenario.frames, desc="render", unit="frame", disable=args.quiet, smoothing=0
    )

    def progress(done: int, total: int) -> None:
        bar.update(done - bar.n)

    result = run(scenario, args.out, force=args.force, workers=workers, progress=progress)
    bar.close()
    elapsed = time.perf_counter() - start
    cam = scenario.rig.camera
    print(
        f"wrote {result.out_dir}: {scenario.frames} frames {cam.width}x{cam.height} of scenario "
        f"'{scenario.name}' in {elapsed:.1f} s (ground truth in ground_truth/)"
    )
    return 0

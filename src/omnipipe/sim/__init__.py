"""Simulator stage: contract datasets with ground truth, from a known pipe and robot run.

``run(scenario, out_dir)`` renders every frame and writes ``rig.yaml``, ``frames/``,
``timestamps.txt``, the robot's ``odometry.txt`` and ``imu.txt`` (sim/sensors.py) and
``ground_truth/{poses.txt, scene.json}``; the dataset appears
at ``out_dir`` only when complete. ``render_sequence`` gives the same frames in memory.
"""

from omnipipe.sim.motion import MotionConfig, simulate_trajectory
from omnipipe.sim.render import RenderConfig, Renderer
from omnipipe.sim.scenario import Scenario, paper_rig
from omnipipe.sim.scenarios import SCENARIOS, make_scenario
from omnipipe.sim.scene import Centreline, Defect, Pipe
from omnipipe.sim.texture import TextureConfig, WallTexture
from omnipipe.sim.writer import SimResult, build_renderer, render_sequence, run

__all__ = [
    "SCENARIOS",
    "Centreline",
    "Defect",
    "MotionConfig",
    "Pipe",
    "RenderConfig",
    "Renderer",
    "Scenario",
    "SimResult",
    "TextureConfig",
    "WallTexture",
    "build_renderer",
    "make_scenario",
    "paper_rig",
    "render_sequence",
    "run",
    "simulate_trajectory",
]

"""End to end: light section + camera motion on a short simulated stop-and-go run."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.evaluation.trajectory import trajectory_errors
from omnipipe.laser import LaserConfig
from omnipipe.laser import run as laser_run
from omnipipe.sfm.pipeline import SfmConfig, SfmInputs
from omnipipe.sfm.pipeline import run as sfm_run
from omnipipe.sim import make_scenario
from omnipipe.sim.writer import build_renderer


@pytest.mark.parametrize("name", ["paper", "bend"])
def test_short_run_trajectory_within_band(name: str) -> None:
    scenario = make_scenario(name, frames=20, size=(640, 480), seed=1)
    renderer, poses, _, moving = build_renderer(scenario)
    frames = [renderer.render(p, seed=50 + i)[0] for i, p in enumerate(poses)]
    rings = laser_run(LaserConfig(), scenario.rig, frames)
    res = sfm_run(SfmConfig(), SfmInputs(scenario.rig, lambda i: frames[i], len(frames), rings))
    assert np.all(np.isfinite(res.world_from_rig))
    # Stops are found: every truly stationary frame shares its station's pose.
    assert np.array_equal(res.stationary[1:], ~moving[1:])
    errs = trajectory_errors(res.world_from_rig, poses)
    print(name, errs.to_dict())
    assert errs.path_length_mm > 50
    assert errs.ate_rmse_mm < 1.0  # mm over ~60 mm of travel at 640x480
    assert errs.scale_error < 0.03
    assert errs.rotation_rmse_deg < 0.3

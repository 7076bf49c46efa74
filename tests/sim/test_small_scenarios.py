"""The -small scenarios measure their own defects whole (issue 31): each defect lies inside
the stretch of wall the short run's laser ring sweeps."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.geometry import apply
from omnipipe.sim import make_scenario, simulate_trajectory


@pytest.mark.parametrize("name", ["paper-small", "bend-small", "other-rig-small", "continuous-small"])
def test_small_scenarios_defects_lie_inside_the_rings_sweep(name: str) -> None:
    sc = make_scenario(name, seed=3)
    poses, _, _ = simulate_trajectory(sc.pipe, sc.motion, sc.frames, sc.seed)
    laser = sc.rig.laser
    n = laser.normal_in_rig
    # Where the laser plane crosses the rig's z axis (the ring's centre), in the world.
    on_axis = np.array([0.0, 0.0, -laser.offset_mm / n[2]])
    centres = np.array([apply(T, on_axis[None])[0] for T in poses])
    sigma = sc.pipe.pipe_coordinates(centres)[0]
    lo, hi = float(sigma.min()), float(sigma.max())
    assert sc.pipe.defects
    for d in sc.pipe.defects:
        start, end = d.axial_start_mm, d.axial_start_mm + d.length_mm
        assert lo + 2.0 <= start and end <= hi - 2.0, (name, lo, hi, start, end)

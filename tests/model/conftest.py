"""Shared references of the model-stage tests."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import cKDTree

from omnipipe.laser import LaserConfig, LaserResult
from omnipipe.laser import run as laser_run
from omnipipe.sim import make_scenario
from omnipipe.sim.render import Renderer
from omnipipe.sim.scenario import Scenario
from omnipipe.sim.writer import build_renderer


def _whole_wall_grid(
    arc: np.ndarray, axial: np.ndarray, pts: np.ndarray, circ: float, mm: float, gap: float
) -> np.ndarray:
    """(H, W, 3) wall grid of one interpolation over all points: the model stage before it
    went strip- and chunk-wise (arc wrapped by 10 % of ``circ`` each side; cells farther
    than ``gap`` mm from every point are NaN)."""
    margin = 0.1 * circ
    lo, hi = arc < margin, arc > circ - margin
    u = np.concatenate([arc, arc[lo] + circ, arc[hi] - circ])
    z = np.concatenate([axial, axial[lo], axial[hi]])
    xyz = np.concatenate([pts, pts[lo], pts[hi]])
    width = int(np.ceil(circ / mm))
    z0 = float(np.floor(axial.min()))
    height = int(np.ceil((axial.max() - z0) / mm)) + 1
    gu, gz = np.meshgrid((np.arange(width) + 0.5) * (circ / width), z0 + np.arange(height) * mm)
    grid = LinearNDInterpolator(np.column_stack([u, z]), xyz)(gu, gz)
    dist, _ = cKDTree(np.column_stack([u, z])).query(np.column_stack([gu.ravel(), gz.ravel()]))
    grid.reshape(-1, 3)[dist > gap] = np.nan
    return grid


@pytest.fixture
def whole_wall_grid() -> Callable[..., np.ndarray]:
    """``whole_wall_grid(arc, axial, pts, circ, mm, gap) -> (H, W, 3)`` (the reference)."""
    return _whole_wall_grid


@dataclass(frozen=True)
class RenderedStations:
    """One rendered frame per station of paper-small (24 frames, seed 2), true poses, and
    their laser rings (the model stage's inputs without the camera motion's errors).

    Attributes:
        scenario, renderer: the scene.
        poses: (F, 4, 4) every frame's true world_from_rig.
        keep: (K,) the stations' frames.
        frames: frame -> (H, W, 3) uint8 image of the stations' frames.
        rings: the laser stage's result on them.
    """

    scenario: Scenario
    renderer: Renderer
    poses: np.ndarray
    keep: np.ndarray
    frames: dict[int, np.ndarray]
    rings: LaserResult


@pytest.fixture(scope="session")
def rendered_stations() -> RenderedStations:
    """:class:`RenderedStations`, rendered once per session (read only)."""
    scenario = make_scenario("paper-small", frames=24, seed=2)
    renderer, poses, _, moving = build_renderer(scenario)
    keep = np.flatnonzero(np.r_[True, moving[1:]])  # one frame per station
    frames = {int(i): renderer.render(poses[i], seed=int(i))[0] for i in keep}
    rings = laser_run(LaserConfig(), scenario.rig, [frames[int(i)] for i in keep])
    return RenderedStations(scenario, renderer, poses, keep, frames, rings)

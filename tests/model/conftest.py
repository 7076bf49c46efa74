"""Shared references of the model-stage tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import cKDTree


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

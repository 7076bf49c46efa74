"""Stray wall points: an injected outlier is removed and leaves no mesh hole; a real
defect's points are all kept."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe import model
from omnipipe.config import dataclass_from_dict
from omnipipe.errors import ConfigError
from omnipipe.laser.extract import LaserRing
from omnipipe.model.outliers import OutlierConfig, reject_outliers, reject_ring_outliers
from omnipipe.sim.scene import plateau

RADIUS_MM = 101.0
LINES = 720  # scan lines per ring (the laser extractor's default)
STEP_MM = 2.0  # ring spacing along the pipe


def _rings(
    n_rings: int = 21, seed: int = 0, bulge: bool = True
) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Rings of a 202 mm pipe on the laser plane z = -82 (rig frame, identity poses
    STEP_MM apart), 0.05 mm noise, and the paper's bulge (5 mm high, 5 mm wide, rings
    5-15, at 90 deg): (points per ring, angles per ring, (K, N) bulge height, mm)."""
    rng = np.random.default_rng(seed)
    angles = np.arange(LINES) * (2 * np.pi / LINES)
    points, angle_list, heights = [], [], []
    for k in range(n_rings):
        h = np.zeros(LINES)
        if bulge:
            arc = (angles - np.pi / 2) * RADIUS_MM
            h = 5.0 * plateau(arc, 5.0, 2.0) * plateau(np.array(k * STEP_MM - 20.0), 20.0, 4.0)
        r = RADIUS_MM - h + rng.normal(0.0, 0.05, LINES)
        points.append(np.column_stack([r * np.cos(angles), r * np.sin(angles), np.full(LINES, -82.0)]))
        angle_list.append(angles.copy())
        heights.append(h)
    return points, angle_list, np.array(heights)


def test_injected_outlier_removed_and_defect_kept() -> None:
    points, angles, heights = _rings()
    stray = 10, 400  # ring, sample (200 deg): 37 mm outside the wall
    points[stray[0]][stray[1], :2] *= (RADIUS_MM + 37.0) / RADIUS_MM
    keep = reject_outliers(points, angles, OutlierConfig())
    assert not keep[stray[0]][stray[1]]
    assert sum(int((~k).sum()) for k in keep) == 1  # nothing else
    # Every point of the real defect is kept: it departs by up to 5 mm on 11 rings.
    on_defect = heights > 0.5
    assert on_defect.sum() > 40
    assert all(k[d].all() for k, d in zip(keep, on_defect, strict=True))


def test_short_defect_in_one_ring_is_a_surface_when_wide() -> None:
    """A departure of >= max_run + 1 samples in a single ring is a surface: kept."""
    points, angles, _ = _rings(bulge=False)
    points[10][100:104, :2] *= (RADIUS_MM - 4.0) / RADIUS_MM  # 4 samples, 4 mm inwards
    points[3][50:52, :2] *= (RADIUS_MM + 20.0) / RADIUS_MM  # 2 samples, 20 mm outwards
    keep = reject_outliers(points, angles, OutlierConfig())
    assert keep[10].all()
    assert np.flatnonzero(~keep[3]).tolist() == [50, 51]


def _boundary_vertices(faces: np.ndarray) -> np.ndarray:
    """Vertices on edges used by one triangle only (the mesh's borders and holes)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    key = e[:, 0].astype(np.int64) * (int(faces.max()) + 1) + e[:, 1]
    uniq, count = np.unique(key, return_counts=True)
    once = uniq[count == 1]
    return np.unique(np.concatenate([once // (int(faces.max()) + 1), once % (int(faces.max()) + 1)]))


def _mesh(points: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    poses = np.stack([np.eye(4) for _ in points])
    poses[:, 2, 3] = np.arange(len(points)) * STEP_MM
    pts, frame = model.integrate(poses, points)
    arc = np.arctan2(pts[:, 1], pts[:, 0]) % (2 * np.pi) * RADIUS_MM
    faces = model.mesh_unrolled(arc, pts[:, 2], pts, 2 * np.pi * RADIUS_MM, 2.0)
    return pts, frame, faces


def test_outlier_leaves_no_mesh_hole() -> None:
    points, angles, _ = _rings(n_rings=9, bulge=False)
    points[4][400, :2] *= (RADIUS_MM + 37.0) / RADIUS_MM
    _, frame, faces = _mesh(points)
    inner = frame[_boundary_vertices(faces)]
    # The unfiltered mesh has a hole around the stray point (borders inside the run).
    assert np.any((inner > 0) & (inner < len(points) - 1))
    rings = [
        LaserRing(np.zeros((LINES, 2)), a, np.ones(LINES), np.ones(LINES), points_in_rig=p,
                  sigma_mm=np.full(LINES, 0.05), scanned=LINES)
        for p, a in zip(points, angles, strict=True)
    ]
    clean, removed = reject_ring_outliers(rings)
    assert removed == 1 and len(clean[4].pixels) == LINES - 1 == len(clean[4].sigma_mm)
    _, frame, faces = _mesh([r.points_in_rig for r in clean])
    border = frame[_boundary_vertices(faces)]
    assert set(np.unique(border).tolist()) == {0, len(points) - 1}  # the run's two ends only


def test_bad_settings_are_named() -> None:
    with pytest.raises(ConfigError, match=r"outliers\.window"):
        OutlierConfig(window=40)
    with pytest.raises(ConfigError, match=r"outliers\.floor_mm"):
        dataclass_from_dict(OutlierConfig, {"floor_mm": 0.0}, "outliers")

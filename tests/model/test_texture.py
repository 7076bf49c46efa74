"""The texture's keyframe choice: scoring only each keyframe's visible rows changes nothing."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.camera import camera_from_rig
from omnipipe.camera.convert import rig_in_model
from omnipipe.model.texture import choose_sources, elevation_bounds, visible_rows
from omnipipe.rig import Rig
from omnipipe.sim import paper_rig

RADIUS_MM = 100.0
MM_PER_PX = 1.5


def _frame(s: np.ndarray, bend_mm: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Centreline point, tangent and two normals at arc lengths s (N,), mm: straight along z,
    or an arc of radius ``bend_mm`` in the xz plane."""
    if bend_mm is None:
        c = np.stack([np.zeros_like(s), np.zeros_like(s), s], axis=1)
        t = np.tile([0.0, 0.0, 1.0], (len(s), 1))
        n1 = np.tile([1.0, 0.0, 0.0], (len(s), 1))
    else:
        a = s / bend_mm
        c = np.stack([bend_mm * (1 - np.cos(a)), np.zeros_like(s), bend_mm * np.sin(a)], axis=1)
        t = np.stack([np.sin(a), np.zeros_like(s), np.cos(a)], axis=1)
        n1 = np.stack([np.cos(a), np.zeros_like(s), -np.sin(a)], axis=1)
    n2 = np.cross(t, n1)
    return c, t, n1, n2


def _pipe(length_mm: float, spacing_mm: float, bend_mm: float | None, seed: int = 0):
    """(H, W, 3) wall grid (rows: arc length, columns: angle; a hole of NaN) and (K, 4, 4)
    keyframe poses on the centreline (rig z along the tangent, jittered)."""
    rng = np.random.default_rng(seed)
    w = int(np.ceil(2 * np.pi * RADIUS_MM / MM_PER_PX))
    s = np.arange(int(length_mm / MM_PER_PX)) * MM_PER_PX
    theta = (np.arange(w) + 0.5) * (2 * np.pi / w)
    c, _, n1, n2 = _frame(s, bend_mm)
    radius = RADIUS_MM * (1 + 0.02 * np.sin(3 * theta))[None, :, None]
    grid = c[:, None] + radius * (
        np.cos(theta)[None, :, None] * n1[:, None] + np.sin(theta)[None, :, None] * n2[:, None]
    )
    grid[len(s) // 3 : len(s) // 3 + 10, w // 4 : w // 4 + 40] = np.nan  # a hole stays a hole
    sk = np.arange(0.0, length_mm, spacing_mm)
    ck, tk, nk1, nk2 = _frame(sk, bend_mm)
    poses = np.tile(np.eye(4), (len(sk), 1, 1))
    for k in range(len(sk)):
        a = rng.normal(scale=0.03, size=3)  # rad: a little tilt, as the robot wobbles
        kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        jitter = np.eye(3) + kx + 0.5 * kx @ kx
        jitter, _ = np.linalg.qr(jitter)
        poses[k, :3, :3] = np.stack([nk1[k], nk2[k], tk[k]], axis=1) @ jitter
        poses[k, :3, 3] = ck[k] + rng.normal(scale=3.0, size=3)
    return grid, poses


def _rig(model: str) -> Rig:
    rig = paper_rig(400, 300)
    return rig if model == "hyperboloid" else rig_in_model(rig, model)[0]


@pytest.mark.parametrize(
    ("bend_mm", "model", "narrow"),
    [
        (None, "hyperboloid", True),
        (1000.0, "hyperboloid", True),
        (1000.0, "unified", True),
        # A U-bend: keyframes see the far leg across it (occlusion is not modelled), so
        # windows may span the run; still the same choice.
        (300.0, "hyperboloid", False),
    ],
)
def test_windowed_scoring_equals_scoring_every_cell(
    bend_mm: float | None, model: str, narrow: bool
) -> None:
    rig = _rig(model)
    grid, poses = _pipe(600.0, 30.0, bend_mm)
    windowed = choose_sources(rig, poses, grid, MM_PER_PX, 3.0)
    full = choose_sources(rig, poses, grid, MM_PER_PX, 3.0, windowed=False)
    assert np.array_equal(windowed.cells, full.cells)
    assert np.array_equal(windowed.best, full.best)
    assert np.array_equal(windowed.best_px, full.best_px)
    assert np.mean(full.best >= 0) > 0.9  # the wall is seen, and holes are not cells
    if narrow:  # ... while each keyframe scored well under the whole run
        rows = visible_rows(camera_from_rig(rig), poses, grid)
        assert np.all(rows[:, 1] > rows[:, 0])
        assert np.mean(rows[:, 1] - rows[:, 0]) < 0.6 * grid.shape[0]


def test_the_window_does_not_grow_with_the_run() -> None:
    rig = _rig("hyperboloid")
    camera = camera_from_rig(rig)
    grid, poses = _pipe(600.0, 30.0, None)
    short = visible_rows(camera, poses, grid)
    grid, poses = _pipe(1200.0, 30.0, None)
    long = visible_rows(camera, poses, grid)
    tile_rows = 8
    assert np.max(long[:, 1] - long[:, 0]) <= np.max(short[:, 1] - short[:, 0]) + tile_rows
    # Every keyframe's window holds the rows of the wall it can see, about R tan(elevation)
    # behind and ahead of it (plus the tiles' looseness), not the run.
    lo, hi = elevation_bounds(camera)
    reach = RADIUS_MM * (np.tan(-lo) + np.tan(hi)) / MM_PER_PX
    assert np.max(long[:, 1] - long[:, 0]) < 1.5 * reach


def test_elevation_bounds_contain_the_cameras_range() -> None:
    for model in ("hyperboloid", "unified"):
        camera = camera_from_rig(_rig(model))
        lo, hi = elevation_bounds(camera)
        e_lo, e_hi = camera.elevation_range()
        assert lo <= e_lo and e_hi <= hi
        assert e_lo - lo < np.radians(2) and hi - e_hi < np.radians(2)

"""The texture's keyframe choice: scoring only each keyframe's visible rows, and a strip of
rows at a time, changes nothing."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.camera import camera_from_rig
from omnipipe.camera.convert import rig_in_model
from omnipipe.errors import ShapeError
from omnipipe.model.texture_grid import WallGrid, wall_points_on_grid
from omnipipe.model.texture_sources import (
    CellChoice,
    choose_sources,
    elevation_bounds,
    magnification_table,
    source_dtype,
    visible_rows,
)
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
    _assert_same_choice(windowed, full)
    wall = np.isfinite(grid).all(axis=2)
    assert np.mean(full.source[wall] >= 0) > 0.9  # the wall is seen
    assert np.all(full.source[~wall] == -1)  # and holes are not cells
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


def _assert_same_choice(a: CellChoice, b: CellChoice) -> None:
    assert a.source.dtype == b.source.dtype
    assert np.array_equal(a.source, b.source)
    assert np.array_equal(a.rows, b.rows)
    for k in range(len(a.pieces)):
        assert np.array_equal(a.cells(k), b.cells(k))
        assert np.array_equal(a.pixels(k), b.pixels(k))


def _old_choice(rig: Rig, poses: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) keyframe and (H, W, 2) pixel of each cell: every cell scored from every
    keyframe on the whole grid at once (the model stage before it went strip-wise)."""
    from omnipipe.geometry import apply, invert

    camera = camera_from_rig(rig)
    h, w = grid.shape[:2]
    flat = grid.reshape(-1, 3)
    idx = np.flatnonzero(np.isfinite(flat).all(axis=1))
    p = flat[idx]
    gp = np.where(np.isfinite(grid), grid, 0.0)
    step_u = np.gradient(gp, axis=1).reshape(-1, 3)[idx]
    step_z = np.gradient(gp, axis=0).reshape(-1, 3)[idx]
    best = np.full(len(idx), -1)
    best_score = np.zeros(len(idx))
    best_px = np.zeros((len(idx), 2), np.float32)
    for k, pose in enumerate(poses):
        m = invert(pose)
        q = apply(m, p)
        px, valid = camera.project(q)
        valid &= np.abs(q @ rig.laser.normal_in_rig + rig.laser.offset_mm) > 3.0
        px_u, _ = camera.project(q + step_u @ m[:3, :3].T)
        px_z, _ = camera.project(q + step_z @ m[:3, :3].T)
        a, b = px_u - px, px_z - px
        dist2 = np.maximum(np.sum(q * q, axis=1), 1e-6)
        score = np.sqrt(np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])) / MM_PER_PX / dist2
        score = np.where(valid & np.isfinite(score), score, 0.0)
        better = score > best_score
        best[better], best_score[better], best_px[better] = k, score[better], px[better]
    source = np.full(h * w, -1)
    source[idx] = best
    pixels = np.zeros((h * w, 2), np.float32)
    pixels[idx] = best_px
    return source.reshape(h, w), pixels.reshape(h, w, 2)


@pytest.mark.parametrize("bend_mm", [None, 300.0])
def test_strips_of_rows_give_the_whole_grid_choice(bend_mm: float | None) -> None:
    rig = _rig("hyperboloid")
    grid, poses = _pipe(310.0, 30.0, bend_mm, seed=1)
    h = grid.shape[0]
    assert h % 8  # a last strip of part of a tile
    one = choose_sources(rig, poses, grid, MM_PER_PX, 3.0, strip_rows=h)
    source, pixels = _old_choice(rig, poses, grid)
    assert np.array_equal(one.source, source)
    for k in range(len(poses)):
        cells = one.cells(k)
        assert np.array_equal(cells, np.flatnonzero(source.reshape(-1) == k))
        assert np.array_equal(one.pixels(k), pixels.reshape(-1, 2)[cells])
        if len(cells):  # the rows holding its cells, tightly
            assert one.rows[k, 0] == cells[0] // grid.shape[1]
            assert one.rows[k, 1] == cells[-1] // grid.shape[1] + 1
    small = choose_sources(rig, poses, grid, MM_PER_PX, 3.0, strip_rows=8)
    _assert_same_choice(small, one)
    assert max(len(p) for p in small.pieces) > 1  # a keyframe's cells span strips
    # 13 rows are rounded up to whole tiles (16); every cell from every keyframe.
    many = choose_sources(rig, poses, grid, MM_PER_PX, 3.0, strip_rows=13, windowed=False)
    _assert_same_choice(many, one)
    # Sections of rows (as the model stage textures them): each cell chosen as in the whole.
    w = grid.shape[1]
    for top in range(0, h, 24):
        end = min(top + 24, h)
        part = choose_sources(rig, poses, grid, MM_PER_PX, 3.0, strip_rows=8, rows=(top, end))
        assert np.array_equal(part.source, source[top:end])
        for k in range(len(poses)):
            cells = part.cells(k) + top * w
            assert np.array_equal(cells, one.cells(k)[(one.cells(k) >= top * w) & (one.cells(k) < end * w)])
            assert np.array_equal(part.pixels(k), pixels.reshape(-1, 2)[cells])
    for bad in ((4, 20), (0, h + 1), (16, 8)):
        with pytest.raises(ShapeError, match="rows"):
            choose_sources(rig, poses, grid, MM_PER_PX, 3.0, strip_rows=8, rows=bad)


def _wall_samples(seed: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Scattered wall points of a wavy tube: (N,) arc, (N,) axial (mm), (N, 3) points and
    the circumference (a hole in the middle)."""
    rng = np.random.default_rng(seed)
    circ = 2 * np.pi * 20.0
    arc = rng.uniform(0, circ, 3000)
    axial = rng.uniform(0, 60.0, 3000)
    keep = ~((np.abs(arc - 60) < 8) & (np.abs(axial - 30) < 6))
    arc, axial = arc[keep], axial[keep]
    theta = arc / 20.0
    r = 20.0 + 0.5 * np.sin(3 * theta) + 0.2 * np.cos(axial / 7)
    pts = np.column_stack([r * np.cos(theta), r * np.sin(theta), axial + 0.1 * np.sin(theta)])
    return arc, axial, pts, circ


def test_the_wall_grid_by_strips_equals_the_whole_grid(whole_wall_grid) -> None:
    arc, axial, pts, circ = _wall_samples()
    mm, gap = 0.5, 2.0
    # The whole grid in one interpolation (the stage before it went strip-wise).
    whole = whole_wall_grid(arc, axial, pts, circ, mm, gap)
    z0, height = float(np.floor(axial.min())), whole.shape[0]
    assert np.isnan(whole).any() and np.isfinite(whole).mean() > 0.9

    wall = WallGrid(arc, axial, pts, circ, mm, gap)
    assert wall.shape == whole.shape[:2] and wall.axial_min_mm == z0
    for strip in (1, 7, 50, height):
        grid, origin = wall_points_on_grid(arc, axial, pts, circ, mm, gap, strip_rows=strip)
        assert origin == z0
        assert np.array_equal(grid, whole, equal_nan=True)
    assert np.array_equal(wall.rows(40, 41), whole[40:41], equal_nan=True)


def test_the_choice_of_a_wall_grid_equals_that_of_its_array() -> None:
    rig = _rig("hyperboloid")
    arc, axial, pts, circ = _wall_samples()
    # The tube along the rig's z axis, keyframes along it.
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 2, 3] = [5.0, 20.0, 35.0, 50.0]
    wall = WallGrid(arc, axial, pts, circ, 0.5, 2.0)
    grid, _ = wall_points_on_grid(arc, axial, pts, circ, 0.5, 2.0)
    lazy = choose_sources(rig, poses, wall, 0.5, 3.0, strip_rows=16)
    _assert_same_choice(lazy, choose_sources(rig, poses, grid, 0.5, 3.0, strip_rows=grid.shape[0]))
    assert np.mean(lazy.source[np.isfinite(grid).all(axis=2)] >= 0) > 0.5


def test_a_strip_no_keyframe_sees_is_left_empty() -> None:
    # A gap in the wall (rings lost over a stretch): whole strips without a wall point.
    rig = _rig("hyperboloid")
    grid, poses = _pipe(310.0, 30.0, None, seed=1)
    gap = grid.copy()
    gap[16:48] = np.nan
    one = choose_sources(rig, poses, gap, MM_PER_PX, 3.0, strip_rows=gap.shape[0])
    small = choose_sources(rig, poses, gap, MM_PER_PX, 3.0, strip_rows=8)
    _assert_same_choice(small, one)
    assert np.all(small.source[16:48] == -1) and np.any(small.source >= 0)


def test_strips_scored_by_worker_processes_give_the_same_choice() -> None:
    from omnipipe.executor import open_executor

    rig = _rig("hyperboloid")
    grid, poses = _pipe(310.0, 30.0, 300.0, seed=1)
    here = choose_sources(rig, poses, grid, MM_PER_PX, 3.0, strip_rows=16)
    with open_executor(2) as ex:
        there = choose_sources(rig, poses, grid, MM_PER_PX, 3.0, strip_rows=16, executor=ex)
    _assert_same_choice(there, here)


def test_the_cells_keyframe_takes_the_smallest_type_that_holds_every_keyframe() -> None:
    assert source_dtype(1) == np.int16 and source_dtype(32766) == np.int16
    assert source_dtype(32767) == np.int32 and source_dtype(10**6) == np.int32
    # the largest keyframe index and -1 survive the round trip through the type
    for k in (1, 32766, 32767, 10**6):
        assert np.array([-1, k - 1], source_dtype(k)).tolist() == [-1, k - 1]


@pytest.mark.parametrize("bend_mm", [None, 1000.0])
def test_compiled_scoring_equals_the_numpy_formulation(bend_mm: float | None) -> None:
    """The compiled view scores (:mod:`omnipipe.model._kernels`) choose what the NumPy
    formulation chooses, at the same pixels and light to float32 rounding, and skipping
    the views that cannot win changes nothing."""
    from omnipipe.model.texture_sources import _choose_in_strip

    grid, poses = _pipe(500.0, 12.0, bend_mm)
    rig = _rig("hyperboloid")
    camera = camera_from_rig(rig)
    assert camera.compiled_projection() is not None
    rig_from_world = np.linalg.inv(poses)
    args = (rig, camera, rig_from_world, grid, 0, grid.shape[0], elevation_bounds(camera), MM_PER_PX, 3.0, True, 4.0)
    fast = _choose_in_strip(*args, compiled=True)
    slow = _choose_in_strip(*args, compiled=False)
    # Views skipped by the magnification bound could not have won: the same choice.
    skipping = _choose_in_strip(*args, compiled=True, magnification=magnification_table(camera))
    for a, b in zip(skipping, fast, strict=True):
        assert np.array_equal(a, b, equal_nan=True)
    assert np.array_equal(fast[2], slow[2])
    # Scores agree to rounding: a choice may differ only between exactly tied views.
    same = fast[0] == slow[0]
    assert same.mean() > 0.9999 and (slow[0] >= 0).mean() > 0.9
    np.testing.assert_allclose(fast[1][same], slow[1][same], rtol=0, atol=1e-3)
    lit = same & np.isfinite(slow[3][:, 0])
    np.testing.assert_allclose(fast[3][lit], slow[3][lit], rtol=1e-5, atol=1e-3)


def test_magnification_table_bounds_the_projection() -> None:
    """Every sampled ray's px per radian (its Jacobian's largest singular value at unit
    distance) lies below its elevation bin's entry."""
    from omnipipe.model._kernels import MAG_BIN_RAD

    camera = camera_from_rig(_rig("hyperboloid"))
    table = magnification_table(camera)
    rng = np.random.default_rng(2)
    lo, hi = elevation_bounds(camera)
    e, a = rng.uniform(lo, hi, 5000), rng.uniform(0, 2 * np.pi, 5000)
    rays = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=1)
    mag = np.linalg.norm(camera.project_jacobian(rays), ord=2, axis=(1, 2))
    bins = ((e + 0.5 * np.pi) / MAG_BIN_RAD).astype(int)
    assert np.all(mag <= table[bins])
    inner = (e > lo + 0.1) & (e < hi - 0.1)  # and it is not vacuous inside the seen band
    assert inner.sum() > 1000 and np.all(table[bins[inner]] <= 2.0 * mag.max())



@pytest.mark.parametrize("model", ["hyperboloid", "unified"])
def test_magnification_table_by_blocks_of_elevations_equals_the_whole(monkeypatch, model: str) -> None:
    """The table sampled a few elevations at a time (blocks of 7: many, a ragged last
    one) is the one sampled at once (every elevation in one block), entry for entry."""
    from omnipipe.model import texture_sources

    camera = camera_from_rig(_rig(model))
    tables = []
    for rows in (7, 100_000):
        monkeypatch.setattr(texture_sources, "MAG_ROWS", rows)
        monkeypatch.setattr(texture_sources, "_MAGNIFICATION", {})
        tables.append(magnification_table(camera))
    assert np.array_equal(tables[0], tables[1]) and np.isfinite(tables[0]).sum() > 10


def test_largest_singular_value_in_closed_form_equals_the_svd() -> None:
    """The table's px per radian: the closed form of a 2 x 3 matrix's largest singular
    value against NumPy's SVD norm (random, rank-one, zero and infinite matrices)."""
    from omnipipe.model.texture_sources import _largest_singular_2x3

    rng = np.random.default_rng(4)
    jac = rng.normal(0, 300, (500, 2, 3))
    jac[:50, 1] = 2.5 * jac[:50, 0]  # rank one: the smaller singular value 0
    jac[50:60] = 0.0
    want = np.linalg.norm(jac, ord=2, axis=(1, 2))
    np.testing.assert_allclose(_largest_singular_2x3(jac), want, rtol=1e-12, atol=1e-12)
    jac[60, 0, 2] = np.inf
    assert np.isinf(_largest_singular_2x3(jac)[60]) and np.isfinite(_largest_singular_2x3(jac)[61])

def test_a_chunked_wall_grid_gives_the_same_choice_in_the_workers() -> None:
    from omnipipe.executor import open_executor

    rig = _rig("hyperboloid")
    arc, axial, pts, circ = _wall_samples()
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 2, 3] = [5.0, 20.0, 35.0, 50.0]
    hole = (np.abs(arc - 0.5 * circ) < 6.0) & (np.abs(axial - np.median(axial)) < 4.0)  # an opening

    def wall() -> WallGrid:
        return WallGrid(arc, axial, pts, circ, 0.5, 2.0, chunk_points=len(arc) // 5, hole=hole, max_edge_mm=4.0)

    h = wall().shape[0]
    with open_executor(2) as ex:
        lazy = wall()
        there = [choose_sources(rig, poses, lazy, 0.5, 3.0, strip_rows=16, rows=(t, min(t + 48, h)), executor=ex)
                 for t in range(0, h, 48)]
    lazy = wall()
    here = [choose_sources(rig, poses, lazy, 0.5, 3.0, strip_rows=16, rows=(t, min(t + 48, h)))
            for t in range(0, h, 48)]
    for a, b in zip(there, here, strict=True):
        _assert_same_choice(a, b)

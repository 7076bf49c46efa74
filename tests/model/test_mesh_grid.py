"""The texture's wall grid drawn from the mesh's own triangles (:class:`MeshGrid`): its
compiled rasteriser against a cell-by-cell reference, bit for bit, and the grid against
the one interpolated over a Delaunay triangulation of its own (:class:`WallGrid`)."""

from __future__ import annotations

import numpy as np
import pytest
from test_chunks import _rings, _tube
from test_texture_holes import CIRC, _wall_with_features
from threadpoolctl import threadpool_limits

from omnipipe.model import mesh_unrolled
from omnipipe.model._kernels import rasterise_faces
from omnipipe.model.mesh import longest_edge, longest_edges, orient_towards_axis
from omnipipe.model.texture_grid import MeshGrid, WallGrid, rows_of_faces
from omnipipe.spill import is_on_disk

RING_CIRC = 2 * np.pi * 20.0  # test_chunks' tube


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """As in the model stage (the reference grid's barycentric transforms)."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def rasterise_by_cell(faces, order, arc, axial, points, circ, z0, mm_per_px, first, max_gap_mm, grid, far):
    """:func:`omnipipe.model._kernels.rasterise_faces` with every triangle tested against
    every cell of the rows (the later one wins): its reference, in its operations."""
    h, w = grid.shape[:2]
    du = circ / w
    gap2 = max_gap_mm * max_gap_mm * (1.0 - 1e-9)
    for f in order:
        i = faces[f]
        u0 = arc[i[0]]
        u1 = u0 + ((arc[i[1]] - u0 + 0.5 * circ) % circ - 0.5 * circ)
        u2 = u0 + ((arc[i[2]] - u0 + 0.5 * circ) % circ - 0.5 * circ)
        v0, v1, v2 = axial[i[0]], axial[i[1]], axial[i[2]]
        den = (v1 - v2) * (u0 - u2) + (u2 - u1) * (v0 - v2)
        if den == 0.0:
            continue
        zc = (z0 + (first + np.arange(h)) * mm_per_px)[:, None]
        for shift in (-circ, 0.0, circ):
            uc = ((np.arange(w) + 0.5) * du + shift)[None, :]
            l0 = ((v1 - v2) * (uc - u2) + (u2 - u1) * (zc - v2)) / den
            l1 = ((v2 - v0) * (uc - u2) + (u0 - u2) * (zc - v2)) / den
            l2 = 1.0 - l0 - l1
            cell = (l0 >= -1e-12) & (l1 >= -1e-12) & (l2 >= -1e-12)
            for a in range(3):
                value = l0 * points[i[0], a] + l1 * points[i[1], a] + l2 * points[i[2], a]
                grid[..., a][cell] = value[cell]
            d2 = np.minimum(np.minimum((uc - u0) ** 2 + (zc - v0) ** 2, (uc - u1) ** 2 + (zc - v1) ** 2),
                            (uc - u2) ** 2 + (zc - v2) ** 2)
            far[cell] = (d2 > gap2)[cell]


def _mesh(arc, axial, pts, circ, hole=None):
    faces = mesh_unrolled(arc, axial, pts, circ, 2.5, hole=hole)
    frame = np.zeros(len(arc), int)
    return orient_towards_axis(faces, arc, axial, circ, pts, frame)


def test_the_rasteriser_is_its_cell_by_cell_reference_bit_for_bit() -> None:
    """A few dozen triangles across angle 0 and a strip of rows: the same cells, points
    and far flags, bit for bit."""
    rng = np.random.default_rng(4)
    arc, axial = _rings(6, 14, seed=2)
    pts = _tube(arc, axial)
    faces = _mesh(arc, axial, pts, RING_CIRC)
    assert len(faces) > 40
    mm, z0, w = 0.7, float(np.floor(axial.min())), int(np.ceil(RING_CIRC / 0.7))
    h = int(np.ceil((axial.max() - z0) / mm)) + 1
    first, stop = 3, h - 2
    order = rng.permutation(len(faces)).astype(faces.dtype)
    out = []
    for fn in (rasterise_faces, rasterise_by_cell):
        grid = np.full((stop - first, w, 3), np.nan)
        far = np.zeros((stop - first, w), bool)
        fn(faces, order, arc, axial, pts, RING_CIRC, z0, mm, first, 1.2, grid, far)
        out.append((grid, far))
    (g1, f1), (g2, f2) = out
    assert np.array_equal(g1.view(np.uint8), g2.view(np.uint8)) and np.array_equal(f1, f2)
    assert np.isfinite(g1).mean() > 0.8 and 0 < f1.sum() < f1.size


def faces_by_row(faces, axial, z0, mm, h):
    """NumPy reference of the texture's row order: each triangle's first row (one early),
    a stable sort by it, the rows' starts and the most rows a triangle spans."""
    zf = axial[faces]
    first = np.clip(np.floor((zf.min(axis=1) - z0) / mm).astype(np.int64) - 1, 0, h - 1)
    last = np.clip(np.ceil((zf.max(axis=1) - z0) / mm).astype(np.int64) + 1, 0, h - 1)
    order = np.argsort(first, kind="stable").astype(faces.dtype)
    start = np.concatenate([[0], np.cumsum(np.bincount(first, minlength=h))])
    return order, start, int((last - first).max()) + 1 if len(faces) else 0


def test_rows_of_faces_orders_every_triangle_by_its_first_row() -> None:
    arc, axial = _rings(30, 40, seed=1)
    faces = _mesh(arc, axial, _tube(arc, axial), RING_CIRC)
    z0, mm = float(np.floor(axial.min())), 0.5
    h = int(np.ceil((axial.max() - z0) / mm)) + 1
    order, start, span = rows_of_faces(faces, axial, z0, mm, h)
    assert np.array_equal(np.sort(order), np.arange(len(faces)))
    zf = axial[faces]
    first = np.clip(np.floor((zf.min(axis=1) - z0) / mm).astype(int) - 1, 0, h - 1)
    last = np.clip(np.ceil((zf.max(axis=1) - z0) / mm).astype(int) + 1, 0, h - 1)
    assert np.array_equal(np.diff(first[order]) >= 0, np.ones(len(faces) - 1, bool))
    assert start[0] == 0 and start[-1] == len(faces)
    for r in (0, h // 3, h - 1):
        assert np.array_equal(np.sort(order[start[r] : start[r + 1]]), np.flatnonzero(first == r))
    assert span == int((last - first).max()) + 1


@pytest.mark.parametrize("block", [1, 7, 500, 1 << 16])
def test_rows_of_faces_a_block_at_a_time_is_faces_by_row(block: int) -> None:
    """The blocked counting sort (the texture's MeshGrid) against the NumPy reference on
    seeded rings, the triangles shuffled (rows in no order): the same order, starts and
    span, bit for bit, the order in the run's scratch."""
    arc, axial = _rings(30, 40, seed=3)
    faces = _mesh(arc, axial, _tube(arc, axial), RING_CIRC)
    faces = faces[np.random.default_rng(5).permutation(len(faces))]
    z0, mm = float(np.floor(axial.min())), 0.5
    h = int(np.ceil((axial.max() - z0) / mm)) + 1
    order, start, span = faces_by_row(faces, axial, z0, mm, h)
    got = rows_of_faces(faces, axial, z0, mm, h, block=block)
    assert got[0].dtype == order.dtype and is_on_disk(got[0])
    assert np.array_equal(got[0], order) and np.array_equal(got[1], start) and got[2] == span
    none = rows_of_faces(faces[:0], axial, z0, mm, h, block=block)
    assert len(none[0]) == 0 and not none[1].any() and none[2] == 0


@pytest.mark.parametrize("order", ["rings", "shuffled"])
def test_points_within_a_window_read_by_blocks_are_the_whole_scan(order: str) -> None:
    """MeshGrid's points near a strip, found from blocks' bounds: the same indices, in
    the same order, as the whole-run comparison, for rings in order and shuffled, with
    NaN values and windows at the ends, in the middle and outside."""
    from omnipipe.model.texture_grid import _block_bounds, _within

    rng = np.random.default_rng(7)
    z = np.repeat(np.arange(300.0) * 0.8, 37) + rng.normal(0.0, 0.3, 300 * 37)
    if order == "shuffled":
        z = z[rng.permutation(len(z))]
    z[rng.choice(len(z), 50, replace=False)] = np.nan
    z[:100] = np.nan  # a block of NaN only
    for block in (1, 64, 4096, 1 << 20):
        bounds = _block_bounds(z, block)
        for lo, hi in ((-5.0, 3.0), (100.2, 131.7), (230.0, 250.0), (400.0, 500.0), (-1e9, 1e9)):
            with np.errstate(invalid="ignore"):
                ref = np.flatnonzero((z >= lo) & (z <= hi))
            got = _within(z, bounds, block, lo, hi)
            assert got.dtype == ref.dtype and np.array_equal(got, ref)


def test_the_longest_edge_a_chunk_at_a_time_is_the_whole_maximum(monkeypatch) -> None:
    """The texture's gap from the mesh's longest edge, a chunk of triangles at a time:
    the whole-run maximum, bit for bit, with chunks of 1, 7 and all triangles."""
    import omnipipe.model.mesh as mesh

    arc, axial = _rings(30, 40, seed=2)
    pts = _tube(arc, axial) + np.random.default_rng(3).normal(0.0, 0.2, (len(arc), 3))
    faces = _mesh(arc, axial, pts, RING_CIRC)
    ref = float(longest_edges(pts, faces).max())
    for chunk in (1, 7, 1 << 16):
        monkeypatch.setattr(mesh, "FACE_CHUNK", chunk)
        assert longest_edge(pts, faces) == ref


def _both(arc, axial, pts, circ, mm, gap, hole=None, chunk=None):
    faces = _mesh(arc, axial, pts, circ, hole)
    longest = float(longest_edges(pts, faces).max())
    kw = {} if chunk is None else {"chunk_points": chunk}
    wall = WallGrid(arc, axial, pts, circ, mm, gap, hole=hole, max_edge_mm=longest, **kw)
    mesh = MeshGrid(faces, arc, axial, pts, circ, mm, gap)
    assert mesh.shape == wall.shape and mesh.axial_min_mm == wall.axial_min_mm
    h = wall.shape[0]
    a = np.concatenate([wall.rows(r, min(r + 50, h)) for r in range(0, h, 50)])
    b = np.concatenate([mesh.rows(r, min(r + 37, h)) for r in range(0, h, 37)])
    return a, b


@pytest.mark.parametrize("gap", [6.0, 2.2])
def test_the_mesh_grid_is_the_delaunay_grid_with_its_holes(gap: float) -> None:
    """A wall with a lateral's opening and a joint's gap (not wall), ~4 mm spacing: the same
    NaN cells and the same points to 1e-9 mm. With a gap of 2.2 mm many cells lie farther
    than that from their triangle's corners: the points near them decide, as the
    Delaunay grid's nearest-point rule does."""
    arc, axial, pts, hole = _wall_with_features()
    a, b = _both(arc, axial, pts, CIRC, 1.0, gap, hole=hole)
    nan_a, nan_b = np.isnan(a[..., 0]), np.isnan(b[..., 0])
    assert np.array_equal(nan_a, nan_b)
    assert np.allclose(a[~nan_a], b[~nan_b], rtol=0, atol=1e-9)
    assert 0.05 < nan_a.mean() < (0.6 if gap < 3 else 0.2)


def test_a_long_runs_mesh_grid_is_the_chunked_delaunay_grid() -> None:
    """Rings along a wavy tube with a stretch unseen, the mesh triangulated a chunk at a
    time: the same grid as the chunked Delaunay grid's."""
    arc, axial = _rings(120, 60, seed=3, gap=(150.0, 170.0))
    pts = _tube(arc, axial)
    faces = mesh_unrolled(arc, axial, pts, RING_CIRC, 2.5, chunk_points=1500)
    assert len(faces) > 10000
    a, b = _both(arc, axial, pts, RING_CIRC, 0.5, 2.0, chunk=1500)
    nan_a, nan_b = np.isnan(a[..., 0]), np.isnan(b[..., 0])
    assert np.array_equal(nan_a, nan_b)
    assert np.allclose(a[~nan_a], b[~nan_b], rtol=0, atol=1e-9)


@pytest.mark.parametrize("block", [1, 7, 500, 1 << 16])
def test_below_blockwise_equals_the_whole_flatnonzero(block: int) -> None:
    from omnipipe.model.mesh import below
    from omnipipe.spill import on_disk

    rng = np.random.default_rng(block)
    unrolled = rng.uniform(0, 600.0, (20_000, 2))
    unrolled[::37, 0] = np.nan
    unrolled[::41, 0] = -np.inf
    for values in (unrolled[:, 0], on_disk(unrolled)[:, 0], unrolled[:0, 0], unrolled[:1, 0]):
        want = np.flatnonzero(values < 60.0)
        got = below(values, 60.0, block)
        assert got.dtype == want.dtype and np.array_equal(got, want)


@pytest.mark.parametrize("block", [1, 7, 1 << 18])
def test_keyframe_index_check_blockwise_equals_the_whole_min_max(block: int) -> None:
    from omnipipe.model.stage import _all_within

    rng = np.random.default_rng(3 + block)
    for _ in range(20):
        index = rng.integers(0, 50, 3000)
        bad = rng.integers(0, 3)
        if bad:
            index[rng.integers(0, len(index))] = -1 if bad == 1 else 50
        want = bool(index.min() >= 0 and index.max() < 50)
        assert _all_within(index, 50, block) == want

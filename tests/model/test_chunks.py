"""The unrolled triangulations a chunk along the pipe at a time: the mesh and the texture's
wall grid equal those of one triangulation of all the points."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import Delaunay
from threadpoolctl import threadpool_limits

from omnipipe.model import mesh_unrolled
from omnipipe.model.chunks import CHUNK_POINTS, AxialChunks
from omnipipe.model.texture_grid import WallGrid

RADIUS_MM = 20.0
CIRC_MM = 2 * math.pi * RADIUS_MM
WHOLE = 10**9  # a chunk size that holds any of these sets: one triangulation


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """As in the model stage: the interpolations' small LAPACK solves with one BLAS thread
    (threads spinning on cores busy elsewhere can stall them for seconds)."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def _scattered(n: int, length_mm: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n,) arc in [0, circumference) and (n,) axial positions (mm), uniformly random."""
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, CIRC_MM, n), rng.uniform(0.0, length_mm, n)


def _rings(
    n_rings: int, per_ring: int, seed: int, gap: tuple[float, float] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Tilted, noisy rings (as the robot measures them) 2-4 mm apart: (N,) arc, (N,) axial
    (mm); the rings with axial position within ``gap`` are left out (a stretch unseen)."""
    rng = np.random.default_rng(seed)
    z = np.cumsum(rng.uniform(2.0, 4.0, n_rings))
    theta = rng.uniform(0.0, 2 * math.pi, (n_rings, per_ring))
    tilt = rng.normal(0.0, 0.05, (n_rings, 1)) * RADIUS_MM * np.sin(theta + rng.uniform(0, 6, (n_rings, 1)))
    axial = z[:, None] + tilt + rng.normal(0.0, 0.05, theta.shape)
    if gap is not None:
        keep = (z < gap[0]) | (z > gap[1])
        theta, axial = theta[keep], axial[keep]
    return (theta * RADIUS_MM).ravel(), axial.ravel()


def _tube(arc: np.ndarray, axial: np.ndarray) -> np.ndarray:
    """(N, 3) points on a wavy tube (mm) at the unrolled positions."""
    theta = arc / RADIUS_MM
    r = RADIUS_MM + 0.5 * np.sin(3 * theta) + 0.2 * np.cos(axial / 7)
    return np.column_stack([r * np.cos(theta), r * np.sin(theta), axial + 0.1 * np.sin(theta)])


def _triangle_set(faces: np.ndarray) -> set[tuple[int, ...]]:
    return {tuple(f) for f in np.sort(faces, axis=1).tolist()}


def _edge_counts(faces: np.ndarray) -> dict[tuple[int, int], int]:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    keys, counts = np.unique(edges, axis=0, return_counts=True)
    return {(int(a), int(b)): int(c) for (a, b), c in zip(keys, counts, strict=True)}


@pytest.mark.parametrize(
    ("kind", "chunk"),
    [("scattered", 700), ("rings", 700), ("rings-gap", 600)],
)
def test_the_chunked_mesh_is_the_whole_delaunay_mesh(kind: str, chunk: int) -> None:
    if kind == "scattered":
        arc, axial = _scattered(6000, 150.0, seed=3)
    else:  # a 40 mm stretch unseen: wider than the first margin (8 typical edges)
        arc, axial = _rings(60, 100, seed=4, gap=(80.0, 120.0) if kind == "rings-gap" else None)
    pts = _tube(arc, axial)
    whole = mesh_unrolled(arc, axial, pts, CIRC_MM, 2.0, chunk_points=WHOLE)
    chunked = mesh_unrolled(arc, axial, pts, CIRC_MM, 2.0, chunk_points=chunk)
    assert len(arc) > 6 * chunk  # several chunks
    assert len(chunked) == len(whole) > 2 * len(arc) * 0.9
    assert _triangle_set(chunked) == _triangle_set(whole)
    # The order does not depend on the chunks: ascending triangles of ascending vertices.
    other = mesh_unrolled(arc, axial, pts, CIRC_MM, 2.0, chunk_points=chunk + 333)
    assert np.array_equal(other, chunked)
    assert np.array_equal(chunked, np.unique(np.sort(chunked, axis=1), axis=0))


def test_the_chunks_triangulated_by_worker_processes_give_the_same_mesh() -> None:
    from omnipipe.executor import open_executor

    arc, axial = _rings(60, 100, seed=4, gap=(80.0, 120.0))
    pts = _tube(arc, axial)
    here = mesh_unrolled(arc, axial, pts, CIRC_MM, 2.0, chunk_points=700)
    with open_executor(2) as ex:
        there = mesh_unrolled(arc, axial, pts, CIRC_MM, 2.0, chunk_points=700, executor=ex)
    assert len(here) > 9000 and np.array_equal(here, there)


def test_the_chunked_mesh_has_no_hole_or_overlap_at_the_seams() -> None:
    arc, axial = _scattered(5000, 120.0, seed=5)
    pts = _tube(arc, axial)
    chunk = 600
    # Every triangle (no edge cut): the wall is closed around and along, open at its ends.
    faces = mesh_unrolled(arc, axial, pts, CIRC_MM, np.inf, chunk_points=chunk)
    assert len(_triangle_set(faces)) == len(faces)  # no triangle twice
    counts = _edge_counts(faces)
    seams = AxialChunks(arc, axial, chunk).cores()[1:]
    assert len(seams) >= 8
    inside = 0
    for (a, b), c in counts.items():
        if min(axial[a], axial[b]) > 5.0 and max(axial[a], axial[b]) < 115.0:
            assert c == 2, (a, b, c)  # an edge of one triangle: a hole; of three: an overlap
            inside += 1
    assert inside > 0.9 * len(counts)
    assert np.array_equal(np.unique(faces), np.arange(len(arc)))  # every point is a vertex


def test_short_runs_are_triangulated_whole_as_before() -> None:
    arc, axial = _scattered(3000, 60.0, seed=6)
    pts = _tube(arc, axial)
    # The mesher before the chunks, verbatim: one Delaunay, faces in qhull's order.
    n, margin = len(pts), 0.1 * CIRC_MM
    wrap = np.flatnonzero(arc < margin)
    uu = np.concatenate([arc, arc[wrap] + CIRC_MM])
    vv = np.concatenate([axial, axial[wrap]])
    ids = np.concatenate([np.arange(n), wrap])
    tri = Delaunay(np.stack([uu, vv], axis=1)).simplices
    cu = uu[tri].mean(axis=1)
    faces = ids[tri[(cu >= 0.5 * margin) & (cu < CIRC_MM + 0.5 * margin)]]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    p = pts[faces]
    longest = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2).max(axis=1)
    before = faces[longest <= 2.0 * np.median(longest)]
    assert len(uu) < CHUNK_POINTS
    assert np.array_equal(mesh_unrolled(arc, axial, pts, CIRC_MM, 2.0), before)


def test_a_chunk_widens_its_margin_until_its_triangles_are_the_whole_sets() -> None:
    arc, axial = _rings(50, 80, seed=7, gap=(60.0, 90.0))
    whole = Delaunay(np.column_stack([arc, axial])).simplices
    chunks = AxialChunks(arc, axial, chunk_points=500)
    chunks.margin_mm = 0.5  # far too narrow at first
    mine: list[np.ndarray] = []
    for z_lo, z_hi in chunks.cores():
        ids, tri = chunks.triangulate(z_lo, z_hi, -np.inf, np.inf)
        t = chunks.order[ids[tri.simplices]]
        cz = axial[t].mean(axis=1)
        mine.append(t[(cz >= z_lo) & (cz < z_hi)])
    assert len(chunks.cores()) >= 6
    t = np.concatenate(mine)
    assert len(t) == len(whole) and _triangle_set(t) == _triangle_set(whole)


def test_a_chunk_at_the_runs_end_stays_a_chunk() -> None:
    """The last ring almost straight (hull slivers along it and down the sides with circles
    of hundreds of metres): the end's chunk is widened only as far as the circles reach
    within the points' u range, not to every point, and its triangles over the end are
    the whole set's."""
    rng = np.random.default_rng(3)
    z = np.cumsum(rng.uniform(2.0, 4.0, 60))
    theta = np.sort(rng.uniform(0.0, 2 * math.pi, (60, 200)), axis=1)
    axial = z[:, None] + rng.normal(0.0, 0.05, theta.shape)
    axial[-1] = z[-1] + rng.normal(0.0, 1e-3, 200)
    arc, axial = (theta * RADIUS_MM).ravel(), axial.ravel()
    chunks = AxialChunks(arc, axial, chunk_points=1000)
    z_lo, z_hi = z[-1] - 1.0, z[-1] + 1.0
    ids, tri = chunks.triangulate(z_lo, z_hi, 0.0, CIRC_MM)
    assert len(ids) < len(arc) / 2
    t = chunks.order[ids[tri.simplices]]
    whole = Delaunay(np.column_stack([arc, axial])).simplices

    def meeting(faces: np.ndarray) -> set[tuple[int, ...]]:
        fz = axial[faces]
        return _triangle_set(faces[(fz.max(axis=1) >= z_lo) & (fz.min(axis=1) <= z_hi)])

    assert meeting(t) == meeting(whole)


@pytest.mark.parametrize("kind", ["scattered", "rings-gap"])
def test_the_chunked_wall_grid_is_the_whole_grid(kind: str, whole_wall_grid) -> None:
    if kind == "scattered":
        arc, axial = _scattered(6000, 150.0, seed=8)
        keep = ~((np.abs(arc - 60) < 8) & (np.abs(axial - 70) < 6))  # a hole stays a hole
        arc, axial = arc[keep], axial[keep]
    else:
        arc, axial = _rings(50, 100, seed=9, gap=(70.0, 95.0))
    pts = _tube(arc, axial)
    mm, gap = 0.5, 2.5
    whole = whole_wall_grid(arc, axial, pts, CIRC_MM, mm, gap)
    wall = WallGrid(arc, axial, pts, CIRC_MM, mm, gap, chunk_points=800)
    assert wall.shape == whole.shape[:2]
    assert np.isnan(whole).any() and np.isfinite(whole).mean() > 0.5
    h = wall.shape[0]
    # Strips with a row either side, as the texture's choice asks for them.
    for r0 in range(0, h, 24):
        lo, hi = max(r0 - 1, 0), min(r0 + 25, h)
        rows = wall.rows(lo, hi)
        assert np.array_equal(np.isnan(rows), np.isnan(whole[lo:hi]))
        np.testing.assert_allclose(rows, whole[lo:hi], rtol=0, atol=1e-9)
    for r in (h - 1, 3, h // 2):  # and any rows, in any order
        np.testing.assert_allclose(wall.rows(r, r + 1), whole[r : r + 1], rtol=0, atol=1e-9)
    assert wall.rows(5, 5).shape == (0, wall.shape[1], 3)


def test_winding_and_seam_split_a_chunk_of_triangles_at_a_time_change_nothing(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import omnipipe.model.mesh as model
    from omnipipe.model.texture_grid import UnrolledImage

    arc, axial = _rings(20, 60, seed=10)
    pts = _tube(arc, axial)
    frame = np.repeat(np.arange(20), 60)
    faces = mesh_unrolled(arc, axial, pts, CIRC_MM, 2.0)
    h, w = int(axial.max()) + 2, int(CIRC_MM)
    image = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    unrolled = UnrolledImage(image, np.ones((h, w), bool), 1.0, float(np.floor(axial.min())), CIRC_MM)
    results = []
    for chunk in (len(faces), 7):
        monkeypatch.setattr(model, "FACE_CHUNK", chunk)
        wound = model.orient_towards_axis(faces, arc, axial, CIRC_MM, pts, frame)
        results.append((wound, *model.textured_mesh(wound, pts, arc, axial, unrolled)))
    for a, b in zip(*results, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert not np.array_equal(results[0][0], faces)  # some triangles were turned

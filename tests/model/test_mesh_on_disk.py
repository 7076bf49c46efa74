"""The mesh's steps over a long run a chunk at a time, in the run's scratch: the same faces,
in the same order, as the whole-array code they replaced (kept here as the reference)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import omnipipe.model.mesh as mesh
from omnipipe.model.mesh import (
    _chunked_triangles,
    longest_edges,
    median_of_parts,
    mesh_unrolled,
    orient_towards_axis,
)
from omnipipe.spill import is_on_disk

RADIUS_MM = 20.0
CIRC_MM = 2 * math.pi * RADIUS_MM


def _rings(n_rings: int, per_ring: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy tilted rings 2-4 mm apart on a wavy tube: (N,) arc, (N,) axial, (N, 3) points."""
    rng = np.random.default_rng(seed)
    z = np.cumsum(rng.uniform(2.0, 4.0, n_rings))
    theta = rng.uniform(0.0, 2 * math.pi, (n_rings, per_ring))
    axial = z[:, None] + rng.normal(0.0, 0.3, (n_rings, 1)) * np.sin(theta) + rng.normal(0, 0.05, theta.shape)
    arc, axial = (theta * RADIUS_MM).ravel(), axial.ravel()
    r = RADIUS_MM + 0.5 * np.sin(3 * arc / RADIUS_MM)
    pts = np.column_stack([r * np.cos(arc / RADIUS_MM), r * np.sin(arc / RADIUS_MM), axial])
    return arc, axial, pts


def _whole_sort_reference(
    arc: np.ndarray, axial: np.ndarray, pts: np.ndarray, factor: float, chunk: int, hole: np.ndarray | None
) -> np.ndarray:
    """The chunked mesh as it was made before: every chunk's triangles concatenated,
    mapped to their points, sorted (each, then all), filtered at once."""
    n = len(pts)
    margin = 0.1 * CIRC_MM
    wrap = np.flatnonzero(arc < margin)
    uu = np.concatenate([arc, arc[wrap] + CIRC_MM])
    vv = np.concatenate([axial, axial[wrap]])
    ids = np.concatenate([np.arange(n), wrap]).astype(np.int32)
    tri = np.concatenate(list(_chunked_triangles(uu, vv, 0.5 * margin, CIRC_MM + 0.5 * margin, chunk)))
    faces = ids[tri]
    faces.sort(axis=1)
    faces = faces[np.lexsort((faces[:, 2], faces[:, 1], faces[:, 0]))]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    if hole is not None and hole.any():
        faces = faces[~hole[faces].any(axis=1)]
    longest = longest_edges(pts, faces)
    return faces[longest <= factor * float(np.median(longest))]


@pytest.mark.parametrize("bits", [3, 6, 16])
@pytest.mark.parametrize("with_hole", [False, True])
def test_chunked_mesh_sorted_a_block_at_a_time_equals_sorting_all_faces(
    monkeypatch: pytest.MonkeyPatch, bits: int, with_hole: bool
) -> None:
    arc, axial, pts = _rings(40, 50, seed=3)
    # Points out of axial order (as stations of a run that backs up): blocks of first
    # vertices then span the chunks.
    order = np.random.default_rng(1).permutation(len(arc))
    arc, axial, pts = arc[order], axial[order], pts[order]
    hole = None
    if with_hole:
        hole = (axial > 40) & (axial < 48) & (arc < 30)
    monkeypatch.setattr(mesh, "BUCKET_BITS", bits)
    want = _whole_sort_reference(arc, axial, pts, 2.0, 400, hole)
    got = mesh_unrolled(arc, axial, pts, CIRC_MM, 2.0, chunk_points=400, hole=hole)
    assert len(want) > 3000
    assert got.dtype == want.dtype and np.array_equal(got, want)
    assert is_on_disk(got)


@pytest.mark.parametrize("n", [1, 2, 7, 1000, 1001])
def test_median_of_parts_is_numpys_median_bit_for_bit(n: int) -> None:
    rng = np.random.default_rng(n)
    values = rng.normal(0.0, 3.0, n) * 10.0 ** rng.integers(-5, 5, n)
    values[rng.random(n) < 0.3] = 0.25  # repeated values
    if n > 2:
        values[:2] = [-0.0, 0.0]
    for cuts in ([], [n // 3], [1, n // 2, n - 1]):
        parts = np.split(values, cuts)
        assert median_of_parts(parts) == np.median(values)
    assert math.isnan(median_of_parts([]))
    assert math.isnan(median_of_parts([np.array([1.0, np.nan])]))


def _orient_reference(
    faces: np.ndarray, arc: np.ndarray, axial: np.ndarray, circ: float, pts: np.ndarray, frame: np.ndarray
) -> np.ndarray:
    """orient_towards_axis as it was, on whole arrays (np.unique's inverse, one np.add.at)."""
    faces = faces.copy()
    u = arc[faces]
    u = (u - u[:, :1] + 0.5 * circ) % circ - 0.5 * circ
    v = axial[faces]
    area2 = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0])
    neg = area2 < 0
    faces[neg] = faces[neg][:, [0, 2, 1]]
    frames, inverse = np.unique(frame, return_inverse=True)
    centres = np.zeros((len(frames), 3))
    np.add.at(centres, inverse, pts)
    centres /= np.bincount(inverse, minlength=len(frames))[:, None]
    p = pts[faces]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    inward = centres[inverse[faces[:, 0]]] - p.mean(axis=1)
    if np.count_nonzero(np.sum(normal * inward, axis=1) > 0) < 0.5 * len(faces):
        faces[:, [1, 2]] = faces[:, [2, 1]]
    return faces


@pytest.mark.parametrize("chunk", [7, 1 << 16])
@pytest.mark.parametrize("reverse", [False, True])
def test_winding_a_chunk_at_a_time_on_disk_equals_the_whole_array_reference(
    monkeypatch: pytest.MonkeyPatch, chunk: int, reverse: bool
) -> None:
    arc, axial, pts = _rings(12, 40, seed=5)
    # Keyframe numbers with gaps, not starting at 0, not in order.
    frame = np.repeat(np.random.default_rng(2).permutation(np.arange(12) * 3 + 5), 40)
    if reverse:  # the other direction of travel: the vote turns every triangle
        arc = CIRC_MM - arc - 1e-9
    faces = mesh_unrolled(arc, axial, pts, CIRC_MM, 2.0)
    want = _orient_reference(faces, arc, axial, CIRC_MM, pts, frame)
    monkeypatch.setattr(mesh, "FACE_CHUNK", chunk)
    before = faces.copy()
    got = orient_towards_axis(faces, arc, axial, CIRC_MM, pts, frame)
    assert got.dtype == want.dtype and np.array_equal(got, want)
    assert np.array_equal(faces, before) and is_on_disk(got)
    assert reverse or not np.array_equal(got, faces)  # some triangles were turned

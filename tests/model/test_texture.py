"""Painting the unrolled wall (model/texture.py): each keyframe's samples into its cells."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.errors import ShapeError
from omnipipe.model.texture import paint, texture_samples
from omnipipe.model.texture_sources import CellChoice


def test_paint_writes_each_keyframes_cells_and_checks_the_samples() -> None:
    source = np.array([[0, 1, -1], [1, 0, 0]])
    px = np.zeros((3, 2), np.float32)
    choice = CellChoice(source, np.array([[0, 2], [0, 2]]), ((px[:1], px[:2]), (px[:2],)))
    assert np.array_equal(choice.cells(0), [0, 4, 5]) and np.array_equal(choice.cells(1), [1, 3])
    samples = {0: np.array([[10] * 3, [40] * 3, [50] * 3], np.uint8), 1: np.array([[20] * 3, [30] * 3], np.uint8)}
    image = np.zeros((6, 3), np.uint8)
    for k, s in samples.items():
        paint(image, choice, k, s)
    assert np.array_equal(image[:, 0].reshape(2, 3), [[10, 20, 0], [30, 40, 50]])
    with pytest.raises(ShapeError):
        paint(image, choice, 1, None)
    with pytest.raises(ShapeError):
        paint(image, choice, 0, samples[0][:2])


def test_texture_samples_take_grey_and_16_bit_images() -> None:
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    px = np.array([[3.0, 4.0], [10.0, 7.0]], np.float32)  # on pixel centres: exact
    assert np.array_equal(texture_samples(rgb, px), rgb[[4, 7], [3, 10]])
    grey = rgb[..., 0]
    assert np.array_equal(texture_samples(grey, px), np.repeat(grey[[4, 7], [3, 10]][:, None], 3, axis=1))
    assert np.array_equal(texture_samples(rgb.astype(np.uint16) * 257, px), rgb[[4, 7], [3, 10]])


def test_textured_mesh_fills_a_given_atlas_in_place() -> None:
    """The model stage paints into the atlas: given it, textured_mesh fills its wrapped
    margin in place and returns the same mesh and atlas as from the image alone."""
    from omnipipe.model.mesh import atlas_margin, textured_mesh
    from omnipipe.model.texture_grid import UnrolledImage

    rng = np.random.default_rng(3)
    h, w, circ = 20, 31, 15.5
    arc = rng.uniform(0, circ, 40)
    axial = rng.uniform(0, 9.5, 40)
    points = np.column_stack([np.cos(arc), np.sin(arc), axial])
    faces = rng.integers(0, 40, (60, 3)).astype(np.int32)
    image = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    unrolled = UnrolledImage(image, np.ones((h, w), bool), 0.5, 0.0, circ)
    expected = textured_mesh(faces, points, arc, axial, unrolled)
    atlas = np.zeros((h, w + atlas_margin(w), 3), np.uint8)
    atlas[:, :w] = image
    view = UnrolledImage(atlas[:, :w], unrolled.alpha, 0.5, 0.0, circ)
    got = textured_mesh(faces, points, arc, axial, view, atlas)
    assert got[3] is atlas
    for a, b in zip(expected, got, strict=True):
        assert np.array_equal(a, b)
    with pytest.raises(ShapeError):
        textured_mesh(faces, points, arc, axial, view, atlas[:, :-1])


def test_textured_mesh_makes_its_outputs_in_the_scratch_equal_to_the_formula(monkeypatch) -> None:
    """The seam-split mesh (vertices, faces, uvs: they grow with the run) is made in the
    run's scratch (omnipipe.spill), equal bit for bit to the formula in memory (the
    vertices of the small-arc corners of triangles across angle 0 copied one
    circumference on); the faces given are left as they were."""
    from omnipipe.model import mesh
    from omnipipe.model.mesh import atlas_margin, textured_mesh
    from omnipipe.model.texture_grid import UnrolledImage
    from omnipipe.spill import is_on_disk

    monkeypatch.setattr(mesh, "FACE_CHUNK", 7)  # several chunks
    rng = np.random.default_rng(4)
    h, w, circ, n = 20, 31, 15.5, 50
    arc = rng.uniform(0, circ, n)
    axial = rng.uniform(0, 9.5, n)
    points = np.column_stack([np.cos(arc), np.sin(arc), axial])
    faces = rng.integers(0, n, (80, 3)).astype(np.int32)
    before = faces.copy()
    unrolled = UnrolledImage(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), np.ones((h, w), bool), 0.5, 1.0, circ)
    verts, tfaces, uvs, _ = textured_mesh(faces, points, arc, axial, unrolled)
    u = arc[faces]
    shift = (np.ptp(u, axis=1) > 0.5 * circ)[:, None] & (u < 0.5 * circ)
    dup = np.unique(faces[shift])
    assert len(dup) > 3
    new_id = np.full(n, -1, np.int32)
    new_id[dup] = n + np.arange(len(dup))
    want_faces = faces.copy()
    want_faces[shift] = new_id[faces[shift]]
    all_arc = np.concatenate([arc, arc[dup] + circ])
    all_axial = np.concatenate([axial, axial[dup]])
    want_uvs = np.column_stack([
        all_arc / (circ * (w + atlas_margin(w)) / w), 1.0 - ((all_axial - 1.0) / 0.5 + 0.5) / h
    ])
    assert np.array_equal(faces, before)
    assert np.array_equal(tfaces, want_faces) and tfaces.dtype == faces.dtype
    assert np.array_equal(verts, np.concatenate([points, points[dup]]))
    assert np.array_equal(uvs, want_uvs) and uvs.dtype == want_uvs.dtype
    assert is_on_disk(verts) and is_on_disk(tfaces) and is_on_disk(uvs)

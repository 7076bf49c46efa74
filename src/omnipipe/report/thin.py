"""The report's 3-D view of a long run: the textured mesh thinned to a bounded size.

A run's mesh grows with its length (about 90 faces a frame on the paper rig); the
view sends at most ``max_faces`` triangles to the browser. Taking every k-th face kept
most vertices (each vertex is shared by six faces) and left holes between the kept
faces; :func:`thin_mesh` instead clusters the vertices on a grid of the texture
(square cells in texture pixels, i.e. in mm of the unrolled wall, grown until at most
``max_faces // 2`` cells are occupied), keeps one vertex of each cell (its first, with
its own position and UV) and the faces that still span three cells: a coarser wall
without holes, whose vertices, faces and page size are bounded whatever the run's
length. The texture seam stays a seam (its two copies of a vertex lie in cells at
u = 0 and u = 1).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from omnipipe.spill import drop_pages

GROWTH = 1.15
"""Factor of the cell side between two tries (the first from the texture's area)."""


def thin_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    uvs: np.ndarray,
    max_faces: int,
    texture_shape: tuple[int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V', 3) vertices, (F', 3) faces and (V', 2) UVs of the view, F' <= ``max_faces``.

    Args:
        vertices: (V, 3) mm; faces: (F, 3) vertex indices; uvs: (V, 2) in [0, 1].
        max_faces: at most this many faces are kept (>= 1).
        texture_shape: (H, W) pixels of the texture the UVs address (cells square in
            its pixels); None: square in UV units.

    A mesh of at most ``max_faces`` faces is returned as it is. Otherwise the vertices
    are clustered on the UV grid (see the module docstring); the vertices kept are
    those of the faces kept, renumbered in their order. A mesh whose UVs do not spread
    (all in one cell) keeps every k-th face instead.
    """
    if len(faces) <= max_faces:
        return vertices, np.asarray(faces, np.int64), uvs
    faces = np.asarray(faces)
    uv = np.asarray(uvs, float)
    h, w = texture_shape if texture_shape is not None else (1, 1)
    lo, hi = _bounds(uv)
    span = hi - lo if len(uv) else np.zeros(2)
    area_px = max(span[0] * w, 1e-12) * max(span[1] * h, 1e-12)
    side = math.sqrt(area_px / max(max_faces // 2, 1))  # cell side (texture px)
    kept = None
    for _ in range(200):
        # Cells first (cheap): about two faces a kept vertex; the faces once they fit.
        if _cells(uv, side, (h, w)) <= max(max_faces // 2, 3):
            kept = _clustered(uv, faces, side, (h, w))
            if kept is None or len(kept) <= max_faces:
                break
        side *= GROWTH
    if kept is None or len(kept) > max_faces:  # no spread in UV: every k-th face
        kept = faces[:: math.ceil(len(faces) / max_faces)]
    used, kept = np.unique(kept, return_inverse=True)
    return _take(np.asarray(vertices), used), kept.reshape(-1, 3), _take(uv, used)


FACE_CHUNK = 1 << 17
"""Faces :func:`_clustered` renumbers at a time (its int64 temporaries a chunk's, not
the mesh's)."""


def _clustered(uv: np.ndarray, faces: np.ndarray, side: float, shape: tuple[int, int]) -> np.ndarray | None:
    """The faces renumbered to their cells' first vertices (cells ``side`` texture px
    square), without the faces that collapsed or repeat another face (the first of each
    kept, in the faces' order); None when every vertex falls in one cell. A chunk of
    :data:`FACE_CHUNK` faces at a time: each chunk's repeats dropped, then the repeats
    across chunks among the (few) faces left. The cells' first vertices are found a
    chunk of vertices at a time too (:func:`_cell_firsts`)."""
    keys, first = _cell_firsts(uv, side, shape)
    if len(first) < 3:
        return None
    # (V,) each vertex's cell's first vertex, a chunk of vertices at a time (int32 where
    # the vertices' indices fit: 4 bytes a vertex, the only array of the mesh's length).
    rep = np.empty(len(uv), np.int32 if len(uv) < 1 << 31 else np.int64)
    for a, cell in _cell_chunks(uv, side, shape):
        rep[a : a + len(cell)] = first[np.searchsorted(keys, cell)]
    del keys, first
    wide = len(uv) >= 1 << 21  # a face no longer fits one int64 key (21 bits a corner)
    kept: list[np.ndarray] = []
    for a in range(0, len(faces), FACE_CHUNK):
        out = rep[np.asarray(faces[a : a + FACE_CHUNK], np.int64)].astype(np.int64)
        drop_pages()  # this chunk's faces read (omnipipe.spill): a chunk's pages resident
        out = out[(out[:, 0] != out[:, 1]) & (out[:, 1] != out[:, 2]) & (out[:, 0] != out[:, 2])]
        kept.append(out[_first_of_each(out, wide)])
    out = np.concatenate(kept) if kept else np.zeros((0, 3), np.int64)
    return out[_first_of_each(out, wide)]


VERTEX_CHUNK = 1 << 17
"""Vertices whose cells are computed at a time (the cells' int64 temporaries a chunk's,
not the mesh's: about 50 bytes a vertex held whole)."""


def _cell_chunks(uv: np.ndarray, side: float, shape: tuple[int, int]) -> Iterator[tuple[int, np.ndarray]]:
    """(first vertex, (n,) int64 cell of each vertex) per chunk of :data:`VERTEX_CHUNK`
    vertices: cell = row x (columns) + column on the grid of ``side`` texture px."""
    h, w = shape
    lo, hi = _bounds(uv)
    # The largest column: that of the largest u (floor is monotonic).
    cols = int(np.floor((hi[0] - lo[0]) * (w / side))) + 1
    for a in range(0, len(uv), VERTEX_CHUNK):
        part = np.asarray(uv[a : a + VERTEX_CHUNK], float)
        col = np.floor((part[:, 0] - lo[0]) * (w / side)).astype(np.int64)
        row = np.floor((part[:, 1] - lo[1]) * (h / side)).astype(np.int64)
        del part
        drop_pages()  # this chunk's UVs read (omnipipe.spill): a chunk's pages resident
        yield a, row * cols + col


def _take(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[idx]`` (``idx`` ascending), a chunk of :data:`VERTEX_CHUNK` indices at a time:
    the kept vertices lie all along a long run's mesh, whose pages (in the run's scratch,
    :mod:`omnipipe.spill`) are then a chunk's resident, not the whole mesh's."""
    out = np.empty((len(idx), *a.shape[1:]), a.dtype)
    for i in range(0, len(idx), VERTEX_CHUNK):
        out[i : i + VERTEX_CHUNK] = a[idx[i : i + VERTEX_CHUNK]]
        drop_pages()
    return out


def _bounds(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(2,) the smallest and (2,) the largest of the (V, 2) ``uv``'s columns, a chunk of
    :data:`VERTEX_CHUNK` rows at a time (a mesh in the run's scratch, :mod:`omnipipe.spill`:
    a chunk's pages resident)."""
    lo, hi = np.full(uv.shape[1], np.inf), np.full(uv.shape[1], -np.inf)
    for a in range(0, len(uv), VERTEX_CHUNK):
        part = uv[a : a + VERTEX_CHUNK]
        lo, hi = np.minimum(lo, part.min(axis=0)), np.maximum(hi, part.max(axis=0))
        del part
        drop_pages()
    return lo, hi


def _cell_firsts(uv: np.ndarray, side: float, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The occupied cells, ascending, and the first vertex of each (``np.unique`` with
    ``return_index`` of every vertex's cell, a chunk of vertices at a time)."""
    keys = np.zeros(0, np.int64)
    first = np.zeros(0, np.int64)
    for a, cell in _cell_chunks(uv, side, shape):
        k, i = np.unique(cell, return_index=True)
        # The cells seen before keep their first vertex (they come first, and
        # np.unique's index is the first occurrence).
        keys, at = np.unique(np.concatenate([keys, k]), return_index=True)
        first = np.concatenate([first, i + a])[at]
    return keys, first


def _first_of_each(faces: np.ndarray, wide: bool) -> np.ndarray:
    """Ascending indices of the first of each set of (F, 3) faces with the same corners."""
    s = np.sort(faces, axis=1)
    if not wide:
        key = (s[:, 0] << 42) | (s[:, 1] << 21) | s[:, 2]
        _, once = np.unique(key, return_index=True)
    else:
        _, once = np.unique(s, axis=0, return_index=True)
    return np.sort(once)


def _cells(uv: np.ndarray, side: float, shape: tuple[int, int]) -> int:
    """Occupied cells of ``side`` texture px (as :func:`_clustered`)."""
    keys = np.zeros(0, np.int64)
    for _, cell in _cell_chunks(uv, side, shape):
        keys = np.union1d(keys, cell)
    return len(keys)

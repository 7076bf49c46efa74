"""The wall mesh of the model stage (paper Sec. VI): integration, unrolled Delaunay, winding.

Integration: every frame's metric ring points go into the world frame with the
frame's pose.

Mesh: a Delaunay triangulation in the unrolled parameterisation of the pipe
(arc length around the axis, distance along it; the analysis stage's centreline
coordinates, so it follows bends). The wall is a tube, a developable surface: a
2-D Delaunay on its unrolling gives the wall's own topology, never a triangle
across the pipe, which a 3-D Delaunay of a hollow cylinder would produce everywhere
(its tetrahedra fill the inside). The angle wraps around: a margin of points is
duplicated past 2 pi and each triangle is kept once. Triangles with an edge much
longer than the spacing of the rings are dropped: holes stay holes; so are triangles
touching a point the analysis found not to be wall (a joint's gap, a lateral's opening):
the mesh shows them as a gap and a hole. A run of more
points than :data:`~.chunks.CHUNK_POINTS` is triangulated a chunk along the pipe at a
time (:class:`~.chunks.AxialChunks`: the same triangles; qhull's memory is a chunk's).

Every triangle is wound so its normal (right-hand rule) points towards the pipe axis:
the wall is seen from inside.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from concurrent.futures import Executor

import numpy as np
from scipy.spatial import Delaunay

from omnipipe.errors import ShapeError
from omnipipe.executor import InlineExecutor, ordered_map, shares_files
from omnipipe.geometry import apply
from omnipipe.model.chunks import CHUNK_POINTS, AxialChunks
from omnipipe.model.texture_grid import UnrolledImage
from omnipipe.spill import drop_pages, on_disk, shared_on_disk, zeros_on_disk


def integrate(
    world_from_rig: np.ndarray, ring_points_in_rig: list[np.ndarray], in_scratch: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Ring points into the world: (N, 3) points (mm) and (N,) keyframe index of each,
    each ring moved and written in place (no list of moved rings and their concatenation
    in memory); ``in_scratch``: both arrays in the run's scratch (:mod:`omnipipe.spill`)."""
    n = sum(len(r) for r in ring_points_in_rig)
    new = zeros_on_disk if in_scratch and n else np.zeros
    points, frame = new((n, 3), float), new((n,), int)
    at = 0
    for k, (world_from_k, ring) in enumerate(zip(world_from_rig, ring_points_in_rig, strict=True)):
        if len(ring):
            points[at : at + len(ring)] = apply(world_from_k, ring)
            frame[at : at + len(ring)] = k
            at += len(ring)
    return points, frame


def unrolled_coordinates(
    points_in_world: np.ndarray, world_from_rig: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Fallback unrolling around a straight axis through the rig origins.

    Returns:
        arc_mm: (N,) in [0, circumference), from the first rig frame's x axis towards y.
        axial_mm: (N,) along the axis from the first rig origin.
        circumference_mm: 2 pi x the median distance from the axis.
    """
    origins = world_from_rig[:, :3, 3]
    axis = world_from_rig[0, :3, 2]
    if len(origins) > 2 and np.linalg.norm(origins[-1] - origins[0]) > 1.0:
        _, _, vt = np.linalg.svd(origins - origins.mean(axis=0), full_matrices=False)
        axis = vt[0] * np.sign(vt[0] @ (origins[-1] - origins[0]))
    x0 = world_from_rig[0, :3, 0] - (world_from_rig[0, :3, 0] @ axis) * axis
    x0 /= np.linalg.norm(x0)
    y0 = np.cross(axis, x0)
    centre = origins.mean(axis=0)
    rel = points_in_world - centre
    axial = rel @ axis + (centre - origins[0]) @ axis
    perp = rel - np.outer(rel @ axis, axis)
    radius = float(np.median(np.linalg.norm(perp, axis=1)))
    circ = 2 * math.pi * radius
    angle = np.arctan2(rel @ y0, rel @ x0) % (2 * math.pi)
    return angle * radius, axial, circ


FACE_CHUNK = 1 << 16
"""Triangles whose (F, 3, 3) corner coordinates are gathered at a time."""


def longest_edges(points_in_world: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) longest edge of each of the (F, 3) triangles, mm, a chunk of triangles at a time
    (no (F, 3, 3) float64 copy of the mesh)."""
    out = np.empty(len(faces))
    for a in range(0, len(faces), FACE_CHUNK):
        p = points_in_world[faces[a : a + FACE_CHUNK]]
        edges = np.stack(
            [np.linalg.norm(p[:, i] - p[:, (i + 1) % 3], axis=1) for i in range(3)], axis=1
        )
        out[a : a + FACE_CHUNK] = edges.max(axis=1)
    return out


def mesh_unrolled(
    arc_mm: np.ndarray,
    axial_mm: np.ndarray,
    points_in_world: np.ndarray,
    circumference_mm: float,
    max_edge_factor: float,
    chunk_points: int = CHUNK_POINTS,
    hole: np.ndarray | None = None,
    executor: Executor | None = None,
) -> np.ndarray:
    """(F, 3) triangles of an unrolled Delaunay over the points (see module docstring),
    vertex indices of :func:`face_dtype` (int32 below 2**31 points: half the memory).

    Args:
        arc_mm, axial_mm: (N,) unrolled coordinates of the points, arc in [0, circumference).
        points_in_world: (N, 3) mm.
        circumference_mm: period of ``arc_mm``.
        max_edge_factor: triangles with a (3-D) edge longer than this x the median longest
            edge are dropped.
        chunk_points: up to this many points (with the wrapped copies) are triangulated
            at once, as they always were (the faces in qhull's order); more a chunk along
            the pipe at a time (:func:`_chunked_triangles`: the same triangles, in
            ascending order of their ascending vertex ids), so that the triangulation's
            memory does not grow with the run.
        hole: (N,) True for points that are not wall (a joint's gap, a lateral's
            opening and the branch seen through it): triangles touching them are dropped,
            so the mesh shows the gap and the hole; None: all wall.
        executor: where a long run's chunks are triangulated (:mod:`omnipipe.executor`;
            None: here); the triangles do not depend on it.
    """
    n = len(points_in_world)
    index = face_dtype(n)
    if n < 3:
        return np.zeros((0, 3), index)
    circ = circumference_mm
    margin = 0.1 * circ
    wrap = below(arc_mm, margin)
    if n + len(wrap) > chunk_points:
        # The unrolled points with their wrapped copies in the run's scratch
        # (omnipipe.spill), each chunk's triangles filtered as it comes and kept there;
        # then sorted a block of first vertices at a time (_sorted_wall_faces).
        uu = _joined_on_disk(arc_mm, arc_mm[wrap] + circ)
        vv = _joined_on_disk(axial_mm, axial_mm[wrap])
        ids = _joined_on_disk(np.arange(n, dtype=index), wrap.astype(index))
        del wrap
        parts = _chunked_triangles(uu, vv, 0.5 * margin, circ + 0.5 * margin, chunk_points, executor)
        del uu, vv
        return _sorted_wall_faces(parts, ids, n, points_in_world, max_edge_factor, hole)
    uu = np.concatenate([arc_mm, arc_mm[wrap] + circ])
    vv = np.concatenate([axial_mm, axial_mm[wrap]])
    ids = np.concatenate([np.arange(n), wrap]).astype(index)
    tri = Delaunay(np.stack([uu, vv], axis=1)).simplices
    # Keep each triangle once: those whose centroid lies in the main period.
    cu = uu[tri].mean(axis=1)
    tri = tri[(cu >= 0.5 * margin) & (cu < circ + 0.5 * margin)]
    faces = _wall(ids[tri], n, hole)
    del uu, vv, tri
    # A typical triangle's longest edge spans one ring spacing; much longer ones bridge gaps.
    longest = longest_edges(points_in_world, faces)
    return faces[longest <= max_edge_factor * float(np.median(longest))]


def below(values: np.ndarray, limit: float, block: int = FACE_CHUNK) -> np.ndarray:
    """``np.flatnonzero(values < limit)`` of the (N,) ``values`` (e.g. a column of an
    array in the run's scratch), a block at a time, each block's pages dropped after it
    (:func:`~omnipipe.spill.drop_pages`): a whole-run pass maps a block of the run."""
    drop_pages()  # what the step before read (omnipipe.spill)
    parts = []
    for a in range(0, len(values), block):
        parts.append(a + np.flatnonzero(values[a : a + block] < limit))
        drop_pages()
    return np.concatenate(parts) if parts else np.zeros(0, np.intp)


def longest_edge(points_in_world: np.ndarray, faces: np.ndarray) -> float:
    """The longest edge of the (F, 3) triangles (F > 0), mm: ``longest_edges(...).max()``,
    a chunk of triangles at a time (no (F,) array of the run's edges)."""
    return max(
        float(longest_edges(points_in_world, faces[a : a + FACE_CHUNK]).max())
        for a in range(0, len(faces), FACE_CHUNK)
    )


def _joined_on_disk(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.concatenate([a, b])`` of two 1-D arrays, made in the run's scratch
    (:func:`~omnipipe.spill.zeros_on_disk`) a chunk at a time (no copy in memory)."""
    out = zeros_on_disk((len(a) + len(b),), np.result_type(a, b))
    for i in range(0, len(a), FACE_CHUNK):
        j = min(i + FACE_CHUNK, len(a))
        out[i:j] = a[i:j]
        drop_pages()
    out[len(a) :] = b
    drop_pages()
    return out


def _wall(faces: np.ndarray, n: int, hole: np.ndarray | None) -> np.ndarray:
    """The (F, 3) ``faces`` without those with a repeated vertex (a triangle wrapped onto
    itself) and, with ``hole`` ((n,) bool, True: not wall), those touching a hole."""
    faces = faces[
        (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    ]
    if hole is not None and len(hole) == n and hole.any():
        faces = faces[~np.asarray(hole, bool)[faces].any(axis=1)]
    return faces


BUCKET_BITS = 16
"""A long run's faces are sorted a block of 2**BUCKET_BITS first vertices at a time
(:func:`_sorted_wall_faces`: about twice as many faces)."""


def _sorted_wall_faces(
    parts: Iterator[np.ndarray],
    ids: np.ndarray,
    n: int,
    points_in_world: np.ndarray,
    max_edge_factor: float,
    hole: np.ndarray | None,
) -> np.ndarray:
    """The chunked triangulation's wall faces (:func:`mesh_unrolled`), in an order of the
    triangles alone: each ascending, the triangles ascending (lexicographic; equal ones in
    the chunks' order), those with a repeated vertex, touching a hole or with an edge longer
    than ``max_edge_factor`` x the median longest edge dropped. In the run's scratch
    (:mod:`omnipipe.spill`), as is each chunk's part meanwhile; in memory a chunk's and a
    block's faces (a block: the faces whose first vertex shares its top bits), never the
    run's: the same faces, in the same order, as sorting and filtering them all at once.

    Args:
        parts: each chunk's (T, 3) triangles, indices into ``ids``, in the chunks' order.
        ids: (n + wrapped,) the point of each triangulated vertex (the wrapped copies'
            originals).
        n: points; points_in_world: (n, 3) mm; hole: (n,) bool or None (:func:`_wall`).
    """
    blocks = (max(n - 1, 0) >> BUCKET_BITS) + 1
    # Per chunk: its faces and their longest edges by block, and where each block begins.
    kept: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for tri in parts:
        f = ids[tri]
        del tri
        f.sort(axis=1)
        f = _wall(f, n, hole)
        block = f[:, 0] >> BUCKET_BITS
        first = np.concatenate([[0], np.cumsum(np.bincount(block, minlength=blocks))])
        by_block = np.argsort(block, kind="stable")
        kept.append((on_disk(f[by_block]), on_disk(longest_edges(points_in_world, f)[by_block]), first))
        del f, block, by_block
        drop_pages()
    limit = max_edge_factor * median_of_parts([longest for _, longest, _ in kept])
    out = zeros_on_disk((sum(int(first[-1]) for _, _, first in kept), 3), ids.dtype)
    done = 0
    for b in range(blocks):
        f = np.concatenate([part[first[b] : first[b + 1]] for part, _, first in kept] or [out[:0]])
        longest = np.concatenate([lg[first[b] : first[b + 1]] for _, lg, first in kept] or [np.zeros(0)])
        order = np.lexsort((f[:, 2], f[:, 1], f[:, 0]))
        f = f[order[longest[order] <= limit]]
        out[done : done + len(f)] = f
        done += len(f)
        drop_pages()
    return out[:done]


def median_of_parts(parts: list[np.ndarray]) -> float:
    """``np.median`` of the 1-D float64 ``parts`` concatenated (bit for bit), without
    concatenating them: the middle order statistic(s) found by four passes over the parts,
    one per 16 bits of the values' order-preserving integer keys (radix selection); NaN
    if a value is NaN or there are none."""
    m = sum(len(p) for p in parts)
    if m == 0 or any(np.isnan(p).any() for p in parts):
        return float("nan")
    if m % 2:
        return float(np.mean(np.array([_kth_smallest(parts, m // 2)])))
    return float(np.mean(np.array([_kth_smallest(parts, m // 2 - 1), _kth_smallest(parts, m // 2)])))


def _order_keys(values: np.ndarray) -> np.ndarray:
    """(n,) uint64 keys of (n,) float64 values (no NaN) in the same order (-0.0 = 0.0)."""
    bits = np.ascontiguousarray(values, np.float64).view(np.uint64)
    bits = np.where(bits == np.uint64(1 << 63), np.uint64(0), bits)  # -0.0 as 0.0
    negative = (bits >> np.uint64(63)).astype(bool)
    return np.where(negative, ~bits, bits | np.uint64(1 << 63))


def _kth_smallest(parts: list[np.ndarray], k: int) -> float:
    """The k-th smallest (0-based) of the values of ``parts`` (float64, no NaN)."""
    prefix, mask = np.uint64(0), np.uint64(0)
    for shift in (48, 32, 16, 0):
        hist = np.zeros(1 << 16, np.int64)
        for p in parts:
            for a in range(0, len(p), FACE_CHUNK):
                keys = _order_keys(p[a : a + FACE_CHUNK])
                keys = keys[(keys & mask) == prefix]
                hist += np.bincount(((keys >> np.uint64(shift)) & np.uint64(0xFFFF)).astype(np.int64), minlength=1 << 16)
            drop_pages()
        below = np.cumsum(hist)
        digit = int(np.searchsorted(below, k, side="right"))
        k -= int(below[digit - 1]) if digit else 0
        prefix |= np.uint64(digit) << np.uint64(shift)
        mask |= np.uint64(0xFFFF) << np.uint64(shift)
    bits = prefix & ~np.uint64(1 << 63) if prefix >> np.uint64(63) else ~prefix
    return float(np.array([bits], np.uint64).view(np.float64)[0])


def face_dtype(points: int) -> type[np.signedinteger]:
    """Integer type of the faces' vertex indices for a mesh of ``points`` vertices
    (with the textured mesh's seam copies, at most twice as many): int32 while they fit,
    as every writer stores them (PLY int, glTF uint32), else int64."""
    return np.int32 if 2 * points < np.iinfo(np.int32).max else np.int64


def _chunked_triangles(
    uu: np.ndarray,
    vv: np.ndarray,
    u_lo: float,
    u_hi: float,
    chunk_points: int,
    executor: Executor | None = None,
) -> Iterator[np.ndarray]:
    """(T, 3) indices into the (n,) points (``uu``, ``vv``; mm) of the triangles of their
    Delaunay triangulation whose centroid has ``u_lo <= u < u_hi``, a chunk along ``vv`` at
    a time (:class:`~omnipipe.model.chunks.AxialChunks`), the chunks triangulated on
    ``executor`` (None: here; a local pool's workers read the points from the run's
    scratch, :func:`~omnipipe.spill.shared_on_disk`).

    Each chunk keeps its verified triangles whose centroid lies in its core interval of
    ``vv``; the cores partition the axis, so every triangle is kept once: its centroid is
    summed over its ascending vertices, the same bits in every chunk that holds it.
    Triangles of ascending vertices, a chunk's at a time, in the chunks' order.
    """
    axial = AxialChunks(uu, vv, chunk_points)
    # Kept as the smallest index type (int64 triangles were twice the mesh's faces,
    # and the parts and their concatenation were held together).
    index = np.int32 if len(uu) < np.iinfo(np.int32).max else np.int64
    ex = executor if executor is not None else InlineExecutor()
    if shares_files(ex):
        axial.order, axial.u, axial.z = (shared_on_disk(a) for a in (axial.order, axial.u, axial.z))
        uu, vv = shared_on_disk(uu), shared_on_disk(vv)
    task = _CoreTriangles(axial, uu, vv, u_lo, u_hi, index)
    yield from ordered_map(ex, task, axial.cores())


class _CoreTriangles:
    """Picklable task: the triangles of one core ``(z_lo, z_hi)`` of
    :func:`_chunked_triangles` (ascending vertices, int ``index``)."""

    def __init__(
        self, axial: AxialChunks, uu: np.ndarray, vv: np.ndarray, u_lo: float, u_hi: float,
        index: type[np.signedinteger],
    ) -> None:
        self.axial, self.uu, self.vv, self.u_lo, self.u_hi, self.index = axial, uu, vv, u_lo, u_hi, index

    def __call__(self, core: tuple[float, float]) -> np.ndarray:
        z_lo, z_hi = core
        uu, vv = self.uu, self.vv
        ids, tri = self.axial.triangulate(z_lo, z_hi, self.u_lo, self.u_hi)
        t = np.sort(self.axial.order[ids[tri.simplices]], axis=1)
        del tri
        cu = (uu[t[:, 0]] + uu[t[:, 1]] + uu[t[:, 2]]) / 3.0
        cv = (vv[t[:, 0]] + vv[t[:, 1]] + vv[t[:, 2]]) / 3.0
        keep = (cu >= self.u_lo) & (cu < self.u_hi) & (cv >= z_lo) & (cv < z_hi)
        return t[keep].astype(self.index)


def orient_towards_axis(
    faces: np.ndarray,
    arc_mm: np.ndarray,
    axial_mm: np.ndarray,
    circumference_mm: float,
    points_in_world: np.ndarray,
    point_frame: np.ndarray,
) -> np.ndarray:
    """The faces wound so each normal ``(b - a) x (c - a)`` points towards the pipe axis.

    All triangles get one winding in the unrolled plane (arc, axial; arc unwrapped per
    triangle), which on the tube is one side of the wall everywhere, bends included.
    Which side that is (it depends on the direction of travel) is decided by a vote
    against the centre of each point's ring (mean of its keyframe's points).

    Args:
        faces: (F, 3) vertex indices into ``points_in_world``.
        arc_mm, axial_mm: (N,) unrolled coordinates of the points, mm.
        circumference_mm: period of ``arc_mm``.
        points_in_world: (N, 3) mm.
        point_frame: (N,) keyframe index of each point.

    Returns:
        (F, 3) the same triangles, some with two vertices swapped.
    """
    if not len(faces):
        return faces
    circ = circumference_mm
    # A copy wound in the run's scratch (omnipipe.spill), a chunk of triangles at a time:
    # the (F, 3) float64 intermediates are a chunk's, and the faces' pages too
    # (drop_pages), not the mesh's.
    wound = zeros_on_disk(faces.shape, faces.dtype)
    for a in range(0, len(faces), FACE_CHUNK):
        f = np.array(faces[a : a + FACE_CHUNK])
        u = np.asarray(arc_mm[f], float)
        u = (u - u[:, :1] + 0.5 * circ) % circ - 0.5 * circ
        v = np.asarray(axial_mm[f], float)
        area2 = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0])
        neg = area2 < 0
        f[neg] = f[neg][:, [0, 2, 1]]
        wound[a : a + len(f)] = f
        drop_pages()
    centres, row, first = ring_centres(points_in_world, point_frame)
    votes = 0
    for a in range(0, len(wound), FACE_CHUNK):  # (F, 3, 3) float64 a chunk at a time
        f = wound[a : a + FACE_CHUNK]
        p = points_in_world[f]
        normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        inward = centres[row[np.asarray(point_frame[f[:, 0]], np.int64) - first]] - p.mean(axis=1)
        votes += int(np.count_nonzero(np.sum(normal * inward, axis=1) > 0))
        drop_pages()
    if votes < 0.5 * len(wound):
        for a in range(0, len(wound), FACE_CHUNK):
            f = wound[a : a + FACE_CHUNK]
            f[:, [1, 2]] = f[:, [2, 1]]
            drop_pages()
    return wound


def ring_centres(points_in_world: np.ndarray, point_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Each ring's centre (the mean of its keyframe's points) and the keyframes' rows.

    Args:
        points_in_world: (N, 3) mm; point_frame: (N,) int keyframe index of each point.

    Returns:
        centres: (R, 3) mm, one per keyframe that has points, in ascending keyframe
            order (``np.unique(point_frame)``); the sums in the points' order.
        row: (K,) int64, the row of ``centres`` of keyframe ``first + i`` (-1: no points).
        first: the lowest keyframe index.

    A chunk of points at a time (their pages dropped after it, :func:`drop_pages`):
    the same sums as one ``np.add.at`` over them all, nothing of the run's length held.
    """
    lo, hi = 0, -1
    for a in range(0, len(point_frame), FACE_CHUNK):
        part = np.asarray(point_frame[a : a + FACE_CHUNK], np.int64)
        lo, hi = (min(lo, int(part.min())), max(hi, int(part.max()))) if a else (int(part.min()), int(part.max()))
        drop_pages()
    count = np.zeros(hi - lo + 1, np.int64)
    for a in range(0, len(point_frame), FACE_CHUNK):
        count += np.bincount(np.asarray(point_frame[a : a + FACE_CHUNK], np.int64) - lo, minlength=len(count))
        drop_pages()
    row = np.cumsum(count > 0) - 1
    row[count == 0] = -1
    centres = np.zeros((int(np.count_nonzero(count)), 3))
    for a in range(0, len(point_frame), FACE_CHUNK):
        at = row[np.asarray(point_frame[a : a + FACE_CHUNK], np.int64) - lo]
        np.add.at(centres, at, points_in_world[a : a + FACE_CHUNK])
        drop_pages()
    centres /= count[count > 0][:, None]
    return centres, row, lo


ATLAS_ROWS = 256
"""Rows of the texture atlas whose wrapped margin :func:`textured_mesh` fills at a time."""


def atlas_margin(w: int) -> int:
    """Columns of the texture atlas's wrapped margin for an unrolled image W wide (10 %)."""
    return int(np.ceil(0.1 * w))


def textured_mesh(
    faces: np.ndarray,
    points_in_world: np.ndarray,
    arc_mm: np.ndarray,
    axial_mm: np.ndarray,
    unrolled: UnrolledImage,
    atlas: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Seam-split mesh and its atlas: (vertices, faces, uvs v-up, texture image).

    Triangles across angle 0 get copies of their small-arc vertices shifted by one
    circumference; the atlas is the unrolled image plus a wrapped margin on the right
    (:func:`atlas_margin` columns). ``atlas``: an (H, W + margin, 3) array whose first W
    columns hold the unrolled image (the model stage paints into it): its margin is
    filled in place and it is returned, no copy made.
    """
    circ = unrolled.circumference_mm
    h, w = unrolled.image.shape[:2]
    extra = atlas_margin(w)
    if atlas is None:
        atlas = np.concatenate([unrolled.image, unrolled.image[:, :extra]], axis=1)
    elif atlas.shape != (h, w + extra, 3):
        raise ShapeError(f"atlas: expected shape ({h}, {w + extra}, 3), got {atlas.shape}")
    else:
        for top in range(0, h, ATLAS_ROWS):  # every page of the atlas: a band's resident
            atlas[top : top + ATLAS_ROWS, w:] = atlas[top : top + ATLAS_ROWS, :extra]
            drop_pages()
    # The outputs grow with the run: made in the run's scratch (omnipipe.spill), not in
    # memory beside the inputs; the inputs (there too) read and the outputs written a
    # chunk at a time, each chunk's pages dropped after it (drop_pages): a chunk's
    # resident, not the run's. The small-arc corners of the triangles across angle 0
    # are found (and the seam copies' ids written) a chunk of triangles at a time.
    n = len(points_in_world)
    dup = np.unique(
        np.concatenate([f[s] for f, s in _seam_chunks(faces, arc_mm, circ)] or [faces[:0, 0]])
    )
    out_faces = zeros_on_disk(faces.shape, faces.dtype)
    for a, (f, s) in zip(range(0, len(faces), FACE_CHUNK), _seam_chunks(faces, arc_mm, circ), strict=True):
        # The copies are numbered after the points in the order of their originals.
        f[s] = (n + np.searchsorted(dup, f[s])).astype(faces.dtype)
        out_faces[a : a + len(f)] = f
        drop_pages()
    verts = zeros_on_disk((n + len(dup), 3), points_in_world.dtype)
    for a in range(0, n, FACE_CHUNK):
        b = min(a + FACE_CHUNK, n)
        verts[a:b] = points_in_world[a:b]
        drop_pages()
    verts[n:] = points_in_world[dup]
    span = circ * (w + extra) / w

    def uv(arc: np.ndarray, axial: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return arc / span, 1.0 - ((axial - unrolled.axial_min_mm) / unrolled.mm_per_px + 0.5) / h

    uvs = zeros_on_disk((n + len(dup), 2), np.result_type(*uv(arc_mm[:0], axial_mm[:0])))
    for a in range(0, n, FACE_CHUNK):
        b = min(a + FACE_CHUNK, n)
        uvs[a:b] = np.column_stack(uv(arc_mm[a:b], axial_mm[a:b]))
        drop_pages()
    uvs[n:] = np.column_stack(uv(arc_mm[dup] + circ, axial_mm[dup]))
    drop_pages()
    return verts, out_faces, uvs, atlas


def _seam_chunks(
    faces: np.ndarray, arc_mm: np.ndarray, circumference_mm: float
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Per chunk of :data:`FACE_CHUNK` of the (F, 3) ``faces``, in order: a copy of the
    chunk's faces and its (n, 3) bool mask of the small-arc corners of the triangles
    across angle 0 (``arc_mm``: (N,) each vertex's arc, mm, in [0, circumference)); the
    chunk's pages of ``faces`` and ``arc_mm`` dropped once read (:func:`drop_pages`)."""
    for a in range(0, len(faces), FACE_CHUNK):
        f = np.array(faces[a : a + FACE_CHUNK])
        u = arc_mm[f]
        crossing = np.ptp(u, axis=1) > 0.5 * circumference_mm
        shift = crossing[:, None] & (u < 0.5 * circumference_mm)
        drop_pages()
        yield f, shift

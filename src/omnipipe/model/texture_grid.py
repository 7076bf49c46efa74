"""The unrolled wall image (paper Sec. VI) and the wall points of its grid.

The wall is unrolled into an image (:class:`UnrolledImage`): columns are arc length
around the axis (angle x reference radius), rows distance along the pipe, ``mm_per_px``
each. Every cell gets a 3-D wall point by linear interpolation of the measured points
over the unrolled Delaunay triangulation (the same one the mesh uses).

Holes stay holes, as in the mesh (:func:`~omnipipe.model.mesh.mesh_unrolled`): a cell
is no wall when it is farther than ``max_gap_mm`` from every measured point, or when the
triangle it lies in is one the mesh drops: it touches a point that is not wall (``hole``:
a joint's gap, a lateral's opening and the branch seen through it) or has an edge longer
than the mesh's longest (``max_edge_mm``: it bridges a gap, e.g. the wall under standing
water). Such cells are NaN, so no keyframe textures them (the unrolled image's alpha is
False there): a lateral shows as a hole, a joint as a gap, not smeared over.

Memory: the grid is evaluated (:class:`WallGrid`) a strip of rows at a time
(:data:`STRIP_ROWS`), so its float64 intermediates do not grow with the run; the
interpolation's triangulation of a long run is made a chunk of the run at a time
(:class:`~omnipipe.model.chunks.AxialChunks`, also the mesh's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from omnipipe.memory import release_freed_memory
from omnipipe.model.chunks import CHUNK_POINTS, AxialChunks
from omnipipe.spill import drop_pages, is_on_disk, on_disk, zeros_on_disk


@dataclass(frozen=True)
class UnrolledImage:
    """The unrolled wall.

    Attributes:
        image: (H, W, 3) uint8; row 0 is the smallest axial position, column 0 angle 0.
        alpha: (H, W) bool, True where the wall was measured and seen.
        mm_per_px: cell size.
        axial_min_mm: axial position of row 0's centre.
        circumference_mm: arc length of the W columns (one full turn).

    Which keyframe each cell came from (:attr:`CellChoice.source`) is not kept: nothing
    writes it, and at 4 bytes a cell it was the largest array held to the run's end.
    """

    image: np.ndarray
    alpha: np.ndarray
    mm_per_px: float
    axial_min_mm: float
    circumference_mm: float

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(angle_min_deg, angle_max_deg, axial_min_mm, axial_max_mm) of the image."""
        h = self.image.shape[0]
        return (0.0, 360.0, self.axial_min_mm, self.axial_min_mm + h * self.mm_per_px)


STRIP_ROWS = 128
"""Default rows of the unrolled grid processed at a time (a multiple of the tiles' rows):
the stage's float64 intermediates are a few strips, not the run (W x 128 cells; up to
2 x workers strips are in flight on the executor, each with its (W x 130 x 3) float64
rows: 128 rows took 35 MB less than 256 at 2400 frames, and no longer)."""


SECTION_ROWS = 8 * STRIP_ROWS
"""Rows of the unrolled grid textured at a time by the model stage (a multiple of the
strips' rows): the cells' chosen pixels (8 bytes a cell) are held for one section, not
the run. A keyframe whose cells lie in two sections has its image read twice."""


EDGE_CHUNK = 1 << 16
"""Triangles whose (T, 3, 3) corners are gathered at a time for their longest edge."""


def dropped_triangles(
    simplices: np.ndarray, xyz: np.ndarray, hole: np.ndarray | None, max_edge_mm: float | None
) -> np.ndarray:
    """(T,) True for the (T, 3) triangles the mesh drops: a corner flagged in ``hole``
    ((N,) bool or None), or a 3-D edge (``xyz``: (N, 3) mm) longer than ``max_edge_mm``."""
    drop = np.zeros(len(simplices), bool)
    if hole is not None:
        drop |= hole[simplices].any(axis=1)
    if max_edge_mm is not None:
        for a in range(0, len(simplices), EDGE_CHUNK):
            p = xyz[simplices[a : a + EDGE_CHUNK]]
            longest = np.max(
                [np.linalg.norm(p[:, i] - p[:, (i + 1) % 3], axis=1) for i in range(3)], axis=0
            )
            drop[a : a + EDGE_CHUNK] |= longest > max_edge_mm
    return drop


class WallGrid:
    """The unrolled grid's wall points (:func:`wall_points_on_grid`), evaluated a strip of
    rows at a time so that the whole (H, W, 3) float64 grid is never held.

    Up to ``chunk_points`` points (with the wrapped copies): one interpolation over all of
    them, and any strip equals the same rows of the whole grid evaluated at once, bit for
    bit: the interpolation's simplex search starts from the previous cell's simplex, so
    each strip is evaluated from two rows before it (the search is warm when the strip
    starts).

    More points: the rows are evaluated a block at a time (rows whose axial range holds
    about ``chunk_points`` points), each block's interpolation on a chunk of the points
    (:class:`AxialChunks`: the block's rows plus a margin, whose triangles over the
    block's cells are those of all the points) and each cell's distance to the nearest
    point within the chunk (the margin is at least ``max_gap_mm``, so every point within
    that distance of a cell is in it). Then the triangulation's memory does not grow with
    the run, and a row equals the whole set's up to the round-off of the barycentric
    transform (about 1e-12 mm), holes the same.

    With ``hole`` (points that are not wall) or ``max_edge_mm``, the cells in triangles the
    mesh drops (:func:`dropped_triangles`, found per cell with the triangulation's
    ``find_simplex``) are NaN; the other cells are the same bits as without them.

    Attributes:
        shape: (H, W) cells; row r at axial ``axial_min_mm + r * mm_per_px``, column c at
            arc ``(c + 0.5) * circumference_mm / W``.
        axial_min_mm: axial position of row 0 (mm).
    """

    HALO = 2

    def __init__(
        self,
        arc_mm: np.ndarray,
        axial_mm: np.ndarray,
        points_in_world: np.ndarray,
        circumference_mm: float,
        mm_per_px: float,
        max_gap_mm: float,
        chunk_points: int = CHUNK_POINTS,
        hole: np.ndarray | None = None,
        max_edge_mm: float | None = None,
    ) -> None:
        """Triangulate the points (:func:`wall_points_on_grid` for the arguments; a chunk
        of ``chunk_points`` at a time if there are more)."""
        circ = circumference_mm
        margin = 0.1 * circ
        lo, hi = arc_mm < margin, arc_mm > circ - margin
        u = np.concatenate([arc_mm, arc_mm[lo] + circ, arc_mm[hi] - circ])
        z = np.concatenate([axial_mm, axial_mm[lo], axial_mm[hi]])
        xyz = np.concatenate([points_in_world, points_in_world[lo], points_in_world[hi]])
        holes = None
        if hole is not None and len(hole) == len(arc_mm) and bool(np.any(hole)):
            flag = np.asarray(hole, bool)
            holes = np.concatenate([flag, flag[lo], flag[hi]])
        self._masked = holes is not None or max_edge_mm is not None
        self._max_edge_mm = max_edge_mm
        width = int(np.ceil(circ / mm_per_px))
        z0 = float(np.floor(axial_mm.min()))
        height = int(np.ceil((axial_mm.max() - z0) / mm_per_px)) + 1
        self.shape = (height, width)
        self.axial_min_mm = z0
        self._u = (np.arange(width) + 0.5) * (circ / width)
        self._z = z0 + np.arange(height) * mm_per_px
        self._max_gap_mm = max_gap_mm
        self._chunks: AxialChunks | None = None
        self._block: _Block | None = None
        self._drop: np.ndarray | None = None
        if len(u) <= chunk_points:
            uz = np.column_stack([u, z])
            self._interpolate = LinearNDInterpolator(uz, xyz)
            self._tree = cKDTree(uz)
            if self._masked:
                self._drop = dropped_triangles(
                    self._interpolate.tri.simplices, xyz, holes, max_edge_mm
                )
            return
        self._chunks = AxialChunks(u, z, chunk_points)
        del u, z
        # Held through the texture's sections, read a block at a time: in the run's
        # scratch (omnipipe.spill), 48 bytes a point.
        self._chunks.to_disk()
        self._xyz = on_disk(xyz[self._chunks.order])
        del xyz
        self._holes = None if holes is None else holes[self._chunks.order]

    def rows(self, first: int, stop: int) -> np.ndarray:
        """(stop - first, W, 3) wall points of rows [first, stop), mm (NaN: no wall)."""
        if self._chunks is None:
            start = max(first - self.HALO, 0)
            interpolate, tree, drop = self._interpolate, self._tree, self._drop
        else:
            start = first
            if stop <= first:
                return np.zeros((0, self.shape[1], 3))
            block = self._block
            if block is None or not (block.first <= first and stop <= block.last):
                self._block = block = None  # the last block's triangulation freed first
                release_freed_memory()  # (qhull's many small blocks, not left resident)
                self._block = block = self._build_block(*self._span(first, stop))
            interpolate, tree, drop = block.interpolate, block.tree, block.drop
        grid = _evaluate(interpolate, tree, drop, self._u, self._z[start:stop], self._max_gap_mm)
        return grid[first - start :]

    def _span(self, first: int, stop: int) -> tuple[int, int]:
        """(first, last): the rows of the block that holds rows [first, stop), as many
        as hold about ``chunk_points`` points (at least to ``stop``)."""
        chunks = self._chunks
        if chunks is None:
            raise RuntimeError("a block of a wall grid that is not chunked")
        h = self.shape[0]
        i0 = int(np.searchsorted(chunks.z, self._z[first], side="left"))
        i1 = min(i0 + chunks.chunk_points, len(chunks.z))
        z_cap = chunks.z[i1 - 1] if i1 > i0 else self._z[first]
        last = int(np.searchsorted(self._z, z_cap, side="right"))
        return first, min(max(last, stop, first + 1), h)

    def _build_block(self, first: int, last: int) -> _Block:
        """The :class:`_Block` of rows [first, last) (:meth:`_span`), on their verified
        chunk (also an executor task: the grid pickles with its points)."""
        chunks = self._chunks
        if chunks is None:
            raise RuntimeError("a block of a wall grid that is not chunked")
        ids, tri = chunks.triangulate(
            float(self._z[first]), float(self._z[last - 1]), float(self._u[0]),
            float(self._u[-1]), min_margin_mm=self._max_gap_mm,
        )
        # The interpolation's barycentric transforms (a small LAPACK solve per triangle,
        # made on first use) with one BLAS thread: spinning threads on busy cores can
        # stall them for seconds.
        with threadpool_limits(limits=1, user_api="blas"):
            tri.transform  # noqa: B018
        xyz = self._xyz[ids]
        drop = None
        if self._masked:
            holes = None if self._holes is None else self._holes[ids]
            drop = dropped_triangles(tri.simplices, xyz, holes, self._max_edge_mm)
        return _Block(first, last, LinearNDInterpolator(tri, xyz), cKDTree(tri.points), drop)

    def __getstate__(self) -> dict[str, object]:
        """Pickled without the block in use (a task builds its own)."""
        state = self.__dict__.copy()
        state["_block"] = None
        return state


def _contiguous_on_disk(a: np.ndarray, dtype: type | None) -> np.ndarray:
    """``np.ascontiguousarray(a, dtype)``'s values in the run's scratch
    (:func:`~omnipipe.spill.zeros_on_disk`), copied a block of rows at a time (no whole
    copy in memory); ``a`` itself where it is there, contiguous and of the dtype already."""
    a = np.asarray(a)
    dt = a.dtype if dtype is None else np.dtype(dtype)
    if a.dtype == dt and a.flags.c_contiguous and is_on_disk(a):
        return a
    out = zeros_on_disk(a.shape, dt)
    for i in range(0, len(a), _COPY_ROWS):
        out[i : i + _COPY_ROWS] = a[i : i + _COPY_ROWS]
        drop_pages()
    return out


_COPY_ROWS = 1 << 16
"""Rows :func:`_contiguous_on_disk` copies at a time."""


FACE_BLOCK = 1 << 16
"""Triangles :func:`rows_of_faces` reads at a time."""


def rows_of_faces(
    faces: np.ndarray, axial: np.ndarray, z0: float, mm_per_px: float, height: int,
    block: int = FACE_BLOCK,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The (F, 3) ``faces`` (vertex indices into the (N,) ``axial``, mm) in order of the
    first grid row they may cover (:func:`~omnipipe.model._kernels.face_first_rows`):
    (F,) ``order`` in the run's scratch (:func:`~omnipipe.spill.zeros_on_disk`), (height
    + 1,) ``start`` (the triangles of first row r are ``order[start[r]:start[r + 1]]``)
    and the most rows one triangle spans.

    A stable counting sort, a block of ``block`` triangles at a time: one pass counts
    each first row's triangles, a second places them (each block's rows computed again);
    the scratch's pages are dropped after each block. In memory a block's rows, never the
    run's.
    """
    from omnipipe.model._kernels import face_first_rows, place_by_row

    n = len(faces)
    counts = np.zeros(height + 1, np.int64)
    span = 0
    for a in range(0, n, block):
        first, s = face_first_rows(faces[a : a + block], axial, z0, mm_per_px, height)
        span = max(span, int(s))
        counts[1:] += np.bincount(first, minlength=height)
        drop_pages()
    start = np.cumsum(counts)
    at = start[:-1].copy()
    order = zeros_on_disk((n,), faces.dtype)
    for a in range(0, n, block):
        first, _ = face_first_rows(faces[a : a + block], axial, z0, mm_per_px, height)
        place_by_row(first, at, order, a)
        drop_pages()
    return order, start, span


class MeshGrid:
    """The unrolled grid's wall points interpolated over the wall mesh's own triangles (the
    model stage's: :func:`~omnipipe.model.mesh.mesh_unrolled`, one triangulation for the
    mesh and the texture), evaluated a strip of rows at a time.

    The same grid as :class:`WallGrid` of the mesh's points with its ``hole`` and
    ``max_edge_mm`` (the mesh's triangles are the unrolled Delaunay's, less the ones it
    drops: those are the cells :class:`WallGrid` leaves NaN), to rounding: a cell in a
    triangle is the triangle's linear interpolation (barycentric coordinates of the
    unrolled cell, :func:`~omnipipe.model._kernels.rasterise_faces`); a cell in no
    triangle, or farther than ``max_gap_mm`` from every point (unrolled, the arc's wrap
    included), is NaN. Each strip draws only the triangles over its rows (the triangles
    in order of their rows, :func:`rows_of_faces`: 4 or 8 bytes
    a triangle, in the run's scratch), so a strip costs its cells and triangles, and
    nothing of the grid is triangulated again.

    Attributes:
        shape: (H, W) cells; row r at axial ``axial_min_mm + r * mm_per_px``, column c at
            arc ``(c + 0.5) * circumference_mm / W``.
        axial_min_mm: axial position of row 0 (mm).
    """

    def __init__(
        self,
        faces: np.ndarray,
        arc_mm: np.ndarray,
        axial_mm: np.ndarray,
        points_in_world: np.ndarray,
        circumference_mm: float,
        mm_per_px: float,
        max_gap_mm: float,
    ) -> None:
        """Order the (F, 3) ``faces`` (vertex indices into the (N,) ``arc_mm``,
        ``axial_mm``, (N, 3) ``points_in_world``; mm) by their rows."""
        circ = float(circumference_mm)
        width = int(np.ceil(circ / mm_per_px))
        z0 = float(np.floor(np.min(axial_mm)))
        height = int(np.ceil((np.max(axial_mm) - z0) / mm_per_px)) + 1
        self.shape = (height, width)
        self.axial_min_mm = z0
        self._circ, self._mm, self._gap = circ, float(mm_per_px), float(max_gap_mm)
        # Contiguous copies (the kernels' inputs) held through the texture: in the run's
        # scratch (omnipipe.spill; no copy where they are there and contiguous already).
        self._faces, self._arc, self._axial, self._points = (
            _contiguous_on_disk(a, dt)
            for a, dt in ((faces, None), (arc_mm, float), (axial_mm, float), (points_in_world, float))
        )
        self._order, self._start, self._span = rows_of_faces(self._faces, self._axial, z0, self._mm, height)
        self._axial_bounds = _block_bounds(self._axial, NEAR_BLOCK)

    def rows(self, first: int, stop: int) -> np.ndarray:
        """(stop - first, W, 3) wall points of rows [first, stop), mm (NaN: no wall)."""
        from omnipipe.model._kernels import rasterise_faces

        h, w = self.shape
        first, stop = max(int(first), 0), min(int(stop), h)
        grid = np.full((max(stop - first, 0), w, 3), np.nan)
        if stop <= first:
            return grid
        far = np.zeros(grid.shape[:2], bool)
        a = int(self._start[max(first - self._span, 0)])
        b = int(self._start[stop])
        rasterise_faces(
            self._faces, np.asarray(self._order[a:b]), self._arc, self._axial, self._points,
            self._circ, self.axial_min_mm, self._mm, first, self._gap, grid, far,
        )
        if far.any():
            self._unfar(grid, far, first)
        return grid

    def _unfar(self, grid: np.ndarray, far: np.ndarray, first: int) -> None:
        """NaN the ``far`` cells of ``grid`` (rows from ``first``) that no point (their
        triangle's corners are not) is within the gap of: a tree of the points near them."""
        rr, cc = np.nonzero(far)
        z = self.axial_min_mm + (first + rr) * self._mm
        u = (cc + 0.5) * (self._circ / self.shape[1])
        near = _within(self._axial, self._axial_bounds, NEAR_BLOCK, z.min() - self._gap, z.max() + self._gap)
        pu, pz = self._arc[near], self._axial[near]
        margin = 0.1 * self._circ
        lo, hi = pu < margin, pu > self._circ - margin
        uz = np.column_stack([
            np.concatenate([pu, pu[lo] + self._circ, pu[hi] - self._circ]),
            np.concatenate([pz, pz[lo], pz[hi]]),
        ])
        dist = cKDTree(uz).query(np.column_stack([u, z]))[0] if len(uz) else np.full(len(u), np.inf)
        out = dist > self._gap
        grid[rr[out], cc[out]] = np.nan


NEAR_BLOCK = 1 << 12
"""Points per block of :class:`MeshGrid`'s axial bounds (:func:`_block_bounds`)."""


def _block_bounds(values: np.ndarray, block: int) -> np.ndarray:
    """(B, 2) NaN-ignoring (min, max) of each block of ``block`` consecutive values of
    the (N,) ``values`` (NaN: a block of NaN only), read a block at a time."""
    out = np.empty((-(-len(values) // block), 2))
    for i, a in enumerate(range(0, len(values), block)):
        v = np.asarray(values[a : a + block], float)
        out[i] = np.fmin.reduce(v), np.fmax.reduce(v)
    drop_pages()
    return out


def _within(values: np.ndarray, bounds: np.ndarray, block: int, lo: float, hi: float) -> np.ndarray:
    """``np.flatnonzero((values >= lo) & (values <= hi))`` of the (N,) ``values``, reading
    only the blocks (``bounds``: :func:`_block_bounds`) that can hold one: the points near
    a strip of the grid, not a pass over the run's (the points come ring after ring)."""
    hits = np.flatnonzero((bounds[:, 1] >= lo) & (bounds[:, 0] <= hi))
    parts = []
    for b in hits.tolist():
        v = values[b * block : (b + 1) * block]
        parts.append(b * block + np.flatnonzero((v >= lo) & (v <= hi)))
    return np.concatenate(parts) if parts else np.zeros(0, np.intp)


@dataclass(frozen=True)
class _Block:
    """Rows [first, last) of a chunked :class:`WallGrid`: their chunk's interpolation, its
    points' tree (unrolled mm) and its triangles the mesh drops (None: none checked)."""

    first: int
    last: int
    interpolate: LinearNDInterpolator
    tree: cKDTree
    drop: np.ndarray | None


def _evaluate(
    interpolate: LinearNDInterpolator,
    tree: cKDTree,
    drop: np.ndarray | None,
    u: np.ndarray,
    z: np.ndarray,
    max_gap_mm: float,
) -> np.ndarray:
    """(len(z), len(u), 3) interpolated wall points of the cells (u, z), mm; NaN where
    no point is within ``max_gap_mm`` or the cell's triangle is one of ``drop``."""
    gu, gz = np.meshgrid(u, z)
    grid = interpolate(gu, gz)
    cells = np.column_stack([gu.ravel(), gz.ravel()])
    # Cells far from any measured point (gaps in the rings, the hull's long edges).
    dist, _ = tree.query(cells)
    grid.reshape(-1, 3)[dist > max_gap_mm] = np.nan
    if drop is not None:
        # Cells in a triangle the mesh drops (a hole corner, a gap-bridging edge).
        simplex = interpolate.tri.find_simplex(cells)
        grid.reshape(-1, 3)[(simplex >= 0) & drop[simplex]] = np.nan
    return grid


def wall_points_on_grid(
    arc_mm: np.ndarray,
    axial_mm: np.ndarray,
    points_in_world: np.ndarray,
    circumference_mm: float,
    mm_per_px: float,
    max_gap_mm: float,
    strip_rows: int = STRIP_ROWS,
    hole: np.ndarray | None = None,
    max_edge_mm: float | None = None,
) -> tuple[np.ndarray, float]:
    """(H, W, 3) interpolated wall points (NaN outside the measured wall) and the axial origin.

    The whole grid at once (the model stage keeps a :class:`WallGrid` and evaluates it a
    strip at a time); ``strip_rows`` rows are interpolated per call, the result does not
    depend on it.

    Args:
        arc_mm, axial_mm: (N,) unrolled coordinates of the points, arc in [0, circumference).
        points_in_world: (N, 3).
        max_gap_mm: cells farther than this from every point stay NaN (holes stay holes).
        hole: (N,) True for points that are not wall: cells in their triangles stay NaN.
        max_edge_mm: cells in triangles with a longer 3-D edge stay NaN (None: unchecked).
    """
    wall = WallGrid(
        arc_mm, axial_mm, points_in_world, circumference_mm, mm_per_px, max_gap_mm,
        hole=hole, max_edge_mm=max_edge_mm,
    )
    h, w = wall.shape
    grid = np.empty((h, w, 3))
    step = max(1, int(strip_rows))
    for r0 in range(0, h, step):
        grid[r0 : r0 + step] = wall.rows(r0, min(r0 + step, h))
    return grid, wall.axial_min_mm

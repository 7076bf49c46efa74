"""Texture mapping (paper Sec. VI): the unrolled wall image and the mesh's texture.

The wall is unrolled into an image: columns are arc length around the axis (angle
x reference radius), rows distance along the pipe, ``mm_per_px`` each. Every cell
gets a 3-D wall point by linear interpolation of the measured points over the
unrolled Delaunay triangulation (the same one the mesh uses), and its colour from
the keyframe that sees it best:

* visible: the point projects into the valid image (mirror rim, blind centre);
* not in the laser light: farther than ``laser_band_mm`` from the laser plane
  and imaged farther than :data:`LASER_BAND_PX` pixels from the laser line's image
  (there the red laser dominates the LED-lit colour; the stripe is a few pixels wide
  in the image whatever its width in mm);
* sharpest and brightest: the largest image footprint in pixels per millimetre of
  wall (a near, frontal view covers more pixels), from the camera model's
  projection of two small steps on the wall, over the squared distance (the LEDs'
  light falls with it, and with it the signal to noise).

Then the illumination is divided out (:func:`flat_field`): the LEDs' falloff from the
range and incidence of each cell's view (known from the reconstruction) and the
mirror's vignetting as a gain of the image radius estimated from the data.

The image is also the mesh's texture atlas: a vertex's UV is its unrolled position.

Cost: a keyframe can only see the wall within the camera's elevation range, so each
keyframe scores only the grid rows it can possibly see (:func:`visible_rows`, a
conservative window: a cell outside it would score 0). The scoring is then linear in
the length of the run, and identical to scoring every cell from every keyframe.
Memory: the grid is evaluated (:class:`WallGrid`) and scored a strip of rows at a
time (:data:`STRIP_ROWS`, windows per strip), so its float64 intermediates do not grow
with the run; what is kept is the (H, W) keyframe of each cell and the chosen pixels.
The interpolation's triangulation of a long run is made a chunk of the run at a time
(:class:`AxialChunks`, also the mesh's), so it does not grow with the run either.
Choosing (:func:`choose_sources`, no image needed) is separate from sampling
(:func:`texture_samples`, one image) so that the model stage can read each keyframe
once for both its ring colours and its texture cells, in parallel.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from itertools import pairwise

import cv2
import numpy as np
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree
from threadpoolctl import threadpool_limits

from omnipipe.camera import CameraModel, camera_from_rig
from omnipipe.errors import ShapeError
from omnipipe.executor import InlineExecutor, ordered_map
from omnipipe.geometry import apply, invert
from omnipipe.image import sample_bilinear
from omnipipe.memory import release_freed_memory
from omnipipe.rig import Rig


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

TILE = (8, 32)
"""Tiles of :func:`visible_rows` (rows, columns)."""

CHUNK_POINTS = 1 << 16
"""Points per axial chunk of the unrolled triangulations (:class:`AxialChunks`). A set of
no more points is triangulated whole, as before the chunks; a longer run a chunk (plus
margins) at a time, so qhull's memory (a few hundred bytes per point) does not grow with
the run."""

MARGIN_EDGES = 8.0
"""A chunk's first margin on either side of its core, in typical triangle sizes (the
median longest edge of a sample's Delaunay, about one ring spacing): the empty circles of
the wall's triangles span a ring spacing or two, so a few spacings hold them all; where
they reach farther (a hole, the gap between two rings far apart) the chunk's margin is
widened until they fit (:meth:`AxialChunks.triangulate`)."""

_PILOT_POINTS = 1 << 14
"""Points (around the middle of the run) of the Delaunay that sets the typical size."""


def _hull_or_all(u: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Indices of the (n,) points (u, z)'s convex hull vertices, ascending; all of them if
    qhull cannot build the hull (fewer than 3 points, all on a line): a superset serves."""
    if len(u) < 3:
        return np.arange(len(u))
    try:
        return np.sort(ConvexHull(np.column_stack([u, z])).vertices)
    except QhullError:
        return np.arange(len(u))


class AxialChunks:
    """Unrolled points (u, z; z along the pipe, mm) sorted by z and Delaunay-triangulated a
    chunk of z at a time, each chunk's triangles over its region those of all the points.

    Delaunay is local: a triangle is one of the triangulation of all points iff its
    circumcircle holds none of them. A chunk holds every point with z within its region's
    z interval widened by a margin on both sides, plus the vertices of the convex hull of
    all points. A chunk triangle whose circumcircle, over the u range of all points, lies
    within the chunk's z range is one of the whole set's: any point inside that circle
    would be in the chunk, and the chunk's triangle has none inside. The chunk's hull is the whole set's, so every point of the
    region lies in some chunk triangle; once every chunk triangle meeting the region is so
    verified, every triangle of the whole set with a point in the region is one of them
    (two Delaunay triangles that overlap are the same). The margin starts at
    :data:`MARGIN_EDGES` typical edges and widens until that holds (at most to all points:
    then there is nothing to verify). Memory: a chunk's qhull, not the run's, unless holes
    longer than a chunk make the margins so wide.

    Degenerate points (4 or more on one empty circle) have no unique Delaunay
    triangulation: a chunk may split such a polygon differently from the whole set.

    Attributes:
        order: (n,) indices of the input points in z order (the "sorted" indices below).
        u, z: (n,) the coordinates in that order, mm.
        hull: ascending sorted indices of the convex hull's vertices (or a superset).
        u_range: (lowest, highest) u of all points, mm.
        margin_mm: the first margin of each chunk.
        chunk_points: points of a chunk's core (:meth:`cores`).
    """

    def __init__(self, u: np.ndarray, z: np.ndarray, chunk_points: int = CHUNK_POINTS) -> None:
        """Sort (n,) ``u``, ``z`` (mm) by z; find the hull and the typical triangle size."""
        if u.shape != z.shape or u.ndim != 1:
            raise ShapeError(f"u, z: expected two (n,) arrays, got {u.shape} and {z.shape}")
        self.chunk_points = max(3, int(chunk_points))
        self.order = np.argsort(z, kind="stable")
        self.u = np.asarray(u, float)[self.order]
        self.z = np.asarray(z, float)[self.order]
        n = len(self.z)
        block = self.chunk_points
        cand = np.concatenate(
            [a + _hull_or_all(self.u[a : a + block], self.z[a : a + block]) for a in range(0, n, block)]
            or [np.zeros(0, int)]
        )
        self.hull = cand[_hull_or_all(self.u[cand], self.z[cand])]
        self.margin_mm = MARGIN_EDGES * self._typical_edge()
        self.u_range = (float(self.u.min()), float(self.u.max())) if n else (0.0, 0.0)

    def _typical_edge(self) -> float:
        """Median longest edge (mm) of the Delaunay triangles of a slab of points around the
        middle of the run (the z extent of all points if they have none)."""
        n = len(self.z)
        extent = float(self.z[-1] - self.z[0]) if n else 0.0
        m = min(n, max(_PILOT_POINTS, self.chunk_points // 4))
        a = (n - m) // 2
        try:
            tri = Delaunay(np.column_stack([self.u[a : a + m], self.z[a : a + m]])).simplices
        except (QhullError, ValueError):
            return extent
        if not len(tri):
            return extent
        p = np.stack([self.u[a : a + m], self.z[a : a + m]], axis=1)[tri]
        longest = np.max(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2), axis=1)
        return float(np.median(longest))

    def cores(self) -> list[tuple[float, float]]:
        """The chunks' core z intervals ``[lo, hi)``: consecutive, ``chunk_points`` points
        each (the last fewer), the first from -inf and the last to +inf."""
        cuts = np.unique(self.z[self.chunk_points :: self.chunk_points])
        cuts = cuts[cuts > self.z[0]] if len(self.z) else cuts
        return list(pairwise([-np.inf, *cuts.tolist(), np.inf]))

    def triangulate(
        self,
        z_lo: float,
        z_hi: float,
        u_lo: float,
        u_hi: float,
        min_margin_mm: float = 0.0,
    ) -> tuple[np.ndarray, Delaunay]:
        """A chunk whose triangles meeting the box ``[u_lo, u_hi] x [z_lo, z_hi]`` (mm) are
        all triangles of the Delaunay triangulation of all points (class docstring).

        Args:
            z_lo, z_hi: the region along the pipe (may be infinite).
            u_lo, u_hi: the region around it (the chunk's hull slivers at the unrolled
                strip's ends are outside it).
            min_margin_mm: the margin is at least this (e.g. for a nearest-point search).

        Returns:
            ids: (m,) sorted indices of the chunk's points (its hull vertices last).
            tri: their Delaunay triangulation (``tri.points[i]`` is point ``ids[i]``).
        """
        n = len(self.z)
        margin = max(self.margin_mm, float(min_margin_mm), 0.0)
        while True:
            a = int(np.searchsorted(self.z, z_lo - margin, side="left"))
            b = int(np.searchsorted(self.z, z_hi + margin, side="right"))
            # Every point with z in [lo, hi] is in the chunk (infinite: the run's end).
            lo = -np.inf if a == 0 else z_lo - margin
            hi = np.inf if b == n else z_hi + margin
            extra = self.hull[(self.hull < a) | (self.hull >= b)]
            ids = np.concatenate([np.arange(a, b), extra])
            tri = Delaunay(np.column_stack([self.u[ids], self.z[ids]]))
            reach = _circle_reach(tri, z_lo, z_hi, u_lo, u_hi, self.u_range)
            if reach is None:
                return ids, tri
            c_lo, c_hi = reach
            if c_lo >= lo and c_hi <= hi:
                return ids, tri
            # Widened on the side(s) that fail only: beyond the run's end (infinite), a
            # circle's reach costs nothing.
            need = max(z_lo - c_lo if c_lo < lo else 0.0, c_hi - z_hi if c_hi > hi else 0.0)
            margin = max(2.0 * margin, 1.25 * need, 1e-3)


def _circle_reach(
    tri: Delaunay,
    z_lo: float,
    z_hi: float,
    u_lo: float,
    u_hi: float,
    u_all: tuple[float, float] = (-np.inf, np.inf),
) -> tuple[float, float] | None:
    """(lowest, highest) z (mm) that the circumcircles of the triangles of ``tri`` whose
    bounding boxes meet ``[u_lo, u_hi] x [z_lo, z_hi]`` reach within the points' u range
    ``u_all`` (mm; no point outside it can lie in a circle there), widened by their
    round-off; None if no triangle meets the box. A flat triangle's circle is infinite.

    The u range matters at the run's ends: a nearly flat triangle along the last ring
    has a circle of hundreds of metres whose lowest point lies far outside the strip's
    u range; within it the circle stays close to the ring.
    """
    s = tri.simplices
    p = tri.points
    pu, pz = p[s, 0], p[s, 1]
    meets = (
        (pu.max(axis=1) >= u_lo) & (pu.min(axis=1) <= u_hi)
        & (pz.max(axis=1) >= z_lo) & (pz.min(axis=1) <= z_hi)
    )
    if not meets.any():
        return None
    pu, pz = pu[meets], pz[meets]
    bu, bz = pu[:, 1] - pu[:, 0], pz[:, 1] - pz[:, 0]
    cu, cz = pu[:, 2] - pu[:, 0], pz[:, 2] - pz[:, 0]
    d = 2.0 * (bu * cz - bz * cu)
    b2, c2 = bu * bu + bz * bz, cu * cu + cz * cz
    with np.errstate(divide="ignore", invalid="ignore"):
        ou = (cz * b2 - bz * c2) / d
        oz = (bu * c2 - cu * b2) / d
        r = np.hypot(ou, oz)
        centre = pz[:, 0] + oz
        tol = 1e-9 * (np.abs(centre) + np.abs(pu[:, 0] + ou) + r) + 1e-9
        r = r + tol
        # The circle's half-height at the u of the points' range nearest its centre.
        off = np.abs(pu[:, 0] + ou - np.clip(pu[:, 0] + ou, u_all[0], u_all[1]))
        half = np.sqrt(np.maximum((r - off) * (r + off), 0.0)) + tol
        low, high = centre - half, centre + half
    flat = ~(np.isfinite(low) & np.isfinite(high))
    if flat.any():
        return -np.inf, np.inf
    seen = off <= r  # circles wholly beside the points' u range hold none of them
    if not seen.any():
        return float(z_lo), float(z_hi)
    return float(low[seen].min()), float(high[seen].max())


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
    ) -> None:
        """Triangulate the points (:func:`wall_points_on_grid` for the arguments; a chunk
        of ``chunk_points`` at a time if there are more)."""
        circ = circumference_mm
        margin = 0.1 * circ
        lo, hi = arc_mm < margin, arc_mm > circ - margin
        u = np.concatenate([arc_mm, arc_mm[lo] + circ, arc_mm[hi] - circ])
        z = np.concatenate([axial_mm, axial_mm[lo], axial_mm[hi]])
        xyz = np.concatenate([points_in_world, points_in_world[lo], points_in_world[hi]])
        width = int(np.ceil(circ / mm_per_px))
        z0 = float(np.floor(axial_mm.min()))
        height = int(np.ceil((axial_mm.max() - z0) / mm_per_px)) + 1
        self.shape = (height, width)
        self.axial_min_mm = z0
        self._u = (np.arange(width) + 0.5) * (circ / width)
        self._z = z0 + np.arange(height) * mm_per_px
        self._max_gap_mm = max_gap_mm
        self._chunks: AxialChunks | None = None
        self._block: tuple[int, int, LinearNDInterpolator, cKDTree] | None = None
        if len(u) <= chunk_points:
            uz = np.column_stack([u, z])
            self._interpolate = LinearNDInterpolator(uz, xyz)
            self._tree = cKDTree(uz)
            return
        self._chunks = AxialChunks(u, z, chunk_points)
        self._xyz = xyz[self._chunks.order]

    def rows(self, first: int, stop: int) -> np.ndarray:
        """(stop - first, W, 3) wall points of rows [first, stop), mm (NaN: no wall)."""
        if self._chunks is None:
            start = max(first - self.HALO, 0)
            interpolate, tree = self._interpolate, self._tree
        else:
            start = first
            if stop <= first:
                return np.zeros((0, self.shape[1], 3))
            block = self._block
            if block is None or not (block[0] <= first and stop <= block[1]):
                self._block = block = None  # the last block's triangulation freed first
                release_freed_memory()  # (qhull's many small blocks, not left resident)
                self._block = block = self._build_block(first, stop)
            interpolate, tree = block[2], block[3]
        gu, gz = np.meshgrid(self._u, self._z[start:stop])
        grid = interpolate(gu, gz)
        # Cells far from any measured point (gaps in the rings, the hull's long edges).
        dist, _ = tree.query(np.column_stack([gu.ravel(), gz.ravel()]))
        grid.reshape(-1, 3)[dist > self._max_gap_mm] = np.nan
        return grid[first - start :]

    def _build_block(
        self, first: int, stop: int
    ) -> tuple[int, int, LinearNDInterpolator, cKDTree]:
        """(first, stop', interpolation, tree) of rows [first, stop') for stop' >= ``stop``:
        as many rows as hold about ``chunk_points`` points, on their verified chunk."""
        chunks = self._chunks
        if chunks is None:
            raise RuntimeError("a block of a wall grid that is not chunked")
        h = self.shape[0]
        i0 = int(np.searchsorted(chunks.z, self._z[first], side="left"))
        i1 = min(i0 + chunks.chunk_points, len(chunks.z))
        z_cap = chunks.z[i1 - 1] if i1 > i0 else self._z[first]
        last = int(np.searchsorted(self._z, z_cap, side="right"))
        last = min(max(last, stop, first + 1), h)
        ids, tri = chunks.triangulate(
            float(self._z[first]), float(self._z[last - 1]), float(self._u[0]),
            float(self._u[-1]), min_margin_mm=self._max_gap_mm,
        )
        # The interpolation's barycentric transforms (a small LAPACK solve per triangle,
        # made on first use) with one BLAS thread: spinning threads on busy cores can
        # stall them for seconds.
        with threadpool_limits(limits=1, user_api="blas"):
            tri.transform  # noqa: B018
        return first, last, LinearNDInterpolator(tri, self._xyz[ids]), cKDTree(tri.points)


class _ArrayRows:
    """An (H, W, 3) array of grid points seen as :class:`WallGrid` (rows are views)."""

    def __init__(self, grid_points: np.ndarray) -> None:
        if grid_points.ndim != 3 or grid_points.shape[2] != 3:
            raise ShapeError(f"grid_points: expected shape (H, W, 3), got {grid_points.shape}")
        self.shape = grid_points.shape[:2]
        self._grid = grid_points

    def rows(self, first: int, stop: int) -> np.ndarray:
        """(stop - first, W, 3) rows [first, stop) of the array."""
        return self._grid[first:stop]


def wall_points_on_grid(
    arc_mm: np.ndarray,
    axial_mm: np.ndarray,
    points_in_world: np.ndarray,
    circumference_mm: float,
    mm_per_px: float,
    max_gap_mm: float,
    strip_rows: int = STRIP_ROWS,
) -> tuple[np.ndarray, float]:
    """(H, W, 3) interpolated wall points (NaN outside the measured wall) and the axial origin.

    The whole grid at once (the model stage keeps a :class:`WallGrid` and evaluates it a
    strip at a time); ``strip_rows`` rows are interpolated per call, the result does not
    depend on it.

    Args:
        arc_mm, axial_mm: (N,) unrolled coordinates of the points, arc in [0, circumference).
        points_in_world: (N, 3).
        max_gap_mm: cells farther than this from every point stay NaN (holes stay holes).
    """
    wall = WallGrid(arc_mm, axial_mm, points_in_world, circumference_mm, mm_per_px, max_gap_mm)
    h, w = wall.shape
    grid = np.empty((h, w, 3))
    step = max(1, int(strip_rows))
    for r0 in range(0, h, step):
        grid[r0 : r0 + step] = wall.rows(r0, min(r0 + step, h))
    return grid, wall.axial_min_mm


@dataclass(frozen=True)
class CellChoice:
    """Which keyframe textures each wall cell, and where in its image (no image read).

    Attributes:
        source: (H, W) keyframe of each cell (-1: not a wall cell, or no keyframe sees
            it); int16 for fewer than 32767 keyframes, else int32 (:func:`source_dtype`:
            a long run's grid holds millions of cells).
        rows: (K, 2) int per keyframe the rows ``[first, stop)`` holding its cells
            (``first == stop``: none).
        pieces: per keyframe, (n_i, 2) float32 (col, row) pixels of its cells in its image,
            in pieces (one per strip of rows) that concatenate in row-major cell order.
        light: (H, W, 2) float16 per cell the view it is textured from, for the flat field
            (:func:`flat_field`): ``log2`` of the LEDs' relative irradiance
            ``cos(incidence) / range^2`` (range in mm and incidence of the cell's wall
            point seen from the keyframe's rig origin) and the chosen pixel's distance
            from the principal point (px); NaN where no keyframe textures the cell (4 bytes
            a cell: the model stage holds it for the whole grid). None: not kept.
    """

    source: np.ndarray
    rows: np.ndarray
    pieces: tuple[tuple[np.ndarray, ...], ...]
    light: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the unrolled grid."""
        return self.source.shape[0], self.source.shape[1]

    def count(self, k: int) -> int:
        """Cells keyframe k textures."""
        return sum(len(piece) for piece in self.pieces[k])

    def cells(self, k: int) -> np.ndarray:
        """(n_k,) ascending flat (row-major) indices of the cells keyframe k textures
        (searched in its :attr:`rows` only: linear in the run for all keyframes)."""
        first, stop = (int(r) for r in self.rows[k])
        w = self.shape[1]
        return first * w + np.flatnonzero(self.source[first:stop].reshape(-1) == k)

    def pixels(self, k: int) -> np.ndarray:
        """(n_k, 2) float32 (col, row) pixels of keyframe k's cells, in :meth:`cells` order."""
        return _concat_pixels(self.pieces[k])


def source_dtype(keyframes: int) -> type[np.signedinteger]:
    """The smallest signed integer type of :attr:`CellChoice.source` for ``keyframes``
    keyframes (and -1)."""
    return np.int16 if keyframes < np.iinfo(np.int16).max else np.int32


def _concat_pixels(pieces: tuple[np.ndarray, ...]) -> np.ndarray:
    """(n, 2) float32: the pieces concatenated (the piece itself when there is one)."""
    if len(pieces) == 1:
        return pieces[0]
    if not pieces:
        return np.zeros((0, 2), np.float32)
    return np.concatenate(pieces)


def elevation_bounds(
    camera: CameraModel, radii: int = 256, angles: int = 360
) -> tuple[float, float]:
    """Conservative (lowest, highest) elevation (rad, from the rig's xy plane towards +z)
    of every ray the valid image annulus can see.

    The annulus is sampled densely (``radii`` x ``angles``, both boundary circles
    included, so models that are not radially symmetric are covered), and the range is
    widened by the largest change between neighbouring samples (a smooth model cannot
    exceed its sampled extremes by more between samples) plus 1e-3 rad (round-off of
    project versus unproject). (-pi/2, pi/2), no bound, if some sample has no ray.
    """
    r = np.linspace(max(camera.radius_min, 1e-6), camera.radius_max, radii)
    phi = np.linspace(0.0, 2.0 * np.pi, angles, endpoint=False)
    px = np.stack(
        [camera.cx + np.outer(r, np.cos(phi)), camera.cy + np.outer(r, np.sin(phi))], axis=-1
    )
    with np.errstate(invalid="ignore"):
        rays = camera.unproject(px.reshape(-1, 2))
    elev = np.arcsin(np.clip(rays[:, 2], -1.0, 1.0)).reshape(radii, angles)
    if not np.isfinite(elev).all():
        return -0.5 * np.pi, 0.5 * np.pi
    step = max(
        float(np.abs(np.diff(elev, axis=0)).max(initial=0.0)),
        float(np.abs(np.diff(elev, axis=1, append=elev[:, :1])).max(initial=0.0)),
    )
    margin = step + 1e-3
    return max(float(elev.min()) - margin, -0.5 * np.pi), min(float(elev.max()) + margin, 0.5 * np.pi)


def _box_elevations(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P,) lowest and highest elevation (rad) of any point of P axis-aligned boxes
    ((P, 3) corners ``lo`` <= ``hi``, rig frame, mm) seen from the origin."""
    x0, y0, z0 = lo[:, 0], lo[:, 1], lo[:, 2]
    x1, y1, z1 = hi[:, 0], hi[:, 1], hi[:, 2]
    # Nearest and farthest distance from the z axis over the box's xy rectangle.
    rho_min = np.hypot(np.maximum(0.0, np.maximum(x0, -x1)), np.maximum(0.0, np.maximum(y0, -y1)))
    rho_max = np.hypot(np.maximum(np.abs(x0), np.abs(x1)), np.maximum(np.abs(y0), np.abs(y1)))
    # atan2(z, rho) rises with z; with rho it falls above the xy plane and rises below.
    top = np.arctan2(z1, np.where(z1 > 0, rho_min, rho_max))
    bottom = np.arctan2(z0, np.where(z0 < 0, rho_min, rho_max))
    return bottom, top


def _tile_boxes(rows: np.ndarray, tile: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """((T, 3), (T, 3)) NaN-ignoring world box (min, max corners, mm) of each tile of the
    (h, W, 3) grid rows, tiles row-major (NaN where a tile has no wall point)."""
    h, w = rows.shape[:2]
    tr, tc = tile
    ntr, ntc = -(-h // tr), -(-w // tc)
    pad = np.full((ntr * tr, ntc * tc, 3), np.nan)
    pad[:h, :w] = rows
    blocks = pad.reshape(ntr, tr, ntc, tc, 3)
    # NaN-ignoring min/max per tile (fmin/fmax: NaN only where the whole tile is empty).
    lo_t = np.fmin.reduce(np.fmin.reduce(blocks, axis=3), axis=1).reshape(-1, 3)
    hi_t = np.fmax.reduce(np.fmax.reduce(blocks, axis=3), axis=1).reshape(-1, 3)
    return lo_t, hi_t


def _seen_rows(
    rows: np.ndarray,
    rig_from_world: np.ndarray,
    bounds: tuple[float, float],
    tile: tuple[int, int],
) -> np.ndarray:
    """(K, 2) per keyframe the window ``[first, stop)`` of the (h, W, 3) grid ``rows``
    outside which it sees no cell (:func:`visible_rows`, within these rows only).

    Args:
        rows: (h, W, 3) wall points, mm (NaN: none).
        rig_from_world: (K, 4, 4) inverse keyframe poses.
        bounds: the camera's :func:`elevation_bounds` (rad).
        tile: tile size in cells (rows, columns).
    """
    h, w = rows.shape[:2]
    n_k = len(rig_from_world)
    tr, tc = tile
    ntc = -(-w // tc)
    lo_t, hi_t = _tile_boxes(rows, tile)
    n_leaf = len(lo_t)
    size = 1 << max(0, (n_leaf - 1).bit_length())
    lo = np.full((size, 3), np.inf)
    hi = np.full((size, 3), -np.inf)
    full = np.isfinite(lo_t).all(axis=1)
    lo[:n_leaf][full], hi[:n_leaf][full] = lo_t[full], hi_t[full]
    levels = [(lo, hi)]
    while len(levels[-1][0]) > 1:
        a, b = levels[-1]
        levels.append((np.minimum(a[0::2], a[1::2]), np.maximum(b[0::2], b[1::2])))
    e_lo, e_hi = bounds
    corner = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], bool)
    station = np.arange(n_k)
    node = np.zeros(n_k, int)
    for depth in range(len(levels) - 1, -1, -1):
        lo_d, hi_d = levels[depth]
        bl, bh = lo_d[node], hi_d[node]
        keep = np.isfinite(bl).all(axis=1)
        station, node, bl, bh = station[keep], node[keep], bl[keep], bh[keep]
        corners = np.where(corner[None], bh[:, None], bl[:, None])  # (P, 8, 3) world
        m = rig_from_world[station]
        q = np.einsum("pij,pcj->pci", m[:, :3, :3], corners) + m[:, None, :3, 3]
        bottom, top = _box_elevations(q.min(axis=1), q.max(axis=1))
        seen = (top >= e_lo) & (bottom <= e_hi)
        station, node = station[seen], node[seen]
        if depth:
            station = np.repeat(station, 2)
            node = (np.repeat(node, 2) * 2) + np.tile([0, 1], len(node))
    out = np.zeros((n_k, 2), int)
    if len(station):
        first = np.full(n_k, np.iinfo(int).max)
        stop = np.full(n_k, -1)
        tile_row = node // ntc
        np.minimum.at(first, station, tile_row * tr)
        np.maximum.at(stop, station, np.minimum((tile_row + 1) * tr, h))
        has = stop >= 0
        out[has, 0], out[has, 1] = first[has], stop[has]
    return out


LASER_BAND_PX = 4.0
"""Texture is not taken within this many pixels of the laser line's image (its stripe,
blurred by the optics, is a few pixels wide whatever it is in mm on the wall)."""


def laser_line_px(
    camera: CameraModel, q: np.ndarray, px: np.ndarray, n_plane: np.ndarray, o_plane: float
) -> np.ndarray:
    """(n,) distance (px) from each wall point's pixel to the laser line's image at its
    azimuth: the point moved along the rig's z axis (the pipe's direction) onto the laser
    plane ``n . x + o = 0``, projected; inf where that point does not image.

    Args:
        camera: the camera model.
        q: (n, 3) wall points in the rig frame, mm.
        px: (n, 2) their pixels (col, row).
    """
    nz = float(n_plane[2])
    if abs(nz) < 1e-6:  # a plane along the axis: no ring to keep away from
        return np.full(len(q), np.inf)
    on_plane = q.copy()
    on_plane[:, 2] -= (q @ n_plane + o_plane) / nz
    line_px, ok = camera.project(on_plane)
    d = np.linalg.norm(line_px - px, axis=1)
    return np.where(ok & np.isfinite(d), d, np.inf)


LIGHT_DTYPE = np.float16
"""Type of :attr:`CellChoice.light` (log2 irradiance to 1e-3, radius to 0.25 px at 600 px)."""

FLAT_FIELD_BINS = 32
"""Bins of image radius (equal cell counts) of the data-driven vignetting gain."""

FLAT_FIELD_LEVEL = 128.0
"""Median luminance (8-bit) of the flat-fielded unrolled wall."""


def flat_field(unrolled: UnrolledImage, light: np.ndarray) -> UnrolledImage:
    """The unrolled wall with the LEDs' falloff and the mirror's vignetting divided out.

    Each cell was imaged with gain ``E x V``: ``E = cos(incidence) / range^2`` of its wall
    point seen from the keyframe's rig origin (:attr:`CellChoice.light`, from the
    reconstruction; the LEDs sit near the axis, close to it), and ``V(r)`` a gain of the
    image radius ``r`` of its pixel: the mirror's vignetting plus whatever ``E``'s model
    misses (the LEDs' own position and beam). ``V`` is estimated from the data, not
    from a rig's parameters: the median of ``luminance / E`` over the cells of each
    of :data:`FLAT_FIELD_BINS` radius bins (equal counts; interpolated between), over
    its overall median. Every wall point around the pipe is seen at every radius, so the
    wall's own reflectance averages out per bin. Colours are divided by ``E x V``
    (clipped to 1/10..10 of the typical gain: grazing views are not blown up) and the
    whole image scaled so its median luminance is :data:`FLAT_FIELD_LEVEL`.

    Args:
        unrolled: the painted unrolled wall.
        light: (H, W, 2) :attr:`CellChoice.light` of its cells.

    Returns:
        The same image, corrected (cells without ``light`` only scaled).
    """
    img = unrolled.image
    h, w = img.shape[:2]
    if light.shape != (h, w, 2):
        raise ShapeError(f"light: expected shape ({h}, {w}, 2), got {light.shape}")
    stride = max(1, (h * w) // 2_000_000)  # the estimate from at most ~2 M cells
    lum = img.reshape(-1, 3)[::stride].astype(np.float32).mean(axis=1)
    irr = np.exp2(light.reshape(-1, 2)[::stride, 0].astype(np.float32))
    rad = light.reshape(-1, 2)[::stride, 1].astype(np.float32)
    ok = unrolled.alpha.reshape(-1)[::stride] & np.isfinite(irr) & (irr > 0) & (lum > 2) & (lum < 253)
    if np.count_nonzero(ok) < 4 * FLAT_FIELD_BINS:
        return unrolled
    irr_ref = float(np.median(irr[ok]))
    ratio = lum[ok] / (irr[ok] / irr_ref)
    r_ok = rad[ok]
    edges = np.unique(np.quantile(r_ok, np.linspace(0.0, 1.0, FLAT_FIELD_BINS + 1)))
    which = np.clip(np.searchsorted(edges, r_ok, side="right") - 1, 0, max(len(edges) - 2, 0))
    centres = np.array([np.median(r_ok[which == b]) for b in range(len(edges) - 1) if np.any(which == b)])
    level = np.array([np.median(ratio[which == b]) for b in range(len(edges) - 1) if np.any(which == b)])
    vign = level / float(np.median(ratio))

    def gain(cells: np.ndarray) -> np.ndarray:
        """(..., ) float32 relative gain E x V of cells' (..., 2) light."""
        cells = cells.astype(np.float32)
        g = (np.exp2(cells[..., 0]) / irr_ref) * np.interp(cells[..., 1], centres, vign)
        return np.where(np.isfinite(g), np.clip(g, 0.1, 10.0), 1.0).astype(np.float32)

    # One scale for the whole wall: its corrected median luminance to the target level.
    seen = unrolled.alpha.reshape(-1)[::stride]
    corrected = lum[seen] / gain(light.reshape(-1, 2)[::stride][seen])
    scale = FLAT_FIELD_LEVEL / max(float(np.median(corrected)), 1e-6)
    out = np.empty_like(img)
    for r0 in range(0, h, STRIP_ROWS):  # float32 intermediates a strip of rows at a time
        g = gain(light[r0 : r0 + STRIP_ROWS])
        part = img[r0 : r0 + STRIP_ROWS].astype(np.float32) * (scale / g)[..., None]
        out[r0 : r0 + STRIP_ROWS] = np.clip(np.round(part), 0, 255).astype(np.uint8)
    return replace(unrolled, image=out)


def _rig_from_world(world_from_rig: np.ndarray) -> np.ndarray:
    """(K, 4, 4) inverses of the (K, 4, 4) poses."""
    if not len(world_from_rig):
        return np.zeros((0, 4, 4))
    return np.stack([invert(T) for T in world_from_rig])


def visible_rows(
    camera: CameraModel,
    world_from_rig: np.ndarray,
    grid_points: np.ndarray,
    tile: tuple[int, int] = TILE,
) -> np.ndarray:
    """(K, 2) per keyframe a window ``[first, stop)`` of grid rows outside which it sees
    no cell: every cell outside projects outside the valid image (its score is 0).

    Conservative by construction: the grid is cut into tiles (``tile`` = rows, columns)
    with the axis-aligned world box of their wall points; a binary tree of boxes over
    the tiles (row-major) is descended per keyframe, keeping a box while the elevation
    range of its rig-frame bounding box meets the camera's :func:`elevation_bounds`.
    The window spans the kept tiles. Cost: about (kept tiles + log tiles) box tests per
    keyframe, so linear in the length of the run. (:func:`choose_sources` does the same
    per strip of rows, on the strip's tiles.)

    Args:
        camera: the camera model (its valid annulus).
        world_from_rig: (K, 4, 4) keyframe poses (mm).
        grid_points: (H, W, 3) wall point of each cell, mm (NaN: none).
        tile: tile size in cells (rows, columns).

    Returns:
        (K, 2) int rows; ``first == stop`` (empty) where the keyframe sees no cell.
    """
    return _seen_rows(grid_points, _rig_from_world(world_from_rig), elevation_bounds(camera), tile)


def choose_sources(
    rig: Rig,
    world_from_rig: np.ndarray,
    grid_points: np.ndarray | WallGrid,
    mm_per_px: float,
    laser_band_mm: float = 3.0,
    windowed: bool = True,
    strip_rows: int = STRIP_ROWS,
    executor: Executor | None = None,
    rows: tuple[int, int] | None = None,
    laser_band_px: float = LASER_BAND_PX,
    rows_done: Callable[[int], None] | None = None,
) -> CellChoice:
    """The keyframe that sees each cell best (module docstring) and the cell's pixel in it.

    ``rows`` = ``(first, stop)``: only the grid's rows ``[first, stop)`` (a section along
    the pipe; ``first`` a multiple of the strips' rows), each cell chosen as in the whole
    grid; the choice's rows are then counted from ``first`` (its ``source`` is
    ``(stop - first, W)``). Sections in order of their rows evaluate a :class:`WallGrid`
    as the whole grid does.

    The strips are scored on ``executor`` (:mod:`omnipipe.executor`; None: here), in
    order, a bounded number at a time; the result does not depend on where they ran.

    The grid is processed in strips of ``strip_rows`` rows (rounded up to a multiple of
    the tiles' rows), each with one row on either side for the steps along the pipe; the
    float64 intermediates are a strip's, and the result does not depend on the strip size.

    Args:
        rig: calibration (camera model and laser plane).
        world_from_rig: (K, 4, 4) keyframe poses (mm).
        grid_points: (H, W, 3) wall point of each cell, mm (NaN: none), or a
            :class:`WallGrid` evaluated a strip at a time.
        mm_per_px: cell size (mm).
        laser_band_mm: cells within this distance of the laser plane are not taken.
        laser_band_px: nor cells that image within this many pixels of the laser line
            (:func:`laser_line_px`).
        windowed: score each keyframe only on the rows of the strip it can see
            (:func:`visible_rows` on the strip's tiles; False: every cell from every
            keyframe; the same result, quadratic in the run's length).
        strip_rows: rows per strip.
        rows_done: called with the rows of the section done after each strip (progress).

    Ties go to the earliest keyframe.
    """
    grid = grid_points if isinstance(grid_points, WallGrid) else _ArrayRows(grid_points)
    camera = camera_from_rig(rig)
    h, w = grid.shape
    n_k = len(world_from_rig)
    tr = TILE[0]
    step = max(tr, -(-int(strip_rows) // tr) * tr)  # strips of whole tiles
    top, end = (0, h) if rows is None else (int(rows[0]), int(rows[1]))
    if not 0 <= top <= end <= h or top % step:
        raise ShapeError(
            f"rows: expected 0 <= first <= stop <= {h} with first a multiple of {step}, got {rows}"
        )
    rig_from_world = _rig_from_world(world_from_rig)
    bounds = elevation_bounds(camera)

    def strips():  # each strip and a row either side (np.gradient along z), made as needed
        for r0 in range(top, end, step):
            r1 = min(r0 + step, end)
            lo, hi = max(r0 - 1, 0), min(r1 + 1, h)
            yield (
                rig, camera, rig_from_world, grid.rows(lo, hi), r0 - lo, r1 - r0, bounds,
                mm_per_px, laser_band_mm, windowed, laser_band_px,
            )

    def scored():  # each strip's scores; ``rows_done`` told once the strip is used
        results = ordered_map(executor or InlineExecutor(), _strip_task, strips())
        for r0, result in zip(range(0, end - top, step), results, strict=True):
            yield result
            if rows_done is not None:
                rows_done(min(r0 + step, end - top))

    return _collect_strips(scored(), n_k, w, step, end - top)


def _collect_strips(
    scored: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    n_k: int,
    w: int,
    step: int,
    n_rows: int,
) -> CellChoice:
    """The :class:`CellChoice` of ``n_rows`` x ``w`` cells from the strips' choices
    (:func:`_choose_in_strip`, in order, ``step`` rows each) among ``n_k`` keyframes."""
    source = np.full((n_rows, w), -1, source_dtype(n_k))
    light = np.full((n_rows, w, 2), np.nan, LIGHT_DTYPE)
    first = np.full(n_k, n_rows)
    stop = np.zeros(n_k, int)
    pieces: list[list[np.ndarray]] = [[] for _ in range(n_k)]
    for r0, (best, best_px, idx, best_light) in zip(range(0, n_rows, step), scored, strict=True):
        r1 = min(r0 + step, n_rows)
        source[r0:r1].reshape(-1)[idx] = best
        light[r0:r1].reshape(-1, 2)[idx] = best_light
        chosen = best >= 0
        order = np.argsort(best[chosen], kind="stable")
        keys = best[chosen][order]
        px = best_px[chosen][order]
        if not len(keys):  # no cell of this strip is seen by any keyframe
            continue
        cell_rows = r0 + idx[chosen][order] // w
        ks, starts = np.unique(keys, return_index=True)
        ends = np.append(starts[1:], len(keys))
        for k, a, b in zip(ks.tolist(), starts.tolist(), ends.tolist(), strict=True):
            pieces[k].append(px[a:b])
            first[k] = min(first[k], int(cell_rows[a]))
            stop[k] = max(stop[k], int(cell_rows[b - 1]) + 1)
    has = stop > 0
    spans = np.zeros((n_k, 2), int)
    spans[has, 0], spans[has, 1] = first[has], stop[has]
    return CellChoice(source, spans, tuple(tuple(p) for p in pieces), light)


def _strip_task(args: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Executor task: :func:`_choose_in_strip` of one strip's arguments."""
    return _choose_in_strip(*args)


def _choose_in_strip(
    rig: Rig,
    camera: CameraModel,
    rig_from_world: np.ndarray,
    ext: np.ndarray,
    offset: int,
    n_rows: int,
    bounds: tuple[float, float],
    mm_per_px: float,
    laser_band_mm: float,
    windowed: bool,
    laser_band_px: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`choose_sources` on one strip: rows ``[offset, offset + n_rows)`` of ``ext``
    ((h, W, 3), mm; the other rows are neighbours for the steps along the pipe).

    Returns:
        best: (n,) keyframe of each wall cell of the strip (-1: none).
        best_px: (n, 2) float32 its pixel there.
        idx: (n,) flat indices of the wall cells in the strip (row-major).
        best_light: (n, 2) float32 its :attr:`CellChoice.light` (NaN: none).
    """
    core = ext[offset : offset + n_rows]
    w = core.shape[1]
    flat = core.reshape(-1, 3)
    idx = np.flatnonzero(np.isfinite(flat).all(axis=1))
    p = flat[idx]
    # Two small steps on the wall per cell (along the rows and columns) for the footprint.
    gp = np.where(np.isfinite(ext), ext, 0.0)
    step_u = np.gradient(gp[offset : offset + n_rows], axis=1).reshape(-1, 3)[idx]
    step_z = np.gradient(gp, axis=0)[offset : offset + n_rows].reshape(-1, 3)[idx]
    del gp
    n_k = len(rig_from_world)
    best = np.full(len(idx), -1)
    best_score = np.zeros(len(idx))
    best_px = np.zeros((len(idx), 2), np.float32)
    best_light = np.full((len(idx), 2), np.nan, np.float32)
    # The wall's normal at each cell (world frame), for the LEDs' incidence.
    normal = np.cross(step_u, step_z)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    centre = np.array([camera.cx, camera.cy])
    # The wall cells of rows [r0, r1) are p[row_start[r0]:row_start[r1]] (idx is row-major).
    row_start = np.searchsorted(idx, np.arange(n_rows + 1) * w)
    if windowed:
        windows = _seen_rows(core, rig_from_world, bounds, TILE)
    else:
        windows = np.tile([0, n_rows], (n_k, 1))
    # Products with 3 columns gain nothing from BLAS threads, which only contend with the
    # executor's workers for the cores (the per-cell values do not depend on them).
    with threadpool_limits(limits=1, user_api="blas"):
        for k in range(n_k):
            sl = slice(int(row_start[windows[k, 0]]), int(row_start[windows[k, 1]]))
            if sl.start >= sl.stop:
                continue
            m = rig_from_world[k]
            q, px, score = _view_score(
                rig, camera, m, (p[sl], step_u[sl], step_z[sl]), mm_per_px, laser_band_mm, laser_band_px
            )
            # Views of the window: strictly better, so ties keep the earlier keyframe.
            better = score > best_score[sl]
            best[sl][better] = k
            best_score[sl][better] = score[better]
            best_px[sl][better] = px[better]
            if better.any():
                qb = q[better]
                dist = np.sqrt(np.maximum(np.sum(qb * qb, axis=1), 1e-6))
                cos_i = np.abs(np.sum((normal[sl][better] @ m[:3, :3].T) * qb, axis=1)) / dist
                best_light[sl][better] = np.column_stack(
                    [np.log2(np.maximum(cos_i, 1e-6) / dist**2), np.linalg.norm(px[better] - centre, axis=1)]
                )
    return best, best_px, idx, best_light


def _view_score(
    rig: Rig,
    camera: CameraModel,
    rig_from_world: np.ndarray,
    cells: tuple[np.ndarray, np.ndarray, np.ndarray],
    mm_per_px: float,
    laser_band_mm: float,
    laser_band_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How well one keyframe (pose ``rig_from_world`` (4, 4)) sees wall cells.

    ``cells`` = (points, step_u, step_z): (n, 3) world points (mm) and their steps along
    the rows and columns. Returns (q (n, 3) points in the rig frame, px (n, 2) their
    pixels, score (n,): sharpness (px per mm of wall) over the squared distance, 0 where
    not seen or within the laser's bands).
    """
    p, step_u, step_z = cells
    n_plane, o_plane = rig.laser.normal_in_rig, rig.laser.offset_mm
    m = rig_from_world
    q = apply(m, p)
    px, valid = camera.project(q)
    valid &= np.abs(q @ n_plane + o_plane) > laser_band_mm
    if laser_band_px > 0:
        valid &= laser_line_px(camera, q, px, n_plane, o_plane) > laser_band_px
    px_u, _ = camera.project(q + step_u @ m[:3, :3].T)
    px_z, _ = camera.project(q + step_z @ m[:3, :3].T)
    a, b = px_u - px, px_z - px
    # Pixels per cell area, over the cell area in mm^2: the footprint's scale.
    # Sharpness (pixels per mm of wall) times the LEDs' inverse-square light: the
    # near view is both finer and brighter.
    dist2 = np.maximum(np.sum(q * q, axis=1), 1e-6)
    score = np.sqrt(np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])) / mm_per_px / dist2
    return q, px, np.where(valid & np.isfinite(score), score, 0.0)


def texture_samples(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 bilinear colours of ``image`` ((H, W, 3) or (H, W), uint8 or uint16)
    at (n, 2) float32 pixels (col, row); the border replicated."""
    img = image
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    return sample_bilinear(img, pixels, border=cv2.BORDER_REPLICATE)


def paint(image: np.ndarray, choice: CellChoice, k: int, samples: np.ndarray | None) -> None:
    """Write keyframe k's (n_k, 3) uint8 samples (in :meth:`CellChoice.cells` order) into
    the (H * W, 3) uint8 ``image``.

    Raises:
        ShapeError: the samples are missing or of the wrong length.
    """
    cells = choice.cells(k)  # (not :meth:`CellChoice.count`: the pixels may be dropped)
    n = len(cells)
    if not n:
        return
    if samples is None or len(samples) != n:
        raise ShapeError(f"keyframe {k}: expected {n} texture samples, got "
                         f"{'none' if samples is None else len(samples)}")
    image[cells] = samples


def finish(
    choice: CellChoice,
    image: np.ndarray,
    mm_per_px: float,
    axial_min_mm: float,
    circumference_mm: float,
) -> UnrolledImage:
    """The unrolled image from the choice and the (H * W, 3) uint8 painted ``image``."""
    h, w = choice.shape
    return UnrolledImage(
        image.reshape(h, w, 3),
        choice.source >= 0,
        mm_per_px,
        axial_min_mm,
        circumference_mm,
    )


def assemble(
    choice: CellChoice,
    samples: dict[int, np.ndarray],
    mm_per_px: float,
    axial_min_mm: float,
    circumference_mm: float,
) -> UnrolledImage:
    """The unrolled image from the choice and, per keyframe k, the (n_k, 3) uint8 samples
    of its cells (in the order of ``choice.cells(k)``).

    Raises:
        ShapeError: a keyframe's samples are missing or of the wrong length.
    """
    h, w = choice.shape
    image = np.zeros((h * w, 3), np.uint8)
    for k in range(len(choice.pieces)):
        paint(image, choice, k, samples.get(k))
    return finish(choice, image, mm_per_px, axial_min_mm, circumference_mm)


def unrolled_image(
    rig: Rig,
    world_from_rig: np.ndarray,
    read_frame: Callable[[int], np.ndarray],
    grid_points: np.ndarray | WallGrid,
    axial_min_mm: float,
    circumference_mm: float,
    mm_per_px: float,
    laser_band_mm: float = 3.0,
    progress: Callable[[int], None] | None = None,
) -> UnrolledImage:
    """Colour every grid cell from the keyframe that sees it best (serial image reads).

    Args:
        rig: calibration (camera model and laser plane).
        world_from_rig: (K, 4, 4) keyframe poses.
        read_frame: k -> (H, W, 3) or (H, W) image of keyframe k; read once for each
            keyframe that textures some cell.
        grid_points: (H, W, 3) wall point of each cell (NaN: none), or a :class:`WallGrid`.
        progress: called with k + 1 after keyframe k's image is sampled.
    """
    choice = choose_sources(rig, world_from_rig, grid_points, mm_per_px, laser_band_mm)
    h, w = choice.shape
    image = np.zeros((h * w, 3), np.uint8)
    for k in range(len(world_from_rig)):
        if choice.count(k):
            paint(image, choice, k, texture_samples(read_frame(k), choice.pixels(k)))
            if progress:
                progress(k + 1)
    unrolled = finish(choice, image, mm_per_px, axial_min_mm, circumference_mm)
    return unrolled if choice.light is None else flat_field(unrolled, choice.light)

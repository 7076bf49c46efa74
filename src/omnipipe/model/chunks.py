"""Unrolled points Delaunay-triangulated a chunk along the pipe at a time (:class:`AxialChunks`).

The mesh (:mod:`omnipipe.model.mesh`) and the texture's wall grid
(:class:`~omnipipe.model.texture_grid.WallGrid`) triangulate a long run's unrolled points
(arc, axial; mm) a chunk of the run at a time, each chunk verified to give the triangles
of the whole set over its region, so qhull's memory does not grow with the run.
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np
from scipy.spatial import ConvexHull, Delaunay, QhullError

from omnipipe.errors import ShapeError
from omnipipe.spill import drop_pages, on_disk

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


HULL_DROP_BLOCKS = 8
"""Blocks of the sorted points whose convex hulls :class:`AxialChunks` finds between two
page drops (:func:`omnipipe.spill.drop_pages`): a pass over the run's points maps a few MB
of them at a time, not all."""


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
        # Kept in the run's scratch (omnipipe.spill: read a chunk at a time), each made
        # in turn: one array of the points' length in memory at a time, and the pages
        # each pass mapped (u, z and the order read whole) dropped after it.
        self.order = on_disk(np.argsort(z, kind="stable"))
        drop_pages()
        self.u = on_disk(np.asarray(u, float)[self.order])
        drop_pages()
        self.z = on_disk(np.asarray(z, float)[self.order])
        drop_pages()
        n = len(self.z)
        block = self.chunk_points
        cand = np.concatenate([self._block_hull(a) for a in range(0, n, block)] or [np.zeros(0, int)])
        drop_pages()
        self.hull = cand[_hull_or_all(self.u[cand], self.z[cand])]
        self.margin_mm = MARGIN_EDGES * self._typical_edge()
        self.u_range = (float(self.u.min()), float(self.u.max())) if n else (0.0, 0.0)

    def _block_hull(self, a: int) -> np.ndarray:
        """Sorted indices of the hull vertices (or all, :func:`_hull_or_all`) of the points
        ``a`` to ``a + chunk_points``; every :data:`HULL_DROP_BLOCKS` blocks the pages read
        so far dropped (:func:`omnipipe.spill.drop_pages`)."""
        block = self.chunk_points
        if a and (a // block) % HULL_DROP_BLOCKS == 0:
            drop_pages()
        return a + _hull_or_all(self.u[a : a + block], self.z[a : a + block])

    def to_disk(self) -> None:
        """Keep :attr:`order`, :attr:`u` and :attr:`z` in the run's scratch
        (:mod:`omnipipe.spill`: the same values, resident while read), for a holder that
        keeps the chunks through a long step (made there already: a no-op unless they
        were replaced)."""
        self.order, self.u, self.z = on_disk(self.order), on_disk(self.u), on_disk(self.z)

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

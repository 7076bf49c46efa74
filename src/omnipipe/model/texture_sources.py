"""The texture's source choice: which keyframe colours each cell of the unrolled wall.

A cell takes its colour from the keyframe that sees it best (:func:`choose_sources`):

* visible: the point projects into the valid image (mirror rim, blind centre);
* not in the laser light: farther than ``laser_band_mm`` from the laser plane and
  imaged farther than :data:`~omnipipe.model.texture_light.LASER_BAND_PX` pixels from
  the laser line's image;
* sharpest and brightest: the largest image footprint in pixels per millimetre of
  wall (a near, frontal view covers more pixels), from the camera model's
  projection of two small steps on the wall, over the squared distance (the LEDs'
  light falls with it, and with it the signal to noise).

Cost: a keyframe can only see the wall within the camera's elevation range, so each
keyframe scores only the grid rows it can possibly see (:func:`visible_rows`, a
conservative window: a cell outside it would score 0). The scoring is then linear in
the length of the run, and identical to scoring every cell from every keyframe. Cameras
with a compiled projection score in one compiled pass per strip
(:func:`omnipipe.model._kernels.score_strip`; the same scores to rounding). The grid
is scored a strip of rows at a time; what is kept is the (H, W) keyframe of each cell
and the chosen pixels (:class:`CellChoice`). Choosing needs no image: sampling
(:func:`omnipipe.model.texture.texture_samples`) is separate, so that the model stage
can read each keyframe once for both its ring colours and its texture cells.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from omnipipe.camera import CameraModel, camera_from_rig
from omnipipe.errors import ShapeError
from omnipipe.executor import InlineExecutor, ordered_map
from omnipipe.geometry import apply, invert
from omnipipe.model._kernels import MAG_BIN_RAD, STEP_RAD, score_strip, tile_order
from omnipipe.model.texture_grid import STRIP_ROWS, MeshGrid, WallGrid
from omnipipe.model.texture_light import LASER_BAND_PX, laser_line_px
from omnipipe.rig import Rig

TILE = (8, 32)
"""Tiles of :func:`visible_rows` (rows, columns)."""


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


def magnification_table(camera: CameraModel, factor: float = 1.25) -> np.ndarray:
    """(N,) per elevation bin of :data:`~omnipipe.model._kernels.MAG_BIN_RAD` (from -pi/2
    up) the camera's largest image displacement per radian of ray direction (px/rad)
    within :data:`~omnipipe.model._kernels.STEP_RAD` of the bin, with ``factor`` to spare;
    inf outside the camera's :func:`elevation_bounds` and where the projection's Jacobian
    is not finite (nothing is skipped there). Computed once per camera (its compiled
    projection's parameters) and process.

    Directions are sampled every quarter bin of elevation and every degree of azimuth;
    the largest singular value of :meth:`CameraModel.project_jacobian` at a unit ray is the
    displacement per radian in the worst direction.
    """
    projection = camera.compiled_projection()
    key = None if projection is None else (type(camera).__name__, projection.kind, projection.params, factor)
    if key is not None and key in _MAGNIFICATION:
        return _MAGNIFICATION[key]
    n_bins = int(round(np.pi / MAG_BIN_RAD))
    lo, hi = elevation_bounds(camera)
    first = max(int((lo + 0.5 * np.pi - STEP_RAD) / MAG_BIN_RAD) - 1, 0)
    stop = min(int((hi + 0.5 * np.pi + STEP_RAD) / MAG_BIN_RAD) + 2, n_bins)
    elev = -0.5 * np.pi + (np.arange(4 * first, 4 * stop) + 0.5) * (MAG_BIN_RAD / 4)
    sampled = np.concatenate([
        _sampled_magnification(camera, elev[i : i + MAG_ROWS]) for i in range(0, len(elev), MAG_ROWS)
    ])
    fine = np.full(n_bins, np.inf)
    fine[first:stop] = np.where(np.isfinite(sampled), sampled, np.inf).reshape(-1, 4).max(axis=1)
    reach = int(np.ceil(STEP_RAD / MAG_BIN_RAD)) + 1  # bins a step may turn the ray across
    padded = np.concatenate([np.full(reach, np.inf), fine, np.full(reach, np.inf)])
    table = factor * np.lib.stride_tricks.sliding_window_view(padded, 2 * reach + 1).max(axis=1)
    if key is not None:
        _MAGNIFICATION[key] = table
    return table


_MAGNIFICATION: dict[tuple, np.ndarray] = {}

MAG_ROWS = 64
"""Elevations :func:`magnification_table` samples at a time (each at 360 azimuths): its
temporaries are a block's (about 2 MB), not the whole table's rays (49 MB)."""


def _sampled_magnification(camera: CameraModel, elev: np.ndarray) -> np.ndarray:
    """(len(elev),) the largest singular value of the projection's Jacobian over 360
    azimuths (one a degree) at each elevation ``elev`` (rad); inf where not finite."""
    azim = np.radians(np.arange(360.0))
    e, a = (g.ravel() for g in np.meshgrid(elev, azim, indexing="ij"))
    rays = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=1)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        jac = camera.project_jacobian(rays).reshape(len(elev), len(azim), 2, 3)
        return _largest_singular_2x3(np.nan_to_num(jac, nan=np.inf)).max(axis=1)


def _largest_singular_2x3(jac: np.ndarray) -> np.ndarray:
    """(...,) largest singular value of each (..., 2, 3) matrix J: the square root of
    the larger eigenvalue of the 2 x 2 J J^T, in closed form (an SVD per matrix cost
    0.2 s for the table's 130,000); inf where J has an infinite entry, NaN where NaN."""
    a = np.einsum("...j,...j->...", jac[..., 0, :], jac[..., 0, :])
    d = np.einsum("...j,...j->...", jac[..., 1, :], jac[..., 1, :])
    b = np.einsum("...j,...j->...", jac[..., 0, :], jac[..., 1, :])
    with np.errstate(invalid="ignore", over="ignore"):
        top = 0.5 * (a + d) + np.hypot(0.5 * (a - d), b)
        return np.where(np.isinf(jac).any(axis=(-2, -1)), np.inf, np.sqrt(top))


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
        q = np.matmul(corners, m[:, :3, :3].transpose(0, 2, 1)) + m[:, None, :3, 3]
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


LIGHT_DTYPE = np.float16
"""Type of :attr:`CellChoice.light` (log2 irradiance to 1e-3, radius to 0.25 px at 600 px)."""


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
    grid_points: np.ndarray | WallGrid | MeshGrid,
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
            :class:`WallGrid` or :class:`MeshGrid` evaluated a strip at a time.
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
    grid = _ArrayRows(grid_points) if isinstance(grid_points, np.ndarray) else grid_points
    camera = camera_from_rig(rig)
    h, w = grid.shape
    n_k = len(world_from_rig)
    tr = TILE[0]
    step = max(tr, -(-int(strip_rows) // tr) * tr)  # strips of whole tiles
    top, end = _section(rows, h, step)
    rig_from_world = _rig_from_world(world_from_rig)
    bounds = elevation_bounds(camera)
    magnification = magnification_table(camera)

    starts = range(top, end, step)
    spans = [(max(r0 - 1, 0), min(r0 + step, end) + 1) for r0 in starts]
    spans = [(lo, min(hi, h)) for lo, hi in spans]
    grid_rows = _grid_rows(grid, spans)

    def strips():  # each strip and a row either side (np.gradient along z), made as needed
        for r0, (lo, _), ext in zip(starts, spans, grid_rows, strict=True):
            r1 = min(r0 + step, end)
            yield (
                rig, camera, rig_from_world, ext, r0 - lo, r1 - r0, bounds,
                mm_per_px, laser_band_mm, windowed, laser_band_px, True, magnification,
            )

    def scored():  # each strip's scores; ``rows_done`` told once the strip is used
        results = ordered_map(executor or InlineExecutor(), _strip_task, strips())
        for r0, result in zip(range(0, end - top, step), results, strict=True):
            yield result
            if rows_done is not None:
                rows_done(min(r0 + step, end - top))

    return _collect_strips(scored(), n_k, w, step, end - top)


def _section(rows: tuple[int, int] | None, h: int, step: int) -> tuple[int, int]:
    """``choose_sources``'s ``rows`` as ``(first, stop)``, checked (whole grid when None)."""
    top, end = (0, h) if rows is None else (int(rows[0]), int(rows[1]))
    if not 0 <= top <= end <= h or top % step:
        raise ShapeError(
            f"rows: expected 0 <= first <= stop <= {h} with first a multiple of {step}, got {rows}"
        )
    return top, end


def _grid_rows(grid: WallGrid | MeshGrid | _ArrayRows, spans: list[tuple[int, int]]) -> Iterator[np.ndarray]:
    """Each span's grid rows, in order, evaluated here as the strips are submitted (a
    long run's grid a block at a time: one block's triangulation held). Evaluating them
    in the workers sent each strip its whole block (21 MB pickled at 3,000 frames) and
    held every block of a section here: 90 MB more at the stage's peak for 10 % less
    time."""
    return (grid.rows(lo, hi) for lo, hi in spans)


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
    compiled: bool = True,
    magnification: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`choose_sources` on one strip: rows ``[offset, offset + n_rows)`` of ``ext``
    ((h, W, 3), mm; the other rows are neighbours for the steps along the pipe).
    ``compiled``: score through the camera's compiled projection where it has one
    (:func:`omnipipe.model._kernels.score_strip`; ``magnification``, the camera's
    :func:`magnification_table`, lets it skip views that cannot win; None: none
    skipped); False: the NumPy formulation.

    Returns:
        best: (n,) keyframe of each wall cell of the strip (-1: none).
        best_px: (n, 2) float32 its pixel there.
        idx: (n,) flat indices of the wall cells in the strip (row-major).
        best_light: (n, 2) float32 its :attr:`CellChoice.light` (NaN: none).
    """
    core = ext[offset : offset + n_rows]
    w = core.shape[1]
    idx, tiles, p, step_u, step_z = _strip_cells(ext, offset, n_rows)
    n_k = len(rig_from_world)
    best = np.full(len(idx), -1)
    best_score = np.zeros(len(idx))
    best_px = np.zeros((len(idx), 2), np.float32)
    best_light = np.full((len(idx), 2), np.nan, np.float32)
    # The wall's normal at each cell (world frame), for the LEDs' incidence.
    normal = np.cross(step_u, step_z)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    # The wall cells of rows [r0, r1) are p[row_start[r0]:row_start[r1]] (r0, r1 on bands'
    # first rows: the tiles keep each band's cells in its range).
    row_start = np.searchsorted(idx, np.arange(n_rows + 1) * w)
    if windowed:
        windows = _seen_rows(core, rig_from_world, bounds, TILE)
    else:
        windows = np.tile([0, n_rows], (n_k, 1))
    spans = np.ascontiguousarray(row_start[windows], np.int64)  # (K, 2) cells each keyframe scores
    projection = camera.compiled_projection() if compiled else None
    if projection is not None:
        # Keyframes near the strip first (the kernel's order of equal views in a block).
        origins = -np.einsum("kji,kj->ki", rig_from_world[:, :3, :3], rig_from_world[:, :3, 3])
        near = np.linalg.norm(origins - p.mean(axis=0), axis=1) if len(p) else np.zeros(n_k)
        score_strip(
            np.ascontiguousarray(rig_from_world, float), spans,
            np.argsort(near, kind="stable").astype(np.int64),
            np.full(1, np.inf) if magnification is None else np.asarray(magnification, float),
            projection.kind, projection.params,
            p, step_u, step_z, normal,
            np.append(rig.laser.normal_in_rig, rig.laser.offset_mm).astype(float),
            np.array([laser_band_mm, laser_band_px], float), float(mm_per_px),
            np.array([camera.cx, camera.cy], float), best, best_score, best_px, best_light,
        )
        return _row_major(tiles, best, best_px, best_light, idx)
    cells = (p, step_u, step_z, normal)
    bands = (laser_band_mm, laser_band_px)
    # Products with 3 columns gain nothing from BLAS threads, which only contend with the
    # executor's workers for the cores (the per-cell values do not depend on them).
    with threadpool_limits(limits=1, user_api="blas"):
        for k in range(n_k):
            sl = slice(int(spans[k, 0]), int(spans[k, 1]))
            if sl.start < sl.stop:
                _keep_better(rig, camera, rig_from_world[k], k, cells, sl, mm_per_px, bands, (best, best_score, best_px, best_light))
    return _row_major(tiles, best, best_px, best_light, idx)


def _strip_cells(
    ext: np.ndarray, offset: int, n_rows: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The wall cells of rows ``[offset, offset + n_rows)`` of ``ext`` ((h, W, 3), mm):
    (n,) their flat indices in the strip (row-major), (n,) the order in which they are
    scored (:func:`omnipipe.model._kernels.tile_order`: tiles within each band of
    ``TILE[0]`` rows, the windows' rows, in which the compiled blocks are compact
    patches of wall; each window holds the same cells) and, in that order, (n, 3) their
    points and two small steps on the wall (along the rows and the columns, mm) for
    the footprint."""
    flat = ext[offset : offset + n_rows].reshape(-1, 3)
    idx = np.flatnonzero(np.isfinite(flat).all(axis=1))
    tiles = tile_order(idx, ext.shape[1], TILE[0])
    tiled = idx[tiles]
    gp = np.where(np.isfinite(ext), ext, 0.0)
    step_u = np.gradient(gp[offset : offset + n_rows], axis=1).reshape(-1, 3)[tiled]
    step_z = np.gradient(gp, axis=0)[offset : offset + n_rows].reshape(-1, 3)[tiled]
    return idx, tiles, flat[tiled], step_u, step_z


def _row_major(
    tiles: np.ndarray, best: np.ndarray, best_px: np.ndarray, best_light: np.ndarray, idx: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_choose_in_strip`'s result from the cells in ``tiles`` order (``idx[tiles]``)
    back in ``idx``'s order."""
    back = np.empty_like(tiles)
    back[tiles] = np.arange(len(tiles))
    return best[back], best_px[back], idx, best_light[back]


def _keep_better(
    rig: Rig,
    camera: CameraModel,
    m: np.ndarray,
    k: int,
    cells: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    sl: slice,
    mm_per_px: float,
    bands: tuple[float, float],
    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """Keyframe ``k``'s (pose ``m`` = rig_from_world (4, 4)) view of the cells ``sl`` of
    ``cells`` (points, step_u, step_z, normal), kept in ``out`` (best, best_score,
    best_px, best_light) where strictly better (ties keep the earlier keyframe)."""
    p, step_u, step_z, normal = cells
    best, best_score, best_px, best_light = out
    q, px, score = _view_score(
        rig, camera, m, (p[sl], step_u[sl], step_z[sl]), mm_per_px, bands[0], bands[1]
    )
    better = score > best_score[sl]
    best[sl][better] = k
    best_score[sl][better] = score[better]
    best_px[sl][better] = px[better]
    if better.any():
        qb = q[better]
        dist = np.sqrt(np.maximum(np.sum(qb * qb, axis=1), 1e-6))
        cos_i = np.abs(np.sum((normal[sl][better] @ m[:3, :3].T) * qb, axis=1)) / dist
        centre = np.array([camera.cx, camera.cy])
        best_light[sl][better] = np.column_stack(
            [np.log2(np.maximum(cos_i, 1e-6) / dist**2), np.linalg.norm(px[better] - centre, axis=1)]
        )


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

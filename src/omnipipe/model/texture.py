"""Texture mapping (paper Sec. VI): the unrolled wall image and the mesh's texture.

The wall is unrolled into an image: columns are arc length around the axis (angle
x reference radius), rows distance along the pipe, ``mm_per_px`` each. Every cell
gets a 3-D wall point by linear interpolation of the measured points over the
unrolled Delaunay triangulation (the same one the mesh uses), and its colour from
the keyframe that sees it best:

* visible: the point projects into the valid image (mirror rim, blind centre);
* not in the laser light: farther than ``laser_band_mm`` from the laser plane
  (there the red laser dominates the LED-lit colour);
* sharpest and brightest: the largest image footprint in pixels per millimetre of
  wall (a near, frontal view covers more pixels), from the camera model's
  projection of two small steps on the wall, over the squared distance (the LEDs'
  light falls with it, and with it the signal to noise).

The image is also the mesh's texture atlas: a vertex's UV is its unrolled position.

Cost: a keyframe can only see the wall within the camera's elevation range, so each
keyframe scores only the grid rows it can possibly see (:func:`visible_rows`, a
conservative window: a cell outside it would score 0). The scoring is then linear in
the length of the run, and identical to scoring every cell from every keyframe.
Choosing (:func:`choose_sources`, no image needed) is separate from sampling
(:func:`texture_samples`, one image) so that the model stage can read each keyframe
once for both its ring colours and its texture cells, in parallel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.interpolate import LinearNDInterpolator
from threadpoolctl import threadpool_limits

from omnipipe.camera import CameraModel, camera_from_rig
from omnipipe.errors import ShapeError
from omnipipe.geometry import apply, invert
from omnipipe.image import sample_bilinear
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
        source_frame: (H, W) int, the keyframe each cell's colour came from (-1: none).
    """

    image: np.ndarray
    alpha: np.ndarray
    mm_per_px: float
    axial_min_mm: float
    circumference_mm: float
    source_frame: np.ndarray

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(angle_min_deg, angle_max_deg, axial_min_mm, axial_max_mm) of the image."""
        h = self.image.shape[0]
        return (0.0, 360.0, self.axial_min_mm, self.axial_min_mm + h * self.mm_per_px)


def wall_points_on_grid(
    arc_mm: np.ndarray,
    axial_mm: np.ndarray,
    points_in_world: np.ndarray,
    circumference_mm: float,
    mm_per_px: float,
    max_gap_mm: float,
) -> tuple[np.ndarray, float]:
    """(H, W, 3) interpolated wall points (NaN outside the measured wall) and the axial origin.

    Args:
        arc_mm, axial_mm: (N,) unrolled coordinates of the points, arc in [0, circumference).
        points_in_world: (N, 3).
        max_gap_mm: cells farther than this from every point stay NaN (holes stay holes).
    """
    from scipy.spatial import cKDTree

    circ = circumference_mm
    margin = 0.1 * circ
    lo, hi = arc_mm < margin, arc_mm > circ - margin
    u = np.concatenate([arc_mm, arc_mm[lo] + circ, arc_mm[hi] - circ])
    z = np.concatenate([axial_mm, axial_mm[lo], axial_mm[hi]])
    xyz = np.concatenate([points_in_world, points_in_world[lo], points_in_world[hi]])
    width = int(np.ceil(circ / mm_per_px))
    z0 = float(np.floor(axial_mm.min()))
    height = int(np.ceil((axial_mm.max() - z0) / mm_per_px)) + 1
    gu, gz = np.meshgrid(
        (np.arange(width) + 0.5) * (circ / width), z0 + np.arange(height) * mm_per_px
    )
    grid = LinearNDInterpolator(np.column_stack([u, z]), xyz)(gu, gz)
    # Cells far from any measured point (gaps in the rings, the hull's long edges).
    dist, _ = cKDTree(np.column_stack([u, z])).query(np.column_stack([gu.ravel(), gz.ravel()]))
    grid.reshape(-1, 3)[dist > max_gap_mm] = np.nan
    return grid, z0


@dataclass(frozen=True)
class CellChoice:
    """Which keyframe textures each wall cell, and where in its image (no image read).

    Attributes:
        shape: (H, W) of the unrolled grid.
        cells: (N,) flat (row-major) indices of the wall cells (finite grid points).
        best: (N,) keyframe index of each cell (-1: no keyframe sees it).
        best_px: (N, 2) float32 (col, row) of the cell in that keyframe's image, px.
    """

    shape: tuple[int, int]
    cells: np.ndarray
    best: np.ndarray
    best_px: np.ndarray

    def by_keyframe(self, n_keyframes: int) -> list[np.ndarray]:
        """Per keyframe k, (n_k,) positions into :attr:`cells` of the cells it textures
        (ascending; O(N log N) for all keyframes at once)."""
        order = np.argsort(self.best, kind="stable")
        counts = np.bincount(self.best + 1, minlength=n_keyframes + 1)
        bounds = np.cumsum(counts)
        return [order[bounds[k] : bounds[k + 1]] for k in range(n_keyframes)]


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


def visible_rows(
    camera: CameraModel,
    world_from_rig: np.ndarray,
    grid_points: np.ndarray,
    tile: tuple[int, int] = (8, 32),
) -> np.ndarray:
    """(K, 2) per keyframe a window ``[first, stop)`` of grid rows outside which it sees
    no cell: every cell outside projects outside the valid image (its score is 0).

    Conservative by construction: the grid is cut into tiles (``tile`` = rows, columns)
    with the axis-aligned world box of their wall points; a binary tree of boxes over
    the tiles (row-major) is descended per keyframe, keeping a box while the elevation
    range of its rig-frame bounding box meets the camera's :func:`elevation_bounds`.
    The window spans the kept tiles. Cost: about (kept tiles + log tiles) box tests per
    keyframe, so linear in the length of the run.

    Args:
        camera: the camera model (its valid annulus).
        world_from_rig: (K, 4, 4) keyframe poses (mm).
        grid_points: (H, W, 3) wall point of each cell, mm (NaN: none).
        tile: tile size in cells (rows, columns).

    Returns:
        (K, 2) int rows; ``first == stop`` (empty) where the keyframe sees no cell.
    """
    h, w = grid_points.shape[:2]
    n_k = len(world_from_rig)
    tr, tc = tile
    ntr, ntc = -(-h // tr), -(-w // tc)
    pad = np.full((ntr * tr, ntc * tc, 3), np.nan)
    pad[:h, :w] = grid_points
    blocks = pad.reshape(ntr, tr, ntc, tc, 3)
    # NaN-ignoring min/max per tile (fmin/fmax: NaN only where the whole tile is empty).
    lo_t = np.fmin.reduce(np.fmin.reduce(blocks, axis=3), axis=1).reshape(-1, 3)
    hi_t = np.fmax.reduce(np.fmax.reduce(blocks, axis=3), axis=1).reshape(-1, 3)
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
    e_lo, e_hi = elevation_bounds(camera)
    rig_from_world = np.stack([invert(T) for T in world_from_rig]) if n_k else np.zeros((0, 4, 4))
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
    rows = np.zeros((n_k, 2), int)
    if len(station):
        first = np.full(n_k, np.iinfo(int).max)
        stop = np.full(n_k, -1)
        tile_row = node // ntc
        np.minimum.at(first, station, tile_row * tr)
        np.maximum.at(stop, station, np.minimum((tile_row + 1) * tr, h))
        has = stop >= 0
        rows[has, 0], rows[has, 1] = first[has], stop[has]
    return rows


def choose_sources(
    rig: Rig,
    world_from_rig: np.ndarray,
    grid_points: np.ndarray,
    mm_per_px: float,
    laser_band_mm: float = 3.0,
    windowed: bool = True,
) -> CellChoice:
    """The keyframe that sees each cell best (module docstring) and the cell's pixel in it.

    Args:
        rig: calibration (camera model and laser plane).
        world_from_rig: (K, 4, 4) keyframe poses (mm).
        grid_points: (H, W, 3) wall point of each cell, mm (NaN: none).
        mm_per_px: cell size (mm).
        laser_band_mm: cells within this distance of the laser plane are not taken.
        windowed: score each keyframe only on its :func:`visible_rows` (False: every
            cell from every keyframe; the same result, quadratic in the run's length).

    Ties go to the earliest keyframe.
    """
    if grid_points.ndim != 3 or grid_points.shape[2] != 3:
        raise ShapeError(f"grid_points: expected shape (H, W, 3), got {grid_points.shape}")
    camera = camera_from_rig(rig)
    h, w = grid_points.shape[:2]
    flat = grid_points.reshape(-1, 3)
    ok = np.isfinite(flat).all(axis=1)
    idx = np.flatnonzero(ok)
    p = flat[idx]
    # Two small steps on the wall per cell (along the rows and columns) for the footprint.
    gp = np.where(np.isfinite(grid_points), grid_points, 0.0)
    step_u = np.gradient(gp, axis=1).reshape(-1, 3)[idx]
    step_z = np.gradient(gp, axis=0).reshape(-1, 3)[idx]
    best = np.full(len(idx), -1)
    best_score = np.zeros(len(idx))
    best_px = np.zeros((len(idx), 2), np.float32)
    # The wall cells of rows [r0, r1) are p[row_start[r0]:row_start[r1]] (idx is row-major).
    row_start = np.searchsorted(idx, np.arange(h + 1) * w)
    if windowed:
        windows = visible_rows(camera, world_from_rig, grid_points)
    else:
        windows = np.tile([0, h], (len(world_from_rig), 1))
    n_plane, o_plane = rig.laser.normal_in_rig, rig.laser.offset_mm
    # Products with 3 columns gain nothing from BLAS threads, which only contend with the
    # executor's workers for the cores (the per-cell values do not depend on them).
    with threadpool_limits(limits=1, user_api="blas"):
        for k, T in enumerate(world_from_rig):
            sl = slice(int(row_start[windows[k, 0]]), int(row_start[windows[k, 1]]))
            if sl.start >= sl.stop:
                continue
            rig_from_world = invert(T)
            q = apply(rig_from_world, p[sl])
            px, valid = camera.project(q)
            valid &= np.abs(q @ n_plane + o_plane) > laser_band_mm
            px_u, _ = camera.project(q + step_u[sl] @ rig_from_world[:3, :3].T)
            px_z, _ = camera.project(q + step_z[sl] @ rig_from_world[:3, :3].T)
            a, b = px_u - px, px_z - px
            # Pixels per cell area, over the cell area in mm^2: the footprint's scale.
            # Sharpness (pixels per mm of wall) times the LEDs' inverse-square light: the
            # near view is both finer and brighter.
            dist2 = np.maximum(np.sum(q * q, axis=1), 1e-6)
            score = np.sqrt(np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])) / mm_per_px / dist2
            score = np.where(valid & np.isfinite(score), score, 0.0)
            # Views of the window: strictly better, so ties keep the earlier keyframe.
            better = score > best_score[sl]
            best[sl][better] = k
            best_score[sl][better] = score[better]
            best_px[sl][better] = px[better]
    return CellChoice((h, w), idx, best, best_px)


def texture_samples(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 bilinear colours of ``image`` ((H, W, 3) or (H, W), uint8 or uint16)
    at (n, 2) float32 pixels (col, row); the border replicated."""
    img = image
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    return sample_bilinear(img, pixels, border=cv2.BORDER_REPLICATE)


def assemble(
    choice: CellChoice,
    samples: dict[int, np.ndarray],
    mm_per_px: float,
    axial_min_mm: float,
    circumference_mm: float,
) -> UnrolledImage:
    """The unrolled image from the choice and, per keyframe k, the (n_k, 3) uint8 samples
    of its cells (in the order of ``choice.by_keyframe(K)[k]``).

    Raises:
        ShapeError: a keyframe's samples are missing or of the wrong length.
    """
    h, w = choice.shape
    image = np.zeros((h * w, 3), np.uint8)
    for k, sel in enumerate(choice.by_keyframe(int(choice.best.max(initial=-1)) + 1)):
        if not len(sel):
            continue
        got = samples.get(k)
        if got is None or len(got) != len(sel):
            raise ShapeError(f"keyframe {k}: expected {len(sel)} texture samples, got "
                             f"{'none' if got is None else len(got)}")
        image[choice.cells[sel]] = got
    source = np.full(h * w, -1)
    source[choice.cells] = choice.best
    alpha = source >= 0
    return UnrolledImage(
        image.reshape(h, w, 3),
        alpha.reshape(h, w),
        mm_per_px,
        axial_min_mm,
        circumference_mm,
        source.reshape(h, w),
    )


def unrolled_image(
    rig: Rig,
    world_from_rig: np.ndarray,
    read_frame: Callable[[int], np.ndarray],
    grid_points: np.ndarray,
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
        grid_points: (H, W, 3) wall point of each cell (NaN: none).
        progress: called with k + 1 after keyframe k's image is sampled.
    """
    choice = choose_sources(rig, world_from_rig, grid_points, mm_per_px, laser_band_mm)
    samples: dict[int, np.ndarray] = {}
    for k, sel in enumerate(choice.by_keyframe(len(world_from_rig))):
        if len(sel):
            samples[k] = texture_samples(read_frame(k), choice.best_px[sel])
            if progress:
                progress(k + 1)
    return assemble(choice, samples, mm_per_px, axial_min_mm, circumference_mm)

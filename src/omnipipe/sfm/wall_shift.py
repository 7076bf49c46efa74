"""A keyframe step's axial length read directly off the wall: the unrolled wall's shift.

The laser's template matches (Eq. 17) and the matched features' depths
(:mod:`omnipipe.sfm.scale_check`) both measure a step from sparse evidence. The wall
itself moves past the rig along the pipe axis: with the laser-measured wall cylinder
(:func:`omnipipe.sfm.scale_check.wall_cylinder`) each keyframe's mirror image is
unrolled onto the wall (through :class:`~omnipipe.camera.CameraModel`: rows = rig z in
mm, columns = angle around the axis), and the axial shift that best aligns the two
unrolled walls (normalised cross-correlation over every pixel, a small roll allowed,
sub-sample peak) is the step's axial length. Dense, it needs no feature or corner:
faint tone, joint rings and brick courses all count.

What it is used for: an independent third reading that decides between a step's
candidate lengths (:func:`omnipipe.sfm.step_scale.resolve_by_wall`), never a length
trusted on its own. Measured on the random-wide renders at 640x480
(benchmarks/RESULTS.md, depth6): within 1-2 % on brick, tile and faint smooth walls,
4-13 % on near-plain joints walls, and useless where the step is a large part of the
visible wall (a 108 mm pipe). So every shift carries its own 1-sigma from the spread of
independent angular sectors, with a relative floor, and a reading is refused when the
sectors disagree, the peak is weak or another peak nearly as high lies in the window
(a course of a periodic wall).

Conventions: rig frames as everywhere (z along the rig axis); a shift is the rig's
travel along rig a's z (mm, signed: positive when the rig moved towards +z, so a wall
point at z in rig a lies at z - shift in rig b); grids in mm; angles in radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.sfm._kernels import wall_maps
from omnipipe.sfm.scale_check import WallCylinder

# Angular sectors whose shifts are measured separately: their spread is the sigma.
SECTORS = 8
# Fewest sectors with a peak near the whole wall's for a reading.
MIN_SECTORS = 6
# Relative 1-sigma floor of a shift: the wall radius's error scales it alike (a shift read
# at radius R' of a wall at R is R' / R of the true one) and on the renders brick and
# smooth walls came out 1-2 % off with sector spreads of 0.3-1 %.
REL_SIGMA_FLOOR = 0.015
# The 1-sigma's floor of a keyframe step's shift, as a fraction of the grid step.
GRID_SIGMA_FLOOR = 0.25
# Weakest normalised cross-correlation peak of the whole wall to read a shift from.
MIN_NCC = 0.1
# Highest second peak (another shift: a course off) relative to the best one.
MAX_AMBIGUITY = 0.85
# Largest roll between the two keyframes searched (rad).
MAX_ROLL_RAD = math.radians(1.5)
# Axial band-pass of the unrolled wall (in grid samples): removes per-frame noise below
# it and the rig-fixed shading (the rig's light, vignetting) and the texture's axial
# streaks above it; the angular blur averages noise along the rows.
BAND_SAMPLES = (1.5, 12.0)
ANGULAR_BLUR_SAMPLES = 4.0
# The template's far and near halves must peak within this many sigmas (or two grid
# steps) of the whole wall's shift (at least one of them; one without a peak is no
# witness).
HALVES_SIGMAS = 3.0
# Rows within this distance (mm) of the laser ring plane are masked (the ring's light).
RING_MASK_MM = 6.0
# Fewest template rows (as mm of wall) left after the search margin.
MIN_TEMPLATE_MM = 15.0
# The unrolled wall's grid: half the wall footprint of a pixel at the annulus' middle,
# within these bounds (mm); at most this many columns, and rows up to this many wall
# radii along the axis.
GRID_MM = (0.25, 2.0)
MAX_COLUMNS = 2048
MAX_AXIAL_RADII = 3.0
MAX_FOOTPRINT_GRIDS = 4.0


@dataclass(frozen=True)
class WallShift:
    """The unrolled wall's axial shift between two keyframes.

    Attributes:
        shift_mm: the rig's travel along rig a's z (mm, signed; NaN: not measured).
        sigma_mm: its 1-sigma (mm; NaN: not measured).
        ncc: the whole wall's normalised cross-correlation at the peak (-1..1).
        ambiguity: the best other peak in the window over the peak (0..1).
        sectors: angular sectors whose own peak lies near the whole wall's.
        reason: why there is no reading ("" when there is).
    """

    shift_mm: float
    sigma_mm: float
    ncc: float
    ambiguity: float
    sectors: int
    reason: str = ""

    @property
    def measured(self) -> bool:
        """True when the shift can be used."""
        return math.isfinite(self.shift_mm) and not self.reason


def _none(reason: str, ncc: float = math.nan, ambiguity: float = math.nan, sectors: int = 0) -> WallShift:
    return WallShift(math.nan, math.nan, ncc, ambiguity, sectors, reason)


@dataclass(frozen=True)
class WallGrid:
    """The unrolled wall's sample grid (shared by both keyframes of a step).

    Attributes:
        z_mm: (R,) rig z of the rows (mm), increasing.
        theta: (C,) angle of the columns around the rig axis (rad), from rig x towards y.
        step_mm: row spacing (mm), also about the columns' arc spacing.
    """

    z_mm: np.ndarray
    theta: np.ndarray
    step_mm: float


def wall_grid(camera: CameraModel, radius_mm: float) -> WallGrid | None:
    """The grid of a wall of ``radius_mm`` seen by ``camera``: rows over the rig z the
    mirror sees at that radius (:meth:`CameraModel.elevation_range`), at most
    :data:`MAX_AXIAL_RADII` radii either way; None for a degenerate wall."""
    if not (math.isfinite(radius_mm) and radius_mm > 0):
        return None
    step = float(np.clip(0.5 * radius_mm * camera.angular_resolution(), *GRID_MM))
    lo, hi = camera.elevation_range()
    reach = MAX_AXIAL_RADII * radius_mm
    z = np.arange(
        max(radius_mm * math.tan(lo), -reach) + 2 * step,
        min(radius_mm * math.tan(hi), reach) - 2 * step,
        step,
    )
    # Only rows the image resolves: along the wall a pixel covers at most
    # MAX_FOOTPRINT_GRIDS grid steps (beyond, the wall's finer texture aliases and does
    # not move with the wall: a synthetic faint wall read 12 % short with them).
    near, _ = camera.project(np.column_stack([np.full(len(z), radius_mm), np.zeros(len(z)), z]))
    ahead, _ = camera.project(np.column_stack([np.full(len(z), radius_mm), np.zeros(len(z)), z + step]))
    px_per_step = np.linalg.norm(ahead - near, axis=1)
    z = z[np.isfinite(px_per_step) & (px_per_step * MAX_FOOTPRINT_GRIDS >= 1.0)]
    if len(z) == 0 or z[-1] - z[0] < 3 * MIN_TEMPLATE_MM:
        return None
    z_lo, z_hi = float(z[0]), float(z[-1])
    n_cols = int(min(max(2 * math.pi * radius_mm / step, 180), MAX_COLUMNS))
    return WallGrid(
        np.arange(z_lo, z_hi + 0.5 * step, step), np.arange(n_cols) * (2 * math.pi / n_cols), step
    )


def unrolled_wall(
    camera: CameraModel, gray: np.ndarray, wall: WallCylinder, grid: WallGrid
) -> tuple[np.ndarray, np.ndarray]:
    """The grey image (H, W) sampled on the wall cylinder at ``grid``: ((R, C) float32
    image, (R, C) bool valid), rows within :data:`RING_MASK_MM` of the ring plane
    invalid. The cylinder is ``wall``'s (its axis parallel to rig z through its
    centre), so the rig's offset from the pipe axis in each keyframe is its own."""
    shape = (len(grid.z_mm), len(grid.theta))
    compiled = camera.compiled_projection()
    if compiled is not None:
        map_col = np.empty(shape, np.float32)
        map_row = np.empty(shape, np.float32)
        ok = np.empty(shape, bool)
        wall_maps(
            compiled.kind, compiled.params,
            wall.centre_xy[0] + wall.radius_mm * np.cos(grid.theta),
            wall.centre_xy[1] + wall.radius_mm * np.sin(grid.theta),
            np.ascontiguousarray(grid.z_mm, float), map_col, map_row, ok,
        )
    else:
        map_col, map_row, ok = _wall_maps(camera, wall, grid)
    image = cv2.remap(
        np.asarray(gray, np.float32),
        map_col,
        map_row,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    valid = ok & (np.abs(grid.z_mm - wall.ring_z_mm) > RING_MASK_MM)[:, None]
    return image, valid & (image > 0)


def _wall_maps(
    camera: CameraModel, wall: WallCylinder, grid: WallGrid
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, C) float32 column and row maps (-10 where not valid) and (R, C) valid of the
    wall samples at ``grid`` through :meth:`CameraModel.project` (a camera without a
    compiled projection; :func:`omnipipe.sfm._kernels.wall_maps` gives the same)."""
    z, th = np.meshgrid(grid.z_mm, grid.theta, indexing="ij")
    pts = np.stack(
        [
            wall.centre_xy[0] + wall.radius_mm * np.cos(th),
            wall.centre_xy[1] + wall.radius_mm * np.sin(th),
            z,
        ],
        axis=-1,
    ).reshape(-1, 3)
    px, ok = camera.project(pts)
    px = np.where(ok[:, None], px, -10.0).astype(np.float32)
    return px[:, 0].reshape(z.shape), px[:, 1].reshape(z.shape), ok.reshape(z.shape)


def axial_band_pass(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(R, C) float32: the log image band-passed along the rows (difference of two
    normalised Gaussian blurs, :data:`BAND_SAMPLES`), blurred along the angle; 0 where
    invalid or where the wide blur reaches past the valid region. The log makes the
    rig's multiplicative shading additive and smooth, which the band removes; axial
    streaks (constant along z) vanish with it."""
    v = valid.astype(np.float32)
    u = np.where(valid, np.log(np.maximum(image, 1.0)), 0.0).astype(np.float32)
    # cv2.GaussianBlur(x, (0, 0), ANGULAR_BLUR_SAMPLES, s_z) bit for bit, its angular
    # (row) pass shared by both axial blurs: the same kernels, border and float32
    # buffer, each pass on its own (a one-tap pass of 1 is exact).
    along = _gaussian_kernel(ANGULAR_BLUR_SAMPLES)
    one = np.ones((1, 1), np.float32)
    rows_v = cv2.sepFilter2D(v, -1, along, one)
    rows_u = cv2.sepFilter2D(u, -1, along, one)

    def blur(rows: np.ndarray, s_z: float) -> np.ndarray:
        return cv2.sepFilter2D(rows, -1, one, _gaussian_kernel(s_z))

    fine, wide = BAND_SAMPLES
    w_fine, w_wide = blur(rows_v, fine), blur(rows_v, wide)
    band = blur(rows_u, fine) / np.maximum(w_fine, 1e-6) - blur(rows_u, wide) / np.maximum(w_wide, 1e-6)
    return np.where(valid & (w_wide > 0.9), band, 0.0).astype(np.float32)


def _gaussian_kernel(sigma: float) -> np.ndarray:
    """(k, 1) float32 Gaussian of ``sigma`` samples as :func:`cv2.GaussianBlur` builds it
    for a float32 image (k = round(8 sigma + 1), odd)."""
    return cv2.getGaussianKernel(int(round(sigma * 8 + 1)) | 1, sigma, cv2.CV_32F)


@dataclass(frozen=True)
class _Rows:
    """Which rows of two unrolled walls are compared: keyframe a's rows t0..t1 (the
    template) against b's rows shifted by k_lo..k_hi rows (b's row = a's row + k; a
    shift s mm is k = -s / grid step)."""

    t0: int
    t1: int
    k_lo: int
    k_hi: int


def _rows(n_rows: int, lo_mm: float, hi_mm: float, step_mm: float) -> _Rows:
    """The rows compared for shifts lo..hi mm (two rows beyond each end for the peak's
    fit): the template is every row of a whose partner stays inside b for every
    shift."""
    k_lo = int(math.floor(-hi_mm / step_mm)) - 2
    k_hi = int(math.ceil(-lo_mm / step_mm)) + 2
    return _Rows(max(0, -k_lo), min(n_rows, n_rows - k_hi), k_lo, k_hi)


# A row of an unrolled wall counts as valid when at least this fraction of its columns
# carries the band-passed wall (the rest: beyond the mirror's view or the band's reach),
# and unless it lies in a run of rows at either end of the grid whose band energy
# exceeds this factor times the median row's.
VALID_ROW_FRACTION = 0.5
EDGE_ENERGY_FACTOR = 4.0


def _valid_rows(x: np.ndarray) -> tuple[int, int]:
    """[first, last + 1) of the (R, C) band-passed wall's valid rows (see
    :data:`EDGE_ENERGY_FACTOR`); (0, 0) without any."""
    frac = (x != 0).mean(axis=1)
    ok = frac >= VALID_ROW_FRACTION * max(float(frac.max()), 1e-9)
    idx = np.flatnonzero(ok)
    if not len(idx):
        return 0, 0
    energy = (x.astype(np.float64) ** 2).mean(axis=1)
    high = energy > EDGE_ENERGY_FACTOR * float(np.median(energy[idx]))
    lo, hi = int(idx[0]), int(idx[-1]) + 1
    while lo < hi and high[lo]:
        lo += 1
    while hi > lo and high[hi - 1]:
        hi -= 1
    return lo, hi


def _inside_valid(rows: _Rows, a: np.ndarray, b: np.ndarray) -> _Rows:
    """``rows`` with the template trimmed to a's valid rows (:func:`_valid_rows`) whose
    partners in b stay within b's valid rows at every shift. The view's ends (the
    mirror's rim, the vignetting: rig-fixed, the log image's steepest) band-pass to
    rows of up to 100 times the wall's energy, a ramp that matches itself at every
    shift, so the correlation there is flat and whichever part of it the window's
    template held decided a faint wall's shift (random-wide seed 10, a smooth wall,
    frames at rest: -0.84 / -0.46 / -0.14 mm over windows -2..6 / -4..4 / -6..2 mm)."""
    a0, a1 = _valid_rows(a)
    b0, b1 = _valid_rows(b)
    t0 = max(rows.t0, a0, b0 - rows.k_lo)
    t1 = min(rows.t1, a1, b1 - rows.k_hi)
    return _Rows(t0, max(t1, t0), rows.k_lo, rows.k_hi)


def _padded(b: np.ndarray, roll: int) -> np.ndarray:
    """``b`` with ``roll`` columns wrapped onto either side (the angle is periodic)."""
    return np.concatenate([b[:, b.shape[1] - roll :], b, b[:, :roll]], axis=1) if roll else b


def _curve(a: np.ndarray, b_padded: np.ndarray, rows: _Rows, j0: int, j1: int) -> np.ndarray:
    """(j1 - j0, 2 roll + 1) NCC of a's template rows against b at row offsets
    k_lo + j0 .. k_lo + j1 - 1 and every roll (``b_padded``: :func:`_padded`)."""
    tpl = a[rows.t0 : rows.t1]
    start = rows.t0 + rows.k_lo + j0
    search = b_padded[start : start + tpl.shape[0] + (j1 - j0) - 1]
    return cv2.matchTemplate(search, tpl, cv2.TM_CCORR_NORMED)


def _peak(curve: np.ndarray, shifts: np.ndarray, keep: np.ndarray) -> tuple[float, float, int]:
    """Sub-sample peak of the (S,) ``curve`` over shifts (S,) mm where ``keep``: (shift
    mm, value, index); NaN without a kept sample."""
    if not keep.any():
        return math.nan, math.nan, -1
    k = int(np.argmax(np.where(keep, curve, -np.inf)))
    s = float(shifts[k])
    if 0 < k < len(curve) - 1 and keep[k - 1] and keep[k + 1]:
        y0, y1, y2 = curve[k - 1 : k + 2]
        den = y0 - 2 * y1 + y2
        if den < 0:
            s += 0.5 * (y0 - y2) / den * float(shifts[k + 1] - shifts[k])
    return s, float(curve[k]), k


def _ambiguity(curve: np.ndarray, k: int, keep: np.ndarray) -> float:
    """The highest kept local maximum of ``curve`` outside the best peak's half-height
    width, over the best (0 when none; a negative best gives 1)."""
    best = curve[k]
    if best <= 0:
        return 1.0
    lo = k
    while lo > 0 and curve[lo - 1] > 0.5 * best:
        lo -= 1
    hi = k
    while hi < len(curve) - 1 and curve[hi + 1] > 0.5 * best:
        hi += 1
    inner = curve[1:-1]
    is_max = np.zeros(len(curve), bool)
    is_max[1:-1] = (inner >= curve[:-2]) & (inner >= curve[2:])
    idx = np.arange(len(curve))
    other = is_max & keep & ((idx < lo) | (idx > hi))
    return float(max(curve[other].max(), 0.0) / best) if other.any() else 0.0


def wall_shift(
    camera: CameraModel,
    gray_a: np.ndarray,
    gray_b: np.ndarray,
    wall_a: WallCylinder | None,
    wall_b: WallCylinder | None,
    window_mm: tuple[float, float],
    grid_floor: float = GRID_SIGMA_FLOOR,
    trim_rim: bool = False,
) -> WallShift:
    """The rig's axial travel from keyframe a to b read off the unrolled wall.

    Args:
        camera: the rig's camera model.
        gray_a, gray_b: (H, W) grey images without the laser of the two keyframes.
        wall_a, wall_b: each keyframe's wall cylinder from its laser ring (rig frame).
        window_mm: (lo, hi) signed shifts (mm) searched: bound it by what is known of
            the step (its candidates, the gait) so that a period of a periodic wall
            cannot alias beyond it; the ambiguity test catches one inside it.
        grid_floor: the 1-sigma's floor as a fraction of the grid step
            (:data:`GRID_SIGMA_FLOOR` for keyframe steps; frame-to-frame creeps,
            :mod:`omnipipe.sfm.creep`, state their own).
        trim_rim: the template kept off the view's ends (:func:`_inside_valid`); on for
            frame-to-frame creeps, not yet measured on keyframe steps.

    Returns:
        The shift with its 1-sigma (the sectors' scatter about their first harmonic,
        :func:`_harmonic_mean`; at least :data:`REL_SIGMA_FLOOR` of the shift and
        ``grid_floor`` of the grid), or a reason why not.
    """
    if wall_a is None or wall_b is None:
        return _none("no wall cylinder")
    grid = wall_grid(camera, 0.5 * (wall_a.radius_mm + wall_b.radius_mm))
    if grid is None:
        return _none("too little wall in view")
    lo, hi = sorted(window_mm)
    rows = _rows(len(grid.z_mm), lo, hi, grid.step_mm)
    if rows.t1 - rows.t0 < MIN_TEMPLATE_MM / grid.step_mm:
        return _none("the step is too long for the wall in view")
    a = axial_band_pass(*unrolled_wall(camera, gray_a, wall_a, grid))
    b = _padded(
        axial_band_pass(*unrolled_wall(camera, gray_b, wall_b, grid)),
        max(1, int(math.ceil(MAX_ROLL_RAD / (grid.theta[1] - grid.theta[0])))),
    )
    if trim_rim:
        rows = _inside_valid(rows, a, b)
        if rows.t1 - rows.t0 < MIN_TEMPLATE_MM / grid.step_mm:
            return _none("the step is too long for the wall in view")
    n_k = rows.k_hi - rows.k_lo + 1
    curve = _curve(a, b, rows, 0, n_k).max(axis=1)
    # A wall point at z in rig a lies at z - shift in rig b: b's row = a's row + k.
    shifts = -(rows.k_lo + np.arange(n_k)) * grid.step_mm
    keep = (shifts >= lo) & (shifts <= hi)
    shift, ncc, k = _peak(curve, shifts, keep)
    if not math.isfinite(shift):
        return _none("empty window")
    if not (0 < k < n_k - 1 and curve[k - 1] < curve[k] > curve[k + 1]):
        # The best correlation at the window's edge: still rising beyond it.
        return _none("no correlation peak inside the window", float(curve[k]))
    ambiguity = _ambiguity(curve, k, keep)
    if ncc < MIN_NCC:
        return _none(f"weak wall correlation ({ncc:.2f})", ncc, ambiguity)
    if ambiguity > MAX_AMBIGUITY:
        return _none(f"another shift correlates nearly as well ({ambiguity:.2f})", ncc, ambiguity)
    found = _sector_shifts(a, b, rows, shifts, shift, k, keep)
    n = int(np.isfinite(found).sum())
    if n < MIN_SECTORS:
        return _none(f"only {n} of {SECTORS} sectors agree", ncc, ambiguity, n)
    mean, sigma_stat = _harmonic_mean(found)
    sigma = math.hypot(sigma_stat, REL_SIGMA_FLOOR * abs(mean), grid_floor * grid.step_mm)
    halves = _half_shifts(a, b, rows, shifts, keep)
    seen = halves[np.isfinite(halves)]
    if not len(seen) or np.any(np.abs(seen - shift) > max(HALVES_SIGMAS * sigma, 2 * grid.step_mm)):
        return _none(
            "the near and far wall disagree ("
            + ", ".join(f"{h:.1f}" for h in halves) + f" mm against {shift:.1f} mm)",
            ncc, ambiguity, n,
        )
    return WallShift(mean, sigma, ncc, ambiguity, n)


def _harmonic_mean(found: np.ndarray) -> tuple[float, float]:
    """The sectors' shifts (SECTORS,) mm (NaN: none) fitted with a constant and the
    first harmonic of the angle, the constant's value and 1-sigma (mm) from the fit's
    residuals. A rig off the pipe axis or tilted against it reads one side of the wall
    long and the other short by the same amount (a first harmonic around the wall, up
    to +-5 % on the renders): it cancels in the constant and is no noise of it."""
    theta = (np.arange(SECTORS) + 0.5) * (2 * math.pi / SECTORS)
    ok = np.isfinite(found)
    A = np.column_stack([np.ones(ok.sum()), np.cos(theta[ok]), np.sin(theta[ok])])
    coef, *_ = np.linalg.lstsq(A, found[ok], rcond=None)
    dof = max(int(ok.sum()) - 3, 1)
    resid = found[ok] - A @ coef
    cov = np.linalg.inv(A.T @ A) * float(resid @ resid) / dof
    return float(coef[0]), math.sqrt(max(float(cov[0, 0]), 0.0))


def _half_shifts(
    a: np.ndarray, b_padded: np.ndarray, rows: _Rows, shifts: np.ndarray, keep: np.ndarray
) -> np.ndarray:
    """(2,) the peak shift (mm) of the template's far and near halves along the axis,
    each over the whole window (NaN: no peak inside it). On a plain wall with axial
    streaks the near wall's best shift may be any (the streaks align at every shift
    once rolled: random-wide seed 10, near wall -5.3 mm, far 21.2 mm for 21.45 true):
    a half peaking elsewhere is a contradiction, one without a peak is no witness."""
    mid = (rows.t0 + rows.t1) // 2
    out = np.full(2, math.nan)
    for i, (t0, t1) in enumerate(((rows.t0, mid), (mid, rows.t1))):
        half = _Rows(t0, t1, rows.k_lo, rows.k_hi)
        c = _curve(a, b_padded, half, 0, len(shifts)).max(axis=1)
        s, _, k = _peak(c, shifts, keep)
        if 0 < k < len(c) - 1 and c[k - 1] < c[k] > c[k + 1]:
            out[i] = s
    return out


def _sector_shifts(
    a: np.ndarray,
    b_padded: np.ndarray,
    rows: _Rows,
    shifts: np.ndarray,
    shift: float,
    k: int,
    keep: np.ndarray,
) -> np.ndarray:
    """(SECTORS,) each angular sector's own peak shift (mm) near the whole wall's peak
    ``shift`` (index ``k`` of ``shifts``) and inside the window (``keep``); NaN where a
    sector has no texture or peaks elsewhere: then it is no witness."""
    n_cols = a.shape[1]
    roll = (b_padded.shape[1] - n_cols) // 2
    width = n_cols // SECTORS
    step = abs(float(shifts[1] - shifts[0]))
    out = np.full(SECTORS, math.nan)
    half = max(3, int(round(6.0 / max(step, 1e-9))))
    j0, j1 = max(k - half, 0), min(k + half + 1, len(shifts))
    for q in range(SECTORS):
        cols = slice(q * width, (q + 1) * width)
        if not np.any(a[rows.t0 : rows.t1, cols]):
            continue
        c = _curve(
            a[:, cols], b_padded[:, q * width : (q + 1) * width + 2 * roll], rows, j0, j1
        ).max(axis=1)
        sq, val, kq = _peak(c, shifts[j0:j1], keep[j0:j1])
        inside = 0 < kq < len(c) - 1 and c[kq - 1] < c[kq] > c[kq + 1]
        if inside and val > 0 and abs(sq - shift) < 0.8 * half * step:
            out[q] = sq
    return out


# Candidate lengths searched from this fraction of the shortest to this multiple of the
# longest (the window; a course beyond it cannot be chosen, one inside it is caught by
# the ambiguity test).
WINDOW = (0.5, 1.6)
# Smallest |cos| between the step's travel and the rig axis for an axial reading.
MIN_AXIAL_COS = 0.5


def candidate_window(candidates_mm: list[float]) -> tuple[float, float]:
    """(lo, hi) lengths (mm) to search around the positive finite candidates
    (:data:`WINDOW`); NaN without any."""
    c = [v for v in candidates_mm if math.isfinite(v) and v > 0]
    return (WINDOW[0] * min(c), WINDOW[1] * max(c)) if c else (math.nan, math.nan)


#: A keyframe step's inputs to :func:`step_wall_length` before its window: the camera,
#: the two grey images, their wall cylinders and rig_b_from_rig_a.
StepImages = tuple[
    CameraModel,
    tuple[np.ndarray, np.ndarray],
    tuple[WallCylinder | None, WallCylinder | None],
    np.ndarray,
]


@dataclass(frozen=True)
class WallLength:
    """A keyframe step's length from the wall's shift (:func:`step_wall_length`).

    Attributes:
        length_mm: the travel's length (mm): the axial shift over the travel direction's
            axial cosine (NaN: not measured).
        sigma_mm: its 1-sigma (mm).
        shift: the underlying reading.
    """

    length_mm: float
    sigma_mm: float
    shift: WallShift

    @property
    def measured(self) -> bool:
        """True when the length can be used."""
        return self.shift.measured and math.isfinite(self.length_mm)


def step_wall_length(
    camera: CameraModel,
    grays: tuple[np.ndarray, np.ndarray],
    walls: tuple[WallCylinder | None, WallCylinder | None],
    b_from_a: np.ndarray,
    window_mm: tuple[float, float],
) -> WallLength:
    """Keyframe step a -> b's length read off the wall, searched over lengths
    ``window_mm`` (lo, hi; mm along the travel, e.g. :func:`candidate_window`).

    Args:
        camera: the rig's camera model.
        grays: (H, W) grey images without the laser of keyframes a and b.
        walls: their wall cylinders (rig frames).
        b_from_a: (4, 4) rig_b_from_rig_a with unit translation (its direction: the
            travel's, whose axial cosine turns the axial shift into the length).
    """
    R, t = np.asarray(b_from_a, float)[:3, :3], np.asarray(b_from_a, float)[:3, 3]
    norm = float(np.linalg.norm(t))
    if norm <= 0 or not all(math.isfinite(w) for w in window_mm):
        return WallLength(math.nan, math.nan, _none("no window"))
    cos_z = float((-R.T @ t)[2] / norm)  # the rig's travel along rig a's z, per length
    if abs(cos_z) < MIN_AXIAL_COS:
        return WallLength(math.nan, math.nan, _none("the step does not travel along the axis"))
    lo, hi = window_mm[0] * cos_z, window_mm[1] * cos_z
    shift = wall_shift(camera, grays[0], grays[1], walls[0], walls[1], (lo, hi))
    if not shift.measured:
        return WallLength(math.nan, math.nan, shift)
    return WallLength(shift.shift_mm / cos_z, shift.sigma_mm / abs(cos_z), shift)

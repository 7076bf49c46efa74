"""The texture's view scores, compiled: every keyframe's score of its cells in one pass.

:func:`omnipipe.model.texture_sources.choose_sources` scores each wall cell from every
keyframe that may see it (visible, out of the laser's bands, image footprint over the
squared distance) and keeps the best. Its NumPy formulation (``_view_score``, kept for
cameras without a compiled projection and as the tests' reference) projects each
cell four times per keyframe into whole-array temporaries; :func:`score_strip` does
the same arithmetic per cell through the camera's compiled projection
(:meth:`omnipipe.camera.base.CameraModel.compiled_projection`), skips the footprint of
cells that are not seen, and updates the best view in place. Scores agree with the
NumPy ones to rounding (a few ulp: BLAS sums the rotations in its own order), so a
choice can differ only between views whose scores tie to 1e-15.

Its blocks of :data:`BLOCK` cells are the strip's cells in the order the caller gives;
:func:`tile_order` orders a strip's cells by small tiles (8 rows x 4 columns) within
each band of rows, so that a block is a compact patch of wall and its one bound
(:func:`_block_bound`) skips the views that cannot win in more of the blocks than a
block 32 cells long in one row (16 mm of wall at 0.5 mm cells) does.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from omnipipe.camera._kernels import project_block, project_point

STEP_RAD = 0.05
"""The largest turn of the ray (rad) over a cell's step that :func:`_bound` bounds."""

MAG_BIN_RAD = float(np.radians(0.5))
"""Elevation bins of the magnification table :func:`_bound` reads (from -pi/2 up; each
bin holds the camera's largest px per radian within :data:`STEP_RAD` of it)."""

SINE_BINS = 4096
"""Bins of :func:`sine_table` over the sine of the elevation, [-1, 1]."""


@numba.njit(cache=True, error_model="numpy")
def sine_table(mag):  # pragma: no cover - compiled
    """(SINE_BINS + 1,) the magnification table ``mag`` (:func:`_bound`'s, by elevation
    bin) read by the sine of the elevation instead: entry i covers sines in
    [-1 + i h, -1 + (i + 1) h] (h = 2 / SINE_BINS) and holds the largest ``mag[j]`` over
    the bins j that :func:`_bound` takes for any sine there (``int((asin(s) + pi/2) /
    MAG_BIN_RAD)``, clipped; the ends widened by 1e-12, far more than the rounding of
    the index ``int((s + 1) SINE_BINS / 2)`` that reads it). So the entry of a ray is
    never below the bin :func:`_bound` reads for it: a bound from it is never lower (no
    view skipped that :func:`_bound` would not skip), without an arcsine per cell. A
    bin of the sine spans at most two of elevation (0.0005 of sine, 0.0087 rad)."""
    out = np.empty(SINE_BINS + 1)
    h = 2.0 / SINE_BINS
    last = len(mag) - 1
    for i in range(SINE_BINS + 1):
        s0 = max(-1.0 + i * h - 1e-12, -1.0)
        s1 = min(-1.0 + (i + 1) * h + 1e-12, 1.0)
        j0 = min(max(int((math.asin(s0) + 0.5 * math.pi) / MAG_BIN_RAD), 0), last)
        j1 = min(max(int((math.asin(s1) + 0.5 * math.pi) / MAG_BIN_RAD), 0), last)
        top = mag[j0]
        for j in range(j0, j1 + 1):
            top = max(top, mag[j])
        out[i] = top
    return out


@numba.njit(cache=True, error_model="numpy")
def _rotate(m, x, y, z):  # pragma: no cover - compiled
    """R (x, y, z) of the (4, 4) transform ``m``'s rotation."""
    return (
        m[0, 0] * x + m[0, 1] * y + m[0, 2] * z,
        m[1, 0] * x + m[1, 1] * y + m[1, 2] * z,
        m[2, 0] * x + m[2, 1] * y + m[2, 2] * z,
    )


@numba.njit(cache=True, error_model="numpy")
def _bound(p, su, sz, m, mag, mm_per_px):  # pragma: no cover - compiled
    """An upper bound of the cell's score (``tests/model/test_kernels.py``'s reference ``score_cell``) of the cell ``p`` from ``m``.

    Seen from distance d, a step s turns the ray by at most |s| / (d - |s|) (while
    that is below :data:`STEP_RAD`), and the pixel moves by at most that times the
    camera's largest px per radian near the ray's elevation (``mag``: the table of
    :func:`omnipipe.model.texture_sources.magnification_table`; one entry: the same
    everywhere); the footprint's area is at most the product of the two steps' moves.
    inf where a step turns the ray further."""
    rx, ry, rz = _rotate(m, p[0], p[1], p[2])
    qx, qy, qz = rx + m[0, 3], ry + m[1, 3], rz + m[2, 3]
    d2 = qx * qx + qy * qy + qz * qz
    d = math.sqrt(d2)
    lu = math.sqrt(su[0] * su[0] + su[1] * su[1] + su[2] * su[2])
    lz = math.sqrt(sz[0] * sz[0] + sz[1] * sz[1] + sz[2] * sz[2])
    if not (lu < STEP_RAD * (d - lu) and lz < STEP_RAD * (d - lz)):
        return math.inf
    j = 0
    if len(mag) > 1:
        elev = math.asin(min(max(qz / d, -1.0), 1.0))
        j = min(max(int((elev + 0.5 * math.pi) / MAG_BIN_RAD), 0), len(mag) - 1)
    return mag[j] * math.sqrt(lu * lz / ((d - lu) * (d - lz))) / mm_per_px / max(d2, 1e-6)


BLOCK = 32
"""Cells :func:`score_strip` bounds and projects as one block."""

TILE_COLUMNS = 4
"""Columns of :func:`tile_order`'s tiles (with 8 rows: :data:`BLOCK` cells)."""


def tile_order(idx: np.ndarray, width: int, band_rows: int, tile_columns: int = TILE_COLUMNS) -> np.ndarray:
    """(n,) int64 the order of a strip's cells by tiles: ``idx`` (n,) ascending flat
    indices of the cells into a (rows, ``width``) grid (row-major), taken band by band
    of ``band_rows`` rows, in each band tile by tile of ``tile_columns`` columns (left
    to right), row-major inside a tile.

    Cells never leave their band: a range of the row-major cells that starts and ends on
    a band's first row (a multiple of ``band_rows``, or the grid's end) holds the same
    cells in this order, so spans of whole bands need no change."""
    idx = np.asarray(idx, np.int64)
    row, col = idx // width, idx % width
    return np.lexsort((col, row, col // tile_columns, row // band_rows))


@numba.njit(cache=True, error_model="numpy")
def _block_geometry(p, step_u, step_z, n):  # pragma: no cover - compiled
    """Per :data:`BLOCK` of the (n, 3) cells ``p``: (B, 3) centre, (B,) radius (the
    farthest cell from it) and (B, 2) the longest steps along the rows and columns (mm)."""
    n_blocks = (n + BLOCK - 1) // BLOCK
    centre = np.zeros((n_blocks, 3))
    radius = np.zeros(n_blocks)
    steps = np.zeros((n_blocks, 2))
    for b in range(n_blocks):
        lo, hi = b * BLOCK, min(b * BLOCK + BLOCK, n)
        for i in range(lo, hi):
            for a in range(3):
                centre[b, a] += p[i, a]
        for a in range(3):
            centre[b, a] /= hi - lo
        for i in range(lo, hi):
            dx, dy, dz = p[i, 0] - centre[b, 0], p[i, 1] - centre[b, 1], p[i, 2] - centre[b, 2]
            radius[b] = max(radius[b], math.sqrt(dx * dx + dy * dy + dz * dz))
            su = math.sqrt(step_u[i, 0] ** 2 + step_u[i, 1] ** 2 + step_u[i, 2] ** 2)
            sz = math.sqrt(step_z[i, 0] ** 2 + step_z[i, 1] ** 2 + step_z[i, 2] ** 2)
            steps[b, 0] = max(steps[b, 0], su)
            steps[b, 1] = max(steps[b, 1], sz)
    return centre, radius, steps


@numba.njit(cache=True, error_model="numpy")
def _block_bound(m, centre, radius, steps, mag, mm_per_px):  # pragma: no cover - compiled
    """An upper bound of :func:`_bound` over the cells of one block (``centre`` (3,),
    ``radius``, ``steps`` (2,): :func:`_block_geometry`'s) seen from ``m``: each cell is
    at least ``|centre| - radius`` away, its steps are at most the block's, its elevation
    within asin(radius / |centre|) of the centre's, and :func:`_bound` falls with the
    distance and rises with the steps (1e-6 to spare for rounding). inf where a cell's
    bound may be inf."""
    rx, ry, rz = _rotate(m, centre[0], centre[1], centre[2])
    qx, qy, qz = rx + m[0, 3], ry + m[1, 3], rz + m[2, 3]
    dc = math.sqrt(qx * qx + qy * qy + qz * qz)
    d = dc - radius * (1.0 + 1e-9) - 1e-9
    lu, lz = steps[0], steps[1]
    if not (lu < STEP_RAD * (d - lu) and lz < STEP_RAD * (d - lz)):
        return math.inf
    top = mag[0] if len(mag) == 1 else 0.0
    if len(mag) > 1:
        elev = math.asin(min(max(qz / dc, -1.0), 1.0))
        spread = math.asin(min(radius / dc, 1.0)) + 1e-9
        j0 = min(max(int((elev - spread + 0.5 * math.pi) / MAG_BIN_RAD) - 1, 0), len(mag) - 1)
        j1 = min(max(int((elev + spread + 0.5 * math.pi) / MAG_BIN_RAD) + 1, 0), len(mag) - 1)
        for j in range(j0, j1 + 1):
            top = max(top, mag[j])
    return top * math.sqrt(lu * lz / ((d - lu) * (d - lz))) / mm_per_px / max(d * d, 1e-6) * (1.0 + 1e-6)


@numba.njit(cache=True, error_model="numpy")
def _laser_band_hit(m, kind, params, p, plane, bands, col, row):  # pragma: no cover - compiled
    """True where the cell ``p`` seen from ``m`` (at ``col``, ``row``) lies in the laser's
    bands: the reference ``score_cell``'s test (tests/model/test_kernels.py), in its operations."""
    rx, ry, rz = _rotate(m, p[0], p[1], p[2])
    qx, qy, qz = rx + m[0, 3], ry + m[1, 3], rz + m[2, 3]
    side = qx * plane[0] + qy * plane[1] + qz * plane[2] + plane[3]
    if not abs(side) > bands[0]:
        return True
    if bands[1] > 0 and abs(plane[2]) >= 1e-6:
        lc, lr, lok = project_point(kind, params, qx, qy, qz - side / plane[2])
        d = math.sqrt((lc - col) ** 2 + (lr - row) ** 2)
        if lok and math.isfinite(d) and not d > bands[1]:
            return True
    return False


@numba.njit(cache=True, error_model="numpy")
def score_strip(
    rig_from_world, spans, order, mag, kind, params, p, step_u, step_z, normal, plane, bands,
    mm_per_px, centre, best, best_score, best_px, best_light,
):  # pragma: no cover - compiled
    """Every keyframe k's view of the cells ``spans[k, 0]:spans[k, 1]`` of ``p``; where it
    is better than ``best_score`` (equal: the earlier keyframe wins), ``best``,
    ``best_score``, ``best_px`` and ``best_light`` (log2 of cos(incidence) / range^2 and
    the pixel's distance from ``centre``) are updated in place. The result does not
    depend on the order in which the keyframes are taken.

    Bit for bit the cell-by-cell reference in tests/model/test_kernels.py, :data:`BLOCK`
    cells at a time (the cells in the order given: :func:`tile_order`): the cells
    :func:`_bound` does not skip (:func:`_block_candidates`), their points and their two
    steps projected as blocks (:func:`~omnipipe.camera._kernels.project_block`); the
    laser band's test only for a view that would win (a cell in the band scores 0, which
    wins nothing). Block by block, the keyframes that score it are taken best first by
    the score of the block's middle cell (:func:`_middle_scores`; ties in ``order``): the
    best view of a compact block's cells is then mostly found first (not kept again and
    again as better ones come), and the bounds skip the views that cannot beat it.

    Args:
        rig_from_world: (K, 4, 4) inverse keyframe poses (mm).
        spans: (K, 2) int64 cell ranges each keyframe scores.
        order: (K,) int64 the keyframes (ties of the blocks' orders in this order).
        mag: (N,) the camera's largest px per radian by elevation (:func:`_bound`;
            [inf]: no view skipped).
        kind, params: the camera's compiled projection.
        p, step_u, step_z, normal: (n, 3) cells' world points, their steps along the rows
            and columns (mm) and unit wall normals.
        plane: (4,) laser plane (normal in the rig frame, offset mm).
        bands: (2,) the laser band (mm from the plane, px from its line's image).
        mm_per_px: the cell size (mm).
        centre: (2,) principal point (px).
    """
    cand = np.empty(BLOCK, np.int64)
    q = np.empty((3, BLOCK))
    u = np.empty((3, BLOCK))
    z = np.empty((3, BLOCK))
    cols = np.empty((3, BLOCK))
    rows = np.empty((3, BLOCK))
    seen = np.empty((3, BLOCK), np.bool_)
    bound = np.empty(BLOCK)
    no_shift = (0.0, 0.0, 0.0)
    b_centre, b_radius, b_steps = _block_geometry(p, step_u, step_z, len(p))
    lens = _step_lengths(step_u, step_z)
    by_sine = sine_table(mag) if len(mag) > 1 else mag
    views = np.empty(len(order), np.int64)
    keys = np.empty(len(order))
    for b in range(len(b_radius)):
        n_views = _middle_scores(b, order, spans, rig_from_world, kind, params, p, step_u, step_z, mm_per_px, views, keys)
        for v in np.argsort(keys[:n_views], kind="mergesort"):
            k = views[v]
            m = rig_from_world[k]
            lo, hi = max(b * BLOCK, spans[k, 0]), min(b * BLOCK + BLOCK, spans[k, 1])
            # The whole block skipped when no cell of it can win (the cells' own
            # bounds would skip each: the same choice).
            worst = math.inf
            for i in range(lo, hi):
                worst = min(worst, best_score[i] if best[i] >= 0 else -1.0)
            if worst > 0 and _block_bound(m, b_centre[b], b_radius[b], b_steps[b], mag, mm_per_px) < worst:
                continue
            n = _block_candidates(
                m, lo, hi, p, step_u, step_z, lens, by_sine, mm_per_px, best, best_score, bound, cand, q, u, z
            )
            if n == 0:
                continue
            project_block(kind, params, q[0], q[1], q[2], no_shift, n, cols[0], rows[0], seen[0])
            project_block(kind, params, u[0], u[1], u[2], no_shift, n, cols[1], rows[1], seen[1])
            project_block(kind, params, z[0], z[1], z[2], no_shift, n, cols[2], rows[2], seen[2])
            _take_block(
                k, m, n, cand, q, cols, rows, seen, kind, params, p, normal, plane, bands, mm_per_px,
                centre, best, best_score, best_px, best_light,
            )


@numba.njit(cache=True, error_model="numpy")
def _middle_scores(b, order, spans, rig_from_world, kind, params, p, step_u, step_z, mm_per_px, views, keys):  # pragma: no cover - compiled
    """The keyframes whose spans reach block ``b`` (in ``order``) into ``views`` and minus
    the score of the block's middle cell from each into ``keys`` (the footprint of its
    steps over the squared distance; 0 where not seen, the laser's bands not tested);
    returns how many."""
    lo, hi = b * BLOCK, min(b * BLOCK + BLOCK, len(p))
    r = (lo + hi) // 2
    n = 0
    for k in order:
        if spans[k, 0] < hi and spans[k, 1] > lo:
            m = rig_from_world[k]
            rx, ry, rz = _rotate(m, p[r, 0], p[r, 1], p[r, 2])
            qx, qy, qz = rx + m[0, 3], ry + m[1, 3], rz + m[2, 3]
            col, row, ok = project_point(kind, params, qx, qy, qz)
            ux, uy, uz = _rotate(m, step_u[r, 0], step_u[r, 1], step_u[r, 2])
            cu, ru, _ = project_point(kind, params, qx + ux, qy + uy, qz + uz)
            zx, zy, zz = _rotate(m, step_z[r, 0], step_z[r, 1], step_z[r, 2])
            cz, rz2, _ = project_point(kind, params, qx + zx, qy + zy, qz + zz)
            area = abs((cu - col) * (rz2 - row) - (ru - row) * (cz - col))
            score = math.sqrt(area) / mm_per_px / max(qx * qx + qy * qy + qz * qz, 1e-6)
            views[n] = k
            keys[n] = -score if ok and math.isfinite(score) else 0.0
            n += 1
    return n


@numba.njit(cache=True, error_model="numpy")
def _step_lengths(step_u, step_z):  # pragma: no cover - compiled
    """(n, 2) the lengths of the cells' steps along the rows and the columns (mm), as
    :func:`_bound` computes them."""
    lens = np.empty((len(step_u), 2))
    for i in range(len(step_u)):
        su, sz = step_u[i], step_z[i]
        lens[i, 0] = math.sqrt(su[0] * su[0] + su[1] * su[1] + su[2] * su[2])
        lens[i, 1] = math.sqrt(sz[0] * sz[0] + sz[1] * sz[1] + sz[2] * sz[2])
    return lens


@numba.njit(cache=True, error_model="numpy", inline="always")
def _block_candidates(
    m, lo, hi, p, step_u, step_z, lens, by_sine, mm_per_px, best, best_score, bound, cand, q, u, z
):  # pragma: no cover - compiled
    """The cells ``lo:hi`` view ``m`` (4, 4 rig_from_world) may win into ``cand``, their
    points and the points one step along the rows/columns away in the rig frame into
    ``q``, ``u``, ``z`` (3, BLOCK); returns how many (``bound``: (BLOCK,) scratch).

    A cell may win unless :func:`_bound` is below its best score, here with
    :func:`_bound`'s arithmetic (steps' lengths from :func:`_step_lengths`) but for the
    magnification, read from ``by_sine`` (:func:`sine_table`; one entry: the same
    everywhere) by the sine of the elevation: never below :func:`_bound`'s entry, so no
    cell is skipped that :func:`_bound` would keep (and one it keeps beyond those cannot
    win: :func:`_bound` bounds its score), without an arcsine per cell."""
    m00, m01, m02, m03 = m[0, 0], m[0, 1], m[0, 2], m[0, 3]
    m10, m11, m12, m13 = m[1, 0], m[1, 1], m[1, 2], m[1, 3]
    m20, m21, m22, m23 = m[2, 0], m[2, 1], m[2, 2], m[2, 3]
    one = len(by_sine) == 1
    for c in range(hi - lo):
        i = lo + c
        x, y, w = p[i, 0], p[i, 1], p[i, 2]
        lu, lz = lens[i, 0], lens[i, 1]
        qx = (m00 * x + m01 * y + m02 * w) + m03
        qy = (m10 * x + m11 * y + m12 * w) + m13
        qz = (m20 * x + m21 * y + m22 * w) + m23
        d2 = qx * qx + qy * qy + qz * qz
        d = math.sqrt(d2)
        s = qz / d
        s = 1.0 if s > 1.0 else (s if s > -1.0 else -1.0)  # NaN (d = 0): -1, then inf below
        j = 0 if one else min(max(int((s + 1.0) * (0.5 * SINE_BINS)), 0), SINE_BINS)
        value = by_sine[j] * math.sqrt(lu * lz / ((d - lu) * (d - lz))) / mm_per_px / max(d2, 1e-6)
        near = (lu < STEP_RAD * (d - lu)) & (lz < STEP_RAD * (d - lz))
        bound[c] = value if near else math.inf
    n = 0
    for c in range(hi - lo):
        i = lo + c
        if best[i] >= 0 and bound[c] < best_score[i]:
            continue
        cand[n] = i
        n += 1
    for c in range(n):
        i = cand[c]
        rx, ry, rz = _rotate(m, p[i, 0], p[i, 1], p[i, 2])
        qx, qy, qz = rx + m[0, 3], ry + m[1, 3], rz + m[2, 3]
        q[0, c], q[1, c], q[2, c] = qx, qy, qz
        ux, uy, uz = _rotate(m, step_u[i, 0], step_u[i, 1], step_u[i, 2])
        u[0, c], u[1, c], u[2, c] = qx + ux, qy + uy, qz + uz
        zx, zy, zz = _rotate(m, step_z[i, 0], step_z[i, 1], step_z[i, 2])
        z[0, c], z[1, c], z[2, c] = qx + zx, qy + zy, qz + zz
    return n


@numba.njit(cache=True, error_model="numpy")
def _take_block(
    k, m, n, cand, q, cols, rows, seen, kind, params, p, normal, plane, bands, mm_per_px,
    centre, best, best_score, best_px, best_light,
):  # pragma: no cover - compiled
    """Keyframe ``k``'s projected block (``cols``/``rows``/``seen``: (3, BLOCK) of the
    cells' points and their steps) scored; where it wins, :func:`score_strip`'s outputs
    updated in place."""
    for c in range(n):
        if not seen[0, c]:
            continue
        i = cand[c]
        col, row = cols[0, c], rows[0, c]
        qx, qy, qz = q[0, c], q[1, c], q[2, c]
        a0, a1 = cols[1, c] - col, rows[1, c] - row
        b0, b1 = cols[2, c] - col, rows[2, c] - row
        dist2 = max(qx * qx + qy * qy + qz * qz, 1e-6)
        score = math.sqrt(abs(a0 * b1 - a1 * b0)) / mm_per_px / dist2
        if not math.isfinite(score):
            continue
        if not (score > best_score[i] or (score == best_score[i] and score > 0 and k < best[i])):
            continue
        if _laser_band_hit(m, kind, params, p[i], plane, bands, col, row):
            continue
        best[i] = k
        best_score[i] = score
        best_px[i, 0] = col
        best_px[i, 1] = row
        dist = math.sqrt(max(qx * qx + qy * qy + qz * qz, 1e-6))
        nx, ny, nz = _rotate(m, normal[i, 0], normal[i, 1], normal[i, 2])
        cos_i = abs(nx * qx + ny * qy + nz * qz) / dist
        best_light[i, 0] = math.log2(max(cos_i, 1e-6) / (dist * dist))
        best_light[i, 1] = math.sqrt((col - centre[0]) ** 2 + (row - centre[1]) ** 2)


@numba.njit(cache=True, error_model="numpy")
def face_first_rows(faces, axial, z0, mm_per_px, height):  # pragma: no cover - compiled
    """(F,) int64 the first grid row each of the (F, 3) triangles (vertex indices into the
    (N,) ``axial`` positions, mm) may cover (row r at ``z0 + r * mm_per_px``; one row
    early to spare for rounding) and the most rows one of them spans (a block of a long
    run's triangles at a time: ``omnipipe.model.texture_grid.rows_of_faces``)."""
    n = len(faces)
    first = np.empty(n, np.int64)
    span = 0
    for f in range(n):
        lo = min(axial[faces[f, 0]], axial[faces[f, 1]], axial[faces[f, 2]])
        hi = max(axial[faces[f, 0]], axial[faces[f, 1]], axial[faces[f, 2]])
        r0 = min(max(int(math.floor((lo - z0) / mm_per_px)) - 1, 0), height - 1)
        r1 = min(max(int(math.ceil((hi - z0) / mm_per_px)) + 1, 0), height - 1)
        first[f] = r0
        span = max(span, r1 - r0 + 1)
    return first, span


@numba.njit(cache=True)
def place_by_row(first, at, order, base):  # pragma: no cover - compiled
    """Triangle ``base + i`` written at ``order[at[first[i]]]`` for each i in turn,
    ``at[first[i]]`` then advanced: a counting sort's placing, for a block of triangles
    numbered from ``base``."""
    for i in range(len(first)):
        r = first[i]
        order[at[r]] = base + i
        at[r] += 1


@numba.njit(cache=True, error_model="numpy")
def rasterise_faces(
    faces, order, arc, axial, points, circ, z0, mm_per_px, first, max_gap_mm, grid, far
):  # pragma: no cover - compiled
    """Each triangle ``faces[order]`` linearly interpolated onto the cells it covers of
    the rows ``first .. first + len(grid)`` of the unrolled grid; ``tests/model/
    test_mesh_grid.py``'s ``rasterise_by_cell`` is its reference, bit for bit.

    The grid's cell (r, c) lies at arc ``(c + 0.5) * (circ / W)`` (and that plus or minus
    ``circ``: a triangle across angle 0 is unwrapped about its first corner) and axial
    ``z0 + r * mm_per_px``; it is in a triangle when its three barycentric coordinates
    are at least -1e-12 (a cell on an edge shared by two triangles takes the later one's
    value: the same to rounding). Its point is the coordinates' sum of the corners'
    ``points`` (mm).

    Args:
        faces: (F, 3) vertex indices; ``order``: the triangles to draw, in order.
        arc, axial: (N,) unrolled coordinates of the vertices (mm), arc in [0, circ).
        points: (N, 3) their 3-D points (mm).
        grid: (h, W, 3) float64, written where a triangle covers a cell (NaN elsewhere,
            as given).
        far: (h, W) bool, set True where a drawn cell's nearest corner is farther than
            ``max_gap_mm`` (unrolled): whether another point is nearer is left to the
            caller.
    """
    h, w = grid.shape[0], grid.shape[1]
    du = circ / w
    gap2 = max_gap_mm * max_gap_mm * (1.0 - 1e-9)
    for f in order:
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        u0 = arc[i0]
        u1 = u0 + ((arc[i1] - u0 + 0.5 * circ) % circ - 0.5 * circ)
        u2 = u0 + ((arc[i2] - u0 + 0.5 * circ) % circ - 0.5 * circ)
        v0, v1, v2 = axial[i0], axial[i1], axial[i2]
        den = (v1 - v2) * (u0 - u2) + (u2 - u1) * (v0 - v2)
        if den == 0.0 or not math.isfinite(den):
            continue
        r_lo = max(int(math.ceil((min(v0, v1, v2) - z0) / mm_per_px)) - 1, first)
        r_hi = min(int(math.floor((max(v0, v1, v2) - z0) / mm_per_px)) + 1, first + h - 1)
        u_lo, u_hi = min(u0, u1, u2), max(u0, u1, u2)
        for shift in (-circ, 0.0, circ):
            c_lo = max(int(math.ceil((u_lo - shift) / du - 0.5)) - 1, 0)
            c_hi = min(int(math.floor((u_hi - shift) / du - 0.5)) + 1, w - 1)
            for r in range(r_lo, r_hi + 1):
                zc = z0 + r * mm_per_px
                for c in range(c_lo, c_hi + 1):
                    uc = (c + 0.5) * du + shift
                    l0 = ((v1 - v2) * (uc - u2) + (u2 - u1) * (zc - v2)) / den
                    l1 = ((v2 - v0) * (uc - u2) + (u0 - u2) * (zc - v2)) / den
                    l2 = 1.0 - l0 - l1
                    if l0 < -1e-12 or l1 < -1e-12 or l2 < -1e-12:
                        continue
                    for a in range(3):
                        grid[r - first, c, a] = l0 * points[i0, a] + l1 * points[i1, a] + l2 * points[i2, a]
                    d2 = min(
                        (uc - u0) ** 2 + (zc - v0) ** 2,
                        (uc - u1) ** 2 + (zc - v1) ** 2,
                        (uc - u2) ** 2 + (zc - v2) ** 2,
                    )
                    far[r - first, c] = d2 > gap2


@numba.njit(cache=True)
def png_filter_rows(rows, above, bpp, out):  # pragma: no cover - compiled
    """The PNG scanlines of the (n, L) uint8 ``rows`` (L = width x ``bpp`` bytes; the
    (L,) uint8 ``above`` is the row above the first, zeros at the image's top) into the
    (n, 1 + L) uint8 ``out``, each row filtered as PIL's encoder does it: the first of
    None (0), Up (2), Sub (1), Paeth (4), in that order, whose sum of the filtered bytes'
    distances from zero (as signed bytes) is smallest, a later one only when strictly
    smaller (Average never). ``tests/model/test_png_writer.py``'s ``filter_rows`` is its
    reference, byte for byte."""
    n, width = rows.shape
    cand = np.empty((3, width), np.uint8)  # Up, Sub, Paeth
    for r in range(n):
        prev = above if r == 0 else rows[r - 1]
        costs = np.zeros(4, np.int64)  # None, Up, Sub, Paeth
        for i in range(width):
            x, b = np.int32(rows[r, i]), np.int32(prev[i])
            a = np.int32(rows[r, i - bpp]) if i >= bpp else np.int32(0)
            c = np.int32(prev[i - bpp]) if i >= bpp else np.int32(0)
            pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
            pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            v0, v1, v2, v3 = x, (x - b) & 255, (x - a) & 255, (x - pred) & 255
            cand[0, i], cand[1, i], cand[2, i] = v1, v2, v3
            costs[0] += min(v0, 256 - v0)
            costs[1] += min(v1, 256 - v1)
            costs[2] += min(v2, 256 - v2)
            costs[3] += min(v3, 256 - v3)
        pick, best = 0, costs[0]
        for k in range(1, 4):
            if costs[k] < best:
                pick, best = k, costs[k]
        out[r, 0] = (0, 2, 1, 4)[pick]
        if pick == 0:
            out[r, 1:] = rows[r]
        else:
            out[r, 1:] = cand[pick - 1]

"""The texture's compiled view scores by blocks (:func:`omnipipe.model._kernels.score_strip`)
against their cell-by-cell reference (``score_strip_by_cell`` below)."""

from __future__ import annotations

import itertools
import math
from unittest import mock

import numba
import numpy as np
import pytest
from test_texture_sources import MM_PER_PX, _pipe, _rig

from omnipipe.camera import camera_from_rig
from omnipipe.camera._kernels import project_point
from omnipipe.model import _kernels
from omnipipe.model.texture_sources import _choose_in_strip, elevation_bounds, magnification_table


@pytest.mark.parametrize("bend_mm", [None, 1000.0])
@pytest.mark.parametrize("skip", [False, True])
def test_block_scores_are_bit_identical_to_cell_by_cell(bend_mm: float | None, skip: bool) -> None:
    """The same keyframe, pixel and light for every cell, bit for bit, with and without
    the bound that skips views, laser bands in mm and px included."""
    import omnipipe.model.texture_sources as ts

    grid, poses = _pipe(300.0, 12.0, bend_mm, seed=3)
    rig = _rig("hyperboloid")
    camera = camera_from_rig(rig)
    rig_from_world = np.linalg.inv(poses)
    mag = magnification_table(camera) if skip else None
    args = (rig, camera, rig_from_world, grid, 0, grid.shape[0], elevation_bounds(camera), MM_PER_PX, 3.0, True, 4.0)
    blocks = _choose_in_strip(*args, compiled=True, magnification=mag)
    with mock.patch.object(ts, "score_strip", score_strip_by_cell):
        cells = _choose_in_strip(*args, compiled=True, magnification=mag)
    for a, b in zip(blocks, cells, strict=True):
        assert np.array_equal(a.view(np.uint8), b.view(np.uint8))
    assert (blocks[0] >= 0).mean() > 0.9 and len(np.unique(blocks[0])) > 10


def test_sine_table_is_never_below_the_bin_the_cell_bound_reads() -> None:
    """The table by sine that the blocks' cell bounds read is at least the entry of the
    elevation bin ``_bound`` takes, for sines drawn at random and next to every bin edge
    (so no view is skipped that the reference would score)."""
    mag = magnification_table(camera_from_rig(_rig("hyperboloid")))
    table = _kernels.sine_table(mag)
    rng = np.random.default_rng(5)
    edges = np.sin(np.arange(len(mag) + 1) * _kernels.MAG_BIN_RAD - 0.5 * np.pi)
    sines = np.concatenate([rng.uniform(-1, 1, 200_000), edges, np.nextafter(edges, 2), np.nextafter(edges, -2), [-1.0, 1.0]])
    sines = np.clip(sines, -1.0, 1.0)
    elevation_bin = np.clip(((np.arcsin(sines) + 0.5 * np.pi) / _kernels.MAG_BIN_RAD).astype(int), 0, len(mag) - 1)
    sine_bin = np.clip(((sines + 1.0) * (0.5 * _kernels.SINE_BINS)).astype(int), 0, _kernels.SINE_BINS)
    assert np.all(table[sine_bin] >= mag[elevation_bin])
    finite = np.isfinite(mag[elevation_bin])
    assert np.median(table[sine_bin][finite] / mag[elevation_bin][finite]) == 1.0  # hardly looser


def test_tile_order_keeps_every_band_s_cells_in_its_range() -> None:
    """A strip's cells (some missing) in tile order: each band of 8 rows holds the same
    cells at the same positions as in row-major order, a full band's first tile is its
    first 8 rows x 4 columns, and every cell comes once."""
    rng = np.random.default_rng(2)
    h, w = 21, 37
    idx = np.flatnonzero(rng.random(h * w) > 0.1)
    full = np.arange(8 * w)  # band 0 complete
    idx = np.union1d(full, idx)
    order = _kernels.tile_order(idx, w, 8)
    assert np.array_equal(np.sort(order), np.arange(len(idx)))
    starts = np.searchsorted(idx, np.arange(0, h + 8, 8).clip(max=h) * w)
    for a, b in itertools.pairwise(starts):
        assert np.array_equal(np.sort(idx[order[a:b]]), idx[a:b])
    first = idx[order[:32]]
    assert np.array_equal(np.sort(first), np.sort((np.arange(8)[:, None] * w + np.arange(4)).ravel()))


@numba.njit(cache=False, error_model="numpy")
def score_cell(m, kind, params, p, su, sz, plane, bands, mm_per_px):
    """(score, col, row, qx, qy, qz) of one cell from one keyframe; score 0 where the
    keyframe does not see it or sees it in the laser's bands (``bands`` = (mm, px))."""
    rx, ry, rz = _kernels._rotate(m, p[0], p[1], p[2])
    qx, qy, qz = rx + m[0, 3], ry + m[1, 3], rz + m[2, 3]
    col, row, ok = project_point(kind, params, qx, qy, qz)
    side = qx * plane[0] + qy * plane[1] + qz * plane[2] + plane[3]
    if not ok or not abs(side) > bands[0]:
        return 0.0, col, row, qx, qy, qz
    if bands[1] > 0 and abs(plane[2]) >= 1e-6:
        # The laser line's image at the cell's azimuth (the point moved along the rig's
        # z axis onto the plane): the cell must image farther from it than bands[1] px.
        lc, lr, lok = project_point(kind, params, qx, qy, qz - side / plane[2])
        d = math.sqrt((lc - col) ** 2 + (lr - row) ** 2)
        if lok and math.isfinite(d) and not d > bands[1]:
            return 0.0, col, row, qx, qy, qz
    ux, uy, uz = _kernels._rotate(m, su[0], su[1], su[2])
    cu, ru, _ = project_point(kind, params, qx + ux, qy + uy, qz + uz)
    zx, zy, zz = _kernels._rotate(m, sz[0], sz[1], sz[2])
    cz, rz2, _ = project_point(kind, params, qx + zx, qy + zy, qz + zz)
    a0, a1, b0, b1 = cu - col, ru - row, cz - col, rz2 - row
    dist2 = max(qx * qx + qy * qy + qz * qz, 1e-6)
    score = math.sqrt(abs(a0 * b1 - a1 * b0)) / mm_per_px / dist2
    if not math.isfinite(score):
        score = 0.0
    return score, col, row, qx, qy, qz


@numba.njit(cache=False, error_model="numpy")
def score_strip_by_cell(
    rig_from_world, spans, order, mag, kind, params, p, step_u, step_z, normal, plane, bands,
    mm_per_px, centre, best, best_score, best_px, best_light,
):
    """:func:`omnipipe.model._kernels.score_strip` cell by cell: its reference.

    Every keyframe k's view of the cells ``spans[k, 0]:spans[k, 1]`` of ``p``; where it
    is better than ``best_score`` (equal: the earlier keyframe wins), ``best``,
    ``best_score``, ``best_px`` and ``best_light`` (log2 of cos(incidence) / range^2 and
    the pixel's distance from ``centre``) are updated in place. The keyframes are taken
    in ``order`` (near ones first: a good view found early lets :func:`_bound` skip the
    views that cannot beat it; the result does not depend on the order).

    Args:
        rig_from_world: (K, 4, 4) inverse keyframe poses (mm).
        spans: (K, 2) int64 cell ranges each keyframe scores.
        order: (K,) int64 the keyframes in the order they are scored.
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
    for k in order:
        m = rig_from_world[k]
        for i in range(spans[k, 0], spans[k, 1]):
            if best[i] >= 0 and _kernels._bound(p[i], step_u[i], step_z[i], m, mag, mm_per_px) < best_score[i]:
                continue
            score, col, row, qx, qy, qz = score_cell(
                m, kind, params, p[i], step_u[i], step_z[i], plane, bands, mm_per_px
            )
            if not (score > best_score[i] or (score == best_score[i] and score > 0 and k < best[i])):
                continue
            best[i] = k
            best_score[i] = score
            best_px[i, 0] = col
            best_px[i, 1] = row
            dist = math.sqrt(max(qx * qx + qy * qy + qz * qz, 1e-6))
            nx, ny, nz = _kernels._rotate(m, normal[i, 0], normal[i, 1], normal[i, 2])
            cos_i = abs(nx * qx + ny * qy + nz * qz) / dist
            best_light[i, 0] = math.log2(max(cos_i, 1e-6) / (dist * dist))
            best_light[i, 1] = math.sqrt((col - centre[0]) ** 2 + (row - centre[1]) ** 2)

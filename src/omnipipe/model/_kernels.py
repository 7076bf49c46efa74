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
"""

from __future__ import annotations

import math

import numba

from omnipipe.camera._kernels import project_point


@numba.njit(cache=True, error_model="numpy")
def _rotate(m, x, y, z):  # pragma: no cover - compiled
    """R (x, y, z) of the (4, 4) transform ``m``'s rotation."""
    return (
        m[0, 0] * x + m[0, 1] * y + m[0, 2] * z,
        m[1, 0] * x + m[1, 1] * y + m[1, 2] * z,
        m[2, 0] * x + m[2, 1] * y + m[2, 2] * z,
    )


@numba.njit(cache=True, error_model="numpy")
def _score_cell(m, kind, params, p, su, sz, plane, bands, mm_per_px):  # pragma: no cover - compiled
    """(score, col, row, qx, qy, qz) of one cell from one keyframe; score 0 where the
    keyframe does not see it or sees it in the laser's bands (``bands`` = (mm, px))."""
    rx, ry, rz = _rotate(m, p[0], p[1], p[2])
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
    ux, uy, uz = _rotate(m, su[0], su[1], su[2])
    cu, ru, _ = project_point(kind, params, qx + ux, qy + uy, qz + uz)
    zx, zy, zz = _rotate(m, sz[0], sz[1], sz[2])
    cz, rz2, _ = project_point(kind, params, qx + zx, qy + zy, qz + zz)
    a0, a1, b0, b1 = cu - col, ru - row, cz - col, rz2 - row
    dist2 = max(qx * qx + qy * qy + qz * qz, 1e-6)
    score = math.sqrt(abs(a0 * b1 - a1 * b0)) / mm_per_px / dist2
    if not math.isfinite(score):
        score = 0.0
    return score, col, row, qx, qy, qz


@numba.njit(cache=True, error_model="numpy")
def score_strip(
    rig_from_world, spans, kind, params, p, step_u, step_z, normal, plane, bands, mm_per_px,
    centre, best, best_score, best_px, best_light,
):  # pragma: no cover - compiled
    """Every keyframe k's view of the cells ``spans[k, 0]:spans[k, 1]`` of ``p``; where it
    is strictly better than ``best_score`` (ties keep the earlier keyframe), ``best``,
    ``best_score``, ``best_px`` and ``best_light`` (log2 of cos(incidence) / range^2 and
    the pixel's distance from ``centre``) are updated in place.

    Args:
        rig_from_world: (K, 4, 4) inverse keyframe poses (mm).
        spans: (K, 2) int64 cell ranges each keyframe scores.
        kind, params: the camera's compiled projection.
        p, step_u, step_z, normal: (n, 3) cells' world points, their steps along the rows
            and columns (mm) and unit wall normals.
        plane: (4,) laser plane (normal in the rig frame, offset mm).
        bands: (2,) the laser band (mm from the plane, px from its line's image).
        mm_per_px: the cell size (mm).
        centre: (2,) principal point (px).
    """
    for k in range(rig_from_world.shape[0]):
        m = rig_from_world[k]
        for i in range(spans[k, 0], spans[k, 1]):
            score, col, row, qx, qy, qz = _score_cell(
                m, kind, params, p[i], step_u[i], step_z[i], plane, bands, mm_per_px
            )
            if not score > best_score[i]:
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
